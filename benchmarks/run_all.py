"""Run every benchmark script (``benchmarks/bench_*.py``) and collect their results.

Usage: ``make bench`` or ``python benchmarks/run_all.py [--only NAME ...]``.

Each script writes ``benchmarks/results/<name>.json`` (and a Markdown fragment); this runner
records the wall time and exit status of each and writes ``benchmarks/results/summary.md``.
Speed and memory targets are checked here and reported, never asserted in the test suite.
"""

from __future__ import annotations

import argparse
import platform
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
#: scripts with make targets of their own (make examples, make bench-scale, make bench-make): not run here
OWN_TARGETS = {"bench_examples", "bench_make", "bench_memory"}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="*", help="benchmark names (e.g. bench_rk)")
    args = ap.parse_args()
    RESULTS.mkdir(exist_ok=True)
    scripts = [s for s in sorted(HERE.glob("bench_*.py")) if s.stem not in OWN_TARGETS]
    if args.only:
        scripts = [s for s in scripts if s.stem in args.only]
    rows = []
    for script in scripts:
        print(f"== {script.stem}", flush=True)
        t0 = time.perf_counter()
        proc = subprocess.run([sys.executable, str(script)], cwd=HERE.parent)
        dt = time.perf_counter() - t0
        rows.append((script.stem, proc.returncode, dt))
    lines = [
        "# Benchmark summary",
        "",
        f"Machine: {platform.platform()}, Python {platform.python_version()}, {_cores()} cores.",
        "",
        "| benchmark | exit | wall time (s) | results |",
        "|---|---|---|---|",
    ]
    for name, rc, dt in rows:
        res = RESULTS / f"{name}.json"
        lines.append(f"| {name} | {rc} | {dt:.1f} | {res.name if res.exists() else '-'} |")
    for name, _, _ in rows:
        md = RESULTS / f"{name}.md"
        if md.exists():
            lines += ["", md.read_text().strip()]
    (RESULTS / "summary.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0 if all(rc == 0 for _, rc, _ in rows) else 1


def _cores() -> int:
    import os

    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()


if __name__ == "__main__":
    sys.exit(main())

"""The README's two commands on a fresh clone: ``make demo`` and ``make test``, each timed with its install.

The committed ``HEAD`` is cloned into a temporary folder (nothing carried over: no virtual environment,
no outputs); ``make demo`` runs there, then ``make test`` (which adds the test and optional extras to the
same environment, as a user who tries the demo first would). Both use pip's wheel cache as the machine has
it, so the install parts are those of a machine that has installed pixmuscle before. The pytest summary
line of ``make test`` is kept.

Run: ``python benchmarks/bench_make.py``; writes ``benchmarks/results/bench_make.json``.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _record import ROOT, Run  # noqa: E402

OUT = ROOT / "benchmarks" / "results" / "bench_make.json"


def timed(cmd: list[str], cwd: Path, log: Path) -> dict:
    t = time.perf_counter()
    with open(log, "w") as fh:
        rc = subprocess.run(cmd, cwd=cwd, stdout=fh, stderr=subprocess.STDOUT).returncode
    text = log.read_text(errors="replace")
    summary = [ln for ln in text.splitlines() if re.search(r"\d+ passed", ln)]
    return {"command": " ".join(cmd), "exit_code": rc, "wall_s": round(time.perf_counter() - t, 1),
            **({"pytest": summary[-1].strip("= ")} if summary else {})}


def main() -> int:
    run = Run(defaults=True)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        clone = Path(tmp) / "pixmuscle"
        subprocess.run(["git", "clone", "--quiet", str(ROOT), str(clone)], check=True)
        for target in ("demo", "test"):
            rows.append({"target": f"make {target}", **timed(["make", target], clone, Path(tmp) / f"{target}.log")})
            print(json.dumps(rows[-1]), flush=True)
            if rows[-1]["exit_code"] != 0:
                print((Path(tmp) / f"{target}.log").read_text()[-4000:], file=sys.stderr)
                break
    OUT.write_text(json.dumps({**run.fields(), "cases": rows}, indent=2) + "\n")
    return max(r["exit_code"] for r in rows)


if __name__ == "__main__":
    raise SystemExit(main())

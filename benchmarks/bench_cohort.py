"""Cohort and study throughput: serial vs a local Dask cluster of two workers.

Cases: ``configs/mg_young_old_small.yaml`` (the MG young/old cohort, small variant: 2 subjects) and the 3 × 3 study of
``configs/mg_young_old_study.yaml`` (IMCT C10 × σ_max) on its young subject only: 9 cases, the
segmentation and models made once and shared (the shipped 18-case study would take longer than a
benchmark step on a shared 2-core machine should). Every run is ``--force`` (all stages redone).

* serial: ``pixmuscle run CONFIG --workers 0 --force`` in a child process; peak memory = that of the
  child's process tree (:func:`_record.run_child`: sampled, its BoomerAMG workers included).
* dask: ``run_pipeline(CONFIG, scheduler=...)`` on :func:`pixmuscle.runners.dask.local_cluster`
  (2 worker processes, exactly what ``--workers 2`` starts); peak memory of each worker process,
  its own high-water mark (``VmHWM``) read on the worker before the cluster closes.

Run:  .venv/bin/python benchmarks/bench_cohort.py [--part cohort study] [--mode serial dask]
Each (part, mode) is merged into benchmarks/results/bench_cohort.json; bench_cohort.md is rewritten
from it with the wall-time ratio serial / dask for every part measured in both modes.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _record import Run, own_peak_kb, run_child  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
CONFIGS = {"cohort": ROOT / "configs" / "mg_young_old_small.yaml", "study": ROOT / "out" / "bench_cohort" / "study_young.yaml"}


def write_study_config() -> Path:
    """The shipped study restricted to its first subject, paths made absolute (out/bench_cohort/)."""
    import yaml

    src = ROOT / "configs" / "mg_young_old_study.yaml"
    raw = yaml.safe_load(src.read_text())
    young = raw.pop("subjects")[0]
    raw["segment"].update({k: str((src.parent / v).resolve()) if k != "seeds" else v
                           for k, v in young["segment"].items()})
    raw["output_dir"] = str(ROOT / "out" / "bench_cohort" / "study_young")
    CONFIGS["study"].parent.mkdir(parents=True, exist_ok=True)
    CONFIGS["study"].write_text(yaml.safe_dump(raw, sort_keys=False))
    return CONFIGS["study"]


def _peak_mb() -> float:
    """Peak resident memory of the process that runs it, MB: its high-water mark (``VmHWM``; not
    ``ru_maxrss``, which keeps the size of a forked parent). Defined here, not imported, so that
    Dask sends it to its workers by value."""
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmHWM:")) / 1024.0


def run_serial(config: Path) -> dict:
    with tempfile.TemporaryFile("w+") as err:  # not a pipe: the child could fill it while run_child waits
        t0 = time.perf_counter()
        code, _, peak_kb = run_child(["-m", "pixmuscle.cli", "-q", "run", str(config), "--workers", "0", "--force"],
                                     cwd=ROOT, stdout=subprocess.DEVNULL, stderr=err, text=True)
        wall = time.perf_counter() - t0
        err.seek(0)
        tail = err.read()[-2000:] if code else ""
    return {"wall_s": wall, "exit": code, "peak_rss_mb": {"process": peak_kb / 1024.0}, "stderr_tail": tail}


def run_dask(config: Path, workers: int = 2) -> dict:
    from distributed import Client

    from pixmuscle.pipeline import run_pipeline
    from pixmuscle.runners.dask import local_cluster

    with local_cluster(workers) as address:
        t0 = time.perf_counter()
        ok = run_pipeline(config, force=True, scheduler=address)
        wall = time.perf_counter() - t0
        with Client(address) as client:
            peaks = client.run(_peak_mb)
    return {"wall_s": wall, "exit": 0 if ok else 1,
            "peak_rss_mb": {"client": own_peak_kb() / 1024.0, **{f"worker {i}": v for i, v in enumerate(peaks.values())}},
            "workers": workers}


def write_md(results: dict, path: Path) -> None:
    lines = ["## bench_cohort: cohort and study, serial vs `--workers 2`", "",
             f"Machine: {results.get('machine') or next(iter(results['runs'].values()), {}).get('machine')}. **Shared with other agents' jobs while measured** (several "
             "concurrent sessions on the same cores; the 1-minute load average at the start and end of each run is "
             "given): wall times include their load, and a serial / dask ratio above the number of workers means "
             "that load changed between the two runs, not that Dask is faster than parallel.", "",
             "| part | cases | mode | wall (s) | load avg (start/end) | peak RSS (MB) | command |",
             "|---|---|---|---|---|---|---|"]
    for key, r in sorted(results["runs"].items()):
        part, mode = key.split(":")
        peaks = ", ".join(f"{k} {v:.0f}" for k, v in r["peak_rss_mb"].items())
        la = r.get("load_average_1min") or ({"start": r["load_average"]["before"][0], "end": r["load_average"]["after"][0]}
                                            if "load_average" in r else None)
        load = f"{la['start']:.1f}/{la['end']:.1f}" if la else "not recorded (≈10–11 by uptime)"
        lines.append(f"| {part} | {r['cases']} | {mode} | {r['wall_s']:.1f} | {load} | {peaks} | `{r['command']}` |")
    for part in CONFIGS:
        s, d = results["runs"].get(f"{part}:serial"), results["runs"].get(f"{part}:dask")
        if s and d:
            lines.append("")
            lines.append(f"{part}: wall time serial / dask = {s['wall_s'] / d['wall_s']:.2f} "
                         f"({s['measured_utc']} and {d['measured_utc']}).")
    path.write_text("\n".join(lines) + "\n")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--part", nargs="*", choices=sorted(CONFIGS), default=sorted(CONFIGS))
    ap.add_argument("--mode", nargs="*", choices=["serial", "dask"], default=["serial", "dask"])
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    js = args.out / "bench_cohort.json"
    results = json.loads(js.read_text()) if js.exists() else {"runs": {}}
    from pixmuscle.pipeline import load_subjects

    write_study_config()
    for part in args.part:
        cfg = CONFIGS[part]
        n = len(load_subjects(cfg))
        for mode in args.mode:
            print(f"== {part} ({n} cases), {mode}", flush=True)
            record = Run(defaults=True, command=f".venv/bin/python benchmarks/bench_cohort.py --part {part} --mode {mode}")
            r = run_serial(cfg) if mode == "serial" else run_dask(cfg)
            # dask: the client and its workers (each worker's own peak); serial: this process and the CLI's tree
            peak = round(sum(r["peak_rss_mb"].values()) / 1024, 2) if mode == "dask" else None
            r.update(cases=n, **record.fields(peak_rss_GB=peak))
            r["measured_utc"] = r["utc"]
            print(json.dumps(r, indent=1), flush=True)
            results["runs"][f"{part}:{mode}"] = r
            js.write_text(json.dumps(results, indent=2))
    write_md(results, args.out / "bench_cohort.md")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The paper's examples as shipped configs, timed stage group by stage group.

Each example is run with the CLI in a child process, in three calls that each redo only what the
previous did not (``--force`` on the first): ``--until segment``, ``--until coarsen``, then the
rest (solve and report). Recorded: wall time of each call, the 1-minute load average before and
after (the machine is shared), the node count of every model, F_max per model and the coarse vs
fine difference (``convergence`` of the report summary), or the cohort's per-volume forces.

Run:  .venv/bin/python benchmarks/bench_examples.py EXAMPLE [--until coarsen]
      EXAMPLE: lower_leg_small, lower_leg, mg_young_old_small, mg_young_old
Each run is merged into benchmarks/results/bench_examples.json; bench_examples.md is rewritten from it.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"
EXAMPLES = {
    "lower_leg_small": "configs/lower_leg_small.yaml",
    "lower_leg": "configs/lower_leg.yaml",
    "mg_young_old_small": "configs/mg_young_old_small.yaml",
    "mg_young_old": "configs/mg_young_old.yaml",
}


def _cli(config: str, *args: str) -> tuple[float, int, str]:
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "pixmuscle.cli", "-q", "run", config, *args], cwd=ROOT,
                          capture_output=True, text=True)
    return time.perf_counter() - t0, proc.returncode, proc.stderr[-1500:]


def _models(out: Path) -> dict:
    """Node counts of the model files under ``out`` (h5py, no pixmuscle import)."""
    import h5py

    found = {}
    for p in sorted(out.rglob("model*.h5")):
        with h5py.File(p, "r") as f:
            found[str(p.relative_to(ROOT))] = int(f["nodes/tissue"].shape[0])
    return found


def _outcome(out: Path) -> dict:
    res = {}
    for js in sorted(out.rglob("report/summary.json")):
        s = json.loads(js.read_text())
        entry = {"F_max_N": s.get("F_max_N"), "n_nodes": s.get("n_nodes"), "compared": s.get("compared")}
        if s.get("convergence"):
            c = s["convergence"]
            entry["convergence"] = {"reference": c["reference"], "F_max_N": c["F_max_N"],
                                    "F_max_relative_difference": c["F_max_relative_difference"],
                                    "max_relative_difference": c["max_relative_difference"]}
        res[str(js.parent.relative_to(ROOT))] = entry
    return res


def run(example: str, until: str | None) -> dict:
    import yaml

    config = EXAMPLES[example]
    raw = yaml.safe_load((ROOT / config).read_text())
    out = ((ROOT / config).parent / raw["output_dir"]).resolve()
    steps = [("segment", ("--until", "segment", "--force")), ("build-model + coarsen", ("--until", "coarsen"))]
    if until != "coarsen":
        steps.append(("solve + report", ()))
    rec = {"example": example, "config": config, "machine": f"{platform.platform()}, Python {platform.python_version()}, "
           f"{os.cpu_count()} cores (shared)", "date_utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime()),
           "command": f"python benchmarks/bench_examples.py {example}" + (f" --until {until}" if until else ""),
           "stages": []}
    for label, args in steps:
        load0 = os.getloadavg()[0]
        wall, code, err = _cli(config, *args)
        rec["stages"].append({"stages": label, "wall_s": round(wall, 1), "exit": code,
                              "load_avg": [round(load0, 1), round(os.getloadavg()[0], 1)],
                              **({"stderr_tail": err} if code else {})})
        if code:
            break
    rec["models_nodes"] = _models(out)
    rec["reports"] = _outcome(out)
    return rec


def write(records: dict) -> None:
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "bench_examples.json").write_text(json.dumps(records, indent=2) + "\n")
    lines = ["## bench_examples: the paper's examples as shipped configs", "",
             "Wall times of `pixmuscle -q run CONFIG` in three calls (segment; build-model + coarsen; solve + "
             "report), on a 2-core machine **shared with other agents' jobs** (load average before/after each call).", ""]
    for name, r in records.items():
        lines += [f"### {name} (`{r['config']}`, {r['date_utc']} UTC)", "", f"Command: `{r['command']}`", "",
                  "| stages | wall (s) | exit | load avg |", "|---|---|---|---|"]
        lines += [f"| {s['stages']} | {s['wall_s']} | {s['exit']} | {s['load_avg'][0]}/{s['load_avg'][1]} |" for s in r["stages"]]
        lines += ["", "Models: " + ", ".join(f"`{k}` {v:,} nodes" for k, v in r["models_nodes"].items()), ""]
        for rep, e in r["reports"].items():
            lines.append(f"- `{rep}`: F_max {e['F_max_N']} N, {e['n_nodes']} nodes")
            c = e.get("convergence")
            if c:
                lines.append(f"  - convergence (reference {c['reference']}): F_max {c['F_max_N']}, relative "
                             f"difference of F_max {c['F_max_relative_difference']}, largest over α {c['max_relative_difference']}")
            q = e.get("compared") or {}
            if q.get("force_per_muscle_volume") is not None:
                lines.append(f"  - F_max / Table 3 total {q.get('force_per_table3_volume'):.4g} N/cm³, F_max / muscle "
                             f"{q.get('force_per_muscle_volume'):.4g} N/cm³, muscle {q.get('muscle'):.4g} cm³, IMAT "
                             f"{q.get('imat'):.4g} cm³, IMCT {q.get('imct'):.4g} cm³")
        lines.append("")
    (RESULTS / "bench_examples.md").write_text("\n".join(lines) + "\n")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("example", choices=sorted(EXAMPLES))
    ap.add_argument("--until", choices=["coarsen"], default=None, help="stop after the coarsen stage (no solve)")
    a = ap.parse_args(argv)
    path = RESULTS / "bench_examples.json"
    records = json.loads(path.read_text()) if path.exists() else {}
    records[a.example + ("" if a.until is None else f" (until {a.until})")] = run(a.example, a.until)
    write(records)
    print(json.dumps(records, indent=2)[-3000:])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

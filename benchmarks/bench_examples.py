"""The paper's examples as shipped configs, timed stage group by stage group.

Each example is run with the CLI in a child process, in three calls that each redo only what the
previous did not (``--force`` on the first): ``--until segment``, ``--until coarsen``, then the
rest (solve and report). Recorded: the fields of :mod:`_record` (command, commit, utc, machine, load
average before and after, ``defaults``: true for a shipped config run as shipped, peak memory of the
process tree); per call its wall time, peak memory (the largest process of the call's tree, from
``wait4``, plus the BoomerAMG workers it started) and 1-minute load average before and after; the node count of every model, and per solved model (``models``): nodes, load steps
converged, Newton iterations, F_max, the solver's own clock and linear-solver work, status; from
the report summaries F_max and the coarse vs fine difference (``convergence``), or the cohort's
per-volume forces.

A run made elsewhere (e.g. a long solve started by hand) is recorded without solving again with
``--from-run DIR``: the models and reports are read from the run folder, the command and start time
from its lock file (``.pixmuscle.lock``: argv, started_utc), the end from its newest file; wall time,
peak memory and load average can be given (``--wall-s``, ``--peak-rss-gb``, ``--load-avg``), as
measured outside the pipeline, which does not store them.

Run:  .venv/bin/python benchmarks/bench_examples.py EXAMPLE [--until coarsen]
      .venv/bin/python benchmarks/bench_examples.py EXAMPLE --from-run DIR [--wall-s S] [--peak-rss-gb G] [--load-avg A B]
      EXAMPLE: lower_leg_small, lower_leg, mg_young_old_small, mg_young_old, uncertainty, mg_young_old_uncertainty
Each run is merged into benchmarks/results/bench_examples.json; bench_examples.md is rewritten from it.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _record import Run, run_child  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"
EXAMPLES = {
    "lower_leg_small": "configs/lower_leg_small.yaml",
    "lower_leg": "configs/lower_leg.yaml",
    "lower_leg_elliptic": "configs/lower_leg_elliptic.yaml",
    "mg_young_old_small": "configs/mg_young_old_small.yaml",
    "mg_young_old": "configs/mg_young_old.yaml",
    "uncertainty": "configs/uncertainty.yaml",
    "mg_young_old_uncertainty": "configs/mg_young_old_uncertainty.yaml",
}


def _cli(config: str, *args: str) -> tuple[float, int, str, float]:
    """Run ``pixmuscle -q run CONFIG ARGS``; wall time (s), exit code, stderr tail and peak memory (GB:
    the largest sampled memory of the child's process tree, its BoomerAMG and Dask workers included,
    :func:`_record.run_child`)."""
    with tempfile.TemporaryFile("w+") as err:
        t0 = time.perf_counter()
        code, _, peak_kb = run_child(["-m", "pixmuscle.cli", "-q", "run", config, *args], cwd=ROOT,
                                     stdout=subprocess.DEVNULL, stderr=err, text=True)
        wall = time.perf_counter() - t0
        err.seek(0)
        tail = err.read()[-1500:]
    return wall, code, tail, peak_kb / 1024**2


def _rel(p: Path) -> str:
    """``p`` relative to the repository when inside it."""
    p = Path(p).resolve()
    return str(p.relative_to(ROOT)) if p.is_relative_to(ROOT) else str(p)


def _models(out: Path) -> dict:
    """Node counts of the model files under ``out`` (h5py, no pixmuscle import)."""
    import h5py

    found = {}
    for p in sorted(out.rglob("model*.h5")):
        with h5py.File(p, "r") as f:
            found[_rel(p)] = int(f["nodes/tissue"].shape[0])
    return found


def _outcome(out: Path, since: float = 0.0) -> dict:
    """F_max, nodes, Table 3 volumes and the coarse vs fine difference of every report summary under
    ``out`` written after ``since`` (epoch s)."""
    res = {}
    for js in sorted(out.rglob("report/summary.json")):
        if js.stat().st_mtime < since:
            continue
        s = json.loads(js.read_text())
        entry = {"F_max_N": s.get("F_max_N"), "n_nodes": s.get("n_nodes"), "compared": s.get("compared")}
        if s.get("convergence"):
            c = s["convergence"]
            entry["convergence"] = {"reference": c["reference"], "F_max_N": c["F_max_N"],
                                    "F_max_relative_difference": c["F_max_relative_difference"],
                                    "max_relative_difference": c["max_relative_difference"]}
        res[_rel(js.parent)] = entry
    return res


def _model_records(out: Path, since: float = 0.0) -> dict:
    """Per model solved under ``out`` after ``since`` (epoch s; key: ``<model>`` or ``<subject>/<model>``): nodes, load steps
    converged / planned, Newton iterations, F_max (N, as the report computes it), the solver's own
    clock (``solver_info.total_s``), linear solver and Krylov iterations, status."""
    from pixmuscle.io.results import load_results
    from pixmuscle.report.curves import axial_forces, end_force, select_force_sets

    found = {}
    for p in sorted(out.rglob("results_*.h5")):  # one file per model and subject
        if p.stat().st_mtime < since:
            continue  # left by an earlier run
        res = load_results(p)
        sets = select_force_sets(res.reaction, None, res.constrained_text())
        force = end_force(axial_forces(res.reaction, sets), res.n_states)
        conv = np.asarray(res.converged, bool)
        info = res.info or {}
        key = str(p.relative_to(out).with_name(p.stem.removeprefix("results_")))
        found[key] = {
            "results": _rel(p),
            "nodes": int(res.model.n_nodes), "status": res.status,
            "steps_converged": int(conv[1:].sum()), "steps_planned": int(res.n_steps_planned),
            "newton_iterations": int(np.asarray(res.iterations)[conv].sum()),
            "F_max_N": float(np.max(force[conv])) if conv.any() else None,
            "alpha_last_converged": float(np.asarray(res.alpha)[conv][-1]) if conv.any() else None,
            "solve_s": None if info.get("total_s") is None else round(float(info["total_s"]), 1),
            "linear_solver": info.get("linear_solver"),
            "non_elliptic_nodes": info.get("non_elliptic_nodes"),   # at the last converged step
            "krylov_iterations": info.get("krylov_iterations"),
        }
    return found


def _status(rec: dict) -> str:
    bad = [s["stages"] for s in rec["stages"] if s.get("exit")]
    if bad:
        return f"failed in {bad[0]}"
    failed = [k for k, m in rec.get("models", {}).items() if m["status"] != "complete"]
    return f"model {failed[0]}: {rec['models'][failed[0]]['status']}" if failed else "complete"


def run(example: str, until: str | None) -> dict:
    import yaml

    config = EXAMPLES[example]
    raw = yaml.safe_load((ROOT / config).read_text())
    out = ((ROOT / config).parent / raw["output_dir"]).resolve()
    steps = [("segment", ("--until", "segment", "--force")), ("build-model + coarsen", ("--until", "coarsen"))]
    if until != "coarsen":
        steps.append(("solve + report", ()))
    record = Run(defaults=True, command=f".venv/bin/python benchmarks/bench_examples.py {example}"
                 + (f" --until {until}" if until else ""))
    rec = {"example": example, "config": config, "date_utc": record.utc[:16].replace("T", " "), "stages": []}
    t_start = time.time()
    for label, args in steps:
        load0 = os.getloadavg()[0]
        wall, code, err, peak = _cli(config, *args)
        rec["stages"].append({"stages": label, "wall_s": round(wall, 1), "exit": code,
                              "load_avg": [round(load0, 1), round(os.getloadavg()[0], 1)],
                              "peak_rss_GB": round(peak, 2), **({"stderr_tail": err} if code else {})})
        if code:
            break
    rec["wall_s"] = round(sum(s["wall_s"] for s in rec["stages"]), 1)
    rec.update(record.fields())
    rec["models_nodes"] = _models(out)
    rec["models"] = _model_records(out, since=t_start)
    rec["reports"] = _outcome(out, since=t_start)
    keys = ("realisations", "F_max_mean_N", "F_max_sd_N", "ci95_low_N", "ci95_high_N", "noise_free_F_max_N",
            "noise_free_inside", "shift_N", "shift_percent", "force_per_muscle_volume_mean_N_per_cm3",
            "force_per_muscle_volume_ci95_low_N_per_cm3", "force_per_muscle_volume_ci95_high_N_per_cm3",
            "noise_free_force_per_muscle_volume_N_per_cm3", "config")
    for summary in [out / "uncertainty.json", *sorted(out.glob("*/uncertainty.json"))]:
        if summary.is_file() and summary.stat().st_mtime >= t_start:   # an uncertainty study: its interval
            u = json.loads(summary.read_text())
            key = "uncertainty" if summary.parent == out else f"uncertainty {summary.parent.name}"
            rec[key] = {k: u.get(k) for k in keys}
    rec["status"] = _status(rec)
    return rec


def from_run(example: str, run_dir: Path, wall_s: float | None, peak_gb: float | None,
             load_avg: list[float] | None) -> tuple[str, dict]:
    """The record of a run already made in ``run_dir`` (no solve); returns its key and the record.

    The key is the example's name, with the solved models in brackets when they are not all of
    the config's (e.g. ``lower_leg [coarse]``).
    """
    import yaml

    run_dir = Path(run_dir).resolve()
    if not run_dir.is_dir():
        raise SystemExit(f"--from-run {run_dir}: not a folder")
    lock = run_dir / ".pixmuscle.lock"
    started, argv = None, None
    if lock.is_file():
        info = json.loads(lock.read_text() or "{}")
        started, argv = info.get("started_utc"), info.get("argv")
    files = [p for p in run_dir.rglob("*") if p.is_file() and p.name != lock.name]
    end = max(p.stat().st_mtime for p in files) if files else None
    wall_source = "given (--wall-s)" if wall_s is not None else "not measured (no lock file in the folder)"
    if wall_s is None and started is not None and end is not None:
        wall_s = end - dt.datetime.fromisoformat(started).timestamp()
        wall_source = ("from the run folder: started_utc of its lock file (the last `pixmuscle run` in it) to the "
                       "newest file's modification time")
    models = _model_records(run_dir)
    config = EXAMPLES[example]
    wanted = yaml.safe_load((ROOT / config).read_text()).get("models") or ["coarse"]
    solved = sorted({k.rsplit("/", 1)[-1] for k in models}, key=lambda m: (m != "coarse", m))
    key = example if set(solved) >= set(wanted) else f"{example} [{', '.join(solved)}]"
    cmd = None
    if argv:
        prog = "pixmuscle" if Path(argv[0]).name in ("pixmuscle", "cli.py") else argv[0]
        cmd = shlex.join([prog, *argv[1:]])
    rec = {"example": example, "config": config,
           "date_utc": (started or "")[:16].replace("T", " "), "run_dir": str(run_dir),
           **Run(defaults=False).fields(peak_rss_GB=peak_gb), "commit_source": "the checkout when recorded, not "
           "necessarily the run's", "utc": started, "defaults_source": "not known for a run made by hand",
           "load_average": {"before": (load_avg or [None])[:1], "after": (load_avg or [None, None])[1:]},
           "command": cmd, "recorded_with": shlex.join(["python", "benchmarks/bench_examples.py", example,
                                                        "--from-run", str(run_dir)]
                                                       + (["--wall-s", f"{wall_s:g}"] if wall_source.startswith("given") else [])
                                                       + (["--peak-rss-gb", f"{peak_gb:g}"] if peak_gb is not None else [])
                                                       + (["--load-avg", *map(str, load_avg)] if load_avg else [])),
           "started_utc": started,
           "finished_utc": None if end is None else dt.datetime.fromtimestamp(end, dt.UTC).isoformat(timespec="seconds"),
           "stages": [], "wall_s": None if wall_s is None else round(float(wall_s), 1), "wall_s_source": wall_source,
           "peak_rss_GB": peak_gb, "peak_rss_source": "given (--peak-rss-gb)" if peak_gb is not None else "not measured",
           "load_avg": load_avg, "models_nodes": _models(run_dir), "models": models, "reports": _outcome(run_dir)}
    rec["status"] = _status(rec)
    return key, rec


def _g(v) -> str:
    return "—" if v is None else f"{v:.4g}"


def write(records: dict) -> None:
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "bench_examples.json").write_text(json.dumps(records, indent=2) + "\n")
    lines = ["## bench_examples: the paper's examples as shipped configs", "",
             "Wall times of `pixmuscle -q run CONFIG` in three calls (segment; build-model + coarsen; solve + "
             "report), on a 2-core machine **shared with other agents' jobs** (load average before/after each call).", ""]
    for name, r in records.items():
        lines += [f"### {name} (`{r['config']}`, {r['date_utc']} UTC)", "", f"Command: `{r['command']}`", ""]
        if r.get("recorded_with"):
            lines += [f"Run by hand in `{r['run_dir']}` ({r['started_utc']} to {r['finished_utc']}), recorded with "
                      f"`{r['recorded_with']}`: wall time {r['wall_s']} s ({r['wall_s_source']}), peak memory "
                      f"{r['peak_rss_GB']} GB ({r['peak_rss_source']}), load average "
                      f"{'/'.join(map(str, r['load_avg'])) if r.get('load_avg') else 'not recorded'}.", ""]
        if r["stages"]:
            peak = any("peak_rss_GB" in s for s in r["stages"])
            lines += ["| stages | wall (s) | exit | load avg |" + (" peak memory (GB) |" if peak else ""),
                      "|---|---|---|---|" + ("---|" if peak else "")]
            lines += [f"| {s['stages']} | {s['wall_s']} | {s['exit']} | {s['load_avg'][0]}/{s['load_avg'][1]} |"
                      + (f" {s.get('peak_rss_GB', '')} |" if peak else "") for s in r["stages"]]
            lines.append("")
        if r.get("status"):
            lines += [f"Status: {r['status']}", ""]
        lines += ["Models: " + ", ".join(f"`{k}` {v:,} nodes" for k, v in r["models_nodes"].items()), ""]
        if r.get("models"):
            lines += ["| model | nodes | steps converged | Newton iterations | F_max (N) | solve (s, solver's clock) "
                      "| linear solver | Krylov iterations | status |", "|---|---|---|---|---|---|---|---|---|"]
            lines += [f"| {k} | {m['nodes']:,} | {m['steps_converged']}/{m['steps_planned']} | {m['newton_iterations']} | "
                      f"{_g(m['F_max_N'])} | "
                      f"{m['solve_s']} | {m['linear_solver']} | {m['krylov_iterations']} | {m['status']} |"
                      for k, m in r["models"].items()]
            lines.append("")
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
    ap.add_argument("--from-run", type=Path, default=None, metavar="DIR",
                    help="record the finished run in DIR (its output folder) instead of running the example")
    ap.add_argument("--wall-s", type=float, default=None, help="with --from-run: the run's wall time, s (default: "
                    "from the lock file's start to the newest file)")
    ap.add_argument("--peak-rss-gb", type=float, default=None, help="with --from-run: the run's peak memory, GB")
    ap.add_argument("--load-avg", type=float, nargs="+", default=None,
                    help="with --from-run: load averages seen during the run (e.g. before and after)")
    a = ap.parse_args(argv)
    if a.from_run is None and (a.wall_s is not None or a.peak_rss_gb is not None or a.load_avg):
        ap.error("--wall-s, --peak-rss-gb and --load-avg go with --from-run")
    path = RESULTS / "bench_examples.json"
    records = json.loads(path.read_text()) if path.exists() else {}
    if a.from_run is not None:
        key, rec = from_run(a.example, a.from_run, a.wall_s, a.peak_rss_gb, a.load_avg)
        records[key] = rec
    else:
        records[a.example + ("" if a.until is None else f" (until {a.until})")] = run(a.example, a.until)
    write(records)
    print(json.dumps(records, indent=2)[-3000:])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

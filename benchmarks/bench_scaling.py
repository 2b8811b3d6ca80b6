"""The distributed solve under ``mpiexec -n P``: weak scaling at ~37k nodes per rank, and the refined
295k leg on two ranks against the serial sweep.

Models: the SYNTHETIC leg of ``bench_solve.py`` (Example 2 grid, both ends fixed, bone surfaces fixed
in-plane): ``37k`` = the 75k leg's cross-section over 12 slices, ``75k`` (25 slices), ``150k`` (50
slices), ``295k`` (the 75k leg on the paper's refined pixels). Solve: α 0 → 0.95 in 10 load steps,
every setting at its default except the backend, ``petsc_mixed`` (the distributed system,
:mod:`pixmuscle.mechanics.distributed`), through ``mpiexec -n P pixmuscle solve``.

Recorded per case: ``ranks``, ``nodes``, the held and owned nodes of rank 0, the wall time of the
command, each rank's own peak resident memory (``VmHWM`` written at its exit; under
``mpiexec`` there are no BoomerAMG worker processes) summed (``peak_rss_GB``) and the largest
(``peak_rss_GB_per_rank_max``), Newton iterations per step, ``krylov_iterations_per_system``, F_max
at ``z_max`` per step and the fields of :mod:`_record`. Four ranks on this 2-core machine are
oversubscribed: their rows count for memory and iterations, not time.

``SIZE:serial`` is the serial baseline of the same model and load steps: ``pixmuscle solve`` at the
shipped defaults (``auto``: ``mixed_amg`` with its BoomerAMG worker) in one child process, its peak
the largest sampled memory of that process tree (:func:`_record.run_child`); these rows stay in this
record only.

Run:  .venv/bin/python benchmarks/bench_scaling.py [--cases 37k:1 75k:2 150k:4 295k:2 295k:serial] [--solve-record]
      .venv/bin/python benchmarks/bench_scaling.py --model     # the memory model from the record
Results: benchmarks/results/bench_weak_scaling.json (``cases``, merged by case); with
``--solve-record`` the rows also go into bench_solve.json (as ``SIZE:petsc_mixed:P``). A killed case
resumes from its checkpoint when the same command runs again (the models and checkpoints live in
``out/bench_scaling/``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _record import Run, run_child  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results" / "bench_weak_scaling.json"
SOLVE_RESULTS = ROOT / "benchmarks" / "results" / "bench_solve.json"
WORK = ROOT / "out" / "bench_scaling"
CASES = ["37k:1", "75k:2", "150k:4"]
#: extra legs of this benchmark: (leg scale, slices[, spacing]) as bench_solve.SIZES
LEGS = {"37k": (1.04, 12), "150k": (1.04, 50)}
STEPS = 10


def _model(size: str, backend: str = "petsc_mixed") -> tuple[Path, Path]:
    """The model file (made once) and the config of ``size`` with ``backend`` (``auto``: the shipped
    default, the solver section left out)."""
    import bench_solve
    import yaml

    from pixmuscle.io.model import save_model

    bench_solve.SIZES.update(LEGS)
    work = WORK / size
    work.mkdir(parents=True, exist_ok=True)
    model_path, cfg_path = work / "model.h5", work / f"{backend}.yaml"
    if not model_path.exists():
        model, _ = bench_solve.leg_case(size, None)
        save_model(model_path, model)
    solve = {"boundary_conditions": [{"nodes": "z_min", "fix": ["x", "y", "z"]},
                                     {"nodes": "z_max", "fix": ["x", "y", "z"]},
                                     {"nodes": "bone_surface", "fix": ["x", "y"]}],
             "steps": STEPS, "activation": {"from": 0.0, "to": 0.95}}
    if backend != "auto":
        solve["solver"] = {"backend": backend}
    cfg_path.write_text(yaml.safe_dump({"solve": solve}))
    return model_path, cfg_path


def run_case(case: str) -> dict:
    """One case, ``SIZE:RANKS`` (``petsc_mixed`` under ``mpiexec -n RANKS``) or ``SIZE:serial`` (the
    shipped defaults in one process, its BoomerAMG worker included: the serial baseline)."""
    if case.split(":")[1] == "serial":
        return run_serial(case)

    from bench_backends import _mpiexec

    size, ranks = case.split(":")
    ranks = int(ranks)
    model_path, cfg_path = _model(size)
    out = model_path.parent / f"results_{ranks}.h5"
    peaks = model_path.parent / f"peak_{ranks}"
    for old in model_path.parent.glob(f"{peaks.name}.*"):
        old.unlink()
    cmd = [_mpiexec(), "-n", str(ranks), sys.executable, str(ROOT / "benchmarks" / "bench_backends.py"), "--rank",
           str(peaks), "--", "-q", "solve", str(model_path), "--config", str(cfg_path), "-o", str(out)]
    env = dict(os.environ, OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1",
               OMPI_MCA_rmaps_base_oversubscribe="1")
    record = Run(defaults=False, command=f".venv/bin/python benchmarks/bench_scaling.py --cases {case}")
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    row = {"case": case, "size": size, "backend": "petsc_mixed", "ranks": ranks, "steps": STEPS,
           "wall_s": round(wall, 1), "exit": proc.returncode,
           "settings": "shipped defaults except solve.solver.backend: petsc_mixed"}
    fields = record.fields()
    fields.pop("peak_rss_GB", None)  # this process's tree does not hold the ranks (mpiexec starts them)
    if proc.returncode:
        return {**row, "stderr_tail": proc.stderr[-2000:], **fields}
    per_rank = [float(p.read_text()) for p in sorted(model_path.parent.glob(f"{peaks.name}.*"))]
    row.update(_results(out), peak_rss_GB=round(sum(per_rank), 2), peak_rss_GB_per_rank_max=round(max(per_rank), 2),
               peak_rss_GB_per_rank=[round(p, 2) for p in per_rank])
    return {**row, **fields}


def run_serial(case: str) -> dict:
    """``SIZE:serial``: ``pixmuscle solve`` of the same model and load steps at the shipped defaults in
    one process; its peak memory is that of its process tree (:func:`_record.run_child`: the
    process and its BoomerAMG worker, sampled)."""
    size = case.split(":")[0]
    model_path, cfg_path = _model(size, "auto")
    out = model_path.parent / "results_serial.h5"
    record = Run(defaults=True, command=f".venv/bin/python benchmarks/bench_scaling.py --cases {case}")
    with tempfile.TemporaryFile("w+") as err:
        t0 = time.perf_counter()
        code, _, peak_kb = run_child(["-m", "pixmuscle.cli", "-q", "solve", str(model_path), "--config", str(cfg_path),
                                      "-o", str(out)], stderr=err, text=True)
        wall = time.perf_counter() - t0
        err.seek(0)
        tail = err.read()[-2000:]
    row = {"case": case, "size": size, "backend": "auto", "ranks": 1, "steps": STEPS, "wall_s": round(wall, 1),
           "exit": code, "settings": "shipped defaults"}
    fields = record.fields(peak_rss_GB=round(peak_kb / 1024**2, 2))
    if code:
        return {**row, "stderr_tail": tail, **fields}
    row.update(_results(out), peak_rss_GB_per_rank_max=fields["peak_rss_GB"])
    return {**row, **fields}


def _results(out: Path) -> dict:
    """The fields of a row read from its results file ``out``."""
    from pixmuscle.io.results import load_results

    res = load_results(out, lazy=False)
    info = res.info
    lin = [int(i) for i in info.get("linear_iterations", [])]
    return dict(nodes=int(res.model.n_nodes), spacing_cm=[float(h) for h in res.model.spacing], status=res.status,
                held_nodes_rank0=info.get("held_nodes"), owned_nodes_rank0=info.get("owned_nodes"),
                newton_iterations_per_step=[int(i) for i in res.iterations],
                krylov_iterations_per_system=lin, krylov_iterations_total=int(sum(lin)),
                preconditioner_builds=info.get("preconditioner_builds"),
                preconditioner_build_s=info.get("preconditioner_build_s"),
                resumed_after_step=info.get("resumed_after_step"), sweep_s=round(float(info["total_s"]), 1),
                build_s=round(float(info["build_s"]), 2),
                force_z_max_N=[float(f) for f in res.force("z_max")])


#: legs of the memory model's predictions: name → (leg scale, slices, spacing, what it is)
PREDICT = {"1M": (1.04, 85, (0.078125, 0.078125, 0.5), "the 295k leg's cross-section on the refined pixels, 42 cm long")}


def memory_model(data: dict, ranks: int = 8) -> dict:
    """Least-squares fit of the largest rank's peak (GB) against the nodes rank 0 held, over the rows of
    ``data``, and what it predicts for the legs of :data:`PREDICT` on ``ranks`` ranks (their held nodes
    from the partition and the halo of nominal supports of their voxel grid: a rank holds the nodes its
    rows need node by node, and the few supports enlarged beside thin features add little to that)."""
    import bench_solve
    import numpy as np

    from pixmuscle.mechanics.distributed import bisection_partition, halo, halo_depth

    rows = [c for c in data["cases"] if not c.get("exit") and c.get("backend") == "petsc_mixed"]
    held = np.array([c["held_nodes_rank0"] or c["nodes"] for c in rows], float)
    peak = np.array([c["peak_rss_GB_per_rank_max"] for c in rows])
    slope, base = np.polyfit(held, peak, 1)
    out = {"base_GB": float(base), "kB_per_held_node": float(slope * 1024**2), "rows": [c["case"] for c in rows],
           "predictions": []}
    depth = halo_depth(1.65, (2, 2, 3))
    for name, (scale, slices, spacing, what) in PREDICT.items():
        labels, _, _ = bench_solve.leg_labels(scale, slices, spacing)
        ijk = np.argwhere((labels > 0) & (labels != 4))
        part = bisection_partition(ijk, ranks)
        held_max = max(int(halo(ijk, part == r, depth).sum()) for r in range(ranks))
        out["predictions"].append({"leg": name, "what": what, "nodes": int(ijk.shape[0]), "ranks": ranks,
                                   "held_max": held_max, "GB_per_rank": float(base + slope * held_max)})
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", default=CASES, help="SIZE:RANKS or SIZE:serial, SIZE in 37k, 75k, 150k, 295k")
    ap.add_argument("--solve-record", action="store_true",
                    help="also merge the rows into bench_solve.json (a serial row as the case SIZE:auto, a sweep at the defaults)")
    ap.add_argument("--from-output", action="store_true",
                    help="no runs: read the fields that come from a case's kept results file (out/bench_scaling/SIZE/) into "
                         "its row again (a field added since it was made), its measured time and memory as they are")
    ap.add_argument("--model", action="store_true", help="only fit the memory model to the record and predict (no runs)")
    a = ap.parse_args(argv)
    data = json.loads(RESULTS.read_text()) if RESULTS.exists() else {"cases": []}
    if a.model:
        data["memory_model"] = {**memory_model(data), "command": ".venv/bin/python benchmarks/bench_scaling.py --model"}
        RESULTS.write_text(json.dumps(data, indent=2) + "\n")
        print(json.dumps(data["memory_model"], indent=2))
        return 0
    for case in a.cases:
        if a.from_output:
            row = next((r for r in data["cases"] if r["case"] == case), None)
            if row is None:
                ap.error(f"--from-output: {RESULTS.name} has no row {case!r} to read its results file into")
            size, ranks = case.split(":")
            row = {**row, **_results(_model(size, "auto" if ranks == "serial" else "petsc_mixed")[0].parent
                                     / f"results_{ranks}.h5")}
        else:
            row = run_case(case)
        data["cases"] = [r for r in data["cases"] if r["case"] != case] + [row]
        RESULTS.write_text(json.dumps(data, indent=2) + "\n")
        if a.solve_record and not row["exit"]:
            solve = json.loads(SOLVE_RESULTS.read_text())
            key = f"{row['size']}:auto" if row["backend"] == "auto" else f"{row['size']}:petsc_mixed:{row['ranks']}"
            entry = {**row, "case": key, "dofs": 3 * row["nodes"], "alpha_to": 0.95,
                     "newton_iterations_total": int(sum(row["newton_iterations_per_step"]))}
            solve["cases"] = [c for c in solve["cases"] if c.get("case") != key] + [entry]
            SOLVE_RESULTS.write_text(json.dumps(solve, indent=2) + "\n")
        print(case, row.get("wall_s"), "s", row.get("peak_rss_GB_per_rank_max"), "GB/rank",
              (row.get("force_z_max_N") or [None])[-1], "exit", row["exit"], flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

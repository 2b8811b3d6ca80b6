"""The linear-solver backends on one model: serial ``mixed_amg`` and ``direct`` against ``petsc_mixed``
under ``mpiexec -n 1`` and ``-n 2``.

Model: the 10,862-node fine model of ``configs/lower_leg_small.yaml`` (made by ``pixmuscle run
configs/lower_leg_small.yaml --until coarsen`` when ``out/lower_leg_small/model.h5`` is missing), solved
by ``pixmuscle solve`` with that config's solve section, 3 load steps (α 0 → 0.95), one backend per
case. Recorded per case: wall time of the command, peak resident memory of every rank (each rank
writes its own peak, ``VmHWM``, at exit) summed (``peak_rss_GB``) and the largest
(``peak_rss_GB_per_rank_max``), ``ranks``, Newton and Krylov iterations, preconditioner builds,
F_max at ``z_max``, the time estimate the solve prints at its start (:func:`pixmuscle.preflight.estimate_solve`)
and the fields of :mod:`_record`.

Run:  .venv/bin/python benchmarks/bench_backends.py [--cases mixed_amg:1 direct:1 petsc_mixed:1 petsc_mixed:2]
Results: benchmarks/results/bench_backends.json (``cases``, one row per backend and rank count, merged).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _record import Run  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results" / "bench_backends.json"
CONFIG = ROOT / "configs" / "lower_leg_small.yaml"
MODEL = ROOT / "out" / "lower_leg_small" / "model.h5"
STEPS = 3
CASES = ["mixed_amg:1", "direct:1", "petsc_mixed:1", "petsc_mixed:2"]


def _rank_main(peak_file: str, argv: list[str]) -> None:
    """Run the CLI in this process and write this rank's peak resident memory (GB) at exit."""
    import atexit

    rank = os.environ.get("OMPI_COMM_WORLD_RANK", os.environ.get("PMI_RANK", "0"))

    def _write():
        with open("/proc/self/status") as f:  # VmHWM, not ru_maxrss, which keeps the size of the forked parent
            kb = next(int(line.split()[1]) for line in f if line.startswith("VmHWM:"))
        Path(f"{peak_file}.{rank}").write_text(str(kb / 1024**2))

    atexit.register(_write)
    from pixmuscle.cli import main

    sys.argv = ["pixmuscle", *argv]
    main()


def _mpiexec() -> str:
    exe = shutil.which("mpiexec", path=str(Path(sys.executable).parent)) or shutil.which("mpiexec")
    if exe is None:
        raise SystemExit("bench_backends: no mpiexec (make test installs the PETSc/MPI backend)")
    return exe


def run_case(case: str, work: Path) -> dict:
    import numpy as np
    import yaml

    from pixmuscle.io.results import load_results
    from pixmuscle.preflight import estimate_solve

    backend, ranks = case.split(":")
    ranks = int(ranks)
    solve = yaml.safe_load(CONFIG.read_text())["solve"]
    solve.update(steps=STEPS, solver={"backend": backend})
    cfg = work / f"{backend}_{ranks}.yaml"
    cfg.write_text(yaml.safe_dump({"solve": solve}))
    out, peaks = work / f"{backend}_{ranks}.h5", work / f"{backend}_{ranks}.peak"
    cmd = [sys.executable, str(Path(__file__).resolve()), "--rank", str(peaks), "--", "-q", "solve", str(MODEL),
           "--config", str(cfg), "-o", str(out)]
    env = dict(os.environ)
    if backend.startswith("petsc"):
        cmd = [_mpiexec(), "-n", str(ranks), *cmd]
        env.update(OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1", OMPI_MCA_rmaps_base_oversubscribe="1")
    record = Run(defaults=False, command=f".venv/bin/python benchmarks/bench_backends.py --cases {case}")
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    row = {"case": case, "backend": backend, "ranks": ranks, "steps": STEPS, "wall_s": round(wall, 1),
           "exit": proc.returncode}
    if proc.returncode:
        row["stderr_tail"] = proc.stderr[-2000:]
        return {**row, **record.fields()}
    per_rank = [float(p.read_text()) for p in sorted(work.glob(f"{peaks.name}.*"))]
    res = load_results(out)
    info = res.info
    row.update(nodes=int(res.model.n_nodes), status=res.status,
               peak_rss_GB=round(sum(per_rank), 2), peak_rss_GB_per_rank_max=round(max(per_rank), 2),
               peak_rss_GB_per_rank=[round(p, 2) for p in per_rank],
               newton_iterations=int(np.sum(res.iterations)), krylov_iterations=info.get("krylov_iterations"),
               preconditioner_builds=info.get("preconditioner_builds"), solve_s=round(float(info["total_s"]), 1),
               force_z_max_N=float(np.max(np.asarray(res.force("z_max")))),
               estimate_s=round(estimate_solve(int(res.model.n_nodes), STEPS)[0], 1))
    fields = record.fields()
    fields.pop("peak_rss_GB", None)  # this process's tree does not hold the ranks (MPI starts them)
    return {**row, **fields}


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--rank"]:
        _rank_main(argv[1], argv[3:])
        return 0
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", default=CASES)
    a = ap.parse_args(argv)
    if not MODEL.exists():
        subprocess.run([sys.executable, "-m", "pixmuscle.cli", "-q", "run", str(CONFIG), "--until", "coarsen"], check=True)
    data = json.loads(RESULTS.read_text()) if RESULTS.exists() else {"model": str(MODEL.relative_to(ROOT)), "cases": []}
    with tempfile.TemporaryDirectory() as tmp:
        for case in a.cases:
            row = run_case(case, Path(tmp))
            data["cases"] = [r for r in data["cases"] if r["case"] != case] + [row]
            RESULTS.write_text(json.dumps(data, indent=2) + "\n")
            print(case, row.get("wall_s"), "s", row.get("peak_rss_GB_per_rank_max"), "GB/rank", row.get("force_z_max_N"),
                  "exit", row["exit"], flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

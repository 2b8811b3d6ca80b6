"""Benchmark of the ``petsc`` backend on 1 and 2 MPI ranks against a serial backend, whole sweeps.

Model: the SYNTHETIC leg of ``bench_solve.py`` at a given size (default ``5k``: 5,460 nodes,
8 slices), the Example 2 boundary conditions, α 0 → 0.95 in 10 load steps, Newton residual
tolerance 1e-2 (the ``5k:cg_amg:1e-2`` case of bench_solve). Every case runs through the CLI,
``pixmuscle solve model.h5 --config c.yaml -o results.h5``, the petsc cases under
``mpiexec -n P``; each rank records its own peak RSS. Records per case: sweep time (the solve's
``total_s``), Newton and Krylov iterations, linear set-up and solve time, final force, peak RSS
per rank, and the force difference from the serial backend (``--serial``, default cg_amg). Writes ``benchmarks/results/bench_petsc.json``
and ``bench_petsc.md``.

Usage::

    .venv/bin/python benchmarks/bench_petsc.py                 # 5k: cg_amg, petsc 1 rank, petsc 2 ranks (10 steps)
    .venv/bin/python benchmarks/bench_petsc.py --size 2k --steps 5 --serial auto   # the recorded run
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import shlex
import shutil
import subprocess
import sys
import tempfile

import numpy as np
import yaml

HERE = pathlib.Path(__file__).parent
OUT = HERE / "results"
sys.path.insert(0, str(HERE.resolve()))
from _record import Run, own_peak_kb  # noqa: E402


def _rank_main(rss_dir: str, argv: list[str]) -> None:
    """Run the CLI in this process and write this rank's peak RSS (GB) on exit."""
    import atexit

    rank = os.environ.get("OMPI_COMM_WORLD_RANK", os.environ.get("PMI_RANK", "0"))

    def _rss():
        gb = own_peak_kb() / 1024**2  # VmHWM: ru_maxrss keeps the size of the forked parent
        pathlib.Path(rss_dir, f"rss_{rank}.txt").write_text(f"{gb:.3f}")

    atexit.register(_rss)
    from pixmuscle.cli import main

    sys.argv = ["pixmuscle"] + argv
    main()


def run_case(tmp: pathlib.Path, model: pathlib.Path, cfg: dict, backend: str, ranks: int) -> dict:
    from pixmuscle.io.results import load_results

    name = f"{backend}_{ranks}"
    conf = tmp / f"{name}.yaml"
    conf.write_text(yaml.safe_dump({"solve": dict(cfg, solver={"backend": backend})}))
    out, rss = tmp / f"{name}.h5", tmp / f"rss_{name}"
    rss.mkdir()
    cmd = [sys.executable, str(pathlib.Path(__file__).resolve()), "--rank-run", str(rss), "-q", "solve", str(model),
           "--config", str(conf), "-o", str(out)]
    if backend == "petsc":
        cmd = [shutil.which("mpiexec"), "--oversubscribe", "-n", str(ranks)] + cmd
    env = dict(os.environ, OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1", OMP_NUM_THREADS="1")
    record = Run(defaults=False, command=shlex.join(cmd))
    subprocess.run(cmd, check=True, env=env)
    res = load_results(out)
    per_rank = [float((rss / f"rss_{r}.txt").read_text()) for r in range(ranks)]
    info = res.info
    return {
        "backend": backend, "ranks": ranks, "status": res.status,
        "sweep_s": round(info["total_s"], 1), "build_s": round(info["build_s"], 1),
        "linear_setup_s": round(info["linear_setup_s"], 1), "linear_solve_s": round(info["linear_solve_s"], 1),
        "material_s": round(info["material_s"], 1),
        "newton_iterations_total": int(np.sum(res.iterations)),
        "krylov_iterations_total": int(info.get("krylov_iterations", 0)),
        "krylov_iterations_per_newton": round(float(np.mean(info["linear_iterations"])), 1),
        "preconditioner_builds": int(info.get("preconditioner_builds", 0)),
        "force_z_max_N": [float(f) for f in res.force("z_max")],
        "peak_rss_GB_per_rank": per_rank,
        # the ranks together (each its own process; the command is the case's, with its temporary files)
        **record.fields(peak_rss_GB=round(sum(per_rank), 2)),
    }


def write_tables(size: str, n_nodes: int, cases: list[dict], command: str) -> None:
    ref = cases[0]  # the serial backend
    f_ref = np.asarray(ref["force_z_max_N"])
    for c in cases:
        c["max_force_deviation_vs_serial"] = float(np.max(np.abs(np.asarray(c["force_z_max_N"]) - f_ref))
                                                   / np.max(np.abs(f_ref)))
    meta = {"command": command, "size": size, "nodes": n_nodes, "machine": cases[0]["machine"],
            "cpus": cases[0]["machine"]["cpus"], "load_average_at_start": cases[0]["load_average"]["before"]}
    (OUT / "bench_petsc.json").write_text(json.dumps({"meta": meta, "cases": cases}, indent=1))
    lines = [f"# bench_petsc: activation sweep of the SYNTHETIC leg ({size}, {n_nodes:,} nodes), petsc vs {cases[0]['backend']} (serial)", "",
             f"Command: `{command}` (10 load steps unless --steps; Newton residual tolerance 1e-2)", "",
             f"Machine: {meta['cpus']} CPUs shared with other jobs (load average at start "
             f"{meta['load_average_at_start'][0]:.1f}): times are upper bounds, the 2-rank case shares the cores.", "",
             "| backend | ranks | sweep s | linear set-up s | linear solve s | Newton its | Krylov its | Krylov/Newton "
             "| peak RSS per rank GB | max ΔF vs serial |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for c in cases:
        lines.append(f"| {c['backend']} | {c['ranks']} | {c['sweep_s']} | {c['linear_setup_s']} | {c['linear_solve_s']} | "
                     f"{c['newton_iterations_total']} | {c['krylov_iterations_total']} | {c['krylov_iterations_per_newton']} | "
                     f"{', '.join(f'{x:.2f}' for x in c['peak_rss_GB_per_rank'])} | {c['max_force_deviation_vs_serial']:.1e} |")
    (OUT / "bench_petsc.md").write_text("\n".join(lines) + "\n")


def main() -> None:
    if len(sys.argv) > 2 and sys.argv[1] == "--rank-run":
        _rank_main(sys.argv[2], sys.argv[3:])
        return
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", default="5k")
    ap.add_argument("--ranks", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--serial", default="cg_amg", help="serial backend to compare with (cg_amg, direct, auto)")
    args = ap.parse_args()
    sys.path.insert(0, str(HERE))
    from bench_solve import leg_case, newton_tolerances

    from pixmuscle.io.model import save_model

    model, _ = leg_case(args.size, None)
    cfg = {"steps": args.steps, "activation": {"from": 0.0, "to": 0.95}, **newton_tolerances(1e-2),
           "boundary_conditions": [{"nodes": "z_min", "fix": ["x", "y", "z"]}, {"nodes": "z_max", "fix": ["x", "y", "z"]},
                                   {"nodes": "bone_surface", "fix": ["x", "y"]}]}
    cases = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = pathlib.Path(tmp)
        save_model(tmp / "model.h5", model)
        cases.append(run_case(tmp, tmp / "model.h5", cfg, args.serial, 1))
        for p in args.ranks:
            cases.append(run_case(tmp, tmp / "model.h5", cfg, "petsc", p))
            print(json.dumps(cases[-1]), flush=True)
    write_tables(args.size, model.n_nodes, cases, ".venv/bin/python benchmarks/bench_petsc.py " + " ".join(sys.argv[1:]))


if __name__ == "__main__":
    main()

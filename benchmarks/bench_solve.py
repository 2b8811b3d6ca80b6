"""Benchmark of the SCNI–RKPM solve on a synthetic lower-leg-like model.

Builds a label volume with an elliptic cross-section (muscle core with two pennate halves, a
subcutaneous fat ring, a connective-tissue septum, a bone hole fixed in-plane), runs a short
isometric activation sweep (paper Example 2 boundary conditions) and records

* build time (RK shape functions + SCNI operators + pattern + NSNI + penalty),
* assembly time per Newton iteration, linear-solver time per iteration (factorisation or
  GMRES with kept factors), number of factorisations,
* Newton iterations per step, peak RSS, non-zeros per row of the stiffness.

Writes ``benchmarks/results/bench_solve.json`` and ``benchmarks/results/bench_solve.md``.

Usage::

    .venv/bin/python benchmarks/bench_solve.py            # ~5k nodes
    .venv/bin/python benchmarks/bench_solve.py --sizes 5000 20000
"""

from __future__ import annotations

import argparse
import json
import pathlib
import platform
import resource
import time

import numpy as np

from pixmuscle.config import parse_section
from pixmuscle.mechanics.config import SolveConfig
from pixmuscle.mechanics.solve import solve
from pixmuscle.model.build import model_from_labels

OUT = pathlib.Path(__file__).parent / "results"


def leg_labels(target_nodes: int, spacing=(0.3125, 0.3125, 1.0), n_slices: int = 8):
    """Label volume (0 bg, 1 muscle, 2 CT, 3 fat, 4 bone) of about ``target_nodes`` nodes, and fibres."""
    per_slice = target_nodes / n_slices
    hx, hy, _ = spacing
    # ellipse area π a b with b = 0.8 a, minus bone: solve for a (cm)
    a = np.sqrt(per_slice * hx * hy / (np.pi * 0.8 * 0.96))
    b = 0.8 * a
    nx, ny = int(np.ceil(2 * a / hx)) + 3, int(np.ceil(2 * b / hy)) + 3
    x = (np.arange(nx) - (nx - 1) / 2) * hx
    y = (np.arange(ny) - (ny - 1) / 2) * hy
    X, Y = np.meshgrid(x, y, indexing="ij")
    r = (X / a) ** 2 + (Y / b) ** 2
    body = r <= 1.0
    bone = ((X + 0.3 * a) / (0.2 * a)) ** 2 + (Y / (0.2 * b)) ** 2 <= 1.0
    fat = body & (r > 0.8)
    septum = body & ~fat & (np.abs(X - 0.1 * a) < 0.6 * hx)
    lab2 = np.zeros((nx, ny), np.int16)
    lab2[body] = 1
    lab2[fat] = 3
    lab2[septum] = 2
    lab2[bone] = 4
    labels = np.repeat(lab2[:, :, None], n_slices, axis=2)
    pen = np.deg2rad(15.0)
    fib2 = np.zeros((nx, ny, 3))
    fib2[X < 0.1 * a] = [np.sin(pen), 0.0, np.cos(pen)]
    fib2[X >= 0.1 * a] = [-np.sin(pen), 0.0, np.cos(pen)]
    fibers = np.repeat(fib2[:, :, None, :], n_slices, axis=2)
    return labels, fibers, np.asarray(spacing, float)


def run_case(target_nodes: int, steps: int, alpha_to: float) -> dict:
    labels, fibers, h = leg_labels(target_nodes)
    t0 = time.perf_counter()
    model = model_from_labels(labels, h, fibers=fibers)
    t_model = time.perf_counter() - t0
    cfg = parse_section(SolveConfig, {
        "steps": steps,
        "activation": {"from": 0.0, "to": alpha_to},
        "boundary_conditions": [{"nodes": "z_min", "fix": ["x", "y", "z"]}, {"nodes": "z_max", "fix": ["x", "y", "z"]},
                                {"nodes": "bone_surface", "fix": ["x", "y"]}],
    }, "solve")
    t1 = time.perf_counter()
    res = solve(model, cfg)
    wall = time.perf_counter() - t1
    info = res.info
    n_it = int(np.sum(res.iterations))
    n_asm = max(int(info["n_assembly"]), 1)
    tissue = np.bincount(model.tissue, minlength=4)
    return {
        "target_nodes": target_nodes,
        "nodes": model.n_nodes,
        "dofs": 3 * model.n_nodes,
        "tissue_nodes": {"muscle": int(tissue[1]), "connective_tissue": int(tissue[2]), "fat": int(tissue[3])},
        "spacing_cm": h.tolist(),
        "steps": steps,
        "alpha_to": alpha_to,
        "status": res.status,
        "model_build_s": round(t_model, 3),
        "build_s": round(info["build_s"], 3),
        "build_detail_s": {k: round(info[k], 3) for k in ("scni_s", "pattern_s", "stabilization_s", "penalty_s")},
        "newton_iterations_per_step": res.iterations.tolist(),
        "newton_iterations_total": n_it,
        "cutbacks": res.cutbacks.tolist(),
        "assembly_s_per_iteration": round(info["assembly_s"] / n_asm, 3),
        "material_eval_s_per_iteration": round(info["material_s"] / max(info["n_evaluate"], 1), 3),
        "linear_s_per_iteration": round((info["linear_setup_s"] + info["linear_solve_s"]) / n_asm, 3),
        "linear_solver": info["linear_solver"],
        "factorizations": info.get("factorizations"),
        "krylov_iterations": info.get("linear_iterations"),
        "solve_wall_s": round(wall, 2),
        "nnz": int(info["nnz"]),
        "nnz_per_row": round(float(info["nnz_per_row"]), 1),
        "beta_N_per_cm3": info["beta"],
        "final_force_z_max_N": float(res.force("z_max")[-1]),
        "peak_rss_MB": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
    }


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[5000], help="target node counts")
    p.add_argument("--steps", type=int, default=3)
    p.add_argument("--alpha", type=float, default=0.3, help="final activation (larger increments need more Newton iterations)")
    args = p.parse_args(argv)
    OUT.mkdir(parents=True, exist_ok=True)
    cases = []
    for n in args.sizes:
        print(f"case ~{n} nodes ...", flush=True)
        cases.append(run_case(n, args.steps, args.alpha))
        print(json.dumps(cases[-1], indent=1), flush=True)
    meta = {"python": platform.python_version(), "machine": platform.machine(), "cpus": __import__("os").cpu_count(),
            "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "note": "peak RSS is per process, cumulative over cases"}
    (OUT / "bench_solve.json").write_text(json.dumps({"meta": meta, "cases": cases}, indent=2))
    lines = ["# bench_solve: SCNI–RKPM isometric activation of a synthetic leg", "",
             f"{meta['date_utc']}, Python {meta['python']}, {meta['cpus']} CPUs (shared). Command: "
             "`.venv/bin/python benchmarks/bench_solve.py " + " ".join(["--sizes", *map(str, args.sizes), "--steps", str(args.steps), "--alpha", str(args.alpha)]) + "`", "",
             "| nodes | nnz/row | build (s) | assembly / it (s) | linear / it (s) | factorisations | Newton its per step | solve wall (s) | peak RSS (MB) | status |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for c in cases:
        lines.append(f"| {c['nodes']} | {c['nnz_per_row']} | {c['build_s']} | {c['assembly_s_per_iteration']} | "
                     f"{c['linear_s_per_iteration']} | {c['factorizations']} | {c['newton_iterations_per_step']} | "
                     f"{c['solve_wall_s']} | {c['peak_rss_MB']} | {c['status'][:40]} |")
    (OUT / "bench_solve.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()

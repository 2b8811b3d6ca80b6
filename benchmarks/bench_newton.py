"""Newton on a clamped muscle block with oblique fibres: iterations per load step and cutbacks.

Case (scale issue, target 6): a 2 × 1.67 × 6 cm block of muscle (Table 2 constants), fibres in
the x–z plane at 25° to the block's axis z, both ends fixed in x, y, z, activation α 0 → 0.95 in
10 load steps; cubic voxels of ``--h`` cm (default 1/3 cm: 6 × 5 × 18 = 540 nodes; the issue's
1/6 cm gives 3,888 nodes). Every other setting at its default; ``solve.volumetric`` nodal and
projected. Records Newton iterations per step (failed attempts included), cutbacks, the end force
and the wall time.

Writes ``benchmarks/results/bench_newton.json`` and ``.md``.

Usage::

    .venv/bin/python benchmarks/bench_newton.py
    .venv/bin/python benchmarks/bench_newton.py --h 0.1666667
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from _record import Run  # noqa: E402

OUT = pathlib.Path(__file__).parent / "results"
SIZE_CM = (2.0, 1.67, 6.0)
ANGLE_DEG = 25.0


def run(h: float, methods) -> list[dict]:
    from pixmuscle.errors import SolverError
    from pixmuscle.mechanics.solve import solve
    from pixmuscle.verify.mechanics import _cfg, mask_model

    n = [max(1, round(s / h)) for s in SIZE_CM]
    a = np.deg2rad(ANGLE_DEG)
    model = mask_model(np.ones(n, bool), (h, h, h), tissue=1, fiber=(np.sin(a), 0.0, np.cos(a)))
    rows = []
    for method in methods:
        cfg = _cfg(steps=10, activation={"from": 0.0, "to": 0.95}, volumetric={"method": method},
                   boundary_conditions=[{"nodes": "z_min", "fix": ["x", "y", "z"]}, {"nodes": "z_max", "fix": ["x", "y", "z"]}])
        t = time.perf_counter()
        try:
            res, status = solve(model, cfg), "complete"
        except SolverError as exc:
            res, status = exc.results, f"failed: {exc}"
        its = res.iterations.tolist()
        rows.append({"volumetric": method, "voxels": n, "h_cm": h, "nodes": model.n_nodes, "status": status,
                     "newton_iterations_per_step": its, "max_iterations_per_step": int(max(its)),
                     "cutbacks": res.cutbacks.tolist(), "force_z_max_N": float(res.force("z_max")[-1]),
                     "sweep_s": round(time.perf_counter() - t, 1)})
        print(json.dumps(rows[-1]), flush=True)
    return rows


def write(rows, run: Run) -> None:
    meta = run.fields()
    command = meta["command"]
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "bench_newton.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    lines = ["# Newton on the clamped oblique-fibre muscle block", "", f"Command: `{command}`", "",
             f"{meta['utc']}, commit {meta['commit'][:10]}, {meta['machine']['cpus']} CPUs, load average "
             f"{meta['load_average']['before'][0]} before, {meta['load_average']['after'][0]} after.", "",
             "| volumetric | nodes | Newton iterations per step | cutbacks | F_z [N] | sweep [s] | status |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['volumetric']} | {r['nodes']} | {r['newton_iterations_per_step']} | {sum(r['cutbacks'])} | "
                     f"{r['force_z_max_N']:.3f} | {r['sweep_s']} | {r['status'][:60]} |")
    (OUT / "bench_newton.md").write_text("\n".join(lines) + "\n")


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--h", type=float, default=1.0 / 3.0, help="voxel edge, cm")
    p.add_argument("--volumetric", nargs="+", default=["nodal", "projected"])
    args = p.parse_args(argv)
    record = Run(defaults=False, command=" ".join([".venv/bin/python benchmarks/bench_newton.py", *argv]))
    rows = run(args.h, args.volumetric)
    write(rows, record)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

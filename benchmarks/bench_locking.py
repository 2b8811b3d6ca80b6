"""Volumetric locking: force error of a clamped, stretched bar against K/μ, nodal vs projected volumetric energy.

Case: a 0.8 × 0.8 × 6 cm bar of connective tissue (Table 1: C10 = 30, C20 = 80, C30 = 800 N/cm²,
μ = 2 C10 = 60 N/cm²) on 0.2 × 0.2 × 0.5 cm voxels (4 × 4 × 12 nodes), bottom end fixed in x, y,
z, top end held in x, y and stretched 0.3 cm; the bulk modulus K is varied so that K/μ = 10 … 8,300
(the paper's tissues have K/μ ≈ 800–1,000). The clamps suppress the lateral contraction, so the
nearly incompressible bar forms boundary layers at both ends: the case where a formulation with
too many volumetric constraints locks.

Reference: scikit-fem mixed Q2–P1disc finite elements on the same voxel domain, each voxel split
into (2, 2, 4) elements (:func:`pixmuscle.verify.tendon_fem.tendon_fem_reaction`), converged to
≈ 0.1 %. Meshfree: ``solve.volumetric`` ``nodal`` (K/2 (J − 1)² at every node, the paper) and
``projected`` (mean dilatation per 3 × 3 × 3-voxel patch, the default).

Writes ``benchmarks/results/bench_locking.json`` and ``.md``.

Usage::

    .venv/bin/python benchmarks/bench_locking.py            # K/μ = 10, 100, 833, 8333
    .venv/bin/python benchmarks/bench_locking.py --kmu 833
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
MU = 60.0  # 2 C10 of connective tissue, N/cm²
H = (0.2, 0.2, 0.5)
STRETCH = 0.3


def run(kmu_values, refine=(2, 2, 4)) -> list[dict]:
    from pixmuscle.mechanics.solve import solve
    from pixmuscle.verify.mechanics import _cfg, mask_model
    from pixmuscle.verify.tendon_fem import tendon_fem_reaction

    mask = np.ones((4, 4, 12), bool)
    model = mask_model(mask, H)
    bcs = [{"nodes": "z_min", "fix": ["x", "y", "z"]}, {"nodes": "z_max", "fix": ["x", "y"], "displace": {"z": STRETCH}}]
    rows = []
    for kmu in kmu_values:
        K = kmu * MU
        t = time.perf_counter()
        fe = tendon_fem_reaction(mask, np.diag([*H, 1.0]), stretch=STRETCH, steps=1, refine=refine, element="mixed",
                                 bc="clamped", material=(30.0, 80.0, 800.0, K))
        ref = float(fe["force"][-1])
        row = {"K_over_mu": kmu, "K_N_per_cm2": K, "fe_force_N": ref, "fe_refine": list(refine), "fe_dofs": int(fe.get("dofs", 0)),
               "fe_s": round(time.perf_counter() - t, 1)}
        for method in ("nodal", "projected"):
            cfg = _cfg(steps=1, activation={"from": 0.0, "to": 0.0}, boundary_conditions=bcs, volumetric={"method": method},
                       materials={"connective_tissue": {"K": K}})
            t = time.perf_counter()
            res = solve(model, cfg)
            f = float(res.force("z_min")[-1])
            row[method] = {"force_N": f, "rel_error": f / ref - 1.0, "newton_iterations": int(res.iterations.sum()),
                           "s": round(time.perf_counter() - t, 2)}
        rows.append(row)
        print(json.dumps(row), flush=True)
    return rows


def write(rows, run: Run) -> None:
    meta = {**run.fields(), "note": "timings taken while other jobs shared the 2-core machine; forces do not depend on that"}
    command = meta["command"]
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "bench_locking.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    lines = ["# Volumetric locking: clamped bar, force error against K/μ", "", f"Command: `{command}`", "",
             f"{meta['utc']}, commit {meta['commit'][:10]}, {meta['machine']['cpus']} CPUs; {meta['note']}.", "",
             "| K/μ | FE force [N] | nodal [N] | nodal error | projected [N] | projected error |", "|---|---|---|---|---|---|"]
    for r in rows:
        n, p = r["nodal"], r["projected"]
        lines.append(f"| {r['K_over_mu']:g} | {r['fe_force_N']:.4f} | {n['force_N']:.4f} | {100 * n['rel_error']:+.2f} % | "
                     f"{p['force_N']:.4f} | {100 * p['rel_error']:+.2f} % |")
    (OUT / "bench_locking.md").write_text("\n".join(lines) + "\n")


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--kmu", type=float, nargs="+", default=[10.0, 100.0, 833.3, 8333.3], help="values of K/μ")
    args = p.parse_args(argv)
    record = Run(defaults=False, command=" ".join([".venv/bin/python benchmarks/bench_locking.py", *argv]))
    rows = run(args.kmu)
    write(rows, record)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

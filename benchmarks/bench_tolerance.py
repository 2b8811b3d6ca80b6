"""How much the Newton tolerance changes forces and fields: the leg sweep at the default and at
looser residual tolerances, side by side.

Case: the SYNTHETIC leg of ``bench_solve.py`` (Example 2 boundary conditions, α 0 → 0.95 in 10
load steps, every setting at its default, ``solver.backend: auto``) solved once per Newton
residual tolerance (``solve.newton.residual_tol``; the energy tolerance follows as 100 · tol²,
as in ``bench_solve.py``, unless a case gives it: ``RES:ENERGY``). Each looser solve is compared, at
every load step, with the solve at the reference tolerance 10⁻⁸ (energy 10⁻¹⁴):

- ``force_rel``: largest |ΔF| of any component of the reaction at either fixed end, over the
  steps, relative to the largest |F| of the reference sweep;
- ``u_rel``: largest |Δu| over nodes and steps relative to the largest |u| of the reference;
- ``stress_rel``: the same for the Cauchy stress (largest |Δσ_ij| relative to the largest |σ_ij|).

Each solve's fields are kept in ``--work`` (``case_<size>_<tol>.npz``), so a killed run is continued by
running the same command again (finished tolerances are read back, not solved again: delete that
folder after changing the code).

Writes ``benchmarks/results/bench_tolerance_<size>.json`` and ``.md``.

Usage::

    .venv/bin/python benchmarks/bench_tolerance.py --size 5k
    .venv/bin/python benchmarks/bench_tolerance.py --size 20k --tols 1e-8 1e-3 1e-2
    .venv/bin/python benchmarks/bench_tolerance.py --size 20k --tols 1e-4:1e-6 1e-4:1e-4   # residual:energy
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import pathlib
import sys
import time

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).parent))
from _record import Run, command_line  # noqa: E402
from bench_solve import SIZES, leg_case  # noqa: E402

OUT = pathlib.Path(__file__).parent / "results"
REFERENCE_TOL = 1e-8  # the reference solve: Newton to about round-off (energy tolerance 1e-14)


def parse_tol(spec: str) -> tuple[float, float]:
    """``RES`` or ``RES:ENERGY`` → (residual tolerance, energy tolerance); the energy tolerance is
    100 · RES² where not given."""
    parts = spec.split(":")
    if not 1 <= len(parts) <= 2:
        raise argparse.ArgumentTypeError(f"tolerance {spec!r}: expected RES or RES:ENERGY")
    res = float(parts[0])
    return _tol(res, float(parts[1]) if len(parts) == 2 else 100.0 * res**2)


def _tol(res: float, energy: float) -> tuple[float, float]:
    """(residual, energy) tolerance rounded to 12 digits, so that 100 · 1e-4² is 1e-6."""
    return float(f"{res:.12g}"), float(f"{energy:.12g}")


def solve_case(size: str, tol: tuple[float, float], steps: int, work: pathlib.Path) -> dict:
    """Fields of one sweep at ``tol`` (residual, energy tolerance) (read from ``work`` when an
    earlier run finished it)."""
    path = work / f"case_{size}_{tol[0]:g}_{tol[1]:g}.npz"
    if path.exists():
        with np.load(path, allow_pickle=False) as f:
            return {k: f[k] for k in f.files}
    from pixmuscle.mechanics.config import NewtonConfig
    from pixmuscle.mechanics.solve import solve

    model, cfg = leg_case(size, None, steps=steps, activation={"from": 0.0, "to": 0.95},
                          newton={"residual_tol": tol[0], "energy_tol": tol[1]})
    record = Run(defaults=steps == 10 and tol == _tol(NewtonConfig().residual_tol, NewtonConfig().energy_tol))
    load0 = os.getloadavg()
    t = time.perf_counter()
    res = solve(model, cfg)
    wall = time.perf_counter() - t
    forces = np.stack([np.asarray(res.reaction[k], float) for k in ("z_min", "z_max")], axis=1)  # (S+1, 2, 3)
    out = {"u": np.asarray(res.u, float), "cauchy": np.asarray(res.cauchy, float), "forces": forces,
           "iterations": np.asarray(res.iterations), "cutbacks": np.asarray(res.cutbacks),
           "linear_iterations": np.asarray(res.info.get("linear_iterations", []), float),
           "sweep_s": np.float64(wall), "nodes": np.int64(model.n_nodes),
           "load": np.asarray([*load0, *os.getloadavg()]), "backend": np.str_(res.info.get("linear_solver", "")),
           "status": np.str_(res.status), "record": np.str_(json.dumps(record.fields()))}
    work.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, **out)
    os.replace(tmp, path)
    return out


def compare(ref: dict, case: dict) -> dict:
    """Largest differences of ``case`` from ``ref`` over every stored step (relative, see module docstring)."""
    def rel(a, b):
        return float(np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300))

    return {"force_rel": rel(case["forces"], ref["forces"]), "u_rel": rel(case["u"], ref["u"]),
            "stress_rel": rel(case["cauchy"], ref["cauchy"])}


def run(size: str, tols: list[tuple[float, float]], steps: int, work: pathlib.Path) -> dict:
    from pixmuscle.mechanics.config import NewtonConfig

    default = _tol(NewtonConfig().residual_tol, NewtonConfig().energy_tol)
    reference = _tol(REFERENCE_TOL, 100.0 * REFERENCE_TOL**2)
    tols = sorted(set(tols) | {reference})
    cases = {}
    for tol in tols:
        cases[tol] = solve_case(size, tol, steps, work)
        c = cases[tol]
        print(f"{size} Newton {tol[0]:g}, energy {tol[1]:g}: {int(np.sum(c['iterations']))} Newton its, "
              f"{float(c['sweep_s']):.0f} s", flush=True)
    ref = cases[reference]
    rows = []
    for tol in tols:
        c = cases[tol]
        rows.append({"newton_residual_tol": tol[0], "newton_energy_tol": tol[1], "reference": tol == reference,
                     "default": tol == default, "status": str(c["status"]), "nodes": int(c["nodes"]),
                     "newton_iterations_per_step": c["iterations"].astype(int).tolist(),
                     "newton_iterations_total": int(np.sum(c["iterations"])), "cutbacks": int(np.sum(c["cutbacks"])),
                     "krylov_iterations_total": int(np.sum(c["linear_iterations"])) or None,
                     "sweep_s": round(float(c["sweep_s"]), 1), "load_avg_before_after": np.round(c["load"], 2).tolist(),
                     "force_z_max_N": float(c["forces"][-1, 1, 2]), **compare(ref, c),
                     **(json.loads(str(c["record"])) if "record" in c else {})})
    return {"size": size, "steps": steps, "backend": str(ref["backend"]), "rows": rows}


def write(rec: dict, command: str) -> None:
    rec = {**rec, "command": command, "date": datetime.date.today().isoformat(), "cpus": os.cpu_count()}
    OUT.mkdir(exist_ok=True)
    stem = OUT / f"bench_tolerance_{rec['size']}"
    stem.with_suffix(".json").write_text(json.dumps(rec, indent=1) + "\n")
    lines = [f"# Newton tolerance on the {rec['size']} leg ({rec['rows'][0]['nodes']:,} nodes, backend "
             f"{rec['backend']}, {rec['steps']} steps)", "", f"`{command}`", "",
             "| Newton residual tol | energy tol | Newton its per step | total | Krylov its | sweep s | max ΔF / max F | "
             "max Δu / max u | max Δσ / max σ | F_z(z_max) at α = 0.95 (N) |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rec["rows"]:
        tol = f"{r['newton_residual_tol']:g}" + (" (reference)" if r["reference"] else "") + (" (default)" if r["default"] else "")
        lines.append(f"| {tol} | {r['newton_energy_tol']:g} | {', '.join(map(str, r['newton_iterations_per_step'][1:]))} | "
                     f"{r['newton_iterations_total']} | {r['krylov_iterations_total'] or '—'} | {r['sweep_s']:.0f} | "
                     f"{r['force_rel']:.1e} | {r['u_rel']:.1e} | "
                     f"{r['stress_rel']:.1e} | {r['force_z_max_N']:.6f} |")
    lines += ["", "Differences are against the reference tolerance, largest over every load step; load average "
              "before and after each sweep in the JSON record."]
    stem.with_suffix(".md").write_text("\n".join(lines) + "\n")


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--size", default="5k", choices=[s for s in SIZES if s != "295k"])
    p.add_argument("--tols", type=parse_tol, nargs="+", default=["1e-3", "1e-2"],
                   help="looser Newton tolerances, RES (energy 100·RES²) or RES:ENERGY")
    p.add_argument("--steps", type=int, default=10)
    p.add_argument("--work", type=pathlib.Path, default=pathlib.Path("/tmp/pixmuscle-bench-tolerance"),
                   help="where each sweep's fields are kept, so an interrupted run resumes")
    args = p.parse_args(argv)
    rec = run(args.size, args.tols, args.steps, args.work)
    write(rec, command_line(argv))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

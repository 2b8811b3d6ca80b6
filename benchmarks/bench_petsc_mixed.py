"""Krylov iterations of ``petsc_mixed`` on the first Newton system of the 224-node clamped body of
tests/test_mixed_solver.py at the tissues' bulk moduli and at K × 10, with the default penalty
(β ∝ the largest modulus, so ∝ K) and with β fixed at 3·10⁴ N/cm³, with and without the region
solves, with the probed Schur diagonal (the default) and the scaled pressure mass (docs/petsc.md,
"Mixed displacement–pressure solve", Measured), and each solution's
relative error against SciPy's direct solve. A ``petsc_options`` entry for
``fieldsplit_u_pc_type`` replaces the region-solve composite, so with one both rows of a penalty
use that PC alone.

Writes ``benchmarks/results/bench_petsc_mixed_<ranks>rank.md`` (the table and the command).

Usage::

    .venv/bin/python benchmarks/bench_petsc_mixed.py                       # one rank
    mpiexec -n 2 .venv/bin/python benchmarks/bench_petsc_mixed.py          # two ranks (rank 0 prints)
    .venv/bin/python benchmarks/bench_petsc_mixed.py '{"fieldsplit_u_sub_0_pc_type": "hypre"}'   # petsc_options
"""

from __future__ import annotations

import json
import pathlib
import sys

import numpy as np
import scipy.sparse.linalg as spla

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests"), str(ROOT / "benchmarks")]  # the package, test helpers, _record

from _record import Run  # noqa: E402
from test_mixed_solver import CLAMPED, _system  # noqa: E402

from pixmuscle.errors import SolverError  # noqa: E402
from pixmuscle.mechanics.distributed import build_distributed_system  # noqa: E402
from pixmuscle.mechanics.linsolve import make_solver  # noqa: E402
from pixmuscle.parallel import import_petsc  # noqa: E402
from pixmuscle.verify.mechanics import _cfg  # noqa: E402


def first_newton(scale: float, beta: float | None, options: dict, region_solves: bool, schur: str) -> str:
    """'iterations (passes)' of the first Newton system (α = 0.6) to 10⁻⁸ of the condensed residual,
    or the failure; every bulk modulus × ``scale``; ``beta`` None: the default penalty number. Under
    ``mpiexec`` the system is the distributed one (each rank its part plus a halo)."""
    penalty = {} if beta is None else {"penalty": {"at": "nodes", "beta": beta}}
    materials = {"muscle": {"K": 5000.0 * scale}, "connective_tissue": {"K": 50000.0 * scale}}
    model, system = _system(held="patch", **materials, **penalty)
    state = system.evaluate(np.zeros((model.n_nodes, 3)), 0.5, 0.6)
    solved, solved_state = system, state
    if import_petsc().COMM_WORLD.getSize() > 1:
        cfg = _cfg(boundary_conditions=CLAMPED, volumetric={"method": "projected", "patch": [2, 2, 3], "held": "patch"},
                   materials=materials, **penalty)
        solved = build_distributed_system(model, cfg)[0]
        solved_state = solved.evaluate(np.zeros((solved.n_nodes, 3)), 0.5, 0.6)
    solver = make_solver("petsc_mixed", model.X, ijk=model.ijk, rtol=1e-10, maxiter=3000, petsc_options=options,
                         region_solves=region_solves, schur=schur)
    solver.prepare(solved, solved_state)
    try:
        x = solver.solve(solved_state.r.ravel(), rtol=1e-8)
    except SolverError as exc:
        return "failed: " + str(exc).split("split ")[-1].split(" (condensed")[0]
    x = solved.gather(x.reshape(-1, 3))  # the whole update on rank 0 (None on the others)
    if x is None:
        return ""
    r = state.r.ravel()
    ref = spla.spsolve(system.stiffness(state).tocsc(), r)
    err = np.linalg.norm(x.ravel() - ref) / np.linalg.norm(ref)
    passes = len(solver.info["passes"])
    return f"{solver.info['iterations']} ({passes} pass{'es' if passes > 1 else ''}, error {err:.0e})"


def main() -> None:
    from pixmuscle.mechanics.linsolve import petsc

    if not petsc.available():
        print(f"bench_petsc_mixed: skipped, {petsc.INSTALL_HINT}")
        return
    PETSc = import_petsc()

    options = json.loads(sys.argv[1]) if len(sys.argv) > 1 else {}
    rank, size = PETSc.COMM_WORLD.getRank(), PETSc.COMM_WORLD.getSize()
    command = " ".join(([f"mpiexec -n {size}"] if size > 1 else []) + [".venv/bin/python benchmarks/bench_petsc_mixed.py"]
                       + [f"'{a}'" for a in sys.argv[1:]])
    from pixmuscle.mechanics.linsolve import multigrid

    record = Run(defaults=not options, command=command)
    amg = "BoomerAMG" if multigrid.hypre_available() else "GAMG"
    lines = [f"# petsc_mixed: first Newton system, {size} rank(s), multigrid {amg}, petsc_options {options}", "",
             f"`{command}`", "",
             "| penalty | region solves | Schur diagonal | K × 1 | K × 10 |", "|---|---|---|---|---|"]
    for beta in (None, 3.0e4):
        for regions in (True, False):
            for schur in ("probed", "mass"):
                row = [first_newton(scale, beta, options, regions, schur) for scale in (1.0, 10.0)]
                name = "default (β ∝ K)" if beta is None else f"β = {beta:.0e} N/cm³"
                lines.append(f"| {name} | {'on' if regions else 'off'} | {schur} | {row[0]} | {row[1]} |")
                if rank == 0:
                    print(lines[-1], flush=True)
    if rank == 0 and not options:  # the default options' table is the record
        out = ROOT / "benchmarks" / "results" / f"bench_petsc_mixed_{size}rank.md"
        fields = record.fields()  # this rank's tree; the ranks run alike
        lines += ["", f"Made at commit {fields['commit'][:10]}, {fields['utc']}, load average "
                      f"{fields['load_average']['before'][0]} before, {fields['load_average']['after'][0]} after, "
                      f"peak memory {fields['peak_rss_GB']} GB per rank."]
        out.write_text("\n".join(lines) + "\n")
        out.with_suffix(".json").write_text(json.dumps({**fields, "table": lines}, indent=1))


if __name__ == "__main__":
    main()

"""Krylov iterations of ``petsc_mixed`` on the first Newton system of the 224-node clamped body of
tests/test_mixed_solver.py at the tissues' bulk moduli and at K × 10, with the default penalty
(β ∝ the largest modulus, so ∝ K) and with β fixed at 3·10⁴ N/cm³, with and without the region
solves (docs/petsc.md, "Mixed displacement–pressure solve", Measured), and each solution's
relative error against SciPy's direct solve. Seconds per row. A ``petsc_options`` entry for
``fieldsplit_u_pc_type`` replaces the region-solve composite, so with one both rows of a penalty
use that PC alone.

Usage::

    .venv/bin/python benchmarks/petsc_mixed_kmu.py                       # one rank
    mpiexec -n 2 .venv/bin/python benchmarks/petsc_mixed_kmu.py          # two ranks (rank 0 prints)
    .venv/bin/python benchmarks/petsc_mixed_kmu.py '{"fieldsplit_u_sub_0_pc_type": "hypre"}'   # petsc_options
"""

from __future__ import annotations

import json
import pathlib
import sys

import numpy as np
import scipy.sparse.linalg as spla

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]  # this checkout's package and test helpers

from test_mixed_solver import _system  # noqa: E402

from pixmuscle.errors import SolverError  # noqa: E402
from pixmuscle.mechanics.linsolve import make_solver  # noqa: E402


def first_newton(scale: float, beta: float | None, options: dict, region_solves: bool) -> str:
    """'iterations (passes)' of the first Newton system (α = 0.6) to 10⁻⁸ of the condensed residual,
    or the failure; every bulk modulus × ``scale``; ``beta`` None: the default penalty number."""
    penalty = {} if beta is None else {"penalty": {"at": "nodes", "beta": beta}}
    model, system = _system(held="patch", muscle={"K": 5000.0 * scale}, connective_tissue={"K": 50000.0 * scale},
                            **penalty)
    state = system.evaluate(np.zeros((model.n_nodes, 3)), 0.5, 0.6)
    r = state.r.ravel()
    solver = make_solver("petsc_mixed", model.X, ijk=model.ijk, rtol=1e-10, maxiter=3000, petsc_options=options,
                         region_solves=region_solves)
    solver.prepare(system, state)
    try:
        x = solver.solve(r, rtol=1e-8)
    except SolverError as exc:
        return "failed: " + str(exc).split("split ")[-1].split(" (condensed")[0]
    K = system.stiffness(state).tocsc()
    ref = spla.spsolve(K, r)
    err = np.linalg.norm(x - ref) / np.linalg.norm(ref)
    passes = len(solver.info["passes"])
    return f"{solver.info['iterations']} ({passes} pass{'es' if passes > 1 else ''}, error {err:.0e})"


def main() -> None:
    from petsc4py import PETSc

    options = json.loads(sys.argv[1]) if len(sys.argv) > 1 else {}
    rank, size = PETSc.COMM_WORLD.getRank(), PETSc.COMM_WORLD.getSize()
    if rank == 0:
        print(f"petsc_mixed, {size} rank(s), petsc_options {options}")
        print("| penalty | region solves | K × 1 | K × 10 |\n|---|---|---|---|")
    for beta in (None, 3.0e4):
        for regions in (True, False):
            row = [first_newton(scale, beta, options, regions) for scale in (1.0, 10.0)]
            if rank == 0:
                name = "default (β ∝ K)" if beta is None else f"β = {beta:.0e} N/cm³"
                print(f"| {name} | {'on' if regions else 'off'} | {row[0]} | {row[1]} |", flush=True)


if __name__ == "__main__":
    main()

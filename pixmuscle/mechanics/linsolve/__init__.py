"""Linear solvers for the Newton systems K Δd = r (3N unknowns, symmetric stiffness).

A backend has ``prepare(system, state)`` (set up for the tangent of a new Newton state) and
``solve(r, rtol=None)``; it keeps ``info`` (last iteration count, set-up and solve times). Each
backend is one module of this package that registers a factory under its name
(:func:`.base.register`); :func:`make_solver` builds one by name, so a new backend needs no change
anywhere else. Backends:

``direct``
    Sparse direct factorisation of the assembled tangent (:class:`DirectSolver`): MKL PARDISO
    LDLᵀ when the optional ``mkl`` package is installed (multi-threaded, symbolic analysis once
    per model), otherwise SciPy's SuperLU in a geometric nested-dissection order. Robust for
    the nearly incompressible tissues and any penalty number; optionally the factors are kept
    and precondition CG on the exact tangent (``reuse_factorization``). The SCNI tangent couples
    each node with ~300 others (±4 voxels), so the factors grow fast: with PARDISO ~2 s and
    0.3 GB at 5k nodes, ~50 s and 2.6 GB at 20k; beyond ~40k nodes they no longer fit 16 GB
    (docs/performance.md).
``cg_amg``
    Conjugate gradients on the matrix-free tangent (:mod:`.tangent`: always the exact current
    tangent, never assembled), preconditioned by smoothed-aggregation AMG (:mod:`pyamg`, six
    rigid-body modes as near-null space, first-level aggregates of 3×3×1 voxels) built from a
    filtered positive stand-in of the tangent (blocks within ±2 voxels,
    :meth:`~pixmuscle.mechanics.solve.MechanicalSystem.preconditioner_matrix`). The hierarchy is
    rebuilt once the iterations lost to its staleness have cost as much as a rebuild
    (:class:`KrylovAMGSolver`). Newton passes an
    adaptive tolerance (inexact Newton). Memory grows linearly with the model.
``mixed_amg`` (experimental)
    The projected-energy tangent in mixed displacement–pressure form, flexible GMRES with a
    block-triangular preconditioner (AMG on the displacement block without patch terms, diagonal
    Schur complement; :mod:`.mixed`). Meant for inf-sup stable patches (2 × 2 × 3); not yet
    robust in K/μ on the leg models (docs/performance.md).
``petsc``
    PETSc (optional petsc4py) on one or several MPI ranks (``mpiexec -n P pixmuscle solve …``):
    each rank assembles the tangent rows of a slab of slices into a distributed AIJ matrix,
    solved by KSP GMRES + GAMG with the rigid-body near-null space by default;
    ``solve.solver.petsc_options`` go to PETSc's options database (:mod:`.petsc`, docs/petsc.md).
``auto``
    ``direct`` up to ``auto_direct_max_dofs`` unknowns (15k nodes with PARDISO, 4k with
    SuperLU), ``cg_amg`` above.
"""

from __future__ import annotations

import numpy as np

from .base import BACKENDS, LinearSolver, pcg, register, rigid_body_modes
from .cg_amg import KrylovAMGSolver, voxel_aggregates
from .direct import DirectSolver, nested_dissection
from .fgmres import fgmres
from .mixed import MixedBlockSolver
from .petsc import PETScSolver

__all__ = ["LinearSolver", "DirectSolver", "KrylovAMGSolver", "BACKENDS", "register", "make_solver", "pcg",
           "rigid_body_modes", "voxel_aggregates", "nested_dissection", "AUTO_DIRECT_MAX_DOFS", "PETScSolver",
           "MixedBlockSolver", "fgmres"]

# direct up to here: PARDISO + reuse is faster than cg_amg at 11.5k nodes (351 s against 626 s for the
# benchmark sweep) and slower at 21k (2,244 s against ~1,200 s extrapolated), docs/performance.md
AUTO_DIRECT_MAX_DOFS = {"pardiso": 45_000, "superlu": 12_000}


def make_solver(backend: str, X: np.ndarray, *, auto_direct_max_dofs: int | None = None, **options) -> LinearSolver:
    """Create a registered backend by name (``auto``, ``direct``, ``cg_amg``, …) for the nodes ``X`` (N, 3).

    ``options`` go to the backend's factory (:data:`BACKENDS`): ``ijk`` (grid indices of the
    nodes; the nested-dissection order of SuperLU, required by ``cg_amg``), ``width``
    (separator thickness per axis, cells), ``rtol``, ``maxiter``, ``reuse``, ``direct_engine``.
    ``auto`` takes ``direct`` up to ``auto_direct_max_dofs`` unknowns (default
    :data:`AUTO_DIRECT_MAX_DOFS` of the direct engine: beyond, the factors outgrow the memory)
    and ``cg_amg`` above.
    """
    from .. import pardiso

    if backend == "auto":
        if auto_direct_max_dofs is None:
            engine = options.get("direct_engine", "auto")
            engine = engine if engine != "auto" else ("pardiso" if pardiso.available() else "superlu")
            auto_direct_max_dofs = AUTO_DIRECT_MAX_DOFS.get(engine, 12_000)
        backend = "direct" if 3 * np.asarray(X).shape[0] <= auto_direct_max_dofs else "cg_amg"
    if backend not in BACKENDS:
        raise ValueError(f"unknown linear solver backend {backend!r}: expected auto or one of {', '.join(sorted(BACKENDS))}")
    return BACKENDS[backend](X, **options)

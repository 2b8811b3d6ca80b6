"""Linear solvers for the Newton systems K Δd = r (3N unknowns, symmetric stiffness).

A backend has ``prepare(system, state)`` (set up for the tangent of a new Newton state),
``solve(r, rtol=None)`` and ``statistics()`` (what the results keep); it keeps ``info`` (last
iteration count, set-up and solve times). Each backend is one module of this package that
registers its :class:`~.base.LinearSolver` class in :data:`BACKENDS` with its own options
dataclass (:mod:`.base`); the package imports its modules when it loads, the config section
``solve.solver: {backend: <name>, …options}`` is validated by that dataclass, and
:func:`make_solver` builds the backend, so a new backend needs no change anywhere else. Backends:

``direct``
    Sparse direct factorisation of the assembled tangent (:class:`DirectSolver`): MKL PARDISO
    LDLᵀ when the optional ``mkl`` package is installed (multi-threaded, symbolic analysis once
    per model), otherwise SciPy's SuperLU in a geometric nested-dissection order. Robust for
    the nearly incompressible tissues and any penalty number; optionally the factors are kept
    and precondition CG on the exact tangent (``reuse_factorization``); the two engines
    (:mod:`.factorization`) share one reuse policy (:class:`~.direct.ReusePolicy`). The SCNI tangent couples
    each node with ~300 others (±4 voxels), so the factors grow fast: with PARDISO ~2 s and
    0.3 GB at 5k nodes, ~50 s and 2.6 GB at 20k; beyond ~40k nodes they no longer fit 16 GB
    (docs/performance.md).
``cg_amg``
    Conjugate gradients on the matrix-free tangent (:mod:`.tangent`: always the exact current
    tangent, never assembled), preconditioned by algebraic multigrid (:mod:`.multigrid`: hypre
    BoomerAMG through petsc4py where installed, else pyamg smoothed aggregation; option ``amg``)
    built from a filtered positive stand-in of the tangent (blocks within ±2 voxels,
    :meth:`~pixmuscle.mechanics.system.MechanicalSystem.preconditioner_matrix`). The hierarchy is
    rebuilt once the iterations lost to its staleness have cost as much as a rebuild
    (:class:`KrylovAMGSolver`). Newton passes an
    adaptive tolerance (inexact Newton). Memory grows linearly with the model. With the projected
    volumetric energy its iterations grow with K/μ (the condensed patch terms are K-scaled; on the
    5,460-node leg with 1 × 1 × 3 patches 142 and 476 CG iterations at K/μ ≈ 95 and 951), so
    ``auto`` takes ``mixed_amg`` instead, which runs this CG for the nodal energy.
``mixed_amg``
    The projected-energy tangent in mixed displacement–pressure form, GMRES with a
    block-triangular preconditioner (:mod:`.mixed`): an AMG V-cycle on the displacement block
    without patch terms, followed by exact solves on the node regions of the boundary conditions
    (end-face slabs, bone surfaces; :mod:`.subdomains`), and a diagonal Schur complement probed
    from that preconditioner. Robust in K/μ with inf-sup stable patches (the default 2 × 2 × 3):
    the first Newton system of the 5,460-node leg to 10⁻⁶ in 32, 32 and 33 iterations at K/μ ≈ 95,
    951 and 9,506, of the 21,169- and 73,753-node legs in 38 and 43 at 951 (docs/performance.md).
    Without a projected energy it runs CG as ``cg_amg``.
``petsc``
    PETSc (optional petsc4py) on one or several MPI ranks (``mpiexec -n P pixmuscle solve …``):
    each rank holds its part of the model plus a halo (:mod:`..distributed`) and assembles the
    tangent rows of its own nodes into a distributed AIJ matrix,
    solved by KSP GMRES + GAMG with the rigid-body near-null space by default;
    ``solve.solver.petsc_options`` go to PETSc's options database (:mod:`.petsc`, docs/petsc.md).
``petsc_mixed``
    The projected-energy tangent in the scaled mixed form of ``mixed_amg``, solved by PETSc on one
    or several MPI ranks (:mod:`.petsc_mixed`): FGMRES with a Schur field split (upper
    block-triangular; GAMG on the displacement block without patch terms followed by exact solves on
    the boundary-condition regions, Jacobi on the scaled pressure mass for the Schur complement),
    refined until the condensed residual meets the target. On the first Newton system of the
    224-node clamped test body 96 and 102 iterations at K × 1 and × 10 with the default penalty
    (GAMG alone: 371 and 1,853; condensed ``petsc``: no convergence; docs/petsc.md).
``auto`` (the default)
    ``direct`` up to ``direct_max_dofs`` unknowns (15k nodes with PARDISO, 4k with SuperLU),
    ``mixed_amg`` above (:mod:`.auto`).

A backend sees the system only through :class:`~.operator.SystemOperator` (apply the tangent, its
assembled or owned rows, the positive stand-in, the pressure space and patch divergence of the
mixed form, the stiff regions, the near-null space). The mixed method is written once
(:mod:`.mixed_method`) for ``mixed_amg`` and ``petsc_mixed``; when the AMG backends rebuild their
preconditioner is a component, :class:`~.rebuild.RebuildPolicy`.
"""

from __future__ import annotations

import numpy as np

from .base import BACKENDS, LinearSolver, SolverMemory, pcg, rigid_body_modes

BACKENDS.discover()

from .auto import AUTO_DIRECT_MAX_DOFS, AutoOptions  # noqa: E402
from .cg_amg import CGAMGOptions, KrylovAMGSolver, voxel_aggregates  # noqa: E402
from .direct import DirectOptions, DirectSolver, ReusePolicy  # noqa: E402
from .factorization import PardisoFactor, SuperLUFactor, nested_dissection  # noqa: E402
from .fgmres import fgmres  # noqa: E402
from .mixed import MixedAMGOptions, MixedBlockSolver  # noqa: E402
from .operator import SystemOperator  # noqa: E402
from .petsc import PETScOptions, PETScSolver  # noqa: E402
from .petsc_mixed import PETScMixedOptions, PETScMixedSolver  # noqa: E402
from .rebuild import RebuildPolicy  # noqa: E402

__all__ = ["LinearSolver", "SolverMemory", "DirectSolver", "KrylovAMGSolver", "BACKENDS", "make_solver", "pcg", "rigid_body_modes",
           "voxel_aggregates", "nested_dissection", "AUTO_DIRECT_MAX_DOFS", "PETScSolver", "MixedBlockSolver", "fgmres",
           "AutoOptions", "CGAMGOptions", "DirectOptions", "MixedAMGOptions", "PETScOptions", "ReusePolicy",
           "PETScMixedOptions", "PETScMixedSolver",
           "PardisoFactor", "SuperLUFactor", "RebuildPolicy", "SystemOperator"]


def make_solver(backend, X: np.ndarray, *, ijk: np.ndarray | None = None, width=(4, 4, 4), **options) -> LinearSolver:
    """Create a backend for the nodes ``X`` (N, 3), cm.

    Parameters
    ----------
    backend : str or options dataclass
        A registered name (``auto``, ``direct``, ``cg_amg``, …) with its ``options`` as keywords,
        or a backend's options instance (the parsed ``solve.solver`` section).
    X : (N, 3) float
    ijk : (N, 3) int, optional
        Voxel indices of the nodes (the nested-dissection order of SuperLU; required by the
        iterative backends).
    width : (3,) int
        Coupling reach of the stiffness per axis, cells (separator thickness of the nested dissection).
    **options
        Options of the named backend (its dataclass's fields, e.g. ``rtol``, ``engine``).

    Raises
    ------
    InputError
        Unknown backend or option (the message names it and lists the choices).
    """
    if isinstance(backend, str):
        backend = BACKENDS.parse({BACKENDS.key: backend, **options}, "solver")
    elif options:
        raise TypeError("make_solver: options are given either as keywords with a name or as an options dataclass")
    return BACKENDS.entry_of(backend).obj.from_options(backend, X, ijk=ijk, width=width)

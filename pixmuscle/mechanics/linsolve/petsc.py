"""Backend ``petsc``: the Newton systems solved by PETSc (petsc4py), on one or several MPI ranks.

The nodes are cut into slabs of voxel slices (:func:`slab_partition`), one slab per rank; each
rank assembles the tangent rows of its own nodes (:meth:`.operator.SystemOperator.owned_rows`: its
nodes plus a halo of one support radius) into a distributed PETSc AIJ matrix (block size 3), so no rank holds
the whole tangent. The system is solved with a PETSc Krylov method, by default
GMRES (the tangent of activated muscle is symmetric but
indefinite) preconditioned by PETSc's smoothed-aggregation multigrid (GAMG) with the six rigid-body
modes of the node coordinates as near-null space. ``solve.solver.petsc_options`` go to PETSc's
options database (``{ksp_type: minres, pc_type: hypre}`` etc.; any ``-ksp_*``/``-pc_*`` option
without the dash). Right-hand sides and solutions are full vectors on every rank (the Newton
iteration, the material evaluation and the model arrays are replicated on every rank).

petsc4py is optional: ``make venv`` installs it on Debian/Ubuntu as root (README, docs/petsc.md).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import field

import numpy as np

from ...errors import SolverError
from ...parallel import INSTALL_HINT, import_petsc
from .base import BACKENDS, Iterative, LinearSolver

#: PETSc options used unless ``petsc_options`` sets them
# GMRES: the tangent of activated muscle is indefinite (CG stops on negative curvature, PETSc reason -10);
# preconditioned on the right, so that it stops on the true residual Newton asks for (on the left it stops on
# the preconditioned one: 2.4e-7 of the true residual where 1e-8 was asked, on the test body)
DEFAULT_OPTIONS = {"ksp_type": "gmres", "ksp_pc_side": "right", "ksp_gmres_restart": 200, "pc_type": "gamg", "pc_gamg_type": "agg", "pc_gamg_agg_nsmooths": 1,
                   "pc_gamg_threshold": 0.01, "mg_levels_ksp_type": "chebyshev", "mg_levels_pc_type": "jacobi"}

_PREFIX = "pixmuscle_"


def set_options(prefix: str, defaults: dict, options: dict | None) -> dict:
    """Write ``options`` over ``defaults`` (names without the dash) into PETSc's options database
    under ``prefix``, replacing whatever was set under it before (another solver of this process);
    returns the merged mapping. ``true`` (or an empty value) sets a bare flag; whole floats are
    written as integers."""
    PETSc = import_petsc()

    merged = {**defaults, **(options or {})}
    db = PETSc.Options()
    for key in db.getAll():  # forget what an earlier solver of this process set under the prefix
        if key.startswith(prefix):
            db.delValue(key)
    for key, value in merged.items():
        key = str(key).lstrip("-")
        # true is a bare flag: PETSc reads "-ksp_monitor true" as a viewer named "true" and fails
        # and the config reads numbers as floats: "0.0" is no value for an integer option
        if isinstance(value, float) and value.is_integer():
            value = int(value)
        text = "" if value is None or value is True else "false" if value is False else str(value)
        db.setValue(prefix + key, text)
    return merged


def available() -> bool:
    """True when petsc4py imports."""
    try:
        import petsc4py  # noqa: F401
    except ImportError:
        return False
    return True


def slab_partition(ijk: np.ndarray, parts: int) -> tuple[np.ndarray, np.ndarray]:
    """Cut the nodes into ``parts`` slabs of whole voxel slices with about equal node counts.

    Parameters
    ----------
    ijk : (N, 3) int
        Voxel indices; the slices are the third index.
    parts : int

    Returns
    -------
    order : (N,) int
        Nodes by slice (stable): slab r is ``order[bounds[r]:bounds[r + 1]]``.
    bounds : (parts + 1,) int
    """
    k = np.asarray(ijk)[:, 2]
    order = np.argsort(k, kind="stable")
    ks = k[order]
    n = order.size
    cuts = np.searchsorted(ks, ks[np.minimum((np.arange(1, parts) * n) // parts, n - 1)], side="left")
    bounds = np.concatenate([[0], cuts, [n]]).astype(np.int64)
    return order, np.maximum.accumulate(bounds)


@dataclasses.dataclass(frozen=True)
class PETScOptions(Iterative):
    """Options of ``solve.solver: {backend: petsc, …}``."""

    petsc_options: dict[str, str | float | bool] = field(default_factory=dict, metadata={"doc": "options for PETSc's options database, names without the dash (default ksp_type: gmres, pc_type: gamg; e.g. {ksp_type: minres, pc_type: hypre, ksp_monitor: true})"})

    def __post_init__(self):
        if not available():
            raise ValueError(f"backend: petsc: {INSTALL_HINT}")


@BACKENDS.register("petsc", options=PETScOptions)
class PETScSolver(LinearSolver):
    """PETSc KSP on the distributed assembled tangent (see the module docstring).

    Parameters
    ----------
    X : (N, 3) float
        Node coordinates, cm (rigid-body near-null space).
    ijk : (N, 3) int
        Voxel indices (slab partition).
    rtol : float
        Relative residual when the caller gives none.
    maxiter : int
    options : dict, optional
        PETSc options (names without the leading dash), over :data:`DEFAULT_OPTIONS`.
    """

    name = "petsc"

    def __init__(self, X, ijk, rtol: float = 1e-10, maxiter: int = 2000, options: dict | None = None):
        super().__init__()
        PETSc = import_petsc()

        self.PETSc = PETSc
        self.comm = PETSc.COMM_WORLD
        self.rank, self.size = self.comm.getRank(), self.comm.getSize()
        self.X = np.asarray(X, float)
        self.order, self.bounds = slab_partition(ijk, self.size)
        self.owned = self.order[self.bounds[self.rank]:self.bounds[self.rank + 1]]
        dof = (3 * self.order[:, None] + np.arange(3)).ravel()
        self.dof = dof  # PETSc global index p ↔ model dof dof[p]
        self.pos = np.empty_like(dof)
        self.pos[dof] = np.arange(dof.size)
        self.lo, self.hi = 3 * int(self.bounds[self.rank]), 3 * int(self.bounds[self.rank + 1])
        self.rtol, self.maxiter = rtol, maxiter
        self.options = set_options(_PREFIX, DEFAULT_OPTIONS, options)
        self._rows = None
        self._ksp = None
        self.info.update(krylov_iterations=0, preconditioner_builds=0, ranks=self.size,
                         owned_nodes=int(self.owned.size))

    @classmethod
    def from_options(cls, opts: PETScOptions, X, *, ijk=None, width=(4, 4, 4)) -> PETScSolver:
        if ijk is None:
            raise ValueError("petsc needs the voxel indices ijk of the nodes")
        return cls(X, ijk, rtol=opts.rtol, maxiter=opts.maxiter, options=dict(opts.petsc_options))

    def prepare(self, system, state):
        PETSc = self.PETSc
        t0 = time.perf_counter()
        if self._rows is None:
            self._rows = system.owned_rows(self.owned)
            self.info["halo_cells"] = int(self._rows.cells.size - self.owned.size)
        K = self._rows.rows(state)
        A = self._displacement_matrix(K)
        if self._ksp is None:
            self._ksp = PETSc.KSP().create(comm=self.comm)
            self._ksp.setOptionsPrefix(_PREFIX)
            self._ksp.setOperators(A)
            self._ksp.setFromOptions()
            self._b, self._x = A.createVecs()
            self._all, self._xall = PETSc.Scatter.toAll(self._x)
        else:
            self._ksp.setOperators(A)
        self._A = A
        self.info["preconditioner_builds"] += 1
        self.info["setup_s"] = time.perf_counter() - t0
        self.info["nnz_local"] = int(K.nnz)

    def _displacement_matrix(self, K):
        """The owned rows ``K`` (CSR, 3n × 3N, model dof columns) as a distributed AIJ matrix (block
        size 3, PETSc's dof order) with the rigid-body modes of the nodes as near-null space."""
        PETSc = self.PETSc
        K = K.copy()
        K.indices = self.pos[K.indices].astype(PETSc.IntType)
        K.has_sorted_indices = False
        K.sort_indices()
        n_loc, n = self.hi - self.lo, self.dof.size
        A = PETSc.Mat().createAIJ(size=((n_loc, n), (n_loc, n)), bsize=3, comm=self.comm,
                                  csr=(K.indptr.astype(PETSc.IntType), K.indices, K.data))
        A.setOption(PETSc.Mat.Option.SYMMETRIC, True)
        A.assemble()
        coords = PETSc.Vec().createMPI((n_loc, n), bsize=3, comm=self.comm)
        coords.setArray(self.X[self.owned].ravel())
        A.setNearNullSpace(PETSc.NullSpace().createRigidBody(coords))
        return A

    def solve(self, r, rtol=None):
        t0 = time.perf_counter()
        rtol = self.rtol if rtol is None else max(float(rtol), 1e-14)
        b = np.asarray(r, float).ravel()[self.dof[self.lo:self.hi]]
        self._b.setArray(b)
        self._ksp.setTolerances(rtol=rtol, atol=0.0, max_it=self.maxiter)
        self._ksp.solve(self._b, self._x)
        its = int(self._ksp.getIterationNumber())
        reason = int(self._ksp.getConvergedReason())
        self._all.scatter(self._x, self._xall, addv=False, mode=self.PETSc.ScatterMode.FORWARD)
        x = np.empty(self.dof.size)
        x[self.dof] = self._xall.getArray()
        self.info["iterations"] = its
        self.info["krylov_iterations"] += its
        self.info["solve_s"] = time.perf_counter() - t0
        if reason < 0:
            raise SolverError(f"petsc: KSP {self.options.get('ksp_type')} diverged (PETSc reason {reason}) after {its} "
                              f"iterations (relative residual target {rtol:.1e}); try solver.petsc_options "
                              "{pc_type: hypre} or {ksp_gmres_restart: 500}, or check the boundary conditions")
        return x.reshape(np.shape(r))

    def statistics(self) -> dict:
        """Name, ``preconditioner_builds``, ``krylov_iterations`` (all solves) and ``ranks`` (MPI processes)."""
        return super().statistics() | {"preconditioner_builds": self.info["preconditioner_builds"],
                                       "krylov_iterations": self.info["krylov_iterations"], "ranks": self.size}

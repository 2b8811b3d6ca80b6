"""Backend ``petsc``: the Newton systems solved by PETSc (petsc4py), on one or several MPI ranks.

Under ``mpiexec -n P`` the system is distributed (:mod:`..distributed`): each rank holds its own
nodes (a recursive coordinate bisection of the voxel grid) plus a halo and assembles the tangent
rows of its own nodes (:meth:`.operator.SystemOperator.owned_rows` of its held system) into a
distributed PETSc AIJ matrix (block size 3), so no rank holds the whole tangent. The system is
solved with a PETSc Krylov method, by default GMRES (the tangent of activated muscle is symmetric
but indefinite) preconditioned by PETSc's smoothed-aggregation multigrid (GAMG) with the six
rigid-body modes of the node coordinates as near-null space. ``solve.solver.petsc_options`` go to
PETSc's options database (``{ksp_type: minres, pc_type: hypre}`` etc.; any ``-ksp_*``/``-pc_*``
option without the dash). Right-hand sides and solutions are the rank's own rows. Without
``mpiexec`` the serial system is used as a distributed system of one rank.
petsc4py is optional: ``make venv`` installs it on Debian/Ubuntu as root (README, docs/petsc.md).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import field

import numpy as np

from ...errors import SolverError
from ...parallel import INSTALL_HINT, import_petsc, set_options
from .base import BACKENDS, Iterative, LinearSolver

#: PETSc options used unless ``petsc_options`` sets them
# GMRES: the tangent of activated muscle is indefinite (CG stops on negative curvature, PETSc reason -10);
# preconditioned on the right, so that it stops on the true residual Newton asks for (on the left it stops on
# the preconditioned one: 2.4e-7 of the true residual where 1e-8 was asked, on the test body)
DEFAULT_OPTIONS = {"ksp_type": "gmres", "ksp_pc_side": "right", "ksp_gmres_restart": 200, "pc_type": "gamg", "pc_gamg_type": "agg", "pc_gamg_agg_nsmooths": 1,
                   "pc_gamg_threshold": 0.01, "mg_levels_ksp_type": "chebyshev", "mg_levels_pc_type": "jacobi"}

_PREFIX = "pixmuscle_"


def available() -> bool:
    """True when petsc4py imports."""
    try:
        import petsc4py  # noqa: F401
    except ImportError:
        return False
    return True


@dataclasses.dataclass(frozen=True)
class PETScOptions(Iterative):
    """Options of ``solve.solver: {backend: petsc, …}``."""

    petsc_options: dict[str, str | float | bool] = field(default_factory=dict, metadata={"doc": "options for PETSc's options database, names without the dash (default ksp_type: gmres, pc_type: gamg; e.g. {ksp_type: minres, pc_type: hypre, ksp_monitor: true})"})

    def __post_init__(self):
        if not available():
            raise ValueError(f"backend: petsc: {INSTALL_HINT}")


def distributed(system, state=None, X=None, ijk=None, made=None):
    """``system`` (and ``state``) as a :class:`..distributed.DistributedSystem` (and its state): a
    serial system with nodes at ``X`` (N, 3) cm and voxel indices ``ijk`` becomes one of a single
    rank (only without ``mpiexec``), or ``made`` when that is already the one of this system."""
    from ..distributed import DistributedState, DistributedSystem

    if isinstance(system, DistributedSystem):
        return system, state
    PETSc = import_petsc()
    if PETSc.COMM_WORLD.getSize() > 1:
        raise SolverError("under mpiexec the PETSc backends solve the distributed system "
                          "(pixmuscle.mechanics.distributed.build_distributed_system), not a whole one")
    ds = made if made is not None and made.held is system else DistributedSystem.single(system, X, ijk)
    if state is None or isinstance(state, DistributedState):
        return ds, state
    vol = None
    if getattr(state, "vol", None) is not None:
        from ..distributed.system import OwnedVolumetric

        vol = OwnedVolumetric(state.vol.pressure)
    return ds, DistributedState(d=state.d, t=state.t, alpha=state.alpha, r=state.r, force_scale=state.force_scale,
                                held=state, vol=vol, pressure=getattr(state, "pressure", None))


@BACKENDS.register("petsc", options=PETScOptions)
class PETScSolver(LinearSolver):
    """PETSc KSP on the distributed assembled tangent (see the module docstring).

    Parameters
    ----------
    X : (N, 3) float
        Node coordinates, cm, of a serial system (a distributed one's layout has its ranks' own).
    ijk : (N, 3) int
        Voxel indices, as ``X``.
    rtol : float
        Relative residual when the caller gives none.
    maxiter : int
    options : dict, optional
        PETSc options (names without the leading dash), over :data:`DEFAULT_OPTIONS`.
    """

    name = "petsc"

    def __init__(self, X=None, ijk=None, rtol: float = 1e-10, maxiter: int = 2000, options: dict | None = None):
        super().__init__()
        PETSc = import_petsc()
        self.PETSc = PETSc
        self.comm = PETSc.COMM_WORLD
        self.rank, self.size = self.comm.getRank(), self.comm.getSize()
        self.rtol, self.maxiter = rtol, maxiter
        self.options = set_options(_PREFIX, DEFAULT_OPTIONS, options)
        self._nodes = (X, ijk) if self.size == 1 else (None, None)  # where a serial system's nodes are
        self._single = None
        self.layout = None
        self._rows = None
        self._ksp = None
        self.info.update(krylov_iterations=0, preconditioner_builds=0, ranks=self.size, owned_nodes=0)

    @classmethod
    def from_options(cls, opts: PETScOptions, X, *, ijk=None, width=(4, 4, 4)) -> PETScSolver:
        return cls(X, ijk, rtol=opts.rtol, maxiter=opts.maxiter, options=dict(opts.petsc_options))

    def _attach(self, system, state):
        """The distributed system and state, and this rank's layout (kept)."""
        system, state = distributed(system, state, *self._nodes, made=self._single)
        if system.layout.size == 1:
            self._single = system  # a serial system's one-rank view, made once
        self.layout = system.layout
        self.info["owned_nodes"] = int(self.layout.n_own)
        return system, state

    def prepare(self, system, state):
        PETSc = self.PETSc
        t0 = time.perf_counter()
        system, state = self._attach(system, state)
        if self._rows is None:
            self._rows = system.held.owned_rows(self.layout.own)
            self.info["halo_cells"] = int(self._rows.cells.size - self.layout.n_own)
        K = self._rows.rows(state.held)
        A = self._displacement_matrix(K, system)
        if self._ksp is None:
            self._ksp = PETSc.KSP().create(comm=self.comm)
            self._ksp.setOptionsPrefix(_PREFIX)
            self._ksp.setOperators(A)
            self._ksp.setFromOptions()
            self._b, self._x = A.createVecs()
        else:
            self._ksp.setOperators(A)
        self._A = A
        self.info["preconditioner_builds"] += 1
        self.info["setup_s"] = time.perf_counter() - t0
        self.info["nnz_local"] = int(K.nnz)

    def _columns(self, cols: np.ndarray) -> np.ndarray:
        """Held dof columns → global PETSc dof columns."""
        cols = np.asarray(cols, np.int64)
        return 3 * self.layout.petsc[cols // 3] + cols % 3

    def _displacement_matrix(self, K, system):
        """The owned rows ``K`` (CSR, 3n × 3n_held, held dof columns) as a distributed AIJ matrix
        (block size 3, PETSc's dof order) with the rigid-body modes of the nodes as near-null space."""
        PETSc = self.PETSc
        K = K.copy()
        K.indices = self._columns(K.indices).astype(PETSc.IntType)
        K.has_sorted_indices = False
        K.sort_indices()
        lay = self.layout
        n_loc, n = 3 * lay.n_own, 3 * lay.n_global
        A = PETSc.Mat().createAIJ(size=((n_loc, n), (n_loc, n)), bsize=3, comm=self.comm,
                                  csr=(K.indptr.astype(PETSc.IntType), K.indices, K.data))
        A.setOption(PETSc.Mat.Option.SYMMETRIC, True)
        A.assemble()
        coords = PETSc.Vec().createMPI((n_loc, n), bsize=3, comm=self.comm)
        coords.setArray(lay.X[lay.own].ravel())
        A.setNearNullSpace(PETSc.NullSpace().createRigidBody(coords))
        return A

    def solve(self, r, rtol=None):
        t0 = time.perf_counter()
        rtol = self.rtol if rtol is None else max(float(rtol), 1e-14)
        self._b.setArray(np.asarray(r, float).ravel())
        self._ksp.setTolerances(rtol=rtol, atol=0.0, max_it=self.maxiter)
        self._ksp.solve(self._b, self._x)
        its = int(self._ksp.getIterationNumber())
        reason = int(self._ksp.getConvergedReason())
        x = self._x.getArray().copy()
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

r"""Algebraic multigrid V-cycles for the iterative backends: pyamg smoothed aggregation, or hypre
BoomerAMG through petsc4py.

Both take the filtered stand-in of the tangent (BSR, 3 × 3 node blocks; in ``mixed_amg`` after
:func:`drop_weak_blocks`) and return an object whose ``@`` applies one V-cycle. ``cg_amg`` and
``mixed_amg`` choose with their option ``amg``: ``auto`` takes BoomerAMG where petsc4py (with
hypre) imports and pyamg otherwise. pyamg is pure pip and always there; BoomerAMG is compiled and
sets up and cycles faster (docs/performance.md).

BoomerAMG settings (hypre's names, :data:`BOOMERAMG_OPTIONS`):

* HMIS coarsening with strength threshold 0.25 (hypre's default), each displacement component on
  its own (the "unknown" approach: ``nodal_coarsen`` 0 with three functions per node, so only
  couplings between like components count and each component gets its own coarse grids);
* extended+i interpolation with at most 4 entries per row;
* one forward hybrid Gauss–Seidel/Jacobi sweep before the coarse-grid correction and one backward
  sweep after it, Gaussian elimination on the coarsest level, so that the cycle is a fixed
  symmetric operator (CG in ``cg_amg`` needs that);
* no rigid-body (vector) interpolation.

hypre runs on one core per process. ``amg_processes`` > 1 (option of ``cg_amg``, ``mixed_amg``
and ``auto``) sets up and cycles each hierarchy on this process and spawned MPI workers
(:mod:`.amg_processes`). ``amg_processes: auto`` (the default, :func:`auto_processes`) takes two
processes from :data:`AUTO_PROCESSES_NODES` nodes on where the run has two cores of its own, else
one.

References
----------
P. Vaněk, J. Mandel, M. Brezina, "Algebraic multigrid by smoothed aggregation for second and
fourth order elliptic problems", Computing 56, 179–196, 1996.
V. E. Henson, U. M. Yang, "BoomerAMG: a parallel algebraic multigrid solver and preconditioner",
Appl. Numer. Math. 41, 155–177, 2002.
H. De Sterck, U. M. Yang, J. J. Heys, "Reducing complexity in parallel algebraic multigrid
preconditioners", SIAM J. Matrix Anal. Appl. 27(4), 1019–1039, 2006 (HMIS coarsening).
"""

from __future__ import annotations

import functools
import os
import sys

import numpy as np
import scipy.sparse as sp

from ...errors import InputError
from ...parallel import INSTALL_HINT, import_petsc, launched_size
from ..amg_worker import hypre_matrix, hypre_pc
from ..threaded import thread_count
from .amg_processes import SpreadBoomerAMG, group
from .amg_processes import available as amg_processes_available

#: choices of the ``amg`` option of the iterative backends
AMG_CHOICES = ("auto", "hypre", "pyamg")

#: ``amg_processes: auto`` spreads BoomerAMG over :data:`AUTO_PROCESSES` processes from this many nodes on
#: (below it the second process costs more than it gains)
AUTO_PROCESSES_NODES = 50_000
#: processes ``amg_processes: auto`` takes at most
AUTO_PROCESSES = 2

_PREFIX = "pixmuscleamg_"
#: PETSc options of the BoomerAMG cycle (names without the dash); ``petsc_mixed`` uses them too
BOOMERAMG_OPTIONS = {"pc_hypre_boomeramg_nodal_coarsen": 0, "pc_hypre_boomeramg_strong_threshold": 0.25,
              "pc_hypre_boomeramg_coarsen_type": "HMIS", "pc_hypre_boomeramg_interp_type": "ext+i",
              "pc_hypre_boomeramg_P_max": 4, "pc_hypre_boomeramg_relax_type_down": "SOR/Jacobi",
              "pc_hypre_boomeramg_relax_type_up": "backward-SOR/Jacobi",
              "pc_hypre_boomeramg_relax_type_coarse": "Gaussian-elimination"}


@functools.cache
def hypre_available() -> bool:
    """True when petsc4py imports and its PETSc has hypre."""
    try:
        PETSc = import_petsc()
    except ImportError:
        return False
    pc = PETSc.PC().create(comm=PETSc.COMM_SELF)
    try:
        pc.setType("hypre")
    except PETSc.Error:  # pragma: no cover - a PETSc built without hypre
        return False
    finally:
        pc.destroy()
    return True


def resolve(amg: str, processes: int = 1) -> str:
    """The multigrid ``amg`` stands for here: ``auto`` is ``hypre`` where it is installed, else ``pyamg``;
    ``processes`` > 1 (:mod:`.amg_processes`) needs hypre, mpi4py and as many cores."""
    cores = len(os.sched_getaffinity(0))
    if processes > cores:
        raise InputError(f"solve.solver.amg_processes: {processes} processes, but this run has {cores} cores: "
                         f"each BoomerAMG process needs a core of its own (at most {cores} here)")
    if processes > 1:
        if amg not in ("hypre", "auto"):
            raise InputError(f"solve.solver.amg_processes: {processes} processes need amg: hypre (or auto), not {amg}")
        if not hypre_available():
            raise InputError(f"solve.solver.amg_processes: {processes} processes need hypre; {INSTALL_HINT}")
        if not amg_processes_available():
            raise InputError(f"solve.solver.amg_processes: {processes} processes need mpi4py, which is not installed: "
                             "`make venv` installs it with the PETSc backend, or `pip install mpi4py`")
    if amg == "auto":
        amg = "hypre" if hypre_available() else "pyamg"
    if amg == "hypre" and not hypre_available():
        raise InputError(f"solve.solver.amg: hypre needs petsc4py built against a PETSc with hypre; {INSTALL_HINT}")
    return amg


def auto_processes(amg: str, n_nodes: int) -> int:
    """Processes of ``amg_processes: auto`` for a model of ``n_nodes`` nodes and the multigrid ``amg``
    (after :func:`resolve`): :data:`AUTO_PROCESSES` from :data:`AUTO_PROCESSES_NODES` nodes on, as
    many as the run's threads allow (numba's threads over the processes of an MPI launch, which a
    Dask cohort caps at its share of the cores, and the cores the process may run on), one under
    ``mpiexec`` with more than one process, in a Dask worker without ``NUMBA_NUM_THREADS``, with
    pyamg or without mpi4py."""
    if amg != "hypre" or n_nodes < AUTO_PROCESSES_NODES or launched_size() > 1 or not amg_processes_available():
        return 1
    if _in_dask_worker() and "NUMBA_NUM_THREADS" not in os.environ:  # a scheduler's worker that was given no thread count
        return 1
    return max(1, min(AUTO_PROCESSES, thread_count(), len(os.sched_getaffinity(0))))


def _in_dask_worker() -> bool:
    """True inside a task of a Dask worker (only where ``distributed`` is imported already)."""
    distributed = sys.modules.get("distributed")
    if distributed is None:
        return False
    try:
        distributed.get_worker()
    except ValueError:
        return False
    return True


class SmoothedAggregation:
    """pyamg smoothed aggregation: first-level aggregates given, six rigid-body modes as near-null
    space, Jacobi-smoothed prolongators, symmetric block Gauss–Seidel, V-cycle.

    Parameters
    ----------
    K : sparse (3N × 3N), or a function of no arguments that returns it
        Symmetric positive definite stand-in of the tangent, N/cm.
    B : (3N, 6) float
        Rigid-body modes.
    aggregates : CSR (N × N_agg)
        First-level aggregation (:func:`.cg_amg.voxel_aggregates`).
    theta : float
        Strength-of-connection threshold of the coarser levels.
    """

    def __init__(self, K, B: np.ndarray, aggregates: sp.csr_matrix, theta: float = 0.1):
        import pyamg

        if callable(K):
            K = K()
        self.nnz_per_row = K.nnz / K.shape[0]
        ml = pyamg.smoothed_aggregation_solver(
            K, B=B, symmetry="symmetric", strength=("symmetric", {"theta": theta}),
            aggregate=[("predefined", {"AggOp": aggregates})] + ["standard"] * 10,
            smooth=("jacobi", {"omega": 4.0 / 3.0, "degree": 1}), max_coarse=300, keep=False,
        )
        self.levels = len(ml.levels)
        self.operator_complexity = float(ml.operator_complexity())
        self._M = ml.aspreconditioner(cycle="V")
        self.shape = K.shape

    def __matmul__(self, v: np.ndarray) -> np.ndarray:
        return self._M @ v


class BoomerAMG:
    """hypre BoomerAMG through petsc4py, one V-cycle per application (settings: module docstring).

    Parameters
    ----------
    K : sparse (3N × 3N), or a function of no arguments that returns it
        Symmetric positive definite stand-in of the tangent, N/cm, 3 × 3 blocks per node (BSR
        with 3 × 3 blocks, or CSR). Given as a function, the stand-in is made here and released as
        soon as PETSc holds its copy, before hypre's set-up: the set-up's peak memory then does
        not hold it.
    """

    def __init__(self, K):
        PETSc = import_petsc()

        if callable(K):
            K = K()
        idx = PETSc.IntType
        self.nnz_per_row = K.nnz / K.shape[0]
        self.shape = K.shape
        if sp.isspmatrix_bsr(K) and K.blocksize == (3, 3):  # blocks straight into PETSc: no CSR copy
            nb = K.shape[0] // 3
            self._A = hypre_matrix(PETSc.COMM_SELF, K.indptr, K.indices, K.data, nb, nb)
        else:
            A = sp.csr_matrix(K)
            A.sort_indices()
            self._A = PETSc.Mat().createAIJ(size=A.shape, bsize=3, comm=PETSc.COMM_SELF,
                                            csr=(A.indptr.astype(idx, copy=False), A.indices.astype(idx, copy=False),
                                                 A.data))
            del A
        del K
        # in place into hypre's own matrix type, which BoomerAMG then uses without a second copy (one
        # copy of the stand-in less); the conversion forgets the 3 × 3 node
        # blocks, which tell hypre the three functions per node
        self._A, self._pc, self._x, self._y = hypre_pc(self._A, _PREFIX, BOOMERAMG_OPTIONS)
        self.levels = None  # hypre does not report them through petsc4py
        self.operator_complexity = None

    def __matmul__(self, v: np.ndarray) -> np.ndarray:
        self._x.setArray(np.ascontiguousarray(v, dtype=float))
        self._pc.apply(self._x, self._y)
        return self._y.getArray().copy()

    def __del__(self):
        for obj in ("_pc", "_A", "_x", "_y"):
            o = getattr(self, obj, None)
            if o is not None:
                o.destroy()


def drop_weak_blocks(K: sp.bsr_matrix, tol: float) -> sp.bsr_matrix:
    """The stand-in without its weak couplings: every off-diagonal 3 × 3 block with
    ‖K_ab‖_F < tol √(‖K_aa‖_F ‖K_bb‖_F) is dropped, the diagonal blocks are kept.

    Most blocks of the ±2-voxel stand-in are weak, and the V-cycle's cost is its fine level,
    proportional to the non-zeros; but a stand-in with blocks left out need not be positive
    definite, which makes the multigrid a worse preconditioner. So ``mixed_amg`` keeps every block
    by default (``drop_tol`` 0). The dropped blocks are not added to the diagonal.

    Parameters
    ----------
    K : BSR (3N × 3N), 3 × 3 blocks
    tol : float
        Relative strength below which a block is dropped; 0 keeps every block.

    Returns
    -------
    BSR (3N × 3N)

    References
    ----------
    A. Bienz, R. D. Falgout, W. Gropp, L. N. Olson, J. B. Schroder, "Reducing parallel communication
    in algebraic multigrid through sparsification", SIAM J. Sci. Comput. 38(5), S332–S357, 2016
    (dropping weak entries of AMG operators).
    """
    if tol <= 0.0:
        return K
    n = K.shape[0] // 3
    rows = np.repeat(np.arange(n, dtype=np.int32), np.diff(K.indptr))
    norm = np.sqrt(np.einsum("kij,kij->k", K.data, K.data))
    diagonal = rows == K.indices
    dnorm = np.zeros(n)
    dnorm[rows[diagonal]] = norm[diagonal]
    keep = diagonal | (norm >= tol * np.sqrt(dnorm[rows] * dnorm[K.indices]))
    indptr = np.concatenate([[0], np.cumsum(np.bincount(rows[keep], minlength=n))])
    return sp.bsr_matrix((K.data[keep], K.indices[keep], indptr), shape=K.shape)


def v_cycle(amg: str, K, B: np.ndarray, aggregates: sp.csr_matrix, theta: float, processes: int = 1):
    """One V-cycle of the multigrid ``amg`` (``hypre`` or ``pyamg``, after :func:`resolve`) built on ``K``
    (a matrix, or a function that makes it: :class:`BoomerAMG`); its ``nnz_per_row`` is ``K``'s.
    ``processes`` > 1: BoomerAMG on this process and ``processes`` − 1 spawned MPI workers
    (:mod:`.amg_processes`; ``K`` in BSR with 3 × 3 blocks)."""
    if amg == "hypre":
        if processes > 1:
            return SpreadBoomerAMG(K, group(processes), _PREFIX, BOOMERAMG_OPTIONS)
        return BoomerAMG(K)
    return SmoothedAggregation(K, B, aggregates, theta)

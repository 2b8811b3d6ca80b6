r"""Algebraic multigrid V-cycles for the iterative backends: pyamg smoothed aggregation, or hypre
BoomerAMG through petsc4py.

Both take the filtered stand-in of the tangent (BSR, 3 × 3 blocks, ~300 non-zeros per row; in
``mixed_amg`` ~140 after :func:`drop_weak_blocks`) and return an object whose ``@`` applies one
V-cycle. ``cg_amg`` and ``mixed_amg`` choose with their
option ``amg``: ``auto`` takes BoomerAMG where petsc4py (with hypre) imports and pyamg otherwise.

Why two. pyamg is pure pip and always there; its set-up (smoothed prolongators, Galerkin
products in Python-driven sparse algebra) dominates a preconditioner build on large models, and
its symmetric block Gauss–Seidel cycle is most of the cost of a Krylov iteration. BoomerAMG
(classical coarsening on the nodal strength matrix, extended+i interpolation, compiled C) sets up
the same 21,169-node stand-in in 1.1 s against ~15 s and cycles in 0.19 s against 0.33 s (with the
region solves), for 50 FGMRES iterations against 47 on the first Newton system of the leg
(docs/performance.md, "Multigrid: BoomerAMG and pyamg").

BoomerAMG settings (hypre's names): HMIS coarsening with strength threshold 0.25, each
displacement component on its own (the "unknown" approach, ``nodal_coarsen`` 0 with three
functions per node: only couplings between like components count, and each component gets its
own coarse grids). Coarsening the three components of a node together (``nodal_coarsen`` 6, the
whole 3 × 3 block as strength) is the textbook choice for elasticity, but it leaves the slow
modes of the leg on pixels finer in-plane than the slice spacing, axial displacement fields
smooth in-plane that vary along the slices (likely because the components' couplings across
slices differ: the fibres stiffen the axial one), to the Krylov method: on the first Newton system
of the leg at 0.078 cm pixels, 43 FGMRES iterations against 54 at 21k nodes and 69 against 80 at
74k, at the same set-up and cycle time (docs/performance.md, "Multigrid: BoomerAMG and pyamg");
with nodal coarsening, strength thresholds 0.25 and 0.7, P_max 6, the node ordering and the
Frobenius-norm block strength (``nodal_coarsen`` 1, 117) gave nothing better. Per component, the
threshold 0.25 (hypre's default) holds the cycle's quality better than 0.5 as the model grows:
GMRES on the displacement block alone (V-cycle and region solves, the first Newton system's
force residual, 10⁻⁶) takes 31 iterations on the 74k leg with 0.25 against 35 with 0.5, and
FGMRES on the mixed system 41 against 43 there and 46 against 49 on the 295k model (5k: 32
either way), with a cheaper cycle (0.20 against 0.24 s at 74k on one process); 0.1 and 0.35
gave 42 and 41 at 74k (docs/performance.md, "The strength threshold"). Extended+i interpolation with
at most 4 entries per row; one forward hybrid Gauss–Seidel/Jacobi sweep before the coarse-grid
correction and one backward sweep after it, Gaussian elimination on the coarsest level, so the
cycle is a fixed symmetric operator (CG in ``cg_amg`` needs that). Operator complexity is ~1.1,
so the fine level's sweeps are the cycle's cost: a symmetric sweep on both sides (hypre's
symmetric-SOR/Jacobi) costs twice as much per cycle for the same or a few per cent fewer
iterations — on the first Newton system of the leg 39 and 50 FGMRES iterations at 5k and 21k
nodes against 39 and 54 with the one-way sweeps, but 0.050 and 0.200 s against 0.039 and 0.136 s
per cycle with the region solves, 15 % less solve time and 24 % less set-up at 21k
(docs/performance.md, "Multigrid: BoomerAMG and pyamg"; these two comparisons with nodal
coarsening). Rigid-body interpolation (hypre's vector interpolation with the nodes' rotations,
on nodal coarsening) gave more iterations on the leg's fine pixels, 56 and 85 at 21k and 74k
nodes against 43 and 69, and a slower set-up and cycle, so it is off. With the earlier stand-in
the V-cycle did on the mixed system what an exact inverse of its stand-in does (34 against 33
FGMRES iterations at 5k, 44 against 46 at 21k on 0.078-cm pixels), so no setting of the cycle
moved the count (docs/performance.md, "Krylov iterations and the model size"): what was left was
the stand-in's difference from the tangent. A stand-in whose cut rows keep their first moments
(:func:`..assembly.local_rows`) took the 46 to 39 (docs/performance.md, "The stand-in keeps first
moments"); on that stand-in the cycle is what falls behind as the model grows, and the threshold
0.25 took the 39 to 35.

hypre runs on one core per process. ``amg_processes`` > 1 (option of ``cg_amg``, ``mixed_amg``
and ``auto``) sets up and cycles each hierarchy on this process and spawned MPI workers
(:mod:`.amg_processes`): the 74k leg's whole sweep takes 342 s on two processes against 402 s
on one (274 s against 304 s on a faster machine), the refined 295k model's 47 min against 67 min;
at 21k nodes two do not pay
(docs/performance.md, "BoomerAMG on two processes"). Hence ``amg_processes: auto`` (the
default, :func:`auto_processes`): two processes from :data:`AUTO_PROCESSES_NODES` nodes on where
the run has two cores of its own, else one.

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
from ...parallel import import_petsc, launched_size
from ..threaded import thread_count
from .amg_processes import SpreadBoomerAMG, group, hypre_matrix, hypre_pc
from .amg_processes import available as amg_processes_available
from .petsc import INSTALL_HINT

#: choices of the ``amg`` option of the iterative backends
AMG_CHOICES = ("auto", "hypre", "pyamg")

#: ``amg_processes: auto`` spreads BoomerAMG over :data:`AUTO_PROCESSES` processes from this many nodes on:
#: the measured whole sweeps at 74k and 295k nodes gain 10-15 % and 30 %, the one at 21k loses 5 %
AUTO_PROCESSES_NODES = 50_000
#: processes ``amg_processes: auto`` takes at most (the number measured; more cores may pay more)
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
        not hold it (0.6 GB on the 74k leg).
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
        # copy of the stand-in less: 0.23 GB at 21k nodes); the conversion forgets the 3 × 3 node
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

    Most blocks of the ±2-voxel stand-in are weak: on the 74k leg ``tol`` = 0.005 keeps 144 of
    335 non-zeros per row, and the V-cycle's cost is its fine level, proportional to the non-zeros.
    But a stand-in with blocks left out is not positive definite: on the 21k leg at 0.078-cm pixels
    ``tol`` = 0.005 gives it 35 negative pivots, and FGMRES then needs 53 instead of 36 iterations
    on the first Newton system (docs/performance.md, "The stand-in is positive definite"). So
    ``mixed_amg`` keeps every block by default (``drop_tol`` 0). Adding the dropped blocks to the
    diagonal costs far more iterations (161 against 39 at 21k with ``tol`` = 0.01).

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

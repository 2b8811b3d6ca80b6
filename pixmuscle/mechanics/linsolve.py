"""Linear solvers for the Newton systems K Δd = r (3N unknowns, symmetric stiffness).

A backend has ``prepare(system, state)`` (set up for the tangent of a new Newton state) and
``solve(r, rtol=None)``; it keeps ``info`` (last iteration count, set-up and solve times).
Backends:

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
``auto``
    ``direct`` up to ``auto_direct_max_dofs`` unknowns (15k nodes with PARDISO, 4k with
    SuperLU), ``cg_amg`` above.
"""

from __future__ import annotations

import logging
import time

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from ..errors import SolverError

_LOG = logging.getLogger(__name__)


class LinearSolver:
    """Interface of a linear-solver backend."""

    name = "base"

    def __init__(self):
        self.info = {"iterations": 0, "setup_s": 0.0, "solve_s": 0.0}

    def prepare(self, system, state) -> None:
        """Set up for the tangent of ``state`` (default: factorise the assembled stiffness)."""
        self.factorize(system.stiffness(state))

    def factorize(self, K: sp.spmatrix) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def solve(self, r: np.ndarray, rtol: float | None = None) -> np.ndarray:  # pragma: no cover - interface
        """Solve K x = r; ``rtol`` is the accuracy the caller needs (iterative backends)."""
        raise NotImplementedError


def nested_dissection(ijk: np.ndarray, width, leaf: int = 64) -> np.ndarray:
    """Geometric nested-dissection ordering of grid nodes (fill-reducing order for LU).

    The node set is split recursively at the median of its longest axis by a separator slab of
    ``width[k]`` grid layers (the coupling reach of the stiffness along axis k: 2·⌊a/h + ½⌋ cells);
    each part is ordered before its separator. Loops run over sub-domains (about N / ``leaf``),
    not over nodes.

    Parameters
    ----------
    ijk : (N, 3) int
        Grid indices of the nodes.
    width : (3,) int
        Separator thickness per axis, in cells.
    leaf : int
        Sub-domains of at most this many nodes are not split further.

    Returns
    -------
    (N,) int64
        Node order (a permutation of 0..N-1).
    """
    ijk = np.asarray(ijk, np.int64)
    width = np.broadcast_to(np.asarray(width, np.int64), (3,))
    done = []
    # iterative post-order: a task is either a node set to split or a separator to emit
    tasks = [("split", np.arange(ijk.shape[0]))]
    while tasks:
        kind, idx = tasks.pop()
        if kind == "emit" or idx.size <= leaf:
            done.append(idx)
            continue
        c = ijk[idx]
        lo, hi = c.min(axis=0), c.max(axis=0)
        ax = int(np.argmax((hi - lo) / np.maximum(width, 1)))
        w = int(width[ax])
        if hi[ax] - lo[ax] + 1 < 2 * w + 2:
            done.append(idx)
            continue
        m = int(np.median(c[:, ax]))
        m = min(max(m, lo[ax] + 1), hi[ax] - w)
        ca = c[:, ax]
        left, sep, right = idx[ca < m], idx[(ca >= m) & (ca < m + w)], idx[ca >= m + w]
        # processed in reverse: left first, then right, then the separator
        tasks.append(("emit", sep))
        tasks.append(("split", right))
        tasks.append(("split", left))
    return np.concatenate(done) if done else np.zeros(0, np.int64)


class DirectSolver(LinearSolver):
    """Sparse direct factorisation of the assembled tangent, with optional factorisation reuse.

    Engines (``engine``):

    ``pardiso``
        MKL PARDISO LDLᵀ (:mod:`.pardiso`; needs the optional ``mkl`` package): supernodal,
        multi-threaded, METIS ordering; the symbolic analysis is done once per sparsity pattern
        (fixed for a model) and every tangent costs only the numerical factorisation. Symmetric
        indefinite pivoting, so tangents with negative eigenvalues are handled.
    ``superlu``
        SciPy's SuperLU in a geometric nested-dissection order of the voxel grid (``ijk``;
        :func:`nested_dissection`) with symmetric (diagonal) pivoting, which keeps that order and
        is several times faster than COLAMD for the wide SCNI stiffness (2.8× on a 2.8k-node
        slab). If a solve is still inaccurate after refinement (small pivots of an indefinite
        tangent), the matrix is refactorised with threshold pivoting in the same order, and as a
        last resort with COLAMD and partial pivoting (the level then stays for later matrices).
    ``auto``
        PARDISO when MKL is installed, otherwise SuperLU.

    Every solve gets up to three steps of iterative refinement against the assembled matrix.

    Reuse (``reuse=True``): the factors of an earlier tangent K₀ are kept and later systems
    K x = r are solved by conjugate gradients on the matrix-free exact tangent
    (:meth:`~pixmuscle.mechanics.solve.MechanicalSystem.tangent_operator`, no assembly)
    preconditioned with K₀⁻¹ (GMRES if K₀ was indefinite), to the tolerance the caller asks
    (inexact Newton). The tangent is refactorised at the next Newton iteration when a solve
    needed more than ``krylov_maxiter``/2 iterations or more than a quarter of the time of the
    last assembly + factorisation, and at once when it fails to converge in ``krylov_maxiter``.
    """

    name = "direct"

    def __init__(self, reuse: bool = True, rtol: float = 1e-10, krylov_maxiter: int = 40, ijk=None, width=(4, 4, 4),
                 engine: str = "auto"):
        super().__init__()
        from . import pardiso

        if engine == "auto":
            engine = "pardiso" if pardiso.available() else "superlu"
        if engine == "pardiso" and not pardiso.available():
            raise ValueError("solver.direct_engine: pardiso needs MKL (pip install 'pixmuscle[fast]'); "
                             "use direct_engine: superlu or auto")
        if engine not in ("pardiso", "superlu"):
            raise ValueError(f"unknown direct engine {engine!r}: expected auto, pardiso or superlu")
        self.engine = engine
        self.reuse = reuse
        self.rtol = rtol
        self.krylov_maxiter = krylov_maxiter
        self.perm = None
        if ijk is not None and engine == "superlu":
            order = nested_dissection(ijk, width)
            self.perm = (3 * order[:, None] + np.arange(3)).ravel()
        # SuperLU pivoting level: 0 ND order, diagonal pivots; 1 ND order, threshold pivoting; 2 COLAMD, partial pivoting
        self._level = 0 if self.perm is not None else 2
        self._lu = None
        self._pattern = None
        self._ldlt = None
        self._K = None
        self._op = None
        self._system = self._state = None
        self._definite = False
        self._fresh = False
        self._stale = False
        self._factor_cost = 0.0  # seconds of the last assembly + factorisation
        self._assembly_s = 0.0
        self.info.update(factorizations=0, krylov_iterations=0, engine=engine, analysis_s=0.0)

    # -- factorisation -------------------------------------------------------------------
    def _refactor(self):
        t0 = time.perf_counter()
        if self.engine == "pardiso":
            self._refactor_pardiso()
        else:
            self._refactor_superlu()
        self._fresh = True
        self._stale = False
        self._factor_cost = self._assembly_s + time.perf_counter() - t0
        self.info["factorizations"] += 1
        self.info["setup_s"] += time.perf_counter() - t0

    def _refactor_pardiso(self):
        from .pardiso import PardisoError, PardisoLDLT, SymmetricPattern

        K = self._K
        if K.format != "bsr" or K.blocksize != (3, 3):
            K = sp.bsr_matrix(K, blocksize=(3, 3))
        if self._pattern is None or not self._pattern.matches(K):
            if self._ldlt is not None:
                self._ldlt.free()
            self._pattern = SymmetricPattern(K)
            self._ldlt = PardisoLDLT(self._pattern)
            self.info["analysis_s"] += self._ldlt.info["analysis_s"]
        try:
            self._ldlt.factorize(self._pattern.values(K))
        except PardisoError as exc:
            raise SolverError(f"direct solver (PARDISO): {exc}; check the boundary conditions") from None
        neg = self._ldlt.info["inertia"][1]
        self._definite = neg == 0
        self.info.update(factor_nnz=self._ldlt.info["factor_nnz"], factor_gflop=self._ldlt.info["factor_gflop"],
                         negative_pivots=neg)

    def _refactor_superlu(self):
        K = sp.csr_matrix(self._K)
        try:
            if self._level >= 2:
                self._lu = spla.splu(K.tocsc(), permc_spec="COLAMD")
                self._p = None
            else:
                p = self.perm
                self._lu = spla.splu(K[p][:, p].tocsc(), permc_spec="NATURAL",
                                     diag_pivot_thresh=0.0 if self._level == 0 else 0.1, options={"SymmetricMode": True})
                self._p = p
        except RuntimeError as exc:  # exactly singular
            if self._level < 2:
                self._level += 1
                return self._refactor_superlu()
            raise SolverError(f"direct solver: stiffness matrix is singular ({exc}); check the boundary conditions") from None
        self._definite = False  # SuperLU gives no inertia: Krylov reuse uses GMRES

    def _factor_solve(self, r):
        if self.engine == "pardiso":
            return self._ldlt.solve(r)
        if self._p is None:
            return self._lu.solve(r)
        x = np.empty_like(r)
        x[self._p] = self._lu.solve(r[self._p])
        return x

    def _accurate_solve(self, r):
        """Factor solve with up to 3 steps of iterative refinement; escalate (SuperLU pivoting, or GMRES) if inaccurate."""
        rn = np.linalg.norm(r)
        while True:
            x = self._factor_solve(r)
            self.info["iterations"] = 1
            for _ in range(3):
                if not np.all(np.isfinite(x)):
                    break
                res = r - self._K @ x
                if np.linalg.norm(res) <= 1e-10 * rn:
                    break
                x = x + self._factor_solve(res)
                self.info["iterations"] += 1
            ok = np.all(np.isfinite(x)) and np.linalg.norm(r - self._K @ x) <= 1e-8 * rn
            if ok:
                return x
            if self.engine == "pardiso":  # perturbed pivots of a nearly singular tangent: Krylov on top
                return self._krylov(self._K, r, 1e-10, x0=x if np.all(np.isfinite(x)) else None, gmres=True)[0]
            if self._level >= 2:
                return x
            self._level += 1
            _LOG.debug("LU was inaccurate (small pivots of an indefinite tangent); refactorising with pivoting level %d",
                       self._level)
            self._refactor()

    def _krylov(self, A, r, rtol, x0=None, gmres=False):
        """Solve A x = r preconditioned by the kept factors; returns (x, iterations, converged)."""
        M = spla.LinearOperator(A.shape, matvec=lambda v: self._factor_solve(np.asarray(v, float).ravel()))
        if not gmres:
            x, its, status = pcg(A, r, M, rtol, self.krylov_maxiter, x0=x0)
            return x, its, status == "converged"
        count = [0]

        def cb(_):
            count[0] += 1

        x, flag = spla.gmres(A, r, x0=x0, rtol=rtol, atol=0.0, restart=self.krylov_maxiter, maxiter=1, M=M,
                             callback=cb, callback_type="pr_norm")
        return x, count[0], flag == 0 and bool(np.all(np.isfinite(x)))

    # -- interface -----------------------------------------------------------------------
    def prepare(self, system, state):
        """Factorise the tangent of ``state``, or (reuse) keep the factors and take the matrix-free tangent."""
        self.info["setup_s"] = 0.0
        if self.reuse and self._factor_ready() and not self._stale:
            self._system, self._state = system, state
            self._K = None
            self._op = system.tangent_operator(state)
            self._fresh = False
            return
        self._system = self._state = None
        t0 = time.perf_counter()
        K = system.stiffness(state)
        self.factorize(K, assembly_s=time.perf_counter() - t0)

    def _factor_ready(self):
        return self._ldlt is not None if self.engine == "pardiso" else self._lu is not None

    def factorize(self, K, assembly_s: float = 0.0):
        """Take the assembled tangent ``K`` (assembled in ``assembly_s`` seconds); factorise it unless
        ``reuse`` keeps earlier factors."""
        self._assembly_s = assembly_s
        self._K = K
        self._op = K
        self.info["setup_s"] = 0.0
        if not self._factor_ready() or not self.reuse or self._stale:
            self._refactor()
        else:
            self._fresh = False

    def solve(self, r, rtol=None):
        t0 = time.perf_counter()
        setup0 = self.info["setup_s"]
        r = np.asarray(r, float)
        x = None
        if not self._fresh:
            target = self.rtol if rtol is None else max(float(rtol), 1e-14)
            x, its, ok = self._krylov(self._op, r, target, gmres=not self._definite)
            self.info["iterations"] = its
            self.info["krylov_iterations"] += its
            if not ok:
                x = None
                self._assembly_s = 0.0
                if self._K is None:  # matrix-free reuse: assemble the current tangent now
                    t1 = time.perf_counter()
                    self._K = self._system.stiffness(self._state)
                    self._assembly_s = time.perf_counter() - t1
                    self.info["setup_s"] += self._assembly_s
                self._refactor()
            elif its > self.krylov_maxiter // 2 or time.perf_counter() - t0 > 0.25 * self._factor_cost:
                self._stale = True  # refactorise at the next Newton iteration
        if x is None:
            x = self._accurate_solve(r)
        self.info["solve_s"] = time.perf_counter() - t0 - (self.info["setup_s"] - setup0)
        if not np.all(np.isfinite(x)):
            raise SolverError("direct solver returned non-finite values (singular stiffness)")
        return x


def rigid_body_modes(X: np.ndarray) -> np.ndarray:
    """Six rigid-body modes (3 translations, 3 rotations about the centroid) as (3N, 6) columns."""
    X = np.asarray(X, float)
    Xc = X - X.mean(axis=0)
    n = X.shape[0]
    B = np.zeros((n, 3, 6))
    for k in range(3):
        B[:, k, k] = 1.0
    x, y, z = Xc.T
    B[:, 0, 3], B[:, 1, 3] = -y, x
    B[:, 1, 4], B[:, 2, 4] = -z, y
    B[:, 0, 5], B[:, 2, 5] = z, -x
    return B.reshape(3 * n, 6)


def pcg(A, b: np.ndarray, M, rtol: float, maxiter: int, x0: np.ndarray | None = None):
    """Preconditioned conjugate gradients for a symmetric positive definite operator.

    Parameters
    ----------
    A, M : objects with ``@`` (operator and preconditioner)
    b : (n,) float
    rtol : float
        Stop when ‖b − A x‖ ≤ rtol ‖b‖ (recursively updated residual).
    maxiter : int
    x0 : (n,) float, optional

    Returns
    -------
    x : (n,) float
    iterations : int
    status : str
        ``"converged"``, ``"maxiter"`` or ``"breakdown"`` (pᵀ A p ≤ 0: A is not positive definite).
    """
    x = np.zeros_like(b) if x0 is None else np.array(x0, float)
    r = b - A @ x if x0 is not None else b.copy()
    bn = float(np.linalg.norm(b))
    if bn == 0.0:
        return x, 0, "converged"
    if float(np.linalg.norm(r)) <= rtol * bn:
        return x, 0, "converged"
    z = M @ r
    p = z.copy()
    rz = float(r @ z)
    for it in range(1, maxiter + 1):
        q = A @ p
        pq = float(p @ q)
        if not pq > 0.0:
            return x, it, "breakdown"
        a = rz / pq
        x += a * p
        r -= a * q
        if float(np.linalg.norm(r)) <= rtol * bn:
            return x, it, "converged"
        z = M @ r
        rz_new = float(r @ z)
        p *= rz_new / rz
        p += z
        rz = rz_new
    return x, maxiter, "maxiter"


def voxel_aggregates(ijk: np.ndarray, block=(3, 3, 1)) -> sp.csr_matrix:
    """Geometric aggregation of grid nodes into boxes of ``block`` voxels (N × N_agg, 0/1 CSR).

    Used as pyamg's first-level aggregation: on the wide SCNI stiffness (~300 block neighbours
    per node) pyamg's standard aggregation makes very few, very large aggregates and a weak
    two-level method; voxel boxes give a proper hierarchy and halve the iteration count
    (docs/linsolve-research.md §2(b)).
    """
    key = np.asarray(ijk, np.int64) // np.asarray(block, np.int64)
    _, agg = np.unique(key, axis=0, return_inverse=True)
    agg = agg.ravel()
    n = agg.shape[0]
    return sp.csr_matrix((np.ones(n), (np.arange(n), agg)), shape=(n, int(agg.max()) + 1))


class KrylovAMGSolver(LinearSolver):
    """CG on the matrix-free tangent, preconditioned by smoothed-aggregation AMG (pyamg).

    Parameters
    ----------
    X : (N, 3) float
        Node coordinates, cm (rigid-body modes).
    ijk : (N, 3) int
        Voxel indices (geometric aggregates and the filtered preconditioner matrix).
    rtol : float
        Relative residual when the caller gives none.
    maxiter : int
        CG iterations per solve.
    reach : int
        Blocks of node pairs at most this many voxels apart enter the preconditioner matrix.
    aggregate : (3,) int
        First-level aggregates, voxels per axis.
    theta : float
        Strength-of-connection threshold.

    Notes
    -----
    Rebuild policy (the "ski-rental" rule): the first solve after a build sets the reference rate,
    CG iterations per decade of residual reduction. Every later solve that needs more iterations
    than that rate predicts adds its extra iterations, times the measured seconds per
    iteration, to an account; when the account exceeds the time of the last build (filtered
    matrix + AMG set-up), the hierarchy is rebuilt from the next Newton iteration's tangent. So
    the time lost to a stale preconditioner never exceeds the time a rebuild costs, whatever
    the model size; on small models (cheap builds) it rebuilds often, on large ones (a build
    costs 45–60 s at 74k nodes) it keeps the hierarchy as long as it pays. The matrix-free
    operator is always the exact tangent, so a stale preconditioner costs iterations, never
    accuracy.
    """

    name = "cg_amg"

    def __init__(self, X, ijk, rtol: float = 1e-8, maxiter: int = 2000, reach: int = 2, aggregate=(3, 3, 1),
                 theta: float = 0.1):
        super().__init__()
        self.B = rigid_body_modes(X)
        self.ijk = np.asarray(ijk)
        self.rtol = rtol
        self.maxiter = maxiter
        self.reach = reach
        self.aggregate = aggregate
        self.theta = theta
        self._M = None
        self._rate0 = None
        self._build_s = 0.0  # seconds of the last build
        self._excess_s = 0.0  # seconds of CG iterations beyond the reference rate since that build
        self._stale = True
        self._system = None
        self._state = None
        self.info.update(preconditioner_builds=0, krylov_iterations=0, levels=0, operator_complexity=0.0)

    def _build(self):
        import pyamg

        t0 = time.perf_counter()
        self._M = None  # release the old hierarchy before the new one is built (peak memory)
        Kp = self._system.preconditioner_matrix(self._state, self.reach)
        self.info["preconditioner_nnz_per_row"] = Kp.nnz / Kp.shape[0]
        ml = pyamg.smoothed_aggregation_solver(
            Kp, B=self.B, symmetry="symmetric", strength=("symmetric", {"theta": self.theta}),
            aggregate=[("predefined", {"AggOp": voxel_aggregates(self.ijk, self.aggregate)})] + ["standard"] * 10,
            smooth=("jacobi", {"omega": 4.0 / 3.0, "degree": 1}), max_coarse=300, keep=False,
        )
        del Kp
        self._M = ml.aspreconditioner(cycle="V")
        self.info["levels"] = len(ml.levels)
        self.info["operator_complexity"] = float(ml.operator_complexity())
        self.info["preconditioner_builds"] += 1
        self._build_s = time.perf_counter() - t0
        self.info["setup_s"] += self._build_s
        self._rate0 = None
        self._excess_s = 0.0
        self._stale = False
        self._fresh = True

    def prepare(self, system, state):
        self.info["setup_s"] = 0.0
        self._system, self._state = system, state
        self._A = system.tangent_operator(state)
        self._fresh = False
        if self._M is None or self._stale:
            self._build()

    def solve(self, r, rtol=None):
        t0 = time.perf_counter()
        setup0 = self.info["setup_s"]
        rtol = self.rtol if rtol is None else max(float(rtol), 1e-14)
        b = np.asarray(r, float)
        x, its, status = pcg(self._A, b, self._M, rtol, self.maxiter)
        total = its
        if status != "converged" and not self._fresh:
            _LOG.debug("CG %s after %d iterations with a stale preconditioner; rebuilding it", status, its)
            self._build()
            x, its, status = pcg(self._A, b, self._M, rtol, self.maxiter)
            total += its
        self.info["iterations"] = total
        self.info["krylov_iterations"] += total
        self.info["solve_s"] = time.perf_counter() - t0 - (self.info["setup_s"] - setup0)
        if status != "converged":
            raise SolverError(f"cg_amg: CG {status} after {its} iterations (relative residual target {rtol:.1e}); "
                              "check the boundary conditions (a free rigid-body motion makes K singular), or use "
                              "solver.backend: direct on small models")
        decades = max(np.log10(1.0 / rtol), 1.0)
        if self._rate0 is None:
            self._rate0 = max(its / decades, 1.0)
        elif its > 0:
            extra = its - self._rate0 * decades
            self._excess_s += max(extra, 0.0) * self.info["solve_s"] / its
            if self._excess_s > self._build_s:
                self._stale = True  # rebuilt at the next prepare(), from that state's tangent
        return x


# direct up to here: PARDISO + reuse is faster than cg_amg at 11.5k nodes (351 s against 626 s for the
# benchmark sweep) and slower at 21k (2,244 s against ~1,200 s extrapolated), docs/performance.md
AUTO_DIRECT_MAX_DOFS = {"pardiso": 45_000, "superlu": 12_000}


def make_solver(backend: str, X: np.ndarray, *, auto_direct_max_dofs: int | None = None, rtol: float = 1e-10,
                maxiter: int = 2000, reuse: bool = True, ijk=None, width=(4, 4, 4),
                direct_engine: str = "auto") -> LinearSolver:
    """Create a backend by name (``auto``, ``direct``, ``cg_amg``) for the nodes ``X`` (N, 3).

    ``ijk`` (grid indices of the nodes) enables the nested-dissection ordering of the direct solver
    and is required by ``cg_amg``; ``width`` is the separator thickness per axis (cells).
    ``auto`` takes ``direct`` up to ``auto_direct_max_dofs`` unknowns (default
    :data:`AUTO_DIRECT_MAX_DOFS` of the direct engine: beyond, the factors outgrow the memory).
    """
    from . import pardiso

    ndof = 3 * np.asarray(X).shape[0]
    if auto_direct_max_dofs is None:
        engine = direct_engine if direct_engine != "auto" else ("pardiso" if pardiso.available() else "superlu")
        auto_direct_max_dofs = AUTO_DIRECT_MAX_DOFS.get(engine, 12_000)
    if backend == "auto":
        backend = "direct" if ndof <= auto_direct_max_dofs else "cg_amg"
    if backend == "direct":
        return DirectSolver(reuse=reuse, rtol=rtol, ijk=ijk, width=width, engine=direct_engine)
    if backend == "cg_amg":
        if ijk is None:
            raise ValueError("cg_amg needs the voxel indices ijk of the nodes")
        return KrylovAMGSolver(X, ijk, rtol=rtol, maxiter=maxiter)
    raise ValueError(f"unknown linear solver backend {backend!r}: expected auto, direct or cg_amg")

"""Sparse factorisation engines of the ``direct`` backend: SciPy's SuperLU and MKL PARDISO.

An engine factorises an assembled tangent K (3N × 3N, symmetric, possibly indefinite) and solves
with the factors; :class:`~.direct.DirectSolver` decides when to factorise and how to refine. Each
engine has

``factorize(K)``   factorise (raises :class:`~pixmuscle.errors.SolverError` if K is singular); K
                   may be a function of no arguments that returns it, and is then let go before
                   the numerical factorisation where the engine can (PARDISO: it keeps the upper
                   triangle's values only)
``solve(r)``       x = K⁻¹ r with the factors, r and x (3N,)
``escalate()``     after an inaccurate solve: switch to a more robust pivoting for the next
                   factorisation and return True, or return False when there is none
``release()``      drop the numerical factors until the next ``factorize`` (an analysis of
                   the pattern is kept)
``definite``       True when the last K was positive definite (known from the factors' inertia)
``info``           what the engine measured (``factor_nnz``, ``analysis_s``, …)
"""

from __future__ import annotations

import logging

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from ...errors import SolverError

_LOG = logging.getLogger(__name__)

#: the engine ``pardiso`` asked for without MKL
PARDISO_MISSING = "engine: pardiso needs MKL (pip install 'pixmuscle[fast]'); use engine: superlu or auto"


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


class SuperLUFactor:
    """SciPy's SuperLU in a geometric nested-dissection order of the voxel grid.

    With ``ijk``, the unknowns are ordered by :func:`nested_dissection` and factorised with
    symmetric (diagonal) pivoting, which keeps that order and is several times faster than COLAMD
    for the wide SCNI stiffness (2.8× on a 2.8k-node slab). Pivoting levels, raised by
    :meth:`escalate` after an inaccurate solve (small pivots of an indefinite tangent) or at once
    when K is exactly singular in the current level, and kept for later matrices: 0, the
    nested-dissection order with diagonal pivots; 1, the same order with threshold pivoting; 2,
    COLAMD with partial pivoting (the only level without ``ijk``).

    Parameters
    ----------
    ijk : (N, 3) int, optional
        Grid indices of the nodes.
    width : (3,) int
        Separator thickness per axis of the nested dissection, cells.
    block : int
        Unknowns per node (3: the displacement components; 1: one component).
    """

    name = "superlu"

    def __init__(self, ijk=None, width=(4, 4, 4), block: int = 3):
        self.perm = None
        if ijk is not None:
            order = nested_dissection(ijk, width)
            self.perm = (block * order[:, None] + np.arange(block)).ravel()
        self.level = 0 if self.perm is not None else 2
        self.definite = False  # SuperLU gives no inertia: Krylov reuse uses GMRES
        self.info: dict = {}
        self._lu = None
        self._p = None

    def factorize(self, K) -> None:
        K = sp.csr_matrix(K() if callable(K) else K)
        try:
            if self.level >= 2:
                self._lu = spla.splu(K.tocsc(), permc_spec="COLAMD")
                self._p = None
            else:
                p = self.perm
                self._lu = spla.splu(K[p][:, p].tocsc(), permc_spec="NATURAL",
                                     diag_pivot_thresh=0.0 if self.level == 0 else 0.1, options={"SymmetricMode": True})
                self._p = p
        except RuntimeError as exc:  # exactly singular
            if self.level < 2:
                self.level += 1
                return self.factorize(K)
            raise SolverError(f"direct solver: stiffness matrix is singular ({exc}); check the boundary conditions") from None

    def release(self) -> None:
        self._lu = None

    def solve(self, r: np.ndarray) -> np.ndarray:
        if self._p is None:
            return self._lu.solve(r)
        x = np.empty_like(r)
        x[self._p] = self._lu.solve(r[self._p])
        return x

    def escalate(self) -> bool:
        if self.level >= 2:
            return False
        self.level += 1
        _LOG.debug("LU was inaccurate (small pivots of an indefinite tangent); refactorising with pivoting level %d",
                   self.level)
        return True


class PardisoFactor:
    """MKL PARDISO LDLᵀ (:mod:`pixmuscle.mechanics.pardiso`; needs the optional ``mkl`` package).

    Supernodal, multi-threaded, METIS ordering; the symbolic analysis is done once per sparsity
    pattern (fixed for a model) and every tangent costs only the numerical factorisation.
    Symmetric indefinite pivoting, so tangents with negative eigenvalues are handled; the inertia
    tells whether K is definite. Small pivots are perturbed, not escalated: an inaccurate solve
    is left to GMRES preconditioned by the factors. With ``single``, the factors are single
    precision and every solve is refined in double precision (:class:`~..pardiso.PardisoLDLT`).
    """

    name = "pardiso"

    def __init__(self, ijk=None, width=None, single: bool = False, block: int = 3):  # the ordering is PARDISO's own
        from .. import pardiso

        if not pardiso.available():
            raise ValueError(PARDISO_MISSING)
        self.single = bool(single)
        self.block = int(block)
        self.definite = False
        self.info: dict = {"analysis_s": 0.0}
        self._pattern = None
        self._ldlt = None
        self._owner = None  # the factor whose analysis this one shares (:meth:`sibling`), or None: its own
        self._which = 0  # this factor's matrix among those of the shared analysis
        self._siblings = 0

    def sibling(self) -> PardisoFactor:
        """A factor of another matrix with this one's sparsity pattern that shares its analysis
        (PARDISO's ``maxfct``: one analysis held for all of them). Made before the first
        :meth:`factorize`; this factor is factorised first, whenever the pattern may have changed."""
        if self._ldlt is not None or self._owner is not None:
            raise RuntimeError("siblings are made from an unshared factor before its first factorisation")
        self._siblings += 1
        other = PardisoFactor(single=self.single, block=self.block)
        other._owner, other._which = self, self._siblings
        return other

    def _handle(self):
        """(pattern, PardisoLDLT) that factorises and solves this factor's matrix."""
        owner = self if self._owner is None else self._owner
        return owner._pattern, owner._ldlt

    def factorize(self, K) -> None:
        from ..pardiso import PardisoError, PardisoLDLT, SymmetricPattern

        if callable(K):
            K = K()
        b = self.block
        if K.format != "bsr" or K.blocksize != (b, b):
            K = sp.bsr_matrix(K, blocksize=(b, b))
        pattern, ldlt = self._handle()
        if self._owner is not None and (pattern is None or not pattern.matches(K)):
            raise ValueError("a sibling PARDISO factor needs the sparsity pattern its owner was last factorised with")
        if self._owner is None and (pattern is None or not pattern.matches(K)):
            if ldlt is not None:
                ldlt.free()
            self._pattern = pattern = SymmetricPattern(K)
            self._ldlt = ldlt = PardisoLDLT(pattern, single=self.single, count=1 + self._siblings)
            self.info["analysis_s"] += ldlt.info["analysis_s"]
        values = pattern.values(K)
        del K  # the caller's function handed it over: only the values stay through the factorisation
        try:
            ldlt.factorize(values, which=self._which)
        except PardisoError as exc:
            raise SolverError(f"direct solver (PARDISO): {exc}; check the boundary conditions") from None
        neg = ldlt.info["inertia"][1]
        self.definite = neg == 0
        # memory_kB: what the (shared) PARDISO handle holds, its analysis and every factor of its matrices
        self.info.update(factor_nnz=ldlt.info["factor_nnz"], factor_gflop=ldlt.info["factor_gflop"],
                         negative_pivots=neg, memory_kB=ldlt.info["memory_kB"], peak_memory_kB=ldlt.info["peak_memory_kB"])

    def solve(self, r: np.ndarray) -> np.ndarray:
        return self._handle()[1].solve(r, which=self._which)

    def release(self) -> None:
        ldlt = self._handle()[1]
        if ldlt is not None:
            ldlt.release_factors(which=self._which)

    def escalate(self) -> bool:
        return False


class ComponentFactors:
    """Factors of the three displacement components' diagonal blocks of a 3×3-block matrix.

    K (3n × 3n, BSR with 3×3 node blocks) is approximated by blockdiag(K_xx, K_yy, K_zz), each
    n × n block (one component's rows and columns) factorised on its own by an engine made with
    ``block=1``. The factors of the three have the nodes' graph, not the 3×-wider graph of the
    coupled unknowns: about a third of the entries of K's factor (each block a ninth), in a
    third of the memory. This is not a solve of K: it is the stand-in of a preconditioner, exact
    where K is block-diagonal by component (a penalty on one displacement component, a scalar
    mass term) and leaving the couplings between components to whatever it is combined with.

    The three blocks have one sparsity pattern; an engine that can share one analysis among
    several matrices of a pattern (:meth:`PardisoFactor.sibling`) holds it once for the three.

    Parameters
    ----------
    engine : callable
        Makes one engine, ``engine(block=1)`` (:data:`ENGINES` with its keywords bound).
    """

    def __init__(self, engine):
        first = engine(block=1)
        share = getattr(first, "sibling", None)
        self.parts = [first] + [share() if share is not None else engine(block=1) for _ in range(2)]
        self.info: dict = {}

    @property
    def definite(self) -> bool:
        return all(f.definite for f in self.parts)

    def factorize(self, K) -> None:
        if callable(K):
            K = K()
        K = sp.bsr_matrix(K, blocksize=(3, 3))
        if not K.has_sorted_indices:  # the three blocks share K's index arrays: sorted once here, not by each
            K = K.sorted_indices()
        n = K.shape[0] // 3
        blocks = [sp.bsr_matrix((np.ascontiguousarray(K.data[:, j:j + 1, j:j + 1]), K.indices, K.indptr), shape=(n, n))
                  for j in range(3)]
        del K  # only the three diagonal blocks' values stay through the factorisations
        for j, f in enumerate(self.parts):
            B, blocks[j] = blocks[j], None
            f.factorize(B)
            del B
        infos = [f.info for f in self.parts]
        self.info = {k: sum(i.get(k, 0) for i in infos) for k in ("factor_nnz", "analysis_s", "negative_pivots")}
        # a shared analysis's handle reports the memory of all its matrices: counted once, after the last
        held = {id(f._handle()[1]) if hasattr(f, "_handle") else id(f): f.info.get("memory_kB", 0) for f in self.parts}
        self.info["memory_kB"] = sum(held.values())
        self.info["peak_memory_kB"] = max(i.get("peak_memory_kB", 0) for i in infos)

    def solve(self, r: np.ndarray) -> np.ndarray:
        r = np.asarray(r, float)
        x = np.empty_like(r)
        for j, f in enumerate(self.parts):
            x[j::3] = f.solve(np.ascontiguousarray(r[j::3]))
        return x

    def release(self) -> None:
        for f in self.parts:
            f.release()

    def escalate(self) -> bool:
        return any([f.escalate() for f in self.parts])


#: direct engines by name (``solve.solver.engine``)
ENGINES = {"pardiso": PardisoFactor, "superlu": SuperLUFactor}


def engine_name(engine: str) -> str:
    """The engine ``engine`` stands for: ``auto`` is PARDISO when MKL is installed, else SuperLU."""
    from .. import pardiso

    if engine != "auto":
        return engine
    return "pardiso" if pardiso.available() else "superlu"

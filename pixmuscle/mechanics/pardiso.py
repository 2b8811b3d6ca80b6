"""Sparse symmetric LDLᵀ factorisation with Intel MKL PARDISO (optional dependency ``mkl``).

PARDISO is a supernodal, multi-threaded direct solver with METIS ordering. Compared with
SciPy's SuperLU it factorises the SCNI tangent of the leg 8× faster at 5k nodes and makes 20k
nodes possible at all (docs/performance.md). It is reached through ``ctypes`` in MKL's single
dynamic library ``libmkl_rt``, installed by the PyPI package ``mkl`` (``pip install
pixmuscle[fast]``); nothing is compiled. The binding is ours and small because the phases must
be separated: the symbolic analysis (ordering, elimination tree) depends only on the sparsity
pattern, which is fixed for a model, and is done once; every new tangent then costs only the
numerical factorisation.

Matrix type −2 (real symmetric indefinite, Bunch–Kaufman pivoting within supernodes and
perturbation of tiny pivots by 1e-8·‖A‖): a finite-strain tangent with active fibre stress may
have negative eigenvalues; the inertia (numbers of positive and negative pivots) is reported.
"""

from __future__ import annotations

import ctypes
import glob
import os
import sys

import numpy as np
import scipy.sparse as sp

_LIB = None


class PardisoUnavailable(ImportError):
    """MKL's runtime library (``libmkl_rt``) was not found."""


def _load():
    global _LIB
    if _LIB is not None:
        return _LIB
    names = [os.environ.get("PIXMUSCLE_MKL_RT", "")]
    names += sorted(glob.glob(os.path.join(sys.prefix, "lib", "libmkl_rt.so*")), key=len)
    names += ["libmkl_rt.so.2", "libmkl_rt.so.3", "libmkl_rt.so", "mkl_rt.2.dll", "libmkl_rt.2.dylib"]
    for name in names:
        if not name:
            continue
        try:
            lib = ctypes.CDLL(name)
        except OSError:
            continue
        f = lib.pardiso
        p_i32 = ctypes.POINTER(ctypes.c_int32)
        f.argtypes = [ctypes.POINTER(ctypes.c_int64), p_i32, p_i32, p_i32, p_i32, p_i32, ctypes.c_void_p,
                      p_i32, p_i32, p_i32, p_i32, p_i32, p_i32, ctypes.c_void_p, ctypes.c_void_p, p_i32]
        f.restype = None
        _LIB = lib
        return lib
    raise PardisoUnavailable("MKL PARDISO is not installed (pip install 'pixmuscle[fast]' or pip install mkl)")


def available() -> bool:
    """True when MKL's runtime library can be loaded."""
    try:
        _load()
    except PardisoUnavailable:
        return False
    return True


_ERRORS = {-1: "input inconsistent", -2: "not enough memory", -3: "reordering problem",
           -4: "zero pivot, numerical factorisation or iterative refinement problem", -5: "unclassified internal error",
           -6: "reordering failed", -7: "diagonal matrix is singular", -8: "32-bit integer overflow",
           -9: "not enough memory for out-of-core", -10: "error opening out-of-core files", -11: "read/write error"}


#: the values handed to a solve that does not read them (:meth:`PardisoLDLT.factorize`)
_UNREAD = np.zeros(1)


class PardisoError(RuntimeError):
    """PARDISO returned a non-zero error code."""


class SymmetricPattern:
    """Fixed map from a BSR matrix with square blocks (3×3: a node's displacement components; 1×1:
    one component) to the upper triangle in CSR, 0-based.

    Built once per sparsity pattern; :meth:`values` gathers the upper-triangle entries of a
    matrix with the same pattern in CSR order without any sorting (one ``take``). What is kept:
    the CSR structure PARDISO reads (``indptr``, ``indices``: int32), the gather map ``take``
    (int32 while the BSR data has fewer than 2³¹ entries, else int64) and a digest of the block
    pattern for :meth:`matches` (not a copy of it): 12 bytes per stored entry in place of 20 plus
    the block pattern's 4 per block.

    Parameters
    ----------
    K : scipy.sparse.bsr_matrix, (n, n) with (b, b) blocks
        Symmetric pattern (both triangles present), sorted block indices.
    """

    def __init__(self, K: sp.bsr_matrix):
        K = sp.bsr_matrix(K)
        K.sort_indices()
        b = K.blocksize[0]
        if K.blocksize != (b, b):
            raise ValueError(f"SymmetricPattern needs square blocks, got {K.blocksize}")
        bb = b * b
        self.n = K.shape[0]
        nb = K.indptr.size - 1
        itype = np.int32 if self.n < np.iinfo(np.int32).max else np.int64
        brow = np.repeat(np.arange(nb, dtype=itype), np.diff(K.indptr))
        bcol = K.indices.astype(itype, copy=False)
        ub = np.flatnonzero(bcol >= brow)  # blocks on or above the diagonal
        ii, jj = (a.ravel() for a in np.meshgrid(np.arange(b), np.arange(b), indexing="ij"))
        keep = (bcol[ub] > brow[ub])[:, None] | (jj >= ii)[None, :]  # whole off-diagonal blocks, upper half of diagonal ones
        take = (ub[:, None].astype(np.int64) * bb + np.arange(bb))[keep]
        row = (brow[ub][:, None] * b + ii[None, :].astype(itype))[keep]
        del keep, brow, ub
        # entries are in (block, i, j) order with sorted block columns in each block row, so a
        # stable sort by scalar row alone leaves every row's columns ascending
        order = np.argsort(row, kind="stable")
        self.take = take[order].astype(np.int32 if bb * K.indices.size < np.iinfo(np.int32).max else np.int64)
        del take
        if self.take.size >= np.iinfo(np.int32).max:
            raise ValueError(f"{self.take.size} non-zeros in the upper triangle: too many for 32-bit PARDISO indices")
        self.indptr = np.zeros(self.n + 1, np.int32)
        np.cumsum(np.bincount(row, minlength=self.n), out=self.indptr[1:])
        del row, order
        self.indices = (bcol[self.take // bb] * b + (self.take % b).astype(itype)).astype(np.int32)
        self.blocks = _digest(K)

    def matches(self, K: sp.bsr_matrix) -> bool:
        """True if ``K`` has exactly this block pattern (same shape, block counts and a digest of
        its block ``indptr`` and ``indices``)."""
        return K.shape[0] == self.n and _digest(K) == self.blocks

    def values(self, K: sp.bsr_matrix) -> np.ndarray:
        """Upper-triangle values of ``K`` in this pattern's CSR order, (nnz,) float64."""
        return np.ascontiguousarray(K.data.reshape(-1)[self.take], dtype=np.float64)


def _digest(K: sp.bsr_matrix) -> tuple:
    """Block pattern of ``K`` as (rows, blocks, BLAKE2b digest of its indptr and indices as int64)."""
    import hashlib

    h = hashlib.blake2b(digest_size=32)
    h.update(np.ascontiguousarray(K.indptr, np.int64).data)
    h.update(np.ascontiguousarray(K.indices, np.int64).data)
    return K.indptr.size - 1, K.indices.size, h.hexdigest()


class PardisoLDLT:
    """LDLᵀ factorisation of symmetric matrices sharing one sparsity pattern.

    Parameters
    ----------
    pattern : SymmetricPattern
        Upper-triangle CSR structure; the symbolic analysis (METIS ordering) is done here, once.

    Attributes
    ----------
    info : dict
        ``analysis_s``, ``factor_nnz`` (entries of L), ``factor_gflop``, ``inertia`` (positive,
        negative pivots of the last factorisation), ``perturbed_pivots``, ``memory_kB`` (what
        PARDISO itself holds, kB: its permanent analysis plus the factors and solve work space,
        iparm[15] + iparm[16]) and ``peak_memory_kB`` (that or the analysis' peak, iparm[14],
        whichever is larger).

    After a factorisation without perturbed pivots the values are not kept: a solve reads them
    only to refine after perturbed pivots (iparm[7] = 0), so the pattern alone stays for the next
    factorisation (on the 295k leg's region blocks, 0.5 GB less).

    Parameters
    ----------
    pattern : SymmetricPattern
    single : bool
        Factorise and solve in single precision (iparm[27] = 1: half the factor's memory), and
        refine each solution in double precision against the kept float64 values
        (x ← x + A₃₂⁻¹ (b − A x), at most ``refine`` steps, until ‖b − A x‖ ≤ ``refine_tol`` ‖b‖).
    count : int
        Matrices of this pattern whose factors are held at once (PARDISO's ``maxfct``; ``which``
        of :meth:`factorize` and :meth:`solve` picks one): they share the one analysis, which
        is then held once, not ``count`` times (the three displacement components' blocks of a
        region, :class:`~.linsolve.factorization.ComponentFactors`).
    """

    MTYPE = -2  # real symmetric indefinite

    def __init__(self, pattern: SymmetricPattern, single: bool = False, refine: int = 10, refine_tol: float = 1e-12,
                 count: int = 1):
        import time

        self._f = _load().pardiso
        self.pattern = pattern
        self.pt = np.zeros(64, np.int64)
        self.iparm = np.zeros(64, np.int32)
        ip = self.iparm
        ip[0] = 1     # iparm given here, not defaults
        ip[1] = 2     # METIS nested dissection
        ip[7] = 0     # iterative refinement: automatic (2 steps when pivots were perturbed)
        ip[9] = 8     # perturb pivots below 1e-8 ‖A‖
        ip[10] = 0    # no scaling (needs weighted matching, not for nearly definite matrices)
        ip[12] = 0
        ip[17] = -1   # report non-zeros of the factor
        ip[18] = -1   # report Gflop of the factorisation
        ip[20] = 1    # Bunch–Kaufman 1×1 and 2×2 pivots
        ip[34] = 1    # zero-based indices
        self.single, self.refine, self.refine_tol = bool(single), int(refine), float(refine_tol)
        self._real = np.float32 if self.single else np.float64
        if self.single:
            ip[27] = 1    # single precision: a, b and x are float32
        self.count = max(1, int(count))
        zero = np.zeros(pattern.indices.shape[0])
        # per matrix: the float64 values (kept only where a solve reads them) and those PARDISO reads
        # (a float32 copy in single precision)
        self._data = [zero] * self.count
        self._a = [zero] * self.count
        self._factored = [False] * self.count
        self.info = {}
        t0 = time.perf_counter()
        z = np.zeros(pattern.n, self._real)
        self._call(11, zero.astype(self._real, copy=False), z, z)
        self.info.update(analysis_s=time.perf_counter() - t0, factor_nnz=self._factor_nnz(), **self._memory())

    def _memory(self) -> dict:
        """PARDISO's own memory, kB (iparm[14..16]; see the class's ``info``)."""
        held = int(self.iparm[15]) + int(self.iparm[16])
        return {"memory_kB": held, "peak_memory_kB": max(held, int(self.iparm[14])),
                "analysis_kB": int(self.iparm[15]), "factors_kB": int(self.iparm[16])}

    def _factor_nnz(self) -> int:
        """Entries of the factor (iparm[17], an int32 that wraps above 2³¹: read as unsigned)."""
        return int(np.int32(self.iparm[17]).view(np.uint32))

    def _call(self, phase, a, b, x, nrhs=1, which=0):
        err = ctypes.c_int32(0)
        i32 = ctypes.c_int32
        p_i32 = ctypes.POINTER(ctypes.c_int32)
        self._f(self.pt.ctypes.data_as(ctypes.POINTER(ctypes.c_int64)), ctypes.byref(i32(self.count)),
                ctypes.byref(i32(which + 1)),
                ctypes.byref(i32(self.MTYPE)), ctypes.byref(i32(phase)), ctypes.byref(i32(self.pattern.n)),
                a.ctypes.data, self.pattern.indptr.ctypes.data_as(p_i32), self.pattern.indices.ctypes.data_as(p_i32),
                None, ctypes.byref(i32(nrhs)), self.iparm.ctypes.data_as(p_i32), ctypes.byref(i32(0)),
                b.ctypes.data, x.ctypes.data, ctypes.byref(err))
        if err.value != 0:
            raise PardisoError(f"PARDISO phase {phase}: error {err.value} ({_ERRORS.get(err.value, 'unknown')})")

    def factorize(self, values: np.ndarray, which: int = 0) -> None:
        """Numerical factorisation of the matrix ``which`` (of ``count``) with upper-triangle
        ``values`` (pattern order)."""
        self._data[which] = np.ascontiguousarray(values, dtype=np.float64)
        self._a[which] = self._data[which].astype(self._real, copy=False)
        dummy = np.zeros(self.pattern.n, self._real)
        self._factored[which] = False
        self._call(22, self._a[which], dummy, dummy, which=which)
        self._factored[which] = True
        self.info.update(factor_nnz=self._factor_nnz(), factor_gflop=float(self.iparm[18]) / 1e3,
                         inertia=(int(self.iparm[21]), int(self.iparm[22])), perturbed_pivots=int(self.iparm[13]),
                         **self._memory())
        if not self.single and self.info["perturbed_pivots"] == 0:
            # a solve (phase 33) reads the values only to refine after perturbed pivots (iparm[7] = 0),
            # and there were none: they are not kept (half the bytes of the pattern and values)
            self._data[which] = self._a[which] = _UNREAD

    def solve(self, b: np.ndarray, which: int = 0) -> np.ndarray:
        """x = A⁻¹ b for the last factorised matrix ``which``; ``b`` (n,) or (n, k)."""
        if not self._factored[which]:
            raise PardisoError("PARDISO: solve before a successful factorisation")
        b = np.asarray(b, dtype=np.float64)
        if self.single:
            return self._refined(b, which)
        bf = np.asfortranarray(b)
        x = np.zeros_like(bf)
        self._call(33, self._data[which], bf, x, nrhs=1 if b.ndim == 1 else b.shape[1], which=which)
        return np.ascontiguousarray(x)

    def _solve32(self, b: np.ndarray, which: int) -> np.ndarray:
        """A₃₂⁻¹ b with the single-precision factors, returned in float64."""
        bf = np.asfortranarray(b, dtype=np.float32)
        x = np.zeros_like(bf)
        self._call(33, self._a[which], bf, x, nrhs=1 if b.ndim == 1 else b.shape[1], which=which)
        return np.ascontiguousarray(x, dtype=np.float64)

    def _refined(self, b: np.ndarray, which: int) -> np.ndarray:
        """Single-precision solve refined in double precision against the float64 values."""
        pat = self.pattern
        data = self._data[which]
        U = sp.csr_matrix((data, pat.indices, pat.indptr), shape=(pat.n, pat.n))
        diag = data[pat.indptr[:-1]]  # each row's first upper entry is its diagonal
        d = diag[:, None] if b.ndim == 2 else diag
        x = self._solve32(b, which)
        bn = np.linalg.norm(b)
        for _ in range(self.refine):
            r = b - (U @ x + U.T @ x - d * x)
            if np.linalg.norm(r) <= self.refine_tol * bn:
                break
            x += self._solve32(r, which)
        return x

    def __matmul__(self, b):
        return self.solve(b)

    def release_factors(self, which: int | None = None) -> None:
        """Release the numerical factors and the values of the matrix ``which`` (default: every
        one; PARDISO phase 0); the analysis stays, and :meth:`factorize` works as before."""
        dummy = np.zeros(1, self._real)
        for k in range(self.count) if which is None else (which,):
            if self._factored[k]:
                self._call(0, dummy, dummy, dummy, which=k)
                self._factored[k] = False
            self._data[k] = self._a[k] = np.zeros(0)

    def free(self) -> None:
        """Release PARDISO's internal memory (factors and analysis)."""
        if self.pt.any():
            dummy = np.zeros(1)
            try:
                self._call(-1, self._data[0], dummy, dummy)
            except PardisoError:
                pass
            self.pt[:] = 0
            self._factored = [False] * self.count

    def __del__(self):
        try:
            self.free()
        except Exception:  # interpreter shutdown
            pass

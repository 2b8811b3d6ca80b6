"""Sparse products on every core.

The matrix-free tangent multiplies CSR matrices with three columns at a time (the displacement
components of every node), the region solves also with single vectors. Both run on all threads:

- three columns: a compiled kernel, rows in parallel on numba's threads, three running sums per
  row. SciPy's ``csr_matvecs`` loops over the columns inside every non-zero instead; on a banded
  matrix of 26 M non-zeros in 220k rows it took 0.098 s against 0.023 s for this kernel on two
  threads;
- vectors: SciPy's ``csr_matvec``, which releases the GIL, on row blocks of about equal numbers of
  non-zeros in a thread pool (0.021 → 0.012 s on two threads for the same matrix; a compiled
  kernel took 0.018 s).

Each output row is summed in the same order whatever the number of threads, so products do not
depend on it, bit for bit. The blocks share the matrix's arrays (no copy).

Threads: numba's (:func:`numba.get_num_threads`: all cores, or ``NUMBA_NUM_THREADS``, which the
Dask runner sets to the cores of a worker and :func:`pixmuscle.parallel.share_cores` to a process's
share of the cores under ``mpiexec``).
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numba
import numpy as np
import scipy.sparse as sp

#: below this many non-zeros a product runs on the calling thread (a pool hand-off costs ~50 µs)
MIN_NNZ = 200_000

_POOL: dict[int, ThreadPoolExecutor] = {}


def thread_count() -> int:
    """Threads of a product: numba's thread count (under ``mpiexec`` the process's share of the cores)."""
    return max(1, numba.get_num_threads())


def _pool(n: int) -> ThreadPoolExecutor:
    if n not in _POOL:
        _POOL[n] = ThreadPoolExecutor(max_workers=n, thread_name_prefix="pixmuscle-csr")
    return _POOL[n]


def _forget_pools() -> None:  # a forked child has none of its parent's threads
    _POOL.clear()


os.register_at_fork(after_in_child=_forget_pools)


@numba.njit(cache=True, inline="always")
def row_dot3(indptr, indices, data, X, r):  # pragma: no cover - compiled
    """(A X)[r] for CSR A and X (·, 3): three running sums over the row's entries in index order."""
    s0 = 0.0
    s1 = 0.0
    s2 = 0.0
    for jj in range(indptr[r], indptr[r + 1]):
        a = data[jj]
        j = indices[jj]
        s0 += a * X[j, 0]
        s1 += a * X[j, 1]
        s2 += a * X[j, 2]
    return s0, s1, s2


@numba.njit(parallel=True, cache=True)
def _matmat3(indptr, indices, data, X, out):  # pragma: no cover - compiled
    """out = A X for CSR A and X (n, 3)."""
    for i in numba.prange(indptr.size - 1):
        out[i, 0], out[i, 1], out[i, 2] = row_dot3(indptr, indices, data, X, i)


class ThreadedCSR:
    """A CSR matrix whose products ``A @ X`` run on all threads (module docstring).

    Parameters
    ----------
    A : sparse (m × n)
        Converted to CSR once; the blocks are views of its arrays.
    threads : int, optional
        Row blocks of a vector product (default :func:`thread_count`); 1, or fewer than
        :data:`MIN_NNZ` non-zeros, runs SciPy's product.

    Attributes
    ----------
    matrix : CSR (m × n)
        The matrix itself (slicing, conversion and assembly use it).
    """

    def __init__(self, A, threads: int | None = None):
        A = sp.csr_matrix(A)
        self.matrix = A
        self.shape = A.shape
        k = thread_count() if threads is None else max(1, int(threads))
        self._blocks = []
        if k > 1 and A.nnz >= MIN_NNZ:
            cuts = np.searchsorted(A.indptr, np.linspace(0, A.nnz, k + 1)[1:-1])
            bounds = np.unique(np.concatenate([[0], cuts, [A.shape[0]]]))
            for lo, hi in zip(bounds[:-1], bounds[1:], strict=True):
                self._blocks.append((int(lo), int(hi), row_view(A, lo, hi)))
        self.threads = max(1, len(self._blocks))

    @property
    def nnz(self) -> int:
        return self.matrix.nnz

    def __matmul__(self, X):
        if sp.issparse(X):
            return self.matrix @ X
        X = np.asarray(X)
        A = self.matrix
        if X.ndim == 2 and X.shape[1] == 3 and X.dtype.kind == "f" and A.dtype == np.float64 and A.nnz >= MIN_NNZ:
            out = np.empty((self.shape[0], 3))
            _matmat3(A.indptr, A.indices, A.data, np.ascontiguousarray(X, dtype=np.float64), out)
            return out
        if self.threads == 1:
            return A @ X
        out = np.empty((self.shape[0],) + X.shape[1:], dtype=np.result_type(self.matrix.dtype, X.dtype))

        def part(block):
            lo, hi, blk = block
            out[lo:hi] = blk @ X

        run_parts(part, self._blocks)
        return out


def row_view(A: sp.csr_matrix, lo: int, hi: int) -> sp.csr_matrix:
    """Rows ``lo:hi`` of the CSR ``A`` as a CSR matrix on views of its arrays (only the row pointers
    are new). SciPy's constructor copies a view that holds less than half of its base
    (``_prune_array``), which would hold every row block of a threaded product twice."""
    s, e = A.indptr[lo], A.indptr[hi]
    blk = sp.csr_matrix((hi - lo, A.shape[1]), dtype=A.dtype)
    blk.indptr = (A.indptr[lo:hi + 1] - s).astype(A.indices.dtype, copy=False)
    blk.indices, blk.data = A.indices[s:e], A.data[s:e]
    return blk


def run_parts(task, parts: list) -> None:
    """``task(part)`` for every part, on the thread pool when there are several (``task`` must
    release the GIL to gain: a numba function compiled with ``nogil``), on this thread otherwise."""
    if len(parts) == 1:
        task(parts[0])
        return
    for f in [_pool(len(parts)).submit(task, p) for p in parts]:
        f.result()


def map_threads(task, items, threads: int | None = None) -> list:
    """``[task(item) for item in items]`` on a pool of ``threads`` threads (default
    :func:`thread_count`), results in the order of ``items``; at most ``threads`` tasks run at once,
    so that their temporaries are held that many times, not once per item. ``task`` must release the
    GIL to gain (SciPy's sparse products do)."""
    items = list(items)
    n = thread_count() if threads is None else max(1, int(threads))
    if n == 1 or len(items) <= 1:
        return [task(item) for item in items]
    return list(_pool(n).map(task, items))

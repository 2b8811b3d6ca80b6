"""Matrix-free products with the nodally integrated stiffness (paper eqs. 17–20).

With SCNI every integration point is a node L, and the tangent stiffness is a sum of products

    K = Σ_L V_L B̃_Lᵀ A_L B̃_L  =  Gᵀ C G,

with G the stacked smoothed-gradient operators (:mod:`.scni`, 3N × N for the three derivative
directions J, applied to the three displacement components i) and C block diagonal with one
9×9 matrix per node (C_L = V_L A_L, index 3i + J). The NSNI stabilisation has the same form with
the gradient-difference operators (:mod:`.stabilization`). So K v never needs K: it is one
sparse product with G (3 columns), a 9×9 contraction per node and one product with Gᵀ. That
costs about as much as a product with the assembled K and holds ~5 % of its memory
(docs/linsolve-research.md §1), and the product is always with the exact current tangent.
"""

from __future__ import annotations

import functools

import numba
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .scni import StackedRows
from .threaded import ThreadedCSR, map_threads, row_dot3


@numba.njit(cache=True, parallel=True)
def _contract(C, w, g, n, out):  # pragma: no cover - compiled
    """out[q, J, L, i] = w[q·n + L] Σ_{k, K} C[q·n + L, 3i + J, 3k + K] g[q, K, L, k] for every group q
    and node L (w of size 0: no weight). Weighting here keeps the moduli as given (no scaled copy)."""
    ng = g.shape[0]
    weighted = w.size > 0
    for p in numba.prange(ng * n):
        q = p // n
        L = p - q * n
        for i in range(3):
            for J in range(3):
                s = 0.0
                a = 3 * i + J
                for k in range(3):
                    for K in range(3):
                        s += C[p, a, 3 * k + K] * g[q, K, L, k]
                out[q, J, L, i] = w[p] * s if weighted else s


#: the weight of :func:`_contract` that leaves the moduli as they are
_UNWEIGHTED = np.empty(0)


#: row blocks of a transposed product Bᵀ X (:class:`TransposedCSR`): a fixed number, so that the sums,
#: and the product bit for bit, do not depend on the number of threads
TRANSPOSE_PARTS = 8


def part_windows(A: sp.csr_matrix, cuts: np.ndarray, own_rows: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The columns [lo_p, hi_p) that the entries of each row block A[cuts[p]:cuts[p + 1]] reach
    (with ``own_rows`` the block's own rows too: an upper triangle's block adds into both).

    A transposed or symmetric product sums each block into a buffer over its window only, not
    over all n rows: in the slice-by-slice node order a block of a node-by-node matrix (the NSNI
    stabilisation, one gradient operator) reaches a band of nodes around its own rows, so its
    buffers hold about n rows plus a band per block instead of ``TRANSPOSE_PARTS`` · n, and are
    cleared and added up in proportion (:func:`add_windows`). A block of stacked operators that
    crosses from one operator to the next reaches most of the columns: at worst n rows, as before.
    The windows are fixed when the product is made: the matrix's pattern must not change after.

    Returns
    -------
    lo, hi : (P,) int64
    """
    P = cuts.size - 1
    lo, hi = np.zeros(P, np.int64), np.zeros(P, np.int64)
    for p in range(P):
        cols = A.indices[A.indptr[cuts[p]]:A.indptr[cuts[p + 1]]]
        if own_rows:  # an entry left of the diagonal (not an upper triangle) still lands inside
            lo[p] = min(int(cuts[p]), int(cols.min())) if cols.size else cuts[p]
            hi[p] = max(int(cuts[p + 1]), int(cols.max()) + 1 if cols.size else 0)
        elif cols.size:
            lo[p], hi[p] = int(cols.min()), int(cols.max()) + 1
    return lo, hi


def window_offsets(lo: np.ndarray, hi: np.ndarray, k: int) -> np.ndarray:
    """Offsets (P + 1,) of the blocks' (hi − lo) × k buffers in one flat array."""
    return np.concatenate([[0], np.cumsum(k * (hi - lo))]).astype(np.int64)


def add_windows(buf: np.ndarray, lo: np.ndarray, hi: np.ndarray, offs: np.ndarray, n: int, k: int) -> np.ndarray:
    """(n, k): the blocks' buffers added into their windows, block 0 first (a fixed order, so the
    sum does not depend on the number of threads)."""
    out = np.zeros((n, k))
    for p in range(lo.size):
        out[lo[p]:hi[p]] += buf[offs[p]:offs[p + 1]].reshape(-1, k)
    return out


@numba.njit(cache=True, parallel=True)
def _tmatmat3(indptr, indices, data, X, cuts, lo, offs, buf):  # pragma: no cover - compiled
    """buf_p = A[cuts[p]:cuts[p + 1]]ᵀ X[cuts[p]:cuts[p + 1]] on the window from column lo[p], for
    CSR A, X (m, 3); buf_p = buf[offs[p]:offs[p + 1]] (cleared here), row-major (·, 3)."""
    for p in numba.prange(cuts.size - 1):
        base, first = offs[p], lo[p]
        for i in range(base, offs[p + 1]):
            buf[i] = 0.0
        for r in range(cuts[p], cuts[p + 1]):
            x0 = X[r, 0]
            x1 = X[r, 1]
            x2 = X[r, 2]
            for jj in range(indptr[r], indptr[r + 1]):
                a = data[jj]
                q = base + 3 * (indices[jj] - first)
                buf[q] += a * x0
                buf[q + 1] += a * x1
                buf[q + 2] += a * x2


class TransposedCSR:
    """Aᵀ of a CSR matrix A (m × n) as an operator, without a transposed copy.

    ``Aᵀ @ X`` for X (m, 3) scatters the rows of A, :data:`TRANSPOSE_PARTS` row blocks of about
    equal non-zeros in parallel, each into its own sum over the columns it reaches
    (:func:`part_windows`), added in a fixed order; other right-hand sides use SciPy's product
    with the CSC view ``A.T``.

    Parameters
    ----------
    A : CSR (m × n)

    Attributes
    ----------
    matrix : CSC (n × m)
        ``A.T``: a view of A's arrays.
    """

    def __init__(self, A: sp.csr_matrix):
        self._A = A
        self.shape = (A.shape[1], A.shape[0])
        cuts = np.searchsorted(A.indptr, np.linspace(0, A.nnz, TRANSPOSE_PARTS + 1)[1:-1])
        self._cuts = np.concatenate([[0], cuts, [A.shape[0]]]).astype(np.int64)
        self._lo, self._hi = part_windows(A, self._cuts)
        self._offs = window_offsets(self._lo, self._hi, 3)

    @property
    def matrix(self) -> sp.csc_matrix:
        return self._A.T

    @property
    def nnz(self) -> int:
        return self._A.nnz

    def __matmul__(self, X):
        A = self._A
        if sp.issparse(X) or np.ndim(X) != 2 or np.shape(X)[1] != 3 or A.dtype != np.float64:
            return A.T @ X
        buf = np.empty(self._offs[-1])
        _tmatmat3(A.indptr, A.indices, A.data, np.ascontiguousarray(X, dtype=np.float64), self._cuts, self._lo,
                  self._offs, buf)
        return add_windows(buf, self._lo, self._hi, self._offs, self.shape[0], 3)


@numba.njit(cache=True, parallel=True)
def _rows_matmat(indptr, indices, data, rows, X, out):  # pragma: no cover - compiled
    """out[i] = A[rows[i]] X for CSR A and X (n, k): each row summed in index order, as a CSR product
    (in registers for one and three columns, in ``out`` for others: the same sums)."""
    k = X.shape[1]
    for i in numba.prange(rows.size):
        r = rows[i]
        if k == 3:
            out[i, 0], out[i, 1], out[i, 2] = row_dot3(indptr, indices, data, X, r)
        elif k == 1:
            s = 0.0
            for jj in range(indptr[r], indptr[r + 1]):
                s += data[jj] * X[indices[jj], 0]
            out[i, 0] = s
        else:
            for c in range(k):
                out[i, c] = 0.0
            for jj in range(indptr[r], indptr[r + 1]):
                a = data[jj]
                j = indices[jj]
                for c in range(k):
                    out[i, c] += a * X[j, c]


class RowSubset:
    """Rows ``rows`` of a CSR matrix A as an operator, without a copy of them: ``A[rows] @ X``
    multiplies with A's own arrays (a compiled product, rows in parallel, each summed in index
    order: the same numbers as the product with the copied rows).

    Parameters
    ----------
    A : CSR (m × n)
    rows : (r,) int
    """

    def __init__(self, A, rows: np.ndarray):
        A = A.matrix if isinstance(A, ThreadedCSR) else A
        self._A = sp.csr_matrix(A)  # no copy of a CSR matrix
        self.rows = np.asarray(rows, np.int64)
        self.shape = (self.rows.size, self._A.shape[1])

    @property
    def matrix(self) -> sp.csr_matrix:
        """The rows as a CSR matrix (a copy)."""
        return self._A[self.rows]

    def __matmul__(self, X):
        A = self._A
        X = np.asarray(X)
        if X.ndim not in (1, 2) or X.dtype.kind != "f" or A.dtype != np.float64:
            return A[self.rows] @ X
        X2 = np.ascontiguousarray(X.reshape(X.shape[0], -1), dtype=np.float64)
        out = np.empty((self.rows.size, X2.shape[1]))
        _rows_matmat(A.indptr, A.indices, A.data, self.rows, X2, out)
        return out.reshape((self.rows.size,) + X.shape[1:])


@numba.njit(cache=True, parallel=True)
def _symmatmat(indptr, indices, data, X, cuts, lo, offs, buf):  # pragma: no cover - compiled
    """buf_p = U_p X + (U_p − diag U_p)ᵀ X for the rows U_p = U[cuts[p]:cuts[p + 1]] of an upper
    triangle U (CSR), X (n, k), on the window from row lo[p]; buf_p = buf[offs[p]:offs[p + 1]]
    (cleared here), row-major (·, k)."""
    k = X.shape[1]
    for p in numba.prange(cuts.size - 1):
        base, first = offs[p], lo[p]
        for i in range(base, offs[p + 1]):
            buf[i] = 0.0
        for r in range(cuts[p], cuts[p + 1]):
            qr = base + k * (r - first)
            for jj in range(indptr[r], indptr[r + 1]):
                a = data[jj]
                j = indices[jj]
                for c in range(k):
                    buf[qr + c] += a * X[j, c]
                if j != r:
                    q = base + k * (j - first)
                    for c in range(k):
                        buf[q + c] += a * X[r, c]


@numba.njit(cache=True, parallel=True)
def _symmatmat3(indptr, indices, data, X, cuts, lo, offs, buf):  # pragma: no cover - compiled
    """:func:`_symmatmat` for X (n, 3), each row's own product summed in registers and added once."""
    for p in numba.prange(cuts.size - 1):
        base, first = offs[p], lo[p]
        for i in range(base, offs[p + 1]):
            buf[i] = 0.0
        for r in range(cuts[p], cuts[p + 1]):
            s0 = 0.0
            s1 = 0.0
            s2 = 0.0
            x0 = X[r, 0]
            x1 = X[r, 1]
            x2 = X[r, 2]
            for jj in range(indptr[r], indptr[r + 1]):
                a = data[jj]
                j = indices[jj]
                s0 += a * X[j, 0]
                s1 += a * X[j, 1]
                s2 += a * X[j, 2]
                if j != r:
                    q = base + 3 * (j - first)
                    buf[q] += a * x0
                    buf[q + 1] += a * x1
                    buf[q + 2] += a * x2
            q = base + 3 * (r - first)
            buf[q] += s0
            buf[q + 1] += s1
            buf[q + 2] += s2


#: row blocks of :func:`gram_upper`: each holds one block of L's rows while it is summed
GRAM_BLOCKS = 8


def gram_upper(terms, n: int, blocks: int = GRAM_BLOCKS) -> sp.csr_matrix:
    """The upper triangle (diagonal included) of L = Σ_t B_tᵀ diag(w_t) B_t, by blocks of L's rows.

    L is never formed whole, nor the stacked operators: for each operator in turn (and its
    transpose, made once) and each block of rows R of L, the rows R of B_tᵀ are weighted,
    (B_tᵀ)_R diag(w_t) B_t is made and its entries left of the diagonal dropped, and the block's
    sum is added to. ``terms`` is iterated once, so a generator can make each operator when it is
    asked for and let it go after: the memory beyond the result is then one operator, its
    transpose and one block's product per thread (on the 295k leg the product of all nine NSNI
    operators stacked held 5.4 GB beside them at its peak). The blocks of an operator are made on
    :func:`.threaded.map_threads`' threads, each into its own part of the result.

    Parameters
    ----------
    terms : iterable of (B_t, w_t)
        Sparse operators B_t (m_t × n) and weights w_t (m_t,) of their rows (any sign).
    n : int
        Columns of every B_t (the order of L).
    blocks : int
        Row blocks of L.

    Returns
    -------
    U : CSR (n × n)
        The upper triangle of L, sorted indices.
    """
    edges = np.linspace(0, n, max(1, min(int(blocks), n)) + 1).astype(np.int64)
    parts = [None] * (edges.size - 1)

    def block(b, B, BT, w):
        lo, hi = edges[b], edges[b + 1]
        Bc = BT[lo:hi]  # ((hi − lo) × m): the rows R of Bᵀ
        Bc.data *= w[Bc.indices]
        # row r of the block is L's row lo + r: keep its columns j >= lo + r
        prod = sp.triu(Bc @ B, k=int(lo), format="csr")
        del Bc
        parts[b] = prod if parts[b] is None else (parts[b] + prod).tocsr()

    for B, w in terms:
        B = sp.csr_matrix(B)
        w = np.asarray(w, np.float64)
        # Bᵀ by rows (B's columns: one copy of this operator), each block of its rows weighted as it is cut
        BT = B.T.tocsr()
        map_threads(functools.partial(block, B=B, BT=BT, w=w), range(edges.size - 1))
        del B, BT
    parts = [sp.csr_matrix((int(hi - lo), n)) if p is None else p
             for p, lo, hi in zip(parts, edges[:-1], edges[1:], strict=True)]
    U = sp.vstack(parts, format="csr")
    U.sort_indices()
    return U


class SymmetricCSR:
    """A symmetric sparse matrix L (n × n) stored as its upper triangle U (diagonal included): half
    the entries.

    ``L @ X`` is one pass over U, :data:`TRANSPOSE_PARTS` row blocks of about equal non-zeros in
    parallel, each adding U_p X and its transpose's share into its own sum over the rows it reaches
    (:func:`part_windows`), added in a fixed order (so the product does not depend on the number of
    threads). With three columns each row's own product is summed in registers and added once.

    Parameters
    ----------
    L : sparse (n × n)
        Symmetric; its upper triangle is kept (the lower one differs from it by round-off at most).
    upper : bool
        ``L`` is already the upper triangle (no copy of it is made).

    Attributes
    ----------
    upper : CSR (n × n)
        U, sorted, 32-bit indices where they fit.
    """

    def __init__(self, L, upper: bool = False):
        U = sp.csr_matrix(L) if upper else sp.triu(sp.csr_matrix(L), format="csr")
        U.sort_indices()
        if U.nnz < np.iinfo(np.int32).max and U.shape[0] < np.iinfo(np.int32).max:
            U.indices = U.indices.astype(np.int32, copy=False)
            U.indptr = U.indptr.astype(np.int32, copy=False)
        self.upper = U
        self.shape = U.shape
        cuts = np.searchsorted(U.indptr, np.linspace(0, U.nnz, TRANSPOSE_PARTS + 1)[1:-1])
        self._cuts = np.concatenate([[0], cuts, [U.shape[0]]]).astype(np.int64)
        self._lo, self._hi = part_windows(U, self._cuts, own_rows=True)

    @property
    def nnz(self) -> int:
        """Stored entries (of U)."""
        return self.upper.nnz

    @property
    def matrix(self) -> sp.csr_matrix:
        """L as a CSR matrix, sorted (made anew at each call: n × n with both triangles)."""
        U = self.upper
        L = (U + sp.triu(U, k=1, format="csr").T).tocsr()
        L.sort_indices()
        return L

    def rows_matrix(self, nodes: np.ndarray) -> sp.csr_matrix:
        """The rows ``nodes`` of L in place (n × n CSR, sorted; the other rows empty)."""
        nodes = np.asarray(nodes, np.int64)
        R = self._rows(nodes).tocoo()
        M = sp.csr_matrix((R.data, (nodes[R.row], R.col)), shape=self.shape)
        M.sort_indices()
        return M

    def _lower(self, nodes: np.ndarray) -> sp.csr_matrix:
        """The strictly lower triangle of L's rows ``nodes`` (distinct), (len(nodes) × n) CSR: the
        entries U[i, j], i < j, of U's columns j in ``nodes``."""
        U = self.upper
        n = self.shape[0]
        local = np.full(n, -1, np.int64)
        local[nodes] = np.arange(nodes.size)
        i = np.repeat(np.arange(n, dtype=U.indices.dtype), np.diff(U.indptr))
        sel = np.flatnonzero((local[U.indices] >= 0) & (U.indices != i))
        M = sp.csr_matrix((U.data[sel], (local[U.indices[sel]], i[sel])), shape=(nodes.size, n))
        M.sort_indices()
        return M

    def _rows(self, nodes: np.ndarray) -> sp.csr_matrix:
        """L[nodes] (len(nodes) × n CSR, distinct ``nodes``)."""
        return (self.upper[nodes] + self._lower(nodes)).tocsr()

    def rows(self, nodes: np.ndarray):
        """The rows ``nodes`` R (distinct) of L as a function Z (n, k) → (L Z)_R: U's own rows, and
        the strictly lower part of L's rows R (U's columns R) stored, about half of L[R]."""
        nodes = np.asarray(nodes, np.int64)
        upper = RowSubset(self.upper, nodes)
        lower = ThreadedCSR(self._lower(nodes))
        return lambda Z: upper @ Z + lower @ Z

    def __matmul__(self, X):
        if sp.issparse(X):
            return self.matrix @ X
        X = np.asarray(X, dtype=np.float64)
        X2 = np.ascontiguousarray(X.reshape(X.shape[0], -1))
        k = X2.shape[1]
        U = self.upper
        offs = window_offsets(self._lo, self._hi, k)
        buf = np.empty(offs[-1])
        (_symmatmat3 if k == 3 else _symmatmat)(U.indptr, U.indices, U.data, X2, self._cuts, self._lo, offs, buf)
        return add_windows(buf, self._lo, self._hi, offs, U.shape[0], k).reshape(X.shape)


class ProductForm:
    """Σ_q Σ_L B_q,Lᵀ C_q,L B_q,L for groups q of three (N × N) gradient-like operators.

    Parameters
    ----------
    groups : list of lists of 3 sparse (N × N)
        ``groups[q][J] @ u`` is the derivative ∂u/∂X_J (or a gradient-like quantity) at every
        node for nodal values ``u`` (N,) or (N, 3).

    Notes
    -----
    The operators are stacked once into a CSR matrix B (3·Q·N × N); each product :meth:`apply`
    is ``Bᵀ (C : (B v))`` with two sparse-times-dense products and one compiled per-node
    contraction, all on every core (:mod:`.threaded`). One group given as
    :class:`~.scni.StackedRows` (the SCNI gradients) is used as it is stacked, without a copy.
    Bᵀ is not stored: its products scatter the rows of B (:class:`TransposedCSR`; on the 21k leg
    B holds 0.026 GB, as its transpose did).

    Attributes
    ----------
    B : ThreadedCSR
        The stacked operators (``.matrix`` is the CSR matrix itself).
    BT : TransposedCSR
        Their transpose, on B's arrays.
    """

    def __init__(self, groups):
        self.n_groups = len(groups)
        self.n = groups[0][0].shape[1]
        if len(groups) == 1 and isinstance(groups[0], StackedRows) and len(groups[0]) == 3:
            B = groups[0].stacked
        else:
            B = StackedRows([M for grp in groups for M in grp]).stacked
        self.B = ThreadedCSR(B)
        self.BT = TransposedCSR(B)

    @property
    def nbytes(self) -> int:
        """Memory of the stacked operators, bytes."""
        M = self.B.matrix
        return M.data.nbytes + M.indices.nbytes + M.indptr.nbytes

    def gradients(self, V: np.ndarray) -> np.ndarray:
        """Per-group gradients of the nodal field V (N, 3): shape (Q, N, 3, 3), index [q, L, i, J]."""
        g = (self.B @ V).reshape(self.n_groups, 3, self.n, 3)
        return g.transpose(0, 2, 3, 1)

    def apply(self, C: np.ndarray, V: np.ndarray, extra=None, weight: np.ndarray | None = None) -> np.ndarray:
        """Σ_q B_qᵀ (w_q C_q : (B_q V) + extra(∇V)).

        Parameters
        ----------
        C : (Q·N, 9, 9) float
            Per-node moduli of every group, group-major, index 3i + J.
        V : (N, 3) float
        extra : callable, optional
            ``extra(grad) -> (N, 3, 3)``: a further stress-like term of the first group's
            gradients ``grad[L, i, J] = ∂V_i/∂X_J`` (already multiplied by the cell volumes).
        weight : (Q·N,) float, optional
            A factor w of each node's moduli (the cell volumes, cm³); none by default.

        Returns
        -------
        (N, 3) float
        """
        g = np.ascontiguousarray((self.B @ V).reshape(self.n_groups, 3, self.n, 3))
        t = np.empty_like(g)
        _contract(C, _UNWEIGHTED if weight is None else weight, g, self.n, t)
        if extra is not None:
            t[0] += extra(g[0].transpose(1, 2, 0)).transpose(2, 0, 1)
        return self.BT @ t.reshape(-1, 3)


class RowProduct:
    """Rows of the nodes R of Σ_q Σ_L B_q,Lᵀ C_q,L B_q,L, matrix-free.

    Row I collects the cells (q, L) whose gradient rows B_q,L hold I, so

        (K Z)_R = B_hRᵀ (C_h : (B_h Z)),

    with B_h the gradient rows of those cells only and B_hR their columns of R. The operators hold
    the cells around R, not the rows of K (whose pairs reach twice as far): on the 74k leg the region
    solves' rows of K_d held 78 M non-zeros. B_h is applied from B's own arrays (:class:`RowSubset`);
    only B_hR, the columns of R transposed, is stored.

    Parameters
    ----------
    form : ProductForm
        The stacked operators B (3·Q·N × N, rows (q, J, L)).
    nodes : (n,) int
        The nodes R.

    Attributes
    ----------
    cells : (n_h,) int
        Indices q·N + L of the cells whose gradient rows hold a node of R (the rows of C that enter).
    """

    def __init__(self, form: ProductForm, nodes: np.ndarray):
        n, Q = form.n, form.n_groups
        B = form.B.matrix
        nodes = np.asarray(nodes, np.int64)
        hit = np.zeros(n, bool)
        hit[nodes] = True
        seen = np.zeros(B.shape[0], bool)
        seen[np.unique(B.tocoo().row[hit[B.indices]])] = True  # rows of B with a column in R
        seen = seen.reshape(Q, 3, n).any(axis=1)  # a cell enters with its three rows
        q, L = np.nonzero(seen)
        self.cells = q * n + L
        rows = (q[None, :] * 3 * n + np.arange(3)[:, None] * n + L[None, :]).ravel()  # rows (J, cell)
        self.n_cells = self.cells.size
        self.Bh = RowSubset(B, rows)  # B's own rows, not a copy
        self.BhT = ThreadedCSR(B[rows][:, nodes].T.tocsr())

    def apply(self, C: np.ndarray, Z: np.ndarray) -> np.ndarray:
        """(K Z)_R, (n, 3), for the moduli of :attr:`cells` C (n_h, 9, 9) and nodal values Z (N, 3)."""
        g = np.ascontiguousarray((self.Bh @ Z).reshape(1, 3, self.n_cells, 3))
        t = np.empty_like(g)
        _contract(np.ascontiguousarray(C), _UNWEIGHTED, g, self.n_cells, t)
        return self.BhT @ t.reshape(-1, 3)


class ConstantStiffness:
    """A constant stiffness Σ_q Σ_L B_q,Lᵀ C_q,L B_q,L (the NSNI term), applied as cheaply as its
    moduli allow.

    Where every C_q,L is a multiple c_q,L of the identity on the 9 components (NSNI with the default
    modulus A_s = 2 μ I), the stiffness acts on each displacement component alike, K = L ⊗ I₃ with
    the scalar operator

        L = Σ_q Σ_J B_qJᵀ diag(c_q) B_qJ    (N × N),

    assembled once: a product is then one sparse product with three columns, in place of two with
    the stacked operators (three times the rows of L) and a 9 × 9 contraction per row. On the 21k
    leg L has as many non-zeros as the stacked operators (337 per row); it is symmetric, and only its
    upper triangle is kept (:class:`SymmetricCSR`: 0.081 → 0.04 GB on the 21k leg). Otherwise the
    product is :class:`ProductForm`'s.

    Parameters
    ----------
    groups : list of lists of 3 sparse (N × N)
        As :class:`ProductForm`.
    C : (Q·N, 9, 9) float
        Per-node moduli of every group, group-major, index 3i + J.
    """

    def __init__(self, groups, C: np.ndarray):
        C = np.asarray(C, dtype=np.float64)
        self.n = groups[0][0].shape[1]
        self.scalar = self.is_scalar(C)
        if self.scalar:
            n, c = self.n, C[:, 0, 0]
            self.L = SymmetricCSR(gram_upper([(M, c[q * n:(q + 1) * n]) for q, grp in enumerate(groups) for M in grp], n),
                                  upper=True)
        else:
            self.form, self.C = ProductForm(groups), np.ascontiguousarray(C)

    @staticmethod
    def is_scalar(C: np.ndarray) -> bool:
        """Is every C_q,L = c_q,L I: each diagonal entry c and no other non-zero (tested without a
        (Q·N, 9, 9) temporary)?"""
        diag = np.einsum("nii->ni", C)
        return bool(np.all(diag == C[:, 0, 0][:, None]) and np.count_nonzero(C) == np.count_nonzero(diag))

    @classmethod
    def scalar_from(cls, terms, n: int) -> ConstantStiffness:
        """The scalar form L = Σ_t B_tᵀ diag(c_t) B_t from an iterable of (B_t, c_t) — a generator
        may make each operator when it is asked for and let it go after (:func:`gram_upper`)."""
        self = cls.__new__(cls)
        self.n, self.scalar = n, True
        self.L = SymmetricCSR(gram_upper(terms, n), upper=True)
        return self

    def apply(self, V: np.ndarray) -> np.ndarray:
        """K V for nodal values V (N, 3); returns (N, 3)."""
        if self.scalar:
            return self.L @ V
        return self.form.apply(self.C, V)

    def rows(self, nodes: np.ndarray):
        """The rows of the nodes R as a function Z (N, 3) → (K Z)_R (n, 3)."""
        if self.scalar:
            return self.L.rows(nodes)
        rp = RowProduct(self.form, nodes)
        C = np.ascontiguousarray(self.C[rp.cells])
        return lambda Z: rp.apply(C, Z)


class MatrixFreeTangent(spla.LinearOperator):
    """The stiffness K (3N × 3N, N/cm) as a linear operator: K v = Gᵀ C G v + K_stab v + K_pen v.

    Parameters
    ----------
    main : ProductForm
        SCNI gradient operators (one group).
    C : (N, 9, 9) float
        The current material tangent A_L per node, N/cm² (held as given: a state's own array).
    volume : (N,) float
        Cell volumes V_L, cm³: the moduli of the product are V_L A_L (N·cm).
    stab : ConstantStiffness or None
        The NSNI stiffness.
    penalty : list of 3 sparse (N × N) or None
        Penalty stiffness per displacement component.
    volumetric : tuple (PatchProjection, VolumetricState) or None
        Rank-one patch terms of a projected volumetric energy (:mod:`.volumetric`).
    """

    def __init__(self, main: ProductForm, C: np.ndarray, volume: np.ndarray, stab=None, penalty=None,
                 volumetric=None):
        n = main.n
        super().__init__(np.float64, (3 * n, 3 * n))
        self.main = main
        self.C = np.ascontiguousarray(C, dtype=np.float64)
        self.volume = np.ascontiguousarray(volume, dtype=np.float64)
        self.stab = stab
        self.penalty = penalty
        self.volumetric = volumetric

    def with_volumetric(self, volumetric) -> MatrixFreeTangent:
        """The same operator with other patch terms ``volumetric`` (as the parameter), sharing the
        moduli, operators and stiffnesses (no second (N, 9, 9) array)."""
        return MatrixFreeTangent(self.main, self.C, self.volume, stab=self.stab, penalty=self.penalty,
                                 volumetric=volumetric)

    def _matvec(self, v):
        return self.apply(v)

    def apply(self, v, extra=None) -> np.ndarray:
        """K v (3N,), with a further stress-like term ``extra(grad) -> (N, 3, 3)`` of the gradients
        grad[L, i, J] = ∂v_i/∂X_J added before the transposed gradient (as :meth:`ProductForm.apply`):
        a caller that needs ∇v or adds Bᵀ of its own stress shares the two gradient products."""
        V = np.asarray(v, dtype=np.float64).reshape(-1, 3)
        term = extra
        if self.volumetric is not None:
            term = self._patch_term if extra is None else (lambda grad: self._patch_term(grad) + extra(grad))
        y = self.main.apply(self.C, V, extra=term, weight=self.volume)
        if self.stab is not None:
            y += self.stab.apply(V)
        if self.penalty is not None:
            for j in range(3):
                y[:, j] += self.penalty[j] @ V[:, j]
        return y.reshape(-1)

    def _patch_term(self, grad):
        proj, vs = self.volumetric
        return proj.apply(grad, vs)

    def _matmat(self, X):
        return np.column_stack([self._matvec(x) for x in np.asarray(X).T])


def spd_surrogate(A: np.ndarray) -> np.ndarray:
    """A symmetric positive semi-definite stand-in for each node's 9×9 tangent.

    The symmetric part's eigenvalues are replaced by their absolute values. At α > 0 the active
    fibre stress makes a few eigenvalues of a muscle node's tangent slightly negative (geometric
    stiffness of the deviatoric active stress), although the assembled K stays positive
    definite; the AMG preconditioner is built from this surrogate, which is positive
    semi-definite node by node.

    Parameters
    ----------
    A : (N, 3, 3, 3, 3) or (N, 9, 9) float

    Returns
    -------
    (N, 3, 3, 3, 3) float
    """
    n = A.shape[0]
    A9 = np.asarray(A, float).reshape(n, 9, 9)
    sym = 0.5 * (A9 + A9.transpose(0, 2, 1))
    lam, Q = np.linalg.eigh(sym)
    out = np.matmul(Q * np.abs(lam)[:, None, :], Q.transpose(0, 2, 1))
    return out.reshape(n, 3, 3, 3, 3)

"""Assembly of the nodally integrated tangent stiffness on a fixed sparsity pattern (paper eqs. 17–20).

With SCNI every integration point is a node L with smoothed gradients g_I(L) = b̃_I(X_L) ∈ R³
(:mod:`pixmuscle.mechanics.scni`). The 3×3 block of the consistent tangent coupling nodes I and J is

    K_IJ[i, k] = Σ_L w_L Σ_{J', L'} g_I(L)[J'] A_L[i, J', k, L'] g_J(L)[L'],

i.e. K = Σ_L w_L B̃_Lᵀ A_L B̃_L (eqs. 18–20), with A_L[i, J, k, L] = ∂P_iJ/∂F_kL the first
elasticity tensor at node L (errata: the 9×9 matrix C of eq. 20 in the 9-vector order of eq. 17)
and w_L = V_L. The pattern — all node pairs that share the support of some cell — is computed once
per model (as the structure of Sᵀ S with S the cell–node support incidence) and stored as a
block-CSR (BSR, 3×3 blocks) matrix; each Newton iteration only refills the values with a compiled
kernel (one pass over cells, no Python loop over nodes or pairs). The same kernel assembles the
stabilisation term with other per-cell gradient vectors on the same supports.
"""

from __future__ import annotations

import numba
import numpy as np
import scipy.sparse as sp

from .threaded import MIN_NNZ, run_parts, thread_count


@numba.njit(cache=True, nogil=True, inline="always")
def _position(indices, lo, hi, key):  # pragma: no cover - compiled
    """Position of ``key`` in the sorted ``indices[lo:hi + 1]`` (binary search; the key is present)."""
    while lo < hi:
        mid = (lo + hi) >> 1
        if indices[mid] < key:
            lo = mid + 1
        else:
            hi = mid
    return lo


@numba.njit(cache=True, nogil=True, inline="always")
def _far(ijk, wide, na, nb, reach):  # pragma: no cover - compiled
    """True when nodes na, nb are more than ``reach`` voxels apart along an axis and neither is ``wide``."""
    if wide[na] or wide[nb]:
        return False
    return (abs(ijk[na, 0] - ijk[nb, 0]) > reach or abs(ijk[na, 1] - ijk[nb, 1]) > reach
            or abs(ijk[na, 2] - ijk[nb, 2]) > reach)


@numba.njit(cache=True, nogil=True)
def _fill(ptr, nodes, g, A, w, indptr, indices, data, ijk, reach, wide, keep, keepcol):  # pragma: no cover - compiled
    nc = ptr.shape[0] - 1
    filtered = reach >= 0
    restricted = keep.shape[0] > 0
    square = keepcol.shape[0] > 0
    t = np.empty((3, 3, 3))
    width = 0
    for L in range(nc):
        width = max(width, ptr[L + 1] - ptr[L])
    # where each row of the cell's nodes stands in the pattern: the columns nb come in increasing
    # order (sorted support), so every row's position only moves forward (a merge, no search)
    cur = np.empty(width, np.int64)
    for L in range(nc):
        s = ptr[L]
        e = ptr[L + 1]
        wL = w[L]
        if wL == 0.0:
            continue
        for aa in range(s, e):
            cur[aa - s] = indptr[nodes[aa]]
        for bb in range(s, e):
            nb = nodes[bb]
            if square and not keepcol[nb]:
                continue
            g0 = g[bb, 0]
            g1 = g[bb, 1]
            g2 = g[bb, 2]
            if g0 == 0.0 and g1 == 0.0 and g2 == 0.0:
                continue
            for i in range(3):
                for J in range(3):
                    for k in range(3):
                        t[i, J, k] = wL * (A[L, i, J, k, 0] * g0 + A[L, i, J, k, 1] * g1 + A[L, i, J, k, 2] * g2)
            for aa in range(s, e):
                na = nodes[aa]
                if restricted and not keep[na]:
                    continue
                h0 = g[aa, 0]
                h1 = g[aa, 1]
                h2 = g[aa, 2]
                if h0 == 0.0 and h1 == 0.0 and h2 == 0.0:
                    continue
                if filtered and _far(ijk, wide, na, nb, reach):
                    continue
                lo = cur[aa - s]
                while indices[lo] < nb:  # nb is in row na
                    lo += 1
                cur[aa - s] = lo
                for i in range(3):
                    for k in range(3):
                        data[lo, i, k] += h0 * t[i, 0, k] + h1 * t[i, 1, k] + h2 * t[i, 2, k]


@numba.njit(cache=True, nogil=True)
def _patch_vectors(ptr, nodes, g, a, wv, patch_of, pptr, pnodes, out):  # pragma: no cover - compiled
    """out[pos(p, I), i] += wv[L] Σ_k a[L, i, k] g[(L, I), k] for every cell L of patch p = patch_of[L]."""
    nc = ptr.shape[0] - 1
    for L in range(nc):
        p = patch_of[L]
        w = wv[L]
        for bb in range(ptr[L], ptr[L + 1]):
            node = nodes[bb]
            lo = _position(pnodes, pptr[p], pptr[p + 1] - 1, node)
            for i in range(3):
                out[lo, i] += w * (a[L, i, 0] * g[bb, 0] + a[L, i, 1] * g[bb, 1] + a[L, i, 2] * g[bb, 2])


@numba.njit(cache=True, nogil=True)
def _fill_rank1(pptr, pnodes, v, coef, indptr, indices, data, ijk, reach, wide, keep, keepcol):  # pragma: no cover - compiled
    """data[(I, J)] += coef[p] v[(p, I)] ⊗ v[(p, J)] for every patch p and node pair of its support."""
    npatch = pptr.shape[0] - 1
    filtered = reach >= 0
    restricted = keep.shape[0] > 0
    square = keepcol.shape[0] > 0
    for p in range(npatch):
        c = coef[p]
        if c == 0.0:
            continue
        s = pptr[p]
        e = pptr[p + 1]
        for aa in range(s, e):
            na = pnodes[aa]
            if restricted and not keep[na]:
                continue
            lo = indptr[na]  # the patch's nodes are sorted: a merge along row na
            for bb in range(s, e):
                nb = pnodes[bb]
                if square and not keepcol[nb]:
                    continue
                if filtered and _far(ijk, wide, na, nb, reach):
                    continue
                while indices[lo] < nb:
                    lo += 1
                for i in range(3):
                    ci = c * v[aa, i]
                    for k in range(3):
                        data[lo, i, k] += ci * v[bb, k]


@numba.njit(cache=True, nogil=True)
def _add_identity(indptr, indices, mptr, mind, mdata, out):  # pragma: no cover - compiled
    for r in range(indptr.size - 1):
        p, end = indptr[r], indptr[r + 1]
        if p == end:
            continue
        for q in range(mptr[r], mptr[r + 1]):
            c = mind[q]
            while p < end and indices[p] < c:
                p += 1
            if p == end:
                break
            if indices[p] == c:
                v = mdata[q]
                out[p, 0, 0] += v
                out[p, 1, 1] += v
                out[p, 2, 2] += v


def strong_entries(rows: np.ndarray, size: np.ndarray, n_rows: int, tol: float) -> np.ndarray:
    """(nnz,) bool: the entries (row ``rows``, magnitude ``size`` ≥ 0) of at least ``tol`` times their row's largest."""
    largest = np.zeros(n_rows)
    np.maximum.at(largest, rows, size)
    return size >= tol * largest[rows]


def local_rows(rows: np.ndarray, cols: np.ndarray, values: np.ndarray, own: np.ndarray, ijk: np.ndarray,
               radius: int, fixed: np.ndarray | None = None, tol: float = 0.0) -> np.ndarray:
    """Cut every row of a row-wise operator to the nodes near the row's own node, keeping its sums
    and first moments.

    A filtered stiffness that keeps only the node pairs of K = Σ_r B_rᵀ C_r B_r at most a few voxels
    apart is not positive definite in general, even where every C_r is: leaving out the far pairs of
    a sum of positive terms is not a sum of positive terms. On the 0.078-cm leg (21k nodes) the
    ±2-voxel stand-in of the displacement block has 41 negative pivots (64 with its weak blocks left
    out too), and the multigrid built on it needs more Krylov iterations the larger the model is.
    Cutting the factors instead keeps every term positive: row r of B (a cell's gradient vectors, a
    constraint point's shape functions) keeps its entries at the nodes within ``radius`` voxels of
    its own node along every axis, so that Σ_r B̂_rᵀ C_r B̂_r couples nodes at most 2 ``radius``
    voxels apart and is positive semi-definite wherever the C_r are, whatever the kept entries are.

    What is cut is spread over the kept entries of its row so that the row keeps its sum and its
    first moments Σ_e b_e (x_e − x_r) (x_e the voxel index of entry e's node, x_r the own node's):
    the cut row acts on every linear field as the whole row does. A smoothed gradient row then
    stays exact on linear displacements and a shape-function row still reproduces linear fields,
    so the stand-in gives every linear displacement field (a translation, a rotation, a
    homogeneous strain) the energy that the full-pattern product with the same C_r gives it. The spread is the smallest (least-squares)
    change of the kept entries that does it: for row r with kept entries K_r, z_e = (1, x_e − x_r),

        b̂_e = b_e + z_eᵀ λ_r (e ∈ K_r),   (Σ_{e∈K_r} z_e z_eᵀ) λ_r = Σ_{e∉K_r} z_e b_eᵀ,

    with a pseudo-inverse where the kept nodes do not span the three axes (the moments along a
    missing axis are then matched in the least-squares sense). Adding the cut entries to the own
    node alone keeps only the sums: on the first Newton system of the leg at 0.078-cm pixels that
    stand-in's V-cycle needed 46 and 54 FGMRES iterations at 21k and 74k nodes, against 39 and 42
    with the moments kept (the git history of docs/performance.md).

    ``tol`` also cuts the entries smaller than ``tol`` times the row's largest (the same way),
    which thins the pattern: on the ±2-voxel pattern of the leg 0.15 leaves ~125 of ~335 non-zeros
    per row.

    Parameters
    ----------
    rows, cols : (m,) int
        Row and node of each entry.
    values : (m,) or (m, k) float
        Entries (k values per entry, cut together).
    own : (n_rows,) int
        Each row's own node (the cell's node, the node a constraint point belongs to); every row
        must have an entry there (an explicit zero will do).
    ijk : (N, 3) int
        Voxel indices of the nodes.
    radius : int
        Voxels along each axis within which a row keeps its entries.
    fixed : (N,) bool, optional
        Nodes whose entries are never cut (enlarged RK supports, whose every pair a filtered
        pattern keeps).
    tol : float
        Entries below ``tol`` times the largest of their row (largest of their k values) are cut
        too, wherever they are.

    Returns
    -------
    ndarray, the shape of ``values``
        The cut entries: zero where cut, the kept ones changed by the spread.
    """
    rows, cols = np.asarray(rows, np.int64), np.asarray(cols, np.int64)
    v = np.asarray(values, float).reshape(rows.shape[0], -1)
    n_rows = len(own)
    at = np.asarray(own, np.int64)[rows]
    if np.any(np.bincount(rows[cols == at], minlength=n_rows) == 0):
        raise ValueError("local_rows: a row has no entry at its own node")
    ijk = np.asarray(ijk)
    offset = (ijk[cols] - ijk[at]).astype(float)  # x_e − x_r, voxels
    near = np.abs(offset).max(axis=1) <= radius
    if fixed is not None:
        near |= np.asarray(fixed, bool)[cols]
    if tol > 0.0:
        near &= strong_entries(rows, np.abs(v).max(axis=1), n_rows, tol)
    near |= cols == at
    kept, cut = np.flatnonzero(near), np.flatnonzero(~near)
    rk, rc = rows[kept], rows[cut]
    zk = np.column_stack([np.ones(kept.size), offset[kept]])  # z_e = (1, x_e − x_r)
    zc = np.column_stack([np.ones(cut.size), offset[cut]])
    del offset
    gram = np.empty((n_rows, 4, 4))
    for a in range(4):
        for b in range(a, 4):
            gram[:, a, b] = gram[:, b, a] = np.bincount(rk, zk[:, a] * zk[:, b], minlength=n_rows)
    moments = np.empty((n_rows, 4, v.shape[1]))
    for a in range(4):
        for j in range(v.shape[1]):
            moments[:, a, j] = np.bincount(rc, zc[:, a] * v[cut, j], minlength=n_rows)
    lam = np.linalg.pinv(gram, rcond=1e-10, hermitian=True) @ moments  # (n_rows, 4, k)
    out = v * near[:, None]
    out[kept] += np.einsum("ea,eaj->ej", zk, lam[rk])
    return out.reshape(np.shape(values))


#: entries :func:`local_rows_csr` cuts at a time: its transients (~130 bytes per entry) stay below
#: 0.1 GB, where the whole support of the 295k leg at once (21 M entries) held ~2.7 GB
LOCAL_CHUNK = 500_000
#: support entries per block of cells of a fill by blocks (:meth:`Assembler.cell_blocks`): its gradients
#: and their cut copy hold 48 bytes per entry (the whole layout's took 2 GB at 295k nodes)
FILL_BLOCK = 2_000_000


def local_rows_csr(ptr: np.ndarray, cols: np.ndarray, values: np.ndarray, ijk: np.ndarray, radius: int,
                   fixed: np.ndarray | None = None, tol: float = 0.0, chunk: int = LOCAL_CHUNK,
                   own: np.ndarray | None = None) -> np.ndarray:
    """:func:`local_rows` of an operator stored row by row, whole rows of about ``chunk`` entries at
    a time.

    Parameters
    ----------
    ptr : (n_rows + 1,) int
        Row r's entries are ``ptr[r]:ptr[r + 1]``.
    cols, values, ijk, radius, fixed, tol
        As :func:`local_rows` (``values`` (m,) or (m, k)).
    chunk : int
        Entries cut at a time (a row longer than that is cut alone).
    own : (n_rows,) int, optional
        Each row's own node; row r's is node r when not given (a cell's gradients: the cells are
        the nodes).

    Returns
    -------
    ndarray, the shape of ``values``
    """
    ptr = np.asarray(ptr, np.int64)
    out = np.empty(np.shape(values))
    start, n_rows = 0, len(ptr) - 1
    while start < n_rows:
        stop = min(n_rows, max(start + 1, int(np.searchsorted(ptr, ptr[start] + chunk, side="right")) - 1))
        lo, hi = ptr[start], ptr[stop]
        rows = np.repeat(np.arange(stop - start, dtype=np.int64), np.diff(ptr[start:stop + 1]))
        at = np.arange(start, stop) if own is None else own[start:stop]
        out[lo:hi] = local_rows(rows, cols[lo:hi], values[lo:hi], at, ijk, radius, fixed, tol)
        start = stop
    return out


def local_operator(M: sp.spmatrix, own: np.ndarray, ijk: np.ndarray, radius: int,
                   fixed: np.ndarray | None = None, tol: float = 0.0) -> sp.csr_matrix:
    """:func:`local_rows` of a sparse (n_rows × N) operator, as CSR (an own-node entry is added where
    a row has none)."""
    C = sp.coo_matrix(M)
    own = np.asarray(own, np.int64)
    m = M.shape[0]
    C = sp.coo_matrix((np.r_[C.data, np.zeros(m)], (np.r_[C.row, np.arange(m)], np.r_[C.col, own])), shape=M.shape)
    C.sum_duplicates()  # keeps the explicit zeros
    order = np.argsort(C.row, kind="stable")
    rows, cols = C.row[order], C.col[order]
    ptr = np.r_[0, np.cumsum(np.bincount(rows, minlength=m))]
    data = local_rows_csr(ptr, cols, C.data[order], ijk, radius, fixed, tol, own=own)
    keep = data != 0.0
    return sp.csr_matrix((data[keep], (rows[keep], cols[keep])), shape=M.shape)


def support_values(ptr: np.ndarray, nodes: np.ndarray, n_nodes: int, mats) -> np.ndarray:
    """Values of three (N_cells × N_nodes) operators on a support layout (CSR structure ``ptr``,
    ``nodes`` with sorted rows), shape (nnz(S), 3).

    Entries of ``mats[k]`` outside the support raise ``ValueError`` (a programming error).
    """
    return scatter_support(len(nodes), mats, support_positions(ptr, nodes, n_nodes, mats))


def support_positions(ptr: np.ndarray, nodes: np.ndarray, n_nodes: int, mats) -> list[np.ndarray]:
    """Where the stored entries of three (N_cells × N_nodes) operators lie in a support layout
    (CSR structure ``ptr``, ``nodes`` with sorted rows): per operator, (nnz(M_k),) int32 (int64
    above 2³¹ entries) positions in the order of its COO form (its CSR order for a CSR matrix),
    for :func:`scatter_support`. 4 bytes per operator entry, where the values on the layout take
    24 per layout entry.

    Entries of ``mats[k]`` outside the support raise ``ValueError`` (a programming error).
    """
    keys = np.repeat(np.arange(len(ptr) - 1, dtype=np.int64), np.diff(ptr)) * n_nodes + np.asarray(nodes, np.int64)
    itype = _int_dtype(keys.shape[0])
    out = []
    for M in mats:
        C = sp.coo_matrix(M)
        q = C.row.astype(np.int64) * n_nodes + C.col
        pos = np.searchsorted(keys, q)
        pos = np.minimum(pos, len(keys) - 1)
        if not np.all(keys[pos] == q):
            raise ValueError("operator has entries outside the cell supports")
        out.append(pos.astype(itype))
    return out


def scatter_support(size: int, mats, positions: list[np.ndarray]) -> np.ndarray:
    """Values of three operators on a support layout of ``size`` entries, (size, 3), from their
    :func:`support_positions` (the same numbers as :func:`support_values`)."""
    out = np.zeros((size, 3))
    for k, (M, pos) in enumerate(zip(mats, positions, strict=True)):
        np.add.at(out[:, k], pos, sp.coo_matrix(M).data)
    return out


def nonzero_blocks(K: sp.bsr_matrix) -> sp.bsr_matrix:
    """``K`` (BSR, 3 × 3 blocks) without its blocks that are all zero (a filtered pattern's pairs
    that no cut factor couples, :func:`local_rows`); the diagonal blocks stay."""
    n = K.shape[0] // 3
    rows = np.repeat(np.arange(n, dtype=np.int32), np.diff(K.indptr))
    keep = np.any(K.data != 0.0, axis=(1, 2)) | (rows == K.indices)
    if keep.all():
        return K
    indptr = np.concatenate([[0], np.cumsum(np.bincount(rows[keep], minlength=n))])
    return sp.bsr_matrix((K.data[keep], K.indices[keep], indptr), shape=K.shape)


def _int_dtype(n: int):
    return np.int32 if n < np.iinfo(np.int32).max else np.int64


def support_pattern(incidence: list, psi_faces: sp.spmatrix) -> sp.csr_matrix:
    """Cell–node support incidence S (N_cells × N_nodes): S[L, I] = 1 where Ψ_I is non-zero on a face of Ω_L.

    Built from the structure (not the values) of the face–cell incidence and of Ψ at the faces,
    so that no entry is lost to an exact cancellation.
    """
    D = abs(incidence[0]) + abs(incidence[1]) + abs(incidence[2])
    D.data[:] = 1.0
    Pf = sp.csr_matrix(psi_faces, copy=True)
    Pf.data[:] = 1.0
    S = (D @ Pf).tocsr()
    S.sort_indices()
    return sp.csr_matrix((np.ones(S.nnz, np.float32), S.indices, S.indptr), shape=S.shape)  # 4-byte ones


class Assembler:
    """Fixed block pattern of the stiffness and a compiled value fill.

    Parameters
    ----------
    support : CSR (N_cells, N_nodes)
        Cell–node support incidence (:func:`support_pattern`); its sorted column indices per row
        are the nodes whose gradient vectors enter cell L.
    ijk : (N_nodes, 3) int, optional
        Voxel indices of the nodes; needed with ``reach``.
    reach : int, optional
        Keep only the blocks of node pairs at most ``reach`` voxels apart along every axis
        (a *filtered* stiffness, used to build preconditioners: :mod:`.linsolve`). The fill then
        skips the other pairs, and :meth:`align_scalar` drops entries outside the pattern.
    wide : (N_nodes,) bool, optional
        Nodes whose every pair is kept in a filtered pattern (nodes with enlarged RK supports,
        which couple further than the nominal support).
    patches : CSR (N_patches, N_cells), optional
        Patch–cell membership of a projected volumetric energy (:mod:`.volumetric`): the pattern
        then also holds every node pair in the support of one patch (its rank-one term,
        :meth:`fill_patches`).
    rows : (n,) int, optional
        Keep only the block rows of these nodes (the others stay empty, and the fills skip them):
        the rows of a subset of the nodes without the memory of the whole pattern.
    square : bool
        With ``rows``: keep only the blocks whose column node is one of them too (the diagonal
        block K_RR of the node set R, which is what a factorisation on R needs).
    local_tol : float
        With ``reach``: the ``tol`` of :func:`local_rows` in :meth:`local` (the fills of a
        filtered pattern).
    pattern : sparse (N × N), optional
        The node pairs to hold, in place of every pair that shares a cell's support (a filtered
        pattern of cut factors: only the pairs they couple). A fill must not reach outside it.

    Attributes
    ----------
    indptr, indices : int32 arrays
        Block-CSR structure of the N × N block pattern (3×3 blocks), columns sorted.
    """

    def __init__(self, support: sp.csr_matrix, ijk: np.ndarray | None = None, reach: int | None = None,
                 wide: np.ndarray | None = None, patches: sp.csr_matrix | None = None, rows: np.ndarray | None = None,
                 square: bool = False, local_tol: float = 0.0, pattern: sp.spmatrix | None = None):
        self.local_tol = float(local_tol)
        S = sp.csr_matrix(support)
        S.sort_indices()
        self.n_cells, self.n_nodes = S.shape
        it = _int_dtype(max(S.nnz, self.n_nodes))
        self.ptr = S.indptr.astype(it)
        self.nodes = S.indices.astype(it)
        Sb = sp.csr_matrix((np.ones(S.nnz, np.float32), S.indices, S.indptr), shape=S.shape)
        P = (Sb.T.tocsr() @ Sb).tocsr() if pattern is None else sp.csr_matrix(pattern, dtype=np.float32)
        self.pptr = self.pnodes = None
        if patches is not None:
            M = sp.csr_matrix(patches, dtype=np.float32, copy=True)
            M.data[:] = 1.0
            Sp = (M @ Sb).tocsr()
            Sp.data[:] = 1.0
            Sp.sort_indices()
            P = (P + Sp.T.tocsr() @ Sp).tocsr()
            itp = _int_dtype(max(Sp.nnz, self.n_nodes))
            self.pptr = Sp.indptr.astype(itp)
            self.pnodes = Sp.indices.astype(itp)
            del Sp, M
        del Sb
        self.keep = np.zeros(0, np.bool_)
        self.keepcol = np.zeros(0, np.bool_)
        if rows is not None:
            self.keep = np.zeros(self.n_nodes, np.bool_)
            self.keep[np.asarray(rows, np.int64)] = True
            sel = np.repeat(self.keep, np.diff(P.indptr))
            if square:
                self.keepcol = self.keep
                sel &= self.keep[P.indices]
            counts = np.bincount(np.repeat(np.arange(self.n_nodes), np.diff(P.indptr))[sel], minlength=self.n_nodes)
            P = sp.csr_matrix((P.data[sel], P.indices[sel], np.concatenate([[0], np.cumsum(counts)])), shape=P.shape)
            del sel, counts
        P.sort_indices()
        self.reach = -1 if reach is None else int(reach)
        if self.reach >= 0:
            if ijk is None:
                raise ValueError("a filtered pattern (reach) needs the voxel indices ijk")
            self.ijk = np.ascontiguousarray(ijk, dtype=np.int32)
            rows = np.repeat(np.arange(self.n_nodes, dtype=np.int32), np.diff(P.indptr))
            near = np.ones(rows.shape[0], bool)
            for ax in range(3):  # per axis: no (nnzb, 3) temporaries
                c = self.ijk[:, ax]
                near &= np.abs(c[rows] - c[P.indices]) <= self.reach
            self.wide = np.zeros(self.n_nodes, np.bool_) if wide is None else np.asarray(wide, np.bool_)
            near |= self.wide[rows] | self.wide[P.indices]
            indptr = np.concatenate([[0], np.cumsum(np.bincount(rows[near], minlength=self.n_nodes))])
            indices = P.indices[near]
            del rows, near
        else:
            self.ijk = np.zeros((1, 3), np.int32)
            self.wide = np.zeros(1, np.bool_)
            indptr, indices = P.indptr, P.indices
        del P
        it = _int_dtype(max(len(indices), self.n_nodes))
        self.indptr = np.asarray(indptr).astype(it)
        self.indices = np.asarray(indices).astype(it)
        self._parts = None

    @property
    def nnzb(self) -> int:
        """Number of 3×3 blocks in the pattern."""
        return int(self.indices.shape[0])

    @property
    def nnz(self) -> int:
        """Number of scalar non-zeros (9 per block)."""
        return 9 * self.nnzb

    def zeros(self) -> np.ndarray:
        """Empty block data, shape (nnzb, 3, 3)."""
        return np.zeros((self.nnzb, 3, 3))

    def on_support(self, mats) -> np.ndarray:
        """Values of three (N_cells × N_nodes) operators on the support layout, shape (nnz(S), 3)
        (:func:`support_values`)."""
        return support_values(self.ptr, self.nodes, self.n_nodes, mats)

    def fill(self, g: np.ndarray, A: np.ndarray, w: np.ndarray, out: np.ndarray | None = None,
             cells: tuple[int, int] | None = None) -> np.ndarray:
        """Add Σ_L w_L B̃_Lᵀ A_L B̃_L to block data.

        Parameters
        ----------
        g : (nnz(S), 3) float
            Gradient vectors g_I(L) on the support layout (:meth:`on_support`), cm⁻¹; with
            ``cells``, those of the cells' entries of the layout only.
        A : (N_cells, 3, 3, 3, 3) float
            Tangent A[L, i, J, k, L'] = ∂P_iJ/∂F_kL', N/cm².
        w : (N_cells,) float
            Integration weights (cell volumes, cm³).
        out : (nnzb, 3, 3) float, optional
            Data to add to (a new zero array when omitted).
        cells : (c0, c1), optional
            Add the cells c0 ≤ L < c1 only (:meth:`cell_blocks`: a fill by blocks of cells holds
            one block's gradients, not the whole layout's).

        Returns
        -------
        (nnzb, 3, 3) float
            Block values of the stiffness, N/cm.
        """
        if out is None:
            out = self.zeros()
        c0, c1 = (0, self.n_cells) if cells is None else (int(cells[0]), int(cells[1]))
        ptr, nodes = self._cell_layout(c0, c1)
        g, A, w = (np.ascontiguousarray(x, dtype=np.float64) for x in (g, A[c0:c1], w[c0:c1]))
        if self.reach >= 0:
            g = np.ascontiguousarray(self.local(g, (c0, c1)))
        run_parts(lambda keep: _fill(ptr, nodes, g, A, w, self.indptr, self.indices, out, self.ijk, self.reach,
                                     self.wide, keep, self.keepcol), self._row_parts())
        return out

    def _cell_layout(self, c0: int, c1: int) -> tuple[np.ndarray, np.ndarray]:
        """The support layout of the cells c0 ≤ L < c1: row pointers from 0 and their nodes (views)."""
        if c0 == 0 and c1 == self.n_cells:
            return self.ptr, self.nodes
        lo, hi = self.ptr[c0], self.ptr[c1]
        return (self.ptr[c0:c1 + 1] - lo).astype(self.ptr.dtype, copy=False), self.nodes[lo:hi]

    def cell_blocks(self, entries: int | None = None) -> list[tuple[int, int]]:
        """Contiguous ranges (c0, c1) of cells of about ``entries`` (default :data:`FILL_BLOCK`)
        support entries each (a cell with more is a range alone)."""
        return self.blocks_of(self.ptr, entries)

    @staticmethod
    def blocks_of(ptr: np.ndarray, entries: int | None = None) -> list[tuple[int, int]]:
        """Contiguous ranges (r0, r1) of the rows of a CSR layout with row pointers ``ptr``, of about
        ``entries`` (default :data:`FILL_BLOCK`) entries each (a row with more is a range alone)."""
        entries = FILL_BLOCK if entries is None else int(entries)
        ptr = np.asarray(ptr, np.int64)
        n = ptr.size - 1
        out, start = [], 0
        while start < n:
            stop = min(n, max(start + 1, int(np.searchsorted(ptr, ptr[start] + entries, side="right")) - 1))
            out.append((start, stop))
            start = stop
        return out

    def local(self, g: np.ndarray, cells: tuple[int, int] | None = None) -> np.ndarray:
        """Values on the support layout with each cell's row cut to the nodes within ``reach // 2``
        voxels of the cell (:func:`local_rows`; the cells are the nodes), so that a filtered fill
        Σ_L w_L B̂_Lᵀ A_L B̂_L is positive semi-definite wherever A is; with ``cells`` (c0, c1),
        ``g`` holds those cells' entries only."""
        if self.n_cells != self.n_nodes:
            raise ValueError("a filtered fill needs one cell per node")
        c0, c1 = (0, self.n_cells) if cells is None else (int(cells[0]), int(cells[1]))
        ptr, nodes = self._cell_layout(c0, c1)
        return local_rows_csr(ptr, nodes, g, self.ijk, self.reach // 2, self.wide, self.local_tol,
                              own=None if cells is None else np.arange(c0, c1))

    def _row_parts(self) -> list[np.ndarray]:
        """Row masks of the fills, one per thread: contiguous node ranges of about equal numbers of
        blocks (within the kept rows). Each thread adds only to its own rows, so the threads of one
        fill never write to the same block, and the sums do not depend on the number of threads."""
        k = thread_count()
        if self._parts is None or len(self._parts) != k:
            if k == 1 or 9 * self.nnzb < MIN_NNZ:
                self._parts = [self.keep]
            else:
                cuts = np.searchsorted(self.indptr, np.linspace(0, self.nnzb, k + 1)[1:-1])
                owner = np.searchsorted(cuts, np.arange(self.n_nodes), side="right")
                base = self.keep if self.keep.size else np.ones(self.n_nodes, np.bool_)
                self._parts = [base & (owner == t) for t in range(k)]
        return self._parts

    def patch_vectors(self, g: np.ndarray, a: np.ndarray, wv: np.ndarray, patch_of: np.ndarray) -> np.ndarray:
        """Vectors g_p = Σ_{L∈p} wv_L B̃_Lᵀ a_L of the patches on the patch-support layout.

        Parameters
        ----------
        g : (nnz(S), 3) float
            Gradient vectors on the support layout (:meth:`on_support`), cm⁻¹.
        a : (N_cells, 3, 3) float
            a_L = J_L F_L⁻ᵀ.
        wv : (N_cells,) float
            Weights V_L / V_p.
        patch_of : (N_cells,) int
            Patch of every cell.

        Returns
        -------
        (nnz(S_p), 3) float
            ``[pos(p, I), i]`` = component i of g_p at node I, cm⁻¹.
        """
        out = np.zeros((self.pnodes.shape[0], 3))
        _patch_vectors(self.ptr, self.nodes, np.ascontiguousarray(g, np.float64), np.ascontiguousarray(a, np.float64),
                       np.ascontiguousarray(wv, np.float64), np.ascontiguousarray(patch_of, np.int64), self.pptr,
                       self.pnodes, out)
        return out

    def fill_patches(self, v: np.ndarray, coef: np.ndarray, out: np.ndarray) -> np.ndarray:
        """Add Σ_p coef_p g_p g_pᵀ (patch vectors ``v`` from :meth:`patch_vectors`) to block data."""
        v, coef = np.ascontiguousarray(v, np.float64), np.ascontiguousarray(coef, np.float64)
        run_parts(lambda keep: _fill_rank1(self.pptr, self.pnodes, v, coef, self.indptr, self.indices, out, self.ijk,
                                           self.reach, self.wide, keep, self.keepcol), self._row_parts())
        return out

    def block_positions(self, brow: np.ndarray, bcol: np.ndarray, missing: str = "raise") -> np.ndarray:
        """Positions of blocks (brow, bcol) in the pattern.

        A block outside the pattern raises ``ValueError`` (``missing="raise"``) or gets position −1
        (``missing="mark"``; what a filtered pattern does with far pairs).
        """
        # the block rows are made for each call, not kept (8 bytes per block: 0.09 GB at 295k nodes)
        keys = np.repeat(np.arange(self.n_nodes, dtype=np.int64) * self.n_nodes, np.diff(self.indptr)) + self.indices
        q = np.asarray(brow, np.int64) * self.n_nodes + np.asarray(bcol, np.int64)
        pos = np.minimum(np.searchsorted(keys, q), len(keys) - 1)
        found = keys[pos] == q
        if missing == "mark":
            return np.where(found, pos, -1)
        if not np.all(found):
            raise ValueError("matrix has entries outside the stiffness pattern")
        return pos

    def align_scalar(self, M: sp.spmatrix, i: int, k: int, out: np.ndarray) -> np.ndarray:
        """Add an (N × N) matrix to component (i, k) of every block: K[3I+i, 3J+k] += M[I, J].

        On a filtered pattern (``reach``) the entries between far nodes are dropped.
        """
        C = sp.coo_matrix(M)
        pos = self.block_positions(C.row, C.col, missing="mark" if self.reach >= 0 or self.keep.size else "raise")
        keep = pos >= 0
        np.add.at(out[:, i, k], pos[keep], C.data[keep])
        return out

    def add_identity_blocks(self, M: sp.csr_matrix, out: np.ndarray) -> np.ndarray:
        """Add M ⊗ I₃ (M an N × N CSR with sorted column indices) to the block data: K[3I+j, 3J+j] +=
        M[I, J] for j = 0, 1, 2, for every block (I, J) of the pattern; the entries of M outside the
        pattern (far pairs of a filtered pattern, rows or columns left out) are dropped. One merge of
        sorted rows, O(nnz(M) + nnzb)."""
        M = sp.csr_matrix(M)
        if not M.has_sorted_indices:
            M = M.sorted_indices()
        _add_identity(self.indptr, self.indices, M.indptr, M.indices, M.data, out)
        return out

    def align(self, M: sp.spmatrix, out: np.ndarray) -> np.ndarray:
        """Add a (3N × 3N) scalar matrix to block data."""
        C = sp.coo_matrix(M)
        pos = self.block_positions(C.row // 3, C.col // 3)
        np.add.at(out, (pos, C.row % 3, C.col % 3), C.data)
        return out

    def matrix(self, data: np.ndarray) -> sp.bsr_matrix:
        """Block-CSR matrix (3N × 3N) over the pattern with the given block values (no copy)."""
        n = 3 * self.n_nodes
        return sp.bsr_matrix((data, self.indices, self.indptr), shape=(n, n), blocksize=(3, 3))

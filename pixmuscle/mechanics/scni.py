"""Stabilised conforming nodal integration (SCNI) on voxel cells (paper §3, eqs. 16–19).

SCNI (Chen, Wu, Yoon & You 2001, IJNME 50:435–466; Chen, Yoon & Wu 2002, IJNME 53:2587–2615)
integrates the Galerkin equations at the nodes, replacing the shape-function gradient at node L by
its average over the node's integration cell Ω_L, turned into a boundary integral by the
divergence theorem:

    b̃_Ik(X_L) = (1/V_L) ∫_{Ω_L} Ψ_I,k dΩ = (1/V_L) ∮_{∂Ω_L} Ψ_I n_k dΓ.

In the pixel-point model every node sits at a voxel centre and its cell is its voxel, the box
``X_L ± spacing/2`` (docs/architecture.md, "Model frame"). The cells tile the tissue exactly, and
two face-neighbouring cells share one face. We enumerate the *unique* faces of the grid per axis —
interior faces between ijk-neighbours and boundary faces of cells without a neighbour — and
evaluate Ψ once at each face centre. With the face–cell incidence matrix D_k (N_cells × N_faces,
entry ±A_f/V_L: + for the cell on the low side of the face, whose outward normal is +e_k, − for
the cell on the high side) the smoothed gradient operators are sparse products

    G_k = D_k Ψ(faces),  G_k[L, I] = b̃_Ik(X_L),  k = 1, 2, 3.

One-point quadrature per face is exact for linear fields: with a linear basis the RK approximation
reproduces any linear u exactly at every point (eq. 5), so u^h is linear on each face, and the
face-centre (midpoint) rule integrates a linear function over a rectangle exactly. Hence G_k
reproduces constant gradients (∇u for u = A X + c) to round-off. Because every interior face is
evaluated once and enters its two cells with opposite signs, the discrete divergence theorem

    Σ_L V_L b̃_Ik(X_L) = Σ_{boundary faces f} A_f n_k(f) Ψ_I(x_f)

holds exactly (the "integration constraint" that makes SCNI pass the linear patch test).

On chosen boundary faces (``vertex_faces``: the end faces whose penalty is integrated at their
vertices, ``penalty.at`` ``auto`` or ``vertices``) the face value is the trapezoidal rule instead,
Ψ̄_I(f) = (1/4) Σ_{4 vertices v} Ψ_I(x_v). It too integrates a linear function over a rectangle
exactly, so G_k still reproduces constant gradients, and a boundary face belongs to one cell only,
so the integration constraint holds with Ψ̄ in place of Ψ(x_f). The boundary rows
Σ_f A_f Ψ̄_I(f) are then the penalty rows Σ_v w_v Ψ_I(x_v) of the vertex rule, and a homogeneous
deformation is reproduced with a gap ∝ 1/β.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import scipy.sparse as sp

from ..errors import InputError


@dataclasses.dataclass
class Faces:
    """Unique faces of the voxel cells.

    Attributes
    ----------
    centre : (F, 3) float64
        Face centres, cm.
    axis : (F,) int8
        Axis k of the face normal.
    low, high : (F,) int32
        Cell on the low (−e_k) and high (+e_k) side of the face; −1 on the boundary.
    area : (F,) float64
        Face area, cm².
    plus, minus : (3, N) int32
        Index of each cell's +e_k and −e_k face per axis k (every cell has all six faces).
    """

    centre: np.ndarray
    axis: np.ndarray
    low: np.ndarray
    high: np.ndarray
    area: np.ndarray
    plus: np.ndarray
    minus: np.ndarray

    @property
    def boundary(self) -> np.ndarray:
        """(F,) bool: faces with a cell on one side only."""
        return (self.low < 0) | (self.high < 0)

    def cell_of(self, face: np.ndarray) -> np.ndarray:
        """(F_b,) int64: the cell of each boundary face in ``face`` (its only cell)."""
        face = np.asarray(face, np.int64)
        return np.where(self.low[face] >= 0, self.low[face], self.high[face]).astype(np.int64)

    @property
    def normal_sign(self) -> np.ndarray:
        """(F,) float: +1 where the face's outward normal (boundary faces) is +e_k, −1 for −e_k, 0 inside."""
        return np.where(self.high < 0, 1.0, np.where(self.low < 0, -1.0, 0.0))


def neighbour_index(ijk: np.ndarray, offset) -> np.ndarray:
    """Index of the node at ``ijk + offset`` for every node, −1 where there is none.

    Parameters
    ----------
    ijk : (N, 3) int
        Voxel indices of the nodes (unique).
    offset : (3,) int

    Returns
    -------
    (N,) int32
    """
    ijk = np.asarray(ijk, dtype=np.int64)
    lo = ijk.min(axis=0) - 1
    dims = ijk.max(axis=0) - lo + 2
    keys = np.ravel_multi_index((ijk - lo).T, dims)
    order = np.argsort(keys, kind="stable")
    sorted_keys = keys[order]
    if np.any(np.diff(sorted_keys) == 0):
        raise InputError("model nodes: two nodes share the same voxel index ijk; expected one node per voxel")
    q = np.ravel_multi_index((ijk + np.asarray(offset, np.int64) - lo).T, dims)
    pos = np.clip(np.searchsorted(sorted_keys, q), 0, len(sorted_keys) - 1)
    found = sorted_keys[pos] == q
    return np.where(found, order[pos], -1).astype(np.int32)


def cell_faces(X: np.ndarray, ijk: np.ndarray, spacing) -> Faces:
    """Enumerate the unique faces of the voxel cells of the nodes.

    Parameters
    ----------
    X : (N, 3) float
        Node coordinates (voxel centres), cm.
    ijk : (N, 3) int
        Voxel indices.
    spacing : (3,) float
        Cell edge lengths, cm.

    Returns
    -------
    Faces
        Per axis: interior faces (one per pair of ijk-neighbours), then boundary faces on the high
        side, then boundary faces on the low side.
    """
    X = np.asarray(X, float)
    h = np.asarray(spacing, float)
    n = X.shape[0]
    centres, axes, lows, highs, areas = [], [], [], [], []
    plus = np.empty((3, n), np.int32)
    minus = np.empty((3, n), np.int32)
    start = 0
    cells = np.arange(n, dtype=np.int32)
    for k in range(3):
        e = np.zeros(3, np.int64)
        e[k] = 1
        up = neighbour_index(ijk, e)
        down = neighbour_index(ijk, -e)
        inner = up >= 0
        top = ~inner
        bottom = down < 0
        lo = np.concatenate([cells[inner], cells[top], np.full(bottom.sum(), -1, np.int32)])
        hi = np.concatenate([up[inner], np.full(top.sum(), -1, np.int32), cells[bottom]])
        shift = np.zeros(3)
        shift[k] = h[k] / 2
        c = np.concatenate([X[inner] + shift, X[top] + shift, X[bottom] - shift])
        nf = len(lo)
        idx = np.arange(start, start + nf, dtype=np.int32)
        # every cell is the low side of exactly one face (interior or top) and the high side of one
        has_low = lo >= 0
        plus[k, lo[has_low]] = idx[has_low]
        has_high = hi >= 0
        minus[k, hi[has_high]] = idx[has_high]
        centres.append(c)
        axes.append(np.full(nf, k, np.int8))
        lows.append(lo)
        highs.append(hi)
        areas.append(np.full(nf, np.prod(h) / h[k]))
        start += nf
    return Faces(
        centre=np.concatenate(centres), axis=np.concatenate(axes), low=np.concatenate(lows),
        high=np.concatenate(highs), area=np.concatenate(areas), plus=plus, minus=minus,
    )


def cell_corners(X: np.ndarray, spacing) -> np.ndarray:
    """The distinct corners of the voxel cells of the nodes (each cell ``X_I ± spacing/2``).

    Parameters
    ----------
    X : (N, 3) float
        Node coordinates (voxel centres), cm.
    spacing : (3,) float
        Cell edge lengths, cm.

    Returns
    -------
    (P, 3) float64
        Cell corners, cm, each once (sorted by their half-voxel grid index).
    """
    X = np.asarray(X, float)
    h = np.asarray(spacing, float)
    if X.shape[0] == 0:
        return np.zeros((0, 3))
    offsets = np.array([[a, b, c] for a in (-1, 1) for b in (-1, 1) for c in (-1, 1)], np.int64)
    base = X.min(axis=0)
    half = np.rint(2 * (X - base) / h).astype(np.int64)          # node index on the half-voxel grid
    key = (half[:, None, :] + offsets[None]).reshape(-1, 3)
    key = np.unique(key, axis=0)
    return base + key * (h / 2)


def face_vertex_rule(faces: Faces, vertex_faces: np.ndarray, spacing) -> tuple[np.ndarray, sp.csr_matrix]:
    """Trapezoidal rule on chosen faces: their distinct vertices and the averaging matrix.

    Parameters
    ----------
    faces : Faces
    vertex_faces : (F_v,) int
        Faces (indices into ``faces``) whose value is the mean over their four vertices.
    spacing : (3,) float
        Cell edge lengths, cm.

    Returns
    -------
    points : (V, 3) float
        The distinct vertices of ``vertex_faces``, cm.
    rule : CSR (F_v, V)
        1/4 at each of the four vertices of each face: face value = ``rule @`` (values at ``points``).
    """
    h = np.asarray(spacing, float)
    vf = np.asarray(vertex_faces, np.int64)
    # the two in-plane axes of each axis-k face and the four corner offsets (±1/2, ±1/2) along them
    sign = np.array([[-1, -1], [1, -1], [-1, 1], [1, 1]], float) / 2
    offsets = np.zeros((3, 4, 3))
    for k in range(3):
        i, j = [a for a in range(3) if a != k]
        offsets[k][:, [i, j]] = sign * h[[i, j]]
    pts = (faces.centre[vf][:, None, :] + offsets[faces.axis[vf]]).reshape(-1, 3)
    if pts.shape[0] == 0:
        return pts, sp.csr_matrix((0, 0))
    key = np.rint(2 * (pts - pts.min(axis=0)) / h).astype(np.int64)   # half-voxel grid index
    _, first, inv = np.unique(key, axis=0, return_index=True, return_inverse=True)
    rule = sp.csr_matrix((np.full(4 * vf.size, 0.25), (np.repeat(np.arange(vf.size), 4), inv.ravel())),
                         shape=(vf.size, first.size))
    return pts[first], rule


def replace_rows(A: sp.spmatrix, rows: np.ndarray, B: sp.spmatrix) -> sp.csr_matrix:
    """``A`` with its rows ``rows`` replaced by the rows of ``B`` (stored entries kept as they are).

    Parameters
    ----------
    A : sparse (F, N)
    rows : (R,) int, distinct
    B : sparse (R, N)

    Returns
    -------
    CSR (F, N)
    """
    A = sp.csr_matrix(A)
    rows = np.asarray(rows, np.int64)
    kept = np.setdiff1d(np.arange(A.shape[0]), rows)
    order = np.empty(A.shape[0], np.int64)
    order[kept] = np.arange(kept.size)
    order[rows] = kept.size + np.arange(rows.size)
    return sp.vstack([A[kept], sp.csr_matrix(B)], format="csr")[order]


def apply_rule(rule: sp.csr_matrix, values: sp.spmatrix) -> sp.csr_matrix:
    """``rule @ values`` keeping every stored entry of the rows it combines (explicit zeros too).

    SciPy's sparse product drops entries that come out 0, so Ψ (exactly 0 at some points where
    ∂Ψ is not) would lose entries that its gradients keep; the assembly needs one pattern for both.

    Parameters
    ----------
    rule : CSR (F, P)
    values : sparse (P, N)

    Returns
    -------
    CSR (F, N)
    """
    R = rule.tocoo()
    M = sp.csr_matrix(values)
    start, stop = M.indptr[R.col], M.indptr[R.col + 1]
    count = stop - start
    entry = np.repeat(start - np.concatenate([[0], np.cumsum(count)[:-1]]), count) + np.arange(count.sum())
    rows = np.repeat(R.row, count)
    out = sp.coo_matrix((np.repeat(R.data, count) * M.data[entry], (rows, M.indices[entry])),
                        shape=(rule.shape[0], M.shape[1])).tocsr()
    out.sort_indices()
    return out


def face_incidence(faces: Faces, volume: np.ndarray) -> list[sp.csr_matrix]:
    """Face–cell incidence matrices D_k with entries ±A_f/V_L (cm⁻¹).

    Parameters
    ----------
    faces : Faces
    volume : (N,) float
        Cell volumes V_L, cm³.

    Returns
    -------
    list of 3 CSR matrices, shape (N, F)
        ``D_k[L, f] = +A_f/V_L`` if L is the low-side cell of the axis-k face f (outward normal
        +e_k), ``−A_f/V_L`` if L is its high-side cell, 0 otherwise.
    """
    n = volume.shape[0]
    nf = faces.centre.shape[0]
    out = []
    fidx = np.arange(nf)
    for k in range(3):
        on = faces.axis == k
        lo_ok = on & (faces.low >= 0)
        hi_ok = on & (faces.high >= 0)
        rows = np.concatenate([faces.low[lo_ok], faces.high[hi_ok]])
        cols = np.concatenate([fidx[lo_ok], fidx[hi_ok]])
        vals = np.concatenate([faces.area[lo_ok] / volume[faces.low[lo_ok]], -faces.area[hi_ok] / volume[faces.high[hi_ok]]])
        out.append(sp.csr_matrix((vals, (rows, cols)), shape=(n, nf)))
    return out


def smoothed_gradients(incidence: list[sp.csr_matrix], psi_faces: sp.csr_matrix) -> StackedRows:
    """SCNI smoothed gradient operators G_k = D_k Ψ(faces) (N_cells × N_nodes, cm⁻¹).

    ``(G_k @ u)[L]`` is the cell average of ∂u^h/∂X_k over Ω_L for nodal coefficients ``u``
    (paper eq. 17 with Ψ_I,k replaced by the smoothed b̃_Ik). The three are row blocks of one
    stacked CSR matrix (:class:`StackedRows`), which the matrix-free tangent uses as it is.
    """
    out = []
    for D in incidence:
        G = (D @ psi_faces).tocsr()
        G.sort_indices()
        out.append(G)
    return StackedRows(out)


class StackedRows(list):
    """Sparse operators of equal width as row blocks of one CSR matrix: a list of the blocks, each
    a CSR matrix on views of the stacked matrix's arrays, so that the blocks and the stack
    (:attr:`stacked`, what :class:`~.tangent.ProductForm` multiplies with) are held once.

    Parameters
    ----------
    mats : sequence of sparse (n_k × N)

    Attributes
    ----------
    stacked : CSR (Σ n_k × N)
        The blocks one above the other; 32-bit indices where they fit.
    """

    def __init__(self, mats):
        B = sp.vstack([sp.csr_matrix(M) for M in mats], format="csr")
        B.sort_indices()
        if B.nnz < np.iinfo(np.int32).max and max(B.shape) < np.iinfo(np.int32).max:
            B.indices = B.indices.astype(np.int32, copy=False)
            B.indptr = B.indptr.astype(np.int32, copy=False)
        self.stacked = B
        lo = 0
        blocks = []
        for M in mats:
            blocks.append(_row_view(B, lo, lo + M.shape[0]))
            lo += M.shape[0]
        super().__init__(blocks)


def _row_view(A: sp.csr_matrix, lo: int, hi: int) -> sp.csr_matrix:
    """Rows ``lo:hi`` of the CSR ``A`` on views of its index and value arrays (only the row
    pointers are new; SciPy's own slicing copies)."""
    s, e = A.indptr[lo], A.indptr[hi]
    blk = sp.csr_matrix((hi - lo, A.shape[1]), dtype=A.dtype)
    blk.indptr = (A.indptr[lo:hi + 1] - s).astype(A.indices.dtype, copy=False)
    blk.indices, blk.data = A.indices[s:e], A.data[s:e]
    blk.has_sorted_indices = True
    return blk


@dataclasses.dataclass
class SCNI:
    """Nodal integration data of a pixel-point model.

    Attributes
    ----------
    G : StackedRows of 3 CSR (N, N)
        Smoothed gradient operators, cm⁻¹: ``G[k][L, I] = b̃_Ik(X_L)``; row blocks of one stacked
        CSR matrix (``G.stacked``, 3N × N), which the matrix-free tangent multiplies with.
    volume : (N,) float
        Cell volumes V_L, cm³.
    faces : Faces
    psi_faces : CSR (F, N) or None
        Ψ_I on each face: at its centre, or the mean over its vertices on the ``vertex_faces`` of
        :func:`build_scni`; None once a mechanical system has made its support pattern from it
        (nothing else needs it after the gradients are built).
    dpsi_faces : list of 3 CSR (F, N) or None
        ∂Ψ_I/∂X_k on each face, by the same rule (needed by the NSNI stabilisation).
    spacing : (3,) float, cm
    support : (3,) or (N, 3) float, cm
        RK support radius per axis.
    """

    G: list
    volume: np.ndarray
    faces: Faces
    psi_faces: sp.csr_matrix | None
    dpsi_faces: list | None
    spacing: np.ndarray
    support: np.ndarray

    @property
    def n_nodes(self) -> int:
        return int(self.volume.shape[0])

    def deformation_gradient(self, d: np.ndarray) -> np.ndarray:
        """Smoothed deformation gradient F_L = I + Σ_I d_I ⊗ b̃_I(X_L) (eq. 16), shape (N, 3, 3).

        ``F[L, i, J] = δ_iJ + (G_J @ d)[L, i]`` for coefficients ``d`` (N, 3) in cm.
        """
        F = np.empty((self.n_nodes, 3, 3))
        for J in range(3):
            F[:, :, J] = self.G[J] @ d
        F[:, 0, 0] += 1.0
        F[:, 1, 1] += 1.0
        F[:, 2, 2] += 1.0
        return F

    def internal_force(self, P: np.ndarray) -> np.ndarray:
        """Internal force f_I = Σ_L V_L P_L b̃_I(X_L) (eq. 19), N, shape (N, 3).

        Parameters
        ----------
        P : (N, 3, 3) float
            First Piola–Kirchhoff stress at the nodes, N/cm².
        """
        f = np.zeros((self.n_nodes, 3))
        VP = P * self.volume[:, None, None]
        for J in range(3):
            f += self.G[J].T @ VP[:, :, J]
        return f


def support_radius(spacing, a_over_h) -> np.ndarray:
    """RK support radius per axis, a = (a/h) · spacing (cm), shape (3,)."""
    a = np.asarray(a_over_h, float) * np.asarray(spacing, float)
    if a.shape != (3,) or np.any(a <= 0):
        raise InputError(f"support: expected 3 positive values of a/h and spacing, got a = {a}")
    return a


def build_scni(X, ijk, spacing, support, *, kernel="cubic", order=1, support_shape="box", face_gradients=False,
               vertex_faces=None, faces: Faces | None = None, singular: str = "raise") -> SCNI:
    """Build the SCNI operators of a pixel-point model.

    Parameters
    ----------
    X : (N, 3) float
        Node coordinates (voxel centres), cm.
    ijk : (N, 3) int
        Voxel indices (cells are ``X ± spacing/2``).
    spacing : (3,) float
        Voxel size, cm.
    support : (3,) or (N, 3) float
        RK support radius per axis, cm (see :func:`support_radius`).
    kernel, order, support_shape
        Passed to :func:`pixmuscle.rk.shape_functions`.
    face_gradients : bool
        Also keep ∂Ψ/∂X_k on the faces (for the NSNI stabilisation).
    vertex_faces : (F_v,) int, optional
        Boundary faces whose value is the mean over their four vertices (trapezoidal rule, for Ψ
        and ∂Ψ/∂X_k) instead of the value at their centre: the end faces that the penalty holds at
        their vertices (:func:`pixmuscle.mechanics.boundary.vertex_rule_faces`).
    faces : Faces, optional
        ``cell_faces(X, ijk, spacing)`` when already built (``vertex_faces`` index into it).
    singular : {"raise", "empty"}
        Face points with a singular moment matrix: an error, or rows without entries
        (:func:`pixmuscle.rk.shape_functions`; a rank's cells beyond its exact zone).

    Returns
    -------
    SCNI
    """
    from ..rk import shape_functions

    X = np.asarray(X, float)
    h = np.asarray(spacing, float)
    if faces is None:
        faces = cell_faces(X, ijk, h)
    volume = np.full(X.shape[0], float(np.prod(h)))
    kw = dict(kernel=kernel, order=order, support_shape=support_shape, gradient=face_gradients, singular=singular)
    res = shape_functions(X, faces.centre, support, **kw)
    psi, dpsi = (res[0], list(res[1])) if face_gradients else (res, None)
    vf = np.unique(np.asarray([] if vertex_faces is None else vertex_faces, np.int64))
    if vf.size:
        points, rule = face_vertex_rule(faces, vf, h)
        res = shape_functions(X, points, support, **kw)
        psi_v, dpsi_v = (res[0], res[1]) if face_gradients else (res, None)
        psi = replace_rows(psi, vf, apply_rule(rule, psi_v))
        if face_gradients:
            dpsi = [replace_rows(g, vf, apply_rule(rule, gv)) for g, gv in zip(dpsi, dpsi_v, strict=True)]
    if face_gradients:
        dpsi = [sp.csr_matrix(g) for g in dpsi]
    psi = sp.csr_matrix(psi)
    G = smoothed_gradients(face_incidence(faces, volume), psi)
    return SCNI(G=G, volume=volume, faces=faces, psi_faces=psi, dpsi_faces=dpsi, spacing=h,
                support=np.asarray(support, float))

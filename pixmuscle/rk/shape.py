"""Reproducing-kernel shape functions and their exact gradients (paper §2, eqs. 1–7).

For a point x with neighbour nodes x_I (those whose kernel support contains x),

    Ψ_I(x) = H^T(0) M^{-1}(x) H(x - x_I) φ_a(x - x_I)                                   (eq. 7)
    M(x)   = Σ_I H(x - x_I) H^T(x - x_I) φ_a(x - x_I)                                   (eq. 6)

H is the complete monomial basis of order n (eqs. 1, 4). The monomials are evaluated in the
shifted, support-normalised variable r = (x - x_I) / s with s a per-axis length scale of the point
(the support radius, or the mean support radius of the point's neighbours when the supports differ
between nodes). H(r) = D H(x - x_I) with a constant diagonal D, so Ψ is unchanged (eq. 5 is
invariant under that change of basis), while M stays O(1) and well conditioned.

Gradient (differentiating eq. 7; with b = M^{-1} H(0), ∂H/∂r_k = G_k H, ∂_k = ∂/∂x_k):

    ∂_k Ψ_I = ∂_k φ_I (b · H_I) + φ_I (c_k · H_I),
    c_k     = ∂_k b + G_k^T b / s_k = -M^{-1} (G_k H(0) / s_k + M'_k b),
    M'_k    = Σ_I H_I H_I^T ∂_k φ_I,

using ∂_k M = (G_k M + M G_k^T) / s_k + M'_k and M b = H(0). This is exact (no finite differences).
"""

from __future__ import annotations

import itertools
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import scipy.sparse as sp

from pixmuscle.errors import InputError
from pixmuscle.rk.basis import derivative_matrices, exponents, monomials
from pixmuscle.rk.kernels import SUPPORT_SHAPES, check_kernel, window
from pixmuscle.rk.neighbors import NodeSearch

#: Smallest accepted reciprocal condition number λ_min / λ_max of the normalised moment matrix.
RCOND_MIN = 1e-10

#: Point–node pairs processed at once (bounds the temporary memory to a few hundred MB).
PAIRS_PER_BLOCK = 1_000_000

_INT32_MAX = np.iinfo(np.int32).max


def shape_functions(
    nodes,
    points,
    support,
    *,
    kernel="cubic",
    order=1,
    support_shape="box",
    gradient=False,
    check_only=False,
    singular="raise",
):
    """RK shape functions Ψ_I(x) (paper eq. 7) and optionally their exact gradients.

    Parameters
    ----------
    nodes : array_like, shape (N, d), cm
        Node coordinates x_I, d = 1, 2 or 3 (shape (N,) is read as d = 1).
    points : array_like, shape (P, d), cm
        Evaluation points x.
    support : float or array_like, shape (d,), (N,) or (N, d), cm
        Kernel support radius a: one value, one per axis, one per node (isotropic) or one per
        node and axis. A length-d vector is read per axis (also when N == d). The kernel of node
        I vanishes where the normalised distance z >= 1 (see ``support_shape``).
    kernel : {"tent", "cubic", "quartic", "quintic"}
        1-D kernel φ(z), formulas in :mod:`pixmuscle.rk.kernels`.
    order : {0, 1, 2}
        Order n of the complete monomial basis (eq. 4); m = (n + d)! / (n! d!) monomials.
    support_shape : {"box", "sphere"}
        ``"box"``: φ_a = Π_k φ(|x_k - x_Ik| / a_Ik) (tensor product);
        ``"sphere"``: φ_a = φ(‖(x - x_I) / a_I‖) (radial in support-normalised coordinates).
    gradient : bool
        Also return the derivatives ∂Ψ_I/∂x_k.
    check_only : bool
        Only test the moment matrices of the points (raising as below) and return None: no shape
        function is computed or kept, so the memory is that of one block of points, not of Ψ
        (~22 kB per node for the SCNI points of a leg).
    singular : {"raise", "empty"}
        Points whose moment matrix is singular or badly conditioned: ``"raise"`` (below), or
        ``"empty"``: their rows are left without entries (for points where no value is needed, e.g.
        at the cut edge of one MPI rank's part of a model).

    Returns
    -------
    psi : scipy.sparse.csr_matrix, shape (P, N)
        Ψ_I(x_p); stored entries are exactly the pairs with x_p inside the support of node I,
        column indices sorted within each row (int32 indices when they fit).
    dpsi : list of d scipy.sparse.csr_matrix, shape (P, N), cm⁻¹
        ∂Ψ_I/∂x_k (k = 0..d-1) with the same sparsity pattern as ``psi``; only when
        ``gradient`` is true. At a kink of the kernel (tent kernel at x_k = x_Ik) the mean of
        the one-sided derivatives is used.

    Raises
    ------
    InputError
        Bad shapes, non-finite values, non-positive supports, unknown options, or points whose
        moment matrix (eq. 6) is singular or badly conditioned (too few nodes in their support
        for the order asked); the message gives how many and some coordinates.

    Notes
    -----
    The result reproduces every monomial of degree <= n exactly (eq. 5):
    Σ_I Ψ_I(x) x_I^α = x^α, and Σ_I ∂_k Ψ_I(x) x_I^α = ∂_k x^α.
    Work is vectorised over point–node pairs in blocks of about ``PAIRS_PER_BLOCK`` pairs.

    Examples
    --------
    >>> import numpy as np
    >>> x = np.linspace(0.0, 1.0, 11)[:, None]
    >>> psi = shape_functions(x, x, 0.25, order=1)
    >>> bool(np.allclose(psi @ x[:, 0], x[:, 0]))
    True
    """
    nodes, points, a, per_node = _check_inputs(nodes, points, support)
    check_kernel(kernel)
    if support_shape not in SUPPORT_SHAPES:
        raise InputError(f"unknown support_shape {support_shape!r}: expected one of {', '.join(SUPPORT_SHAPES)}")
    if isinstance(order, (bool, np.bool_)) or order not in (0, 1, 2):
        raise InputError(f"RK basis order must be 0, 1 or 2, got {order!r}")
    if singular not in ("raise", "empty"):
        raise InputError(f"singular must be 'raise' or 'empty', got {singular!r}")
    order = int(order)

    n_nodes, dim = nodes.shape
    n_points = points.shape[0]
    alphas = exponents(dim, order)
    g0 = derivative_matrices(alphas)[:, :, 0]  # (d, m): G_k H(0)
    search = NodeSearch(nodes, a.max(axis=0) if per_node else a, np.inf if support_shape == "box" else 2.0)

    counts = np.zeros(n_points, dtype=np.int64)
    cols_parts, psi_parts, dpsi_parts, bad_parts = [], [], [], []

    def one(span):
        start, stop = span
        return start, stop, _block(points[start:stop], nodes, a, per_node, search, kernel, support_shape, alphas, g0,
                                   gradient, compute=not check_only, empty_bad=singular == "empty")

    # the first block measures the pairs per point, which sizes the others; those run on the
    # process's threads (numpy's array operations and LAPACK release the GIL), taken in order
    first = one((0, min(n_points, 4096)))
    per_point = max(first[2]["n_pairs"] / max(first[1], 1), 1.0)
    block = max(1, int(PAIRS_PER_BLOCK / per_point))
    spans = [(lo, min(n_points, lo + block)) for lo in range(first[1], n_points, block)]
    threads = min(_threads(), len(spans))
    pool = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="pixmuscle-rk") if threads > 1 else None
    try:
        results = itertools.chain([first], (map if pool is None else pool.map)(one, spans))
        _collect(results, counts, cols_parts, psi_parts, dpsi_parts, bad_parts, gradient, check_only)
    finally:
        if pool is not None:
            pool.shutdown()

    if bad_parts:
        _raise_bad_points(np.concatenate(bad_parts), points, n_points, dim, order, alphas.shape[0])
    if check_only:
        return None

    nnz = int(counts.sum())
    index_dtype = np.int32 if max(nnz, n_nodes) <= _INT32_MAX else np.int64
    indptr = np.zeros(n_points + 1, dtype=index_dtype)
    np.cumsum(counts, out=indptr[1:])
    indices = _concat(cols_parts, index_dtype)
    shape = (n_points, n_nodes)
    psi = _csr(_concat(psi_parts, float), indices, indptr, shape)
    if not gradient:
        return psi
    dpsi = [
        _csr(_concat([part[k] for part in dpsi_parts], float), indices.copy(), indptr.copy(), shape) for k in range(dim)
    ]
    return psi, dpsi


def _threads() -> int:
    """Threads of :func:`shape_functions`: numba's thread count (all cores, or the process's share of
    them under ``mpiexec``, :func:`pixmuscle.parallel.share_cores`)."""
    import numba

    return max(1, numba.get_num_threads())


def _collect(results, counts, cols_parts, psi_parts, dpsi_parts, bad_parts, gradient, check_only) -> None:
    """Gather the blocks' results in order; after the first singular point only the singular points
    are kept (the error reports them all)."""
    for start, stop, out in results:
        if out["bad"].size:
            bad_parts.append(out["bad"] + start)
        elif not bad_parts and not check_only:
            counts[start:stop] = out["counts"]
            cols_parts.append(out["cols"])
            psi_parts.append(out["psi"])
            if gradient:
                dpsi_parts.append(out["dpsi"])
        if bad_parts:  # the values are of no use any more
            for parts in (cols_parts, psi_parts, dpsi_parts):
                parts.clear()


def _block(points, nodes, a, per_node, search, kind, support_shape, alphas, g0, gradient, compute, empty_bad=False):
    """Shape functions of one block of points (all arrays local to the block); with ``empty_bad`` the
    points of singular moment matrices get no entries instead of being reported."""
    n_points = points.shape[0]
    dim = nodes.shape[1]
    rows, cols = search.pairs(points)
    diff = points[rows] - nodes[cols]
    a_pair = a[cols] if per_node else a
    u = diff / a_pair
    z = np.abs(u).max(axis=1) if support_shape == "box" else np.sqrt(np.einsum("ij,ij->i", u, u))
    keep = z < 1.0
    if not keep.all():
        rows, cols, diff, u = rows[keep], cols[keep], diff[keep], u[keep]
        if per_node:
            a_pair = a_pair[keep]
    n_pairs = rows.size
    counts = np.bincount(rows, minlength=n_points)

    if gradient:
        phi, dphi = window(u, a_pair, kind, support_shape, gradient=True)
    else:
        phi = window(u, a_pair, kind, support_shape)

    # per-point length scale s of the shifted, normalised monomials
    if per_node:
        safe = np.maximum(counts, 1)
        scale = np.stack(
            [np.bincount(rows, weights=a_pair[:, k], minlength=n_points) / safe for k in range(dim)],
            axis=1,
        )
        scale[counts == 0] = 1.0
        r = diff / scale[rows]
    else:
        scale = np.broadcast_to(a, (n_points, dim))
        r = u
    h = monomials(r, alphas)

    moment = _moments(rows, phi, h, n_points)
    with np.errstate(all="ignore"):
        lam = np.linalg.eigvalsh(moment)
    good = lam[:, 0] > RCOND_MIN * lam[:, -1]
    out = {"n_pairs": n_pairs, "bad": np.flatnonzero(~good)}
    if (out["bad"].size and not empty_bad) or not compute:
        return out
    if not good.all():  # empty_bad: their rows go without entries
        out["bad"] = out["bad"][:0]
        moment[~good] = np.eye(moment.shape[1])
        keep = good[rows]
        rows, cols, phi, h = rows[keep], cols[keep], phi[keep], h[keep]
        if gradient:
            dphi = dphi[keep]
        counts = np.where(good, counts, 0)

    minv = np.linalg.inv(moment)
    b = minv[:, :, 0].copy()  # M^{-1} H(0), H(0) = e_0
    hb = np.einsum("ij,ij->i", h, b[rows])
    out.update(counts=counts, cols=cols, psi=phi * hb)
    if gradient:
        dpsi = []
        for k in range(dim):
            mk = _moments(rows, dphi[:, k], h, n_points)
            v = g0[k][None, :] / scale[:, k : k + 1] + np.einsum("pij,pj->pi", mk, b)
            c = -np.einsum("pij,pj->pi", minv, v)
            dpsi.append(dphi[:, k] * hb + phi * np.einsum("ij,ij->i", h, c[rows]))
        out["dpsi"] = dpsi
    return out


def _moments(rows, weight, h, n_points):
    """Σ over each point's pairs of weight · H H^T, shape (P, m, m) (eq. 6)."""
    m = h.shape[1]
    out = np.empty((n_points, m, m))
    wh = weight[:, None] * h
    for i in range(m):
        for j in range(i, m):
            out[:, i, j] = np.bincount(rows, weights=wh[:, i] * h[:, j], minlength=n_points)
            out[:, j, i] = out[:, i, j]
    return out


def _concat(parts, dtype):
    if not parts:
        return np.zeros(0, dtype=dtype)
    return np.concatenate(parts).astype(dtype, copy=False)


def _csr(data, indices, indptr, shape):
    mat = sp.csr_matrix((data, indices, indptr), shape=shape, copy=False)
    mat.has_sorted_indices = True
    return mat


class SingularMomentError(InputError):
    """Some evaluation points have a singular moment matrix (too few nodes in their support).

    Attributes
    ----------
    point_index : ndarray of int64
        Indices (into ``points``) of the offending points.
    """

    def __init__(self, message: str, point_index: np.ndarray):
        super().__init__(message)
        self.point_index = np.asarray(point_index, dtype=np.int64)


def _raise_bad_points(bad, points, n_points, dim, order, m):
    shown = ", ".join("(" + ", ".join(f"{c:.6g}" for c in points[i]) + ")" for i in bad[:5])
    more = " ..." if bad.size > 5 else ""
    raise SingularMomentError(
        f"RK shape functions: {bad.size} of {n_points} evaluation points have a singular or "
        f"badly conditioned moment matrix (reciprocal condition < {RCOND_MIN:g}): an order-{order} "
        f"basis in {dim}-D needs at least {m} nodes, not all on a lower-degree curve/plane, with "
        f"the point strictly inside their kernel support. Points (cm): {shown}{more}. "
        f"Enlarge the support a, lower the basis order, or keep the points inside the node cloud.",
        bad,
    )


def _as_coords(arr, name, dim=None):
    arr = np.asarray(arr, dtype=float)
    if arr.ndim == 1 and (dim is None or dim == 1):
        arr = arr[:, None]
    if arr.ndim != 2 or arr.shape[1] not in (1, 2, 3):
        raise InputError(f"RK {name} must have shape (n, d) with d = 1, 2 or 3, got {arr.shape}")
    if dim is not None and arr.shape[1] != dim:
        raise InputError(f"RK {name} have dimension {arr.shape[1]} but the nodes have dimension {dim}")
    nonfinite = ~np.isfinite(arr).all(axis=1)
    if nonfinite.any():
        first = int(np.flatnonzero(nonfinite)[0])
        raise InputError(
            f"RK {name}: {int(nonfinite.sum())} rows have non-finite coordinates "
            f"(first: row {first}, {arr[first].tolist()})"
        )
    return np.ascontiguousarray(arr)


def _check_inputs(nodes, points, support):
    nodes = _as_coords(nodes, "nodes")
    n_nodes, dim = nodes.shape
    points = _as_coords(points, "points", dim)
    if n_nodes == 0 and points.shape[0] > 0:
        raise InputError("RK shape functions: no nodes given, cannot evaluate at any point")
    a = np.asarray(support, dtype=float)
    if a.ndim == 0:
        a = np.full(dim, float(a))
    elif a.shape == (dim,):
        pass
    elif a.shape == (n_nodes,):
        a = np.repeat(a[:, None], dim, axis=1)
    elif a.shape != (n_nodes, dim):
        raise InputError(
            f"RK support must be a scalar or have shape ({dim},), ({n_nodes},) or "
            f"({n_nodes}, {dim}) (cm), got {a.shape}"
        )
    if not (np.isfinite(a).all() and (a > 0).all()):
        raise InputError("RK support radius must be finite and > 0 (cm) everywhere")
    per_node = a.ndim == 2
    if per_node and (n_nodes == 0 or (a == a[0]).all()):
        a = a[0].copy() if n_nodes else np.ones(dim)
        per_node = False
    return nodes, points, np.ascontiguousarray(a), per_node

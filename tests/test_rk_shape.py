"""RK shape functions (paper eqs. 5–7): reproducing conditions, exact gradients, sparsity, errors."""

import itertools

import numpy as np
import pytest
import scipy.sparse as sp

from pixmuscle.errors import InputError
from pixmuscle.rk import KERNELS, shape_functions
from pixmuscle.rk import shape as rk_shape

H = 0.3  # node spacing, cm
OFFSET = 2.0  # cm, keeps coordinates away from the origin so x^alpha is not trivially small
N_PER_AXIS = {1: 14, 2: 8, 3: 6}


def node_cloud(dim, jitter, seed=0):
    """Grid of nodes (optionally jittered by up to 0.25 h) with spacing H, 3H along axis 0."""
    rng = np.random.default_rng(seed)
    n = N_PER_AXIS[dim]
    grid = np.stack(np.meshgrid(*[np.arange(n)] * dim, indexing="ij"), -1).reshape(-1, dim)
    spacing = np.full(dim, H)
    spacing[0] = 3 * H  # anisotropic node cloud
    x = grid.astype(float)
    if jitter:
        x += rng.uniform(-0.25, 0.25, x.shape)
    return OFFSET + x * spacing, spacing


def eval_points(dim, spacing, n=30, seed=1):
    rng = np.random.default_rng(seed)
    hi = (N_PER_AXIS[dim] - 1) * spacing
    return OFFSET + rng.uniform(0.0, 1.0, (n, dim)) * hi


def monomial_exponents(dim, order):
    return [a for a in itertools.product(range(order + 1), repeat=dim) if sum(a) <= order]


def support_for(spacing, order, shape):
    # normalised support (a/h per axis): large enough for order 2 with jitter, 3x along axis 0
    ratio = {0: 1.6, 1: 1.9, 2: 2.6}[order] * (1.25 if shape == "sphere" else 1.0)
    return ratio * spacing


def check_reproduction(nodes, points, psi, dpsi, order, rtol=1e-10):
    dim = nodes.shape[1]
    for alpha in monomial_exponents(dim, order):
        alpha = np.array(alpha)
        f_nodes = np.prod(nodes**alpha, axis=1)
        f_pts = np.prod(points**alpha, axis=1)
        scale = np.abs(f_pts).max()
        np.testing.assert_allclose(psi @ f_nodes, f_pts, rtol=0, atol=rtol * scale)
        if dpsi is None:
            continue
        for k in range(dim):
            lower = alpha.copy()
            lower[k] = max(lower[k] - 1, 0)
            df = alpha[k] * np.prod(points**lower, axis=1)
            gscale = max(np.abs(df).max(), scale / H)
            np.testing.assert_allclose(dpsi[k] @ f_nodes, df, rtol=0, atol=rtol * gscale)


@pytest.mark.parametrize("dim", [1, 2, 3])
@pytest.mark.parametrize("kind", KERNELS)
@pytest.mark.parametrize("shape", ["box", "sphere"])
@pytest.mark.parametrize("jitter", [False, True], ids=["grid", "scattered"])
def test_reproducing_conditions_values_and_gradients(dim, kind, shape, jitter):
    nodes, spacing = node_cloud(dim, jitter)
    points = np.vstack([eval_points(dim, spacing), nodes[:: max(1, len(nodes) // 20)]])
    for order in (0, 1, 2):
        a = support_for(spacing, order, shape)
        psi, dpsi = shape_functions(nodes, points, a, kernel=kind, order=order, support_shape=shape, gradient=True)
        check_reproduction(nodes, points, psi, dpsi, order)


@pytest.mark.parametrize("dim", [1, 2, 3])
@pytest.mark.parametrize("shape", ["box", "sphere"])
def test_reproducing_conditions_per_node_supports(dim, shape):
    nodes, spacing = node_cloud(dim, jitter=True, seed=3)
    points = eval_points(dim, spacing, seed=4)
    rng = np.random.default_rng(5)
    for order in (1, 2):
        base = support_for(spacing, order, shape)
        a = base * rng.uniform(1.0, 1.4, (nodes.shape[0], dim))  # (N, d), varies node to node
        psi, dpsi = shape_functions(nodes, points, a, kernel="cubic", order=order, support_shape=shape, gradient=True)
        check_reproduction(nodes, points, psi, dpsi, order)
        # the stored pattern is exactly the set of pairs inside node I's own support
        u = (points[:, None, :] - nodes[None, :, :]) / a[None]
        z = np.abs(u).max(-1) if shape == "box" else np.linalg.norm(u, axis=-1)
        np.testing.assert_array_equal(psi.toarray() != 0, z < 1)
    # isotropic per-node support, shape (N,)
    a_iso = 2.7 * H * rng.uniform(1.0, 1.3, nodes.shape[0]) * 3
    psi = shape_functions(nodes, points, a_iso, kernel="quintic", order=1, support_shape=shape)
    check_reproduction(nodes, points, psi, None, 1)


@pytest.mark.parametrize(
    ("dim", "kind", "shape", "order"),
    [
        (1, "tent", "box", 1),
        (1, "quintic", "box", 2),
        (2, "cubic", "box", 1),
        (2, "quartic", "sphere", 2),
        (2, "tent", "sphere", 1),
        (3, "cubic", "box", 1),
        (3, "cubic", "sphere", 2),
        (3, "quintic", "box", 2),
    ],
)
def test_gradient_matches_central_differences(dim, kind, shape, order):
    nodes, spacing = node_cloud(dim, jitter=True, seed=7)
    points = eval_points(dim, spacing, n=12, seed=8)
    rng = np.random.default_rng(9)
    a = support_for(spacing, order, shape) * rng.uniform(1.0, 1.3, (nodes.shape[0], dim))
    kw = dict(kernel=kind, order=order, support_shape=shape)
    psi, dpsi = shape_functions(nodes, points, a, gradient=True, **kw)
    eps = 1e-6 * H
    for k in range(dim):
        step = np.zeros(dim)
        step[k] = eps
        plus = shape_functions(nodes, points + step, a, **kw).toarray()
        minus = shape_functions(nodes, points - step, a, **kw).toarray()
        fd = (plus - minus) / (2 * eps)
        exact = dpsi[k].toarray()
        assert np.abs(fd - exact).max() <= 1e-6 * np.abs(exact).max()


def reference_shape_functions(nodes, points, a):
    """Textbook eq. 7 point by point: cubic box kernel, linear basis in unscaled x - x_I."""
    out = np.zeros((points.shape[0], nodes.shape[0]))
    for p, x in enumerate(points):  # test-only loop over a handful of points
        diff = x - nodes
        z = np.abs(diff) / a
        w1 = np.where(z <= 0.5, 2 / 3 - 4 * z**2 + 4 * z**3, np.where(z < 1, 4 / 3 * (1 - z) ** 3, 0))
        phi = w1.prod(axis=1)
        hmat = np.column_stack([np.ones(len(nodes)), diff])
        moment = (hmat * phi[:, None]).T @ hmat
        b = np.linalg.solve(moment, np.eye(hmat.shape[1])[0])
        out[p] = hmat @ b * phi
    return out


def test_matches_textbook_formula_and_partition_of_unity():
    nodes, spacing = node_cloud(2, jitter=True, seed=11)
    points = eval_points(2, spacing, n=8, seed=12)
    a = 1.9 * spacing
    psi = shape_functions(nodes, points, a, kernel="cubic", order=1)
    ref = reference_shape_functions(nodes, points, a)
    np.testing.assert_allclose(psi.toarray(), ref, atol=1e-12)
    np.testing.assert_allclose(np.asarray(psi.sum(axis=1)).ravel(), 1.0, atol=1e-13)


def test_sparse_layout():
    nodes, spacing = node_cloud(3, jitter=False)
    psi, dpsi = shape_functions(nodes, nodes, 1.65 * spacing, gradient=True)
    assert sp.issparse(psi) and psi.format == "csr" and psi.shape == (len(nodes), len(nodes))
    assert psi.indices.dtype == np.int32 and psi.indptr.dtype == np.int32
    assert len(dpsi) == 3
    for d in dpsi:
        assert d.format == "csr" and d.shape == psi.shape
        np.testing.assert_array_equal(d.indices, psi.indices)
        np.testing.assert_array_equal(d.indptr, psi.indptr)
        assert not np.shares_memory(d.indices, psi.indices)
    # sorted column indices within each row (independent check with scipy)
    check = psi.copy()
    check.has_sorted_indices = False
    check.sort_indices()
    np.testing.assert_array_equal(check.indices, psi.indices)
    # interior grid node with a = 1.65 h per axis: 3^3 neighbours
    counts = np.diff(psi.indptr)
    assert counts.max() == 27 and counts.min() == 8
    assert np.isfinite(psi.data).all()


def test_blocked_evaluation_equals_single_block(monkeypatch):
    nodes, spacing = node_cloud(2, jitter=True, seed=13)
    points = eval_points(2, spacing, n=200, seed=14)
    a = 2.6 * spacing
    whole, dwhole = shape_functions(nodes, points, a, order=2, gradient=True)
    monkeypatch.setattr(rk_shape, "PAIRS_PER_BLOCK", 100)
    parts, dparts = shape_functions(nodes, points, a, order=2, gradient=True)
    assert (whole != parts).nnz == 0 or abs(whole - parts).max() < 1e-14
    for d1, d2 in zip(dwhole, dparts, strict=True):
        assert abs(d1 - d2).max() < 1e-12
    # the error collects bad points over all blocks
    far = np.vstack([points, [[-50.0, -50.0], [60.0, 0.0], [0.0, 70.0]]])
    with pytest.raises(InputError, match=r"\b3 of 203 evaluation points"):
        shape_functions(nodes, far[::-1], a, order=2)


def test_check_only_tests_the_same_points_and_keeps_nothing(monkeypatch):
    """``check_only``: None where every moment matrix is regular; otherwise the same error, naming the
    same points (over several blocks), as the evaluation."""
    from pixmuscle.rk import SingularMomentError

    nodes, spacing = node_cloud(2, jitter=True, seed=13)
    points = eval_points(2, spacing, n=200, seed=14)
    a = 2.6 * spacing
    monkeypatch.setattr(rk_shape, "PAIRS_PER_BLOCK", 100)
    assert shape_functions(nodes, points, a, order=2, check_only=True) is None
    far = np.vstack([points, [[-50.0, -50.0], [60.0, 0.0], [0.0, 70.0]]])[::-1]
    errors = []
    for check_only in (False, True):
        with pytest.raises(SingularMomentError) as info:
            shape_functions(nodes, far, a, order=2, check_only=check_only)
        errors.append(info.value)
    assert str(errors[0]) == str(errors[1]) and np.array_equal(errors[0].point_index, errors[1].point_index)


def test_two_nodes_in_2d_linear_basis_is_singular():
    nodes = np.array([[0.0, 0.0], [1.0, 0.0]])
    points = np.array([[0.5, 0.0], [0.25, 0.0]])
    with pytest.raises(InputError) as info:
        shape_functions(nodes, points, 2.0, order=1, gradient=True)
    msg = str(info.value)
    assert "2 of 2 evaluation points" in msg
    assert "(0.5, 0)" in msg and "at least 3 nodes" in msg


def test_too_small_support_for_quadratic_basis_in_1d():
    x = np.linspace(0.0, 1.0, 11)[:, None]
    shape_functions(x, x, 0.25, order=2)  # a/h = 2.5: fine
    with pytest.raises(InputError, match="order-2 basis in 1-D needs at least 3 nodes"):
        shape_functions(x, x, 0.15, order=2)  # a/h = 1.5: only 2 nodes at the ends


def test_points_outside_the_node_cloud_raise_not_nan():
    x = np.linspace(0.0, 1.0, 11)[:, None]
    with pytest.raises(InputError, match=r"1 of 2 evaluation points.*\(3\)"):
        shape_functions(x, np.array([[0.5], [3.0]]), 0.2)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        (dict(support=-1.0), "finite and > 0"),
        (dict(support=np.ones(5)), "support must be"),
        (dict(kernel="gauss"), "unknown RK kernel"),
        (dict(order=3), "order must be 0, 1 or 2"),
        (dict(support_shape="cube"), "unknown support_shape"),
        (dict(points=np.zeros((3, 3))), "dimension 3"),
        (dict(points=np.array([[np.nan, 0.0]])), "non-finite"),
        (dict(nodes=np.zeros((4, 4))), r"d = 1, 2 or 3"),
    ],
)
def test_bad_input_raises_input_error(kwargs, match):
    args = dict(nodes=np.random.default_rng(0).uniform(0, 1, (20, 2)), points=np.full((1, 2), 0.5))
    args["support"] = 0.8
    args.update(kwargs)
    nodes, points, support = args.pop("nodes"), args.pop("points"), args.pop("support")
    with pytest.raises(InputError, match=match):
        shape_functions(nodes, points, support, **args)


def test_no_points_gives_empty_matrix():
    x = np.linspace(0.0, 1.0, 5)[:, None]
    psi, (d,) = shape_functions(x, np.zeros((0, 1)), 0.5, gradient=True)
    assert psi.shape == (0, 5) and d.shape == (0, 5) and psi.nnz == 0

"""DTI tensors, eigenvectors, sign-invariant features and resampling between grids."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pixmuscle.errors import InputError
from pixmuscle.imaging.dti import (
    canonical_sign,
    components_from_tensor,
    fiber_features,
    principal_eigenvector,
    resample_tensor_to_grid,
    resample_vectors_to_grid,
    tensor_from_components,
)
from pixmuscle.imaging.resample import resample_labels, resample_to_grid


def affine(spacing, origin, perm=(0, 1, 2), flip=(1, 1, 1)):
    """Voxel -> world affine whose voxel axis n runs along world axis perm[n] (sign flip[n])."""
    a = np.zeros((4, 4))
    for n in range(3):
        a[perm[n], n] = flip[n] * spacing[n]
    a[:3, 3] = origin
    a[3, 3] = 1.0
    return a


def world_points(aff, shape):
    idx = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), axis=-1)
    return idx @ aff[:3, :3].T + aff[:3, 3]


def test_principal_eigenvector_of_rotated_tensor():
    rots = Rotation.random(50, random_state=1).as_matrix()
    evals = np.array([2.1e-3, 1.5e-3, 1.2e-3])
    d = rots @ np.diag(evals) @ np.swapaxes(rots, 1, 2)
    v, lam, fa = principal_eigenvector(d)
    truth = rots[:, :, 0]
    np.testing.assert_allclose(np.abs(np.sum(v * truth, axis=1)), 1.0, atol=1e-10)
    np.testing.assert_allclose(lam, np.broadcast_to(evals, lam.shape), rtol=1e-10)
    # FA by the textbook formula (pairwise differences), independent of the implementation
    l1, l2, l3 = evals
    fa_ref = np.sqrt(0.5 * ((l1 - l2) ** 2 + (l2 - l3) ** 2 + (l3 - l1) ** 2) / (l1**2 + l2**2 + l3**2))
    np.testing.assert_allclose(fa, fa_ref, rtol=1e-10)
    assert np.all(v[:, 2] >= 0)


def test_zero_tensor_gives_zero_vector_and_fa():
    v, lam, fa = principal_eigenvector(np.zeros((2, 3, 3)))
    assert np.all(v == 0) and np.all(fa == 0) and np.all(lam == 0)


def test_canonical_sign():
    rng = np.random.default_rng(0)
    v = rng.normal(size=(100, 3))
    c = canonical_sign(v)
    np.testing.assert_array_equal(c, canonical_sign(-v))
    assert np.all(c[:, 2] > 0)
    np.testing.assert_allclose(np.abs(c), np.abs(v))
    ties = np.array([[1.0, -2.0, 0.0], [-3.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    np.testing.assert_array_equal(canonical_sign(ties), [[-1.0, 2.0, 0.0], [3.0, 0.0, 0.0], [0, 0, 0]])
    np.testing.assert_array_equal(canonical_sign(-ties), canonical_sign(ties))


@pytest.mark.parametrize("mode", ["outer", "abs", "canonical"])
def test_fiber_features_are_sign_invariant(mode):
    rng = np.random.default_rng(1)
    v = rng.normal(size=(7, 5, 3))
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    signs = np.where(rng.random((7, 5, 1)) < 0.5, -1.0, 1.0)
    np.testing.assert_array_equal(fiber_features(v, mode), fiber_features(v * signs, mode))


def test_outer_features_are_the_outer_product():
    v = np.array([0.2, -0.3, np.sqrt(1 - 0.13)])
    f = fiber_features(v, "outer")
    o = np.outer(v, v)
    np.testing.assert_allclose(f, [o[0, 0], o[0, 1], o[0, 2], o[1, 1], o[1, 2], o[2, 2]])


@pytest.mark.parametrize("order,where", [
    ("fsl", [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]),
    ("dipy", [(0, 0), (0, 1), (1, 1), (0, 2), (1, 2), (2, 2)]),
    ("mrtrix", [(0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)]),
])
def test_component_orders(order, where):
    comp = np.array([11.0, 12.0, 13.0, 14.0, 15.0, 16.0])
    d = tensor_from_components(comp, order)
    for n, (r, c) in enumerate(where):
        assert d[r, c] == comp[n] and d[c, r] == comp[n]
    rng = np.random.default_rng(2)
    a = rng.normal(size=(4, 3, 3))
    sym = a + np.swapaxes(a, 1, 2)
    np.testing.assert_allclose(tensor_from_components(components_from_tensor(sym, order), order), sym)
    with pytest.raises(InputError, match="order"):
        tensor_from_components(comp, "nonsense")


def linear_tensor_field(x):
    """D(x) = D0 + x_i D_i: symmetric, linear in world position (cm)."""
    d0 = np.array([[2.0, 0.1, 0.2], [0.1, 1.5, -0.1], [0.2, -0.1, 1.2]])
    di = [np.array([[0.1, 0.02, 0], [0.02, 0, 0.01], [0, 0.01, -0.03]]),
          np.array([[0, 0.03, 0.01], [0.03, 0.05, 0], [0.01, 0, 0.02]]),
          np.array([[-0.02, 0, 0.04], [0, 0.01, 0.02], [0.04, 0.02, 0.03]])]
    return d0 + sum(x[..., i, None, None] * di[i] for i in range(3))


def test_tensor_resampling_reproduces_linear_field_on_other_grid():
    src_shape = (12, 10, 6)
    src = affine((0.4, 0.4, 0.6), (1.0, -2.0, 3.0))
    d = linear_tensor_field(world_points(src, src_shape))
    # target: finer in-plane, shifted, axes permuted and one flipped
    dst_shape = (9, 14, 11)
    dst = affine((0.5, 0.25, 0.3), (1.3, 1.1, 2.5), perm=(2, 0, 1), flip=(1, 1, -1))
    out, covered = resample_tensor_to_grid(d, src, dst_shape, dst)
    xw = world_points(dst, dst_shape)
    # inside the hull of the source voxel centres, linear interpolation is exact
    idx = (xw - src[:3, 3]) / np.diag(src)[:3]
    hull = np.all((idx >= -1e-9) & (idx <= np.array(src_shape) - 1 + 1e-9), axis=-1)
    assert hull.sum() > 50 and np.all(covered[hull])
    np.testing.assert_allclose(out[hull], linear_tensor_field(xw[hull]), atol=1e-12)
    assert np.all(out[~covered] == 0)
    assert not np.all(covered)


def test_non_overlapping_fields_of_view():
    d = np.tile(np.eye(3), (4, 4, 4, 1, 1))
    src = affine((1.0, 1.0, 1.0), (0.0, 0.0, 0.0))
    dst = affine((1.0, 1.0, 1.0), (50.0, 0.0, 0.0))
    with pytest.raises(InputError, match="do not overlap"):
        resample_tensor_to_grid(d, src, (4, 4, 4), dst)


def test_vector_resampling_is_sign_invariant_and_correct():
    rng = np.random.default_rng(3)
    shape = (10, 8, 5)
    src = affine((0.4, 0.4, 0.6), (0.0, 0.0, 0.0))
    x = world_points(src, shape)
    # a slowly rotating fibre field
    ang = 0.15 * x[..., 0]
    v = np.stack([np.sin(ang) * 0.5, np.cos(ang) * 0.3, np.ones_like(ang)], axis=-1)
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    signs = np.where(rng.random(shape + (1,)) < 0.5, -1.0, 1.0)
    dst_shape = (15, 11, 7)
    dst = affine((0.25, 0.27, 0.4), (0.1, 0.2, 0.1), perm=(1, 0, 2))
    a, ma = resample_vectors_to_grid(v, src, dst_shape, dst)
    b, mb = resample_vectors_to_grid(v * signs, src, dst_shape, dst)
    np.testing.assert_array_equal(ma, mb)
    np.testing.assert_allclose(a, b, atol=1e-12)
    assert ma.sum() > 100
    xd = world_points(dst, dst_shape)[ma]
    angd = 0.15 * xd[:, 0]
    truth = np.stack([np.sin(angd) * 0.5, np.cos(angd) * 0.3, np.ones_like(angd)], axis=-1)
    truth /= np.linalg.norm(truth, axis=-1, keepdims=True)
    assert np.min(np.abs(np.sum(a[ma] * truth, axis=1))) > 0.999


def test_vector_resampling_marks_missing_data():
    v = np.zeros((6, 6, 3, 3))
    v[:3, :, :, 2] = 1.0  # data only in the lower half along axis 0
    src = affine((1.0, 1.0, 1.0), (0.0, 0.0, 0.0))
    out, has = resample_vectors_to_grid(v, src, (6, 6, 3), src)
    assert np.all(has[:3]) and not np.any(has[3:])
    assert np.all(out[~has] == 0)


def test_scalar_resampling_and_labels():
    shape = (8, 9, 4)
    src = affine((0.5, 0.5, 1.0), (0.0, 0.0, 0.0))
    x = world_points(src, shape)
    f = 1.0 + 2.0 * x[..., 0] - x[..., 1] + 0.5 * x[..., 2]
    dst = affine((0.3, 0.3, 0.5), (0.2, 0.1, 0.3), perm=(0, 2, 1))
    dst_shape = (10, 5, 12)
    out, cov = resample_to_grid(f, src, dst_shape, dst)
    xd = world_points(dst, dst_shape)
    idx = (xd - src[:3, 3]) / np.diag(src)[:3]
    hull = np.all((idx >= 0) & (idx <= np.array(shape) - 1), axis=-1)
    np.testing.assert_allclose(out[hull], (1 + 2 * xd[..., 0] - xd[..., 1] + 0.5 * xd[..., 2])[hull], atol=1e-12)
    # nearest-neighbour labels: the same grid gives the same labels; values are never averaged
    lab = np.random.default_rng(0).integers(0, 5, size=shape).astype(np.int16)
    np.testing.assert_array_equal(resample_labels(lab, src, shape, src), lab)
    r = resample_labels(lab, src, dst_shape, dst)
    assert r.dtype == np.int16 and set(np.unique(r)) <= set(range(5))
    # each resampled label is the label of the source voxel nearest to the target centre
    near = np.clip(np.rint(idx), 0, np.array(shape) - 1).astype(int)
    ok = hull & np.all(np.abs(idx - np.rint(idx)) < 0.49, axis=-1)
    np.testing.assert_array_equal(r[ok], lab[near[ok][:, 0], near[ok][:, 1], near[ok][:, 2]])
    mask = lab > 2
    assert resample_labels(mask, src, dst_shape, dst).dtype == bool

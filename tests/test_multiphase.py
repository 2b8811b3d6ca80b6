"""Multiphase multichannel Vese–Chan (paper eq. 21), sign invariance, regions -> muscles."""

import numpy as np
import pytest

from pixmuscle.errors import InputError
from pixmuscle.segmentation.features import fiber_channels
from pixmuscle.segmentation.multiphase import (
    kmeans_regions,
    level_sets_from_regions,
    multiphase_chan_vese,
    regions_to_muscles,
    seed_features,
    seed_regions,
)

KW = dict(stop="regions", tol=0.0, window=10, energy_scale="variance")


def dice(a, b):
    return 2.0 * np.sum(a & b) / (np.sum(a) + np.sum(b))


def four_regions(shape=(64, 72)):
    """Truth labels 0..3 (background, disk, bar, triangle) and the 2-channel image."""
    yy, xx = np.mgrid[: shape[0], : shape[1]]
    lab = np.zeros(shape, int)
    lab[(yy - 20) ** 2 + (xx - 20) ** 2 < 12**2] = 1
    lab[40:58, 8:64] = 2
    lab[(yy < 34) & (xx > 36) & (xx - 36 > 34 - yy)] = 3
    table = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    return lab, np.moveaxis(table[lab], -1, 0)


def matched_dice(found, truth, n):
    """Dice of each truth label with the found region it overlaps most; and that mapping."""
    out, mapping = [], []
    for t in range(n):
        r = np.bincount(found[truth == t], minlength=found.max() + 1).argmax()
        mapping.append(r)
        out.append(dice(found == r, truth == t))
    return np.array(out), mapping


def test_four_regions_noise_free_exact():
    lab, img = four_regions()
    res = multiphase_chan_vese(img, n_levelsets=2, mu=0.05, lambdas=1.0, max_iter=300,
                               init="kmeans", **KW)
    d, mapping = matched_dice(res.regions, lab, 4)
    assert len(set(mapping)) == 4  # a one-to-one map of regions
    assert np.all(d == 1.0)
    # region means are the piecewise constants
    np.testing.assert_allclose(res.means[mapping], [[0, 0], [1, 0], [0, 1], [1, 1]], atol=1e-12)


def test_four_regions_mild_noise():
    lab, img = four_regions()
    rng = np.random.default_rng(0)
    noisy = img + rng.normal(0.0, 0.15, img.shape)
    res = multiphase_chan_vese(noisy, n_levelsets=2, mu=0.1, lambdas=1.0, max_iter=300,
                               init="kmeans", **KW)
    d, mapping = matched_dice(res.regions, lab, 4)
    assert len(set(mapping)) == 4
    assert d.min() > 0.98


def test_length_term_removes_noise_that_clustering_keeps():
    # strong noise: voxel-wise clustering (the initial regions) misclassifies many voxels;
    # the length term of eq. (21) cleans them up
    lab, img = four_regions()
    rng = np.random.default_rng(0)
    noisy = img + rng.normal(0.0, 0.3, img.shape)
    start, _ = kmeans_regions(noisy, 4)
    res = multiphase_chan_vese(noisy, n_levelsets=2, mu=0.5, lambdas=1.0, max_iter=300,
                               init=start, **KW)
    d, mapping = matched_dice(res.regions, lab, 4)
    d0, _ = matched_dice(start, lab, 4)
    assert len(set(mapping)) == 4
    assert d.min() > 0.98 and d0.min() < 0.85


def test_four_regions_3d_volume():
    lab2, img2 = four_regions()
    lab = np.repeat(lab2[None], 3, axis=0)
    img = np.repeat(img2[:, None], 3, axis=1)
    rng = np.random.default_rng(1)
    noisy = img + rng.normal(0.0, 0.15, img.shape)
    res = multiphase_chan_vese(noisy, n_levelsets=2, mu=0.1, spacing=(3.0, 1.0, 1.0),
                               max_iter=300, init="kmeans", **KW)
    d, mapping = matched_dice(res.regions, lab, 4)
    assert len(set(mapping)) == 4
    assert d.min() > 0.98


def fibre_image(rng):
    """Four regions with different fibre directions, 5 deg of direction noise, random signs."""
    yy, xx = np.mgrid[:48, :60]
    lab = np.zeros((48, 60), int)
    lab[:, 20:40] = 1
    lab[(yy - 24) ** 2 + (xx - 50) ** 2 < 8**2] = 2
    lab[30:44, 3:15] = 3
    dirs = np.array([[0.3, 0.1, 1.0], [-0.4, 0.5, 0.8], [0.6, -0.5, 0.6], [0.9, 0.3, 0.2]])
    v = dirs[lab] / np.linalg.norm(dirs[lab], axis=-1, keepdims=True)
    v = v + rng.normal(0.0, np.radians(5.0), v.shape)
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    signs = rng.choice([-1.0, 1.0], size=lab.shape)
    return lab, v, v * signs[..., None]


@pytest.mark.parametrize("mode", ["outer", "canonical", "abs"])
def test_sign_flips_do_not_change_the_segmentation(mode):
    rng = np.random.default_rng(3)
    lab, v, v_flipped = fibre_image(rng)
    kw = dict(n_levelsets=2, mu=1.0, lambdas=0.02, max_iter=200, init="kmeans", **KW)
    a = multiphase_chan_vese(fiber_channels(v, mode=mode), **kw)
    b = multiphase_chan_vese(fiber_channels(v_flipped, mode=mode), **kw)
    np.testing.assert_array_equal(a.regions, b.regions)
    if mode != "abs":  # |v| cannot tell mirror-image directions apart; not asked of it here
        d, mapping = matched_dice(a.regions, lab, 4)
        assert len(set(mapping)) == 4 and d.min() > 0.97


def test_signed_components_would_fail():
    # the raw components of sign-scrambled eigenvectors do not separate the regions: the
    # reason for sign-invariant channels
    rng = np.random.default_rng(3)
    lab, _, v_flipped = fibre_image(rng)
    raw = np.moveaxis(v_flipped, -1, 0) * 255.0
    res = multiphase_chan_vese(raw, n_levelsets=2, mu=1.0, lambdas=0.02, max_iter=200,
                               init="kmeans", **KW)
    d, _ = matched_dice(res.regions, lab, 4)
    assert d.mean() < 0.8


def test_level_sets_encode_regions():
    rng = np.random.default_rng(4)
    regions = rng.integers(0, 8, size=(10, 12))
    phi = level_sets_from_regions(regions, 3)
    assert phi.shape == (3, 10, 12)
    back = sum((phi[k] > 0).astype(int) << k for k in range(3))
    np.testing.assert_array_equal(back, regions)


def test_seed_init_assigns_nearest_seed_feature():
    lab, img = four_regions()
    seeds = [np.array([[20, 20]]), np.array([[50, 30]]), np.array([[20, 65]])]
    feats = seed_features(img, seeds)
    np.testing.assert_allclose(feats, [[1, 0], [0, 1], [1, 1]])
    # muscles 0, 1, 2 -> regions 0, 1, 2; voxels outside the mask -> the spare region 3
    regions = seed_regions(img, feats, 4, mask=lab > 0)
    np.testing.assert_array_equal(regions, np.array([3, 0, 1, 2])[lab])
    # a few voxels unlike every seed inside the mask also go to the spare region
    odd = img.copy()
    odd[:, 30:33, 40:43] = 5.0
    regions = seed_regions(odd, feats, 4, mask=lab > 0)
    assert np.all(regions[30:33, 40:43][lab[30:33, 40:43] > 0] == 3)


def test_regions_to_muscles_split_by_nearest_seed():
    regions = np.zeros((20, 41), int)
    domain = np.ones_like(regions, bool)
    seeds = [np.array([[10, 10]]), np.array([[10, 30]])]
    mid, info = regions_to_muscles(regions, domain, seeds)
    assert info["shared"] == [[1, 2]]
    assert np.all(mid[:, :20] == 1) and np.all(mid[:, 21:] == 2)
    # with physical spacing the bisector is where the distances in cm are equal
    seeds = [np.array([[2, 10]]), np.array([[18, 10]])]
    mid, _ = regions_to_muscles(regions, domain, seeds, spacing=(1.0, 0.1))
    assert np.all(mid[:10] == 1) and np.all(mid[11:] == 2)


def test_regions_to_muscles_components_and_islands():
    regions = np.zeros((30, 30), int)
    regions[:, 15:] = 1
    regions[3:6, 3:6] = 1  # island of region 1 inside region 0, no seed
    domain = np.ones_like(regions, bool)
    domain[:, 14] = False  # a gap
    seeds = [np.array([[15, 7]]), np.array([[15, 22]])]
    mid, info = regions_to_muscles(regions, domain, seeds)
    assert info["shared"] == []
    assert np.all(mid[:, :14] == 1)  # island joins the muscle around it
    assert np.all(mid[:, 15:] == 2)
    assert np.all(mid[:, 14] == 0)  # outside the domain
    assert info["claimed_fraction"] == pytest.approx(1 - 9 / domain.sum())


def test_regions_to_muscles_bad_seed():
    regions = np.zeros((10, 10), int)
    domain = np.ones_like(regions, bool)
    domain[0, 0] = False
    with pytest.raises(InputError, match="not in the muscle domain"):
        regions_to_muscles(regions, domain, [np.array([[0, 0]])])
    with pytest.raises(InputError, match="outside the image"):
        regions_to_muscles(regions, domain, [np.array([[0, 10]])])


@pytest.mark.parametrize("kwargs, match", [
    (dict(channels=np.zeros((8, 8))), "channels"),
    (dict(channels=np.zeros((2, 8, 8)), lambdas=np.ones(3)), "lambdas"),
    (dict(channels=np.zeros((2, 8, 8)), n_levelsets=3, mu=[1.0, 2.0]), "mu"),
    (dict(channels=np.zeros((2, 8, 8)), init=np.zeros((5, 5), int)), "init"),
])
def test_bad_input_raises(kwargs, match):
    ch = kwargs.pop("channels")
    with pytest.raises(InputError, match=match):
        multiphase_chan_vese(ch, **kwargs)

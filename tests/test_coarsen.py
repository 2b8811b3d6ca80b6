"""coarsen: the coarse model keeps the fine nodes on a coarser in-plane lattice (paper §4.2)."""

import dataclasses
import logging

import numpy as np
import pytest
from scipy import ndimage

from pixmuscle.errors import InputError
from pixmuscle.io.model import load_model, save_model
from pixmuscle.model.build import model_from_labels
from pixmuscle.model.coarsen import coarsen_model, lattice_offsets
from pixmuscle.model.tissues import NODE_TISSUES

SPACING = np.array([0.078125, 0.078125, 0.5])          # paper: 1 pixel = 0.078125 cm
ORIGIN_AFFINE = np.diag([*SPACING, 1.0])
ORIGIN_AFFINE[:3, 3] = [-1.0, 2.5, 10.0]


def disk_labels(shape=(23, 21, 3), radius=8.3, seed=0):
    """Per-slice pattern: a disk of muscle with a fat ring, a bone disk, and a few CT voxels."""
    rng = np.random.default_rng(seed)
    I, J, K = shape
    i, j = np.meshgrid(np.arange(I), np.arange(J), indexing="ij")
    r = np.hypot(i - I / 2 + 0.3, j - J / 2 - 0.2)
    sl = np.zeros((I, J), np.int16)
    sl[r <= radius] = 3
    sl[r <= radius - 2] = 1
    sl[np.hypot(i - I / 2 + 2, j - J / 2) <= 2.2] = 4
    labels = np.repeat(sl[:, :, None], K, axis=2)
    ct = (rng.random(shape) < 0.05) & (labels == 1)
    labels[ct] = 2
    return labels


def build(labels, affine=ORIGIN_AFFINE, **kw):
    return model_from_labels(labels, affine, muscle_fibers={"muscle": [0.1, 0.2, 1.0]}, **kw)


def test_rectangle_kept_nodes_coordinates_spacing_volume():
    labels = np.zeros((11, 12, 4), np.int16)
    labels[1:8, 2:9, :] = 1                              # 7 × 7 pixels per slice, 4 slices
    fine = build(labels)
    coarse = coarsen_model(fine, 2)
    i0, j0 = lattice_offsets(fine.ijk, 2)
    assert (i0, j0) == (1, 0)                            # centred: both extreme planes kept
    keep = ((fine.ijk[:, 0] - i0) % 2 == 0) & ((fine.ijk[:, 1] - j0) % 2 == 0)
    assert coarse.n_nodes == keep.sum() == 4 * 4 * 4
    np.testing.assert_array_equal(coarse.X, fine.X[keep])                 # same points, bit for bit
    np.testing.assert_allclose(coarse.origin + coarse.ijk * coarse.spacing, fine.X[keep], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(coarse.ijk[:, :2], (fine.ijk[keep, :2] - [i0, j0]) // 2)
    np.testing.assert_array_equal(coarse.ijk[:, 2], fine.ijk[keep, 2])    # slices unchanged
    np.testing.assert_allclose(coarse.spacing, SPACING * [2, 2, 1])
    assert coarse.coarsen_factor == 2
    # volume: 7×7 fine cells of h² vs 4×4 coarse cells of (2h)²: (n + 1)² h² for odd n
    h2dz = SPACING[0] * SPACING[1] * SPACING[2]
    assert fine.n_nodes * fine.cell_volume == pytest.approx(49 * 4 * h2dz)
    assert coarse.n_nodes * coarse.cell_volume == pytest.approx(64 * 4 * h2dz)
    assert coarse.sets["x_min"].size == 16 and coarse.sets["z_max"].size == 16


def test_disk_labels_carried_and_volume_within_boundary_band():
    labels = disk_labels()
    fib = np.random.default_rng(4).standard_normal(labels.shape + (3,))
    fib[..., 2] = np.abs(fib[..., 2]) + 0.1                  # canonical sign already (z > 0)
    fine = model_from_labels(labels, ORIGIN_AFFINE, fibers=fib)
    coarse = coarsen_model(fine, 2)
    i0, j0 = lattice_offsets(fine.ijk, 2)
    fine_ijk = coarse.ijk.astype(int) * [2, 2, 1] + [i0, j0, 0]
    # labels and fibres carried: the input volumes themselves at the kept fine voxel
    np.testing.assert_array_equal(coarse.tissue, labels[tuple(fine_ijk.T)])
    np.testing.assert_allclose(coarse.X, fine.origin + fine_ijk * fine.spacing, atol=1e-12)
    f = fib[tuple(fine_ijk.T)]
    f /= np.linalg.norm(f, axis=1, keepdims=True)
    m = coarse.tissue == 1
    np.testing.assert_allclose(coarse.fiber[m], f[m], atol=1e-12)
    assert not coarse.fiber[~m].any()
    # every fine node on the lattice is kept, and no other
    on = np.isin(labels, NODE_TISSUES)
    on_lattice = np.zeros_like(on)
    on_lattice[i0::2, j0::2] = on[i0::2, j0::2]
    assert coarse.n_nodes == on_lattice.sum()
    # the coarse cells (2h × 2h around each kept node) differ from the fine cells only within one
    # fine voxel of the fine domain's boundary: |ΔV| ≤ (band voxels) × h² dz
    band = ndimage.binary_dilation(on, np.ones((3, 3, 1))) & ~ndimage.binary_erosion(on, np.ones((3, 3, 1)), border_value=0)
    dv = abs(coarse.n_nodes * coarse.cell_volume - fine.n_nodes * fine.cell_volume)
    assert dv <= band.sum() * fine.cell_volume
    assert dv / (fine.n_nodes * fine.cell_volume) < 0.2


@pytest.mark.parametrize("factor", [2, 3])
def test_equals_model_of_subsampled_image(factor):
    """Coarsening the model = building the model of the coarse image (common points, paper §4.2)."""
    labels = disk_labels(seed=1)
    mask = np.zeros(labels.shape, bool)
    mask[:, :, 0] = True
    fine = build(labels, masks={"first": mask})
    coarse = coarsen_model(fine, factor)
    i0, j0 = lattice_offsets(fine.ijk, factor)
    aff = ORIGIN_AFFINE.copy()
    aff[:3, :3] = np.diag(SPACING * [factor, factor, 1])
    aff[:3, 3] += [i0 * SPACING[0], j0 * SPACING[1], 0]
    ref = build(labels[i0::factor, j0::factor], aff)
    np.testing.assert_array_equal(coarse.ijk, ref.ijk)
    np.testing.assert_allclose(coarse.X, ref.X, atol=1e-12)
    np.testing.assert_allclose(coarse.spacing, ref.spacing)
    np.testing.assert_allclose(coarse.origin, ref.origin, atol=1e-12)
    np.testing.assert_array_equal(coarse.shape, ref.shape)
    np.testing.assert_array_equal(coarse.tissue, ref.tissue)
    np.testing.assert_array_equal(coarse.bone_ijk, ref.bone_ijk)
    for name, idx in ref.sets.items():
        np.testing.assert_array_equal(coarse.sets[name], idx, err_msg=name)
    assert len(ref.sets["bone_surface"]) > 0
    np.testing.assert_array_equal(coarse.sets["first"], np.flatnonzero(coarse.ijk[:, 2] == 0))
    assert coarse.coarsen_factor == factor


def test_mask_sets_by_coarse_cell_brute_force():
    labels = np.ones((9, 10, 2), np.int16)
    thin = np.zeros(labels.shape, bool)
    thin[3, 2:7, 1] = True                                # one voxel wide, off the kept lattice
    fine = build(labels, masks={"thin": thin})
    coarse = coarsen_model(fine, 2, offset=(0, 0))
    # reference: coarse node n is in the set when a masked fine voxel centre lies in its closed cell
    ref = set()
    for n, (ci, cj, ck) in enumerate(coarse.ijk.tolist()):
        for fi, fj, fk in np.argwhere(thin).tolist():
            if fk == ck and abs(fi - 2 * ci) <= 1 and abs(fj - 2 * cj) <= 1:
                ref.add(n)
    assert ref and set(coarse.sets["thin"].tolist()) == ref


def test_factor_one_and_errors_and_file_round_trip(tmp_path):
    fine = build(disk_labels())
    same = coarsen_model(fine, 1)
    np.testing.assert_array_equal(same.X, fine.X)
    assert same.coarsen_factor == 1
    with pytest.raises(InputError, match="factor"):
        coarsen_model(fine, 0)
    with pytest.raises(InputError, match="offset"):
        coarsen_model(fine, 2, offset=(2, 0))
    one = np.zeros((5, 5, 1), np.int16)
    one[1, 1, 0] = 3
    with pytest.raises(InputError, match="no node lies on the coarse lattice"):
        coarsen_model(model_from_labels(one, [1, 1, 1]), 2, offset=(0, 0))
    twice = coarsen_model(coarsen_model(fine, 2), 2)
    assert twice.coarsen_factor == 4
    np.testing.assert_allclose(twice.spacing, SPACING * [4, 4, 1])
    # bone_ijk survives the file, so a loaded model coarsens the same way
    coarse = coarsen_model(fine, 2)
    loaded = load_model(save_model(tmp_path / "m.h5", fine))
    again = coarsen_model(loaded, 2)
    for name in coarse.sets:
        np.testing.assert_array_equal(again.sets[name], coarse.sets[name])


def test_without_bone_voxels_falls_back_to_cell_rule(caplog):
    fine = build(disk_labels())
    exact = coarsen_model(fine, 2)
    with caplog.at_level(logging.WARNING):
        approx = coarsen_model(dataclasses.replace(fine, bone_ijk=None), 2)
    assert "no bone voxels" in caplog.text
    # the cell rule is more generous: it contains every node the exact rule finds
    for name in ("bone_surface", "outer_surface"):
        assert set(exact.sets[name].tolist()) <= set(approx.sets[name].tolist())
    assert approx.bone_ijk is None

"""Whole segmentation (paper §4.1–4.2) on the SYNTHETIC leg phantom against its ground truth."""

import dataclasses

import h5py
import numpy as np
import pytest
from scipy import ndimage as ndi

from pixmuscle.errors import InputError
from pixmuscle.imaging.dti import resample_tensor_to_grid, tensor_from_components
from pixmuscle.imaging.nifti import load_volume
from pixmuscle.segmentation.config import MultiphaseConfig, SegmentConfig
from pixmuscle.segmentation.volume import segment_volume
from pixmuscle.store import open_stage
from pixmuscle.synth.leg import make_leg_phantom


def dice(a, b):
    return 2.0 * np.sum(a & b) / (np.sum(a) + np.sum(b))


@pytest.fixture(scope="module")
def leg():
    ph = make_leg_phantom(shape=(96, 96, 4), seed=0)  # default noise: realistic
    d, covered = resample_tensor_to_grid(tensor_from_components(ph.dti_tensor, "fsl"),
                                         ph.dti_affine, ph.mri.shape, ph.affine)
    # one "click" per muscle: its deepest voxel in the middle slice, given in cm
    k = ph.mri.shape[2] // 2
    seeds = {}
    for m, name in enumerate(ph.muscle_names, 1):
        depth = ndi.distance_transform_edt(ph.muscle_id[:, :, k] == m)
        i, j = np.unravel_index(np.argmax(depth), depth.shape)
        seeds[name] = [list((ph.affine @ [i, j, k, 1.0])[:3])]
    return ph, d, covered, seeds


def run(leg, **kw):
    ph, d, covered, seeds = leg
    cfg = SegmentConfig(seeds=seeds, seed_units="cm", **kw)
    return segment_volume(ph.mri, ph.affine, d, covered, ph.imct_mask, ph.imat_mask, cfg)


@pytest.fixture(scope="module")
def result(leg):
    return run(leg)


def muscle_dice(ph, muscle_id):
    return np.array([dice(muscle_id == m, ph.muscle_id == m)
                     for m in range(1, len(ph.muscle_names) + 1)])


def seed_region_dice(ph, res):
    """Dice of the connected piece of the multiphase region at each seed: what the level sets
    themselves separated, before any nearest-seed assignment."""
    out = []
    for m, pts in enumerate(res.qc["seed_voxels_ijk"], 1):
        s = tuple(pts[0])
        lab, _ = ndi.label(res.regions == res.regions[s])
        out.append(dice(lab == lab[s], ph.muscle_id == m))
    return np.array(out)


def test_outer_boundary_and_bones(leg, result):
    ph = leg[0]
    assert dice(result.labels > 0, ph.labels > 0) >= 0.95
    assert dice(result.labels == 4, ph.labels == 4) >= 0.95


def test_individual_muscles(leg, result):
    ph = leg[0]
    assert result.muscle_names == ph.muscle_names
    d = muscle_dice(ph, result.muscle_id)
    assert d.mean() >= 0.90 and d.min() >= 0.8
    assert result.qc["shared_regions"] == []


def test_tissue_labels_and_fibres(leg, result):
    ph = leg[0]
    assert dice(result.labels == 1, ph.labels == 1) >= 0.95
    assert dice(result.labels == 3, ph.labels == 3) >= 0.85
    # IMCT comes from its mask, inside the leg
    np.testing.assert_array_equal(result.labels == 2, ph.imct_mask & (result.labels > 0)
                                  & (result.labels != 4))
    assert np.all((result.muscle_id > 0) == (result.labels == 1))
    f = result.fiber[result.labels == 1]
    np.testing.assert_allclose(np.linalg.norm(f, axis=1), 1.0, atol=1e-5)
    assert np.all(f[:, 2] >= 0)  # canonical sign
    both = (result.labels == 1) & (ph.labels == 1)
    cos = np.abs(np.sum(result.fiber[both] * ph.fiber_true[both], axis=1))
    assert np.degrees(np.arccos(np.clip(np.median(cos), -1, 1))) < 5.0
    assert np.all(result.fiber[result.labels != 1] == 0)


def test_mri_alone_cannot_separate_the_muscles(leg, result):
    # the paper's point: adjacent muscles look alike on MRI and differ in fibre direction
    ph = leg[0]
    mri_only = run(leg, multiphase=MultiphaseConfig(fiber_channels="none"))
    with_fibres = seed_region_dice(ph, result)
    without = seed_region_dice(ph, mri_only)
    assert with_fibres.mean() > 0.85
    assert without.mean() < 0.6
    # after the nearest-seed fall-back the final muscles are still clearly worse
    assert (muscle_dice(ph, mri_only.muscle_id).mean()
            < muscle_dice(ph, result.muscle_id).mean() - 0.1)


def test_volume_mode(leg):
    res = run(leg, mode="3d")
    ph = leg[0]
    assert dice(res.labels == 4, ph.labels == 4) >= 0.95
    assert muscle_dice(ph, res.muscle_id).mean() >= 0.90


def test_seed_outside_any_muscle(leg):
    ph, d, covered, seeds = leg
    bad = dict(seeds, soleus=[list((ph.affine @ [2.0, 2.0, 1.0, 1.0])[:3])])  # in the air
    cfg = SegmentConfig(seeds=bad)
    with pytest.raises(InputError, match="soleus"):
        segment_volume(ph.mri, ph.affine, d, covered, ph.imct_mask, ph.imat_mask, cfg)


def test_segment_stage_files(leg, result, tmp_path):
    from pixmuscle.config import parse_section
    from pixmuscle.stages.segment import run_segment
    from pixmuscle.synth.write import write_phantom

    ph, _, _, seeds = leg
    files = write_phantom(ph, tmp_path / "in", "leg")
    cfg = parse_section(SegmentConfig, {
        "mri": str(files["mri"]), "dti_tensor": str(files["dti_tensor"]),
        "imct_mask": str(files["imct"]), "imat_mask": str(files["imat"]), "seeds": seeds,
    }, "segment", tmp_path)
    out = tmp_path / "out" / "segmentation.h5"
    res = run_segment(cfg, out)
    # the files carry what was computed, on the same grid as the phantom (RAS+ already)
    with open_stage(out, schema="pixmuscle.segmentation", version=1) as f:
        np.testing.assert_array_equal(f["labels"][...], res.labels)
        np.testing.assert_array_equal(f["muscle_id"][...], res.muscle_id)
        assert [n.decode() if isinstance(n, bytes) else n for n in f["muscle_names"][...]] \
            == ph.muscle_names
        assert f["fiber"].shape == ph.mri.shape + (3,) and f["fiber"].dtype == np.float32
        np.testing.assert_allclose(f["affine"][...], ph.affine, atol=1e-6)
        assert f["affine"].attrs["units"] == "cm"
    lab = load_volume(out.with_name("segmentation_labels.nii.gz"), kind="labels")
    np.testing.assert_array_equal(lab.data, res.labels)
    fib = load_volume(out.with_name("segmentation_fibers.nii.gz"), kind="vectors")
    np.testing.assert_allclose(fib.data, res.fiber, atol=1e-6)
    pngs = sorted((tmp_path / "out" / "segmentation_qc").glob("slice_*.png"))
    assert len(pngs) == ph.mri.shape[2]
    # the NIfTI round trip (mm on disk) does not change the segmentation
    assert np.mean(res.labels == result.labels) > 0.999
    with h5py.File(out) as f:
        assert "seed_voxels_ijk" in f["qc"]
    # missing inputs are reported by key
    with pytest.raises(InputError, match="dti"):
        run_segment(dataclasses.replace(cfg, dti_tensor=None), tmp_path / "x.h5")


def test_seed_next_to_a_muscle_is_moved_with_a_warning(leg):
    """A click one or two voxels off the muscle (on a voxel without fibre data: here a fat or
    connective-tissue voxel) is moved to the nearest muscle voxel, and the stage says so."""
    from pixmuscle.io.lineage import capture_warnings

    ph, d, covered, seeds = leg
    k = ph.mri.shape[2] // 2
    sol = ph.muscle_names.index("soleus") + 1
    near = ndi.distance_transform_edt(ph.muscle_id[:, :, k] != sol)
    off = np.argwhere((near >= 1.5) & (near <= 2.5) & np.isin(ph.labels[:, :, k], (3, 4)))[0]
    moved = dict(seeds, soleus=[list((ph.affine @ [off[0], off[1], k, 1.0])[:3])])
    with capture_warnings() as w:
        res = segment_volume(ph.mri, ph.affine, d, covered, ph.imct_mask, ph.imat_mask, SegmentConfig(seeds=moved))
    assert any(x.startswith("segment.seeds.soleus: seed at voxel") and "moved" in x for x in w), w
    assert dice(res.muscle_id == sol, ph.muscle_id == sol) >= 0.85

"""Segmentation QC (pixmuscle.segmentation.qc): bones or the outline that vanish or jump in area between
neighbouring slices, and muscles assigned mostly by the nearest-seed fall-back — on label volumes built
here (so what is wrong is known) and on the old 0.312 cm demo phantom, whose bones the level sets lose."""

from __future__ import annotations

import json

import h5py
import numpy as np
from scipy import ndimage as ndi

from pixmuscle.segmentation.multiphase import regions_to_muscles
from pixmuscle.segmentation.qc import bone_areas, fallback_findings, segmentation_findings, slice_jumps

H = 0.25  # cm, pixel of the constructed volumes
AFFINE = np.diag([H, H, 0.5, 1.0])


def _disk(shape, centre, radius):
    i, j = np.indices(shape)
    return (i - centre[0]) ** 2 + (j - centre[1]) ** 2 <= radius**2


def tapered_leg(n_slices=8, taper=0.02):
    """Labels (40, 40, K): a fat-covered muscle disk with two bones, all shrinking by ``taper`` per slice."""
    lab = np.zeros((40, 40, n_slices), np.int16)
    for k in range(n_slices):  # a few slices
        s = 1.0 - taper * k
        lab[..., k][_disk((40, 40), (20, 20), 16 * s)] = 3
        lab[..., k][_disk((40, 40), (20, 20), 14 * s)] = 1
        lab[..., k][_disk((40, 40), (14, 20), 4.0 * s)] = 4
        lab[..., k][_disk((40, 40), (27, 20), 2.5 * s)] = 4
    return lab


def test_smooth_taper_has_no_finding():
    lab = tapered_leg()
    assert segmentation_findings(lab, AFFINE) == []
    areas = bone_areas(lab == 4)
    assert areas.shape == (8, 2)
    np.testing.assert_array_equal(areas.sum(axis=1), (lab == 4).reshape(-1, 8).sum(axis=0))


def test_a_bone_removed_in_one_slice_is_found_in_that_slice_only():
    lab = tapered_leg()
    gone = _disk((40, 40), (27, 20), 3.0)
    lab[..., 4][gone & (lab[..., 4] == 4)] = 1  # the small bone became muscle in slice 4
    found = segmentation_findings(lab, AFFINE)
    assert len(found) == 1, [f.message for f in found]
    f = found[0]
    assert f.check == "bone" and f.slices == (4,)
    assert f.subject.startswith("bone 2 of 2") and "x = 6.75, y = 5 cm" in f.subject  # centre (27, 20) px × 0.25 cm
    assert "missing in slice(s) 4" in f.message


def test_a_bone_much_smaller_in_one_slice_is_a_jump():
    lab = tapered_leg()
    big = _disk((40, 40), (14, 20), 5.0)
    lab[..., 3][big & (lab[..., 3] == 4)] = 1
    lab[..., 3][_disk((40, 40), (14, 20), 2.5)] = 4  # area 21 instead of about 46 pixels
    found = segmentation_findings(lab, AFFINE)
    assert [f.check for f in found] == ["bone"]
    assert found[0].slices == (2, 3, 4) and "more than 30 %" in found[0].message
    assert found[0].subject.startswith("bone 1 of 2")


def test_outline_that_vanishes_or_shrinks():
    lab = tapered_leg()
    lab[..., 0] = 0  # nothing segmented in the first slice
    found = segmentation_findings(lab, AFFINE)
    outline = [f for f in found if f.check == "outline"]
    assert len(outline) == 1 and outline[0].slices == (0,)
    assert {f.check for f in found} == {"outline", "bone"}  # the bones are missing there too
    lab = tapered_leg()
    lab[..., 5][~_disk((40, 40), (20, 20), 11)] = 0  # the outline cut to a smaller disk
    found = segmentation_findings(lab, AFFINE)
    assert [f.check for f in found] == ["outline"] and found[0].slices == (4, 5, 6)


def test_slice_jumps_thresholds():
    vanished, jumped, change = slice_jumps([10, 10, 0, 10], max_change=0.3)
    assert vanished.tolist() == [1, 2] and jumped.tolist() == []
    np.testing.assert_allclose(change, [0.0, 1.0, 1.0])
    assert slice_jumps([100, 69, 100])[1].tolist() == [0, 1]  # 31 % down, 31 % up
    assert slice_jumps([100, 75, 100])[1].tolist() == []
    # a few pixels of a small bone are not a failure
    assert [a.tolist() for a in slice_jumps([10, 6, 10], min_change=4)[:2]] == [[], []]
    assert slice_jumps([0, 0, 0])[0].tolist() == []


def test_muscle_assigned_by_the_nearest_seed_fallback():
    # muscle A: a left block that is one region; muscle B: its seed in a 2 × 2 island of its own region,
    # the rest of the right half a third region no seed claims (assigned to the nearest claimed voxel)
    regions = np.zeros((20, 10), np.int16)
    regions[10:] = 2
    regions[14:16, 4:6] = 1
    domain = np.ones_like(regions, bool)
    mid, info = regions_to_muscles(regions, domain, [np.array([[3, 5]]), np.array([[14, 4]])])
    claimed = (regions == 0) | (regions == 1)  # what the level sets gave each muscle (known here)
    np.testing.assert_array_equal(info["muscle_voxels"], [np.sum(mid == 1), np.sum(mid == 2)])
    np.testing.assert_array_equal(info["fallback_voxels"], [np.sum((mid == 1) & ~claimed), np.sum((mid == 2) & ~claimed)])
    assert info["fallback_voxels"][0] > 0 and info["fallback_voxels"][1] > 0.8 * info["muscle_voxels"][1]
    found = fallback_findings(info["fallback_voxels"], info["muscle_voxels"], ["A", "B"])
    assert [f.subject for f in found] == ["B"] and f"{int(info['fallback_voxels'][1])} of" in found[0].message
    # a component shared by two seeds is split by nearest seed: all of it is fall-back
    _, info = regions_to_muscles(np.zeros((8, 4), np.int16), np.ones((8, 4), bool), [np.array([[1, 1]]), np.array([[6, 2]])])
    np.testing.assert_array_equal(info["fallback_voxels"], info["muscle_voxels"])
    assert len(fallback_findings(info["fallback_voxels"], info["muscle_voxels"], ["A", "B"])) == 2


def test_old_coarse_demo_phantom_loses_its_bones_and_the_stage_says_so(tmp_path):
    """The 0.312 cm leg phantom that the demo used before: the level sets lose the bones in some slices
    (bone Dice 0.38); the segment stage now warns, and the warning is in segmentation.h5."""
    from pixmuscle.config import parse_section
    from pixmuscle.io.lineage import stage_record
    from pixmuscle.segmentation.config import SegmentConfig
    from pixmuscle.segmentation.scoring import dice
    from pixmuscle.stages.segment import run_segment
    from pixmuscle.synth.leg import make_leg_phantom
    from pixmuscle.synth.write import write_phantom

    ph = make_leg_phantom(shape=(48, 48, 5), pixel_cm=0.312, slice_cm=0.5, seed=0)
    files = write_phantom(ph, tmp_path / "in", "old_demo")
    k = ph.mri.shape[2] // 2
    seeds = {}
    for m, name in enumerate(ph.muscle_names, 1):  # one click per muscle: its deepest voxel in the middle slice
        depth = ndi.distance_transform_edt(ph.muscle_id[:, :, k] == m)
        i, j = np.unravel_index(np.argmax(depth), depth.shape)
        seeds[name] = [list((ph.affine @ [i, j, k, 1.0])[:3])]
    cfg = parse_section(SegmentConfig, {"mri": str(files["mri"]), "dti_tensor": str(files["dti_tensor"]),
                                        "imct_mask": str(files["imct"]), "imat_mask": str(files["imat"]),
                                        "seeds": seeds, "qc_png": False}, "segment", tmp_path)
    out = tmp_path / "seg" / "segmentation.h5"
    res = run_segment(cfg, out)
    assert dice(res.labels == 4, ph.labels == 4) < 0.6  # the failure is real
    assert any(f.check == "bone" for f in res.findings)
    with h5py.File(out) as f:
        warnings = json.loads(f.attrs["warnings"])
    assert any(w.startswith("segmentation QC: bone") and "missing in slice(s)" in w for w in warnings), warnings
    # what every downstream stage file (model, results) carries into the report
    assert any(w.startswith("segmentation QC: bone") for w in stage_record(out)[-1]["warnings"])

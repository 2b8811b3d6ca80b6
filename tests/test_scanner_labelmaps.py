"""Label maps from 3D Slicer (.seg.nrrd, written here with pynrrd) and ITK-SNAP (NIfTI + label description file)
build the same model as the NIfTI labels of the bundled SYNTHETIC demo phantom; the segment stage's own
.seg.nrrd given back as build_model.labels (a segmentation corrected by hand, here unchanged) rebuilds the
segmentation's model; layers, cropped extents and grids are placed through the affines; names that map to
nothing, and maps that cannot be placed, stop with the file named."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

nrrd = pytest.importorskip("nrrd")

from pixmuscle.config import parse_section  # noqa: E402
from pixmuscle.errors import InputError  # noqa: E402
from pixmuscle.imaging.nifti import load_volume, save_volume  # noqa: E402
from pixmuscle.io.labelmap import read_label_map, write_seg_nrrd  # noqa: E402
from pixmuscle.model.config import BuildModelConfig  # noqa: E402
from pixmuscle.stages.build_model import _build  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "data" / "synthetic"
NAMES = ["tibialis_anterior", "extensor_digitorum_longus", "peroneus_longus", "tibialis_posterior", "soleus",
         "medial_gastrocnemius", "lateral_gastrocnemius"]


def _truth():
    """The phantom's labels as one map: muscle m → m, connective tissue 12, fat 13, bone 14."""
    lab = load_volume(DATA / "leg_demo_labels.nii.gz", kind="labels")
    mid = load_volume(DATA / "leg_demo_muscle_id.nii.gz", kind="labels").data
    combined = np.where(lab.data == 1, mid, 0).astype(np.int32)
    for code in (2, 3, 4):
        combined[lab.data == code] = 10 + code
    return combined, lab.affine


TISSUES = {12: "connective_tissue", 13: "fat", 14: "bone"}


def _model(tmp_path, section: dict):
    cfg = parse_section(BuildModelConfig, section, "build_model", tmp_path)
    return _build(cfg, None)[0]


def _same(a, b):
    for k in ("ijk", "tissue", "muscle_id", "spacing", "origin", "shape"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k), err_msg=k)
    np.testing.assert_allclose(a.fiber, b.fiber, atol=1e-12)
    assert list(a.muscle_names) == list(b.muscle_names)


def _nifti_route(tmp_path):
    combined, affine = _truth()
    save_volume(tmp_path / "combined.nii.gz", combined, affine, kind="labels")
    tmap = {0: "background", **{m + 1: {"muscle": n} for m, n in enumerate(NAMES)}, **TISSUES}
    return _model(tmp_path, {"labels": "combined.nii.gz", "tissue_map": tmap,
                             "fibers": str(DATA / "leg_demo_fibers.nii.gz")})


def test_slicer_segmentation_builds_the_nifti_model(tmp_path):
    """Segment names map through label_names (the muscles' Slicer names) and the tissue names map themselves."""
    combined, affine = _truth()
    names = {**{m + 1: n.replace("_", " ").title() for m, n in enumerate(NAMES)}, **TISSUES}
    write_seg_nrrd(tmp_path / "labels.seg.nrrd", combined, affine, names)
    header = nrrd.read_header(str(tmp_path / "labels.seg.nrrd"))
    assert header["Segment0_Name"] == "Tibialis Anterior" and header["space"] == "left-posterior-superior"
    label_names = {n.replace("_", " ").title(): {"muscle": n} for n in NAMES}
    model = _model(tmp_path, {"labels": "labels.seg.nrrd", "label_names": label_names,
                              "fibers": str(DATA / "leg_demo_fibers.nii.gz")})
    _same(model, _nifti_route(tmp_path))


def test_itksnap_labels_with_descriptions_build_the_nifti_model(tmp_path):
    combined, affine = _truth()
    save_volume(tmp_path / "snap.nii.gz", combined, affine, kind="labels")
    lines = ["################################################", "# ITK-SnAP Label Description File",
             '    0     0    0    0        0  0  0    "Clear Label"']
    lines += [f'  {m + 1:3d}   255    0    0        1  1  1    "{n}"' for m, n in enumerate(NAMES)]
    lines += [f'  {v:3d}     0  255    0        1  1  1    "{t}"' for v, t in TISSUES.items()]
    (tmp_path / "snap.txt").write_text("\n".join(lines) + "\n")
    label_names = {n: {"muscle": n} for n in NAMES}
    model = _model(tmp_path, {"labels": "snap.nii.gz", "label_descriptions": "snap.txt", "label_names": label_names,
                              "fibers": str(DATA / "leg_demo_fibers.nii.gz")})
    _same(model, _nifti_route(tmp_path))


def test_the_segment_stage_segmentation_given_back_rebuilds_its_model(tmp_path):
    """segmentation.seg.nrrd as written by the segment stage, given back with the segmentation: muscle names map
    themselves, fibres come from the segmentation, and the model is the segmentation's own."""
    import dataclasses

    from pixmuscle.pipeline import load_config
    from pixmuscle.stages.segment import run_segment

    seg = dataclasses.replace(load_config(ROOT / "configs" / "demo.yaml").segment, qc_png=False)
    run_segment(seg, tmp_path / "segmentation.h5")
    assert read_label_map(tmp_path / "segmentation.seg.nrrd").names[1] == seg_name(seg)
    plain = _model(tmp_path, {"segmentation": "segmentation.h5"})
    corrected = _model(tmp_path, {"segmentation": "segmentation.h5", "labels": "segmentation.seg.nrrd"})
    _same(corrected, plain)


def seg_name(seg):
    return list(seg.seeds)[0]


def test_layers_are_merged_and_a_cropped_extent_is_placed(tmp_path):
    """A two-layer Slicer file (overlapping segments in different layers, the later wins) cropped to its extent
    with the origin moved accordingly lands on the full grid where the segments are."""
    combined, affine = _truth()
    lo, hi = np.array([20, 15, 1]), np.array([70, 80, 4])
    crop = combined[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
    layer0 = np.where(crop == 5, 1, 0) + np.where(crop == 14, 2, 0)      # soleus 1, bone 2
    layer1 = np.where(np.isin(crop, (5, 6)), 1, 0)                        # gastrocnemius over soleus
    data = np.stack([layer0, layer1]).astype(np.uint8)
    lps = np.diag([-1.0, -1.0, 1.0])
    header = {"type": "unsigned char", "dimension": 4, "space": "left-posterior-superior",
              "kinds": ["list", "domain", "domain", "domain"],
              "space directions": np.vstack([np.full(3, np.nan), (lps @ affine[:3, :3] * 10).T]),
              "space origin": lps @ (affine[:3, :3] @ lo + affine[:3, 3]) * 10, "encoding": "gzip",
              "Segment0_Name": "soleus", "Segment0_LabelValue": "1", "Segment0_Layer": "0",
              "Segment1_Name": "bone", "Segment1_LabelValue": "2", "Segment1_Layer": "0",
              "Segment2_Name": "medial_gastrocnemius", "Segment2_LabelValue": "1", "Segment2_Layer": "1"}
    nrrd.write(str(tmp_path / "layers.seg.nrrd"), data, header, index_order="F")
    lm = read_label_map(tmp_path / "layers.seg.nrrd")
    assert lm.names == {1: "soleus", 2: "bone", 3: "medial_gastrocnemius"}
    assert any("overlaps" in n for n in lm.notes)
    from pixmuscle.imaging.resample import resample_labels

    placed = resample_labels(lm.labels, lm.affine, combined.shape, affine)
    expected = np.zeros_like(combined)
    box = np.zeros(combined.shape, bool)
    box[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]] = True
    expected[box & (combined == 5)] = 1
    expected[box & (combined == 14)] = 2
    expected[box & np.isin(combined, (5, 6))] = 3
    np.testing.assert_array_equal(placed, expected)


def test_names_that_match_nothing_stop_naming_the_file(tmp_path):
    combined, affine = _truth()
    write_seg_nrrd(tmp_path / "x.seg.nrrd", combined, affine,
                   {**{m + 1: f"Segment_{m + 1}" for m in range(7)}, **TISSUES})
    with pytest.raises(InputError, match=r"x\.seg\.nrrd: label\(s\) 'Segment_1'.*build_model\.label_names"):
        _model(tmp_path, {"labels": "x.seg.nrrd"})
    with pytest.raises(InputError, match="'segment_9' name"):
        _model(tmp_path, {"labels": "x.seg.nrrd", "label_names": {
            **{f"Segment_{m + 1}": {"muscle": n} for m, n in enumerate(NAMES)}, "Segment_9": "fat"}})


def test_a_map_without_geometry(tmp_path):
    """No geometry: on the segmentation's grid when the shapes agree (a warning), else exit 2; alone, exit 2."""
    combined, _ = _truth()
    nrrd.write(str(tmp_path / "bare.nrrd"), combined[:, :, :4].astype(np.uint8), index_order="F")
    with pytest.raises(InputError, match="bare.nrrd: the label map has no geometry"):
        _model(tmp_path, {"labels": "bare.nrrd"})
    import h5py

    from pixmuscle.io.segmentation import write_segmentation  # noqa: F401  (the segmentation below is the stage's)

    (tmp_path / "s").mkdir()
    import dataclasses

    from pixmuscle.pipeline import load_config
    from pixmuscle.stages.segment import run_segment

    run_segment(dataclasses.replace(load_config(ROOT / "configs" / "demo.yaml").segment, qc_png=False),
                tmp_path / "s" / "segmentation.h5")
    with h5py.File(tmp_path / "s" / "segmentation.h5") as f:
        shape = f["labels"].shape
    assert shape != combined[:, :, :4].shape
    with pytest.raises(InputError, match=r"bare.nrrd: the label map has no geometry and its grid \(96, 96, 4\) differs"):
        _model(tmp_path, {"labels": "bare.nrrd", "segmentation": "s/segmentation.h5", "tissue_map": {1: "muscle"}})


def test_cli_exit_2_for_unmapped_segments(tmp_path):
    combined, affine = _truth()
    write_seg_nrrd(tmp_path / "x.seg.nrrd", combined, affine, {**{m + 1: f"Segment_{m + 1}" for m in range(7)}, **TISSUES})
    cfg = {"title": "t", "synthetic": True, "output_dir": str(tmp_path / "out"), "models": ["fine"],
           "build_model": {"labels": str(tmp_path / "x.seg.nrrd"), "fibers": str(DATA / "leg_demo_fibers.nii.gz")}}
    (tmp_path / "c.yaml").write_text(yaml.safe_dump(cfg))
    run = subprocess.run([sys.executable, "-m", "pixmuscle.cli", "run", str(tmp_path / "c.yaml"), "--until",
                          "build-model"], capture_output=True, text=True)
    assert run.returncode == 2, run.stderr
    assert "x.seg.nrrd" in run.stderr and "Segment_1" in run.stderr

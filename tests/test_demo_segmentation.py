"""`make demo`'s segmentation (configs/demo.yaml on the committed SYNTHETIC leg_demo phantom) scored against
the phantom's own truth (data/synthetic/leg_demo_labels.nii.gz, leg_demo_muscle_id.nii.gz): the outline,
the bones and the muscles are found, and segmentation QC has nothing to say."""

from __future__ import annotations

import json
from pathlib import Path

import h5py

from pixmuscle.imaging.nifti import load_volume
from pixmuscle.pipeline import load_config
from pixmuscle.segmentation.scoring import score_segmentation
from pixmuscle.stages.segment import run_segment

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "data" / "synthetic"


def test_demo_segmentation_matches_the_phantom_truth(tmp_path):
    import dataclasses

    cfg = dataclasses.replace(load_config(ROOT / "configs" / "demo.yaml").segment, qc_png=False)
    out = tmp_path / "segmentation.h5"
    res = run_segment(cfg, out)
    truth = json.loads((DATA / "leg_demo_truth.json").read_text())
    assert res.muscle_names == truth["muscle_names"]
    score = score_segmentation(res.labels, res.muscle_id, load_volume(DATA / "leg_demo_labels.nii.gz", kind="labels").data,
                               load_volume(DATA / "leg_demo_muscle_id.nii.gz", kind="labels").data, res.muscle_names)
    assert score["outline"] >= 0.95, score
    assert score["tissues"]["bone"] >= 0.95, score
    assert score["muscle_mean"] >= 0.90 and score["muscle_min"] >= 0.80, score
    assert res.findings == []
    with h5py.File(out) as f:
        assert not [w for w in json.loads(f.attrs["warnings"]) if w.startswith("segmentation QC")]

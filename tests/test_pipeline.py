"""`pixmuscle run` end to end on a tiny synthetic phantom: stages, skip/resume, cohorts, report contents."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import h5py
import meshio
import numpy as np
import pytest
import yaml
from fixtures_results import write_mg_phantom

from pixmuscle.pipeline import load_subjects, run_pipeline, run_subject


@pytest.fixture(scope="module")
def phantom_dir(tmp_path_factory):
    """A tiny SYNTHETIC medial-gastrocnemius phantom (48 × 32 × 3 voxels) written as NIfTI."""
    return write_mg_phantom(tmp_path_factory.mktemp("phantom"))


def _config(phantom_dir, out_dir, *, steps=2, subjects=None) -> dict:
    d, seed = phantom_dir
    cfg = {
        "title": "tiny test phantom",
        "synthetic": True,
        "output_dir": str(out_dir),
        "models": ["coarse"],
        "segment": {
            "mri": str(d / "mg_mri.nii.gz"), "dti_tensor": str(d / "mg_dti_tensor.nii.gz"),
            "imct_mask": str(d / "mg_imct.nii.gz"), "imat_mask": str(d / "mg_imat.nii.gz"),
            "seeds": {"medial_gastrocnemius": [seed]},
        },
        "build_model": {},
        "coarsen": {"factor": 2},
        "solve": {
            "steps": steps, "activation": {"from": 0.0, "to": 0.5},
            "boundary_conditions": [{"nodes": "z_min", "fix": ["x", "y", "z"]},
                                    {"nodes": "z_max", "fix": ["x", "y", "z"]}],
        },
        "report": {"vtu": True, "slices": True, "html": True},
    }
    if subjects is not None:
        cfg["subjects"] = subjects
    return cfg


def _write(tmp_path, cfg) -> Path:
    p = tmp_path / "config.yaml"
    p.write_text(yaml.safe_dump(cfg))
    return p


@pytest.fixture
def first_run(phantom_dir, tmp_path):
    """A full run of this test's own (the tiny phantom runs in seconds): tests may change it freely.

    Not shared between tests: its outputs record their absolute input paths, so a copy in another
    folder would not be the same run, and a shared one would make the tests depend on their order.
    """
    cfg_path = _write(tmp_path, _config(phantom_dir, tmp_path / "out"))
    summary = run_subject(load_subjects(cfg_path)[0])
    return cfg_path, summary


def test_run_end_to_end(first_run):
    cfg_path, summary = first_run
    out = Path(summary["output_dir"])
    assert summary["ran"] == ["segment", "build-model", "coarsen", "solve (coarse)", "report"]
    for name in ["segmentation.h5", "model.h5", "model_coarse.h5", "results_coarse.h5", "report/index.html"]:
        assert (out / name).exists(), name
    # report numbers are the results' numbers (independent read with h5py)
    with h5py.File(out / "results_coarse.h5") as f:
        alpha = f["steps/alpha"][()]
        r_top = f["steps/reaction/z_max"][()]
        u_last = f["steps/u"][-1]
        n_nodes = f["nodes/X"].shape[0]
    with open(out / "report/force_activation.csv") as fh:
        rows = list(csv.DictReader(fh))
    np.testing.assert_allclose([float(r["alpha"]) for r in rows], alpha, rtol=1e-12)
    rz = [k for k in rows[0] if k.startswith("z_max.Rz")][0]
    np.testing.assert_allclose([float(r[rz]) for r in rows], r_top[:, 2], rtol=1e-9, atol=1e-12)
    # an activated muscle held at both ends pulls on them: tension at the top end (z-up support force)
    assert r_top[-1, 2] > 0
    assert sorted((out / "report").rglob("*.vtu"))
    with meshio.xdmf.TimeSeriesReader(out / "report" / "fields.xdmf") as xr:  # same series as the VTUs
        _, cells = xr.read_points_cells()
        _, _, cd = xr.read_data(xr.num_steps - 1)
    assert cells[0].data.shape == (n_nodes, 8)  # one voxel cell per node
    for field in ["displacement [cm]", "fiber_direction [1]", "tissue", "muscle_id", "max_principal_cauchy [N/cm^2]"]:
        assert field in cd, field
    np.testing.assert_allclose(cd["displacement [cm]"][0], u_last, rtol=1e-6, atol=1e-12)
    html = (out / "report/index.html").read_text()
    assert "data:image/png;base64" in html and "synthetic" in html.lower()
    # segmentation QC in the report: per-slice areas equal the voxel counts of segmentation.h5 (h5py)
    assert "Segmentation QC" in html and (out / "report" / "segmentation_qc.png").exists()
    with h5py.File(out / "segmentation.h5") as f:
        labels, aff = f["labels"][()], f["affine"][()]
    px = np.prod(np.linalg.norm(aff[:3, :3], axis=0)[:2])
    with open(out / "report/segmentation_areas.csv") as fh:
        areas = list(csv.DictReader(fh))
    np.testing.assert_allclose([float(r["muscle [cm^2]"]) for r in areas], (labels == 1).sum(axis=(0, 1)) * px, rtol=1e-12)


def test_rerun_skips_and_config_change_reruns_only_downstream(first_run):
    cfg_path, summary = first_run
    cfg = load_subjects(cfg_path)[0]
    again = run_subject(cfg)
    assert again["skipped"] == ["segment", "build-model", "coarsen", "solve (coarse)"]
    # a solve-section change redoes the solve only
    raw = yaml.safe_load(cfg_path.read_text())
    raw["solve"]["activation"]["to"] = 0.4
    cfg_path.write_text(yaml.safe_dump(raw))
    changed = run_subject(load_subjects(cfg_path)[0])
    assert changed["skipped"] == ["segment", "build-model", "coarsen"]
    assert "solve (coarse)" in changed["ran"]
    # --force redoes everything; --from/--until pick stages
    forced = run_subject(load_subjects(cfg_path)[0], force=True, start="coarsen", until="coarsen")
    assert forced["ran"] == ["coarsen"] and forced["skipped"] == []


def test_changed_input_file_reruns(first_run, tmp_path):
    cfg_path, summary = first_run
    cfg = load_subjects(cfg_path)[0]
    model = Path(summary["output_dir"]) / "model.h5"
    with h5py.File(model, "a") as f:        # tamper with an intermediate: coarsen must notice
        f.attrs["tampered"] = 1
    again = run_subject(cfg, until="coarsen")
    assert "coarsen" in again["ran"]


def test_cohort_with_one_broken_subject(phantom_dir, tmp_path):
    d, _ = phantom_dir
    broken = tmp_path / "broken_mri.nii.gz"
    broken.write_bytes(b"this is not a NIfTI file")
    subjects = [
        {"name": "good"},
        {"name": "missing", "segment": {"mri": str(tmp_path / "does_not_exist.nii.gz")}},
        {"name": "corrupt", "segment": {"mri": str(broken)}},
    ]
    cfg_path = _write(tmp_path, _config(phantom_dir, tmp_path / "cohort", steps=1, subjects=subjects))
    ok = run_pipeline(cfg_path)
    assert ok is False
    status = json.loads((tmp_path / "cohort" / "cohort_status.json").read_text())
    assert [s["name"] for s in status["ok"]] == ["good"]
    failed = {f["name"]: f["error"] for f in status["failed"]}
    assert "does_not_exist.nii.gz" in failed["missing"] and "file not found" in failed["missing"]
    assert "broken_mri.nii.gz" in failed["corrupt"]
    assert (tmp_path / "cohort" / "good" / "report" / "index.html").exists()
    assert (tmp_path / "cohort" / "cohort.html").exists()


def test_cohort_until_segment_writes_no_cohort_page(phantom_dir, tmp_path):
    """A cohort stopped before its reports (``--until segment``) succeeds and writes no cohort page."""
    subjects = [{"name": "a"}, {"name": "b"}]
    cfg_path = _write(tmp_path, _config(phantom_dir, tmp_path / "cohort", steps=1, subjects=subjects))
    assert run_pipeline(cfg_path, until="segment") is True
    assert (tmp_path / "cohort" / "a" / "segmentation.h5").exists()
    assert not (tmp_path / "cohort" / "cohort.html").exists()

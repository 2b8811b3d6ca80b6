"""Coarse and fine models of one case in every report output (paper Example 2's convergence check).

A tiny real run (labels → model → coarse model → two solves → one report); the difference table is
checked against an independent recomputation from the two results files (h5py, reaction · n_out).
"""

from __future__ import annotations

import csv
import json

import h5py
import nibabel as nib
import numpy as np
import pytest
import yaml

from pixmuscle.pipeline import run_pipeline
from pixmuscle.report.convergence import convergence_table, force_at


def _end_force(path):
    """Mean axial end force per state from a results file: R(z_max)·(+z) and R(z_min)·(−z)."""
    with h5py.File(path, "r") as f:
        r = f["steps/reaction"]
        fz = 0.5 * (r["z_max"][()][:, 2] - r["z_min"][()][:, 2])
        return f["steps/alpha"][()], fz, f["steps/converged"][()].astype(bool)


@pytest.fixture(scope="module")
def two_models(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("models")
    lab = np.zeros((8, 6, 4), np.int16)
    lab[1:7, 1:5, :] = 1            # muscle
    lab[1:7, 1, :] = 2              # a connective-tissue sheet
    lab[3, 3, 1:3] = 3              # an IMAT pocket
    nib.save(nib.Nifti1Image(lab, np.diag([2.0, 2.0, 5.0, 1.0])), tmp / "labels.nii.gz")  # mm
    cfg = {
        "title": "two models", "synthetic": True, "output_dir": "out", "models": ["coarse", "fine"],
        "build_model": {"labels": "labels.nii.gz",
                        "tissue_map": {0: "background", 1: {"muscle": "block", "fiber": [0, 0.2, 1]},
                                       2: "connective_tissue", 3: "fat"}},
        "coarsen": {"factor": 2},
        "solve": {"steps": 3, "activation": {"from": 0.0, "to": 0.6},
                  "boundary_conditions": [{"nodes": "z_min", "fix": ["x", "y", "z"]},
                                          {"nodes": "z_max", "fix": ["x", "y", "z"]}]},
        "report": {"view3d": False, "segmentation_qc": False},
    }
    (tmp / "case.yaml").write_text(yaml.safe_dump(cfg))
    run_pipeline(tmp / "case.yaml")
    return tmp / "out"


def test_both_models_in_every_output(two_models):
    rep = two_models / "report"
    s = json.loads((rep / "summary.json").read_text())
    assert set(s["models"]) == {"coarse", "fine"}
    assert s["models"]["fine"]["n_nodes"] > s["models"]["coarse"]["n_nodes"]
    for k in ("coarse", "fine"):
        assert s["models"][k]["F_max_N"] > 0
        assert len(s["models"][k]["curve"]["end_force_N"]) == 4
    with open(rep / "force_activation.csv") as fh:
        header = next(csv.reader(fh))
    assert "end_force coarse [N]" in header and "end_force fine [N]" in header
    for f in ("force_activation.csv", "tissue_table.csv", "summary.json", "fields.pvd", "slices_displacement.png"):
        assert (rep / "coarse" / f).is_file(), f
    assert (rep / "fields.pvd").is_file() and (rep / "slices_displacement.png").is_file()
    page = (rep / "index.html").read_text()
    assert "Models compared" in page and "Tissue volumes — coarse model" in page and "coarse model: " in page
    assert s["outputs"]["convergence_csv"].endswith("convergence.csv")


def test_difference_table_recomputed_from_the_results_files(two_models):
    s = json.loads((two_models / "report" / "summary.json").read_text())
    conv = s["convergence"]
    assert conv["reference"] == "fine" and conv["models"] == ["coarse", "fine"]
    ac, fc, cc = _end_force(two_models / "results_coarse.h5")
    af, ff, cf = _end_force(two_models / "results_fine.h5")
    assert conv["F_max_N"]["fine"] == pytest.approx(ff[cf].max(), rel=1e-9)
    assert conv["F_max_N"]["coarse"] == pytest.approx(fc[cc].max(), rel=1e-9)
    rel = (fc[cc].max() - ff[cf].max()) / ff[cf].max()
    assert conv["F_max_relative_difference"]["coarse"] == pytest.approx(rel, rel=1e-9)
    for row in conv["rows"][:-1]:     # one row per converged α of the fine model
        i = int(np.argmin(np.abs(af - row[0])))
        j = int(np.argmin(np.abs(ac - row[0])))
        assert ac[j] == pytest.approx(row[0])    # same activation steps: no interpolation needed
        assert row[1] == pytest.approx(fc[j], rel=1e-9, abs=1e-12)
        assert row[2] == pytest.approx(ff[i], rel=1e-9, abs=1e-12)
        assert row[3] == pytest.approx(fc[j] - ff[i], rel=1e-9, abs=1e-9)
    with open(two_models / "report" / "convergence.csv") as fh:
        assert len(list(csv.reader(fh))) == len(conv["rows"]) + 1


def test_the_finest_model_is_the_headline_with_its_discretisation_estimate(two_models):
    """Config order "coarse, fine": the report's answer is still the fine model, and the difference to the
    coarse one is shown as its discretisation estimate, first in summary.json and on the page's first screen."""
    rep = two_models / "report"
    s = json.loads((rep / "summary.json").read_text())
    ac, fc, cc = _end_force(two_models / "results_coarse.h5")
    af, ff, cf = _end_force(two_models / "results_fine.h5")
    fine, coarse = ff[cf].max(), fc[cc].max()
    assert s["F_max_N"] == pytest.approx(fine, rel=1e-9)
    assert s["results"].endswith("results_fine.h5") and s["n_nodes"] == s["models"]["fine"]["n_nodes"]
    est = s["discretisation"]
    assert est["headline"] == "fine" and est["headline_is_finest"] and est["compared_with"] == "coarse"
    assert est["difference_N"] == pytest.approx(fine - coarse, rel=1e-9)
    assert est["relative"] == pytest.approx((fine - coarse) / fine, rel=1e-9)
    assert est["large"] == (abs(fine - coarse) > 0.02 * fine)
    assert est["large"] == any(w.startswith("discretisation estimate") for w in s["warnings"])
    keys = list(s)
    assert keys.index("F_max_N") < keys.index("discretisation") < keys.index("curve")
    first = (rep / "index.html").read_text().split("<h2>", 1)[0]
    assert "Headline: the fine model" in first and "discretisation estimate" in first
    assert ("larger than 2 %" in first) == est["large"]


def test_discretisation_estimate_warns_above_two_percent():
    from pixmuscle.report.convergence import discretisation_estimate

    a = np.array([0.0, 1.0])
    conv = convergence_table({"c": (a, [0.0, 103.0], [True] * 2), "f": (a, [0.0, 100.0], [True] * 2)}, {"c": 10, "f": 80})
    est = discretisation_estimate(conv, "f", {"c": 10, "f": 80})
    assert est["relative"] == pytest.approx(-0.03) and est["large"] and est["headline_is_finest"]
    conv = convergence_table({"c": (a, [0.0, 101.0], [True] * 2), "f": (a, [0.0, 100.0], [True] * 2)}, {"c": 10, "f": 80})
    assert not discretisation_estimate(conv, "f", {"c": 10, "f": 80})["large"]
    coarse = discretisation_estimate(conv, "c", {"c": 10, "f": 80})
    assert not coarse["headline_is_finest"] and coarse["compared_with"] is None


def test_force_at_interpolates_between_converged_states_only():
    a = np.array([0.0, 0.5, 1.0])
    f = np.array([0.0, 10.0, 30.0])
    out = force_at(a, f, np.array([True, True, False]), np.array([0.25, 0.5, 0.75]))
    assert out[0] == pytest.approx(5.0) and out[1] == pytest.approx(10.0) and np.isnan(out[2])
    t = convergence_table({"c": (a, f * 1.1, [True] * 3), "f": (a, f, [True] * 3)}, {"c": 10, "f": 40})
    assert t["reference"] == "f"
    assert t["F_max_relative_difference"]["c"] == pytest.approx(0.1)
    assert t["max_relative_difference"]["c"] == pytest.approx(0.1)

"""Experiments of several solves: per-muscle force contributions and force–length sweeps.

Truths (:mod:`pixmuscle.mechanics.homogeneous`, the material law alone, no discretisation):

* two muscles side by side along the fibres between roller ends stay homogeneous (F = I) for any
  activation, so each muscle alone gives its own isometric column force and the interaction is 0;
* a one-muscle block between roller ends stretched to λ = L/L0 is the homogeneous uniaxial bar:
  total force at α and passive force at α = 0 match :func:`~homogeneous.uniaxial_bar`, and the
  active force (total − passive) divided by α σ_max A0 is the fibre force–length law f_active(λ)
  of eqs. 24–26 (the active nominal fibre stress of a nearly incompressible bar).
"""

import numpy as np
import pytest

from pixmuscle.config import parse_section
from pixmuscle.errors import InputError
from pixmuscle.io.force_length import load_force_length
from pixmuscle.io.model import save_model
from pixmuscle.io.muscle_forces import load_muscle_forces
from pixmuscle.mechanics import homogeneous
from pixmuscle.mechanics.config import SolveConfig
from pixmuscle.mechanics.experiments import ForceLengthConfig, MuscleForcesConfig, decompose, force_length_cases
from pixmuscle.mechanics.materials import f_active
from pixmuscle.mechanics.solve import make_materials
from pixmuscle.model.tissues import MUSCLE
from pixmuscle.report.config import ReportConfig
from pixmuscle.stages.force_length import run_force_length
from pixmuscle.stages.muscle_forces import run_muscle_forces
from pixmuscle.stages.report import make_report
from pixmuscle.stages.solve import run_solve
from pixmuscle.verify.mechanics import mask_model, roller_bcs


def test_decompose_adds_up():
    dec = decompose(np.array([0.0, 5.0]), np.array([0.0, 1.0]), {"a": np.array([0.0, 2.5]), "b": np.array([0.0, 2.0])})
    assert dec["contribution"]["a"][1] == 1.5 and dec["interaction"][1] == pytest.approx(1.5)
    assert dec["baseline"][1] + sum(c[1] for c in dec["contribution"].values()) + dec["interaction"][1] == 5.0


def test_muscle_forces_of_independent_columns(tmp_path):
    model = mask_model(np.ones((4, 2, 4), bool), (0.2, 0.2, 0.3), tissue=MUSCLE)
    model.muscle_id = np.where(model.ijk[:, 0] < 2, 1, 2).astype(np.int16)
    model.muscle_names = ["medial", "lateral"]
    save_model(tmp_path / "model.h5", model)
    cfg = parse_section(SolveConfig, dict(steps=2, boundary_conditions=roller_bcs(model, 0.0),
                                          activation={"from": 0.0, "to": {"medial": 0.9, "lateral": 0.4}}), "solve")
    run_solve(tmp_path / "model.h5", cfg, tmp_path / "results.h5", progress=False)
    out = run_muscle_forces(tmp_path / "model.h5", cfg, MuscleForcesConfig(), tmp_path / "mf.h5",
                            results_path=tmp_path / "results.h5")
    mf = load_muscle_forces(out)
    mat = make_materials(cfg.materials)[MUSCLE]
    half = 0.4 * 0.4
    for name, a in (("medial", 0.9), ("lateral", 0.4)):
        assert mf["contribution"][name][-1] == pytest.approx(homogeneous.isometric_block(mat, a, half)["force"], rel=2e-3)
        assert mf["contribution"][name][1] == pytest.approx(homogeneous.isometric_block(mat, a / 2, half)["force"],
                                                            rel=2e-3)
    assert abs(mf["interaction"][-1]) < 1e-3 * mf["total"][-1] and np.allclose(mf["baseline"], 0.0, atol=1e-9)
    assert mf["muscles"] == ["medial", "lateral"] and set(mf["runs"]) == {"all", "baseline", "medial", "lateral"}
    # report: the tissue table's F_max column per muscle, the stacked plot and the CSV
    summary = make_report(tmp_path / "results.h5", tmp_path / "report",
                          ReportConfig(vtu=False, slices=False, view3d=False),
                          extra={"muscle_forces": str(out)})
    rows = {r["region"]: r for r in summary["tissue_table"]}
    assert rows["medial"]["F_max [N]"] == pytest.approx(mf["contribution"]["medial"][-1])
    assert rows["lateral"]["F_max [N]"] == pytest.approx(mf["contribution"]["lateral"][-1])
    assert not [w for w in summary["warnings"] if "muscle" in w]
    for name in ("muscle_forces.png", "muscle_forces.csv", "index.html"):
        assert (tmp_path / "report" / name).is_file()
    page = (tmp_path / "report" / "index.html").read_text()
    assert "Force by muscle" in page
    # the table's footnote says what its per-muscle F_max is now (not "volumes only")
    assert "volumes only" not in summary["tissue_footnote"] and "volumes only" not in page
    assert "contribution to the end force" in summary["tissue_footnote"]
    # muscles ramped differently: curves against the load factor, each muscle's α named (not the node mean)
    from pixmuscle.report.curves import load_factor_label

    label = load_factor_label(summary["solver_info"]["activation"])
    assert label.startswith("load factor") and "medial 0→0.9" in label and "lateral 0→0.4" in label
    assert load_factor_label({"medial": [0.0, 0.9], "lateral": [0.0, 0.9]}) is None
    with pytest.raises(InputError, match="unknown muscle 'soleus'"):
        run_muscle_forces(tmp_path / "model.h5", cfg, MuscleForcesConfig(muscles=["soleus"]), tmp_path / "x.h5")
    assert not (tmp_path / "x.h5").exists()


def test_force_length_matches_the_homogeneous_bar_and_the_fibre_law(tmp_path):
    shape, h = (3, 3, 4), (0.2, 0.2, 0.3)
    model = mask_model(np.ones(shape, bool), h, tissue=MUSCLE)
    save_model(tmp_path / "model.h5", model)
    L0, area = shape[2] * h[2], shape[0] * h[0] * shape[1] * h[1]
    solve_cfg = parse_section(SolveConfig, dict(steps=1, boundary_conditions=roller_bcs(model, 0.0)), "solve")
    fl = parse_section(ForceLengthConfig, dict(shortening=0.24, lengthening=0.24, points=2, activation=0.8, steps=2),
                       "force_length")
    out = run_force_length(tmp_path / "model.h5", solve_cfg, fl, tmp_path / "fl.h5")
    c = load_force_length(out)
    assert c["L0_cm"] == pytest.approx(L0)
    np.testing.assert_allclose(c["stretch"], [0.8, 0.9, 1.0, 1.1, 1.2])
    mat = make_materials(solve_cfg.materials)[MUSCLE]
    for lam, tot, pas, act in zip(c["stretch"], c["total"], c["passive"], c["active"], strict=True):
        ref_tot = homogeneous.uniaxial_bar(mat, lam, area, activation=0.8)["force"]
        ref_pas = homogeneous.uniaxial_bar(mat, lam, area, activation=0.0)["force"]
        assert tot == pytest.approx(ref_tot, rel=5e-3, abs=1e-3)
        assert pas == pytest.approx(ref_pas, rel=5e-3, abs=1e-3)
        law = 0.8 * mat.sigma_max * area * float(f_active(lam / mat.lambda_opt))
        assert act == pytest.approx(law, rel=1e-2), lam  # measured: within 0.4 %
    np.testing.assert_allclose(c["fibre_law"], 0.8 * mat.sigma_max * area * f_active(c["stretch"]), rtol=1e-12)
    from pixmuscle.report.experiments import force_length_section

    parts, info = force_length_section(c, tmp_path)
    assert (tmp_path / "force_length.png").is_file() and "Force–length" in parts[0]


def test_force_length_config_errors():
    solve_cfg = parse_section(SolveConfig, dict(boundary_conditions=[{"nodes": "z_min", "fix": ["z"]}]), "solve")
    with pytest.raises(ValueError, match="'z_max' has no boundary condition"):
        force_length_cases(solve_cfg, ForceLengthConfig())
    with pytest.raises(InputError, match="nothing to sweep"):
        parse_section(ForceLengthConfig, {"shortening": 0, "lengthening": 0}, "force_length")


def test_pipeline_runs_the_protocols_and_reports_them(tmp_path):
    """Labels → model → solve → muscle forces → force–length → report through `run_pipeline`."""
    import yaml

    from pixmuscle.imaging.nifti import save_volume
    from pixmuscle.pipeline import load_config, run_pipeline

    labels = np.ones((4, 2, 4), np.int16)
    labels[2:] = 5
    save_volume(tmp_path / "labels.nii.gz", labels, np.diag([0.2, 0.2, 0.3, 1.0]), kind="labels")
    cfg = {
        "synthetic": True, "output_dir": "out",
        "build_model": {"labels": "labels.nii.gz", "tissue_map": {
            0: "background", 1: {"muscle": "medial", "fiber": [0, 0, 1]}, 5: {"muscle": "lateral", "fiber": [0, 0, 1]}}},
        "solve": {"steps": 2, "activation": {"from": 0, "to": {"medial": 0.9, "default": 0.3}},
                  "boundary_conditions": [{"nodes": "z_min", "fix": ["x", "y", "z"]},
                                          {"nodes": "z_max", "fix": ["x", "y", "z"]}]},
        "muscle_forces": {},
        "force_length": {"shortening": 0.0, "lengthening": 0.06, "points": 1, "steps": 2, "activation": 0.5},
        "report": {"vtu": False, "slices": False, "view3d": False},
    }
    (tmp_path / "run.yaml").write_text(yaml.safe_dump(cfg))
    assert run_pipeline(tmp_path / "run.yaml")
    out = tmp_path / "out"
    mf = load_muscle_forces(out / "muscle_forces_fine.h5")
    fl = load_force_length(out / "force_length_fine.h5")
    assert set(mf["contribution"]) == {"medial", "lateral"} and fl["length"].shape == (2,)
    summary = __import__("json").loads((out / "report" / "summary.json").read_text())
    rows = {r["region"]: r for r in summary["tissue_table"]}
    assert rows["medial"]["F_max [N]"] == pytest.approx(mf["contribution"]["medial"][-1])
    page = (out / "report" / "index.html").read_text()
    assert "Force by muscle" in page and "Force–length" in page and "Activation per muscle" in page
    # names are checked against the case before any stage runs (here: the tissue map has no seeds,
    # so the solve stage checks against the model)
    cfg["solve"]["activation"]["to"] = {"soleus": 1.0}
    (tmp_path / "bad.yaml").write_text(yaml.safe_dump(cfg))
    load_config(tmp_path / "bad.yaml")
    with pytest.raises(InputError, match="unknown muscle 'soleus'; the model's muscles are: medial, lateral"):
        run_pipeline(tmp_path / "bad.yaml")


@pytest.mark.parametrize("name", ["muscle_forces.yaml", "force_length.yaml", "activation_image.yaml", "dwi.yaml"])
def test_shipped_configs_parse_and_names_are_checked_before_running(tmp_path, name):
    from pathlib import Path

    import yaml

    from pixmuscle.pipeline import load_config

    root = Path(__file__).resolve().parents[1]
    cfg = load_config(root / "configs" / name)
    assert cfg.solve is not None
    if cfg.segment is None:  # force_length.yaml: a labelled block, names checked by the solve stage
        return
    raw = yaml.safe_load((root / "configs" / name).read_text())
    raw["solve"]["activation"] = {"from": 0.0, "to": {"solues": 1.0}}
    (tmp_path / "configs").mkdir()
    (tmp_path / "data").symlink_to(root / "data")  # the config's relative data paths stay valid
    (tmp_path / "configs" / name).write_text(yaml.safe_dump(raw))
    with pytest.raises(InputError, match=r"solve\.activation\.to\.solues: unknown muscle 'solues'; .*soleus"):
        load_config(tmp_path / "configs" / name)

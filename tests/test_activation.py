"""Per-muscle activation: config, per-node ramp, activation image, and the solve.

Truth: a block of two side-by-side muscles with fibres along z between roller ends stays at F = I
for any activation that varies only across the fibres (the active stress α σ_max a⊗a is then
divergence free and traction free on the lateral faces), so the end force is the sum over the
columns of the homogeneous isometric block force at each column's α
(:func:`pixmuscle.mechanics.homogeneous.isometric_block`).
"""

import numpy as np
import pytest

from pixmuscle.config import parse_section
from pixmuscle.errors import InputError
from pixmuscle.mechanics import homogeneous
from pixmuscle.mechanics.activation import ActivationRamp, activation_ramp, image_on_nodes, muscle_values
from pixmuscle.mechanics.config import SolveConfig
from pixmuscle.mechanics.solve import make_materials, solve
from pixmuscle.model.tissues import MUSCLE
from pixmuscle.verify.mechanics import mask_model, roller_bcs

SHAPE, SPACING = (4, 2, 4), (0.2, 0.2, 0.3)


def two_muscle_block():
    """4 × 2 × 4 muscle block, fibres along z: 'medial' at x index 0-1, 'lateral' at 2-3."""
    model = mask_model(np.ones(SHAPE, bool), SPACING, tissue=MUSCLE)
    model.muscle_id = np.where(model.ijk[:, 0] < 2, 1, 2).astype(np.int16)
    model.muscle_names = ["medial", "lateral"]
    return model


def _cfg(model, **kw):
    return parse_section(SolveConfig, dict(steps=2, boundary_conditions=roller_bcs(model, 0.0), **kw), "solve")


def test_config_accepts_numbers_mappings_and_image(tmp_path):
    cfg = parse_section(SolveConfig, {"activation": {"from": 0, "to": {"soleus": 0.95, "default": 0}}}, "solve")
    assert cfg.activation["to"] == {"soleus": 0.95, "default": 0.0} and cfg.activation["from"] == 0.0
    assert not cfg.uniform_activation and cfg.alpha_to == 0.0
    assert parse_section(SolveConfig, {"activation": {"to": 0.5}}, "solve").uniform_activation
    (tmp_path / "a.nii.gz").write_bytes(b"")
    cfg = parse_section(SolveConfig, {"activation": {"image": "a.nii.gz"}}, "solve", tmp_path)
    assert cfg.activation["image"] == (tmp_path / "a.nii.gz").resolve() and not cfg.uniform_activation


@pytest.mark.parametrize("act, match", [
    ({"to": {"soleus": 1.5}}, r"activation\.to\.soleus: expected a number in \[0, 1\]"),
    ({"to": "high"}, r"activation\.to: expected a number"),
    ({"image": "missing.nii.gz"}, r"activation\.image: file not found"),
    ({"tu": 1}, "unknown key 'tu'"),
])
def test_config_errors(act, match):
    with pytest.raises(InputError, match=match):
        parse_section(SolveConfig, {"activation": act}, "solve")


def test_unknown_muscle_names_the_muscle_and_lists_known_ones():
    with pytest.raises(InputError, match=r"solve\.activation\.to\.soleus: unknown muscle 'soleus'; the model's "
                                         r"muscles are: medial, lateral"):
        muscle_values({"soleus": 1.0}, ["medial", "lateral"], "solve.activation.to")
    model = two_muscle_block()
    with pytest.raises(InputError, match="unknown muscle 'solues'"):
        activation_ramp(model, {"from": {"solues": 0.1}, "to": 1.0})


def test_ramp_per_muscle_with_default():
    model = two_muscle_block()
    ramp = activation_ramp(model, {"from": 0.0, "to": {"medial": 0.8, "default": 0.3}})
    med = model.muscle_id == 1
    assert np.all(ramp.end[med] == 0.8) and np.all(ramp.end[~med] == 0.3) and np.all(ramp.start == 0)
    assert ramp.at(0.5)[med][0] == pytest.approx(0.4)
    assert ramp.mean(1.0) == pytest.approx(0.55)
    uni = ActivationRamp.uniform(0.1, 0.9, model.tissue == MUSCLE)
    assert np.all(uni.at(0.5) == pytest.approx(0.5))


def test_image_sampled_through_its_affine():
    # a linear field on a finer, shifted grid in mm-free cm units: trilinear sampling is exact
    model = two_muscle_block()
    aff = np.diag([0.05, 0.05, 0.1, 1.0])
    aff[:3, 3] = [-0.3, -0.2, -0.25]
    ijk = np.stack(np.meshgrid(*[np.arange(n) for n in (30, 20, 20)], indexing="ij"), -1)
    world = ijk @ aff[:3, :3].T + aff[:3, 3]
    data = 0.2 + 0.5 * world[..., 0] + 0.1 * world[..., 2]
    vals, inside = image_on_nodes(data, aff, model.X, model.origin, model.rotation)
    assert inside.all()
    np.testing.assert_allclose(vals, 0.2 + 0.5 * model.X[:, 0] + 0.1 * model.X[:, 2], atol=1e-12)
    with pytest.raises(InputError, match="outside the image's field of view"):
        activation_ramp(model, {"from": 0.0, "to": 1.0, "image": "act.nii.gz"}, (data[:10], aff))
    with pytest.raises(InputError, match="not in \\[0, 1\\]"):
        activation_ramp(model, {"from": 0.0, "to": 1.0, "image": "act.nii.gz"}, (data + 1.0, aff))


def test_per_muscle_force_is_the_sum_of_homogeneous_columns():
    model = two_muscle_block()
    cfg = _cfg(model, activation={"from": 0.0, "to": {"medial": 0.8, "lateral": 0.3}})
    res = solve(model, cfg)
    mat = make_materials(cfg.materials)[MUSCLE]
    half = 2 * SPACING[0] * SHAPE[1] * SPACING[1]
    ref = homogeneous.isometric_block(mat, 0.8, half)["force"] + homogeneous.isometric_block(mat, 0.3, half)["force"]
    assert res.force("z_max")[-1] == pytest.approx(ref, rel=2e-3)
    assert res.alpha[-1] == pytest.approx(0.55) and res.alpha[1] == pytest.approx(0.275)


def test_activation_image_force_matches_columns(tmp_path):
    from pixmuscle.imaging.nifti import load_volume, save_volume
    from pixmuscle.io.model import save_model
    from pixmuscle.stages.solve import run_solve

    model = two_muscle_block()
    # α varies across the fibres only (with x): 0.25, 0.5, 0.75, 1.0 in the four columns of x
    aff = np.diag([0.2, 0.2, 0.3, 1.0])
    data = np.broadcast_to((np.arange(4)[:, None, None] + 1) / 4.0, SHAPE).copy()
    save_volume(tmp_path / "act.nii.gz", data, aff)
    save_model(tmp_path / "model.h5", model)
    raw = dict(steps=2, boundary_conditions=roller_bcs(model, 0.0),
               activation={"from": 0.0, "to": {"medial": 1.0, "default": 0.5}, "image": "act.nii.gz"})
    cfg = parse_section(SolveConfig, raw, "solve", tmp_path)
    run_solve(tmp_path / "model.h5", cfg, tmp_path / "results.h5", progress=False)
    from pixmuscle.io.results import load_results

    res = load_results(tmp_path / "results.h5")
    mat = make_materials(cfg.materials)[MUSCLE]
    col = SPACING[0] * SHAPE[1] * SPACING[1]
    alphas = [0.25, 0.5, 0.75 * 0.5, 1.0 * 0.5]
    ref = sum(homogeneous.isometric_block(mat, a, col)["force"] for a in alphas)
    assert res.force("z_max")[-1] == pytest.approx(ref, rel=2e-3)
    assert res.info["activation"] == {"medial": [0.0, pytest.approx(0.375)], "lateral": [0.0, pytest.approx(0.4375)]}
    assert load_volume(tmp_path / "act.nii.gz", kind="image").data.shape == SHAPE
    # the report's activation section
    from pixmuscle.report.config import ReportConfig
    from pixmuscle.stages.report import make_report

    make_report(tmp_path / "results.h5", tmp_path / "report", ReportConfig(vtu=False, slices=False, view3d=False))
    page = (tmp_path / "report" / "index.html").read_text()
    assert "Activation per muscle" in page and "0.4375" in page


def test_cli_set_takes_a_per_muscle_mapping():
    """`--set solve.activation.to={...}` is read as YAML and validated like the same key in the file."""
    from pathlib import Path

    from pixmuscle.pipeline import load_run

    cfg = Path(__file__).resolve().parents[1] / "configs" / "demo.yaml"
    run = load_run(cfg, overrides=["solve.activation.to={soleus: 0.9, default: 0.1}"])
    assert run.cases[0].solve.activation["to"] == {"soleus": 0.9, "default": 0.1}
    with pytest.raises(InputError, match="solve.activation.to.solues: unknown muscle 'solues'"):
        load_run(cfg, overrides=["solve.activation.to={solues: 0.9}"])

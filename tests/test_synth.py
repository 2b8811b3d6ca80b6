"""SYNTHETIC phantoms: determinism, Table 3 proportions, DTI sign handling, Rician noise, realism."""

import json
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage

from pixmuscle.errors import InputError
from pixmuscle.imaging.dti import principal_eigenvector, resample_vectors_to_grid, tensor_from_components
from pixmuscle.imaging.nifti import load_volume
from pixmuscle.synth import make_leg_phantom, make_mg_phantom, tissue_volumes, write_phantom
from pixmuscle.synth.mg import TABLE3

LEG = dict(shape=(84, 84, 3), pixel_cm=0.2, slice_cm=0.6)
MG = dict(shape=(64, 40, 4), pixel_cm=0.12, slice_cm=0.5)
DATA = Path(__file__).resolve().parents[1] / "data" / "synthetic"


@pytest.fixture(scope="module")
def leg():
    return make_leg_phantom(**LEG, noise=0.05, seed=3)


@pytest.fixture(scope="module")
def leg_clean():
    return make_leg_phantom(**LEG, noise=0.0, dti_noise=0.0, bias=0.0, seed=3)


def test_determinism_under_a_seed(leg):
    again = make_leg_phantom(**LEG, noise=0.05, seed=3)
    for name in ("mri", "labels", "muscle_id", "dti_tensor", "dti_v1", "fiber_true", "imat_mask"):
        np.testing.assert_array_equal(getattr(leg, name), getattr(again, name), err_msg=name)
    other = make_leg_phantom(**LEG, noise=0.05, seed=4)
    assert not np.array_equal(leg.mri, other.mri)


def test_leg_truth_is_consistent(leg):
    assert set(np.unique(leg.labels)) == {0, 1, 2, 3, 4}
    assert sorted(np.unique(leg.muscle_id)) == list(range(8))
    np.testing.assert_array_equal(leg.muscle_id > 0, leg.labels == 1)
    np.testing.assert_array_equal(leg.imct_mask, leg.labels == 2)
    assert np.all(leg.labels[leg.imat_mask] == 3) and leg.imat_mask.any()
    assert np.all(leg.imct_mask[leg.outer_ct_mask])
    norms = np.linalg.norm(leg.fiber_true, axis=-1)
    np.testing.assert_allclose(norms[leg.labels == 1], 1.0)
    assert np.all(norms[leg.labels != 1] == 0)
    assert len(leg.muscle_names) == 7 and leg.params["synthetic"] is True
    # the DTI lives on its own, coarser grid with a different field of view
    assert leg.dti_tensor.shape[:3] != leg.mri.shape
    assert not np.allclose(leg.dti_affine, leg.affine)


def test_rician_background(leg):
    sigma = leg.noise_sigma
    far = ~ndimage.binary_dilation(leg.labels > 0, iterations=3)
    bg = leg.mri[far]
    assert bg.size > 5000
    # Rayleigh: mean sigma sqrt(pi/2), std sigma sqrt(2 - pi/2)
    assert abs(bg.mean() / (sigma * np.sqrt(np.pi / 2)) - 1) < 0.03
    assert abs(bg.std() / (sigma * np.sqrt(2 - np.pi / 2)) - 1) < 0.05
    assert np.all(bg >= 0)


def test_muscles_look_alike_but_fibres_differ(leg):
    sigma = leg.noise_sigma
    means, dirs = [], []
    for m in range(1, 8):
        core = ndimage.binary_erosion(leg.muscle_id == m, structure=np.ones((3, 3, 1)))
        assert core.sum() > 20
        means.append(leg.mri[core].mean())
        f = leg.fiber_true[leg.muscle_id == m]
        dirs.append(principal_eigenvector(np.einsum("ni,nj->ij", f, f))[0])
    assert max(means) - min(means) < 2 * sigma
    # muscle MRI clearly differs from fat and connective tissue
    assert leg.mri[leg.labels == 3].mean() - max(means) > 5 * sigma
    # adjacent muscles (touching across a septum) have clearly different fibres
    pairs = 0
    for m in range(1, 8):
        grown = ndimage.binary_dilation(leg.muscle_id == m, structure=np.ones((3, 3, 1)), iterations=2)
        for n in range(m + 1, 8):
            if np.any(grown & (leg.muscle_id == n)):
                pairs += 1
                ang = np.degrees(np.arccos(min(1.0, abs(float(dirs[m - 1] @ dirs[n - 1])))))
                assert ang > 20, (leg.muscle_names[m - 1], leg.muscle_names[n - 1], ang)
    assert pairs >= 8


def test_dti_signs_random_but_axis_matches_truth(leg_clean):
    p = leg_clean
    v = p.dti_v1[p.dti_mask]
    assert 0.3 < np.mean(v[:, 2] < 0) < 0.7  # both signs, about equally often
    assert np.all(p.dti_tensor[~p.dti_mask] == 0)
    vm, has = resample_vectors_to_grid(p.dti_v1, p.dti_affine, p.mri.shape, p.affine)
    muscle = (p.labels == 1) & has
    assert muscle.sum() > 0.95 * (p.labels == 1).sum()
    cos = np.abs(np.sum(vm[muscle] * p.fiber_true[muscle], axis=-1))
    assert cos.mean() > 0.95
    # muscle tensors carry the muscle diffusivities (mm^2/s); fat and bone give no signal
    _, ev, fa = principal_eigenvector(tensor_from_components(p.dti_tensor[p.dti_mask]))
    np.testing.assert_allclose(np.median(ev, axis=0), [2.1e-3, 1.5e-3, 1.2e-3], rtol=0.03)


def test_dti_noise_perturbs_directions_moderately(leg):
    vm, has = resample_vectors_to_grid(leg.dti_v1, leg.dti_affine, leg.mri.shape, leg.affine)
    muscle = (leg.labels == 1) & has
    cos = np.abs(np.sum(vm[muscle] * leg.fiber_true[muscle], axis=-1))
    assert 0.85 < np.median(cos) < 0.9999


@pytest.mark.parametrize("subject", ["young", "old"])
def test_mg_table3_proportions(subject):
    p = make_mg_phantom(subject, **MG, seed=5)
    v = tissue_volumes(p)
    t = TABLE3[subject]
    assert abs((v["imct"] / v["muscle"]) / (t["imct"] / t["muscle"]) - 1) < 0.10
    assert abs((v["imat"] / v["muscle"]) / (t["imat"] / t["muscle"]) - 1) < 0.10
    assert p.muscle_names == ["medial_gastrocnemius"]
    assert v["outer_ct"] > 0 and np.all(p.imct_mask[p.outer_ct_mask])
    # pennate fibres: the default angle from the muscle axis, up to the smooth random spread
    f = p.fiber_true[p.labels == 1]
    ang = np.degrees(np.arccos(principal_eigenvector(np.einsum("ni,nj->ij", f, f))[0][2]))
    assert abs(ang - p.params["pennation_deg"]) < 4.0


def test_mg_pennation_without_spread():
    p = make_mg_phantom("young", **MG, seed=5, pennation_deg=30.0, fiber_spread_deg=0.0)
    f = p.fiber_true[p.labels == 1]
    np.testing.assert_allclose(f, np.broadcast_to([0.0, 0.5, np.sqrt(0.75)], f.shape), atol=1e-12)


def test_mg_old_vs_young_muscle_volume():
    y = tissue_volumes(make_mg_phantom("young", **MG, seed=5))
    o = tissue_volumes(make_mg_phantom("old", **MG, seed=5))
    ratio = TABLE3["old"]["muscle"] / TABLE3["young"]["muscle"]
    assert abs((o["muscle"] / y["muscle"]) / ratio - 1) < 0.10


def test_mg_tissue_ratios_and_aponeurosis():
    """Given ratios are the phantom's IMCT/muscle and IMAT/muscle (voxel-centre quantiles), and a thicker
    aponeurosis adds outer connective tissue without changing the muscle."""
    base = make_mg_phantom("young", **MG, seed=5)
    v0 = tissue_volumes(base)
    p = make_mg_phantom("young", **MG, seed=5, tissue_ratios={"imct_per_muscle": 0.40, "imat_per_muscle": 0.05},
                        aponeurosis_cm=0.24)
    v = tissue_volumes(p)
    assert abs(v["imct"] / v["muscle"] / 0.40 - 1) < 0.10 and abs(v["imat"] / v["muscle"] / 0.05 - 1) < 0.10
    assert v["outer_ct"] > 1.3 * v0["outer_ct"]
    thick = tissue_volumes(make_mg_phantom("young", **MG, seed=5, aponeurosis_cm=0.24))
    assert thick["muscle"] == v0["muscle"] and thick["outer_ct"] > 1.3 * v0["outer_ct"]
    assert "tissue_ratios" not in base.params and p.params["aponeurosis_cm"] == 0.24
    with pytest.raises(InputError, match="tissue_ratios"):
        make_mg_phantom("young", **MG, tissue_ratios={"imct": 0.2})
    with pytest.raises(InputError, match="aponeurosis_cm"):
        make_mg_phantom("young", **MG, aponeurosis_cm=0.0)


def test_bad_arguments():
    with pytest.raises(InputError, match="does not fit"):
        make_leg_phantom(shape=(32, 32, 2), pixel_cm=0.156)
    with pytest.raises(InputError, match="subject"):
        make_mg_phantom("middle-aged")
    with pytest.raises(InputError, match="pixel_cm"):
        make_leg_phantom(pixel_cm=0)


def test_write_phantom_round_trip(tmp_path, leg):
    files = write_phantom(leg, tmp_path, "leg")
    assert {f.name for f in tmp_path.iterdir()} == {p.name for p in files.values()}
    truth = json.loads(files["truth"].read_text())
    assert truth["synthetic"] is True and truth["muscle_names"] == leg.muscle_names
    assert truth["seed"] == 3
    lab = load_volume(files["labels"], kind="labels")
    np.testing.assert_array_equal(lab.data, leg.labels)
    np.testing.assert_allclose(lab.affine, leg.affine, atol=1e-6)
    mri = load_volume(files["mri"])
    np.testing.assert_allclose(mri.data, leg.mri, rtol=1e-6, atol=1e-6)
    v1 = load_volume(files["dti_V1"], kind="vectors")
    np.testing.assert_allclose(v1.data, leg.dti_v1, atol=1e-6)
    np.testing.assert_allclose(v1.affine, leg.dti_affine, atol=1e-6)
    t = load_volume(files["dti_tensor"], kind="tensor")
    np.testing.assert_allclose(t.data, leg.dti_tensor, atol=1e-9)
    imat = load_volume(files["imat"], kind="labels", allow_empty=True)
    np.testing.assert_array_equal(imat.data > 0, leg.imat_mask)


def test_committed_samples():
    names = ["leg_small", "mg_young_small", "mg_old_small"]
    total = sum(f.stat().st_size for f in DATA.glob("*") if f.is_file())
    assert total < 14e6  # includes the paper-size phantoms (leg_paper: 176 x 176 x 25 voxels, mg_young/mg_old)
    for n in names:
        truth = json.loads((DATA / f"{n}_truth.json").read_text())
        assert truth["synthetic"] is True
        lab = load_volume(DATA / f"{n}_labels.nii.gz", kind="labels")
        mid = load_volume(DATA / f"{n}_muscle_id.nii.gz", kind="labels")
        assert mid.data.max() == len(truth["muscle_names"])
        np.testing.assert_array_equal(mid.data > 0, lab.data == 1)
    readme = (DATA / "README.md").read_text().lower()
    assert "synthetic" in readme and "not patient data" in readme


def test_synthetic_readme_lists_every_shipped_file():
    """data/synthetic/README.md names every phantom and file shipped in that folder."""
    from pathlib import Path

    folder = Path(__file__).resolve().parents[1] / "data" / "synthetic"
    text = (folder / "README.md").read_text()
    for f in sorted(folder.iterdir()):
        if f.name == "README.md":
            continue
        stem = f.name.split(".")[0]
        prefix = next((p for p in ("leg_demo", "leg_small", "mg_young_small", "mg_old_small", "leg_paper_small",
                                   "leg_paper", "mg_young", "mg_old")
                       if stem.startswith(p + "_") and stem[len(p) + 1:] in
                       ("mri", "dti_tensor", "dti_V1", "labels", "muscle_id", "imct", "imat", "aponeurosis", "fibers",
                        "truth")), None)
        assert (f"`{prefix}`" in text) if prefix else (stem in text), f.name

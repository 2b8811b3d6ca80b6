"""Scanner DWI: FSL b-vector convention, dipy tensor fit against a known tensor field.

Truth: signals generated from a known tensor field (:mod:`pixmuscle.synth.dwi`, the tensor model
with Rician noise), written in several stored voxel orientations of an oblique affine with the
FSL b-vectors of each; the fitted principal eigenvector must agree with the field's:

* noise free: < 0.01° in every voxel, for every stored orientation;
* SNR 30 (b = 500 s/mm², 30 directions, FA ≈ 0.3): median < 6°, 95th percentile < 12°
  (measured 4.2° / 9.1°);
* b-vectors read in the wrong frame (world instead of FSL): median > 20° — the convention matters.
"""

import numpy as np
import pytest

pytest.importorskip("dipy")

from pixmuscle.config import parse_section  # noqa: E402
from pixmuscle.errors import InputError  # noqa: E402
from pixmuscle.imaging.dwi import fsl_bvecs_to_world, load_dwi_tensor, read_gradients, world_to_fsl_bvecs  # noqa: E402
from pixmuscle.segmentation.config import SegmentConfig  # noqa: E402
from pixmuscle.synth.dwi import synthesize_dwi, write_dwi  # noqa: E402

SHAPE = (10, 10, 4)


def tensor_field(shape=SHAPE):
    """Tensors (λ = 2.1, 1.4, 1.1 ·10⁻³ mm²/s) whose V1 sweeps 15°..65° from z and a full turn in azimuth."""
    ijk = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1).astype(float)
    th = np.deg2rad(15 + 50 * ijk[..., 0] / shape[0])
    ph = np.deg2rad(360 * ijk[..., 1] / shape[1])
    v1 = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)
    a = np.cross(v1, [0.3, 0.4, 0.866])
    a /= np.linalg.norm(a, axis=-1, keepdims=True)
    c = np.cross(v1, a)

    def outer(u):
        return u[..., :, None] * u[..., None, :]

    return 2.1e-3 * outer(v1) + 1.4e-3 * outer(a) + 1.1e-3 * outer(c), v1


def oblique_affine():
    c, s = np.cos(0.35), np.sin(0.35)
    aff = np.eye(4)
    aff[:3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ np.diag([0.2, 0.2, 0.4])
    aff[:3, 3] = [1.0, 2.0, 3.0]
    return aff


def v1_angles(fit, v1_true, affine):
    """Angle (deg) between fitted and true V1 per voxel, matching voxels by their world position."""
    ijk = np.stack(np.meshgrid(*[np.arange(n) for n in fit.fa.shape], indexing="ij"), -1).reshape(-1, 3)
    w = ijk @ fit.affine[:3, :3].T + fit.affine[:3, 3]
    src = np.rint(np.linalg.solve(affine[:3, :3], (w - affine[:3, 3]).T).T).astype(int)
    vt = v1_true[src[:, 0], src[:, 1], src[:, 2]]
    cos = np.abs(np.sum(vt * fit.v1.reshape(-1, 3), axis=1))
    return np.degrees(np.arccos(np.clip(cos, 0, 1)))


def test_fsl_convention_round_trip_and_flip():
    g = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [0.6, 0.8, 0]])
    ras = np.diag([2.0, 2.0, 3.0, 1.0])  # det > 0: FSL's x is the negated first voxel axis
    np.testing.assert_allclose(fsl_bvecs_to_world([[1.0, 0, 0]], ras), [[-1.0, 0, 0]])
    las = np.diag([-2.0, 2.0, 3.0, 1.0])  # det < 0: voxel axes as they are, world x = −voxel x
    np.testing.assert_allclose(fsl_bvecs_to_world([[1.0, 0, 0]], las), [[-1.0, 0, 0]])
    aff = oblique_affine()
    np.testing.assert_allclose(fsl_bvecs_to_world(world_to_fsl_bvecs(g, aff), aff), g, atol=1e-12)


@pytest.mark.parametrize("orientation", ["RAS", "LPS", "PIL"])
def test_noise_free_fit_recovers_v1_in_any_stored_orientation(tmp_path, orientation):
    D, v1 = tensor_field()
    aff = oblique_affine()
    data, bvals, g = synthesize_dwi(D)
    f = write_dwi(tmp_path / "dwi", data, aff, bvals, g, orientation=orientation)
    fit = load_dwi_tensor(f["image"], f["bvals"], f["bvecs"])
    assert v1_angles(fit, v1, aff).max() < 0.01
    lam = np.array([2.1e-3, 1.4e-3, 1.1e-3])
    fa = np.sqrt(1.5 * np.sum((lam - lam.mean()) ** 2) / np.sum(lam**2))
    np.testing.assert_allclose(fit.fa, fa, rtol=1e-4)
    np.testing.assert_allclose(fit.md, lam.mean(), rtol=1e-4)


def test_fit_at_snr_30_and_wrong_convention(tmp_path):
    D, v1 = tensor_field()
    aff = oblique_affine()
    data, bvals, g = synthesize_dwi(D, snr=30, seed=1)
    f = write_dwi(tmp_path / "dwi", data, aff, bvals, g, orientation="LPS")
    ang = v1_angles(load_dwi_tensor(f["image"], f["bvals"], f["bvecs"]), v1, aff)
    assert np.median(ang) < 6.0 and np.percentile(ang, 95) < 12.0
    wrong = v1_angles(load_dwi_tensor(f["image"], f["bvals"], f["bvecs"], convention="world"), v1, aff)
    assert np.median(wrong) > 20.0


def test_gradient_file_errors(tmp_path):
    (tmp_path / "b.bval").write_text("0 500 500 500\n")
    (tmp_path / "b.bvec").write_text("0 1 0 0\n0 0 1 0\n0 0 0 1\n")  # FSL: 3 rows, one column per volume
    bvals, bvecs = read_gradients(tmp_path / "b.bval", tmp_path / "b.bvec")
    assert bvals.tolist() == [0, 500, 500, 500] and bvecs.tolist()[1:] == np.eye(3).tolist()
    with pytest.raises(InputError, match="4 b-values for a series of 5 volumes"):
        read_gradients(tmp_path / "b.bval", tmp_path / "b.bvec", n_volumes=5)
    (tmp_path / "c.bvec").write_text("0 2 0 0\n0 0 1 0\n0 0 0 1\n")
    with pytest.raises(InputError, match="not unit vectors"):
        read_gradients(tmp_path / "b.bval", tmp_path / "c.bvec")


def test_segment_config_dwi(tmp_path):
    for n in ("d.nii.gz", "d.bval", "d.bvec", "t.nii.gz"):
        (tmp_path / n).write_text("")
    cfg = parse_section(SegmentConfig, {"dwi": {"image": "d.nii.gz", "bvals": "d.bval", "bvecs": "d.bvec"}},
                        "segment", tmp_path)
    assert cfg.dwi.bvecs_convention == "fsl" and cfg.dwi.image == (tmp_path / "d.nii.gz").resolve()
    with pytest.raises(InputError, match="segment.dwi.bvecs: required key is missing"):
        parse_section(SegmentConfig, {"dwi": {"image": "d.nii.gz", "bvals": "d.bval"}}, "segment", tmp_path)
    with pytest.raises(InputError, match="not both"):
        parse_section(SegmentConfig, {"dwi": {"image": "d.nii.gz", "bvals": "d.bval", "bvecs": "d.bvec"},
                                      "dti_tensor": "t.nii.gz"}, "segment", tmp_path)


def test_segment_stage_dwi_sample_matches_the_phantom_tensors(tmp_path):
    """The committed scanner-style sample (configs/dwi.yaml) gives the phantom's fibres on the MRI grid."""
    from pathlib import Path

    from pixmuscle.imaging.dti import principal_eigenvector, resample_tensor_to_grid, tensor_from_components
    from pixmuscle.pipeline import load_config
    from pixmuscle.stages.segment import _dti_on_grid
    from pixmuscle.synth.leg import make_leg_phantom
    from pixmuscle.synth.write import SAMPLES

    root = Path(__file__).resolve().parents[1]
    cfg = load_config(root / "configs" / "dwi.yaml").segment
    ph = make_leg_phantom(**SAMPLES["leg_demo"][1])
    d, covered = _dti_on_grid(cfg, ph.mri.shape, ph.affine, tmp_path / "qc")
    ref, _ = resample_tensor_to_grid(tensor_from_components(ph.dti_tensor, "fsl"), ph.dti_affine, ph.mri.shape,
                                     ph.affine)
    muscle = (ph.labels == 1) & covered
    v_fit = principal_eigenvector(d[muscle])[0]
    v_ref = principal_eigenvector(ref[muscle])[0]
    ang = np.degrees(np.arccos(np.clip(np.abs(np.sum(v_fit * v_ref, axis=1)), 0, 1)))
    assert np.median(ang) < 5.0
    for name in ("dwi_fa.nii.gz", "dwi_md.nii.gz", "dwi_v1.nii.gz", "dwi_maps.png", "dwi_summary.json"):
        assert (tmp_path / "qc" / name).is_file()
    from pixmuscle.report.sections.dwi import dwi_section

    html = "".join(dwi_section(tmp_path / "qc"))
    assert "Diffusion data (DWI tensor fit)" in html and "fsl" in html and "data:image/png" in html

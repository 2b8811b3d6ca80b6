"""DICOM folders as input: series written here with pydicom from the bundled SYNTHETIC demo phantom (any
orientation, head- or feet-first, shuffled file names, rescale slope/intercept, a second series in the folder)
convert to the NIfTI the phantom was written from (dcm2niix), segment and solve to the same answer, and give the
dipy fit the same fibres as the NIfTI + .bval/.bvec route; every bad folder stops with exit 2 naming it."""

from __future__ import annotations

import random
from pathlib import Path

import h5py
import nibabel as nib
import numpy as np
import pytest
import yaml
from nibabel.orientations import apply_orientation, axcodes2ornt, inv_ornt_aff, io_orientation, ornt_transform

pytest.importorskip("pydicom")
pytest.importorskip("dcm2niix")

from pixmuscle.errors import InputError  # noqa: E402
from pixmuscle.imaging.dwi import fsl_bvecs_to_world, load_dwi_tensor, read_gradients  # noqa: E402
from pixmuscle.imaging.nifti import load_volume  # noqa: E402
from pixmuscle.io.dicom import dicom_to_nifti, find_series, write_mr_series  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "data" / "synthetic"


def _mri():
    return load_volume(DATA / "leg_demo_mri.nii.gz")


def _reoriented(data, affine, codes):
    """The same image stored in another voxel order (``codes`` as nibabel's axcodes, e.g. 'LPS')."""
    now = io_orientation(affine)
    t = ornt_transform(now, axcodes2ornt(codes))
    return apply_orientation(data, t), affine @ inv_ornt_aff(t, data.shape)


def _write_shuffled(folder, data, affine, seed=0, **kw):
    n = data.shape[2] * (data.shape[3] if data.ndim == 4 else 1)
    names = [f"{x:08x}" for x in random.Random(seed).sample(range(1 << 30), n)]   # no extension, any order
    return write_mr_series(folder, data, affine, names=names, **kw)


@pytest.mark.parametrize("codes,position", [("LPS", "HFS"), ("RAS", "HFS"), ("LAI", "FFS"), ("PRS", "FFS")])
def test_conversion_gives_back_the_image_and_its_geometry(tmp_path, codes, position):
    """Any in-plane orientation, slices up or down the leg, head- or feet-first: the converted NIfTI read by
    pixmuscle equals the original voxel by voxel (within the 16-bit rescale step) on the same cm grid."""
    mri = _mri()
    data, affine = _reoriented(mri.data, mri.affine, codes)
    _write_shuffled(tmp_path / "dcm", data, affine, patient_position=position)
    conv = dicom_to_nifti(tmp_path / "dcm", tmp_path / "cache")
    back = load_volume(conv.image)
    step = np.ptp(mri.data) / 65535
    assert back.data.shape == mri.data.shape
    assert np.abs(back.data - mri.data).max() <= 0.51 * step + 1e-9
    np.testing.assert_allclose(back.affine, mri.affine, atol=1e-5)


def test_conversion_is_cached_by_content(tmp_path):
    """A rerun reuses the conversion; a changed file makes a new one; the cache holds no partial folder."""
    mri = _mri()
    write_mr_series(tmp_path / "dcm", mri.data, mri.affine)
    first = dicom_to_nifti(tmp_path / "dcm", tmp_path / "cache")
    mtime = first.image.stat().st_mtime_ns
    again = dicom_to_nifti(tmp_path / "dcm", tmp_path / "cache")
    assert again.image == first.image and again.image.stat().st_mtime_ns == mtime
    write_mr_series(tmp_path / "dcm", mri.data * 1.5, mri.affine)       # same names, new content
    changed = dicom_to_nifti(tmp_path / "dcm", tmp_path / "cache")
    assert changed.image != first.image
    assert sorted(p.name for p in (tmp_path / "cache").iterdir() if p.name.startswith(".")) == []


def _demo_config(tmp_path, out, **segment):
    cfg = yaml.safe_load((ROOT / "configs" / "demo.yaml").read_text())
    for k in ("mri", "dti_tensor", "imct_mask", "imat_mask"):
        cfg["segment"][k] = str((ROOT / "configs" / cfg["segment"][k]).resolve())
    cfg["segment"].update(segment, qc_png=False)
    cfg.update(output_dir=str(out))
    cfg["solve"]["steps"] = 2
    cfg["solve"]["newton"] = {"residual_tol": 1e-10, "energy_tol": 1e-14}   # converged far below the comparison
    p = tmp_path / f"{out.name}.yaml"
    p.write_text(yaml.safe_dump(cfg))
    return p


def test_demo_from_a_dicom_folder_equals_the_nifti_run(tmp_path):
    """The demo from a DICOM folder (feet-first, shuffled names, a localiser series beside it, chosen with
    segment.series) gives the NIfTI run's labels voxel for voxel and its reaction force. The two grids differ
    by the float32 rounding of the affines (2e-7 cm: NIfTI stores float32, so does dcm2niix), which moves the
    points where the DTI is resampled: the fibres differ by up to 3e-5 (segmentation) and 2e-6 (nodes), and that
    alone moves the force by 5e-5 of itself (measured by swapping only the fibres into the NIfTI model). So the
    forces are compared to 2e-4, with Newton converged far below it."""
    from pixmuscle.pipeline import load_subjects, run_subject

    mri = _mri()
    data, affine = _reoriented(mri.data, mri.affine, "LAI")
    _write_shuffled(tmp_path / "scanner", data, affine, series_number=5, description="T1 axial", patient_position="FFS")
    write_mr_series(tmp_path / "scanner" / "loc", mri.data[:, :, :1], mri.affine, series_number=1,
                    description="localizer")
    runs = {}
    for name, seg in (("nifti", {}), ("dicom", {"mri": str(tmp_path / "scanner"), "series": "T1 axial"})):
        case = load_subjects(_demo_config(tmp_path, tmp_path / name, **seg))[0]
        run_subject(case, until="solve")
        with h5py.File(tmp_path / name / "segmentation.h5") as f:
            labels, mid, fib = f["labels"][()], f["muscle_id"][()], f["fiber"][()]
        with h5py.File(tmp_path / name / "results_coarse.h5") as f:
            runs[name] = labels, mid, fib, f["steps/reaction/z_max"][-1, 2]
    (l0, m0, fib0, f0), (l1, m1, fib1, f1) = runs["nifti"], runs["dicom"]
    assert (l0 == l1).all() and (m0 == m1).all()
    assert np.abs(fib1 - fib0).max() < 1e-4
    assert f1 == pytest.approx(f0, rel=2e-4) and f0 > 0


def test_a_folder_of_several_series_without_a_choice_lists_them(tmp_path):
    mri = _mri()
    write_mr_series(tmp_path / "d" / "a", mri.data, mri.affine, series_number=3, description="T1 axial")
    write_mr_series(tmp_path / "d" / "b", mri.data[:, :, :1], mri.affine, series_number=1, description="localizer")
    assert [s.number for s in find_series(tmp_path / "d")] == [1, 3]
    with pytest.raises(InputError) as exc:
        dicom_to_nifti(tmp_path / "d", tmp_path / "cache", key="segment.series")
    msg = str(exc.value)
    assert "segment.series" in msg and "SeriesNumber 1, SeriesDescription 'localizer', 1 files" in msg
    assert "SeriesNumber 3, SeriesDescription 'T1 axial', 5 files" in msg
    assert dicom_to_nifti(tmp_path / "d", tmp_path / "cache", series=3).image.is_file()
    with pytest.raises(InputError, match="'T2' matches no series"):
        dicom_to_nifti(tmp_path / "d", tmp_path / "cache", series="T2")


def _dwi_world():
    stem = DATA / "leg_demo_dwi"
    img = nib.load(stem.with_suffix(".nii.gz"))
    data = np.asarray(img.dataobj, float)
    affine = img.affine.copy()
    affine[:3] *= 0.1
    bvals, bvecs = read_gradients(stem.with_suffix(".bval"), stem.with_suffix(".bvec"), data.shape[3])
    return data, affine, bvals, fsl_bvecs_to_world(bvecs, img.affine)


def test_dwi_from_dicom_tags_gives_the_nifti_fibres(tmp_path):
    """The bundled DWI written as DICOM with the standard diffusion tags (b-value, gradient in LPS): dcm2niix's
    .bval/.bvec and the dipy fit give the principal directions of the NIfTI + .bval/.bvec route within 1°."""
    data, affine, bvals, g = _dwi_world()
    _write_shuffled(tmp_path / "dwi", data, affine, bvals=bvals, gradients=g, description="DWI")
    conv = dicom_to_nifti(tmp_path / "dwi", tmp_path / "cache", diffusion=True)
    stem = DATA / "leg_demo_dwi"
    ref = load_dwi_tensor(stem.with_suffix(".nii.gz"), stem.with_suffix(".bval"), stem.with_suffix(".bvec"))
    new = load_dwi_tensor(conv.image, conv.bvals, conv.bvecs)
    np.testing.assert_allclose(new.affine, ref.affine, atol=1e-5)
    fibre = ref.fa > 0.1
    assert fibre.sum() > 1000
    cos = np.abs((ref.v1 * new.v1).sum(-1))[fibre]
    assert np.degrees(np.arccos(np.clip(cos, 0.0, 1.0))).max() <= 1.0


# ------------------------------------------------------------------------------------------ bad folders

def _series(tmp_path, **kw):
    mri = _mri()
    return write_mr_series(tmp_path / "d", mri.data, mri.affine, **kw), tmp_path / "d"


def _edit(path, **tags):
    import pydicom

    ds = pydicom.dcmread(path)
    for k, v in tags.items():
        if v is None:
            delattr(ds, k)
        else:
            setattr(ds, k, v)
    ds.save_as(path)


def _bad(folder, tmp_path, match, **kw):
    with pytest.raises(InputError, match=match) as exc:
        dicom_to_nifti(folder, tmp_path / "cache", **kw)
    assert str(folder) in str(exc.value)
    assert not list((tmp_path / "cache").glob("*")) if (tmp_path / "cache").exists() else True


def test_a_folder_without_dicom(tmp_path):
    (tmp_path / "d").mkdir()
    (tmp_path / "d" / "notes.txt").write_text("not an image")
    _bad(tmp_path / "d", tmp_path, "no DICOM files")


def test_dicom_without_pixel_data(tmp_path):
    files, folder = _series(tmp_path)
    _edit(files[2], PixelData=None)
    with pytest.raises(InputError, match="without pixel data") as exc:
        dicom_to_nifti(folder, tmp_path / "cache")
    assert files[2].name in str(exc.value)


def test_a_missing_slice(tmp_path):
    files, folder = _series(tmp_path)
    files[2].unlink()
    _bad(folder, tmp_path, "1 slice\\(s\\) missing")


def test_a_duplicated_slice(tmp_path):
    files, folder = _series(tmp_path)
    import shutil

    shutil.copyfile(files[1], folder / "copy.dcm")
    _edit(folder / "copy.dcm", SOPInstanceUID="1.2.3.4.5")
    _bad(folder, tmp_path, "duplicated")


def test_non_uniform_slice_spacing(tmp_path):
    files, folder = _series(tmp_path)
    import pydicom

    ipp = [float(x) for x in pydicom.dcmread(files[4]).ImagePositionPatient]
    _edit(files[4], ImagePositionPatient=[ipp[0], ipp[1], ipp[2] + 1.7])
    _bad(folder, tmp_path, "non-uniform slice spacing")


def test_mixed_orientations(tmp_path):
    files, folder = _series(tmp_path)
    _edit(files[3], ImageOrientationPatient=[1, 0, 0, 0, 0, -1])
    _bad(folder, tmp_path, "mixed orientations")


def test_a_dwi_series_without_b_values(tmp_path):
    data, affine, bvals, g = _dwi_world()
    write_mr_series(tmp_path / "d", data[..., :4], affine, bvals=bvals[:4], gradients=g[:4], with_bvalues=False)
    _bad(tmp_path / "d", tmp_path, "DWI series without b-values", diffusion=True)


def test_cli_names_the_folder_and_exits_2(tmp_path):
    """Through `pixmuscle run`: exit 2, one line naming the folder, no half-converted cache."""
    import subprocess
    import sys

    files, folder = _series(tmp_path)
    files[2].unlink()
    cfg = _demo_config(tmp_path, tmp_path / "out", mri=str(folder))
    run = subprocess.run([sys.executable, "-m", "pixmuscle.cli", "run", str(cfg)], capture_output=True, text=True)
    assert run.returncode == 2, run.stderr
    assert str(folder) in run.stderr and "missing" in run.stderr
    assert not list((tmp_path / "out").rglob(".partial-*"))


def test_shipped_scanner_config_runs_from_its_dicom_folder(tmp_path):
    """configs/scanner.yaml: the bundled DICOM folder's T1 and DWI series, N4 and the report's bias-field section;
    the bones and the outline it segments match the phantom's truth, and a rerun converts and segments nothing."""
    pytest.importorskip("SimpleITK")
    pytest.importorskip("dipy")
    from pixmuscle.pipeline import load_run, run_subject
    from pixmuscle.segmentation.scoring import dice

    case = load_run(ROOT / "configs" / "scanner.yaml", output_dir=tmp_path / "out").cases[0]
    summary = run_subject(case)
    out = Path(summary["output_dir"])
    assert (out / "segmentation_bias_field.nii.gz").is_file() and (out / "segmentation.seg.nrrd").is_file()
    html = (out / "report" / "index.html").read_text()
    assert "MRI bias field" in html and "Diffusion data (DWI tensor fit)" in html
    with h5py.File(out / "segmentation.h5") as f:
        labels = f["labels"][()]
    truth = load_volume(DATA / "leg_demo_labels.nii.gz", kind="labels").data
    assert dice(labels == 4, truth == 4) >= 0.95 and dice(labels > 0, truth > 0) >= 0.99
    rerun = run_subject(load_run(ROOT / "configs" / "scanner.yaml", output_dir=tmp_path / "out").cases[0])
    assert "segment" in rerun["skipped"]                    # the folder's files unchanged: nothing converted again


def test_without_the_extra_the_error_names_the_install_command(tmp_path, monkeypatch):
    """A DICOM folder, an NRRD label map or N4 without their libraries: exit-2 errors with the one install command."""
    import sys

    from pixmuscle.imaging.bias import n4_correct
    from pixmuscle.io.labelmap import read_label_map

    files, folder = _series(tmp_path)
    for module in ("pydicom", "nrrd", "SimpleITK"):
        monkeypatch.setitem(sys.modules, module, None)                     # import fails as if not installed
    for call in (lambda: dicom_to_nifti(folder, tmp_path / "cache"),
                 lambda: read_label_map(tmp_path / "x.seg.nrrd"),
                 lambda: n4_correct(np.ones((4, 4, 2)), (0.1, 0.1, 0.5))):
        with pytest.raises(InputError, match=r"pip install 'pixmuscle\[scanner\]'"):
            call()


def test_n4_recovers_a_known_bias_field():
    """N4 against the field that made the image: a two-tissue phantom times a smooth ±30 % field; the estimated
    field equals the true one up to a constant factor (the one thing N4 cannot know) within 2 % at 95 % of the
    object's voxels and 5 % at every one, and the corrected image's tissues are flat again (their spread at
    least 5 times smaller than before: 6 % and 13 % → under 2 %)."""
    pytest.importorskip("SimpleITK")
    from pixmuscle.imaging.bias import n4_correct

    n = (64, 64, 8)
    h = np.array([0.2, 0.2, 0.5])
    x, y, z = np.meshgrid(*(np.arange(k) * s for k, s in zip(n, h, strict=True)), indexing="ij")
    r = np.hypot(x - 6.3, y - 6.3)
    tissue = np.where(r < 5.5, np.where(r < 2.5, 1.0, 0.45), 0.0)             # fat-like core, muscle-like ring, air
    field = 1.0 + 0.3 * np.sin(0.35 * x + 0.2) * np.cos(0.25 * y) + 0.05 * np.cos(0.4 * z)
    corrected, est = n4_correct(tissue * field, h)
    inside = tissue > 0
    ratio = est[inside] / field[inside]
    dev = np.abs(ratio / np.median(ratio) - 1)
    assert np.percentile(dev, 95) < 0.02 and dev.max() < 0.05
    for level in (1.0, 0.45):
        before, after = (tissue * field)[tissue == level], corrected[tissue == level]
        cv = after.std() / after.mean()
        assert cv < 0.02 and cv < before.std() / before.mean() / 5, level

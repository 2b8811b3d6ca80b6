"""NIfTI reading/writing: units to cm, closest-canonical orientation, vector conventions, errors."""

import gzip

import nibabel as nib
import numpy as np
import pytest

from pixmuscle.errors import InputError
from pixmuscle.imaging.nifti import load_volume, save_volume


def write_raw(path, data, affine_mm, unit="mm"):
    img = nib.Nifti1Image(np.asarray(data), affine_mm)
    img.header.set_xyzt_units(unit)
    nib.save(img, str(path))
    return path


def world(aff, shape):
    idx = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), axis=-1)
    return idx @ aff[:3, :3].T + aff[:3, 3]


def test_round_trip_in_cm(tmp_path):
    a = np.diag([0.156, 0.156, 0.5, 1.0])
    a[:3, 3] = [-3.0, 4.0, 12.0]
    x = np.random.default_rng(0).random((5, 6, 4))
    p = save_volume(tmp_path / "x.nii.gz", x, a)
    v = load_volume(p)
    np.testing.assert_allclose(v.data, x, rtol=1e-6)
    np.testing.assert_allclose(v.affine, a, atol=1e-12)
    np.testing.assert_allclose(v.spacing, [0.156, 0.156, 0.5])
    # on disk: millimetres
    img = nib.load(str(p))
    assert img.header.get_xyzt_units()[0] == "mm"
    np.testing.assert_allclose(img.affine[:3, :3], 10 * a[:3, :3], rtol=1e-6)
    assert [f.name for f in tmp_path.iterdir()] == ["x.nii.gz"]  # no temporary left behind


@pytest.mark.parametrize("unit,factor", [("mm", 0.1), ("unknown", 0.1), ("meter", 100.0), ("micron", 1e-4)])
def test_units_to_cm(tmp_path, unit, factor):
    a = np.diag([2.0, 3.0, 4.0, 1.0])
    a[:3, 3] = [10.0, -20.0, 30.0]
    p = write_raw(tmp_path / "u.nii", np.ones((2, 3, 4)), a, unit)
    v = load_volume(p)
    expected = a.copy()
    expected[:3, :] *= factor
    np.testing.assert_allclose(v.affine, expected, rtol=1e-12)


def test_reorientation_to_ras_keeps_each_voxel_at_its_world_position(tmp_path):
    # a volume stored L-P-I with axes permuted (voxel axis 0 along world z, flipped, etc.)
    a = np.zeros((4, 4))
    a[2, 0] = -2.0  # voxel axis 0 -> -z
    a[0, 1] = -1.0  # voxel axis 1 -> -x
    a[1, 2] = 1.5  # voxel axis 2 -> +y
    a[:3, 3] = [5.0, -7.0, 20.0]
    a[3, 3] = 1.0
    shape = (4, 5, 6)
    data = np.arange(np.prod(shape), dtype=float).reshape(shape) + 1
    p = write_raw(tmp_path / "o.nii.gz", data, a)
    v = load_volume(p)
    # canonical: diagonal, positive affine (RAS+)
    lin = v.affine[:3, :3]
    assert np.allclose(lin, np.diag(np.diag(lin))) and np.all(np.diag(lin) > 0)
    np.testing.assert_allclose(np.diag(lin), [0.1, 0.15, 0.2])
    # each value sits at the same world position (cm) as in the original
    w_orig = world(a, shape) * 0.1
    w_new = world(v.affine, v.data.shape)
    ref = {tuple(np.round(w, 6)): val for w, val in zip(w_orig.reshape(-1, 3), data.ravel(), strict=True)}
    got = {tuple(np.round(w, 6)): val for w, val in zip(w_new.reshape(-1, 3), v.data.ravel(), strict=True)}
    assert ref == got
    # agrees with nibabel's own canonical reorientation
    can = nib.as_closest_canonical(nib.load(str(p)))
    np.testing.assert_array_equal(v.data, can.get_fdata())


def test_world_vectors_are_unchanged_by_reorientation(tmp_path):
    a = np.diag([-1.0, 1.0, 1.0, 1.0])  # stored left-right flipped
    a[:3, 3] = [10.0, 0.0, 0.0]
    rng = np.random.default_rng(1)
    vec = rng.normal(size=(3, 4, 2, 3))
    p = write_raw(tmp_path / "v.nii.gz", vec, a)
    v = load_volume(p, kind="vectors")
    np.testing.assert_allclose(v.data, vec[::-1], rtol=1e-6)  # voxels flipped, components not


def test_voxel_and_fsl_component_conventions(tmp_path):
    rng = np.random.default_rng(2)
    a = np.zeros((4, 4))
    a[1, 0], a[0, 1], a[2, 2], a[3, 3] = 2.0, -2.0, 3.0, 1.0  # rotation by 90 deg about z
    r = a[:3, :3] / np.linalg.norm(a[:3, :3], axis=0)
    vw = rng.normal(size=(3, 3, 2, 3))  # the truth, in world axes
    v_vox = vw @ r  # components along the stored voxel axes: R^T v
    p = write_raw(tmp_path / "vv.nii.gz", v_vox, a)
    got = load_volume(p, kind="vectors", components="voxel").data
    ref = load_volume(write_raw(tmp_path / "vw.nii.gz", vw, a), kind="vectors").data
    np.testing.assert_allclose(got, ref, atol=1e-6)
    # FSL: for a positive-determinant affine the x component is negated relative to voxel axes
    assert np.linalg.det(a[:3, :3]) > 0
    v_fsl = v_vox * np.array([-1.0, 1.0, 1.0])
    got = load_volume(write_raw(tmp_path / "vf.nii.gz", v_fsl, a), kind="vectors", components="fsl").data
    np.testing.assert_allclose(got, ref, atol=1e-6)
    # tensors: D_world = R D_vox R^T
    m = rng.normal(size=(3, 3))
    dw = m @ m.T
    dv = r.T @ dw @ r
    comp = np.array([dv[0, 0], dv[0, 1], dv[0, 2], dv[1, 1], dv[1, 2], dv[2, 2]])
    t = load_volume(write_raw(tmp_path / "t.nii.gz", np.tile(comp, (2, 2, 2, 1)), a), kind="tensor",
                    components="voxel").data
    np.testing.assert_allclose(t[0, 0, 0], [dw[0, 0], dw[0, 1], dw[0, 2], dw[1, 1], dw[1, 2], dw[2, 2]],
                               atol=1e-5)


def test_nifti_vector_5d_layout(tmp_path):
    vec = np.random.default_rng(3).normal(size=(3, 4, 2, 1, 3))
    v = load_volume(write_raw(tmp_path / "v5.nii.gz", vec, np.eye(4)), kind="vectors")
    assert v.data.shape == (3, 4, 2, 3)


def test_labels_are_integers(tmp_path):
    lab = np.array([0, 1, 2, 3, 4, 1, 1, 2]).reshape(2, 2, 2).astype(np.float32)
    v = load_volume(write_raw(tmp_path / "l.nii.gz", lab, np.eye(4)), kind="labels")
    assert v.data.dtype.kind == "i"
    np.testing.assert_array_equal(v.data, lab)
    with pytest.raises(InputError, match="integer-valued; 1 voxels"):
        load_volume(write_raw(tmp_path / "l2.nii.gz", lab + np.r_[0.5, np.zeros(7)].reshape(2, 2, 2),
                              np.eye(4)), kind="labels")


def test_empty_mask_allowed_only_on_request(tmp_path):
    p = save_volume(tmp_path / "m.nii.gz", np.zeros((3, 3, 3), bool), np.eye(4), kind="labels")
    with pytest.raises(InputError, match="all voxels are zero"):
        load_volume(p, kind="labels")
    assert not load_volume(p, kind="labels", allow_empty=True).data.any()


def test_errors(tmp_path):
    with pytest.raises(InputError, match="file not found"):
        load_volume(tmp_path / "missing.nii.gz")
    bad = tmp_path / "bad.nii.gz"
    with gzip.open(bad, "wb") as f:
        f.write(b"this is not an image" * 50)
    with pytest.raises(InputError, match="bad.nii.gz: not a"):
        load_volume(bad)
    txt = tmp_path / "notes.txt"
    txt.write_text("hello")
    with pytest.raises(InputError, match="notes.txt"):
        load_volume(txt)
    four = write_raw(tmp_path / "four.nii.gz", np.ones((2, 2, 2, 3)), np.eye(4))
    with pytest.raises(InputError, match=r"kind 'image' needs a 3-D volume.*\(2, 2, 2, 3\)"):
        load_volume(four)
    three = write_raw(tmp_path / "three.nii.gz", np.ones((2, 2, 2)), np.eye(4))
    with pytest.raises(InputError, match=r"kind 'tensor' needs a 4-D volume \(I, J, K, 6\)"):
        load_volume(three, kind="tensor")
    nan = np.ones((3, 3, 3), np.float32)
    nan[0, 0, :2] = np.nan
    nan[1, 1, 1] = np.inf
    with pytest.raises(InputError, match="3 of 27 values are NaN or infinite"):
        load_volume(write_raw(tmp_path / "nan.nii.gz", nan, np.eye(4)))
    with pytest.raises(InputError, match="all voxels are zero"):
        load_volume(write_raw(tmp_path / "zero.nii.gz", np.zeros((2, 2, 2)), np.eye(4)))
    sing = np.eye(4)
    sing[2, 2] = 0.0
    img = nib.Nifti1Image(np.ones((2, 2, 2)), None)
    img.set_sform(sing, code=2)  # only the sform can hold a singular matrix
    nib.save(img, str(tmp_path / "sing.nii.gz"))
    with pytest.raises(InputError, match="singular affine"):
        load_volume(tmp_path / "sing.nii.gz")
    with pytest.raises(InputError, match="unknown kind"):
        load_volume(three, kind="mesh")
    with pytest.raises(InputError, match="needs a 4-D volume"):
        save_volume(tmp_path / "w.nii.gz", np.ones((2, 2, 2)), np.eye(4), kind="vectors")
    with pytest.raises(InputError, match="NaN"):
        save_volume(tmp_path / "w.nii.gz", np.full((2, 2, 2), np.nan), np.eye(4))

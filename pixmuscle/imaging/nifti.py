"""NIfTI input/output in pixmuscle's conventions: lengths in cm, closest-canonical RAS+ voxels.

Reading (:func:`load_volume`):

* The affine (nibabel's choice of sform/qform) is converted from the header's spatial unit to
  cm: mm (also when the unit is "unknown", the NIfTI default) x 0.1, meter x 100, micron x 1e-4.
* Voxels are reordered to the closest canonical RAS+ orientation (an exact permutation/flip,
  no interpolation; :func:`nibabel.orientations.io_orientation`). An oblique scan keeps a
  residual rotation in the affine.
* Vector and tensor images: pixmuscle's convention is that **components are in world
  (scanner) axes**, the axes the affine maps to. Reordering voxels does not change the world
  axes, so components are left as they are. Images whose components are along the stored
  voxel axes (``components="voxel"``) or in FSL's convention (``components="fsl"``: voxel axes
  with x negated when the stored affine has a positive determinant, as FSL's ``dtifit`` V1 and
  bvecs) are rotated to world axes on reading.

Writing (:func:`save_volume`) uses mm (affine x 10), atomically (temporary file + rename).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import nibabel as nib
import numpy as np
from nibabel.orientations import apply_orientation, inv_ornt_aff, io_orientation

from pixmuscle.errors import InputError, OutputError
from pixmuscle.imaging.dti import components_from_tensor, tensor_from_components

KINDS = ("image", "labels", "vectors", "tensor")
#: cm per header spatial unit
UNIT_TO_CM = {"unknown": 0.1, "mm": 0.1, "meter": 100.0, "micron": 1e-4}
#: trailing component count of each kind (None: scalar)
_COMPONENTS = {"image": None, "labels": None, "vectors": 3, "tensor": 6}


@dataclass
class Volume:
    """An image on a grid.

    Attributes
    ----------
    data : ndarray
        (I, J, K) for images (float64) and labels (integer); (I, J, K, 3) vectors and
        (I, J, K, 6) tensor components (float64) in world axes.
    affine : (4, 4) ndarray
        Voxel index -> world position, cm.
    path : Path or None
        File it came from.
    spacing : (3,) ndarray
        Voxel edge lengths, cm (column norms of the affine); derived, not an argument.
    """

    data: np.ndarray
    affine: np.ndarray
    path: Path | None = None
    spacing: np.ndarray = field(init=False)

    def __post_init__(self):
        self.affine = np.asarray(self.affine, dtype=float)
        self.spacing = np.linalg.norm(self.affine[:3, :3], axis=0)


def _fail(path, msg):
    raise InputError(f"{path}: {msg}")


def _expected(kind):
    n = _COMPONENTS[kind]
    return "a 3-D volume (I, J, K)" if n is None else f"a 4-D volume (I, J, K, {n})"


def _shape_for_kind(data, kind, path):
    """Drop singleton axes beyond the third (NIfTI stores vectors as (I,J,K,1,C)); check shape."""
    n = _COMPONENTS[kind]
    shape = list(data.shape)
    while len(shape) > 3 and shape[3] == 1 and (n is None or len(shape) > 4):
        shape.pop(3)
    data = data.reshape(shape)
    ok = data.ndim == 3 if n is None else (data.ndim == 4 and data.shape[3] == n)
    if not ok:
        _fail(path, f"kind {kind!r} needs {_expected(kind)}, got shape {tuple(data.shape)}")
    return data


def _voxel_to_world(data, kind, components, affine, tensor_order):
    """Rotate component images from voxel (or FSL) axes to world axes of ``affine``."""
    r = affine[:3, :3] / np.linalg.norm(affine[:3, :3], axis=0)
    if components == "fsl" and np.linalg.det(affine[:3, :3]) > 0:
        r = r @ np.diag([-1.0, 1.0, 1.0])
    if kind == "vectors":
        return data @ r.T
    d = tensor_from_components(data, tensor_order)
    d = r @ d @ r.T
    return components_from_tensor(d, tensor_order)


def file_affine_cm(path) -> np.ndarray:
    """Voxel index → world cm of the NIfTI file's **own** voxel grid (as stored, before the
    reorientation of :func:`load_volume`), shape ``(4, 4)``."""
    path = Path(path)
    try:
        img = nib.load(str(path))
    except Exception as exc:  # nibabel raises several types for unreadable files
        _fail(path, f"not a readable NIfTI file ({type(exc).__name__}: {exc})")
    unit = img.header.get_xyzt_units()[0]
    if unit not in UNIT_TO_CM:
        _fail(path, f"unsupported spatial unit {unit!r}; expected mm, meter or micron")
    a = np.asarray(img.affine, dtype=float).copy()
    a[:3, :] *= UNIT_TO_CM[unit]
    return a


def load_volume(path, *, kind: str = "image", components: str = "world", tensor_order: str = "fsl",
                allow_empty: bool = False) -> Volume:
    """Read a NIfTI file in cm and closest-canonical RAS+ orientation.

    Parameters
    ----------
    path : str or Path
        ``.nii`` or ``.nii.gz`` file.
    kind : {"image", "labels", "vectors", "tensor"}
        ``image``: 3-D float; ``labels``: 3-D integer-valued (also masks); ``vectors``:
        (I, J, K, 3) (or NIfTI's (I, J, K, 1, 3)); ``tensor``: (I, J, K, 6) components in
        ``tensor_order``.
    components : {"world", "voxel", "fsl"}
        Axes of vector/tensor components in the file (see module notes); returned components
        are always in world axes.
    tensor_order : {"fsl", "dipy", "mrtrix"}
        Component order of a tensor file (kept in the returned data).
    allow_empty : bool
        Accept an all-zero volume (e.g. an empty IMAT mask); otherwise that is an error.

    Returns
    -------
    Volume

    Raises
    ------
    InputError
        Missing file, not NIfTI, wrong dimensionality for ``kind``, NaN/inf voxels, all-zero
        volume, singular affine, non-integer labels, unknown unit.
    """
    path = Path(path)
    if kind not in KINDS:
        raise InputError(f"load_volume: unknown kind {kind!r}; expected one of {KINDS}")
    if components not in ("world", "voxel", "fsl"):
        raise InputError(f"load_volume: unknown components {components!r}; expected 'world', 'voxel' or 'fsl'")
    if not path.exists():
        _fail(path, "file not found")
    if path.is_dir():
        _fail(path, "is a directory, expected a NIfTI file (.nii or .nii.gz)")
    try:
        img = nib.load(str(path))
    except Exception as exc:  # nibabel raises several types for unreadable files
        _fail(path, f"not a readable NIfTI file ({type(exc).__name__}: {exc})")
    if not isinstance(img, (nib.Nifti1Image, nib.Nifti2Image)):
        _fail(path, f"not a NIfTI file (nibabel read it as {type(img).__name__}); expected .nii or .nii.gz")
    unit = img.header.get_xyzt_units()[0]
    if unit not in UNIT_TO_CM:
        _fail(path, f"unsupported spatial unit {unit!r}; expected mm, meter or micron")
    affine = np.asarray(img.affine, dtype=float)
    if not np.all(np.isfinite(affine)):
        _fail(path, "the affine has non-finite entries")
    lin = affine[:3, :3]
    if abs(np.linalg.det(lin)) <= 1e-9 * max(np.abs(lin).max(), 1e-300) ** 3:
        _fail(path, f"singular affine (voxel axes linearly dependent):\n{affine}")
    try:
        raw = np.asanyarray(img.dataobj)
        data = np.asarray(raw, dtype=float) if raw.dtype.kind != "f" else np.asarray(raw, dtype=np.float64)
    except Exception as exc:
        _fail(path, f"could not read the voxel data ({type(exc).__name__}: {exc})")
    data = _shape_for_kind(data, kind, path)
    bad = ~np.isfinite(data)
    if bad.any():
        _fail(path, f"{int(bad.sum())} of {data.size} values are NaN or infinite")
    if not allow_empty and not np.any(data):
        _fail(path, "all voxels are zero")
    if kind == "labels":
        frac = np.abs(data - np.rint(data))
        if np.any(frac > 1e-6):
            _fail(path, f"labels must be integer-valued; {int(np.sum(frac > 1e-6))} voxels are not "
                        f"(e.g. {data[frac > 1e-6].flat[0]!r})")
        lo, hi = data.min(), data.max()
        dtype = np.int16 if -32768 <= lo and hi <= 32767 else np.int64
        data = np.rint(data).astype(dtype)
    if kind in ("vectors", "tensor") and components != "world":
        data = _voxel_to_world(data, kind, components, affine, tensor_order)
    # closest canonical (RAS+) voxel order: exact permutation / flip of the first three axes
    ornt = io_orientation(affine)
    data = apply_orientation(data, ornt)
    affine = affine @ inv_ornt_aff(ornt, img.shape[:3])
    affine[:3, :] *= UNIT_TO_CM[unit]
    return Volume(data=np.ascontiguousarray(data), affine=affine, path=path)


def save_volume(path, data, affine_cm, *, kind: str = "image") -> Path:
    """Write a NIfTI file (mm units, affine x 10) atomically: temporary file, then rename.

    Parameters
    ----------
    path : str or Path
        Target; ``.nii.gz`` is gzip-compressed.
    data : ndarray
        (I, J, K) for ``image`` (stored float32) and ``labels`` (int16, or uint8 for bool
        masks); (I, J, K, 3) ``vectors`` and (I, J, K, 6) ``tensor`` (float32).
    affine_cm : (4, 4) array_like
        Voxel index -> world, cm.
    kind : {"image", "labels", "vectors", "tensor"}

    Returns
    -------
    Path
    """
    path = Path(path)
    if kind not in KINDS:
        raise InputError(f"save_volume: unknown kind {kind!r}; expected one of {KINDS}")
    data = np.asarray(data)
    n = _COMPONENTS[kind]
    ok = data.ndim == 3 if n is None else (data.ndim == 4 and data.shape[3] == n)
    if not ok:
        raise InputError(f"save_volume {path}: kind {kind!r} needs {_expected(kind)}, got shape {data.shape}")
    if data.dtype.kind == "f" and not np.all(np.isfinite(data)):
        raise InputError(f"save_volume {path}: {int(np.sum(~np.isfinite(data)))} values are NaN or infinite")
    affine = np.array(affine_cm, dtype=float)
    if affine.shape != (4, 4):
        raise InputError(f"save_volume {path}: affine must be (4, 4), got {affine.shape}")
    affine[:3, :] *= 10.0
    if kind == "labels":
        data = data.astype(np.uint8) if data.dtype == bool else data.astype(np.int16)
    else:
        data = data.astype(np.float32)
    img = nib.Nifti1Image(data, affine)
    img.header.set_xyzt_units("mm")
    img.set_sform(affine, code=1)
    img.set_qform(affine, code=1)
    suffix = ".nii.gz" if path.name.endswith(".nii.gz") else ".nii"
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}{suffix}")
    try:
        nib.save(img, str(tmp))
        os.replace(tmp, path)
    except OSError as exc:  # disk full, read-only: one line naming the file (nibabel's error names none)
        from ..outdir import WRITE_ERRNOS, describe_os_error

        if exc.errno in WRITE_ERRNOS:
            raise OutputError(describe_os_error(exc, path) + "; nothing was written") from None
        raise
    finally:
        if tmp.exists():
            tmp.unlink()
    return path

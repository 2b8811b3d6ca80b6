"""DICOM series: a folder of a scanner's files in, NIfTI (+ FSL ``.bval`` / ``.bvec``) out; and a
writer of single-frame MR series (synthetic phantoms as a scanner would export them, and tests).

Reading is two well-kept tools, each for what it does best:

* **pydicom** reads the headers of every file in the folder (any names, any order, sub-folders
  too), groups them into series by SeriesInstanceUID, picks the one the config names and checks it
  before anything is converted: pixel data present, one orientation, one in-plane grid, slice
  positions that form a uniform stack (no gap, no duplicate), b-values for a diffusion series.
* **dcm2niix** (Rorden's converter, the field's reference) converts the chosen series: orientation
  from ImageOrientationPatient / ImagePositionPatient (LPS, any in-plane orientation, head- or
  feet-first), slice spacing from the positions (not SliceThickness), RescaleSlope / Intercept
  kept as the NIfTI scaling (applied on reading), b-values and gradient directions from the
  standard or vendor diffusion tags written as FSL ``.bval`` / ``.bvec`` (the convention of
  :func:`pixmuscle.imaging.dwi.read_gradients` with ``bvecs_convention: fsl``).

Each conversion is cached in a folder named by the SHA-256 of the series' files (and the
converter's version): a rerun finds it, a changed file makes a new one. A conversion is made in a
temporary folder and renamed into place when complete, so the cache never holds half a series.

Both libraries are the optional extra ``scanner`` (``pip install 'pixmuscle[scanner]'``).

References
----------
Li, X., Morgan, P. S., Ashburner, J., Smith, J., Rorden, C. (2016). The first step for
neuroimaging data analysis: DICOM to NIfTI conversion. *J Neurosci Methods* 264, 47–56.
NEMA PS3.3, C.7.6.2 Image Plane Module (ImageOrientationPatient, ImagePositionPatient, LPS).
NEMA PS3.3, C.8.13.5.9 MR Diffusion Macro (DiffusionBValue, DiffusionGradientOrientation).
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import uuid
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pixmuscle.errors import InputError, OutputError

__all__ = ["INSTALL_HINT", "ConvertedSeries", "Series", "convert_series", "dicom_to_nifti", "find_series",
           "select_series", "check_series", "write_mr_series"]

INSTALL_HINT = "pip install 'pixmuscle[scanner]'"
#: b-value tags: the standard MR Diffusion Macro's, then Siemens, GE and Philips private ones
_BVALUE_TAGS = ((0x0018, 0x9087), (0x0019, 0x100C), (0x0043, 0x1039), (0x2001, 0x1003))
#: slice positions closer than this (mm) are the same slice
_SAME_POSITION_MM = 1e-3
#: relative spread of slice gaps still called uniform
_UNIFORM_REL = 0.01


def _pydicom():
    try:
        import pydicom
    except ImportError:
        raise InputError(f"reading DICOM needs pydicom and dcm2niix: {INSTALL_HINT}") from None
    return pydicom


def _dcm2niix() -> str:
    try:
        import dcm2niix
    except ImportError:
        raise InputError(f"converting DICOM needs dcm2niix: {INSTALL_HINT}") from None
    return str(dcm2niix.bin)


@dataclass
class Series:
    """One DICOM series of a folder.

    Attributes
    ----------
    uid : str
        SeriesInstanceUID.
    number : int or None
        SeriesNumber.
    description : str
        SeriesDescription ('' when absent).
    files : list of Path
        Its files, sorted by name.
    headers : list of pydicom.Dataset
        Their headers (pixel data deferred, not read).
    """

    uid: str
    number: int | None
    description: str
    files: list[Path] = field(default_factory=list)
    headers: list = field(default_factory=list, repr=False)

    def line(self) -> str:
        """One line for a listing: number, description, file count, UID."""
        return (f"SeriesNumber {self.number if self.number is not None else '-'}, "
                f"SeriesDescription {self.description!r}, {len(self.files)} files, SeriesInstanceUID {self.uid}")


def find_series(folder: str | os.PathLike) -> list[Series]:
    """The DICOM series of the files under ``folder`` (recursively; non-DICOM files are skipped).

    Raises
    ------
    InputError
        The folder holds no DICOM file.
    """
    pydicom = _pydicom()
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"{folder}: not a folder")
    found: dict[str, Series] = {}
    for p in sorted(q for q in folder.rglob("*") if q.is_file() and q.name.upper() != "DICOMDIR"):
        try:
            ds = pydicom.dcmread(p, defer_size=1024)
        except (pydicom.errors.InvalidDicomError, OSError, ValueError, EOFError):
            continue
        uid = str(ds.get("SeriesInstanceUID", "") or "(no SeriesInstanceUID)")
        s = found.get(uid)
        if s is None:
            number = ds.get("SeriesNumber")
            s = found[uid] = Series(uid, int(number) if number not in (None, "") else None,
                                    str(ds.get("SeriesDescription", "") or ""))
        s.files.append(p)
        s.headers.append(ds)
    if not found:
        raise InputError(f"{folder}: no DICOM files in this folder (files with the DICM preamble)")
    return sorted(found.values(), key=lambda s: (s.number is None, s.number or 0, s.uid))


def select_series(series: Sequence[Series], selector: str | int | None, folder, key: str) -> Series:
    """The series that ``selector`` names: its SeriesInstanceUID, SeriesNumber or SeriesDescription.

    Without a selector the folder must hold one series. ``key`` is the config key of the selector,
    named in the error that lists the series found.
    """
    listing = "\n".join(f"  {s.line()}" for s in series)
    if selector is None:
        if len(series) == 1:
            return series[0]
        raise InputError(f"{folder}: {len(series)} DICOM series in this folder; choose one with {key} "
                         f"(SeriesNumber, SeriesDescription or SeriesInstanceUID):\n{listing}")
    text = str(selector).strip()
    hits = [s for s in series if s.uid == text]
    if not hits and text.lstrip("-").isdigit():
        hits = [s for s in series if s.number == int(text)]
    if not hits:
        hits = [s for s in series if s.description == text]
    if len(hits) == 1:
        return hits[0]
    what = "matches no series" if not hits else f"matches {len(hits)} series (give the SeriesNumber or UID)"
    raise InputError(f"{folder}: {key} = {text!r} {what}; the series found:\n{listing}")


def _floats(ds, name: str, n: int, path: Path) -> np.ndarray:
    v = ds.get(name)
    if v is None or len(v) != n:
        raise InputError(f"{path}: DICOM tag {name} missing or not {n} numbers")
    return np.asarray([float(x) for x in v])


def _has_bvalue(ds) -> bool:
    return any(tag in ds for tag in _BVALUE_TAGS)


def check_series(s: Series, folder, *, diffusion: bool = False) -> int:
    """Check that a series forms one uniform image stack; return its number of volumes.

    Checks: every file has pixel data; one ImageOrientationPatient, Rows × Columns and PixelSpacing;
    the slice positions along the slice normal repeat the same number of times (the volumes) and
    are equally spaced (no missing slice, no duplicate, no irregular spacing); a diffusion series
    carries a b-value in every file. Multi-frame (enhanced) files are left to the converter.

    Raises
    ------
    InputError
        Naming the folder (and the file where one file is at fault).
    """
    headers, files = s.headers, s.files
    what = f"{folder} (series {s.number if s.number is not None else s.uid})"
    for ds, p in zip(headers, files, strict=True):
        if "PixelData" not in ds and "FloatPixelData" not in ds and "DoubleFloatPixelData" not in ds:
            raise InputError(f"{p}: DICOM file without pixel data (series of {what})")
    if any(int(ds.get("NumberOfFrames", 1) or 1) > 1 for ds in headers):
        if len(files) > 1:
            raise InputError(f"{what}: multi-frame files mixed with other files in one series")
        return int(headers[0].NumberOfFrames)
    iop = np.array([_floats(ds, "ImageOrientationPatient", 6, p) for ds, p in zip(headers, files, strict=True)])
    bad = np.flatnonzero(np.abs(iop - iop[0]).max(axis=1) > 1e-4)
    if bad.size:
        raise InputError(f"{what}: mixed orientations in one series: {files[0].name} has ImageOrientationPatient "
                         f"{iop[0].round(4).tolist()}, {files[bad[0]].name} {iop[bad[0]].round(4).tolist()}")
    grids = {(int(ds.Rows), int(ds.Columns), *np.round(_floats(ds, "PixelSpacing", 2, p), 5))
             for ds, p in zip(headers, files, strict=True)}
    if len(grids) > 1:
        raise InputError(f"{what}: slices of different sizes or pixel spacings in one series: {sorted(grids)}")
    normal = np.cross(iop[0, :3], iop[0, 3:])
    ipp = np.array([_floats(ds, "ImagePositionPatient", 3, p) for ds, p in zip(headers, files, strict=True)])
    d = ipp @ normal                                     # mm along the slice normal
    order = np.argsort(d, kind="stable")
    ds_sorted = d[order]
    new = np.r_[True, np.diff(ds_sorted) > _SAME_POSITION_MM]
    positions = ds_sorted[new]
    counts = np.diff(np.r_[np.flatnonzero(new), d.size])
    volumes = int(np.median(counts))
    odd = np.flatnonzero(counts != volumes)
    if odd.size:
        i = odd[0]
        name = files[order[np.flatnonzero(new)[i]]].name
        kind = "duplicated" if counts[i] > volumes else "missing in some volumes"
        raise InputError(f"{what}: slice at {positions[i]:.3f} mm along the normal is {kind} "
                         f"({counts[i]} files, e.g. {name}, against {volumes} at the other positions)")
    if positions.size > 2:
        gaps = np.diff(positions)
        h = float(np.median(gaps))
        tol = max(_UNIFORM_REL * h, 0.01)
        off = np.flatnonzero(np.abs(gaps - h) > tol)
        if off.size:
            i = off[0]
            ratio = gaps[i] / h
            if abs(ratio - round(ratio)) * h <= tol and round(ratio) >= 2:
                raise InputError(f"{what}: {round(ratio) - 1} slice(s) missing between positions {positions[i]:.3f} "
                                 f"and {positions[i + 1]:.3f} mm along the normal (spacing {h:.3f} mm)")
            raise InputError(f"{what}: non-uniform slice spacing: {gaps[i]:.3f} mm between positions "
                             f"{positions[i]:.3f} and {positions[i + 1]:.3f}, {h:.3f} mm elsewhere")
    if diffusion:
        if volumes < 2:
            raise InputError(f"{what}: a diffusion series needs several volumes (one per gradient), found one")
        missing = [p.name for ds, p in zip(headers, files, strict=True) if not _has_bvalue(ds)]
        if missing:
            raise InputError(f"{what}: a DWI series without b-values (no DiffusionBValue (0018,9087) or vendor "
                             f"b-value tag in {len(missing)} files, e.g. {missing[0]})")
    return volumes


@dataclass(frozen=True)
class ConvertedSeries:
    """A converted series in the cache.

    Attributes
    ----------
    image : Path
        NIfTI (``.nii.gz``).
    bvals, bvecs : Path or None
        FSL b-values (s/mm²) and b-vectors of a diffusion series.
    """

    image: Path
    bvals: Path | None = None
    bvecs: Path | None = None


def _series_key(files: Sequence[Path], tool_version: str) -> str:
    from pixmuscle.store import sha256_file

    h = hashlib.sha256(tool_version.encode())
    for digest in sorted(sha256_file(p) for p in files):
        h.update(digest.encode())
    return h.hexdigest()


def _tool_version(binary: str) -> str:
    try:
        import dcm2niix

        return f"dcm2niix {dcm2niix.__version__}"
    except (ImportError, AttributeError):
        return binary


def convert_series(s: Series, cache_dir: str | os.PathLike, *, diffusion: bool = False) -> ConvertedSeries:
    """Convert one checked series with dcm2niix into ``cache_dir/<key>/`` (once; reused after).

    Parameters
    ----------
    s : Series
    cache_dir : path-like
        Folder of the conversions (created if needed).
    diffusion : bool
        Require and return the ``.bval`` / ``.bvec`` files.

    Returns
    -------
    ConvertedSeries
    """
    binary = _dcm2niix()
    cache_dir = Path(cache_dir)
    key = _series_key(s.files, _tool_version(binary))[:20]
    done = cache_dir / key

    def result(folder: Path) -> ConvertedSeries:
        img = folder / "image.nii.gz"
        if not diffusion:
            return ConvertedSeries(img)
        return ConvertedSeries(img, folder / "image.bval", folder / "image.bvec")

    if (done / "image.nii.gz").is_file():
        return result(done)
    tmp = cache_dir / f".partial-{key}-{uuid.uuid4().hex[:8]}"
    try:
        (tmp / "in").mkdir(parents=True)
        (tmp / "out").mkdir()
        for i, p in enumerate(s.files):                  # only this series' files, under neutral names
            link = tmp / "in" / f"{i:06d}.dcm"
            try:
                os.link(p, link)
            except OSError:
                shutil.copyfile(p, link)
        run = subprocess.run([binary, "-z", "y", "-b", "y", "-ba", "y", "-f", "image", "-o", str(tmp / "out"),
                              str(tmp / "in")], capture_output=True, text=True)
        made = sorted(q.name for q in (tmp / "out").glob("*.nii.gz"))
        if run.returncode != 0 or made != ["image.nii.gz"]:
            tail = " | ".join((run.stdout + run.stderr).strip().splitlines()[-4:])
            raise InputError(f"{s.files[0].parent}: dcm2niix could not convert series "
                             f"{s.number if s.number is not None else s.uid} into one image "
                             f"(made {made or 'nothing'}; exit {run.returncode}): {tail}")
        if diffusion and not ((tmp / "out" / "image.bval").is_file() and (tmp / "out" / "image.bvec").is_file()):
            raise InputError(f"{s.files[0].parent}: a DWI series without b-values: dcm2niix found no diffusion "
                             f"gradients in series {s.number if s.number is not None else s.uid}")
        try:
            (tmp / "out").rename(done)
        except OSError:
            if not (done / "image.nii.gz").is_file():    # not another run's identical result: a real failure
                raise
    except OSError as exc:
        raise OutputError(f"{cache_dir}: cannot write the DICOM conversion: {exc}") from None
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return result(done)


def dicom_to_nifti(folder: str | os.PathLike, cache_dir: str | os.PathLike, *, series: str | int | None = None,
                   key: str = "series", diffusion: bool = False) -> ConvertedSeries:
    """Find, check and convert the chosen series of a DICOM folder (cached).

    Parameters
    ----------
    folder : path-like
        A folder of DICOM files (any names, any order).
    cache_dir : path-like
        Where conversions are kept.
    series : str or int, optional
        SeriesInstanceUID, SeriesNumber or SeriesDescription; needed when the folder holds several.
    key : str
        The config key of ``series``, for error messages.
    diffusion : bool
        A diffusion series: b-values are required and converted.

    Returns
    -------
    ConvertedSeries
    """
    found = find_series(folder)
    s = select_series(found, series, folder, key)
    check_series(s, folder, diffusion=diffusion)
    return convert_series(s, cache_dir, diffusion=diffusion)


# --------------------------------------------------------------------------------------------- writing

_RAS_TO_LPS = np.diag([-1.0, -1.0, 1.0])


def write_mr_series(folder: str | os.PathLike, data, affine_cm, *, series_number: int = 1,
                    description: str = "T1", study_uid: str | None = None, patient_position: str = "HFS",
                    bvals=None, gradients=None, names: Sequence[str] | None = None,
                    with_bvalues: bool = True, uid_seed: str | None = None) -> list[Path]:
    """Write a volume as a single-frame MR Image Storage series, one file per slice (and volume).

    Parameters
    ----------
    folder : path-like
        Created if needed.
    data : ndarray, shape (I, J, K) or (I, J, K, V)
        Image values (any float range); stored as uint16 with RescaleSlope / RescaleIntercept so
        that ``stored * slope + intercept`` gives them back to within ``slope / 2``.
    affine_cm : (4, 4) array
        Voxel index (i, j, k) → RAS world position, cm. Columns of a DICOM slice run along i,
        rows along j, slices along k: any orientation the affine describes is written as it is.
    series_number, description, study_uid, patient_position : DICOM attributes of the series.
    bvals : (V,) array, optional
        b-values, s/mm² (a diffusion series: the MR Diffusion Macro's tags in every file).
    gradients : (V, 3) array, optional
        Unit gradient directions in world RAS axes (written in LPS as DICOM wants).
    names : sequence of str, optional
        File names, one per written file in (volume, slice) order; default ``IM_<n>.dcm``.
    with_bvalues : bool
        Write the diffusion tags (False makes a DWI series without b-values).
    uid_seed : str, optional
        Derive every UID from this text (the same files on every run); default random UIDs.

    Returns
    -------
    list of Path
        The files written.
    """
    pydicom = _pydicom()
    from pydicom.dataset import FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian, MRImageStorage, generate_uid

    data = np.asarray(data, dtype=float)
    if data.ndim == 3:
        data = data[..., None]
    if data.ndim != 4:
        raise InputError(f"write_mr_series: expected a 3-D or 4-D array, got shape {data.shape}")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    A = np.asarray(affine_cm, float)
    lin = _RAS_TO_LPS @ A[:3, :3] * 10.0                  # mm, LPS
    origin = _RAS_TO_LPS @ A[:3, 3] * 10.0
    sx, sy = np.linalg.norm(lin[:, 0]), np.linalg.norm(lin[:, 1])
    iop = np.r_[lin[:, 0] / sx, lin[:, 1] / sy]
    lo, hi = float(data.min()), float(data.max())
    slope = (hi - lo) / 65535.0 if hi > lo else 1.0
    stored = np.rint((data - lo) / slope).clip(0, 65535).astype(np.uint16)
    n_i, n_j, n_k, n_v = data.shape
    def uid(*what) -> str:
        return generate_uid() if uid_seed is None else generate_uid(entropy_srcs=[uid_seed, *map(str, what)])

    study_uid = study_uid or uid("study")
    series_uid, frame_uid = uid("series", series_number), uid("frame")
    written = []
    for v in range(n_v):
        for k in range(n_k):
            n = v * n_k + k
            meta = FileMetaDataset()
            meta.MediaStorageSOPClassUID = MRImageStorage
            meta.MediaStorageSOPInstanceUID = uid("instance", series_number, n)
            meta.TransferSyntaxUID = ExplicitVRLittleEndian
            ds = pydicom.Dataset()
            ds.file_meta = meta
            ds.SOPClassUID, ds.SOPInstanceUID = MRImageStorage, meta.MediaStorageSOPInstanceUID
            ds.Modality, ds.Manufacturer = "MR", "pixmuscle synthetic"
            ds.PatientName, ds.PatientID, ds.PatientPosition = "SYNTHETIC^PHANTOM", "SYNTHETIC", patient_position
            ds.StudyInstanceUID, ds.SeriesInstanceUID, ds.FrameOfReferenceUID = study_uid, series_uid, frame_uid
            ds.SeriesNumber, ds.SeriesDescription = series_number, description
            ds.InstanceNumber, ds.AcquisitionNumber = n + 1, 1
            ds.ImageType = ["ORIGINAL", "PRIMARY", "M", "ND"]
            ds.ImageOrientationPatient = [f"{x:.8f}" for x in iop]
            ds.ImagePositionPatient = [f"{x:.6f}" for x in origin + lin[:, 2] * k]
            ds.PixelSpacing = [f"{sy:.6f}", f"{sx:.6f}"]       # row spacing (along j), column spacing (along i)
            ds.SliceThickness = f"{np.linalg.norm(lin[:, 2]):.6f}"
            ds.Rows, ds.Columns = n_j, n_i
            ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
            ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 0
            ds.RescaleSlope, ds.RescaleIntercept, ds.RescaleType = f"{slope:.10g}", f"{lo:.10g}", "US"
            if bvals is not None and with_bvalues:
                b = float(bvals[v])
                ds.add_new((0x0018, 0x9087), "FD", b)                      # DiffusionBValue
                if b > 0 and gradients is not None:
                    g = _RAS_TO_LPS @ np.asarray(gradients[v], float)
                    ds.add_new((0x0018, 0x9075), "CS", "DIRECTIONAL")
                    ds.add_new((0x0018, 0x9089), "FD", [float(x) for x in g])  # DiffusionGradientOrientation
                else:
                    ds.add_new((0x0018, 0x9075), "CS", "NONE")
            ds.PixelData = np.ascontiguousarray(stored[:, :, k, v].T).tobytes()
            p = folder / (names[n] if names is not None else f"IM_{n + 1:05d}.dcm")
            ds.save_as(p, enforce_file_format=True)
            written.append(p)
    return written

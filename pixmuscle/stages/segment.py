"""``segment`` stage: MRI + DTI (+ IMCT/IMAT masks) -> ``segmentation.h5``.

Reads the inputs named in the ``segment`` config section (:class:`~pixmuscle.segmentation.
config.SegmentConfig`): NIfTI files, or DICOM folders converted once into ``<out folder>/dicom/``
(:mod:`pixmuscle.io.dicom`); removes the MRI's bias field when ``bias_correction: n4``
(:mod:`pixmuscle.imaging.bias`; the field is written as ``<stem>_bias_field.nii.gz`` and
``<stem>_qc/bias_field.png``); fits the tensor of a scanner DWI series when ``segment.dwi`` is given
(:mod:`pixmuscle.stages.dwi_qc`: FA/MD/V1 maps in the QC folder), maps the DTI onto the MRI grid
through the affines (tensors are interpolated, never eigenvectors), runs :func:`pixmuscle.segmentation.volume.segment_volume`
and writes

* ``<out>`` — HDF5, schema ``pixmuscle.segmentation`` v1 (docs/architecture.md);
* ``<stem>_labels.nii.gz``, ``<stem>_muscles.nii.gz`` (muscle ids), ``<stem>_fibers.nii.gz``
  — for ITK-SNAP / 3D Slicer;
* ``<stem>.seg.nrrd`` — one 3D Slicer segmentation with a named segment per muscle and tissue, to
  correct by hand and give back as ``build_model.labels`` (written when pynrrd is installed);
* ``<stem>_qc/slice_XXX.png`` — MRI with tissue and muscle contours, one per slice.
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import numpy as np

from pixmuscle.errors import InputError, OutputError
from pixmuscle.imaging.dti import (
    resample_tensor_to_grid,
    resample_vectors_to_grid,
    tensor_from_components,
)
from pixmuscle.imaging.nifti import file_affine_cm, load_volume, save_volume
from pixmuscle.imaging.resample import resample_labels
from pixmuscle.io.lineage import capture_warnings, stage_attrs
from pixmuscle.io.segmentation import write_segmentation
from pixmuscle.outdir import WRITE_ERRNOS, describe_os_error, prepare_output_dir
from pixmuscle.segmentation.config import SegmentConfig
from pixmuscle.segmentation.volume import SegmentationResult, segment_volume

__all__ = ["run_segment", "write_qc_pngs", "dti_source"]

_LOG = logging.getLogger(__name__)


def _same_grid(a_shape, a_affine, b_shape, b_affine):
    return tuple(a_shape) == tuple(b_shape) and np.allclose(a_affine, b_affine, atol=1e-6)


def _mask_on_grid(path, shape, affine, name):
    vol = load_volume(path, kind="labels", allow_empty=True)
    if _same_grid(vol.data.shape, vol.affine, shape, affine):
        return vol.data != 0
    _LOG.info("%s: resampling from %s to the MRI grid (nearest neighbour)", name, vol.data.shape)
    return resample_labels(vol.data != 0, vol.affine, shape, affine, name=f"{name} {path}")


def dti_source(cfg, qc_dir=None, *, cache_dir=None, where: str = "segment") -> tuple[np.ndarray, np.ndarray, str]:
    """The segment section's DTI on its own grid: tensors (I, J, K, 3, 3) mm²/s, affine (cm), kind.

    ``kind`` is ``"tensor"`` (a tensor image, or the fit of a scanner DWI series) or ``"v1"`` (a
    principal-eigenvector image (I, J, K, 3), which carries a direction but no tensor and no noise).

    Parameters
    ----------
    cfg : SegmentConfig
    qc_dir : path-like, optional
        Where the DWI fit's FA/MD/V1 maps go (:func:`pixmuscle.stages.dwi_qc.dwi_tensor_with_qc`);
        None: no maps.
    cache_dir : path-like, optional
        A DWI series given as a DICOM folder is converted once into ``<cache_dir>/dicom``
        (:func:`scanner_inputs`; default the working directory). The segment stage converts its
        inputs before and passes NIfTI files.
    where : str
        Names the caller in the error message.

    Raises
    ------
    InputError
        The section names no DTI (``dwi``, ``dti_tensor`` or ``dti_v1``).
    """
    if cfg.dwi is not None:
        from pixmuscle.stages.dwi_qc import dwi_tensor_with_qc

        if cfg.dwi.image.is_dir():
            cfg = scanner_inputs(cfg, Path(cache_dir or ".") / "dicom")
        fit = dwi_tensor_with_qc(cfg.dwi, qc_dir)
        return fit.tensor, fit.affine, "tensor"
    if cfg.dti_tensor is not None:
        vol = load_volume(cfg.dti_tensor, kind="tensor", components=cfg.dti_components,
                          tensor_order=cfg.tensor_order)
        return tensor_from_components(vol.data, cfg.tensor_order), vol.affine, "tensor"
    if cfg.dti_v1 is not None:
        vol = load_volume(cfg.dti_v1, kind="vectors", components=cfg.dti_components)
        return vol.data, vol.affine, "v1"
    raise InputError(f"{where}: no DTI input; set segment.dwi (a scanner DWI series), "
                     "segment.dti_tensor or segment.dti_v1")


def _dti_on_grid(cfg, shape, affine, qc_dir=None):
    """The DTI of ``cfg`` (:func:`dti_source`) on the MRI grid: (tensors (I, J, K, 3, 3), covered
    (I, J, K) bool); tensors are interpolated, never eigenvectors; a V1 image gives rank-one tensors
    v vᵀ (trace 1 where there is data)."""
    data, d_affine, kind = dti_source(cfg, qc_dir)
    if kind == "v1":
        v, has = resample_vectors_to_grid(data, d_affine, shape, affine)
        return v[..., :, None] * v[..., None, :], has
    return resample_tensor_to_grid(data, d_affine, shape, affine)


def run_segment(cfg, out_path, progress=None, *, synthetic=False):
    """Run the segment stage.

    Parameters
    ----------
    cfg : SegmentConfig
        Needs ``mri``, ``dti_tensor`` or ``dti_v1``, and ``seeds``; ``imct_mask`` and
        ``imat_mask`` are optional.
    out_path : path-like
        The HDF5 file to write (the NIfTI and PNG outputs go next to it).
    progress : object with ``advance(n=1, **fields)`` and ``log(msg)``, optional
        If None, a :func:`pixmuscle.progress.progress` bar is used.
    synthetic : bool
        The inputs are synthetic phantoms (also detected from a phantom's ``*_truth.json``).

    Returns
    -------
    SegmentationResult
    """
    if not isinstance(cfg, SegmentConfig):
        raise InputError(f"run_segment: expected a SegmentConfig, got {type(cfg).__name__}")
    if cfg.mri is None:
        raise InputError("segment.mri: required key is missing (anatomical MRI, NIfTI)")
    out_path = Path(out_path)
    prepare_output_dir(out_path.parent, "output folder")  # before the work, not after it
    stem = out_path.name[:-len(out_path.suffix)] if out_path.suffix else out_path.name
    inputs = _input_paths(cfg)                             # as the config names them (a DICOM folder too)
    with capture_warnings() as warnings:
        mri, res, masks, bias_field = _segment(scanner_inputs(cfg, out_path.parent / "dicom"),
                                               out_path.with_name(f"{stem}_qc"), progress)
    affine = mri.affine
    if bias_field is not None:
        save_volume(out_path.with_name(f"{stem}_bias_field.nii.gz"), bias_field, affine, kind="image")
        write_bias_png(out_path.with_name(f"{stem}_qc") / "bias_field.png", bias_field)
    # the side outputs first, the stage file last: it is what marks the stage as done (a full disk
    # half-way must not leave a complete-looking segmentation.h5 without its images)
    save_volume(out_path.with_name(f"{stem}_labels.nii.gz"), res.labels, affine, kind="labels")
    save_volume(out_path.with_name(f"{stem}_muscles.nii.gz"), res.muscle_id, affine,
                kind="labels")
    save_volume(out_path.with_name(f"{stem}_fibers.nii.gz"), res.fiber, affine, kind="vectors")
    write_slicer_segmentation(out_path.with_name(f"{stem}.seg.nrrd"), res, affine)
    if cfg.qc_png:
        write_qc_pngs(out_path.with_name(f"{stem}_qc"), mri.data, res)
    write_segmentation(out_path, res, affine, config=cfg, inputs=inputs,
                       attrs=stage_attrs("segment", inputs, warnings, synthetic=synthetic), masks=masks)
    return res


def _input_paths(cfg) -> list[Path]:
    """The input files and folders the config names, for the stage's provenance."""
    return [p for p in (cfg.mri, *cfg.dti_files(), cfg.imct_mask, cfg.imat_mask, cfg.aponeurosis_mask)
            if p is not None]


def scanner_inputs(cfg, cache_dir) -> SegmentConfig:
    """``cfg`` with its DICOM folders (``mri``, ``dwi.image``) replaced by their NIfTI conversions.

    Conversions are cached in ``cache_dir`` by the content of the series' files
    (:func:`pixmuscle.io.dicom.dicom_to_nifti`); a config of NIfTI files is returned as it is.
    """
    changes = {}
    if cfg.mri is not None and cfg.mri.is_dir():
        from pixmuscle.io.dicom import dicom_to_nifti

        changes.update(mri=dicom_to_nifti(cfg.mri, cache_dir, series=cfg.series, key="segment.series").image,
                       series=None)
    if cfg.dwi is not None and cfg.dwi.image.is_dir():
        from pixmuscle.io.dicom import dicom_to_nifti

        conv = dicom_to_nifti(cfg.dwi.image, cache_dir, series=cfg.dwi.series, key="segment.dwi.series",
                              diffusion=True)
        changes["dwi"] = dataclasses.replace(cfg.dwi, image=conv.image, bvals=conv.bvals, bvecs=conv.bvecs,
                                             series=None, bvecs_convention="fsl")
    return dataclasses.replace(cfg, **changes) if changes else cfg


def seeds_in_cm(cfg) -> dict:
    """The seeds of ``cfg`` in world cm: mm divided by 10, voxel indices of the MRI file's own
    grid through the file's affine (not the reoriented grid the segmentation works on)."""
    if cfg.seed_units == "cm":
        return cfg.seeds
    if cfg.seed_units == "mm":
        return {k: (np.asarray(v, float) * 0.1).tolist() for k, v in cfg.seeds.items()}
    a = file_affine_cm(cfg.mri)
    return {k: (np.asarray(v, float).reshape(-1, 3) @ a[:3, :3].T + a[:3, 3]).tolist() for k, v in cfg.seeds.items()}


def _segment(cfg, qc_dir, progress):
    """Read the inputs (NIfTI) and segment: (MRI volume as segmented, SegmentationResult, masks to keep:
    name → (I, J, K) bool on the MRI grid, the aponeurosis when given; the bias field or None)."""
    cfg = dataclasses.replace(cfg, seeds=seeds_in_cm(cfg), seed_units="cm")
    mri = load_volume(cfg.mri, kind="image")
    shape, affine = mri.data.shape, mri.affine
    bias_field = None
    if cfg.bias_correction == "n4":
        from pixmuscle.imaging.bias import n4_correct

        corrected, bias_field = n4_correct(mri.data, mri.spacing)
        _LOG.info("bias field (N4): %.2f to %.2f over the image", bias_field.min(), bias_field.max())
        mri = dataclasses.replace(mri, data=corrected)
    d_grid, covered = _dti_on_grid(cfg, shape, affine, qc_dir)
    imct = None if cfg.imct_mask is None else _mask_on_grid(cfg.imct_mask, shape, affine,
                                                           "segment.imct_mask")
    imat = None if cfg.imat_mask is None else _mask_on_grid(cfg.imat_mask, shape, affine,
                                                           "segment.imat_mask")
    masks = {}
    if cfg.aponeurosis_mask is not None:  # connective tissue, but not IMCT (paper Table 3)
        masks["aponeurosis"] = _mask_on_grid(cfg.aponeurosis_mask, shape, affine, "segment.aponeurosis_mask")
        imct = masks["aponeurosis"] if imct is None else imct | masks["aponeurosis"]
    if progress is None:
        from pixmuscle.progress import progress as bar

        with bar(5, "segment") as p:
            res = segment_volume(mri.data, affine, d_grid, covered, imct, imat, cfg, progress=p)
    else:
        res = segment_volume(mri.data, affine, d_grid, covered, imct, imat, cfg,
                             progress=progress)
    for finding in res.findings:  # segmentation QC (segmentation/qc.py): into the log, the file, the report
        _LOG.warning("segmentation QC: %s", finding.message)
    if "aponeurosis" in masks:
        masks["aponeurosis"] &= res.labels == 2  # only where the labels have connective tissue
    return mri, res, masks, bias_field


def write_slicer_segmentation(path, res: SegmentationResult, affine) -> Path | None:
    """The segmentation as one named label map for 3D Slicer: muscle ``m`` is value ``m`` named by its
    muscle, then connective_tissue, fat and bone (and ``muscle`` for muscle voxels of no muscle).
    Names are those :mod:`pixmuscle.model.label_names` maps back. None when pynrrd is missing."""
    try:
        import nrrd  # noqa: F401
    except ImportError:
        _LOG.info("pynrrd is not installed: no %s (pip install 'pixmuscle[scanner]')", Path(path).name)
        return None
    from pixmuscle.io.labelmap import write_seg_nrrd

    m = len(res.muscle_names)
    combined = np.where(res.labels == 1, res.muscle_id, 0).astype(np.int32)
    names = {i + 1: n for i, n in enumerate(res.muscle_names)}
    for k, (code, tissue) in enumerate(((2, "connective_tissue"), (3, "fat"), (4, "bone"))):
        combined[res.labels == code] = m + 1 + k
        names[m + 1 + k] = tissue
    stray = (res.labels == 1) & (res.muscle_id == 0)
    if stray.any():
        combined[stray] = m + 4
        names[m + 4] = "muscle"
    present = set(np.unique(combined).tolist())
    return write_seg_nrrd(path, combined, affine, {v: n for v, n in names.items() if v in present})


def write_bias_png(path, field) -> Path:
    """The bias field's middle slice as a PNG (colour bar: multiplicative factor)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    k = field.shape[2] // 2
    fig = Figure(figsize=(5, 4.2), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    im = ax.imshow(field[:, :, k].T, origin="lower", cmap="coolwarm", interpolation="nearest")
    fig.colorbar(im, ax=ax, label="bias field (multiplicative)")
    ax.set_title(f"N4 bias field, slice {k}")
    ax.set_axis_off()
    return _save_png(fig, path)


def _save_png(fig, path: Path) -> Path:
    """``fig`` to ``path``; a full disk leaves no half PNG and raises one line naming it."""
    try:
        fig.savefig(path)
    except OSError as exc:
        path.unlink(missing_ok=True)
        if exc.errno in WRITE_ERRNOS:
            raise OutputError(describe_os_error(exc, path)) from None
        raise
    return path


def write_qc_pngs(folder, mri, res: SegmentationResult):
    """One PNG per slice: the MRI with tissue contours (colours) and muscle boundaries (white).

    Parameters
    ----------
    folder : path-like
        Created if needed; files ``slice_000.png`` ...
    mri : ndarray, shape ``(I, J, K)``
    res : SegmentationResult

    Returns
    -------
    list of Path
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    lo, hi = np.percentile(mri, [0.5, 99.5])
    colors = {1: "tab:red", 2: "tab:green", 3: "gold", 4: "tab:blue"}
    paths = []
    for k in range(mri.shape[2]):
        fig = Figure(figsize=(5, 5 * mri.shape[1] / mri.shape[0]), dpi=100)
        FigureCanvasAgg(fig)
        ax = fig.add_axes((0, 0, 1, 1))
        ax.imshow(mri[:, :, k].T, origin="lower", cmap="gray", vmin=lo, vmax=hi,
                  interpolation="nearest")
        for code, color in colors.items():
            m = (res.labels[:, :, k] == code).T.astype(float)
            if 0 < m.sum() < m.size:
                ax.contour(m, levels=[0.5], colors=color, linewidths=0.6)
        mid = res.muscle_id[:, :, k].T
        for m_id in np.unique(mid[mid > 0]):
            ax.contour((mid == m_id).astype(float), levels=[0.5], colors="white",
                       linewidths=0.4)
        ax.set_axis_off()
        ax.text(2, 2, f"slice {k}", color="yellow", fontsize=8)
        paths.append(_save_png(fig, folder / f"slice_{k:03d}.png"))
    return paths

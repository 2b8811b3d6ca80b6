"""DWI part of the ``segment`` stage: fit the tensor of a scanner series and write its QC maps.

Files written into the segmentation's QC folder (``<stem>_qc/``):

* ``dwi_fa.nii.gz``, ``dwi_md.nii.gz`` (mm²/s), ``dwi_v1.nii.gz`` (world axes) on the DWI grid;
* ``dwi_maps.png``: FA, MD and the direction-encoded colour map (|V1| · FA as RGB) of the
  middle slice;
* ``dwi_summary.json``: volumes, b-values, b-vector convention, FA and MD percentiles in the
  fitted voxels (the report shows it).
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path

import numpy as np

from pixmuscle.imaging.dwi import DWITensorFit, load_dwi_tensor
from pixmuscle.imaging.nifti import save_volume

_LOG = logging.getLogger(__name__)

__all__ = ["dwi_tensor_with_qc", "write_dwi_qc"]


def dwi_tensor_with_qc(dwi_cfg, qc_dir: str | Path | None) -> DWITensorFit:
    """Fit the tensors of ``segment.dwi`` (:class:`~pixmuscle.segmentation.config.DWIConfig`); write QC maps."""
    fit = load_dwi_tensor(dwi_cfg.image, dwi_cfg.bvals, dwi_cfg.bvecs, convention=dwi_cfg.bvecs_convention,
                          b0_threshold=dwi_cfg.b0_threshold)
    sel = fit.fa > 0
    _LOG.info("segment.dwi: tensor fitted in %d voxels (dipy TensorModel, WLS), median FA %.3f, median MD %.3g mm²/s",
              int(sel.sum()), float(np.median(fit.fa[sel])) if sel.any() else 0.0,
              float(np.median(fit.md[sel])) if sel.any() else 0.0)
    if qc_dir is not None:
        write_dwi_qc(qc_dir, fit, dwi_cfg)
    return fit


def write_dwi_qc(folder, fit: DWITensorFit, dwi_cfg=None) -> dict:
    """Write the FA/MD/V1 maps, the PNG and the summary JSON of a tensor fit; returns {name: Path}."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    out = {
        "fa": save_volume(folder / "dwi_fa.nii.gz", fit.fa, fit.affine),
        "md": save_volume(folder / "dwi_md.nii.gz", fit.md, fit.affine),
        "v1": save_volume(folder / "dwi_v1.nii.gz", fit.v1, fit.affine, kind="vectors"),
    }
    k = fit.fa.shape[2] // 2
    fig = Figure(figsize=(10, 3.6), dpi=100)
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, 3)
    im = axes[0].imshow(fit.fa[:, :, k].T, origin="lower", cmap="gray", vmin=0, vmax=max(0.5, float(fit.fa.max())))
    fig.colorbar(im, ax=axes[0], shrink=0.8)
    axes[0].set_title("FA")
    im = axes[1].imshow(1e3 * fit.md[:, :, k].T, origin="lower", cmap="viridis")
    fig.colorbar(im, ax=axes[1], shrink=0.8)
    axes[1].set_title("MD (10⁻³ mm²/s)")
    dec = np.clip(np.abs(fit.v1[:, :, k]) * np.clip(fit.fa[:, :, k, None] / max(float(fit.fa.max()), 1e-9), 0, 1), 0, 1)
    axes[2].imshow(np.transpose(dec, (1, 0, 2)), origin="lower")
    axes[2].set_title("V1 colour (R = x, G = y, B = z) · FA")
    for ax in axes:
        ax.set_axis_off()
    fig.suptitle(f"diffusion tensor fit, slice {k} of the DWI grid")
    fig.tight_layout()
    out["png"] = folder / "dwi_maps.png"
    fig.savefig(out["png"])
    sel = fit.fa > 0
    pct = [5, 50, 95]
    summary = {
        "method": "dipy TensorModel (WLS)",
        "fitted_voxels": int(sel.sum()),
        "grid_shape": list(fit.fa.shape),
        "fa_percentiles_5_50_95": np.percentile(fit.fa[sel], pct).tolist() if sel.any() else [],
        "md_percentiles_5_50_95_mm2_per_s": np.percentile(fit.md[sel], pct).tolist() if sel.any() else [],
    }
    if dwi_cfg is not None:
        summary.update(image=str(dwi_cfg.image), bvals=str(dwi_cfg.bvals), bvecs=str(dwi_cfg.bvecs),
                       bvecs_convention=dwi_cfg.bvecs_convention, b0_threshold=dwi_cfg.b0_threshold)
    path = folder / "dwi_summary.json"
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    tmp.write_text(json.dumps(summary, indent=2) + "\n")
    os.replace(tmp, path)
    out["summary"] = path
    return out

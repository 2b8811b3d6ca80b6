"""``perturb`` stage: one noisy realisation of the scan → the realisation's ``segmentation.h5``.

Reads the noise-free ``segmentation.h5`` of the segment stage and the DTI the segment section names;
writes a ``segmentation.h5`` (schema ``pixmuscle.segmentation`` v1, so the build-model stage reads it
as it is) with

* the labels, muscle ids and node-set masks moved by a smooth random in-plane displacement of at most
  ``uncertainty.boundary_voxels`` voxels (:mod:`pixmuscle.segmentation.perturb`);
* the fibre directions re-estimated as the principal eigenvector of a noisy tensor: the DTI's tensors
  on their own grid, Rician noise at ``uncertainty.dti_snr`` on their simulated signals, fitted again
  (:mod:`pixmuscle.imaging.dti_noise`), mapped onto the MRI grid like the segment stage does
  (tensors interpolated, never eigenvectors) and thresholded by the same ``segment.fiber_min_fa`` /
  ``fiber_min_trace``. A muscle voxel without usable fibre data takes the fibre of the nearest voxel
  with data.

The muscles are not re-segmented from the noisy DTI: the segmentation's own uncertainty is the moved
boundary. The realisation is drawn from ``(uncertainty.seed, realisation)`` alone, the DTI noise and
the boundary field from independent streams, so changing one leaves the other as it was.
``perturbation.json`` beside the file gives what the realisation changed (voxels relabelled, fibre
angle to the noise-free fibres).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from scipy import ndimage as ndi

from pixmuscle.errors import InputError
from pixmuscle.imaging.dti import resample_tensor_to_grid, resample_vectors_to_grid
from pixmuscle.imaging.dti_noise import acquisition, fibre_angle_deg, noisy_tensors
from pixmuscle.io.lineage import capture_warnings, stage_attrs
from pixmuscle.io.segmentation import read_segmentation, write_segmentation
from pixmuscle.segmentation.assemble import MUSCLE, fiber_data
from pixmuscle.segmentation.perturb import boundary_displacement, warp_labels
from pixmuscle.segmentation.volume import SegmentationResult
from pixmuscle.stages.segment import dti_source

__all__ = ["run_perturb", "realisation_rngs", "nearest_fill", "dti_source"]


def realisation_rngs(seed: int, realisation: int) -> tuple[np.random.Generator, np.random.Generator]:
    """Independent generators (DTI noise, boundary field) of realisation ``realisation``."""
    dti, boundary = np.random.SeedSequence([int(seed), int(realisation)]).spawn(2)
    return np.random.default_rng(dti), np.random.default_rng(boundary)


def _fibres_on_grid(seg_cfg, unc, rng, shape, affine, cache_dir) -> tuple[np.ndarray, np.ndarray]:
    """(valid (I, J, K) bool, unit fibres (I, J, K, 3)) of a noisy (or, with ``dti_snr`` null, the
    noise-free) DTI on the MRI grid."""
    data, d_affine, kind = dti_source(seg_cfg, cache_dir=cache_dir, where="uncertainty")
    if kind == "v1":
        if unc.dti_snr is not None:
            raise InputError("uncertainty.dti_snr: segment.dti_v1 gives fibre directions without their tensors, so "
                             "there is no signal to add noise to; give segment.dti_tensor or segment.dwi, or set "
                             "uncertainty.dti_snr: null")
        v, has = resample_vectors_to_grid(data, d_affine, shape, affine)
        d_grid, covered = v[..., :, None] * v[..., None, :], has
    else:
        if unc.dti_snr is not None:
            bvals, g = acquisition(unc.dti_bvalue, unc.dti_directions, unc.dti_b0_volumes)
            data = noisy_tensors(data, unc.dti_snr, rng, bvals=bvals, gradients=g)
        d_grid, covered = resample_tensor_to_grid(data, d_affine, shape, affine)
    valid, v, _ = fiber_data(d_grid, covered, min_fa=seg_cfg.fiber_min_fa, min_trace=seg_cfg.fiber_min_trace)
    return valid, v


def nearest_fill(v: np.ndarray, valid: np.ndarray, where: np.ndarray, spacing) -> np.ndarray:
    """``v`` with the voxels of ``where`` that are not ``valid`` given the value of the nearest valid voxel."""
    need = where & ~valid
    if not need.any() or not valid.any():
        return v
    _, idx = ndi.distance_transform_edt(~valid, sampling=spacing, return_indices=True)
    out = v.copy()
    out[need] = v[tuple(i[need] for i in idx)]
    return out


def run_perturb(segment_cfg, uncertainty_cfg, realisation: int, segmentation_path, out_path, *,
                synthetic: bool = False) -> Path:
    """Write one realisation's ``segmentation.h5`` (see the module notes).

    Parameters
    ----------
    segment_cfg : pixmuscle.segmentation.config.SegmentConfig
        The case's segment section (its DTI and fibre thresholds).
    uncertainty_cfg : pixmuscle.uncertainty.UncertaintyConfig
    realisation : int
        1, 2, ...: which realisation.
    segmentation_path : path-like
        The noise-free ``segmentation.h5``.
    out_path : path-like
        The realisation's ``segmentation.h5``; ``perturbation.json`` is written beside it.
    synthetic : bool
        The inputs are synthetic phantoms.

    Returns
    -------
    Path
    """
    seg_path, out_path = Path(segmentation_path), Path(out_path)
    unc = uncertainty_cfg
    inputs = [seg_path, *segment_cfg.dti_files()]
    with capture_warnings() as warnings:
        seg = read_segmentation(seg_path)
        labels, mid, fiber0 = seg["labels"], seg["muscle_id"], seg["fiber"]
        if mid is None or fiber0 is None:
            raise InputError(f"{seg_path}: no /muscle_id or /fiber: not written by the segment stage")
        affine = seg["affine"]
        spacing = np.linalg.norm(affine[:3, :3], axis=0)
        rng_dti, rng_boundary = realisation_rngs(unc.seed, realisation)
        masks = dict(seg["masks"])
        if unc.boundary_voxels > 0:
            u = boundary_displacement(labels.shape, affine, unc.boundary_voxels, unc.boundary_length_cm, rng_boundary)
            names = list(masks)
            moved = warp_labels([labels, mid, *(masks[n] for n in names)], u)
            new_labels, new_mid = moved[0], moved[1]
            masks = {n: m & (new_labels == 2) for n, m in zip(names, moved[2:], strict=True)}
            shift = float(np.max(np.linalg.norm(u, axis=-1)))
        else:
            new_labels, new_mid, shift = labels, mid, 0.0
        new_mid = np.where(new_labels == MUSCLE, new_mid, 0).astype(np.int16)
        valid, v = _fibres_on_grid(segment_cfg, unc, rng_dti, labels.shape, affine, out_path.parent)
        muscle = new_labels == MUSCLE
        v = nearest_fill(v, valid, muscle, spacing)
        fiber = np.where(muscle[..., None], v, 0.0).astype(np.float32)
        both = muscle & (labels == MUSCLE)
        angle = fibre_angle_deg(fiber[both], fiber0[both])
        angle = angle[np.isfinite(angle)]
        stats = {
            "realisation": int(realisation), "seed": int(unc.seed),
            "voxels_relabelled": int(np.count_nonzero(new_labels != labels)),
            "muscle_voxels_relabelled": int(np.count_nonzero((new_mid != mid) & ((labels == MUSCLE) | muscle))),
            "muscle_voxels": int(muscle.sum()), "muscle_voxels_noise_free": int((labels == MUSCLE).sum()),
            "largest_boundary_shift_voxels": shift,
            "fibre_angle_median_deg": float(np.median(angle)) if angle.size else None,
            "fibre_angle_rms_deg": float(np.sqrt(np.mean(angle**2))) if angle.size else None,
            "muscle_voxels_without_fibre_data": int(np.count_nonzero(muscle & ~valid)),
        }
    res = SegmentationResult(labels=new_labels.astype(np.int16), muscle_id=new_mid, muscle_names=seg["muscle_names"],
                             fiber=fiber, qc={f"perturbation_{k}": val for k, val in stats.items() if val is not None})
    out_path.parent.mkdir(parents=True, exist_ok=True)
    (out_path.parent / "perturbation.json").write_text(json.dumps(stats, indent=2))
    cfg = {"segment": segment_cfg, "uncertainty": unc, "realisation": int(realisation)}
    write_segmentation(out_path, res, affine, config=cfg, inputs=inputs,
                       attrs=stage_attrs("perturb", inputs, warnings, synthetic=synthetic), masks=masks)
    return out_path

"""Label assembly (paper §4.2): boundaries, bones, masks and fibre data -> tissue labels.

Tissue codes (docs/architecture.md): 0 background, 1 muscle, 2 connective tissue (IMCT),
3 fat (subcutaneous and IMAT), 4 bone.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi

from pixmuscle.errors import InputError
from pixmuscle.imaging.dti import canonical_sign, principal_eigenvector, tensor_from_components

__all__ = [
    "BACKGROUND", "MUSCLE", "CONNECTIVE", "FAT", "BONE",
    "fill_holes_per_slice", "largest_component_per_slice", "fiber_data", "assemble_labels",
]

BACKGROUND, MUSCLE, CONNECTIVE, FAT, BONE = 0, 1, 2, 3, 4


def fill_holes_per_slice(mask, axis=2):
    """Fill the holes of a binary volume slice by slice (2-D holes in planes normal to ``axis``).

    Parameters
    ----------
    mask : ndarray of bool, 3-D (or 2-D: filled as one image)
    axis : int
        Slice axis.

    Returns
    -------
    ndarray of bool, same shape
    """
    mask = np.asarray(mask, bool)
    if mask.ndim == 2:
        return ndi.binary_fill_holes(mask)
    out = np.empty_like(mask)
    for k in range(mask.shape[axis]):
        sl = [slice(None)] * mask.ndim
        sl[axis] = k
        out[tuple(sl)] = ndi.binary_fill_holes(mask[tuple(sl)])
    return out


def largest_component_per_slice(mask, axis=2):
    """Keep, in every slice, the largest 4-connected component of a binary volume."""
    mask = np.asarray(mask, bool)
    out = np.zeros_like(mask)
    for k in range(mask.shape[axis]):
        sl = [slice(None)] * mask.ndim
        sl[axis] = k
        lab, n = ndi.label(mask[tuple(sl)])
        if n:
            sizes = np.bincount(lab.ravel())[1:]
            out[tuple(sl)] = lab == 1 + int(np.argmax(sizes))
    return out


def fiber_data(tensor, covered=None, *, min_fa=0.0, min_trace=0.5, order="fsl"):
    """Voxels with usable fibre data and their fibre directions.

    A voxel has fibre data where it is covered by the DTI, its tensor is non-zero, its trace is
    at least ``min_trace`` times the median trace of all non-zero covered tensors (this drops
    voxels that got only a small share of interpolation weight from tissue with signal) and its
    fractional anisotropy is at least ``min_fa``.

    Parameters
    ----------
    tensor : ndarray, shape ``(..., 3, 3)`` or ``(..., 6)`` (components in ``order``)
        Diffusion tensors on the label grid (mm^2/s; only ratios matter).
    covered : ndarray of bool, shape ``tensor.shape[:-2]`` (or ``[:-1]``), optional
        Inside the DTI field of view.
    min_fa : float
        Minimum fractional anisotropy, 0..1.
    min_trace : float
        Minimum trace as a fraction of the median non-zero trace.
    order : str
        Component order when ``tensor`` has 6 components.

    Returns
    -------
    valid : ndarray of bool, spatial shape
    v : ndarray of float64, spatial shape + ``(3,)``
        Unit principal eigenvector, canonical sign (:func:`pixmuscle.imaging.dti.canonical_sign`),
        0 where not ``valid``.
    fa : ndarray of float64, spatial shape
    """
    t = np.asarray(tensor, dtype=float)
    if t.shape[-1] == 6:
        t = tensor_from_components(t, order)
    if t.shape[-2:] != (3, 3):
        raise InputError(f"DTI tensor on the label grid: expected (..., 3, 3) or (..., 6), got "
                         f"shape {t.shape}")
    spatial = t.shape[:-2]
    covered = np.ones(spatial, bool) if covered is None else np.asarray(covered, bool)
    if covered.shape != spatial:
        raise InputError(f"DTI coverage mask: shape {covered.shape}, expected {spatial}")
    v, _, fa = principal_eigenvector(t)
    trace = np.trace(t, axis1=-2, axis2=-1)
    nonzero = covered & np.any(t != 0, axis=(-2, -1)) & (trace > 0)
    if not nonzero.any():
        raise InputError("DTI: no non-zero tensor on the label grid (does the DTI overlap the "
                         "MRI? check both affines)")
    ref = np.median(trace[nonzero])
    valid = nonzero & (trace >= min_trace * ref) & (fa >= min_fa)
    v = np.where(valid[..., None], canonical_sign(v), 0.0)
    return valid, v, fa


def assemble_labels(leg, bone, fiber_valid, muscle_id, imct_mask=None, imat_mask=None,
                    fibers=None):
    """Tissue labels from the segmented pieces (paper §4.2, Fig. 8).

    interior = leg (holes filled) minus bone; IMCT voxels of the interior -> 2, IMAT -> 3;
    remaining interior voxels with fibre data -> muscle (1) with their ``muscle_id``; the rest
    of the interior (subcutaneous fat) -> 3; bone -> 4; outside the leg -> 0.

    Parameters
    ----------
    leg : ndarray of bool, shape ``S``
        Inside of the outer boundary (holes filled).
    bone : ndarray of bool, shape ``S``
        Bones, filled (cortex and marrow).
    fiber_valid : ndarray of bool, shape ``S``
        Voxels with fibre (DTI) data.
    muscle_id : ndarray of int, shape ``S``
        Muscle of each voxel (1..M) at least where muscle voxels will be; 0 elsewhere.
    imct_mask, imat_mask : ndarray of bool, shape ``S``, optional
        Connective tissue and intramuscular fat from their specialised sequences.
    fibers : ndarray, shape ``S + (3,)``, optional
        Fibre directions (any sign).

    Returns
    -------
    labels : ndarray of int16, shape ``S``
    muscle_id : ndarray of int16, shape ``S``
        0 where ``labels != 1``.
    fiber : ndarray of float32, shape ``S + (3,)``
        Unit fibre directions with canonical sign on muscle voxels, 0 elsewhere.
    """
    leg = np.asarray(leg, bool)
    shape = leg.shape
    masks = {"bone": bone, "fiber_valid": fiber_valid, "imct_mask": imct_mask,
             "imat_mask": imat_mask}
    for name, m in masks.items():
        if m is not None and np.shape(m) != shape:
            raise InputError(f"{name}: shape {np.shape(m)}, expected the label grid {shape}")
    bone = np.asarray(bone, bool) & leg
    interior = leg & ~bone
    labels = np.zeros(shape, dtype=np.int16)
    labels[bone] = BONE
    labels[interior] = FAT
    muscle = interior & np.asarray(fiber_valid, bool)
    if imct_mask is not None:
        muscle &= ~np.asarray(imct_mask, bool)
    if imat_mask is not None:
        muscle &= ~np.asarray(imat_mask, bool)
    labels[muscle] = MUSCLE
    if imct_mask is not None:
        labels[interior & np.asarray(imct_mask, bool)] = CONNECTIVE
    mid = np.where(labels == MUSCLE, np.asarray(muscle_id), 0).astype(np.int16)
    if (mid[labels == MUSCLE] <= 0).any():
        raise InputError(f"{int((mid[labels == MUSCLE] <= 0).sum())} muscle voxels have no "
                         "muscle id")
    fiber = np.zeros(shape + (3,), dtype=np.float32)
    if fibers is not None:
        f = np.asarray(fibers, dtype=float)
        if f.shape != shape + (3,):
            raise InputError(f"fibers: shape {f.shape}, expected {shape + (3,)}")
        n = np.linalg.norm(f, axis=-1, keepdims=True)
        f = canonical_sign(np.divide(f, n, out=np.zeros_like(f), where=n > 0))
        fiber[labels == MUSCLE] = f[labels == MUSCLE]
    return labels, mid, fiber

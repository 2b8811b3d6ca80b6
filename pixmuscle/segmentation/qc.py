"""Quality checks of a finished segmentation: findings that say a step probably went wrong.

The level sets can converge and still give a wrong answer: on a coarse scan the thin dark cortex
of a bone may not separate from the muscle around it, and the bone is lost in some slices; or the
multiphase regions may miss a muscle, which then gets its voxels only from the nearest-seed
fall-back of :func:`pixmuscle.segmentation.multiphase.regions_to_muscles`. Anatomy changes slowly
along a limb (a few per cent of cross-section per centimetre at mid-calf), so such failures show
up as jumps between neighbouring slices. The checks:

1. **Outline** (every voxel inside the limb) and **each bone**: the area must not vanish in a
   slice next to one where the structure is present, nor change by more than ``max_change``
   (relative to the larger of the two) between neighbouring slices — changes of a few pixels, or
   of less than half a pixel of boundary all round, excepted. Bones are told apart by
   their footprint: the connected components (in-plane) of the union of the bone voxels over all
   slices, grown by one pixel; a bone's area in a slice is its bone voxels inside its footprint.
2. **Muscles**: the share of each muscle's voxels that the nearest-seed fall-back assigned
   (rules 2 and 3 of ``regions_to_muscles``) must stay at most ``max_fallback``.

Pure: arrays in, a list of :class:`Finding` out; the segment stage logs them as warnings, so they
reach ``segmentation.h5`` (root attribute ``warnings``) and the report.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage as ndi

__all__ = ["Finding", "bone_areas", "bone_footprints", "fallback_findings", "segmentation_findings", "slice_jumps"]

#: largest relative change of a structure's area between neighbouring slices
MAX_CHANGE = 0.30
#: largest share of a muscle that the nearest-seed fall-back may assign
MAX_FALLBACK = 0.50


@dataclass(frozen=True)
class Finding:
    """One quality problem of a segmentation.

    Attributes
    ----------
    check : str
        ``"outline"``, ``"bone"`` or ``"fallback"``.
    subject : str
        What it concerns: ``"outline"``, ``"bone 1"`` ..., or a muscle name.
    slices : tuple of int
        Slices (index along axis 2) where it was seen; empty for whole-muscle findings.
    message : str
        One line for the log and the report.
    """

    check: str
    subject: str
    slices: tuple
    message: str


def slice_jumps(area, *, max_change: float = MAX_CHANGE, min_change: float = 0.0, ring: float = 0.5):
    """Neighbouring slices between which a structure vanishes or its area jumps.

    Parameters
    ----------
    area : (K,) array_like of float
        Area of the structure in each slice, in pixels.
    max_change : float
        Largest allowed ``|a[k+1] − a[k]| / max(a[k], a[k+1])`` (0..1).
    min_change : float
        Changes of at most this many pixels are never flagged: a few pixels of a small bone are
        noise, not a failure. A structure present on one side and absent on the other is flagged
        when the present area exceeds ``min_change``.
    ring : float
        Nor are changes up to a boundary shift of ``ring`` pixels all round: ``ring`` times the
        perimeter of a disk of the larger area, ``2 sqrt(π a)`` pixels (on a small bone one pixel
        of boundary is a large share of the area).

    Returns
    -------
    vanished : (n,) int64
        ``k`` for each pair (k, k+1) where exactly one of the two slices has none of it.
    jumped : (m,) int64
        ``k`` for each pair (k, k+1), both present, whose relative change exceeds ``max_change``.
    change : (K-1,) float64
        Relative change of every pair (NaN where both are empty).
    """
    a = np.asarray(area, dtype=float)
    lo, hi = a[:-1], a[1:]
    big = np.maximum(lo, hi)
    diff = np.abs(hi - lo)
    with np.errstate(invalid="ignore", divide="ignore"):
        change = np.where(big > 0, diff / big, np.nan)
    one_empty = (np.minimum(lo, hi) == 0) & (big > 0)
    vanished = np.flatnonzero(one_empty & (diff > min_change))
    tolerance = np.maximum(min_change, ring * 2.0 * np.sqrt(np.pi * big))
    jumped = np.flatnonzero(~one_empty & (big > 0) & (diff > tolerance) & (change > max_change))
    return vanished, jumped, change


def bone_footprints(bone):
    """In-plane footprints of the bones: components of the union of the bone voxels over all
    slices, grown by one pixel.

    Parameters
    ----------
    bone : (I, J, K) array_like of bool

    Returns
    -------
    labels : (I, J) int32
        0 outside every footprint, 1..B inside bone b's.
    n : int
        Number of bones B.
    """
    bone = np.asarray(bone, bool)
    footprint = ndi.binary_dilation(bone.any(axis=2), structure=np.ones((3, 3), bool))
    lab, n = ndi.label(footprint)
    return lab, int(n)


def bone_areas(bone) -> np.ndarray:
    """Area (voxels) of each bone in each slice.

    Parameters
    ----------
    bone : (I, J, K) array_like of bool
        Bone voxels; axis 2 is the slice axis.

    Returns
    -------
    (K, B) int64
        Voxels of bone ``b`` (inside footprint ``b`` of :func:`bone_footprints`) in slice ``k``;
        B = 0 when there is no bone.
    """
    bone = np.asarray(bone, bool)
    K = bone.shape[2]
    lab, n = bone_footprints(bone)
    if n == 0:
        return np.zeros((K, 0), np.int64)
    i, j, k = np.nonzero(bone)
    counts = np.bincount(k * n + (lab[i, j] - 1), minlength=K * n)
    return counts.reshape(K, n).astype(np.int64)


def _list(ks) -> str:
    return ", ".join(str(int(k)) for k in ks[:12]) + (" ..." if len(ks) > 12 else "")


def _pairs(ks) -> str:
    return ", ".join(f"{int(k)}–{int(k) + 1}" for k in ks[:12]) + (" ..." if len(ks) > 12 else "")


def _area_findings(check, subject, area, pixel_cm2, max_change, min_change, advice):
    vanished, jumped, change = slice_jumps(area, max_change=max_change, min_change=min_change)
    out = []
    if vanished.size:
        a = np.asarray(area, float)
        empty, present = np.flatnonzero(a == 0), np.flatnonzero(a > 0)
        out.append(Finding(check, subject, tuple(int(k) for k in empty),
                           f"{subject} is missing in slice(s) {_list(empty)} but present in {_list(present)} "
                           f"({_areas(area, pixel_cm2)}); {advice}"))
    if jumped.size:
        worst = int(jumped[np.nanargmax(change[jumped])])
        out.append(Finding(check, subject, tuple(sorted({int(k) for k in jumped} | {int(k) + 1 for k in jumped})),
                           f"{subject} area changes by more than {100 * max_change:.0f} % between slices "
                           f"{_pairs(jumped)} (largest {100 * change[worst]:.0f} %, slices {worst}–{worst + 1}; "
                           f"{_areas(area, pixel_cm2)}); {advice}"))
    return out


def _areas(area, pixel_cm2) -> str:
    a = np.asarray(area, float)
    vals = ", ".join(f"{x * pixel_cm2:.3g}" for x in a[:25]) + (" ..." if a.size > 25 else "")
    return f"area per slice {vals} cm²"


def fallback_findings(fallback_voxels, muscle_voxels, names, *, max_fallback: float = MAX_FALLBACK) -> list[Finding]:
    """Muscles most of whose voxels came from the nearest-seed fall-back, not from the level sets.

    Parameters
    ----------
    fallback_voxels, muscle_voxels : (M,) array_like of int
        Per muscle: voxels assigned by the fall-back, and all its voxels (the muscle domain of
        :func:`~pixmuscle.segmentation.multiphase.regions_to_muscles`).
    names : sequence of str, length M
    max_fallback : float
        Largest allowed share (0..1).
    """
    fb, n = np.asarray(fallback_voxels, float), np.asarray(muscle_voxels, float)
    with np.errstate(invalid="ignore", divide="ignore"):
        share = np.where(n > 0, fb / n, 0.0)
    out = []
    for m in np.flatnonzero(share > max_fallback):  # loop over flagged muscles (a handful)
        out.append(Finding("fallback", str(names[m]), (),
                           f"{names[m]}: {100 * share[m]:.0f} % of its voxels ({int(fb[m])} of {int(n[m])}) were assigned "
                           "by the nearest-seed fall-back, not by the multiphase level sets (its seed's region "
                           "is shared with another muscle or holds little of it); check its seed points, "
                           "segment.multiphase (n_levelsets, lambdas, fiber_channels) and the QC overlays"))
    return out


def segmentation_findings(labels, affine=None, *, fallback_voxels=None, muscle_voxels=None, names=(),
                          max_change: float = MAX_CHANGE, min_change_cm2: float | None = None,
                          max_fallback: float = MAX_FALLBACK) -> list[Finding]:
    """All checks of the module docstring on one segmentation.

    Parameters
    ----------
    labels : (I, J, K) array_like of int
        Tissue codes (0 background, 4 bone; see docs/architecture.md); axis 2 is the slice axis.
    affine : (4, 4) array_like, optional
        Voxel → cm; used for the areas in the messages and for ``min_change_cm2``.
    fallback_voxels, muscle_voxels : (M,) array_like of int, optional
        Per-muscle counts for the fall-back check (skipped when not given).
    names : sequence of str
        Muscle names (length M).
    max_change : float
        Largest relative change of an area between neighbouring slices.
    min_change_cm2 : float, optional
        Area changes up to this (cm²) are ignored; default four pixels.
    max_fallback : float
        Largest share of a muscle assigned by the nearest-seed fall-back.

    Returns
    -------
    list of Finding
    """
    labels = np.asarray(labels)
    h = np.ones(3) if affine is None else np.linalg.norm(np.asarray(affine, float)[:3, :3], axis=0)
    pixel = float(h[0] * h[1])
    min_change = 4.0 if min_change_cm2 is None else float(min_change_cm2) / pixel
    out = []
    if labels.ndim == 3 and labels.shape[2] > 1:
        outline = (labels > 0).reshape(-1, labels.shape[2]).sum(axis=0)
        out += _area_findings("outline", "outline (limb cross-section)", outline, pixel, max_change, min_change,
                              "check the QC overlays and segment.outer")
        bones = bone_areas(labels == 4)
        lab, n = bone_footprints(labels == 4)
        centres = ndi.center_of_mass(np.ones(lab.shape), lab, np.arange(1, n + 1)) if n else []
        for b in range(bones.shape[1]):  # loop over bones (two in a lower leg)
            where = ""
            if affine is not None:
                x, y = (np.asarray(affine, float) @ [*centres[b], 0.0, 1.0])[:2]
                where = f" (at x = {x:.3g}, y = {y:.3g} cm)"
            out += _area_findings("bone", f"bone {b + 1} of {n}{where}", bones[:, b], pixel, max_change,
                                  min_change, "the bone was probably lost to fat or muscle in the slice(s) where it "
                                              "shrinks; check the QC overlays and segment.bone (on a coarse scan "
                                              "the cortex may be thinner than a pixel)")
    if fallback_voxels is not None and muscle_voxels is not None:
        out += fallback_findings(fallback_voxels, muscle_voxels, names, max_fallback=max_fallback)
    return out

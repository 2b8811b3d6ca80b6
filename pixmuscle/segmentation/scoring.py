"""Scores of a segmentation against ground-truth labels (e.g. a phantom's ``<name>_labels.nii.gz``).

Dice coefficient (Dice 1945): ``2 |A ∩ B| / (|A| + |B|)`` of two voxel sets, 1 for identical sets,
0 for disjoint ones. Pure: label arrays in, numbers out.

References
----------
Dice, L. R. (1945). Measures of the amount of ecologic association between species. *Ecology* 26(3),
297–302.
"""

from __future__ import annotations

import numpy as np

from pixmuscle.errors import InputError

__all__ = ["dice", "score_segmentation"]

#: tissue codes of docs/architecture.md
_TISSUES = {1: "muscle", 2: "connective_tissue", 3: "fat", 4: "bone"}


def dice(a, b) -> float:
    """Dice coefficient of two boolean arrays of one shape (1.0 when both are empty)."""
    a, b = np.asarray(a, bool), np.asarray(b, bool)
    if a.shape != b.shape:
        raise InputError(f"dice: shapes {a.shape} and {b.shape} differ")
    n = int(a.sum()) + int(b.sum())
    return 1.0 if n == 0 else 2.0 * int(np.count_nonzero(a & b)) / n


def score_segmentation(labels, muscle_id, truth_labels, truth_muscle_id, names=()) -> dict:
    """Dice of the outline, of every tissue and of every muscle against the truth.

    Parameters
    ----------
    labels, truth_labels : (I, J, K) array_like of int
        Tissue codes (0 background, 1 muscle, 2 connective tissue, 3 fat, 4 bone) on one grid.
    muscle_id, truth_muscle_id : (I, J, K) array_like of int
        Muscle ids 1..M (0 elsewhere), the same numbering in both (the order of the seeds and of
        the phantom's ``muscle_names``).
    names : sequence of str, optional
        Muscle names for the keys of ``muscles`` (default ``"1"``, ``"2"``, ...).

    Returns
    -------
    dict
        ``outline`` (labels > 0), ``tissues`` (name → Dice), ``muscles`` (name → Dice),
        ``muscle_mean`` and ``muscle_min`` (over the M muscles of the truth).
    """
    labels, truth = np.asarray(labels), np.asarray(truth_labels)
    mid, tmid = np.asarray(muscle_id), np.asarray(truth_muscle_id)
    if not (labels.shape == truth.shape == mid.shape == tmid.shape):
        raise InputError(f"score_segmentation: shapes differ: labels {labels.shape}, truth {truth.shape}, "
                         f"muscle ids {mid.shape} and {tmid.shape}")
    M = int(tmid.max()) if tmid.size else 0
    keys = [str(n) for n in names] if len(names) else [str(m) for m in range(1, M + 1)]
    if len(keys) < M:
        raise InputError(f"score_segmentation: {len(keys)} names for {M} muscles in the truth")
    muscles = {keys[m - 1]: dice(mid == m, tmid == m) for m in range(1, M + 1)}  # loop over muscles
    vals = np.array(list(muscles.values())) if muscles else np.array([np.nan])
    return {"outline": dice(labels > 0, truth > 0),
            "tissues": {name: dice(labels == c, truth == c) for c, name in _TISSUES.items()},
            "muscles": muscles, "muscle_mean": float(np.mean(vals)), "muscle_min": float(np.min(vals))}

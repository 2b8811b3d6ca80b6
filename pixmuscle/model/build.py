"""Label volume → pixel-point model (paper §4.2, "Full model construction").

Every voxel of a node tissue (muscle, connective tissue, fat) becomes one node at its voxel
centre; background and bone voxels carry no node. The model frame is the grid-aligned frame of
the canonical (RAS+) label grid (docs/architecture.md, "Model frame")::

    X = origin + ijk * spacing          (cm)

with ``spacing`` the voxel edge lengths (column norms of the affine's 3×3 block), ``origin`` the
centre of voxel (0, 0, 0) and a residual ``rotation = affine[:3, :3] / spacing`` that maps model
frame directions to scanner directions (the identity except for an oblique acquisition).

Fibre directions are vectors in the **scanner frame** of the affine (x right, y anterior,
z superior), from a 4-D fibre image or one direction per muscle. They are rotated into the model
frame (``v_model = rotationᵀ v_scanner``), normalised, and given the canonical sign of
:func:`pixmuscle.imaging.dti.canonical_sign` (``v_z ≥ 0``); the sign of a fibre is irrelevant.
"""

from __future__ import annotations

import dataclasses
import difflib
import logging
from collections.abc import Mapping, Sequence
from typing import Literal

import numpy as np

from ..errors import InputError
from ..imaging.dti import canonical_sign
from .model import Model
from .nodesets import _check_set_name, compute_node_sets
from .tissues import BONE, MUSCLE, NODE_TISSUES, TISSUE_CODES, TISSUE_NAMES

_LOG = logging.getLogger(__name__)

#: label value → tissue of a label volume written with the codes of docs/architecture.md
DEFAULT_TISSUE_MAP = {code: name for code, name in TISSUE_NAMES.items()}

#: a fibre vector shorter than this (or not finite) counts as "no fibre"
MIN_FIBER_NORM = 1e-6

#: tolerance on ``rotation - I`` above which the scan counts as oblique
OBLIQUE_TOL = 1e-3

FiberFallback = Literal["error", "muscle_mean"]


@dataclasses.dataclass(frozen=True)
class LabelRule:
    """What one label value of the volume means.

    Attributes
    ----------
    tissue : int
        Tissue code (:mod:`pixmuscle.model.tissues`).
    muscle : str or None
        Muscle name for ``tissue == MUSCLE``.
    fiber : (3,) float or None
        Fixed unit fibre direction (scanner frame) for every voxel of this label.
    """

    tissue: int
    muscle: str | None = None
    fiber: tuple | None = None


def _check_direction(v, where: str) -> np.ndarray:
    try:
        a = np.asarray(v, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"{where}: expected a direction [x, y, z] of 3 numbers, got {v!r}") from None
    if a.shape != (3,) or not np.isfinite(a).all() or not np.linalg.norm(a) > 0:
        raise InputError(f"{where}: expected a direction [x, y, z] of 3 finite numbers, not all zero, got {v!r}")
    return a / np.linalg.norm(a)


def parse_tissue_map(tissue_map: Mapping | None, where: str = "tissue_map") -> dict[int, LabelRule]:
    """Validate a tissue map and turn it into one :class:`LabelRule` per label value.

    Parameters
    ----------
    tissue_map : mapping of int → str or mapping, optional
        Label value → ``"muscle"``, ``"connective_tissue"``, ``"fat"``, ``"bone"``,
        ``"background"``, or ``{"muscle": "<name>", "fiber": [x, y, z]}`` (fibre optional,
        scanner frame). A plain ``"muscle"`` is named ``"muscle"`` when it is the only plain
        muscle label, ``"muscle_<label>"`` otherwise. Several labels may name the same muscle.
        ``None``: :data:`DEFAULT_TISSUE_MAP`.
    where : str
        Key path used in error messages.

    Returns
    -------
    dict of int → LabelRule
    """
    if tissue_map is None:
        tissue_map = DEFAULT_TISSUE_MAP
    if not isinstance(tissue_map, Mapping) or not tissue_map:
        raise InputError(f"{where}: expected a non-empty mapping of label value → tissue, got {tissue_map!r}")
    plain = [k for k, v in tissue_map.items() if isinstance(v, str) and v == "muscle"]
    rules: dict[int, LabelRule] = {}
    for label, v in tissue_map.items():
        if isinstance(label, bool) or not isinstance(label, (int, np.integer)):
            raise InputError(f"{where}: label values must be integers, got key {label!r}")
        key = f"{where}[{label}]"
        if isinstance(v, str):
            if v not in TISSUE_CODES:
                close = difflib.get_close_matches(v, list(TISSUE_CODES), n=1)
                hint = f" (did you mean {close[0]!r}?)" if close else ""
                raise InputError(f"{key}: unknown tissue {v!r}{hint}; expected one of {', '.join(TISSUE_CODES)} "
                                 "or {muscle: <name>, fiber: [x, y, z]}")
            code = TISSUE_CODES[v]
            name = ("muscle" if len(plain) == 1 else f"muscle_{int(label)}") if code == MUSCLE else None
            rules[int(label)] = LabelRule(code, name)
        elif isinstance(v, Mapping):
            bad = sorted(set(map(str, v)) - {"muscle", "fiber"})
            if bad or "muscle" not in v:
                raise InputError(f"{key}: expected {{muscle: <name>, fiber: [x, y, z] (optional)}}, got {dict(v)!r}")
            name = v["muscle"]
            if not isinstance(name, str) or not name.strip() or "/" in name:
                raise InputError(f"{key}.muscle: expected a muscle name (non-empty, no '/'), got {name!r}")
            fib = v.get("fiber")
            fib = tuple(_check_direction(fib, f"{key}.fiber")) if fib is not None else None
            rules[int(label)] = LabelRule(MUSCLE, name.strip(), fib)
        else:
            raise InputError(f"{key}: expected a tissue name or {{muscle: <name>, fiber: [x, y, z]}}, got {v!r}")
    return rules


def grid_frame(affine_or_spacing) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Split a voxel → cm affine into spacing, origin and residual rotation.

    Parameters
    ----------
    affine_or_spacing : (4, 4) or (3,) array_like
        Voxel index → scanner coordinates in cm, or just the voxel sizes in cm (origin 0,
        no rotation).

    Returns
    -------
    affine : (4, 4) float64
    spacing : (3,) float64
        Voxel edge lengths, cm (column norms of ``affine[:3, :3]``).
    origin : (3,) float64
        Centre of voxel (0, 0, 0), cm.
    rotation : (3, 3) float64
        ``affine[:3, :3] / spacing``: model frame → scanner frame.
    """
    a = np.asarray(affine_or_spacing, dtype=float)
    if a.shape == (3,):
        if not (np.isfinite(a).all() and (a > 0).all()):
            raise InputError(f"voxel spacing: expected 3 positive numbers (cm), got {a.tolist()}")
        a = np.diag([*a, 1.0])
    if a.shape != (4, 4) or not np.isfinite(a).all():
        raise InputError(f"affine: expected a finite (4, 4) voxel → cm matrix or 3 voxel sizes, got shape {a.shape}")
    if not np.allclose(a[3], [0, 0, 0, 1]):
        raise InputError(f"affine: last row must be [0, 0, 0, 1], got {a[3].tolist()}")
    spacing = np.linalg.norm(a[:3, :3], axis=0)
    if not (spacing > 0).all() or abs(np.linalg.det(a[:3, :3])) < 1e-12 * np.prod(spacing):
        raise InputError(f"affine: singular voxel axes {a[:3, :3].tolist()}")
    return a, spacing, a[:3, 3].copy(), a[:3, :3] / spacing


def canonical_reorientation(affine: np.ndarray, shape) -> tuple[np.ndarray, np.ndarray]:
    """Voxel reordering (axis permutation and flips) to the closest canonical RAS+ grid.

    Parameters
    ----------
    affine : (4, 4) float
        Voxel → cm affine of a grid of ``shape``.
    shape : (3,) int

    Returns
    -------
    ornt : (3, 2) float
        nibabel orientation array (apply with ``nibabel.orientations.apply_orientation``).
    affine : (4, 4) float
        The affine of the reordered grid (the same scanner points).
    """
    from nibabel.orientations import inv_ornt_aff, io_orientation

    ornt = io_orientation(affine)
    if not np.isfinite(ornt).all():
        raise InputError("affine: cannot find the closest canonical orientation (degenerate voxel axes)")
    return ornt, affine @ inv_ornt_aff(ornt, tuple(int(s) for s in shape[:3]))


def _is_identity_ornt(ornt) -> bool:
    return np.array_equal(ornt, [[0, 1], [1, 1], [2, 1]])


def _integer_labels(labels) -> np.ndarray:
    a = np.asarray(labels)
    if a.ndim != 3:
        raise InputError(f"labels: expected a 3-D label volume (I, J, K), got shape {a.shape}")
    if a.dtype == bool or a.dtype.kind in "iu":
        return a.astype(np.int64, copy=False) if a.dtype == bool else a
    if a.dtype.kind == "f":
        if not np.isfinite(a).all() or (a != np.round(a)).any():
            raise InputError("labels: expected integer label values; the volume holds non-integer or NaN values")
        return a.astype(np.int64)
    raise InputError(f"labels: expected integer label values, got dtype {a.dtype}")


def _present_labels(labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distinct values of an integer volume and their voxel counts."""
    lo, hi = int(labels.min()), int(labels.max())
    if hi - lo < (1 << 20):
        counts = np.bincount(labels.ravel().astype(np.int64) - lo)
        vals = np.flatnonzero(counts)
        return vals + lo, counts[vals]
    return np.unique(labels, return_counts=True)


def principal_directions(vectors, groups, n_groups: int) -> tuple[np.ndarray, np.ndarray]:
    """Sign-invariant mean direction per group: principal eigenvector of Σ v vᵀ.

    Parameters
    ----------
    vectors : (n, 3) float
        Directions (normalised here; sign irrelevant).
    groups : (n,) int
        Group of each vector, 0..n_groups-1.
    n_groups : int

    Returns
    -------
    directions : (n_groups, 3) float
        Unit eigenvector of the largest eigenvalue of the group's Σ v̂ v̂ᵀ, canonical sign; zeros
        for empty groups.
    counts : (n_groups,) int
    """
    v = np.asarray(vectors, dtype=float)
    g = np.asarray(groups, dtype=np.int64)
    v = v / np.linalg.norm(v, axis=1, keepdims=True)
    T = np.zeros((n_groups, 3, 3))
    for a in range(3):
        for b in range(a, 3):
            T[:, a, b] = T[:, b, a] = np.bincount(g, weights=v[:, a] * v[:, b], minlength=n_groups)
    counts = np.bincount(g, minlength=n_groups)
    _, vecs = np.linalg.eigh(T)                        # ascending eigenvalues
    d = canonical_sign(vecs[:, :, 2])
    d[counts == 0] = 0.0
    return d, counts


def _describe_nodes(sel: np.ndarray, ijk: np.ndarray, affine: np.ndarray, limit: int = 3) -> str:
    idx = np.flatnonzero(sel)[:limit]
    xyz = ijk[idx] @ affine[:3, :3].T + affine[:3, 3]
    return "; ".join(f"ijk ({i}, {j}, {k}) at ({x:.2f}, {y:.2f}, {z:.2f}) cm"
                     for (i, j, k), (x, y, z) in zip(ijk[idx].tolist(), xyz.tolist(), strict=True))


def _node_fibers(ijk, is_muscle, muscle_id, names, label_of_node, rules, fibers, muscle_fibers,
                 fiber_fallback, rotation, affine) -> np.ndarray:
    """Unit fibre direction (model frame, canonical sign) per node; zeros off muscle."""
    n = ijk.shape[0]
    vec = np.zeros((n, 3))
    valid = np.zeros(n, dtype=bool)
    if fibers is not None:
        lin = np.ravel_multi_index((ijk[:, 0], ijk[:, 1], ijk[:, 2]), fibers.shape[:3])
        v = np.asarray(fibers).reshape(-1, 3)[lin].astype(float)
        with np.errstate(invalid="ignore", over="ignore"):
            norm = np.sqrt(np.einsum("ij,ij->i", v, v))
            valid = is_muscle & np.isfinite(norm) & (norm > MIN_FIBER_NORM)
            scale = np.zeros(n)
            np.divide(1.0, norm, out=scale, where=valid)
            vec = v * scale[:, None]
        vec[~np.isfinite(norm)] = 0.0                  # NaN/inf rows: NaN × 0 is still NaN
    explicit = np.zeros(n, dtype=bool)
    for label, rule in rules.items():                  # a handful of labels
        if rule.fiber is not None and label_of_node is not None:
            sel = is_muscle & (label_of_node == label)
            vec[sel], explicit[sel] = rule.fiber, True
    for name, d in (muscle_fibers or {}).items():      # a handful of muscles
        if name not in names:
            raise InputError(f"muscle_fibers: unknown muscle {name!r}; the model's muscles are {', '.join(names) or 'none'}")
        d = _check_direction(d, f"muscle_fibers.{name}")
        sel = muscle_id == names.index(name) + 1
        if (sel & explicit).any():
            raise InputError(f"muscle_fibers.{name}: the fibre of this muscle is also given in tissue_map; give it once")
        vec[sel], explicit[sel] = d, True
    valid |= explicit
    if not np.array_equal(rotation, np.eye(3)):
        vec = vec @ rotation                           # v_model = Rᵀ v_scanner, row-wise
        nv = np.sqrt(np.einsum("ij,ij->i", vec, vec))
        vec /= np.where(valid, nv, 1.0)[:, None]

    missing = is_muscle & ~valid
    if missing.any():
        m_ids = np.unique(muscle_id[missing])
        if fiber_fallback == "muscle_mean":
            mean, counts = principal_directions(vec[valid & is_muscle], muscle_id[valid & is_muscle], len(names) + 1)
            empty = [int(i) for i in m_ids if counts[i] == 0]
            if empty:
                detail = ", ".join(f"'{names[i - 1]}' ({_describe_nodes(missing & (muscle_id == i), ijk, affine, 1)})"
                                   for i in empty)
                raise InputError(f"fiber_fallback muscle_mean: muscle(s) {detail} have no usable fibre vector at all, "
                                 "so no mean direction; give a direction in build_model.muscle_fibers")
            vec[missing] = mean[muscle_id[missing]]
            for i in m_ids:
                c = int(np.count_nonzero(missing & (muscle_id == i)))
                _LOG.warning("muscle '%s': %d of %d nodes have no usable fibre direction; using the muscle's "
                             "mean direction (%.3f, %.3f, %.3f)", names[i - 1], c,
                             int(np.count_nonzero(muscle_id == i)), *mean[i])
        else:
            why = ("there is no fibre image and no per-muscle direction" if fibers is None else
                   "the fibre image is zero or not finite there and the muscle has no per-muscle direction")
            parts = [f"'{names[i - 1]}': {np.count_nonzero(missing & (muscle_id == i))} nodes, e.g. "
                     + _describe_nodes(missing & (muscle_id == i), ijk, affine) for i in m_ids]
            raise InputError(f"{int(missing.sum())} muscle nodes have no usable fibre direction ({why}): "
                             + " | ".join(parts)
                             + ". Fix the fibre image, give build_model.muscle_fibers {name: [x, y, z]}, or set "
                             "build_model.fiber_fallback: muscle_mean")
    vec = canonical_sign(vec)
    vec[~is_muscle] = 0.0
    return vec


def _checked_inputs(labels, affine_cm, fibers, fiber_fallback, masks, muscle_ids):
    """The inputs of :func:`model_from_labels` as arrays, their shapes checked against the label grid.

    Returns
    -------
    labels, affine (4 × 4, cm), fibers or None, masks (dict of arrays), muscle_ids or None
    """
    labels = _integer_labels(labels)
    shape0 = labels.shape
    affine, _, _, _ = grid_frame(affine_cm)
    if fiber_fallback not in ("error", "muscle_mean"):
        raise InputError(f"fiber_fallback: expected 'error' or 'muscle_mean', got {fiber_fallback!r}")
    if fibers is not None:
        fibers = np.asarray(fibers)
        if fibers.shape != (*shape0, 3):
            raise InputError(f"fibers: expected shape {(*shape0, 3)} (the label grid × 3), got {fibers.shape}")
    masks = dict(masks or {})
    for name, m in masks.items():
        _check_set_name(name)
        masks[name] = np.asarray(m)
        if masks[name].shape != shape0:
            raise InputError(f"mask '{name}': expected shape {shape0} (the label grid), got {masks[name].shape}")
    if muscle_ids is not None:
        muscle_ids = np.asarray(muscle_ids)
        if muscle_ids.shape != shape0 or muscle_ids.dtype.kind not in "iu":
            raise InputError(f"muscle_id: expected an integer volume of shape {shape0}, got {muscle_ids.dtype} {muscle_ids.shape}")
    return labels, affine, fibers, masks, muscle_ids


def _canonical_grid(labels, affine, fibers, masks, muscle_ids):
    """The volumes reordered to the closest canonical (RAS+) grid (unchanged when already canonical),
    and that grid's frame ``(affine, spacing, origin, rotation)`` (:func:`grid_frame`); warns of an
    oblique scan and of voxels that look like mm."""
    ornt, affine = canonical_reorientation(affine, labels.shape)
    if not _is_identity_ornt(ornt):
        from nibabel.orientations import apply_orientation

        _LOG.info("labels reordered to the closest canonical (RAS+) orientation")
        labels = apply_orientation(labels, ornt)
        fibers = apply_orientation(fibers, ornt) if fibers is not None else None
        masks = {k: apply_orientation(m, ornt) for k, m in masks.items()}
        muscle_ids = apply_orientation(muscle_ids, ornt) if muscle_ids is not None else None
    affine, spacing, origin, rotation = grid_frame(affine)
    if np.abs(rotation - np.eye(3)).max() > OBLIQUE_TOL:
        _LOG.warning("oblique scan: the voxel axes are rotated by up to %.2f° from the scanner axes; the model is "
                     "built in the grid-aligned frame and the rotation is kept in grid/rotation",
                     np.degrees(np.arccos(np.clip(np.diag(rotation).min(), -1, 1))))
    if (spacing > 2.0).any():
        _LOG.warning("voxel size %s cm looks large: is the affine in mm instead of cm?", np.round(spacing, 4).tolist())
    return labels, fibers, masks, muscle_ids, (affine, spacing, origin, rotation)


def _tissue_volume(labels, tissue_map):
    """The tissue code of every voxel, from :func:`parse_tissue_map`'s rules.

    Returns
    -------
    rules : dict of int → rule
    keys : (L,) int64
        The mapped label values, sorted.
    tissue_vol : int8 array of labels' shape

    Raises
    ------
    InputError
        Label values that the map does not name.
    """
    rules = parse_tissue_map(tissue_map)
    vals, counts = _present_labels(labels)
    unknown = [(int(v), int(c)) for v, c in zip(vals, counts, strict=True) if int(v) not in rules]
    if unknown:
        listed = ", ".join(f"{v} ({c} voxels)" for v, c in unknown[:10]) + (" ..." if len(unknown) > 10 else "")
        raise InputError(f"labels: values {listed} are not in the tissue map (which names {sorted(rules)}); "
                         "add them to build_model.tissue_map, e.g. {5: fat}")
    keys = np.array(sorted(rules), dtype=np.int64)
    key_tissue = np.array([rules[k].tissue for k in keys], dtype=np.int8)
    return rules, keys, key_tissue[np.searchsorted(keys, labels)]


def _muscle_identity(label_of_node, is_muscle, ijk, affine, rules, keys, tissue_map, node_muscle_ids, muscle_names):
    """Muscle names and each node's muscle id (0: not muscle), from a muscle_id volume's values at
    the nodes (``node_muscle_ids``) or else from the tissue map's muscle labels.

    Returns
    -------
    names : list of str
    mid : (N,) int64
    label_of_node : (N,) int or None
        The nodes' label values, None with a muscle_id volume (per-label fibres are not allowed then).
    """
    if node_muscle_ids is not None:
        if tissue_map is not None and any(isinstance(v, Mapping) for v in tissue_map.values()):
            raise InputError("tissue_map: with a separate muscle_id volume (segmentation.h5) the tissue map may only "
                             "name tissues; muscles and their names come from /muscle_id and /muscle_names")
        names = [str(s) for s in (muscle_names or [])]
        mid = node_muscle_ids.astype(np.int64)
        if mid.size and (mid.min() < 0 or mid.max() > len(names)):
            raise InputError(f"muscle_id: values must be 0..{len(names)} (the number of muscle names), "
                             f"got {mid.min()}..{mid.max()}")
        mid[~is_muscle] = 0
        unassigned = is_muscle & (mid == 0)
        if unassigned.any():
            names.append("unassigned")
            mid[unassigned] = len(names)
            _LOG.warning("%d muscle voxels have muscle_id 0; they form an extra muscle 'unassigned' (e.g. %s)",
                         int(unassigned.sum()), _describe_nodes(unassigned, ijk, affine, 1))
        label_of_node = None                              # per-label fibres are not allowed here
    else:
        names = list(dict.fromkeys(r.muscle for r in rules.values() if r.tissue == MUSCLE))
        key_mid = np.array([names.index(rules[k].muscle) + 1 if rules[k].tissue == MUSCLE else 0 for k in keys])
        mid = key_mid[np.searchsorted(keys, label_of_node)]
    present = set(np.unique(mid[is_muscle]).tolist())
    absent = [nm for i, nm in enumerate(names, 1) if i not in present]
    if absent:
        _LOG.warning("muscle(s) %s have no voxel in the labels (kept with their id, no nodes)", ", ".join(absent))
    return names, mid, label_of_node


def model_from_labels(
    labels,
    affine_cm,
    *,
    tissue_map: Mapping | None = None,
    fibers=None,
    muscle_fibers: Mapping[str, Sequence[float]] | None = None,
    fiber_fallback: FiberFallback = "error",
    masks: Mapping[str, np.ndarray] | None = None,
    muscle_ids=None,
    muscle_names: Sequence[str] | None = None,
) -> Model:
    """Build the pixel-point model of a label volume (paper §4.2).

    Parameters
    ----------
    labels : (I, J, K) int
        Label volume. Values are mapped to tissues by ``tissue_map``.
    affine_cm : (4, 4) or (3,) float
        Voxel index → scanner coordinates in **cm**, or the voxel sizes (cm). A grid that is not
        in the closest canonical RAS+ orientation is reordered to it first (as
        :func:`pixmuscle.imaging.nifti.load_volume` does), together with ``fibers``, ``masks``
        and ``muscle_ids``; the model's ``ijk`` refer to the canonical grid.
    tissue_map : mapping of int → str or mapping, optional
        See :func:`parse_tissue_map`. Default: the tissue codes (0 background, 1 muscle,
        2 connective_tissue, 3 fat, 4 bone). Values in the volume that the map does not name
        are an error.
    fibers : (I, J, K, 3) float, optional
        Fibre direction per voxel, scanner frame; any length and sign (normalised here); zero or
        NaN = none.
    muscle_fibers : mapping of str → (3,) float, optional
        One fibre direction (scanner frame) per muscle name; overrides the image for that muscle.
    fiber_fallback : {"error", "muscle_mean"}
        What to do with muscle nodes without a usable fibre: raise (default), or use the
        muscle's sign-invariant mean direction (principal eigenvector of Σ v vᵀ over its valid
        nodes) and log a warning with the count.
    masks : mapping of str → (I, J, K) array, optional
        Extra node sets: the nodes whose voxel is non-zero in the mask (same grid as labels).
    muscle_ids : (I, J, K) int, optional
        Individual muscle per voxel, 0 or 1..M (``/muscle_id`` of segmentation.h5). When given,
        muscle identity comes from it (``tissue_map`` may then hold only tissue names); muscle
        voxels with id 0 go to an extra muscle ``"unassigned"`` (with a warning).
    muscle_names : sequence of str, optional
        Names of the M muscles of ``muscle_ids``.

    Returns
    -------
    Model
        Nodes in C order of (i, j, k); node sets from :func:`compute_node_sets`; ``bone_ijk``
        holds the bone voxels.

    Raises
    ------
    InputError
        Unmapped label values, shape mismatches, no node voxels, or muscle nodes without a fibre
        (``fiber_fallback="error"``); messages say how many and where.
    """
    labels, affine, fibers, masks, muscle_ids = _checked_inputs(labels, affine_cm, fibers, fiber_fallback, masks,
                                                                muscle_ids)
    labels, fibers, masks, muscle_ids, (affine, spacing, origin, rotation) = _canonical_grid(
        labels, affine, fibers, masks, muscle_ids)
    shape = labels.shape
    rules, keys, tissue_vol = _tissue_volume(labels, tissue_map)
    node_mask = np.isin(tissue_vol, NODE_TISSUES)
    bone_mask = tissue_vol == BONE
    ijk = np.argwhere(node_mask)
    if ijk.shape[0] == 0:
        raise InputError("labels: no voxel of a node tissue (muscle, connective tissue, fat); check the tissue map")
    sel = (ijk[:, 0], ijk[:, 1], ijk[:, 2])
    tissue = tissue_vol[sel]
    is_muscle = tissue == MUSCLE
    names, mid, label_of_node = _muscle_identity(labels[sel], is_muscle, ijk, affine, rules, keys, tissue_map,
                                                 None if muscle_ids is None else muscle_ids[sel], muscle_names)

    fiber = _node_fibers(ijk, is_muscle, mid, names, label_of_node, rules,
                         fibers, muscle_fibers, fiber_fallback, rotation, affine)
    sets = compute_node_sets(ijk, shape, bone_mask, masks)
    X = origin + ijk * spacing
    _LOG.info("model: %d nodes (%s) on a %s grid, spacing %s cm, %d muscle(s)", ijk.shape[0],
              ", ".join(f"{TISSUE_NAMES[t]} {np.count_nonzero(tissue == t)}" for t in NODE_TISSUES),
              "×".join(map(str, shape)), np.round(spacing, 5).tolist(), len(names))
    return Model(
        X=X, ijk=ijk.astype(np.int32), tissue=tissue.astype(np.int8), muscle_id=mid.astype(np.int16),
        fiber=fiber, muscle_names=names, spacing=spacing, origin=origin,
        shape=np.array(shape, dtype=np.int64), rotation=rotation, sets=sets, coarsen_factor=1,
        bone_ijk=np.argwhere(bone_mask).astype(np.int32),
    )


#: the name used in docs/architecture.md ("Public APIs")
build_model = model_from_labels

__all__ = ["DEFAULT_TISSUE_MAP", "LabelRule", "build_model", "canonical_reorientation", "grid_frame",
           "model_from_labels", "parse_tissue_map", "principal_directions"]

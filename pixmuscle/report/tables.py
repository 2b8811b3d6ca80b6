"""Tissue volume table in the style of paper Table 3 (muscle, IMAT, IMCT volumes, F_max).

Volumes are node counts × cell volume: every node of the pixel-point model owns one axis-aligned
integration cell of size ``grid/spacing`` (docs/architecture.md, "Model frame").

Definitions (the tissue codes do not separate them, so the report derives them from geometry):

IMAT
    fat that is not part of the subcutaneous layer. Rule ``"enclosed"`` (default): a fat node is
    subcutaneous when it lies outside the *muscle envelope* and its fat region, connected through
    voxel faces *within its slice*, touches the outside of the body or the skin in that slice; all
    other fat is IMAT. The outside is the background connected to the in-plane border of the grid;
    the skin is the connective tissue within ``skin_cm`` (0.2 cm) of the outside; the muscle
    envelope is the in-slice region enclosed by muscle and non-skin connective tissue (IMCT,
    fascia, aponeurosis) after a morphological closing of radius ``envelope_cm`` (0.5 cm), which
    bridges the gaps a thin aponeurosis has on a coarse grid. All three are physical lengths, so
    the rule does not change with the resolution: on a coarse grid a thin skin has gaps and the fat
    touches the background, on a fine grid it is a closed ring the fat touches.
    Rule ``"near_muscle"``: fat within ``attach_distance`` cells of a muscle node is IMAT (simple,
    but it also counts the subcutaneous fat lying against muscle).
IMCT
    connective-tissue nodes that are neither skin nor in the ``aponeurosis`` node set (built from
    ``segment.aponeurosis_mask``), as in paper Table 3 ("IMCT here does not include the
    aponeurosis"). Without that set the aponeurosis cannot be told from IMCT and is counted in it.
Total volume (the paper's, beside Table 3)
    muscle + IMAT + IMCT + aponeurosis: the muscle with its outer connective-tissue layer, without
    subcutaneous fat and skin (paper, young vs old example: "force generated per unit total volume
    (including the outer layer of connective tissue)"). "F_max / total volume" is always this.
    The volume of every node of the model (with subcutaneous fat and skin) is called the
    *whole-model volume*.
Attribution to muscles
    IMAT and IMCT nodes belong to the muscle of their nearest muscle node (Chebyshev distance in
    grid cells) when it is within ``attach_distance`` cells; otherwise they are "not attributed".
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from ..errors import InputError
from ..model.tissues import CONNECTIVE_TISSUE, FAT, MUSCLE

#: in-plane (axes 0, 1) face connectivity: slices are independent
_INPLANE = np.zeros((3, 3, 3), bool)
_INPLANE[1, 1, 1] = _INPLANE[0, 1, 1] = _INPLANE[2, 1, 1] = _INPLANE[1, 0, 1] = _INPLANE[1, 2, 1] = True

#: the paper's total volume: muscle + IMAT + IMCT + aponeurosis (module docstring)
TOTAL = "total volume: muscle + IMAT + IMCT + aponeurosis [cm^3]"
#: every node's cell, subcutaneous fat and skin included
WHOLE = "whole model [cm^3]"
FORCE_PER_TOTAL = "F_max / total volume [N/cm^3]"
TABLE_HEADER = [
    "region", "muscle [cm^3]", "IMAT [cm^3]", "IMCT [cm^3]", "aponeurosis [cm^3]", TOTAL, "subcutaneous fat [cm^3]",
    "skin [cm^3]", WHOLE, "muscle nodes", "IMAT nodes", "IMCT nodes", "aponeurosis nodes",
    "subcutaneous fat nodes", "skin nodes", "F_max [N]", FORCE_PER_TOTAL,
]
#: the classes of :func:`tissue_classes`, in table order
CLASSES = ("muscle", "imat", "imct", "aponeurosis", "subcutaneous", "skin")
_NAMES = {"muscle": "muscle", "imat": "IMAT", "imct": "IMCT", "aponeurosis": "aponeurosis",
          "subcutaneous": "subcutaneous fat", "skin": "skin"}

FOOTNOTE = (
    "Volumes = node count × cell volume. F_max is the largest end force over the converged steps of the "
    "whole model (mean of the axial reactions of the force sets); {per_muscle}. IMAT: {imat_rule}. IMCT: "
    "{imct_rule}. IMAT and IMCT are attributed to the muscle of the nearest muscle node within {attach:g} cells, "
    "otherwise 'not attributed'. Total volume = muscle + IMAT + IMCT + aponeurosis, the paper's (the muscle with "
    "its outer connective tissue, without subcutaneous fat and skin); F_max / total volume uses it. Whole model = "
    "every node's cell, subcutaneous fat and skin included."
)
#: what the per-muscle rows' F_max is, without and with the one-muscle-at-a-time solves (muscle_forces)
PER_MUSCLE_NOTES = {
    False: "one end reaction cannot be split between muscles, so per-muscle rows give volumes only (the "
           "muscle_forces section of the configuration gives each muscle's force)",
    True: "a muscle's F_max is its contribution to the end force at the step of F_max, from the solves with one "
          "muscle active at a time (section Force by muscle)",
}
IMCT_RULES = {
    True: "connective tissue other than the skin and the aponeurosis mask (paper Table 3)",
    False: "connective tissue other than the skin (no aponeurosis mask: aponeurosis and tendon are included)",
}
#: connective tissue within this distance (cm) of the outside of the body is skin
SKIN_CM = 0.2
#: radius (cm) of the closing that makes the muscle envelope
ENVELOPE_CM = 0.5
IMAT_RULES = {
    "enclosed": "fat inside the muscle envelope or not connected, within its slice, to the outside of the body or the "
                "skin (the rest is subcutaneous fat)",
    "near_muscle": "fat within {attach:g} cells of a muscle node (the rest is subcutaneous fat)",
}


def outside_and_skin(ijk: np.ndarray, tissue: np.ndarray, shape: Sequence[int], spacing: Sequence[float],
                     skin_cm: float = SKIN_CM) -> tuple[np.ndarray, np.ndarray, tuple]:
    """The outside of the body and the skin, slice by slice.

    Parameters
    ----------
    ijk : (N, 3) int; tissue : (N,) int; shape : (3,) int
        Node voxel indices, tissue codes and the grid shape.
    spacing : (3,) float
        Cell edge lengths, cm.
    skin_cm : float
        Connective tissue whose voxel lies within this distance (cm, in-plane, from the voxel's
        near face) of the outside is skin.

    Returns
    -------
    outside : (I+2, J+2, K) bool
        Background (non-node, including non-node bone) connected through in-plane faces to the
        in-plane border of the grid, on the grid padded by one cell in-plane.
    skin : (N,) bool
        Connective-tissue nodes that are skin.
    p : tuple of 3 (N,) int arrays
        The nodes' indices into the padded grid.
    """
    ijk = np.asarray(ijk, np.int64)
    pad = np.array([1, 1, 0])
    occ = np.zeros(np.asarray(shape, np.int64) + 2 * pad, np.int8)
    p = tuple((ijk + pad).T)
    occ[p] = np.asarray(tissue, np.int8)
    bg_lab, _ = ndimage.label(occ == 0, structure=_INPLANE)
    border = np.unique(np.concatenate([bg_lab[0].ravel(), bg_lab[-1].ravel(), bg_lab[:, 0].ravel(), bg_lab[:, -1].ravel()]))
    outside = np.isin(bg_lab, border[border > 0])
    h = np.asarray(spacing, float)
    # in-plane distance (cm) from each voxel centre to the nearest outside voxel centre; slices apart
    dist = ndimage.distance_transform_edt(~outside, sampling=(h[0], h[1], 1e9 * max(h[0], h[1])))
    skin = (occ == CONNECTIVE_TISSUE) & (dist - 0.5 * min(h[0], h[1]) <= skin_cm)
    return outside, skin[p], p


def _disk(radius_cm: float, h: np.ndarray) -> np.ndarray:
    """In-plane elliptical structuring element (rx, ry pixels from ``radius_cm`` and spacing ``h``), 3-D with one slice."""
    r = np.maximum(np.ceil(radius_cm / h[:2] - 1e-9).astype(int), 1)
    x, y = np.ogrid[-r[0]:r[0] + 1, -r[1]:r[1] + 1]
    return ((x * h[0]) ** 2 + (y * h[1]) ** 2 <= radius_cm ** 2 + 1e-12)[:, :, None]


def muscle_envelope(occ: np.ndarray, skin: np.ndarray, spacing: Sequence[float], radius_cm: float = ENVELOPE_CM) -> np.ndarray:
    """In-slice region enclosed by muscle and non-skin connective tissue.

    Parameters
    ----------
    occ : (I, J, K) int
        Tissue code per voxel (0 where no node).
    skin : (I, J, K) bool
        Skin voxels.
    spacing : (3,) float
        Cell edge lengths, cm.
    radius_cm : float
        Radius of the in-plane closing applied before the holes are filled, cm.

    Returns
    -------
    (I, J, K) bool
    """
    h = np.asarray(spacing, float)
    wall = (occ == MUSCLE) | ((occ == CONNECTIVE_TISSUE) & ~skin)
    r = np.maximum(np.ceil(radius_cm / h[:2] - 1e-9).astype(int), 1)
    padded = np.pad(wall, ((r[0], r[0]), (r[1], r[1]), (0, 0)))
    closed = ndimage.binary_closing(padded, structure=_disk(radius_cm, h))[r[0]:-r[0], r[1]:-r[1]]
    out = np.empty_like(closed)
    for k in range(closed.shape[2]):  # a loop over slices (not nodes): holes are filled slice by slice
        out[:, :, k] = ndimage.binary_fill_holes(closed[:, :, k])
    return out


def subcutaneous_fat(ijk: np.ndarray, tissue: np.ndarray, shape: Sequence[int],
                     spacing: Sequence[float] = (1.0, 1.0, 1.0), skin_cm: float = SKIN_CM,
                     envelope_cm: float = ENVELOPE_CM) -> np.ndarray:
    """Fat nodes outside the muscle envelope whose in-slice fat region touches the outside of the
    body or the skin (module docstring, rule "enclosed").

    See :func:`outside_and_skin` for the outside and the skin (bone and other holes enclosed by
    tissue are not outside) and :func:`muscle_envelope`.

    Parameters
    ----------
    ijk : (N, 3) int
        Voxel index of every node.
    tissue : (N,) int
        Tissue code of every node.
    shape : (3,) int
        Grid shape.
    spacing : (3,) float
        Cell edge lengths, cm.
    skin_cm, envelope_cm : float
        Skin thickness and closing radius of the envelope, cm.

    Returns
    -------
    (N,) bool
        True for subcutaneous fat nodes.
    """
    outside, skin, p = outside_and_skin(ijk, tissue, shape, spacing, skin_cm)
    shell = outside.copy()
    skin_vox = np.zeros(outside.shape, bool)
    skin_vox[tuple(a[skin] for a in p)] = True
    shell |= skin_vox
    occ = np.zeros(outside.shape, np.int8)
    occ[p] = np.asarray(tissue, np.int8)
    fat = (occ == FAT) & ~muscle_envelope(occ, skin_vox, spacing, envelope_cm)
    fat_lab, _ = ndimage.label(fat, structure=_INPLANE)
    touching = ndimage.binary_dilation(shell, structure=_INPLANE) & fat
    sub_labels = np.unique(fat_lab[touching])
    sub = np.isin(fat_lab, sub_labels[sub_labels > 0])
    return sub[p]


def nearest_muscle(ijk: np.ndarray, tissue: np.ndarray, muscle_id: np.ndarray, query: np.ndarray,
                   max_cells: float) -> tuple[np.ndarray, np.ndarray]:
    """Muscle id of the nearest muscle node, for the nodes selected by ``query``.

    Distance is the Chebyshev (max-norm) distance in grid cells between voxel indices.

    Parameters
    ----------
    ijk : (N, 3) int
    tissue, muscle_id : (N,) int
    query : (N,) bool
        Nodes to look up.
    max_cells : float
        Largest distance considered, cells.

    Returns
    -------
    ids : (n,) int64
        Muscle id (1..M) of the nearest muscle node within ``max_cells``, 0 where none.
    dist : (n,) float64
        Distance in cells (inf where none within ``max_cells``).
    """
    ismus = np.asarray(tissue) == MUSCLE
    q = np.asarray(ijk, float)[query]
    if not ismus.any() or q.shape[0] == 0:
        return np.zeros(q.shape[0], np.int64), np.full(q.shape[0], np.inf)
    tree = cKDTree(np.asarray(ijk, float)[ismus])
    dist, idx = tree.query(q, k=1, p=np.inf, distance_upper_bound=max_cells + 1e-9)
    found = np.isfinite(dist)
    ids = np.zeros(q.shape[0], np.int64)
    ids[found] = np.asarray(muscle_id)[ismus][idx[found]]
    return ids, dist


def tissue_classes(ijk, tissue, muscle_id, shape, *, rule: str = "enclosed", attach_distance: float = 2.0,
                   spacing: Sequence[float] = (1.0, 1.0, 1.0), aponeurosis: np.ndarray | None = None,
                   skin_cm: float = SKIN_CM) -> dict:
    """Classify every node as muscle, IMAT, IMCT, aponeurosis, subcutaneous fat or skin, and
    attribute it to a muscle.

    Parameters
    ----------
    ijk : (N, 3) int; tissue, muscle_id : (N,) int; shape : (3,) int
    rule : {"enclosed", "near_muscle"}
        IMAT rule (module docstring).
    attach_distance : float
        Cells (Chebyshev) within which IMAT/IMCT is attributed to a muscle.
    spacing : (3,) float
        Cell edge lengths, cm.
    aponeurosis : (N,) bool, optional
        Nodes of the aponeurosis mask; its connective tissue is not IMCT.
    skin_cm : float
        Skin thickness, cm.

    Returns
    -------
    dict with (N,) bool arrays ``muscle``, ``imat``, ``imct``, ``aponeurosis``, ``subcutaneous``,
    ``skin`` (every node in at most one) and ``owner`` (int64: muscle id 1..M the node is
    attributed to, 0 = not attributed).
    """
    tissue = np.asarray(tissue)
    muscle_id = np.asarray(muscle_id, np.int64)
    fat = tissue == FAT
    _, skin, _ = outside_and_skin(ijk, tissue, shape, spacing, skin_cm)
    if rule == "enclosed":
        sub = subcutaneous_fat(ijk, tissue, shape, spacing, skin_cm)
        imat = fat & ~sub
    elif rule == "near_muscle":
        ids, _ = nearest_muscle(ijk, tissue, muscle_id, fat, attach_distance)
        imat = np.zeros(tissue.shape, bool)
        imat[fat] = ids > 0
    else:
        raise InputError(f"report.imat_rule: expected 'enclosed' or 'near_muscle', got {rule!r}")
    ct = tissue == CONNECTIVE_TISSUE
    apo = ct & ~skin & (np.zeros(tissue.shape, bool) if aponeurosis is None else np.asarray(aponeurosis, bool))
    imct = ct & ~skin & ~apo
    owner = np.where(tissue == MUSCLE, muscle_id, 0)
    other = imat | imct | apo
    ids, _ = nearest_muscle(ijk, tissue, muscle_id, other, attach_distance)
    owner[other] = ids
    return {"muscle": tissue == MUSCLE, "imat": imat, "imct": imct, "aponeurosis": apo,
            "subcutaneous": fat & ~imat, "skin": ct & skin, "owner": owner}


def tissue_table(ijk, tissue, muscle_id, shape, spacing, muscle_names: Sequence[str], *,
                 f_max: float | None = None, rule: str = "enclosed", attach_distance: float = 2.0,
                 aponeurosis: np.ndarray | None = None) -> dict:
    """Per-muscle and total tissue volumes, F_max and force per unit total volume (paper Table 3 and
    the text beside it; the definitions are in the module docstring).

    Parameters
    ----------
    ijk : (N, 3) int; tissue, muscle_id : (N,) int; shape : (3,) int
        Node grid indices, tissue codes, muscle ids and the grid shape.
    spacing : (3,) float
        Cell edge lengths, cm.
    muscle_names : list of str
        Names of muscles 1..M.
    f_max : float, optional
        Largest end force of the whole model, N.
    rule, attach_distance, aponeurosis
        See :func:`tissue_classes`.

    Returns
    -------
    dict with ``header`` (list of str), ``rows`` (list of dict keyed like the header, one per
    muscle, then "not attributed", then "total"), ``cell_volume_cm3``, ``volumes_cm3`` (totals:
    ``table3_total`` is the total volume muscle + IMAT + IMCT + aponeurosis, ``total`` the whole
    model), ``f_max_N``, ``force_per_volume_N_per_cm3`` (F_max / total volume, the paper's),
    ``force_per_whole_model_volume_N_per_cm3``, ``force_per_muscle_volume_N_per_cm3``, ``footnote``
    (see :func:`footnote`).
    """
    cell = float(np.prod(np.asarray(spacing, float)))
    if not cell > 0:
        raise InputError(f"grid/spacing: expected positive cell sizes in cm, got {list(spacing)}")
    cls = tissue_classes(ijk, tissue, muscle_id, shape, rule=rule, attach_distance=attach_distance,
                         spacing=spacing, aponeurosis=aponeurosis)
    m = len(muscle_names)
    owner = cls["owner"]
    if owner.size and owner.max() > m:
        raise InputError(f"/nodes/muscle_id: ids up to {owner.max()} but only {m} muscle names in /muscles/names")

    def per_owner(mask):
        return np.bincount(owner[mask], minlength=m + 1)  # [0] = not attributed

    counts = {k: per_owner(cls[k]) for k in CLASSES}
    names = list(muscle_names) + ["not attributed"]
    order = list(range(1, m + 1)) + [0]
    rows = []
    for name, o in zip(names, order, strict=True):
        c = {k: int(counts[k][o]) for k in counts}
        rows.append(_row(name, c, cell))
    tot = {k: int(counts[k].sum()) for k in counts}
    total = _row("total", tot, cell)
    n_total = int(np.asarray(tissue).shape[0])
    total[WHOLE] = n_total * cell
    ok = f_max is not None and np.isfinite(f_max)
    if ok:
        total["F_max [N]"] = float(f_max)
        total[FORCE_PER_TOTAL] = float(f_max) / total[TOTAL] if total[TOTAL] > 0 else None
    rows.append(total)
    vols = {k: total[f"{_NAMES[k]} [cm^3]"] for k in CLASSES}
    table3 = total[TOTAL]
    return {
        "header": list(TABLE_HEADER),
        "rows": rows,
        "cell_volume_cm3": cell,
        "volumes_cm3": {"muscle": vols["muscle"], "imat": vols["imat"], "imct": vols["imct"],
                        "aponeurosis": vols["aponeurosis"], "subcutaneous_fat": vols["subcutaneous"],
                        "skin": vols["skin"], "total": total[WHOLE], "table3_total": table3},
        "force_per_table3_volume_N_per_cm3": float(f_max) / table3 if ok and table3 > 0 else None,
        "force_per_muscle_volume_N_per_cm3": float(f_max) / vols["muscle"] if ok and vols["muscle"] > 0 else None,
        "f_max_N": None if f_max is None or not np.isfinite(f_max) else float(f_max),
        "force_per_volume_N_per_cm3": total[FORCE_PER_TOTAL] if ok else None,
        "force_per_whole_model_volume_N_per_cm3": float(f_max) / total[WHOLE] if ok and total[WHOLE] > 0 else None,
        "rule": rule,
        "attach_distance": attach_distance,
        "aponeurosis_mask": aponeurosis is not None,
        "footnote": footnote(rule, attach_distance, aponeurosis is not None),
        "imat_mask": cls["imat"],
    }


def footnote(rule: str, attach_distance: float, aponeurosis_mask: bool, per_muscle_force: bool = False) -> str:
    """The table's footnote: definitions, and what the per-muscle rows' F_max is (``per_muscle_force``:
    filled from the one-muscle-at-a-time solves)."""
    return FOOTNOTE.format(imat_rule=IMAT_RULES[rule].format(attach=attach_distance), attach=attach_distance,
                           imct_rule=IMCT_RULES[aponeurosis_mask], per_muscle=PER_MUSCLE_NOTES[per_muscle_force])


def _row(name: str, c: dict, cell: float) -> dict:
    row = {"region": name}
    for k in CLASSES:
        row[f"{_NAMES[k]} [cm^3]"] = c[k] * cell
    row[TOTAL] = sum(c[k] for k in ("muscle", "imat", "imct", "aponeurosis")) * cell
    row[WHOLE] = sum(c[k] for k in CLASSES) * cell
    for k in CLASSES:
        row[f"{_NAMES[k]} nodes"] = c[k]
    row["F_max [N]"] = row[FORCE_PER_TOTAL] = None
    return row


def table_csv_rows(table: dict) -> list[list]:
    """Rows of ``tissue_table.csv`` (empty cells where a value does not apply)."""
    out = []
    for r in table["rows"]:
        out.append(["" if r[h] is None else (repr(float(r[h])) if isinstance(r[h], float) else r[h]) for h in table["header"]])
    return out

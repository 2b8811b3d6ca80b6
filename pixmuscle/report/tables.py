"""Tissue volume table in the style of paper Table 3 (muscle, IMAT, IMCT volumes, F_max).

Volumes are node counts × cell volume: every node of the pixel-point model owns one axis-aligned
integration cell of size ``grid/spacing`` (docs/architecture.md, "Model frame").

Definitions (the tissue codes do not separate them, so the report derives them from geometry):

IMAT
    fat that is not part of the subcutaneous layer. Rule ``"enclosed"`` (default): a fat node is
    subcutaneous when its fat region, connected through voxel faces *within its slice*, touches
    the outside of the body in that slice (background connected to the in-plane border of the
    grid); all other fat is IMAT. Rule ``"near_muscle"``: fat within ``attach_distance`` cells of a
    muscle node is IMAT (simple, but it also counts the subcutaneous fat lying against muscle).
IMCT
    all connective-tissue nodes (code 2). The code does not separate IMCT from aponeurosis and
    tendon, so unlike paper Table 3 the aponeurosis is included.
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

TABLE_HEADER = [
    "region", "muscle [cm^3]", "IMAT [cm^3]", "IMCT [cm^3]", "subcutaneous fat [cm^3]", "total [cm^3]",
    "muscle nodes", "IMAT nodes", "IMCT nodes", "subcutaneous fat nodes", "F_max [N]", "F_max / total volume [N/cm^3]",
]

FOOTNOTE = (
    "Volumes = node count × cell volume. F_max is the largest end force over the converged steps of the "
    "whole model (mean of the axial reactions of the force sets); one end reaction cannot be split between "
    "muscles, so per-muscle rows give volumes only. IMAT: {imat_rule}. IMCT: every connective-tissue node "
    "(includes aponeurosis and tendon, which the tissue codes do not separate). IMAT and IMCT are attributed "
    "to the muscle of the nearest muscle node within {attach:g} cells, otherwise 'not attributed'. "
    "Force per unit volume uses the total model volume (paper Example 3)."
)
IMAT_RULES = {
    "enclosed": "fat not connected, within its slice, to the outside of the body (the rest is subcutaneous fat)",
    "near_muscle": "fat within {attach:g} cells of a muscle node (the rest is subcutaneous fat)",
}


def subcutaneous_fat(ijk: np.ndarray, tissue: np.ndarray, shape: Sequence[int]) -> np.ndarray:
    """Fat nodes whose in-slice fat region touches the outside of the body.

    The outside of a slice is the background (non-node, including non-node bone) connected through
    in-plane voxel faces to the in-plane border of the grid; bone and other holes enclosed by
    tissue are not outside.

    Parameters
    ----------
    ijk : (N, 3) int
        Voxel index of every node.
    tissue : (N,) int
        Tissue code of every node.
    shape : (3,) int
        Grid shape.

    Returns
    -------
    (N,) bool
        True for subcutaneous fat nodes.
    """
    ijk = np.asarray(ijk, np.int64)
    pad = np.array([1, 1, 0])
    occ = np.zeros(np.asarray(shape, np.int64) + 2 * pad, np.int8)
    p = tuple((ijk + pad).T)
    occ[p] = np.asarray(tissue, np.int8)
    bg_lab, _ = ndimage.label(occ == 0, structure=_INPLANE)
    border = np.unique(np.concatenate([bg_lab[0].ravel(), bg_lab[-1].ravel(), bg_lab[:, 0].ravel(), bg_lab[:, -1].ravel()]))
    outside = np.isin(bg_lab, border[border > 0])
    fat = occ == FAT
    fat_lab, _ = ndimage.label(fat, structure=_INPLANE)
    touching = ndimage.binary_dilation(outside, structure=_INPLANE) & fat
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


def tissue_classes(ijk, tissue, muscle_id, shape, *, rule: str = "enclosed", attach_distance: float = 2.0) -> dict:
    """Classify every node as muscle, IMAT, IMCT or subcutaneous fat and attribute it to a muscle.

    Returns
    -------
    dict with (N,) arrays ``muscle``, ``imat``, ``imct``, ``subcutaneous`` (bool) and ``owner``
    (int64: muscle id 1..M the node is attributed to, 0 = not attributed).
    """
    tissue = np.asarray(tissue)
    muscle_id = np.asarray(muscle_id, np.int64)
    fat = tissue == FAT
    if rule == "enclosed":
        sub = subcutaneous_fat(ijk, tissue, shape)
        imat = fat & ~sub
    elif rule == "near_muscle":
        ids, _ = nearest_muscle(ijk, tissue, muscle_id, fat, attach_distance)
        imat = np.zeros(tissue.shape, bool)
        imat[fat] = ids > 0
    else:
        raise InputError(f"report.imat_rule: expected 'enclosed' or 'near_muscle', got {rule!r}")
    imct = tissue == CONNECTIVE_TISSUE
    owner = np.where(tissue == MUSCLE, muscle_id, 0)
    other = imat | imct
    ids, _ = nearest_muscle(ijk, tissue, muscle_id, other, attach_distance)
    owner[other] = ids
    return {"muscle": tissue == MUSCLE, "imat": imat, "imct": imct, "subcutaneous": fat & ~imat, "owner": owner}


def tissue_table(ijk, tissue, muscle_id, shape, spacing, muscle_names: Sequence[str], *,
                 f_max: float | None = None, rule: str = "enclosed", attach_distance: float = 2.0) -> dict:
    """Per-muscle and total tissue volumes, F_max and force per unit total volume (paper Table 3).

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

    Returns
    -------
    dict with ``header`` (list of str), ``rows`` (list of dict keyed like the header, one per
    muscle, then "not attributed", then "total"), ``cell_volume_cm3``, ``volumes_cm3`` (totals),
    ``f_max_N``, ``force_per_volume_N_per_cm3``, ``footnote``.
    """
    cell = float(np.prod(np.asarray(spacing, float)))
    if not cell > 0:
        raise InputError(f"grid/spacing: expected positive cell sizes in cm, got {list(spacing)}")
    cls = tissue_classes(ijk, tissue, muscle_id, shape, rule=rule, attach_distance=attach_distance)
    m = len(muscle_names)
    owner = cls["owner"]
    if owner.size and owner.max() > m:
        raise InputError(f"/nodes/muscle_id: ids up to {owner.max()} but only {m} muscle names in /muscles/names")

    def per_owner(mask):
        return np.bincount(owner[mask], minlength=m + 1)  # [0] = not attributed

    counts = {k: per_owner(cls[k]) for k in ("muscle", "imat", "imct", "subcutaneous")}
    names = list(muscle_names) + ["not attributed"]
    order = list(range(1, m + 1)) + [0]
    rows = []
    for name, o in zip(names, order, strict=True):
        c = {k: int(counts[k][o]) for k in counts}
        rows.append(_row(name, c, cell))
    tot = {k: int(counts[k].sum()) for k in counts}
    total = _row("total", tot, cell)
    n_total = int(np.asarray(tissue).shape[0])
    total["total [cm^3]"] = n_total * cell
    fpv = None
    if f_max is not None and np.isfinite(f_max):
        total["F_max [N]"] = float(f_max)
        fpv = float(f_max) / total["total [cm^3]"] if total["total [cm^3]"] > 0 else None
        total["F_max / total volume [N/cm^3]"] = fpv
    rows.append(total)
    imat_rule = IMAT_RULES[rule].format(attach=attach_distance)
    return {
        "header": list(TABLE_HEADER),
        "rows": rows,
        "cell_volume_cm3": cell,
        "volumes_cm3": {"muscle": total["muscle [cm^3]"], "imat": total["IMAT [cm^3]"], "imct": total["IMCT [cm^3]"],
                        "subcutaneous_fat": total["subcutaneous fat [cm^3]"], "total": total["total [cm^3]"]},
        "f_max_N": None if f_max is None or not np.isfinite(f_max) else float(f_max),
        "force_per_volume_N_per_cm3": fpv,
        "rule": rule,
        "attach_distance": attach_distance,
        "footnote": FOOTNOTE.format(imat_rule=imat_rule, attach=attach_distance),
        "imat_mask": cls["imat"],
    }


def _row(name: str, c: dict, cell: float) -> dict:
    vol = {k: c[k] * cell for k in c}
    return {
        "region": name,
        "muscle [cm^3]": vol["muscle"], "IMAT [cm^3]": vol["imat"], "IMCT [cm^3]": vol["imct"],
        "subcutaneous fat [cm^3]": vol["subcutaneous"],
        "total [cm^3]": vol["muscle"] + vol["imat"] + vol["imct"] + vol["subcutaneous"],
        "muscle nodes": c["muscle"], "IMAT nodes": c["imat"], "IMCT nodes": c["imct"],
        "subcutaneous fat nodes": c["subcutaneous"], "F_max [N]": None, "F_max / total volume [N/cm^3]": None,
    }


def table_csv_rows(table: dict) -> list[list]:
    """Rows of ``tissue_table.csv`` (empty cells where a value does not apply)."""
    out = []
    for r in table["rows"]:
        out.append(["" if r[h] is None else (repr(float(r[h])) if isinstance(r[h], float) else r[h]) for h in table["header"]])
    return out

"""Coarse pixel-point model: every ``factor``-th pixel in-plane, all slices (paper §4.2).

The paper builds its coarse model "by sorting common points between the coarse and the fine
images for each slice": the coarse nodes are the fine nodes that lie on a coarser in-plane
lattice. Here the kept nodes are those with ::

    i ≡ i0 (mod factor)  and  j ≡ j0 (mod factor)          (slices, axis 2, unchanged)

and the coarse grid is ``ijk_c = ((i - i0) // factor, (j - j0) // factor, k)`` with
``spacing_c = spacing * (factor, factor, 1)`` and ``origin_c = origin + (i0, j0, 0) * spacing``.
So ``origin_c + ijk_c * spacing_c`` is exactly the fine voxel centre of the kept node: the coarse
nodes stay where the fine nodes were, and the coarse integration cells (boxes of size
``spacing_c`` centred on the nodes) tile the coarse grid, as SCNI needs.

Offsets (i0, j0), chosen per in-plane axis by :func:`lattice_offsets`: the kept lattice is
centred on the node cloud's bounding box ``lo..hi``, ``i0 = (lo + ((hi - lo) % factor) // 2)
% factor``. With ``factor = 2`` both extreme planes are kept when the extent ``hi - lo + 1`` is
odd, and the lower one when it is even.

Node sets on the coarse grid:

* the geometric sets (``z_min`` … ``outer_surface``) are recomputed on the coarse grid by
  :func:`~pixmuscle.model.nodesets.compute_node_sets`, with the coarse bone mask = the fine bone
  voxels that lie on the kept lattice (the same "common points" rule as for the nodes; needs
  ``model.bone_ijk``). Without ``bone_ijk`` the two surfaces fall back to the rule below.
* every other set (masks from the config): a coarse node is in the set when a fine node of the
  set lies in its closed coarse cell, i.e. within ``factor / 2`` fine voxels of it in-plane, on
  the same slice. For even factors a fine node half-way between two coarse nodes belongs to both
  cells. Thin regions therefore survive coarsening; a set that becomes empty is logged.
* tissue sets (:data:`TISSUE_SETS`: the aponeurosis of ``segment.aponeurosis_mask``) describe
  what a node *is*, like its tissue code: a coarse node is in the set when the fine node it keeps
  is (the paper's "common points" rule), so their volumes converge with the resolution.

Tissue, muscle id and fibre of a coarse node are those of the fine node it keeps.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from ..errors import InputError
from .model import Model
from .nodesets import GEOMETRIC_SETS, compute_node_sets, index_volume

_LOG = logging.getLogger(__name__)


#: node sets that describe tissue (carried by the kept node, not by coarse cell)
TISSUE_SETS = ("aponeurosis",)


def lattice_offsets(ijk, factor: int) -> tuple[int, int]:
    """In-plane lattice offsets (i0, j0) that centre the kept lattice on the node cloud.

    Parameters
    ----------
    ijk : (N, 3) int
        Fine voxel indices of the nodes.
    factor : int
        Coarsening factor (≥ 1).

    Returns
    -------
    (i0, j0) : tuple of int, each in ``0..factor-1``
    """
    ijk = np.asarray(ijk, dtype=np.int64)
    out = []
    for a in (0, 1):
        lo, hi = int(ijk[:, a].min()), int(ijk[:, a].max())
        out.append((lo + ((hi - lo) % factor) // 2) % factor)
    return out[0], out[1]


def coarse_cells_containing(ijk_fine, factor: int, offset, coarse_index: np.ndarray) -> np.ndarray:
    """Coarse nodes whose closed coarse cell contains at least one of the given fine voxel centres.

    Parameters
    ----------
    ijk_fine : (n, 3) int
        Fine voxel indices.
    factor : int
        In-plane coarsening factor.
    offset : (2,) int
        Lattice offsets (i0, j0).
    coarse_index : (Ic, Jc, K) int
        Dense coarse index volume (-1 = no node), see :func:`~pixmuscle.model.nodesets.index_volume`.

    Returns
    -------
    (m,) int64
        Sorted unique coarse node indices.
    """
    ijk_fine = np.asarray(ijk_fine, dtype=np.int64).reshape(-1, 3)
    per_axis = []
    for a in (0, 1):
        t = ijk_fine[:, a] - int(offset[a])
        lo = t // factor
        r = t - lo * factor                                       # 0..factor-1
        per_axis.append(((lo, 2 * r <= factor), (lo + 1, 2 * (factor - r) <= factor)))
    found = []
    k = ijk_fine[:, 2]
    for ca, va in per_axis[0]:                                    # at most 2 × 2 candidate cells
        for cb, vb in per_axis[1]:
            ok = (va & vb & (ca >= 0) & (ca < coarse_index.shape[0]) & (cb >= 0) & (cb < coarse_index.shape[1])
                  & (k >= 0) & (k < coarse_index.shape[2]))
            idx = coarse_index[ca[ok], cb[ok], k[ok]]
            found.append(idx[idx >= 0])
    return np.unique(np.concatenate(found)).astype(np.int64)


def _on_lattice(ijk: np.ndarray, factor: int, offset) -> np.ndarray:
    return ((ijk[:, 0] - offset[0]) % factor == 0) & ((ijk[:, 1] - offset[1]) % factor == 0)


def _to_coarse(ijk: np.ndarray, factor: int, offset) -> np.ndarray:
    c = ijk.astype(np.int64).copy()
    c[:, 0] = (c[:, 0] - offset[0]) // factor
    c[:, 1] = (c[:, 1] - offset[1]) // factor
    return c


def coarsen_model(model: Model, factor: int = 2, *, offset: tuple[int, int] | None = None) -> Model:
    """Coarse model: keep every ``factor``-th pixel in-plane, all slices (paper §4.2, Fig. 9b).

    Parameters
    ----------
    model : Model
        Fine (or already coarsened) model.
    factor : int
        In-plane coarsening factor, ≥ 1 (paper: 2). 1 returns a copy.
    offset : (i0, j0), optional
        Lattice offsets in ``0..factor-1``; default :func:`lattice_offsets`.

    Returns
    -------
    Model
        ``spacing`` × (factor, factor, 1), ``coarsen_factor`` × factor, kept nodes at their fine
        coordinates, node sets recomputed (see the module docstring).

    Raises
    ------
    InputError
        Bad factor or offset, or no node left on the coarse lattice.
    """
    if isinstance(factor, bool) or not isinstance(factor, (int, np.integer)) or factor < 1:
        raise InputError(f"coarsen factor: expected an integer ≥ 1, got {factor!r}")
    f = int(factor)
    ijk = np.asarray(model.ijk, dtype=np.int64)
    if f == 1:
        return dataclasses.replace(model, sets={k: np.asarray(v).copy() for k, v in model.sets.items()})
    if offset is None:
        offset = lattice_offsets(ijk, f)
    offset = tuple(int(o) for o in offset)
    if len(offset) != 2 or not all(0 <= o < f for o in offset):
        raise InputError(f"coarsen offset: expected two integers in 0..{f - 1}, got {offset}")

    keep = _on_lattice(ijk, f, offset)
    if not keep.any():
        raise InputError(f"coarsen: no node lies on the coarse lattice (factor {f}, offset {offset}); the model is "
                         "thinner than the coarse spacing")
    ijk_c = _to_coarse(ijk[keep], f, offset)
    scale = np.array([f, f, 1])
    shape = np.asarray(model.shape, dtype=np.int64)
    shape_c = np.array([(shape[0] - offset[0] + f - 1) // f, (shape[1] - offset[1] + f - 1) // f, shape[2]], np.int64)
    spacing_c = np.asarray(model.spacing, float) * scale
    origin_c = np.asarray(model.origin, float) + np.array([offset[0], offset[1], 0]) * np.asarray(model.spacing, float)

    bone_c = None
    bone_mask = None
    if model.bone_ijk is not None:
        b = np.asarray(model.bone_ijk, dtype=np.int64).reshape(-1, 3)
        bone_c = _to_coarse(b[_on_lattice(b, f, offset)], f, offset)
        bone_mask = np.zeros(tuple(shape_c), dtype=bool)
        bone_mask[bone_c[:, 0], bone_c[:, 1], bone_c[:, 2]] = True
    sets = compute_node_sets(ijk_c, shape_c, bone_mask)

    by_cell = [k for k in model.sets if k not in GEOMETRIC_SETS and k not in TISSUE_SETS]
    kept = np.cumsum(keep) - 1  # fine node index → coarse node index (where kept)
    for name in TISSUE_SETS:
        if name in model.sets:
            fine = np.asarray(model.sets[name], dtype=np.int64)
            sets[name] = kept[fine[keep[fine]]].astype(np.int64)
    if model.bone_ijk is None:
        _LOG.warning("coarsen: the model has no bone voxels (grid/bone_ijk); bone_surface and outer_surface are "
                     "carried over from the fine sets by coarse cell instead of recomputed")
        by_cell = ["bone_surface", "outer_surface", *by_cell]
    if by_cell:
        coarse_index = index_volume(ijk_c, shape_c)
        for name in by_cell:
            fine = np.asarray(model.sets.get(name, []), dtype=np.int64)
            sets[name] = coarse_cells_containing(ijk[fine], f, offset, coarse_index)
    for name, fine in model.sets.items():
        if len(fine) and name in sets and not len(sets[name]):
            _LOG.warning("coarsen: node set '%s' (%d fine nodes) is empty on the coarse grid", name, len(fine))

    _LOG.info("coarse model (factor %d, offset %s): %d of %d nodes kept, spacing %s cm", f, offset,
              ijk_c.shape[0], ijk.shape[0], np.round(spacing_c, 5).tolist())
    return Model(
        X=np.asarray(model.X, float)[keep].copy(), ijk=ijk_c.astype(np.int32),
        tissue=np.asarray(model.tissue)[keep].copy(), muscle_id=np.asarray(model.muscle_id)[keep].copy(),
        fiber=np.asarray(model.fiber, float)[keep].copy(), muscle_names=list(model.muscle_names),
        spacing=spacing_c, origin=origin_c, shape=shape_c, rotation=np.asarray(model.rotation, float).copy(),
        sets=sets, coarsen_factor=int(model.coarsen_factor) * f,
        bone_ijk=bone_c.astype(np.int32) if bone_c is not None else None,
    )

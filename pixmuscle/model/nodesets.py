"""Named node sets of a pixel-point model: model ends, extreme planes, bone and outer surfaces.

Every set is an ``int64`` array of node indices, sorted ascending. Neighbourhoods are taken on
the voxel grid through the 6 **faces** of a voxel (6-connectivity): two voxels are neighbours
when they differ by one in exactly one index. Edge and corner contacts do not count, which
matches the integration cells of the model (axis-aligned boxes that share faces, see
docs/architecture.md, "Model frame").

Sets (names fixed, see :data:`GEOMETRIC_SETS`):

``z_min``, ``z_max``
    nodes on the first / last slice (axis 2) that holds nodes;
``x_min``, ``x_max``, ``y_min``, ``y_max``
    nodes on the extreme grid planes of the node cloud along axis 0 / 1;
``bone_surface``
    nodes with at least one face neighbour that is a bone voxel;
``outer_surface``
    nodes with at least one face neighbour that is neither a node nor bone (background, or
    outside the grid). A node can be in both surfaces. The end slices are part of the outer
    surface.

plus one set per extra mask: the nodes whose voxel lies in the mask.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from ..errors import InputError
from .tissues import BONE

#: names of the sets computed from the geometry alone (recomputed on coarsening)
GEOMETRIC_SETS = ("z_min", "z_max", "x_min", "x_max", "y_min", "y_max", "bone_surface", "outer_surface")

#: the 6 face-neighbour offsets
FACE_OFFSETS = np.array([[-1, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0], [0, 0, -1], [0, 0, 1]], dtype=np.int64)


def _check_ijk(ijk, shape) -> tuple[np.ndarray, tuple[int, int, int]]:
    ijk = np.asarray(ijk)
    shape = tuple(int(s) for s in np.asarray(shape).ravel())
    if ijk.ndim != 2 or ijk.shape[1] != 3:
        raise InputError(f"node indices: expected an (N, 3) array, got shape {ijk.shape}")
    if len(shape) != 3 or min(shape) < 1:
        raise InputError(f"grid shape: expected 3 positive integers, got {shape}")
    if ijk.dtype.kind not in "iu":
        raise InputError(f"node indices: expected integers, got dtype {ijk.dtype}")
    ijk = ijk.astype(np.int64)
    if ijk.size and ((ijk < 0).any() or (ijk >= np.array(shape)).any()):
        raise InputError(f"node indices: some lie outside the grid of shape {shape}")
    return ijk, shape


def index_volume(ijk, shape, pad: int = 0) -> np.ndarray:
    """Dense index volume: ``vol[i+pad, j+pad, k+pad] = n`` for node n at (i, j, k), else -1.

    Parameters
    ----------
    ijk : (N, 3) int
        Voxel indices of the nodes.
    shape : (3,) int
        Grid shape.
    pad : int
        Width of a -1 border added on every side (lets neighbour look-ups step off the grid).

    Returns
    -------
    (I+2 pad, J+2 pad, K+2 pad) int32 or int64

    Raises
    ------
    InputError
        Indices outside the grid, or two nodes on the same voxel.
    """
    ijk, shape = _check_ijk(ijk, shape)
    n = ijk.shape[0]
    dtype = np.int32 if n < np.iinfo(np.int32).max else np.int64
    vol = np.full(tuple(s + 2 * pad for s in shape), -1, dtype=dtype)
    p = ijk + pad
    vol[p[:, 0], p[:, 1], p[:, 2]] = np.arange(n, dtype=dtype)
    if np.count_nonzero(vol >= 0) != n:
        raise InputError("node indices: two or more nodes share a voxel")
    return vol


def _bone_mask(labels_or_bone_mask, shape) -> np.ndarray:
    if labels_or_bone_mask is None:
        return np.zeros(shape, dtype=bool)
    a = np.asarray(labels_or_bone_mask)
    if a.shape != shape:
        raise InputError(f"bone mask / labels: expected shape {shape} (the grid), got {a.shape}")
    if a.dtype == bool:
        return a
    if a.dtype.kind not in "iu":
        raise InputError(f"bone mask / labels: expected a bool mask or integer tissue codes, got dtype {a.dtype}")
    return a == BONE


def _check_set_name(name) -> None:
    if not isinstance(name, str) or not name or "/" in name or name.strip() != name:
        raise InputError(f"node set name {name!r}: expected a non-empty name without '/' or surrounding spaces")
    if name in GEOMETRIC_SETS:
        raise InputError(f"node set name {name!r}: clashes with a built-in set ({', '.join(GEOMETRIC_SETS)})")


def face_neighbour_flags(ijk, shape, bone_mask) -> tuple[np.ndarray, np.ndarray]:
    """Which nodes touch bone, and which touch empty space, through a voxel face.

    Parameters
    ----------
    ijk : (N, 3) int
        Voxel indices of the nodes (unique).
    shape : (3,) int
        Grid shape.
    bone_mask : (I, J, K) bool
        Bone voxels (never nodes).

    Returns
    -------
    touches_bone, touches_empty : (N,) bool
        ``touches_empty``: a face neighbour is neither a node nor bone (outside the grid counts
        as empty).
    """
    ijk, shape = _check_ijk(ijk, shape)
    occ = index_volume(ijk, shape, pad=1) >= 0          # node occupancy, padded by one
    occ_shape = occ.shape
    bone = np.zeros_like(occ)
    bone[1:-1, 1:-1, 1:-1] = bone_mask
    if (occ & bone).any():
        raise InputError("node sets: a node lies on a bone voxel")
    occ, bone = occ.ravel(), bone.ravel()
    strides = np.array([occ_shape[1] * occ_shape[2], occ_shape[2], 1], dtype=np.int64)
    lin = (ijk + 1) @ strides                            # flat index of each node in the padded grid
    touches_bone = np.zeros(ijk.shape[0], dtype=bool)
    touches_empty = np.zeros(ijk.shape[0], dtype=bool)
    for d in FACE_OFFSETS:                               # 6 shifts, vectorised over nodes
        q = lin + int(d @ strides)
        nb_node = occ[q]
        nb_bone = bone[q]
        touches_bone |= nb_bone
        touches_empty |= ~(nb_node | nb_bone)
    return touches_bone, touches_empty


def compute_node_sets(ijk, shape, labels_or_bone_mask=None,
                      extra_masks: Mapping[str, np.ndarray] | None = None) -> dict[str, np.ndarray]:
    """Compute the named node sets of a pixel-point model.

    Parameters
    ----------
    ijk : (N, 3) int
        Voxel index of each node in the grid (unique).
    shape : (3,) int
        Grid shape (I, J, K).
    labels_or_bone_mask : (I, J, K) bool or int, optional
        Bone voxels: a bool mask, or an integer volume of tissue codes (bone = 4, see
        :mod:`pixmuscle.model.tissues`). ``None``: no bone (``bone_surface`` is empty).
    extra_masks : mapping of str → (I, J, K) array, optional
        Extra sets: the nodes whose voxel is non-zero in the mask.

    Returns
    -------
    dict of str → (n,) int64
        The sets listed in the module docstring plus one per extra mask, each sorted.

    Raises
    ------
    InputError
        Bad shapes, a node on a bone voxel, or a mask name that clashes with a built-in set.
    """
    ijk, shape = _check_ijk(ijk, shape)
    bone = _bone_mask(labels_or_bone_mask, shape)
    sets: dict[str, np.ndarray] = {}
    n = ijk.shape[0]
    for axis, name in enumerate("xyz"):
        if n == 0:
            sets[f"{name}_min"] = sets[f"{name}_max"] = np.zeros(0, np.int64)
            continue
        c = ijk[:, axis]
        sets[f"{name}_min"] = np.flatnonzero(c == c.min()).astype(np.int64)
        sets[f"{name}_max"] = np.flatnonzero(c == c.max()).astype(np.int64)
    touches_bone, touches_empty = face_neighbour_flags(ijk, shape, bone)
    sets["bone_surface"] = np.flatnonzero(touches_bone).astype(np.int64)
    sets["outer_surface"] = np.flatnonzero(touches_empty).astype(np.int64)
    sets = {k: sets[k] for k in GEOMETRIC_SETS}
    for name, mask in (extra_masks or {}).items():
        _check_set_name(name)
        m = np.asarray(mask)
        if m.shape != shape:
            raise InputError(f"mask '{name}': expected shape {shape} (the label grid), got {m.shape}")
        sets[name] = np.flatnonzero(m[ijk[:, 0], ijk[:, 1], ijk[:, 2]] != 0).astype(np.int64)
    return sets

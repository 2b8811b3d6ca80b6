"""Resampling images between grids related by their voxel -> world affines.

Two grids (e.g. a DTI and an anatomical MRI) usually differ in resolution, field of view and
sometimes axis order; what relates them is the affine of each, never the array indices. A
target voxel centre ``x = A_dst @ ijk_dst`` is looked up in the source at the fractional index
``ijk_src = A_src^-1 @ x``.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import map_coordinates

from pixmuscle.errors import InputError


def _check_affine(a, name):
    a = np.asarray(a, dtype=float)
    if a.shape != (4, 4) or not np.all(np.isfinite(a)):
        raise InputError(f"{name}: expected a finite (4, 4) affine, got shape {a.shape}")
    if abs(np.linalg.det(a[:3, :3])) < 1e-12 * max(np.abs(a[:3, :3]).max(), 1e-300) ** 3:
        raise InputError(f"{name}: the affine is singular (voxel axes are linearly dependent)")
    return a


def source_coordinates(src_affine, dst_shape, dst_affine, k) -> np.ndarray:
    """Fractional source indices (3, I, J) of the voxel centres of target slice ``k``."""
    m = np.linalg.solve(src_affine, dst_affine)
    ii, jj = np.meshgrid(np.arange(dst_shape[0]), np.arange(dst_shape[1]), indexing="ij")
    idx = np.stack([ii, jj, np.full_like(ii, k), np.ones_like(ii)]).reshape(4, -1).astype(float)
    return (m @ idx)[:3].reshape((3,) + tuple(dst_shape[:2]))


def resample_to_grid(data, src_affine, dst_shape, dst_affine, order: int = 1, *, cval: float = 0.0,
                     name: str = "image") -> tuple[np.ndarray, np.ndarray]:
    """Interpolate an image (and each of its channels) onto another grid.

    Parameters
    ----------
    data : (I, J, K) or (I, J, K, C) array_like
        Source image; channels (trailing axis) are interpolated independently.
    src_affine, dst_affine : (4, 4) array_like
        Voxel index -> world (same length unit for both, cm in pixmuscle).
    dst_shape : (I', J', K') tuple of int
        Target grid shape.
    order : int
        Spline order of :func:`scipy.ndimage.map_coordinates` (0 nearest, 1 trilinear, 3
        cubic). Linear interpolation reproduces fields that are linear in world position
        exactly inside the source grid.
    cval : float
        Value of target voxels outside the source field of view.
    name : str
        Used in error messages.

    Returns
    -------
    out : (I', J', K'[, C]) ndarray
        Resampled image (float64; ``cval`` outside the source field of view).
    covered : (I', J', K') bool ndarray
        Target voxels whose centre lies inside the source field of view (within half a voxel
        of the source grid's outermost voxel centres; values there use edge extension).

    Raises
    ------
    InputError
        Bad shapes or affines, or when no target voxel lies in the source field of view.
    """
    data = np.asarray(data)
    if data.ndim not in (3, 4):
        raise InputError(f"{name}: expected a 3-D or 4-D array, got shape {data.shape}")
    src_affine = _check_affine(src_affine, f"{name} source affine")
    dst_affine = _check_affine(dst_affine, f"{name} target affine")
    dst_shape = tuple(int(n) for n in dst_shape)
    if len(dst_shape) != 3 or min(dst_shape) < 1:
        raise InputError(f"{name}: target shape must be 3 positive ints, got {dst_shape}")
    chans = data.reshape(data.shape[:3] + (-1,)).astype(float)
    out = np.full(dst_shape + (chans.shape[3],), float(cval))
    covered = np.zeros(dst_shape, dtype=bool)
    n = np.array(data.shape[:3], dtype=float)
    for k in range(dst_shape[2]):
        c = source_coordinates(src_affine, dst_shape, dst_affine, k)
        inside = np.all((c >= -0.5 - 1e-9) & (c <= (n - 0.5 + 1e-9)[:, None, None]), axis=0)
        covered[:, :, k] = inside
        if not inside.any():
            continue
        pts = c[:, inside]
        for ch in range(chans.shape[3]):
            out[:, :, k, ch][inside] = map_coordinates(chans[..., ch], pts, order=order, mode="nearest")
    if not covered.any():
        raise InputError(
            f"{name}: the source and target fields of view do not overlap (source voxel centres span "
            f"{_extent(src_affine, data.shape[:3])}, target {_extent(dst_affine, dst_shape)})"
        )
    return out.reshape(dst_shape + data.shape[3:]), covered


def _extent(affine, shape):
    corners = np.array(np.meshgrid(*[[0, n - 1] for n in shape], indexing="ij")).reshape(3, -1)
    w = affine[:3, :3] @ corners + affine[:3, 3:4]
    return "x {:.2f}..{:.2f}, y {:.2f}..{:.2f}, z {:.2f}..{:.2f}".format(
        *np.ravel(np.column_stack([w.min(axis=1), w.max(axis=1)])))


def resample_labels(labels, src_affine, dst_shape, dst_affine, *, fill: int = 0,
                    name: str = "labels") -> np.ndarray:
    """Nearest-neighbour resampling of a label or mask image onto another grid.

    Label values are copied, never averaged; target voxels outside the source field of view
    get ``fill``. Returns an array of ``labels.dtype`` (bool masks stay bool) and shape
    ``dst_shape``.
    """
    labels = np.asarray(labels)
    if labels.ndim != 3:
        raise InputError(f"{name}: expected a 3-D label image, got shape {labels.shape}")
    src = labels.astype(np.float64)
    out, covered = resample_to_grid(src, src_affine, dst_shape, dst_affine, order=0, cval=fill, name=name)
    return np.where(covered, np.rint(out), fill).astype(labels.dtype)

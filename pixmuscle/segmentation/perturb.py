"""A segmentation's boundaries moved within their partial volume: a smooth random in-plane warp of the labels.

A segmented boundary is known to within about a voxel: the level set's zero crossing lies somewhere
inside the voxels it cuts (partial volume), and where exactly depends on noise, contrast and the
level-set weights. One realisation of that uncertainty moves every boundary by a smooth random
in-plane displacement ``u(x)`` of at most ``max_voxels`` voxels:

``labels'(x) = labels(x + u(x))`` (nearest voxel), ``u = max_voxels · g / max(1, |g|)``,

where ``g = (g_0, g_1)`` are two independent zero-mean, unit-variance smooth random fields
(:func:`pixmuscle.synth.noise.smooth_field`, sums of random plane waves with correlation length
``length_cm``, evaluated at the voxel centres in cm, so a realisation does not depend on the grid's
resolution). Every label (tissue, muscle id, node-set mask) moves with the same ``u``, so the
segmentation stays consistent. The displacement is in-plane (grid axes 0 and 1) because the
segmentation is found slice by slice (paper §4.1): the slices are 3–6 × thicker than the pixels, and
a through-plane boundary shift of one slice would be a different, much larger uncertainty.

The bound, in the frame of voxel cells: a voxel takes a new label only when a cell of that label lies
within ``|u(x)| ≤ max_voxels`` voxels of its centre, i.e. when the moved boundary has passed its centre.
A boundary at a cell face is half a voxel from the centres on either side, so ``max_voxels ≤ 0.5``
moves no voxel; ``1`` lets the boundary sit anywhere within the boundary voxels of either side.
"""

from __future__ import annotations

import numpy as np

from pixmuscle.errors import InputError
from pixmuscle.synth.noise import smooth_field

__all__ = ["boundary_displacement", "warp_labels"]


def boundary_displacement(shape, affine, max_voxels: float, length_cm: float, rng: np.random.Generator) -> np.ndarray:
    """A smooth random in-plane displacement field, at most ``max_voxels`` long at every voxel.

    Parameters
    ----------
    shape : tuple of 3 int
        Grid ``(I, J, K)``.
    affine : (4, 4) array_like
        Voxel index → cm.
    max_voxels : float
        Largest displacement, voxels (in-plane).
    length_cm : float
        Correlation length of the field, cm.
    rng : numpy.random.Generator

    Returns
    -------
    (I, J, K, 2) ndarray
        Displacement along grid axes 0 and 1, in voxels.
    """
    if max_voxels < 0 or not length_cm > 0:
        raise InputError(f"boundary perturbation: expected max_voxels ≥ 0 and length_cm > 0, got {max_voxels}, "
                         f"{length_cm}")
    shape = tuple(int(n) for n in shape)
    fields = [smooth_field(rng, length_cm=(length_cm,) * 3) for _ in range(2)]
    a = np.asarray(affine, float)
    ij = np.stack(np.meshgrid(np.arange(shape[0]), np.arange(shape[1]), indexing="ij"), axis=-1).reshape(-1, 2)
    g = np.empty(shape + (2,))
    for k in range(shape[2]):  # one slice at a time bounds the memory of the plane-wave sums
        ijk = np.column_stack([ij, np.full(len(ij), k)]).astype(float)
        pts = ijk @ a[:3, :3].T + a[:3, 3]
        g[:, :, k] = np.stack([f(pts) for f in fields], axis=-1).reshape(shape[0], shape[1], 2)
    norm = np.linalg.norm(g, axis=-1, keepdims=True)
    return float(max_voxels) * g / np.maximum(1.0, norm)


def warp_labels(volumes, displacement) -> list[np.ndarray]:
    """Label volumes sampled at ``x + u(x)`` (nearest voxel, clamped to the grid).

    Parameters
    ----------
    volumes : sequence of (I, J, K) or (I, J, K, C) arrays
        Labels, ids, masks (any dtype); all moved by the same field.
    displacement : (I, J, K, 2) array_like
        In-plane displacement, voxels (:func:`boundary_displacement`).

    Returns
    -------
    list of ndarray
        Same shapes and dtypes as ``volumes``.
    """
    u = np.asarray(displacement, float)
    shape = u.shape[:3]
    i, j, k = np.meshgrid(*(np.arange(n) for n in shape), indexing="ij")
    si = np.clip(np.rint(i + u[..., 0]), 0, shape[0] - 1).astype(np.intp)
    sj = np.clip(np.rint(j + u[..., 1]), 0, shape[1] - 1).astype(np.intp)
    out = []
    for v in volumes:
        v = np.asarray(v)
        if v.shape[:3] != shape:
            raise InputError(f"warp_labels: volume of shape {v.shape}, expected the grid {shape}")
        out.append(v[si, sj, k])
    return out

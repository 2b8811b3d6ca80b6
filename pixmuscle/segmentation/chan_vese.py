"""Two-phase multichannel Chan–Vese segmentation (Chan & Vese 2001; Chan, Sandberg & Vese 2000).

Minimises::

    mu * length(C) + nu * area(inside)
      + (1/N) sum_i [ lambda1_i int_inside (u_i - c1_i)**2 + lambda2_i int_outside (u_i - c2_i)**2 ]

over the contour ``C = {phi = 0}`` (inside: ``phi > 0``) and the channel means ``c1``, ``c2``
with the semi-implicit finite-difference scheme described in :mod:`.levelset`. With one channel
in 2-D, ``nu = 0`` and no reinitialisation this is the scheme of scikit-image's ``chan_vese``
(same curvature discretisation, Dirac, sharp Heaviside for the means and stopping rule);
intensities are *not* rescaled here — ``lambda``'s scale is that of ``u**2``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pixmuscle.errors import InputError
from pixmuscle.segmentation.levelset import (
    checkerboard_level_set,
    disk_level_set,
    evolve,
)

__all__ = ["ChanVeseResult", "chan_vese", "initial_level_set"]


@dataclass
class ChanVeseResult:
    """Outcome of :func:`chan_vese`.

    Attributes
    ----------
    segmentation : ndarray of bool, spatial shape
        ``phi > 0``.
    phi : ndarray of float64, spatial shape
        Final level set.
    c1, c2 : ndarray of float64, shape ``(N,)``
        Channel means inside / outside.
    n_iter : int
    converged : bool
        Whether the stopping tolerance was met before ``max_iter``.
    """

    segmentation: np.ndarray
    phi: np.ndarray
    c1: np.ndarray
    c2: np.ndarray
    n_iter: int
    converged: bool


def initial_level_set(init, shape, spacing=None):
    """Initial level set from a name or an array.

    Parameters
    ----------
    init : {"checkerboard", "disk", "small disk"} or ndarray
        ``"checkerboard"``: ``prod sin(pi x / 5)``; ``"disk"``: ball of half the smallest extent
        around the centre; ``"small disk"``: half that radius. An array is used as it is
        (positive = inside). (:func:`chan_vese` also accepts ``"mean"``.)
    shape : tuple of int
        Spatial shape.
    spacing : sequence of float, optional
        Voxel size (for the disk radius).

    Returns
    -------
    phi : ndarray of float64, shape ``shape``
    """
    if isinstance(init, str):
        if init == "mean":
            raise InputError("init='mean' needs the image: use chan_vese(..., init='mean')")
        if init == "checkerboard":
            return checkerboard_level_set(shape, 5.0)
        if init in ("disk", "small disk"):
            phi = disk_level_set(shape, spacing=spacing)
            return phi if init == "disk" else 2.0 * phi - 1.0
        raise InputError(f"init: unknown initial level set {init!r}; expected 'checkerboard', "
                         "'disk', 'small disk' or an array")
    phi = np.asarray(init, dtype=float)
    if phi.shape != tuple(shape):
        raise InputError(f"init: initial level set has shape {phi.shape}, expected {tuple(shape)}"
                         " (the image's spatial shape)")
    return phi


def _as_channels(image, channel_axis):
    image = np.asarray(image)
    if channel_axis is None:
        image = image[None]
    else:
        image = np.moveaxis(image, channel_axis, 0)
    if image.ndim not in (3, 4):
        raise InputError(f"image: expected a 2-D (Y, X) or 3-D (Z, Y, X) image per channel, got "
                         f"spatial shape {image.shape[1:]}")
    if not np.issubdtype(image.dtype, np.number) or np.iscomplexobj(image):
        raise InputError(f"image: expected real numbers, got dtype {image.dtype}")
    image = image.astype(np.float64)
    if not np.isfinite(image).all():
        raise InputError("image: contains NaN or infinite values")
    return image


def _per_channel(value, n, name):
    arr = np.asarray(value, dtype=float)
    try:
        arr = np.broadcast_to(arr, (n,))
    except ValueError:
        raise InputError(f"{name}: expected a number or {n} numbers (one per channel), "
                         f"got shape {arr.shape}") from None
    if (arr < 0).any():
        raise InputError(f"{name}: expected values >= 0, got {arr}")
    return arr


def _mean_init(u, mask, lam):
    # +1 / -1 split at the mean along the first principal axis of the weighted channels
    m = np.ones(u.shape[1:], bool) if mask is None else mask
    x = u[:, m] * np.sqrt(lam)[:, None]
    x = x - x.mean(axis=1, keepdims=True)
    if x.shape[0] == 1:
        axis = np.ones(1)
    else:
        axis = np.linalg.eigh(x @ x.T)[1][:, -1]
        axis = axis * np.sign(axis[np.argmax(np.abs(axis))])
    proj = np.tensordot(axis * np.sqrt(lam), u - (u[:, m].mean(axis=1)).reshape(
        (-1,) + (1,) * (u.ndim - 1)), axes=1)
    return np.where(proj > 0, 1.0, -1.0)


def chan_vese(image, *, mu=0.25, nu=0.0, lambda1=1.0, lambda2=1.0, dt=0.5, eps=1.0, tol=1e-3,
              max_iter=500, init="checkerboard", reinit_every=0, spacing=None,
              channel_axis=None, mask=None, stop="phi", window=5, energy_scale="range"):
    """Two-phase (multichannel) Chan–Vese segmentation.

    Parameters
    ----------
    image : ndarray
        ``(Y, X)`` or ``(Z, Y, X)``; with ``channel_axis`` one more axis of ``N`` channels.
        Intensities are used as given (``lambda`` multiplies squared intensity differences).
    mu : float
        Weight of the contour length, ``>= 0``.
    nu : float
        Weight of the inside area (Chan & Vese's ``nu``; positive shrinks the inside).
    lambda1, lambda2 : float or sequence of float
        Data weights inside / outside, per channel; the data term is averaged over channels.
    dt : float
        Time step of the semi-implicit scheme (scikit-image's convention, see
        :mod:`.levelset`).
    eps : float
        Width of the regularised Dirac, in level-set units.
    tol : float
        Stop when the RMS change of ``phi`` in one sweep is ``<= tol``.
    max_iter : int
        Iteration limit.
    init : str or ndarray
        See :func:`initial_level_set`; or ``"mean"``: ``+1`` where the image (its first
        principal component, ``lambda``-weighted, for several channels) is above its mean over
        ``mask``, ``-1`` elsewhere (a good start for intensity classes; no spatial prior).
    reinit_every : int
        Reinitialise ``phi`` to a signed distance every so many sweeps (0: never).
    spacing : sequence of float, optional
        Voxel size per spatial axis for the curvature (default 1 on every axis).
    channel_axis : int, optional
        Axis of ``image`` holding the channels; ``None`` for a single-channel image.
    mask : ndarray of bool, optional
        Spatial mask: means and data force only over ``mask``; the result is ``False`` outside.
    stop : {"phi", "regions"}
        Stopping test: RMS level-set change (scikit-image's) or fraction of voxels changing
        side over ``window`` sweeps (see :func:`.levelset.evolve`).
    window : int
        Sweeps between region comparisons for ``stop="regions"``.
    energy_scale : {"range", "variance"} or float
        Constant the energy is divided by (same minimisers; sets the time scale of ``dt``):
        ``"range"`` (default) makes one channel on ``[0, 1]`` with ``lambda = 1`` follow
        scikit-image's ``chan_vese`` exactly; see :func:`.levelset.evolve`.

    Returns
    -------
    ChanVeseResult
    """
    u = _as_channels(image, channel_axis)
    n_ch = u.shape[0]
    spatial = u.shape[1:]
    is_2d = len(spatial) == 2
    if spacing is None:
        spacing = np.ones(len(spatial))
    spacing = np.asarray(spacing, dtype=float)
    if spacing.shape != (len(spatial),) or (spacing <= 0).any():
        raise InputError(f"spacing: expected {len(spatial)} positive numbers, got {spacing}")
    for name, v in (("mu", mu), ("dt", dt), ("eps", eps), ("tol", tol)):
        if not np.isfinite(v) or v < 0 or (name in ("dt", "eps") and v == 0):
            raise InputError(f"{name}: expected a finite number {'> 0' if name in ('dt', 'eps') else '>= 0'}"
                             f", got {v!r}")
    if int(max_iter) < 1:
        raise InputError(f"max_iter: expected an integer >= 1, got {max_iter!r}")
    lam1 = _per_channel(lambda1, n_ch, "lambda1")
    lam2 = _per_channel(lambda2, n_ch, "lambda2")
    if mask is not None:
        mask = np.asarray(mask, bool)
        if mask.shape != spatial:
            raise InputError(f"mask: shape {mask.shape}, expected {spatial}")
        if not mask.any():
            raise InputError("mask: empty (no voxel to segment)")
    if isinstance(init, str) and init == "mean":
        phi0 = _mean_init(u, mask, 0.5 * (lam1 + lam2))
    else:
        phi0 = initial_level_set(init, spatial, spacing)
    if is_2d:
        u = u[:, None]
        phi0 = phi0[None]
        spacing = np.concatenate([[1.0], spacing])
        mask = None if mask is None else mask[None]
    lam = np.stack([lam2, lam1])  # region 0 = outside, region 1 = inside
    area = np.array([0.0, float(nu)])
    phi, c, n_iter, converged = evolve(
        u, phi0[None], lam, area, np.array([float(mu)]), dt=dt, eps=eps, tol=tol,
        max_iter=int(max_iter), reinit_every=int(reinit_every), spacing=spacing, mask=mask,
        stop=stop, window=int(window), energy_scale=energy_scale)
    phi = phi[0, 0] if is_2d else phi[0]
    seg = phi > 0
    if mask is not None:
        seg &= mask[0] if is_2d else mask
    return ChanVeseResult(seg, phi, c[1].copy(), c[0].copy(), n_iter, converged)

"""Segmentation channels: intensity normalisation and sign-invariant fibre channels (paper §4.1).

Intensity convention (used by every level-set model in the pipeline): the MRI is scaled
robustly to ``[0, 255]`` (the grey levels of the paper's images) and the fibre channels are
fibre features times 255, i.e. on the MRI's range ("the EV data is scaled to be at the similar
level of the MRI intensities", §4.1). The paper's weights ``lambda = 0.02`` and ``mu = 1`` (or
100) are meant on this scale. The solver divides the energy by a constant so that its time
step does not depend on this scale (see :func:`pixmuscle.segmentation.levelset.evolve`).
"""

from __future__ import annotations

import numpy as np

from pixmuscle.errors import InputError
from pixmuscle.imaging.dti import fiber_features

__all__ = ["INTENSITY_MAX", "normalize_intensity", "fiber_channels", "n_fiber_channels"]

#: upper end of the intensity scale of every segmentation channel
INTENSITY_MAX = 255.0

_N_CHANNELS = {"outer": 6, "abs": 3, "canonical": 3}


def normalize_intensity(image, mask=None, percentiles=(0.5, 99.5), scale=INTENSITY_MAX):
    """Robust linear rescaling to ``[0, scale]``.

    The ``percentiles`` of ``image`` (over ``mask`` if given) are mapped to 0 and ``scale``;
    values outside are clipped.

    Parameters
    ----------
    image : ndarray
        Any shape, any units.
    mask : ndarray of bool, optional
        Voxels used for the percentiles.
    percentiles : (float, float)
        Lower and upper percentile, 0..100.
    scale : float
        Output maximum.

    Returns
    -------
    ndarray of float64, same shape, values in ``[0, scale]``
    """
    image = np.asarray(image, dtype=float)
    if not np.isfinite(image).all():
        raise InputError("MRI: contains NaN or infinite values")
    vals = image[mask] if mask is not None else image
    if vals.size == 0:
        raise InputError("normalize_intensity: empty mask")
    lo, hi = np.percentile(vals, percentiles)
    if not hi > lo:
        raise InputError(f"MRI: constant intensity ({lo:g}) between the {percentiles} percentiles;"
                         " nothing to segment")
    return np.clip((image - lo) / (hi - lo), 0.0, 1.0) * scale


def n_fiber_channels(mode):
    """Number of channels :func:`fiber_channels` makes for ``mode``."""
    try:
        return _N_CHANNELS[mode]
    except KeyError:
        raise InputError(f"fiber channel mode {mode!r}: expected one of {sorted(_N_CHANNELS)}") \
            from None


def fiber_channels(v, valid=None, mode="outer", scale=INTENSITY_MAX, channel_axis=0):
    """Fibre-direction channels for the multiphase segmentation, on the MRI's intensity scale.

    Parameters
    ----------
    v : ndarray, shape ``(..., 3)``
        Fibre (principal eigen-) vectors, unit or zero; their signs do not matter.
    valid : ndarray of bool, shape ``v.shape[:-1]``, optional
        Voxels with fibre data; the channels are 0 elsewhere.
    mode : {"outer", "abs", "canonical"}
        ``outer``: the 6 unique components of ``v v^T`` (xx, xy, xz, yy, yz, zz) with the
        off-diagonal ones times ``sqrt(2)``, so that the squared channel distance of two
        directions is ``|v v^T - w w^T|_F**2 = 2 sin(angle)**2`` (sign invariant, continuous,
        rotation invariant); ``canonical``: ``v`` with the sign making ``v_z >= 0`` (the paper's
        ``e1, e2, e3``; discontinuous where ``v_z`` ~ 0); ``abs``: ``|v_i|``.
    scale : float
        Multiplier (the MRI's range).
    channel_axis : int
        Where the channel axis goes in the output (0: ``(F, ...)``; -1: ``(..., F)``).

    Returns
    -------
    ndarray of float64, shape ``(F, ...)`` (default)
    """
    v = np.asarray(v, dtype=float)
    n_fiber_channels(mode)
    f = fiber_features(v, mode=mode)
    if mode == "outer":
        f = f * np.array([1.0, np.sqrt(2), np.sqrt(2), 1.0, np.sqrt(2), 1.0])
    f = f * scale
    if valid is not None:
        f = np.where(np.asarray(valid, bool)[..., None], f, 0.0)
    return np.moveaxis(f, -1, channel_axis)

"""Noisy realisations of a diffusion-tensor image at a given signal-to-noise ratio.

A tensor field ``D`` (mm²/s, world axes) is turned back into the signals of a diffusion acquisition,
``S_g = S_0 exp(−b_g g_gᵀ D g_g)`` with ``S_0 = 1``, the signals get Rician noise (the magnitude of
the signal plus complex Gaussian noise of standard deviation ``σ = S_0 / SNR`` in each of the real
and imaginary channels, as in a magnitude image), and the tensor is fitted again by weighted linear
least squares of ``ln S`` (the log-linear fit, weights ``Ŝ²`` from an ordinary least-squares first
pass: the fit of dipy's ``TensorModel(fit_method="WLS")``, which :mod:`pixmuscle.imaging.dwi` uses
for scanner series). The principal eigenvector of the re-fitted tensor
(:func:`pixmuscle.imaging.dti.principal_eigenvector`) is a fibre direction as it would have come out
of a scan at that SNR.

**SNR** is that of the non-weighted (b = 0) signal, ``S_0 / σ``, the same in every voxel — the
definition of the DTI noise literature (Anderson, MRM 46:1174, 2001; Damon, MRM 60:934, 2008, for
skeletal muscle, where SNR ≥ 25 at b ≈ 500 s/mm² keeps the fibre-direction bias small). Fat's
brighter b = 0 signal and the T2 differences between tissues are not modelled.

To first order the error of the principal eigenvector ``e1`` is
``δe1 = Σ_{j=2,3} (e_jᵀ δD e1) / (λ1 − λj) e_j`` (Anderson 2001), with ``δD`` the fit's error,
whose covariance is ``σ² (Bᵀ diag(S²) B)⁻¹`` for the design matrix ``B`` of :func:`design_matrix`;
tests/test_uncertainty.py checks the Monte-Carlo angular error against that prediction.
"""

from __future__ import annotations

import numpy as np

from pixmuscle.errors import InputError

__all__ = ["acquisition", "design_matrix", "noisy_tensors", "fibre_angle_deg"]

#: voxels fitted at a time (bounds the memory of the (n, 7, 7) normal equations)
CHUNK = 100_000


def acquisition(bvalue: float, n_directions: int, n_b0: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """A single-shell diffusion scheme: ``n_b0`` non-weighted volumes and ``n_directions`` gradients.

    Parameters
    ----------
    bvalue : float
        b-value of the weighted volumes, s/mm².
    n_directions : int
        Gradient directions, spread over the half sphere (a Fibonacci lattice), at least 6.
    n_b0 : int
        Non-weighted volumes, at least 1.

    Returns
    -------
    bvals : (G,) ndarray
        s/mm², ``G = n_b0 + n_directions``.
    gradients : (G, 3) ndarray
        Unit directions (zero rows for b = 0), world axes.
    """
    if n_directions < 6 or n_b0 < 1 or not bvalue > 0:
        raise InputError(f"DTI scheme: need ≥ 6 directions, ≥ 1 b = 0 volume and b > 0, got {n_directions}, "
                         f"{n_b0}, {bvalue}")
    k = np.arange(n_directions) + 0.5
    z = 1.0 - k / n_directions
    phi = np.pi * (3.0 - np.sqrt(5.0)) * k
    r = np.sqrt(1.0 - z**2)
    g = np.vstack([np.zeros((n_b0, 3)), np.column_stack([r * np.cos(phi), r * np.sin(phi), z])])
    return np.r_[np.zeros(n_b0), np.full(n_directions, float(bvalue))], g


def design_matrix(bvals, gradients) -> np.ndarray:
    """Design matrix ``B`` (G, 7) of the log-linear tensor model ``ln S = B · (Dxx, Dyy, Dzz, Dxy, Dxz, Dyz, ln S0)``.

    Parameters
    ----------
    bvals : (G,) array_like
        s/mm².
    gradients : (G, 3) array_like
        Unit directions.
    """
    b = np.asarray(bvals, float)
    g = np.asarray(gradients, float)
    gx, gy, gz = g.T
    return np.column_stack([-b * gx * gx, -b * gy * gy, -b * gz * gz, -2 * b * gx * gy, -2 * b * gx * gz,
                            -2 * b * gy * gz, np.ones_like(b)])


def _params(d: np.ndarray) -> np.ndarray:
    """(n, 3, 3) tensors → (n, 7) model parameters with ln S0 = 0."""
    return np.column_stack([d[:, 0, 0], d[:, 1, 1], d[:, 2, 2], d[:, 0, 1], d[:, 0, 2], d[:, 1, 2],
                            np.zeros(len(d))])


def _tensors(p: np.ndarray) -> np.ndarray:
    """(n, 7) model parameters → (n, 3, 3) symmetric tensors."""
    d = np.empty((len(p), 3, 3))
    for n, (r, c) in enumerate(((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))):
        d[:, r, c] = d[:, c, r] = p[:, n]
    return d


def _fit_wls(signals: np.ndarray, B: np.ndarray, floor: float) -> np.ndarray:
    """Weighted log-linear fit of (n, G) signals → (n, 7) parameters."""
    y = np.log(np.maximum(signals, floor))
    p0 = y @ np.linalg.pinv(B).T                      # ordinary least squares
    w = np.exp(2.0 * (p0 @ B.T))                      # weights Ŝ² (n, G)
    lhs = np.einsum("ng,gi,gj->nij", w, B, B)
    rhs = np.einsum("ng,gi,ng->ni", w, B, y)
    return np.linalg.solve(lhs, rhs[..., None])[..., 0]


def noisy_tensors(tensor, snr: float, rng: np.random.Generator, *, bvals, gradients) -> np.ndarray:
    """One noisy realisation of a tensor field: signals, Rician noise at ``snr``, weighted log-linear fit.

    Parameters
    ----------
    tensor : (..., 3, 3) array_like
        Diffusion tensors, mm²/s, world axes. All-zero tensors (no data) stay zero.
    snr : float
        ``S_0 / σ`` of the non-weighted signal (see the module notes).
    rng : numpy.random.Generator
    bvals, gradients : (G,) and (G, 3) array_like
        The acquisition (:func:`acquisition`, or a scan's own b-values and world-axis gradients).

    Returns
    -------
    (..., 3, 3) ndarray
        The re-fitted tensors, mm²/s.
    """
    d = np.asarray(tensor, float)
    if d.shape[-2:] != (3, 3):
        raise InputError(f"tensors: expected trailing shape (3, 3), got {d.shape}")
    if not snr > 0:
        raise InputError(f"DTI noise: expected an SNR > 0, got {snr}")
    B = design_matrix(bvals, gradients)
    if np.linalg.matrix_rank(B) < 7:
        raise InputError("DTI noise: the acquisition does not determine a tensor (needs b = 0 and ≥ 6 "
                         "non-collinear directions)")
    flat = d.reshape(-1, 3, 3)
    data = np.flatnonzero(np.any(flat != 0, axis=(1, 2)))
    out = np.zeros_like(flat)
    sigma = 1.0 / float(snr)
    for start in range(0, len(data), CHUNK):
        idx = data[start:start + CHUNK]
        s = np.exp(_params(flat[idx]) @ B.T)          # (n, G), S0 = 1
        noisy = np.hypot(s + sigma * rng.standard_normal(s.shape), sigma * rng.standard_normal(s.shape))
        out[idx] = _tensors(_fit_wls(noisy, B, floor=1e-3 * sigma))
    return out.reshape(d.shape)


def fibre_angle_deg(a, b) -> np.ndarray:
    """Angle between fibre directions, degrees in [0, 90] (a fibre has no sign).

    Parameters
    ----------
    a, b : (..., 3) array_like
        Directions (any length; zero vectors give NaN).
    """
    a = np.asarray(a, float)
    b = np.asarray(b, float)
    na, nb = np.linalg.norm(a, axis=-1), np.linalg.norm(b, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        c = np.abs(np.sum(a * b, axis=-1)) / (na * nb)
    return np.degrees(np.arccos(np.clip(c, 0.0, 1.0)))

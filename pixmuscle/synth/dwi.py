"""SYNTHETIC diffusion-weighted series from a known tensor field (for tests and the DWI example).

Signals follow the tensor model S_g = S_0 exp(−b_g g_gᵀ D g_g) with Rician noise of standard
deviation S_0 / SNR; gradients are spread over a half sphere (a Fibonacci lattice); the series is
written in any stored voxel orientation with FSL-convention b-vectors for that orientation
(:func:`pixmuscle.imaging.dwi.world_to_fsl_bvecs`), as dcm2niix would.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from pixmuscle.imaging.dwi import world_to_fsl_bvecs

__all__ = ["gradient_directions", "synthesize_dwi", "write_dwi"]


def gradient_directions(n: int) -> np.ndarray:
    """``n`` unit directions spread over the half sphere z ≥ 0 (Fibonacci lattice), (n, 3)."""
    k = np.arange(n) + 0.5
    z = 1.0 - k / n
    phi = np.pi * (3.0 - np.sqrt(5.0)) * k
    r = np.sqrt(1.0 - z**2)
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def synthesize_dwi(tensor, *, b: float = 500.0, n_directions: int = 30, n_b0: int = 2, s0=1000.0,
                   snr: float | None = None, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Signals of a tensor field.

    Parameters
    ----------
    tensor : (I, J, K, 3, 3) float
        Diffusion tensors, mm²/s, world axes (zero tensors give S = S_0).
    b : float
        b-value of the weighted volumes, s/mm².
    n_directions, n_b0 : int
        Weighted volumes (directions of :func:`gradient_directions`) and non-weighted volumes.
    s0 : float or (I, J, K) array
        Non-weighted signal.
    snr : float, optional
        S_0 / σ of Rician noise (σ from the largest S_0); None: noise free.
    seed : int

    Returns
    -------
    data (I, J, K, G), bvals (G,), gradients (G, 3) in world axes (zero rows for b = 0)
    """
    D = np.asarray(tensor, float)
    g = np.vstack([np.zeros((n_b0, 3)), gradient_directions(n_directions)])
    bvals = np.r_[np.zeros(n_b0), np.full(n_directions, float(b))]
    q = np.einsum("gi,...ij,gj->...g", g, D, g)
    s0 = np.broadcast_to(np.asarray(s0, float), D.shape[:3])
    data = s0[..., None] * np.exp(-bvals * q)
    if snr is not None:
        sigma = float(np.max(s0)) / float(snr)
        rng = np.random.default_rng(seed)
        data = np.hypot(data + sigma * rng.standard_normal(data.shape), sigma * rng.standard_normal(data.shape))
    return data, bvals, g


def write_dwi(prefix, data, affine_cm, bvals, gradients, *, orientation: str = "RAS") -> dict:
    """Write ``{prefix}.nii.gz``, ``{prefix}.bval``, ``{prefix}.bvec`` (FSL convention) in a stored orientation.

    Parameters
    ----------
    prefix : path
        Output path without suffix.
    data : (I, J, K, G) float
        Signals on a grid with voxel → world affine ``affine_cm`` (cm).
    bvals : (G,) ; gradients : (G, 3) world axes
    orientation : str
        Stored voxel axis codes, e.g. ``"RAS"``, ``"LPS"``, ``"PLS"`` (voxels are reordered, the
        affine follows, the b-vectors are written for the stored affine).
    """
    import nibabel as nib
    from nibabel.orientations import apply_orientation, axcodes2ornt, inv_ornt_aff, io_orientation, ornt_transform

    prefix = Path(prefix)
    affine = np.asarray(affine_cm, float).copy()
    affine[:3, :] *= 10.0  # mm
    now = io_orientation(affine)
    tf = ornt_transform(now, axcodes2ornt(tuple(orientation)))
    stored = apply_orientation(np.asarray(data, float), tf)
    stored_affine = affine @ inv_ornt_aff(tf, np.asarray(data).shape[:3])
    img = nib.Nifti1Image(stored.astype(np.float32), stored_affine)
    img.header.set_xyzt_units("mm")
    img.set_sform(stored_affine, code=1)
    img.set_qform(stored_affine, code=1)
    bvecs = world_to_fsl_bvecs(gradients, stored_affine)
    out = {"image": prefix.with_name(prefix.name + ".nii.gz"), "bvals": prefix.with_name(prefix.name + ".bval"),
           "bvecs": prefix.with_name(prefix.name + ".bvec")}
    tmp = out["image"].with_name(f".{out['image'].name}.tmp{os.getpid()}.nii.gz")
    nib.save(img, str(tmp))
    os.replace(tmp, out["image"])
    out["bvals"].write_text(" ".join(f"{v:g}" for v in bvals) + "\n")
    out["bvecs"].write_text("\n".join(" ".join(f"{v + 0.0:.6f}" for v in row) for row in bvecs.T) + "\n")
    return out

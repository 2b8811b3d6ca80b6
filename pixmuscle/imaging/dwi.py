"""Diffusion-weighted images as they come from the scanner: b-values, b-vectors, tensor fit.

A DWI series is a 4-D NIfTI (I, J, K, G) with one volume per gradient, plus the b-values
(``.bval``: G numbers, s/mm²) and gradient directions (``.bvec``: 3 rows of G numbers) that
dcm2niix / FSL write. The tensor is fitted with dipy's :class:`dipy.reconst.dti.TensorModel`
(weighted least squares), a well-kept implementation of the standard model
S_g = S_0 exp(−b_g g_gᵀ D g_g).

**b-vector convention (FSL).** FSL's b-vectors are given in the *voxel* axes of the image as
stored, with the first axis negated when the stored affine has a positive determinant (FSL
works in a radiological voxel frame). In world (scanner) axes of that affine::

    g_world = R · diag(−1, 1, 1) · b_vec   if det(A) > 0,   R · b_vec otherwise,

with R the rotation of the stored affine (columns normalised). :func:`fsl_bvecs_to_world` does
this before the fit, so the fitted tensors have world components (pixmuscle's convention,
:mod:`pixmuscle.imaging.dti`) whatever the voxel order or obliquity of the series; the voxels
are then reordered to the closest canonical orientation like every other image
(:func:`pixmuscle.imaging.nifti.load_volume`).

dipy is an optional dependency (``pip install 'pixmuscle[dwi]'``).
"""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path

import numpy as np

from pixmuscle.errors import InputError

__all__ = ["DWITensorFit", "fit_tensor", "fsl_bvecs_to_world", "load_dwi_tensor", "read_gradients",
           "world_to_fsl_bvecs"]


def _dipy():
    try:
        from dipy.core.gradients import gradient_table
        from dipy.reconst.dti import TensorModel
    except ImportError:
        raise InputError("segment.dwi: fitting diffusion tensors needs dipy; install it with "
                         "pip install 'pixmuscle[dwi]'") from None
    return gradient_table, TensorModel


def _rotation(affine) -> np.ndarray:
    lin = np.asarray(affine, float)[:3, :3]
    return lin / np.linalg.norm(lin, axis=0)


def fsl_bvecs_to_world(bvecs, affine) -> np.ndarray:
    """Gradient directions from FSL's voxel-frame convention to world axes, (G, 3).

    Parameters
    ----------
    bvecs : (G, 3) array_like
        b-vectors as in the ``.bvec`` file (rows = gradients).
    affine : (4, 4) array_like
        The stored affine of the DWI series (before any voxel reordering).
    """
    b = np.asarray(bvecs, float).reshape(-1, 3)
    if np.linalg.det(np.asarray(affine, float)[:3, :3]) > 0:
        b = b * np.array([-1.0, 1.0, 1.0])
    return b @ _rotation(affine).T


def world_to_fsl_bvecs(gradients, affine) -> np.ndarray:
    """Inverse of :func:`fsl_bvecs_to_world`: world directions (G, 3) → FSL b-vectors (G, 3)."""
    b = np.asarray(gradients, float).reshape(-1, 3) @ _rotation(affine)
    if np.linalg.det(np.asarray(affine, float)[:3, :3]) > 0:
        b = b * np.array([-1.0, 1.0, 1.0])
    return b


def read_gradients(bvals_path, bvecs_path, n_volumes: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """b-values (G,) in s/mm² and b-vectors (G, 3) from FSL-style text files (dipy's reader).

    Raises InputError naming the file for unreadable files, mismatched counts, a count that
    differs from ``n_volumes``, or non-unit non-zero b-vectors.
    """
    _dipy()
    from dipy.io.gradients import read_bvals_bvecs

    for p in (bvals_path, bvecs_path):
        if not Path(p).is_file():
            raise InputError(f"{p}: file not found")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            bvals, bvecs = read_bvals_bvecs(str(bvals_path), str(bvecs_path))
    except (OSError, ValueError) as exc:
        raise InputError(f"{bvals_path} / {bvecs_path}: not readable as FSL b-values / b-vectors ({exc})") from None
    bvals = np.atleast_1d(np.asarray(bvals, float))
    bvecs = np.atleast_2d(np.asarray(bvecs, float))
    if not (np.isfinite(bvals).all() and np.isfinite(bvecs).all()):
        raise InputError(f"{bvals_path} / {bvecs_path}: non-finite values")
    if n_volumes is not None and bvals.shape[0] != n_volumes:
        raise InputError(f"{bvals_path}: {bvals.shape[0]} b-values for a series of {n_volumes} volumes")
    norm = np.linalg.norm(bvecs, axis=1)
    bad = (bvals > 50) & (np.abs(norm - 1.0) > 0.05)
    if bad.any():
        raise InputError(f"{bvecs_path}: {int(bad.sum())} diffusion-weighted b-vectors are not unit vectors "
                         f"(norms {norm[bad].min():.3g}..{norm[bad].max():.3g})")
    if (bvals < 0).any():
        raise InputError(f"{bvals_path}: negative b-values")
    return bvals, bvecs


@dataclasses.dataclass
class DWITensorFit:
    """Tensor fit of a DWI series on its grid (canonical voxel order, world components).

    Attributes
    ----------
    tensor : (I, J, K, 3, 3) float
        Diffusion tensor, mm²/s, world axes (0 outside the fit mask).
    fa, md : (I, J, K) float
        Fractional anisotropy (1) and mean diffusivity (mm²/s).
    v1 : (I, J, K, 3) float
        Principal eigenvector (world axes, arbitrary sign; 0 outside the mask).
    affine : (4, 4) float
        Voxel → world, cm.
    b0 : (I, J, K) float
        Mean non-weighted signal.
    """

    tensor: np.ndarray
    fa: np.ndarray
    md: np.ndarray
    v1: np.ndarray
    affine: np.ndarray
    b0: np.ndarray


def fit_tensor(data, bvals, gradients, *, mask=None, b0_threshold: float = 50.0):
    """Fit diffusion tensors voxel by voxel (dipy ``TensorModel``, WLS).

    Parameters
    ----------
    data : (I, J, K, G) array_like
        Signals, one volume per gradient.
    bvals : (G,) array_like
        b-values, s/mm².
    gradients : (G, 3) array_like
        Unit gradient directions in the axes the tensors are wanted in (world).
    mask : (I, J, K) bool, optional
        Voxels to fit (default: mean b0 signal above 10 % of its 99th percentile).
    b0_threshold : float
        b-values at most this are non-weighted.

    Returns
    -------
    tensor (I, J, K, 3, 3), fa (I, J, K), md (I, J, K), v1 (I, J, K, 3), b0 (I, J, K)
    """
    gradient_table, TensorModel = _dipy()
    data = np.asarray(data, float)
    bvals = np.asarray(bvals, float)
    g = np.asarray(gradients, float)
    if data.ndim != 4 or data.shape[3] != bvals.shape[0] or g.shape != (bvals.shape[0], 3):
        raise InputError(f"DWI: {data.shape} signals for {bvals.shape[0]} b-values and {g.shape[0]} b-vectors")
    is_b0 = bvals <= b0_threshold
    if not is_b0.any():
        raise InputError(f"DWI: no non-weighted volume (b ≤ {b0_threshold:g} s/mm²)")
    if np.count_nonzero(~is_b0) < 6:
        raise InputError(f"DWI: {np.count_nonzero(~is_b0)} diffusion-weighted volumes; a tensor needs at least 6")
    b0 = data[..., is_b0].mean(axis=-1)
    if mask is None:
        mask = b0 > 0.1 * max(float(np.percentile(b0, 99)), 1e-300)
    g = np.where(is_b0[:, None], 0.0, g)
    gtab = gradient_table(bvals, bvecs=g, b0_threshold=b0_threshold)
    with warnings.catch_warnings(), np.errstate(all="ignore"):
        warnings.simplefilter("ignore")
        fit = TensorModel(gtab, fit_method="WLS").fit(np.clip(data, 1e-6, None), mask=np.asarray(mask, bool))
        tensor = np.nan_to_num(np.asarray(fit.quadratic_form, float))
        fa = np.nan_to_num(np.asarray(fit.fa, float))
        md = np.nan_to_num(np.asarray(fit.md, float))
        v1 = np.nan_to_num(np.asarray(fit.evecs, float)[..., :, 0])
    return tensor, fa, md, v1, b0


def load_dwi_tensor(image, bvals_path, bvecs_path, *, convention: str = "fsl",
                    b0_threshold: float = 50.0) -> DWITensorFit:
    """Read a DWI series with its gradient files and fit the tensors.

    Parameters
    ----------
    image : path
        4-D NIfTI (I, J, K, G).
    bvals_path, bvecs_path : path
        FSL-style ``.bval`` / ``.bvec`` text files.
    convention : {"fsl", "world"}
        Frame of the b-vectors: FSL's voxel frame (dcm2niix, FSL; see the module notes) or
        world (scanner) axes.
    b0_threshold : float
        b-values at most this (s/mm²) are non-weighted.

    Returns
    -------
    DWITensorFit
        On the series' grid in canonical voxel order, affine in cm.
    """
    import nibabel as nib
    from nibabel.orientations import apply_orientation, inv_ornt_aff, io_orientation

    from pixmuscle.imaging.nifti import UNIT_TO_CM

    image = Path(image)
    if not image.is_file():
        raise InputError(f"{image}: file not found")
    try:
        img = nib.load(str(image))
        data = np.asarray(img.dataobj, dtype=float)
    except Exception as exc:  # nibabel raises several types for unreadable files
        raise InputError(f"{image}: not a readable NIfTI file ({type(exc).__name__}: {exc})") from None
    while data.ndim > 4 and data.shape[3] == 1:
        data = data.reshape(data.shape[:3] + data.shape[4:])
    if data.ndim != 4:
        raise InputError(f"{image}: a DWI series needs a 4-D volume (I, J, K, G), got shape {data.shape}")
    if not np.isfinite(data).all():
        raise InputError(f"{image}: {int((~np.isfinite(data)).sum())} values are NaN or infinite")
    unit = img.header.get_xyzt_units()[0]
    if unit not in UNIT_TO_CM:
        raise InputError(f"{image}: unsupported spatial unit {unit!r}; expected mm, meter or micron")
    stored = np.asarray(img.affine, float)
    bvals, bvecs = read_gradients(bvals_path, bvecs_path, n_volumes=data.shape[3])
    if convention == "fsl":
        g = fsl_bvecs_to_world(bvecs, stored)
    elif convention == "world":
        g = bvecs
    else:
        raise InputError(f"segment.dwi.bvecs_convention: expected 'fsl' or 'world', got {convention!r}")
    tensor, fa, md, v1, b0 = fit_tensor(data, bvals, g, b0_threshold=b0_threshold)
    ornt = io_orientation(stored)
    affine = stored @ inv_ornt_aff(ornt, data.shape[:3])
    affine[:3, :] *= UNIT_TO_CM[unit]

    def canon(a):
        return np.ascontiguousarray(apply_orientation(a, ornt))

    return DWITensorFit(tensor=canon(tensor), fa=canon(fa), md=canon(md), v1=canon(v1), affine=affine, b0=canon(b0))

"""Diffusion tensors, principal eigenvectors and sign-invariant fibre features.

Conventions (pixmuscle assumes these; convert other data before use):

* Tensor and vector components are expressed in the image's **world (scanner) axes**, i.e.
  the axes the NIfTI affine maps voxel indices to (RAS+ after :func:`pixmuscle.imaging.nifti.
  load_volume`), not in voxel axes. A component image written in voxel axes (e.g. FSL's
  ``dtifit`` output of a volume stored with a negative-determinant affine, whose x component
  is flipped) must be converted by the caller: ``v_world = R @ v_voxel`` with ``R`` the
  rotation part of the affine (columns normalised).
* Diffusivities are in mm^2/s (the unit DTI software writes); only directions matter to
  pixmuscle.
* A principal eigenvector has no sign: ``v`` and ``-v`` describe the same fibre. Every
  feature derived here is either sign-invariant (``v v^T``, ``|v|``) or made unique by
  :func:`canonical_sign`.
"""

from __future__ import annotations

import numpy as np

from pixmuscle.errors import InputError

#: component (row, col) of each of the 6 stored values, per storage convention
COMPONENT_ORDERS = {
    # FSL dtifit --save_tensor: Dxx Dxy Dxz Dyy Dyz Dzz (upper triangle, row-major)
    "fsl": ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)),
    # dipy: lower triangle row-major: Dxx Dxy Dyy Dxz Dyz Dzz
    "dipy": ((0, 0), (0, 1), (1, 1), (0, 2), (1, 2), (2, 2)),
    # MRtrix dwi2tensor: Dxx Dyy Dzz Dxy Dxz Dyz
    "mrtrix": ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)),
}


def _order(order: str):
    try:
        return COMPONENT_ORDERS[order]
    except KeyError:
        raise InputError(
            f"unknown tensor component order {order!r}; expected one of {sorted(COMPONENT_ORDERS)}"
        ) from None


def tensor_from_components(comp, order: str = "fsl") -> np.ndarray:
    """Symmetric tensors (..., 3, 3) from 6 stored components (..., 6).

    Parameters
    ----------
    comp : (..., 6) array_like
        Unique tensor components in the storage ``order``.
    order : {"fsl", "dipy", "mrtrix"}
        ``fsl``: Dxx Dxy Dxz Dyy Dyz Dzz; ``dipy``: Dxx Dxy Dyy Dxz Dyz Dzz (lower
        triangular); ``mrtrix``: Dxx Dyy Dzz Dxy Dxz Dyz.
    """
    comp = np.asarray(comp, dtype=float)
    if comp.shape[-1:] != (6,):
        raise InputError(f"tensor components: expected a last axis of length 6, got shape {comp.shape}")
    d = np.empty(comp.shape[:-1] + (3, 3))
    for n, (r, c) in enumerate(_order(order)):
        d[..., r, c] = comp[..., n]
        d[..., c, r] = comp[..., n]
    return d


def components_from_tensor(d, order: str = "fsl") -> np.ndarray:
    """The 6 unique components (..., 6) of symmetric tensors ``d`` (..., 3, 3) in ``order``."""
    d = np.asarray(d, dtype=float)
    if d.shape[-2:] != (3, 3):
        raise InputError(f"tensors: expected trailing shape (3, 3), got {d.shape}")
    return np.stack([0.5 * (d[..., r, c] + d[..., c, r]) for r, c in _order(order)], axis=-1)


def canonical_sign(v) -> np.ndarray:
    """Flip each vector so that it has a unique sign: ``v_z >= 0``.

    Ties are broken in order: if ``v_z == 0`` then ``v_y > 0``; if also ``v_y == 0`` then
    ``v_x > 0``. Zero vectors stay zero. ``canonical_sign(-v) == canonical_sign(v)`` for
    every v. The choice is discontinuous for fibres lying in the x-y plane (a direction
    near the plane may flip between neighbouring voxels); use :func:`fiber_features` with
    ``mode="outer"`` where that matters.

    Parameters
    ----------
    v : (..., 3) array_like
    """
    v = np.asarray(v, dtype=float)
    s = np.sign(v[..., 2])
    s = np.where(s == 0, np.sign(v[..., 1]), s)
    s = np.where(s == 0, np.sign(v[..., 0]), s)
    s = np.where(s == 0, 1.0, s)
    return v * s[..., None]


def principal_eigenvector(d) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Principal eigenvector, eigenvalues and fractional anisotropy of symmetric tensors.

    Parameters
    ----------
    d : (..., 3, 3) array_like
        Symmetric tensors (any units; diffusivities in mm^2/s usually).

    Returns
    -------
    v : (..., 3) ndarray
        Unit eigenvector of the largest eigenvalue, :func:`canonical_sign`; zero where the
        tensor is zero.
    evals : (..., 3) ndarray
        Eigenvalues in decreasing order.
    fa : (...) ndarray
        Fractional anisotropy ``sqrt(3/2) |lambda - mean| / |lambda|`` (0 for a zero tensor).
    """
    d = np.asarray(d, dtype=float)
    if d.shape[-2:] != (3, 3):
        raise InputError(f"tensors: expected trailing shape (3, 3), got {d.shape}")
    if not np.all(np.isfinite(d)):
        raise InputError(f"tensors: {int(np.sum(~np.isfinite(d)))} non-finite components")
    w, q = np.linalg.eigh(0.5 * (d + np.swapaxes(d, -1, -2)))
    evals = w[..., ::-1]
    v = q[..., :, 2]
    zero = ~np.any(d != 0, axis=(-2, -1))
    v = np.where(zero[..., None], 0.0, v)
    norm = np.linalg.norm(evals, axis=-1)
    dev = np.linalg.norm(evals - evals.mean(axis=-1, keepdims=True), axis=-1)
    fa = np.sqrt(1.5) * np.divide(dev, norm, out=np.zeros_like(norm), where=norm > 0)
    return canonical_sign(v), evals, fa


def fiber_features(v, mode: str = "outer") -> np.ndarray:
    """Sign-invariant channels built from fibre (eigen)vectors, for segmentation.

    Parameters
    ----------
    v : (..., 3) array_like
        Fibre directions (unit or zero); the sign of each vector is irrelevant.
    mode : {"outer", "abs", "canonical"}
        ``outer``: the 6 unique components of ``v v^T`` in FSL order (xx, xy, xz, yy, yz,
        zz), sign-invariant by construction and continuous in v (recommended);
        ``abs``: ``|v_x|, |v_y|, |v_z|`` (3 channels; cannot tell mirror-image directions
        apart); ``canonical``: :func:`canonical_sign` of v (3 channels; discontinuous near
        the x-y plane).

    Returns
    -------
    (..., 6) or (..., 3) ndarray
    """
    v = np.asarray(v, dtype=float)
    if v.shape[-1:] != (3,):
        raise InputError(f"fibre vectors: expected a last axis of length 3, got shape {v.shape}")
    if mode == "outer":
        return components_from_tensor(v[..., :, None] * v[..., None, :], "fsl")
    if mode == "abs":
        return np.abs(v)
    if mode == "canonical":
        return canonical_sign(v)
    raise InputError(f"fiber_features: unknown mode {mode!r}; expected 'outer', 'abs' or 'canonical'")


def resample_tensor_to_grid(d, d_affine, target_shape, target_affine, order: int = 1):
    """Map a diffusion-tensor image onto another grid (e.g. the anatomical MRI) via the affines.

    Tensors are interpolated component by component (never eigenvectors, which have no sign
    and cannot be averaged); linear interpolation of a tensor field that is linear in world
    position is exact.

    Parameters
    ----------
    d : (I, J, K, 3, 3) array_like
        Symmetric tensors, components in world axes (see module notes).
    d_affine, target_affine : (4, 4) array_like
        Voxel index -> world (cm) of the DTI and of the target grid.
    target_shape : (I', J', K') tuple of int
    order : int
        Interpolation order (1: trilinear). Orders > 1 may produce non-positive tensors.

    Returns
    -------
    out : (I', J', K', 3, 3) ndarray
        Tensors on the target grid; zero where not ``covered``.
    covered : (I', J', K') bool ndarray
        Target voxels inside the DTI field of view.

    Raises
    ------
    InputError
        If the fields of view do not overlap, or shapes are wrong.
    """
    from pixmuscle.imaging.resample import resample_to_grid

    d = np.asarray(d, dtype=float)
    if d.ndim != 5 or d.shape[3:] != (3, 3):
        raise InputError(f"DTI tensor image: expected shape (I, J, K, 3, 3), got {d.shape}")
    comp = components_from_tensor(d, "fsl")
    out, covered = resample_to_grid(comp, d_affine, target_shape, target_affine, order=order,
                                    name="DTI tensor image")
    return tensor_from_components(out, "fsl"), covered


def resample_vectors_to_grid(v, v_affine, target_shape, target_affine, order: int = 1,
                             min_weight: float = 0.5):
    """Map principal-eigenvector (fibre) images onto another grid, independent of their signs.

    For users who have only the V1 image: each vector is turned into ``v v^T`` (sign-free),
    these are interpolated, and the principal eigenvector of the result is taken again.

    Parameters
    ----------
    v : (I, J, K, 3) array_like
        Unit vectors in world axes, or zero where there is no DTI data; signs arbitrary.
    v_affine, target_affine : (4, 4) array_like
        Voxel index -> world (cm).
    target_shape : (I', J', K') tuple of int
    order : int
        Interpolation order (1: trilinear).
    min_weight : float
        A target voxel has data where the interpolated ``trace(v v^T)`` (the share of
        interpolation weight on voxels with data) is at least this.

    Returns
    -------
    out : (I', J', K', 3) ndarray
        Unit vectors with :func:`canonical_sign`, zero where ``has_data`` is False.
    has_data : (I', J', K') bool ndarray
        Inside the source field of view and with enough data (see ``min_weight``).
    """
    from pixmuscle.imaging.resample import resample_to_grid

    v = np.asarray(v, dtype=float)
    if v.ndim != 4 or v.shape[3] != 3:
        raise InputError(f"fibre vector image: expected shape (I, J, K, 3), got {v.shape}")
    if not np.all(np.isfinite(v)):
        raise InputError(f"fibre vector image: {int(np.sum(~np.isfinite(v)))} non-finite components")
    comp = fiber_features(v, "outer")
    out, covered = resample_to_grid(comp, v_affine, target_shape, target_affine, order=order,
                                    name="fibre vector image")
    weight = out[..., 0] + out[..., 3] + out[..., 5]
    has_data = covered & (weight >= min_weight)
    vec, _, _ = principal_eigenvector(tensor_from_components(out, "fsl"))
    vec[~has_data] = 0.0
    return vec, has_data

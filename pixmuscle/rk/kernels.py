"""Kernel (window) functions φ_a of the reproducing-kernel approximation (paper §2, eq. 3).

Every kernel is written in the normalised distance ``z = |x - x_I| / a`` (dimensionless, ``a`` the
support radius in cm) and vanishes for ``z >= 1``:

``"tent"`` (C0, paper Fig. 1b)
    φ(z) = 1 - z
``"cubic"`` (C2 cubic B-spline, paper Fig. 1c)
    φ(z) = 2/3 - 4 z² + 4 z³          for 0 <= z <= 1/2
    φ(z) = 4/3 (1 - z)³               for 1/2 < z < 1
``"quartic"`` (C2 quartic spline)
    φ(z) = 1 - 6 z² + 8 z³ - 3 z⁴
``"quintic"`` (C4 quintic B-spline, with q = 3 z)
    φ(z) = [(3 - q)₊⁵ - 6 (2 - q)₊⁵ + 15 (1 - q)₊⁵] / 66,   (t)₊ = max(t, 0)

The overall scale of φ does not matter for the RK shape functions (it cancels in eq. 7).

Multi-dimensional windows (:func:`window`) are either the tensor product of 1-D kernels over the
axes (``"box"``: φ = Π_k φ(|x_k - x_Ik| / a_k)) or radial (``"sphere"``:
φ = φ(‖(x - x_I) / a‖), the material kernel of eq. 15 with per-axis support).
"""

from __future__ import annotations

import numpy as np

from pixmuscle.errors import InputError

KERNELS = ("tent", "cubic", "quartic", "quintic")
SUPPORT_SHAPES = ("box", "sphere")


def _tent(z):
    return 1.0 - z, -np.ones_like(z)


def _cubic(z):
    z2 = z * z
    t = 1.0 - z
    t2 = t * t
    inner = z <= 0.5
    w = np.where(inner, 2.0 / 3.0 + 4.0 * z2 * (z - 1.0), (4.0 / 3.0) * t2 * t)
    dw = np.where(inner, z * (12.0 * z - 8.0), -4.0 * t2)
    return w, dw


def _quartic(z):
    z2 = z * z
    t = 1.0 - z
    w = 1.0 + z2 * (-6.0 + z * (8.0 - 3.0 * z))
    dw = -12.0 * z * t * t
    return w, dw


def _quintic(z):
    q = 3.0 * z
    t3 = np.maximum(3.0 - q, 0.0)
    t2 = np.maximum(2.0 - q, 0.0)
    t1 = np.maximum(1.0 - q, 0.0)
    p3, p2, p1 = t3 * t3 * t3 * t3, t2 * t2 * t2 * t2, t1 * t1 * t1 * t1
    w = (p3 * t3 - 6.0 * p2 * t2 + 15.0 * p1 * t1) / 66.0
    dw = -15.0 * (p3 - 6.0 * p2 + 15.0 * p1) / 66.0  # d/dz = 3 d/dq
    return w, dw


_KERNEL_FUNCS = {"tent": _tent, "cubic": _cubic, "quartic": _quartic, "quintic": _quintic}


def check_kernel(kind):
    """Raise :class:`~pixmuscle.errors.InputError` unless ``kind`` names a known kernel."""
    if kind not in _KERNEL_FUNCS:
        raise InputError(f"unknown RK kernel {kind!r}: expected one of {', '.join(KERNELS)}")


def kernel(z, kind="cubic"):
    """Value and derivative of a 1-D kernel in the normalised distance (paper eq. 3, Fig. 1).

    Parameters
    ----------
    z : array_like
        Normalised distance ``|x - x_I| / a`` (dimensionless), any shape. Negative values are
        read as ``|z|``.
    kind : {"tent", "cubic", "quartic", "quintic"}
        Kernel; formulas in the module docstring.

    Returns
    -------
    phi : ndarray
        φ(|z|), same shape as ``z``; exactly 0 for ``|z| >= 1``.
    dphi_dz : ndarray
        dφ/d|z| (derivative with respect to the distance, not to signed ``z``); 0 for
        ``|z| >= 1``. For the tent kernel the value at ``z = 0`` is the one-sided -1.
    """
    check_kernel(kind)
    z = np.abs(np.asarray(z, dtype=float))
    inside = z < 1.0
    zc = np.where(inside, z, 1.0)
    w, dw = _KERNEL_FUNCS[kind](zc)
    return np.where(inside, w, 0.0), np.where(inside, dw, 0.0)


def window(u, support, kind="cubic", support_shape="box", gradient=False):
    """Multi-dimensional kernel φ_a(x - x_I) for a batch of point–node pairs.

    Parameters
    ----------
    u : ndarray, shape (n, d)
        Normalised offsets ``(x - x_I) / a_I`` per axis (dimensionless), all with ``z < 1``.
    support : ndarray, shape (d,) or (n, d)
        Support radius ``a_I`` per axis (cm), used only for the chain rule of the gradient.
    kind : str
        1-D kernel, see :func:`kernel`.
    support_shape : {"box", "sphere"}
        Tensor-product (``z_k = |u_k|``) or radial (``z = ‖u‖``) window.
    gradient : bool
        Also return ∂φ/∂x_k.

    Returns
    -------
    phi : ndarray, shape (n,)
    dphi : ndarray, shape (n, d), cm⁻¹
        ∂φ/∂x_k, only when ``gradient`` is true. Where φ has a kink (tent kernel at
        ``u_k = 0``) the mean of the two one-sided derivatives, 0, is returned.
    """
    d = u.shape[1]
    if support_shape == "box":
        zk = np.abs(u)
        w, dw = _KERNEL_FUNCS[kind](zk)
        phi = np.prod(w, axis=1)
        if not gradient:
            return phi
        dphi = np.sign(u) * dw / support
        for k in range(d):
            for j in range(d):
                if j != k:
                    dphi[:, k] *= w[:, j]
        return phi, dphi
    if support_shape == "sphere":
        z = np.sqrt(np.einsum("ij,ij->i", u, u))
        phi, dw = _KERNEL_FUNCS[kind](z)
        if not gradient:
            return phi
        # dz/dx_k = u_k / (z a_k); the product is 0 at z = 0 (u = 0 there)
        ratio = np.divide(dw, z, out=np.zeros_like(z), where=z > 0)
        return phi, ratio[:, None] * u / support
    raise InputError(f"unknown support_shape {support_shape!r}: expected one of {', '.join(SUPPORT_SHAPES)}")

"""Homogeneous-deformation reference solutions for verifying the solver.

Pure functions of a material law (:mod:`pixmuscle.mechanics.materials`), with no RK
approximation and no discretisation: a bar or block under a homogeneous deformation gradient F,
found with :func:`scipy.optimize.brentq` (1 unknown) or :func:`scipy.optimize.minimize`
(5 unknowns). The body's axis is z (axis 2); ``area0`` is the reference cross-section [cm²];
forces are ``P_zz · area0`` [N], positive in tension (the body pulls on its ends).
"""

from __future__ import annotations

import math

import numpy as np
from scipy import optimize

from ..errors import InputError, SolverError

__all__ = ["uniaxial_bar", "isometric_block", "homogeneous_min_energy"]


def _positive(name, value):
    v = float(value)
    if not (math.isfinite(v) and v > 0):
        raise InputError(f"{name} must be a finite number > 0, got {value!r}")
    return v


def _fiber(fiber):
    N = np.asarray(fiber, dtype=np.float64)
    if N.shape != (3,) or not np.isfinite(N).all() or not np.linalg.norm(N) > 0:
        raise InputError(f"fiber must be a non-zero 3-vector, got {fiber!r}")
    return N / np.linalg.norm(N)


def _is_transversely_isotropic_about_z(material, N):
    if not hasattr(material, "lambda_opt"):  # isotropic material: any fibre argument is ignored
        return True
    return abs(abs(N[2]) - 1.0) < 1e-12


def _lateral_solve(material, lam, kw):
    """Solve P_xx(F = diag(t, t, lam)) = 0 for t; returns t, F (3,3), P (3,3)."""

    def F_of(t):
        return np.diag([t, t, lam])[None]

    def r(t):
        return material.stress(F_of(t), **kw)[0, 0, 0]

    t0 = lam**-0.5  # isochoric guess
    lo, hi = t0, t0
    for _ in range(200):
        if r(lo) < 0:
            break
        lo /= 1.05
    else:
        raise SolverError(f"no lateral stretch with P_xx < 0 found below {t0:.4g} (axial stretch {lam})")
    for _ in range(200):
        if r(hi) > 0:
            break
        hi *= 1.05
    else:
        raise SolverError(f"no lateral stretch with P_xx > 0 found above {t0:.4g} (axial stretch {lam})")
    t = optimize.brentq(r, lo, hi, xtol=1e-15, rtol=4 * np.finfo(float).eps, maxiter=500)
    F = F_of(t)
    return t, F[0], material.stress(F, **kw)[0]


def uniaxial_bar(material, stretch, area0, *, fiber=(0.0, 0.0, 1.0), activation=0.0):
    """Bar along z under prescribed axial stretch with traction-free lateral faces.

    F = diag(λt, λt, λ) with λ prescribed and λt the root of P_xx = 0 (1-D, brentq).

    Parameters
    ----------
    material : Yeoh or TransverselyIsotropicMuscle
    stretch : float
        Axial stretch λ = F_zz (> 0).
    area0 : float
        Reference cross-section [cm²].
    fiber : (3,) array_like
        Fibre direction (muscle only); must be ±z so that the bar is transversely isotropic
        about its axis and F stays diagonal (otherwise use :func:`homogeneous_min_energy`).
    activation : float
        α in [0, 1] (muscle only).

    Returns
    -------
    dict
        ``force`` [N] = P_zz · area0 (tension positive), ``lateral_stretch`` λt,
        ``F`` (3, 3), ``P`` (3, 3) first Piola–Kirchhoff stress [N/cm²].
    """
    lam = _positive("stretch", stretch)
    area0 = _positive("area0", area0)
    N = _fiber(fiber)
    if not _is_transversely_isotropic_about_z(material, N):
        raise InputError(
            f"uniaxial_bar needs fibres along the bar axis z, got fiber={tuple(N)}; "
            "use homogeneous_min_energy for oblique fibres"
        )
    kw = dict(fiber=N[None], activation=activation)
    t, F, P = _lateral_solve(material, lam, kw)
    return dict(force=P[2, 2] * area0, lateral_stretch=t, F=F, P=P)


def isometric_block(material, alpha, area0, fiber=(0.0, 0.0, 1.0)):
    """Block held at its reference length between roller ends, fibres along z, activated to α.

    F = diag(λt, λt, 1): F_zz = 1 (ends fixed in z, free to slide laterally), lateral faces
    traction free, P_xx = 0 solved for λt (1-D, brentq).

    Parameters
    ----------
    material : TransverselyIsotropicMuscle (or an isotropic material: then α has no effect)
    alpha : float
        Activation α in [0, 1].
    area0 : float
        Reference cross-section [cm²].
    fiber : (3,) array_like
        Must be ±z (use :func:`homogeneous_min_energy` for oblique fibres).

    Returns
    -------
    dict
        ``force`` [N] = P_zz · area0, positive when the block pulls on its ends (tension),
        ``lateral_stretch`` λt, ``F`` (3, 3), ``P`` (3, 3) [N/cm²].
    """
    return uniaxial_bar(material, 1.0, area0, fiber=fiber, activation=alpha)


def homogeneous_min_energy(material, F_constraints, area0, *, fiber=(0.0, 0.0, 1.0), activation=0.0):
    """Minimum-energy homogeneous state with the third row of F prescribed (roller ends).

    Roller ends keep every end face planar and perpendicular to z (u_z constant on each end)
    but let it slide laterally: F_zx = F_zy = 0 and F_zz = λ, and the six other entries of F are
    free. Rotations about z leave the third row unchanged; they are removed with the triangular
    form (a QR factorisation of the first two rows)

        F = [[a, b, c],
             [0, e, f],
             [F_zx, F_zy, F_zz]],   a, e > 0,

    and W(F) is minimised over (a, b, c, e, f) (trust-region Newton with the exact gradient
    P and Hessian A of the material). By objectivity the gradient along the removed rotation
    vanishes too, so at the minimum P_xx = P_xy = P_xz = P_yx = P_yy = P_yz = 0: the end faces
    carry only the normal traction P_zz, and the lateral faces carry no in-plane traction.

    Caveat for oblique fibres: the z-components P_zx, P_zy on the lateral faces (conjugate to
    the *prescribed* F_zx, F_zy) then equal −P_zz (M⁻¹c)_x,y with M = [[a, b], [0, e]],
    c = (F_xz, F_yz)ᵀ (balance of angular momentum). They vanish when the block does not shear
    (fibres along z), but not in general: the homogeneous state solves the roller problem with
    u_z = (λ − 1)Z imposed throughout (or with these axial shear tractions applied on the
    lateral faces), not the problem with fully traction-free lateral faces, whose solution is
    inhomogeneous. They are returned as ``lateral_axial_traction``.

    Parameters
    ----------
    material : Yeoh or TransverselyIsotropicMuscle
    F_constraints : float or (3,) array_like
        Axial stretch λ (then the third row is (0, 0, λ)), or the whole third row
        (F_zx, F_zy, F_zz) with F_zz > 0.
    area0 : float
        Reference cross-section [cm²].
    fiber : (3,) array_like
        Reference fibre direction (muscle only), any orientation.
    activation : float
        α in [0, 1] (muscle only).

    Returns
    -------
    dict
        ``force`` [N] = P_zz · area0 (tension positive), ``F`` (3, 3), ``P`` (3, 3) [N/cm²],
        ``energy`` W [N/cm²], ``lateral_axial_traction`` (P_zx, P_zy) [N/cm²],
        ``stationarity`` max |P| over the six free components [N/cm²].
    """
    row = np.atleast_1d(np.asarray(F_constraints, dtype=np.float64))
    if row.shape == (1,):
        row = np.array([0.0, 0.0, row[0]])
    if row.shape != (3,) or not np.isfinite(row).all() or not row[2] > 0:
        raise InputError(
            f"F_constraints must be an axial stretch > 0 or a third row (F_zx, F_zy, F_zz) with "
            f"F_zz > 0, got {F_constraints!r}"
        )
    area0 = _positive("area0", area0)
    N = _fiber(fiber)
    kw = dict(fiber=N[None], activation=activation)
    # free unknowns (a, b, c, e, f) = F_xx, F_xy, F_xz, F_yy, F_yz
    free = (np.array([0, 0, 0, 1, 1]), np.array([0, 1, 2, 1, 2]))

    def F_of(v):
        F = np.zeros((1, 3, 3))
        F[0][free] = v
        F[0, 2] = row
        return F

    def fun(v):
        try:
            return float(material.energy(F_of(v), **kw)[0])
        except SolverError:  # trial step inverted the block: reject it
            return np.inf

    def jac(v):
        return material.stress(F_of(v), **kw)[0][free]

    def hess(v):
        A = material.stress_tangent(F_of(v), **kw)[1][0]
        i, j = free
        return A[i[:, None], j[:, None], i[None, :], j[None, :]]

    t0 = row[2] ** -0.5
    v0 = np.array([t0, 0.0, 0.0, t0, 0.0])
    scale = max(material.bulk_modulus, 1.0)
    res = optimize.minimize(
        fun, v0, jac=jac, hess=hess, method="trust-exact", options=dict(gtol=1e-13 * scale, maxiter=500)
    )
    v = res.x
    # a few full Newton steps to polish to round-off (the Hessian is positive definite here)
    for _ in range(3):
        v = v - np.linalg.solve(hess(v), jac(v))
    F = F_of(v)
    P = material.stress(F, **kw)[0]
    stat = float(np.abs(np.concatenate([P[free], [P[1, 0]]])).max())
    if not (np.all(np.isfinite(P)) and stat <= 1e-8 * max(scale, np.abs(P).max())):
        raise SolverError(
            f"homogeneous_min_energy did not converge: largest free stress component {stat:.3g} N/cm² ({res.message})"
        )
    return dict(
        force=P[2, 2] * area0,
        F=F[0],
        P=P,
        energy=float(material.energy(F, **kw)[0]),
        lateral_axial_traction=P[2, :2].copy(),
        stationarity=stat,
    )

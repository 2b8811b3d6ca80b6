r"""Hyperelastic materials of the paper (§5, eqs. 22–27), vectorised over material points.

Every material is a frozen dataclass of constants in N/cm² with the same interface, all
arrays float64 and ``n`` the number of material points:

``energy(F, **kw)``          W, shape (n,), strain energy per unit reference volume [N/cm² = N·cm/cm³]
``stress(F, **kw)``          P, shape (n, 3, 3), first Piola–Kirchhoff stress [N/cm²]
``stress_tangent(F, **kw)``  (P, A) with ``A[n, i, J, k, L] = ∂P_iJ/∂F_kL`` (n, 3, 3, 3, 3) [N/cm²],
                             the first elasticity tensor ∂²W/∂F∂F (eq. 20 as corrected in ERRATA)
``cauchy(F, **kw)``          σ = J⁻¹ P Fᵀ, shape (n, 3, 3) [N/cm²]

A deformation gradient with det F ≤ 0 (or non-finite entries) raises
:class:`~pixmuscle.errors.SolverError`; the Newton solver catches it and cuts the step back.

Derivation (shared by both materials)
-------------------------------------
Both energies are *uncoupled*: functions of the isochoric invariants and of J,

    C = FᵀF,  J = det F,  H = F⁻ᵀ,  B = FFᵀ,
    I1 = tr C,  I2 = ½(I1² − tr C²),  I4 = N·CN = |a|², a = FN   (N unit fibre, reference),
    Ī = J^(−2m/3) I   with m = 1 for I1 and I4, m = 2 for I2     (Ī2 = I2 J^(−4/3), ERRATA),
    λ̂ = √Ī4 = √(N·C̄N),  C̄ = J^(−2/3) C.

Derivatives of the raw invariants (∂J/∂F = J H, ∂H_iJ/∂F_kL = −H_iL H_kJ):

    ∂I1 = 2F,  ∂I2 = 2(I1 F − FC),  ∂I4 = 2 a⊗N,
    ∂²I1 = 2𝕀,  ∂²I4 = 2 δ_ik N_J N_L,
    ∂²I2 = 2[2 F⊗F + I1 𝕀 − δ_ik C_JL − F_iL F_kJ − B_ik δ_JL],

with 𝕀_iJkL = δ_ik δ_JL, (X⊗Y)_iJkL = X_iJ Y_kL and (X⊙Y)_iJkL = X_iL Y_kJ. For Ī = j I with
j = J^(−2m/3) (∂j = −(2m/3) j H):

    ∂Ī  = j [∂I − (2m/3) I H]
    ∂²Ī = j [∂²I − (2m/3)(∂I⊗H + H⊗∂I) + (2m/3)² I H⊗H + (2m/3) I H⊙H].

With W = Ŵ(Ī1, Ī2, Ī4) + U(J), U = K/2 (J − 1)², and W_a = ∂Ŵ/∂Ī_a, W_ab = ∂²Ŵ/∂Ī_a∂Ī_b:

    P = Σ_a W_a ∂Ī_a + U' J H
    A = Σ_ab W_ab ∂Ī_a⊗∂Ī_b + Σ_a W_a ∂²Ī_a + (U''J² + U'J) H⊗H − U'J H⊙H.

Every term is one of four kinds: dyads Σ_pq c_pq X_p⊗X_q over the basis X = {F, H, FC, a⊗N},
crossed dyads c_HH H⊙H + c_FF F⊙F, δ_ik M_JL and c_B B_ik δ_JL. :func:`_response` computes the
small per-point coefficients (c, c_HH, c_FF, M, c_B) with numpy and a numba kernel writes the 81
entries of A per point in one pass, so no (n,3,3,3,3) temporary is built per term.

Fibre term (eq. 24): W_fiber(λ̂) is the exact integral from λ̂ = 1 of
∂W_fiber/∂λ̂ = (σ_max/λ̂0)(α f_active(λ*) + f_passive(λ*)), λ* = λ̂/λ̂0, in closed form, so energy,
stress and tangent are consistent; in terms of Ī4 = λ̂²: W_4 = g/(2λ̂), W_44 = (g'λ̂ − g)/(4λ̂³),
g = ∂W_fiber/∂λ̂.

Deviatoric fibre stress. Pushing the fibre part of P forward gives

    σ_fiber = J⁻¹ σ_max λ* (α f_active + f_passive) (n⊗n − I/3),   n = FN/|FN|,

a *deviatoric* stress: because the fibre energy depends on C̄ and not on C, it carries no
pressure. At λ̂ = λ̂0 with α = 1 the fibre pulls with σ_max along n and pushes with σ_max/3 across
it (σ_nn − σ_tt = σ_max/J), and the volumetric term K/2 (J − 1)² alone sets the mean stress.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any

import numba
import numpy as np

from ..errors import InputError, SolverError

__all__ = [
    "CubicIsotropic",
    "TransverselyIsotropicMuscle",
    "CONNECTIVE_TISSUE",
    "FAT",
    "MUSCLE",
    "f_active",
    "f_passive",
    "material_from_config",
    "voigt9",
    "tangent9",
]

# 9-vector order of eq. 17: F11 F22 F33 F12 F21 F13 F31 F23 F32 (0-based row, column pairs)
_V9_ROW = np.array([0, 1, 2, 0, 1, 0, 2, 1, 2])
_V9_COL = np.array([0, 1, 2, 1, 0, 2, 0, 2, 1])


def voigt9(P):
    """Tensor (..., 3, 3) → 9-vector (..., 9) in the order of eq. 17.

    Order: F11 F22 F33 F12 F21 F13 F31 F23 F32. For reporting and tests only.
    """
    P = np.asarray(P)
    if P.shape[-2:] != (3, 3):
        raise InputError(f"voigt9 expects an array of shape (..., 3, 3), got {P.shape}")
    return P[..., _V9_ROW, _V9_COL]


def tangent9(A):
    """Fourth-order tensor (..., 3, 3, 3, 3) → (..., 9, 9) matrix in the order of eq. 17.

    ``A9[..., a, b] = A[..., i_a, J_a, k_b, L_b]`` so that ``voigt9(dP) = A9 @ voigt9(dF)``.
    """
    A = np.asarray(A)
    if A.shape[-4:] != (3, 3, 3, 3):
        raise InputError(f"tangent9 expects an array of shape (..., 3, 3, 3, 3), got {A.shape}")
    r, c = _V9_ROW, _V9_COL
    return A[..., r[:, None], c[:, None], r[None, :], c[None, :]]


# --------------------------------------------------------------------------------------------
# kinematics


class _Kinematics:
    """F, J, H = F⁻ᵀ, C = FᵀF, I1 for n points; raises SolverError on det F ≤ 0."""

    def __init__(self, F):
        F = np.ascontiguousarray(F, dtype=np.float64)
        if F.ndim != 3 or F.shape[1:] != (3, 3):
            raise InputError(f"deformation gradient F must have shape (n, 3, 3), got {F.shape}")
        n = F.shape[0]
        finite = np.isfinite(F).all(axis=(1, 2))
        if not finite.all():
            raise SolverError(f"{int(n - finite.sum())} of {n} material points have a non-finite deformation gradient")
        f0, f1, f2 = F[:, :, 0], F[:, :, 1], F[:, :, 2]
        cof = np.empty_like(F)  # cof(F) = J F⁻ᵀ, columns are cross products of F's columns
        cof[:, :, 0] = np.cross(f1, f2)
        cof[:, :, 1] = np.cross(f2, f0)
        cof[:, :, 2] = np.cross(f0, f1)
        J = np.einsum("ni,ni->n", f0, cof[:, :, 0])
        bad = ~(J > 0.0)
        if bad.any():
            raise SolverError(
                f"{int(bad.sum())} of {n} material points have det F <= 0 "
                f"(smallest det F = {J.min():.4g}): the material is inverted there"
            )
        self.n = n
        self.F = F
        self.J = J
        self.H = cof / J[:, None, None]
        self.C = np.matmul(F.transpose(0, 2, 1), F)
        self.I1 = np.einsum("nij,nij->n", F, F)
        self.j1 = np.cbrt(J) ** -2  # J^(-2/3)

    @property
    def I2(self):
        return 0.5 * (self.I1**2 - np.einsum("nij,nij->n", self.C, self.C))


def _response(kin, dW, d2W, Up, Upp, *, use_I2, fib, tangent):
    """First Piola–Kirchhoff stress and first elasticity tensor of an uncoupled energy.

    Parameters
    ----------
    kin : _Kinematics
    dW : list of (n,) arrays
        ∂Ŵ/∂Ī_a for the isochoric invariants present, in the order Ī1, [Ī2], [Ī4].
    d2W : (n, m, m) array or None
        ∂²Ŵ/∂Ī_a∂Ī_b in the same order (only used when ``tangent``).
    Up, Upp : (n,) arrays
        U'(J), U''(J) of the volumetric energy.
    use_I2 : bool
    fib : None or (a (n,3), N (n,3), I4 (n,))
    tangent : bool

    Returns
    -------
    P : (n, 3, 3)
    A : (n, 3, 3, 3, 3) or None
    """
    F, H, J, j1, n = kin.F, kin.H, kin.J, kin.j1, kin.n
    nb = 2 + int(use_I2) + int(fib is not None)
    X = np.empty((n, nb, 3, 3))  # basis {F, H, [FC], [a⊗N]}
    X[:, 0] = F
    X[:, 1] = H
    iF, iH = 0, 1
    I1 = kin.I1
    invs = [(dW[0], {iF: 2.0}, I1, 1, j1)]  # (W_a, ∂I_a as {basis index: coefficient}, I_a, m_a, j_a)
    if use_I2:
        iFC = 2
        np.matmul(F, kin.C, out=X[:, iFC])
        invs.append((dW[1], {iF: 2.0 * I1, iFC: -2.0}, kin.I2, 2, j1 * j1))
    if fib is not None:
        a, N, I4 = fib
        iaN = nb - 1
        np.multiply(a[:, :, None], N[:, None, :], out=X[:, iaN])
        invs.append((dW[-1], {iaN: 2.0}, I4, 1, j1))

    G = np.zeros((n, len(invs), nb))  # coefficients of ∂Ī_a over the basis
    s = np.zeros((n, nb))  # coefficients of P over the basis
    s[:, iH] = Up * J
    for r, (Wa, dI, I, m, j) in enumerate(invs):
        for idx, val in dI.items():
            G[:, r, idx] = j * val
        G[:, r, iH] -= (2.0 * m / 3.0) * j * I
        s += Wa[:, None] * G[:, r]
    Xf = X.reshape(n, nb, 9)
    P = np.matmul(s[:, None, :], Xf).reshape(n, 3, 3)
    if not tangent:
        return P, None

    c = np.matmul(G.transpose(0, 2, 1), np.matmul(d2W, G))  # Σ_ab W_ab ∂Ī_a⊗∂Ī_b
    c[:, iH, iH] += Upp * J * J + Up * J
    cHH = -Up * J
    M = np.zeros((n, 3, 3))
    for Wa, dI, I, m, j in invs:
        wj = Wa * j
        k = 2.0 * m / 3.0
        for idx, val in dI.items():
            c[:, idx, iH] -= k * wj * val
            c[:, iH, idx] -= k * wj * val
        c[:, iH, iH] += k * k * wj * I
        cHH = cHH + k * wj * I
    w1 = dW[0] * j1
    for i in range(3):
        M[:, i, i] = 2.0 * w1
    cFF = np.zeros(n)
    cB = np.zeros(n)
    if use_I2:
        w2 = dW[1] * j1 * j1
        c[:, iF, iF] += 4.0 * w2
        M -= (2.0 * w2)[:, None, None] * kin.C
        for i in range(3):
            M[:, i, i] += 2.0 * w2 * I1
        cFF = -2.0 * w2
        cB = -2.0 * w2
    if fib is not None:
        w4 = dW[-1] * j1
        M += (2.0 * w4)[:, None, None] * (N[:, :, None] * N[:, None, :])

    A = np.empty((n, 3, 3, 3, 3))
    _fill_tangent(X, c, H, cHH, F, cFF, M, cB, bool(use_I2), A)
    return P, A


@numba.njit(cache=True)
def _fill_tangent(X, c, H, cHH, F, cFF, M, cB, use_B, out):  # pragma: no cover - compiled
    """out[e,i,J,k,L] = Σ_pq c_pq X_p,iJ X_q,kL + cHH H_iL H_kJ + cFF F_iL F_kJ
    + δ_ik M_JL + cB B_ik δ_JL, with B = F Fᵀ (B term only if use_B)."""
    n, nb = X.shape[0], X.shape[1]
    Y = np.empty((nb, 3, 3))
    B = np.zeros((3, 3))
    for e in range(n):
        for p in range(nb):
            for k in range(3):
                for L in range(3):
                    acc = 0.0
                    for q in range(nb):
                        acc += c[e, p, q] * X[e, q, k, L]
                    Y[p, k, L] = acc
        if use_B:
            for i in range(3):
                for k in range(3):
                    B[i, k] = cB[e] * (F[e, i, 0] * F[e, k, 0] + F[e, i, 1] * F[e, k, 1] + F[e, i, 2] * F[e, k, 2])
        for a in range(9):  # A is major-symmetric: fill the upper triangle of the 9×9 form
            i, J = a // 3, a % 3
            for b in range(a, 9):
                k, L = b // 3, b % 3
                acc = cHH[e] * H[e, i, L] * H[e, k, J] + cFF[e] * F[e, i, L] * F[e, k, J]
                for p in range(nb):
                    acc += X[e, p, i, J] * Y[p, k, L]
                if i == k:
                    acc += M[e, J, L]
                if J == L:
                    acc += B[i, k]
                out[e, i, J, k, L] = acc
                out[e, k, L, i, J] = acc


def _cauchy(kin, P):
    return np.einsum("nik,njk->nij", P, kin.F) / kin.J[:, None, None]


def _as_const(obj, names):
    """Validate dataclass constants: real, finite numbers; store them as float."""
    for name in names:
        v = getattr(obj, name)
        if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
            raise InputError(f"{type(obj).__name__}.{name} must be a number (N/cm² or dimensionless), got {v!r}")
        if not math.isfinite(float(v)):
            raise InputError(f"{type(obj).__name__}.{name} must be finite, got {v!r}")
        object.__setattr__(obj, name, float(v))


# --------------------------------------------------------------------------------------------
# isotropic cubic material (eq. 27)


@dataclasses.dataclass(frozen=True)
class CubicIsotropic:
    """Uncoupled isotropic cubic hyperelastic material, eq. 27 (connective tissue and fat).

    W = C10(Ī1 − 3) + C20(Ī1 − 3)² + C30(Ī1 − 3)³ + K/2 (J − 1)²,  Ī1 = I1 J^(−2/3).

    Parameters
    ----------
    C10, C20, C30 : float
        Deviatoric constants [N/cm²]; the small-strain shear modulus is μ = 2 C10 (> 0 required).
    K : float
        Bulk modulus [N/cm²] (> 0).

    Notes
    -----
    The methods accept ``fiber`` and ``activation`` keywords and ignore them, so an assembly loop
    may call every material the same way.
    """

    C10: float
    C20: float
    C30: float
    K: float

    def __post_init__(self):
        _as_const(self, ("C10", "C20", "C30", "K"))
        if self.C10 <= 0:
            raise InputError(f"CubicIsotropic.C10 must be > 0 (shear modulus 2·C10), got {self.C10}")
        if self.K <= 0:
            raise InputError(f"CubicIsotropic.K must be > 0 (bulk modulus, N/cm²), got {self.K}")

    @property
    def shear_modulus(self) -> float:
        """Small-strain shear modulus μ = 2 C10 [N/cm²]."""
        return 2.0 * self.C10

    @property
    def bulk_modulus(self) -> float:
        """Small-strain bulk modulus K [N/cm²]."""
        return self.K

    def energy(self, F, *, fiber=None, activation=None):
        """Strain energy density W (n,) [N/cm²] at deformation gradients F (n, 3, 3)."""
        kin = _Kinematics(F)
        x = kin.j1 * kin.I1 - 3.0
        return x * (self.C10 + x * (self.C20 + x * self.C30)) + 0.5 * self.K * (kin.J - 1.0) ** 2

    def _eval(self, F, tangent):
        kin = _Kinematics(F)
        x = kin.j1 * kin.I1 - 3.0
        W1 = self.C10 + x * (2.0 * self.C20 + 3.0 * self.C30 * x)
        W11 = (2.0 * self.C20 + 6.0 * self.C30 * x)[:, None, None]
        Up = self.K * (kin.J - 1.0)
        Upp = np.full(kin.n, self.K)
        P, A = _response(kin, [W1], W11, Up, Upp, use_I2=False, fib=None, tangent=tangent)
        return kin, P, A

    def stress(self, F, *, fiber=None, activation=None):
        """First Piola–Kirchhoff stress P (n, 3, 3) [N/cm²]."""
        return self._eval(F, False)[1]

    def stress_tangent(self, F, *, fiber=None, activation=None):
        """P (n, 3, 3) and A (n, 3, 3, 3, 3), ``A[n,i,J,k,L] = ∂P_iJ/∂F_kL`` [N/cm²]."""
        _, P, A = self._eval(F, True)
        return P, A

    def cauchy(self, F, *, fiber=None, activation=None):
        """Cauchy stress σ = J⁻¹ P Fᵀ (n, 3, 3) [N/cm²]."""
        kin, P, _ = self._eval(F, False)
        return _cauchy(kin, P)


#: Table 1, connective tissue (N/cm²).
CONNECTIVE_TISSUE = CubicIsotropic(C10=30.0, C20=80.0, C30=800.0, K=50000.0)
#: Table 1, fat: ten times softer than connective tissue (N/cm²).
FAT = CubicIsotropic(C10=3.0, C20=8.0, C30=80.0, K=5000.0)


# --------------------------------------------------------------------------------------------
# fibre force–length relations (eqs. 25, 26 with the ERRATA)

# f_active is piecewise quadratic: on piece k, with t = s − s_ref,
#   f = p0 + p1 t + p2 t²,  ∫_0^s f = F0 + p0 t + p1 t²/2 + p2 t³/3.
# Pieces: s < 0.4 | [0.4, 0.6] | (0.6, 1.4] | (1.4, 1.6] | s > 1.6 (ERRATA band: 0 outside).
_FA06 = 3.0 * 0.2**3  # ∫_0^0.6 f_active
_FA10 = _FA06 + 0.4 - (4.0 / 3.0) * 0.4**3  # ∫_0^1
_FA16 = 2.0 * _FA10  # ∫_0^1.6: f_active is symmetric about s = 1
_ACT_BREAKS = np.array([0.4, 0.6, 1.4, 1.6])
_ACT_TABLE = np.array(
    [  # s_ref, F0, p0, p1, p2
        [0.4, 0.0, 0.0, 0.0, 0.0],
        [0.4, 0.0, 0.0, 0.0, 9.0],
        [1.0, _FA10, 1.0, 0.0, -4.0],
        [1.6, _FA16, 0.0, 0.0, 9.0],
        [1.6, _FA16, 0.0, 0.0, 0.0],
    ]
)


def _active_parts(s):
    """∫_0^s f_active, f_active(s), f_active'(s) for normalised stretch s (any shape)."""
    s = np.asarray(s, dtype=np.float64)
    s_ref, F0, p0, p1, p2 = _ACT_TABLE[np.searchsorted(_ACT_BREAKS, s, side="left")].T
    t = s - s_ref
    f = p0 + t * (p1 + t * p2)
    df = p1 + 2.0 * p2 * t
    F = F0 + t * (p0 + t * (0.5 * p1 + t * p2 / 3.0))
    return F, f, df


def _passive_parts(s, g1, g2):
    """∫_1^s f_passive, f_passive(s), f_passive'(s) (C¹ third branch of the ERRATA)."""
    s = np.asarray(s, dtype=np.float64)
    t = np.clip(s, 1.0, 1.4) - 1.0  # clipped so the exponential never overflows
    e = np.exp(g2 * t)
    E = math.exp(0.4 * g2)
    FP14 = g1 * (math.expm1(0.4 * g2) / g2 - 0.4)
    d = s - 1.4
    c = [s <= 1.0, s <= 1.4]
    F = np.select(c, [0.0, g1 * (np.expm1(g2 * t) / g2 - t)], FP14 + 0.5 * g1 * g2 * E * d**2 + g1 * (E - 1.0) * d)
    f = np.select(c, [0.0, g1 * (e - 1.0)], g1 * g2 * E * d + g1 * (E - 1.0))
    df = np.select(c, [0.0, g1 * g2 * e], g1 * g2 * E)
    return F, f, df


def f_active(lam_star):
    """Normalised active fibre force–length relation, eq. 26 with the ERRATA band.

    f = 9(λ*−0.4)² on [0.4, 0.6], 1 − 4(1−λ*)² on (0.6, 1.4], 9(λ*−1.6)² on (1.4, 1.6], else 0.

    Parameters
    ----------
    lam_star : array_like
        Normalised fibre stretch λ* = λ̂/λ̂0 (dimensionless).
    """
    return _active_parts(lam_star)[1]


def f_passive(lam_star, gamma1=0.05, gamma2=6.6):
    """Normalised passive fibre force, eq. 25 with the C¹ third branch of the ERRATA.

    f = 0 for λ* ≤ 1, γ1(e^(γ2(λ*−1)) − 1) on (1, 1.4],
    γ1γ2e^(0.4γ2)(λ*−1.4) + γ1(e^(0.4γ2) − 1) for λ* > 1.4.
    """
    return _passive_parts(lam_star, gamma1, gamma2)[1]


# --------------------------------------------------------------------------------------------
# transversely isotropic muscle (eqs. 22–26)


def _unit_fibers(fiber, n):
    if fiber is None:
        raise InputError("the muscle material needs fiber=(n, 3) unit fibre directions (reference configuration)")
    N = np.asarray(fiber, dtype=np.float64)
    if N.shape == (3,):
        N = np.broadcast_to(N, (n, 3))
    if N.shape != (n, 3):
        raise InputError(f"fiber must have shape ({n}, 3) or (3,), got {N.shape}")
    norm = np.sqrt(np.einsum("ni,ni->n", N, N))
    bad = ~(norm > 1e-12)
    if bad.any():
        raise InputError(f"{int(bad.sum())} of {n} fibre directions are zero or not finite; expected unit vectors")
    return N / norm[:, None]


def _activations(activation, n):
    a = np.asarray(0.0 if activation is None else activation, dtype=np.float64)
    if a.ndim == 0:
        a = np.full(n, float(a))
    if a.shape != (n,):
        raise InputError(f"activation must be a number or an array of shape ({n},), got shape {a.shape}")
    if not (np.isfinite(a).all() and (a >= 0.0).all() and (a <= 1.0).all()):
        raise InputError("activation α must lie in [0, 1] (eq. 24) at every material point")
    return a


@dataclasses.dataclass(frozen=True)
class TransverselyIsotropicMuscle:
    """Transversely isotropic uncoupled muscle material, eqs. 22–26 with the ERRATA.

    W = W_matrix(Ī1, Ī2, J) + W_fiber(λ̂)

    W_matrix = Σ_{1≤i+j≤2} C_ij (Ī1−3)^i (Ī2−3)^j + K/2 (J − 1)²    (eq. 23, Ī2 = I2 J^(−4/3))
    λ̂ ∂W_fiber/∂λ̂ = σ_max λ* (α f_active(λ*) + f_passive(λ*)),  λ* = λ̂/λ̂0,  λ̂ = √(N·C̄N)
                                                                        (eqs. 24–26)

    W_fiber(1) = 0. The fibre stress is deviatoric (see the module notes): at λ̂ = λ̂0, α = 1,
    σ_fiber = σ_max (n⊗n − I/3)/J.

    Parameters
    ----------
    C10, C01, C20, C02, C11 : float
        Matrix constants [N/cm²] (Table 2 as corrected in the ERRATA); C10 + C01 > 0 required
        (small-strain shear modulus 2(C10 + C01)).
    K : float
        Bulk modulus [N/cm²] (> 0).
    sigma_max : float
        Maximum isometric stress σ_max [N/cm²] (≥ 0), 30 N/cm² per ERRATA.
    lambda_opt : float
        Optimal fibre stretch λ̂0 (> 0); 1 puts the image configuration at optimal length.
    gamma1, gamma2 : float
        Passive fibre constants of eq. 25 (γ1 ≥ 0, γ2 > 0).

    Notes
    -----
    Methods take ``fiber`` (n, 3) or (3,) reference fibre directions (normalised here; a zero
    vector raises InputError) and ``activation`` α, a number or (n,) array in [0, 1] (default 0).
    """

    C10: float = 6.43
    C01: float = -3.8
    C20: float = 0.94
    C02: float = 0.0005
    C11: float = -0.0043
    K: float = 5000.0
    sigma_max: float = 30.0
    lambda_opt: float = 1.0
    gamma1: float = 0.05
    gamma2: float = 6.6

    def __post_init__(self):
        _as_const(self, [f.name for f in dataclasses.fields(self)])
        checks = [
            (self.C10 + self.C01 > 0, "C10 + C01 must be > 0 (shear modulus 2(C10 + C01))"),
            (self.K > 0, "K must be > 0 (bulk modulus, N/cm²)"),
            (self.sigma_max >= 0, "sigma_max must be >= 0 (N/cm²)"),
            (self.lambda_opt > 0, "lambda_opt must be > 0"),
            (self.gamma1 >= 0, "gamma1 must be >= 0"),
            (self.gamma2 > 0, "gamma2 must be > 0"),
        ]
        for ok, msg in checks:
            if not ok:
                raise InputError(f"TransverselyIsotropicMuscle: {msg}; got {self}")

    @property
    def shear_modulus(self) -> float:
        """Small-strain shear modulus of the matrix 2(C10 + C01) [N/cm²] (fibres passive, slack)."""
        return 2.0 * (self.C10 + self.C01)

    @property
    def bulk_modulus(self) -> float:
        """Small-strain bulk modulus K [N/cm²]."""
        return self.K

    # fibre energy and its λ̂-derivatives -------------------------------------------------
    def _fiber(self, lam, alpha):
        """W_fiber, g = ∂W_fiber/∂λ̂, g' = ∂²W_fiber/∂λ̂² at fibre stretch λ̂ (n,)."""
        l0, sm = self.lambda_opt, self.sigma_max
        s = lam / l0
        Fa, fa, dfa = _active_parts(s)
        Fp, fp, dfp = _passive_parts(s, self.gamma1, self.gamma2)
        Fa0 = float(_active_parts(1.0 / l0)[0])
        Fp0 = float(_passive_parts(1.0 / l0, self.gamma1, self.gamma2)[0])
        W = sm * (alpha * (Fa - Fa0) + (Fp - Fp0))
        g = (sm / l0) * (alpha * fa + fp)
        gp = (sm / l0**2) * (alpha * dfa + dfp)
        return W, g, gp

    def _parts(self, F, fiber, activation):
        kin = _Kinematics(F)
        N = _unit_fibers(fiber, kin.n)
        alpha = _activations(activation, kin.n)
        a = np.einsum("nij,nj->ni", kin.F, N)
        I4 = np.einsum("ni,ni->n", a, a)
        lam = np.sqrt(kin.j1 * I4)
        return kin, N, alpha, a, I4, lam

    def energy(self, F, *, fiber=None, activation=0.0):
        """Strain energy density W (n,) [N/cm²] at F (n, 3, 3)."""
        kin, N, alpha, a, I4, lam = self._parts(F, fiber, activation)
        x = kin.j1 * kin.I1 - 3.0
        y = kin.j1**2 * kin.I2 - 3.0
        Wm = (
            self.C10 * x
            + self.C01 * y
            + self.C20 * x * x
            + self.C02 * y * y
            + self.C11 * x * y
            + 0.5 * self.K * (kin.J - 1.0) ** 2
        )
        return Wm + self._fiber(lam, alpha)[0]

    def _eval(self, F, fiber, activation, tangent):
        kin, N, alpha, a, I4, lam = self._parts(F, fiber, activation)
        x = kin.j1 * kin.I1 - 3.0
        y = kin.j1**2 * kin.I2 - 3.0
        W1 = self.C10 + 2.0 * self.C20 * x + self.C11 * y
        W2 = self.C01 + 2.0 * self.C02 * y + self.C11 * x
        _, g, gp = self._fiber(lam, alpha)
        W4 = g / (2.0 * lam)
        d2W = None
        if tangent:
            d2W = np.zeros((kin.n, 3, 3))
            d2W[:, 0, 0] = 2.0 * self.C20
            d2W[:, 1, 1] = 2.0 * self.C02
            d2W[:, 0, 1] = d2W[:, 1, 0] = self.C11
            d2W[:, 2, 2] = (gp * lam - g) / (4.0 * lam**3)
        Up = self.K * (kin.J - 1.0)
        Upp = np.full(kin.n, self.K)
        P, A = _response(kin, [W1, W2, W4], d2W, Up, Upp, use_I2=True, fib=(a, N, I4), tangent=tangent)
        return kin, P, A

    def stress(self, F, *, fiber=None, activation=0.0):
        """First Piola–Kirchhoff stress P (n, 3, 3) [N/cm²]."""
        return self._eval(F, fiber, activation, False)[1]

    def stress_tangent(self, F, *, fiber=None, activation=0.0):
        """P (n, 3, 3) and A (n, 3, 3, 3, 3), ``A[n,i,J,k,L] = ∂P_iJ/∂F_kL`` [N/cm²]."""
        _, P, A = self._eval(F, fiber, activation, True)
        return P, A

    def cauchy(self, F, *, fiber=None, activation=0.0):
        """Cauchy stress σ = J⁻¹ P Fᵀ (n, 3, 3) [N/cm²]."""
        kin, P, _ = self._eval(F, fiber, activation, False)
        return _cauchy(kin, P)

    def fiber_stretch(self, F, *, fiber=None):
        """Isochoric fibre stretch λ̂ = √(N·C̄N) (n,) at F (n, 3, 3)."""
        return self._parts(F, fiber, 0.0)[5]


#: Table 2 (ERRATA) muscle with σ_max = 30 N/cm², λ̂0 = 1.
MUSCLE = TransverselyIsotropicMuscle()

_DEFAULTS = {"muscle": MUSCLE, "connective_tissue": CONNECTIVE_TISSUE, "fat": FAT}


def material_from_config(tissue: str, params: Mapping[str, Any] | None = None):
    """Material instance for a tissue name with the paper defaults, overridden by ``params``.

    Parameters
    ----------
    tissue : {"muscle", "connective_tissue", "fat"}
    params : mapping of constant name → number, optional
        Overrides of the defaults (Table 1, Table 2/ERRATA), e.g. ``{"lambda_opt": 1.4}``.

    Raises
    ------
    InputError
        Unknown tissue, unknown parameter name (the message lists the allowed ones), or a bad value.
    """
    if tissue not in _DEFAULTS:
        raise InputError(f"unknown tissue {tissue!r} for a material; expected one of {sorted(_DEFAULTS)}")
    base = _DEFAULTS[tissue]
    params = {} if params is None else dict(params)
    allowed = [f.name for f in dataclasses.fields(base)]
    unknown = [k for k in params if k not in allowed]
    if unknown:
        raise InputError(
            f"unknown material parameter(s) {', '.join(map(repr, unknown))} for tissue {tissue!r}; "
            f"allowed: {', '.join(allowed)}"
        )
    return dataclasses.replace(base, **params)

r"""Stress and tangent of an uncoupled hyperelastic energy, shared by the laws of the paper (§5).

Every material law (:mod:`pixmuscle.mechanics.materials`) is a frozen dataclass of constants in
N/cm² with the same interface, all arrays float64 and ``n`` the number of material points:

``energy(F, **kw)``          W, shape (n,), strain energy per unit reference volume [N/cm² = N·cm/cm³]
``stress(F, **kw)``          P, shape (n, 3, 3), first Piola–Kirchhoff stress [N/cm²]
``stress_tangent(F, **kw)``  (P, A) with ``A[n, i, J, k, L] = ∂P_iJ/∂F_kL`` (n, 3, 3, 3, 3) [N/cm²],
                             the first elasticity tensor ∂²W/∂F∂F (eq. 20 as corrected in ERRATA)
``cauchy(F, **kw)``          σ = J⁻¹ P Fᵀ, shape (n, 3, 3) [N/cm²]

A deformation gradient with det F ≤ 0 (or non-finite entries) raises
:class:`~pixmuscle.errors.SolverError`; the Newton solver catches it and cuts the step back.

Derivation (shared by the Yeoh and muscle laws)
-----------------------------------------------
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
crossed dyads c_HH H⊙H + c_FF F⊙F, δ_ik M_JL and c_B B_ik δ_JL. :func:`response` computes the
small per-point coefficients (c, c_HH, c_FF, M, c_B) with numpy and a numba kernel writes the 81
entries of A per point in one pass, so no (n,3,3,3,3) temporary is built per term.
"""

from __future__ import annotations

import dataclasses
import math

import numba
import numpy as np

from ...errors import InputError, SolverError

__all__ = ["Kinematics", "response", "cauchy_stress", "check_constants", "voigt9", "tangent9"]

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


class Kinematics:
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


def response(kin, dW, d2W, Up, Upp, *, use_I2, fib, tangent):
    """First Piola–Kirchhoff stress and first elasticity tensor of an uncoupled energy.

    Parameters
    ----------
    kin : Kinematics
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


def cauchy_stress(kin, P):
    """Cauchy stress σ = J⁻¹ P Fᵀ (n, 3, 3) from P (n, 3, 3) at the kinematics ``kin``."""
    return np.einsum("nik,njk->nij", P, kin.F) / kin.J[:, None, None]


def check_constants(obj) -> None:
    """Validate the constants of a material-law dataclass and store them as float.

    Every field must be a real, finite number within the bounds of its metadata (``gt``: strict
    lower bound; ``range``: inclusive (lo, hi), either None), the same bounds the config validator
    (:func:`pixmuscle.config.parse_section`) applies with key paths.

    Raises
    ------
    InputError
        ``<Law>.<name>``, what was expected (with the field's ``doc``) and what was given.
    """
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        where = f"{type(obj).__name__}.{f.name}"
        if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
            raise InputError(f"{where} must be a number (N/cm² or dimensionless), got {v!r}")
        v = float(v)
        if not math.isfinite(v):
            raise InputError(f"{where} must be finite, got {v!r}")
        gt = f.metadata.get("gt")
        lo, hi = f.metadata.get("range", (None, None))
        doc = f" ({f.metadata['doc']})" if "doc" in f.metadata else ""
        if gt is not None and not v > gt:
            raise InputError(f"{where} must be > {gt}{doc}, got {v}")
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            raise InputError(f"{where} must lie in [{lo}, {hi}]{doc}, got {v}")
        object.__setattr__(obj, f.name, v)

r"""Transversely isotropic muscle law of the paper (eqs. 22–26 with the ERRATA; Blemker-type).

    W = W_matrix(Ī1, Ī2, J) + W_fiber(λ̂),   λ̂ = √(N·C̄N),  N the reference fibre direction.

Needs the per-node fibre direction and the activation α. Stress and tangent follow the uncoupled
derivation of :mod:`.uncoupled`, with the fibre invariant Ī4.

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
from dataclasses import field

import numpy as np

from ...errors import InputError
from . import LAWS
from .uncoupled import Kinematics, cauchy_stress, check_constants, response

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


@LAWS.register("blemker", needs=("fiber", "activation"))
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

    C10: float = field(default=6.43, metadata={"doc": "N/cm²"})
    C01: float = field(default=-3.8, metadata={"doc": "N/cm²"})
    C20: float = field(default=0.94, metadata={"doc": "N/cm²"})
    C02: float = field(default=0.0005, metadata={"doc": "N/cm²"})
    C11: float = field(default=-0.0043, metadata={"doc": "N/cm²"})
    K: float = field(default=5000.0, metadata={"gt": 0, "doc": "bulk modulus, N/cm²"})
    sigma_max: float = field(default=30.0, metadata={"range": (0.0, None), "doc": "maximum isometric fibre stress, N/cm²"})
    lambda_opt: float = field(default=1.0, metadata={"gt": 0, "doc": "optimal fibre stretch λ̂0 (1.0: image configuration at optimal length)"})
    gamma1: float = field(default=0.05, metadata={"range": (0.0, None), "doc": "passive fibre constant γ1 of eq. 25"})
    gamma2: float = field(default=6.6, metadata={"gt": 0, "doc": "passive fibre constant γ2 of eq. 25"})

    def __post_init__(self):
        check_constants(self)
        if not self.C10 + self.C01 > 0:
            raise InputError(f"TransverselyIsotropicMuscle: C10 + C01 must be > 0 (shear modulus 2(C10 + C01)); got {self}")

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
        kin = Kinematics(F)
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
        P, A = response(kin, [W1, W2, W4], d2W, Up, Upp, use_I2=True, fib=(a, N, I4), tangent=tangent)
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
        return cauchy_stress(kin, P)

    def fiber_stretch(self, F, *, fiber=None):
        """Isochoric fibre stretch λ̂ = √(N·C̄N) (n,) at F (n, 3, 3)."""
        return self._parts(F, fiber, 0.0)[5]


#: Table 2 (ERRATA) muscle with σ_max = 30 N/cm², λ̂0 = 1.
MUSCLE = TransverselyIsotropicMuscle()

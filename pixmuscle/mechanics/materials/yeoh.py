r"""Yeoh law: uncoupled isotropic cubic polynomial in Ī1 (paper eq. 27, connective tissue and fat).

    W = C10(Ī1 − 3) + C20(Ī1 − 3)² + C30(Ī1 − 3)³ + K/2 (J − 1)²,  Ī1 = I1 J^(−2/3)

(Yeoh 1993, with the uncoupled volumetric term). Constants of Table 1: :data:`CONNECTIVE_TISSUE`
and :data:`FAT`. Stress and tangent: :func:`.uncoupled.response`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import field

import numpy as np

from . import LAWS
from .uncoupled import Kinematics, cauchy_stress, check_constants, response


@LAWS.register("yeoh", needs=())
@dataclasses.dataclass(frozen=True)
class Yeoh:
    """Yeoh law, paper eq. 27.

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

    C10: float = field(metadata={"gt": 0, "doc": "N/cm²; small-strain shear modulus 2·C10"})
    C20: float = field(metadata={"doc": "N/cm²"})
    C30: float = field(metadata={"doc": "N/cm²"})
    K: float = field(metadata={"gt": 0, "doc": "bulk modulus, N/cm²"})

    def __post_init__(self):
        check_constants(self)

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
        kin = Kinematics(F)
        x = kin.j1 * kin.I1 - 3.0
        return x * (self.C10 + x * (self.C20 + x * self.C30)) + 0.5 * self.K * (kin.J - 1.0) ** 2

    def _eval(self, F, tangent):
        kin = Kinematics(F)
        x = kin.j1 * kin.I1 - 3.0
        W1 = self.C10 + x * (2.0 * self.C20 + 3.0 * self.C30 * x)
        W11 = (2.0 * self.C20 + 6.0 * self.C30 * x)[:, None, None]
        Up = self.K * (kin.J - 1.0)
        Upp = np.full(kin.n, self.K)
        P, A = response(kin, [W1], W11, Up, Upp, use_I2=False, fib=None, tangent=tangent)
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
        return cauchy_stress(kin, P)


#: Table 1, connective tissue (N/cm²).
CONNECTIVE_TISSUE = Yeoh(C10=30.0, C20=80.0, C30=800.0, K=50000.0)
#: Table 1, fat: ten times softer than connective tissue (N/cm²).
FAT = Yeoh(C10=3.0, C20=8.0, C30=80.0, K=5000.0)

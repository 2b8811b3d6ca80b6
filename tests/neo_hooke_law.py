r"""A material law added in one file: the compressible neo-Hookean solid (registered as ``neo_hooke``).

    W = μ/2 (I1 − 3) − μ ln J + λ/2 (ln J)²,
    P = μ (F − H) + λ ln J H,                                   H = F⁻ᵀ,
    A = μ 𝕀 + λ H⊗H + (μ − λ ln J) H⊙H,   (H⊙H)_iJkL = H_iL H_kJ.

It is not of the uncoupled form Ŵ(C̄) + K/2 (J − 1)², so it has no ``bulk_modulus``: a solve with
it uses ``solve.volumetric.method: nodal``. Importing this module registers the law; nothing else
in pixmuscle changes.
"""

from __future__ import annotations

import dataclasses
from dataclasses import field

import numpy as np

from pixmuscle.mechanics.materials import LAWS
from pixmuscle.mechanics.materials.uncoupled import Kinematics, cauchy_stress, check_constants


@LAWS.register("neo_hooke", needs=())
@dataclasses.dataclass(frozen=True)
class NeoHooke:
    """Compressible neo-Hookean law (Lamé constants μ, λ in N/cm²)."""

    mu: float = field(default=3.0, metadata={"gt": 0, "doc": "shear modulus μ, N/cm²"})
    lam: float = field(default=50.0, metadata={"range": (0.0, None), "doc": "Lamé constant λ, N/cm²"})

    bulk_modulus = None  # no additive K/2 (J − 1)²: the projected volumetric energy does not apply

    def __post_init__(self):
        check_constants(self)

    def energy(self, F):
        kin = Kinematics(F)
        lnJ = np.log(kin.J)
        return 0.5 * self.mu * (kin.I1 - 3.0) - self.mu * lnJ + 0.5 * self.lam * lnJ**2

    def stress(self, F):
        kin = Kinematics(F)
        return self.mu * (kin.F - kin.H) + (self.lam * np.log(kin.J))[:, None, None] * kin.H

    def stress_tangent(self, F):
        kin = Kinematics(F)
        H = kin.H
        lnJ = np.log(kin.J)
        eye = np.eye(3)
        A = self.mu * np.einsum("ik,JL->iJkL", eye, eye)[None]
        A = A + self.lam * np.einsum("niJ,nkL->niJkL", H, H)
        A = A + (self.mu - self.lam * lnJ)[:, None, None, None, None] * np.einsum("niL,nkJ->niJkL", H, H)
        return self.stress(F), np.ascontiguousarray(A)

    def cauchy(self, F):
        return cauchy_stress(Kinematics(F), self.stress(F))

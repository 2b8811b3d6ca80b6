r"""The pressure unknowns of the mixed (displacement, pressure) form of the projected volumetric energy.

With the projected volumetric energy (:mod:`.volumetric`) the condensed tangent is
K = K_d + Gᵀ D G: K_d the tangent without the patch terms of the patches whose pressure is an
unknown, G (N_p' × 3N) their dilatation rates g_pᵀ, D = diag(V_p K̄_p). This module holds what a
solver of the mixed form needs of those patches: :class:`PressureSpace` (which patches, their
volumes, bulk and shear moduli, the scale w of the scaled form, their boxes on the patch grid) and
:class:`PatchDivergence` (G matrix-free, its transpose, its rows assembled). The system makes both
(:meth:`~.system.MechanicalSystem.pressure_space`, :meth:`~.system.MechanicalSystem.patch_divergence`);
the mixed method that uses them is :mod:`.linsolve.mixed_method`.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import scipy.sparse as sp


def pressure_scale(mu: np.ndarray, vp: np.ndarray, spacing) -> float:
    """w = mean_p(μ_p V_p) / s, N: the shear scale of the scaled mixed form (:mod:`.linsolve.mixed_method`).

    Parameters
    ----------
    mu, vp : (N_p,) float
        Shear modulus (N/cm²) and volume (cm³) of every pressure patch.
    spacing : (3,) float
        Voxel edges, cm; s is the smallest.
    """
    return float(np.mean(mu * vp)) / float(np.min(spacing))


@dataclasses.dataclass(frozen=True)
class PressureSpace:
    """The patches of a projected volumetric energy as unknowns of the mixed form.

    Attributes
    ----------
    n_patches : int
        N_p, all patches (held single-node patches included).
    free : (N_p',) int
        The patches whose pressure is an unknown (all but the held single-node ones), ascending.
    volume : (N_p,) float
        V_p, cm³.
    kbar : (N_p,) float
        Patch bulk modulus K̄_p, N/cm² (D = V_p K̄_p).
    shear : (N_p,) float
        Patch shear modulus μ_p (volume-weighted mean over its nodes of the reference tangent), N/cm².
    weight : float
        w = mean(μ_p V_p) / s over the free patches, N (:func:`pressure_scale`): the force a unit
        pressure residual stands for in the scaled mixed form.
    box : (N_p, 3) int
        Box index of each patch on the patch grid (the colours of the probed Schur diagonal).
    patch_of : (N,) int
        Patch of every node (the owner of a patch in a row partition is one of its nodes).
    """

    n_patches: int
    free: np.ndarray
    volume: np.ndarray
    kbar: np.ndarray
    shear: np.ndarray
    weight: float
    box: np.ndarray
    patch_of: np.ndarray

    def scaled_rhs(self, rp: np.ndarray, patches: np.ndarray) -> np.ndarray:
        """The pressure block −w r_p of the scaled mixed right-hand side on ``patches`` (n,), N,
        from the pressure residual ``rp`` (N_p,) θ_p − 1 − p_p/K̄_p (dimensionless)."""
        return -self.weight * np.asarray(rp, float)[patches]

    def update(self, q: np.ndarray, patches: np.ndarray) -> np.ndarray:
        """The pressure update Δp (N_p,) N/cm², 0 outside ``patches``, from the scaled unknowns
        q̃ = V_p Δp / w (n,) cm of ``patches``."""
        dp = np.zeros(self.n_patches)
        dp[patches] = self.weight * np.asarray(q, float) / self.volume[patches]
        return dp


class PatchDivergence:
    """The patch dilatation rates G (N_p' × 3N) of a subset of patches, matrix-free.

    (G x)_p = Σ_L Q_pL a_L : ∇̃x_L — the rate of the patch dilatation θ_p along x — and
    Gᵀ q = Σ_L B̃_Lᵀ ((Qᵀ q)_L a_L).

    Parameters
    ----------
    B, BT : ThreadedCSR (3N × N), (N × 3N)
        Stacked smoothed-gradient operators G_J (rows J·N + L) and their transpose
        (:class:`~.tangent.ProductForm`'s).
    a : (N, 3, 3) float
        a_L = J_L F_L⁻ᵀ.
    Q : CSR (N_p', N)
        Volume weights of the nodes of the chosen patches.
    """

    def __init__(self, B, BT, a: np.ndarray, Q: sp.csr_matrix):
        self.B, self.BT, self.Q = B, BT, Q
        self.n = a.shape[0]
        self.a = np.ascontiguousarray(a)  # [L, i, J]
        self.aT = np.ascontiguousarray(a.transpose(2, 0, 1))  # [J, L, i]
        self.QT = Q.T.tocsr()

    @property
    def shape(self) -> tuple[int, int]:
        return self.Q.shape[0], 3 * self.n

    def __matmul__(self, x: np.ndarray) -> np.ndarray:
        g = (self.B @ np.asarray(x).reshape(-1, 3)).reshape(3, self.n, 3)  # [J, L, i] = ∂x_i/∂X_J
        return self.Q @ np.einsum("jli,jli->l", self.aT, g)

    def of_gradient(self, grad: np.ndarray) -> np.ndarray:
        """G x (N_p',) from the nodal gradients grad[L, i, J] = ∂x_i/∂X_J (N, 3, 3) of x: what a
        product that has them already (:meth:`~.tangent.MatrixFreeTangent.apply`'s ``extra``) needs."""
        return self.Q @ np.einsum("lij,lij->l", self.a, grad)

    def stress(self, q: np.ndarray) -> np.ndarray:
        """(Qᵀ q)_L a_L (N, 3, 3): the nodal stress whose transposed gradient product is Gᵀ q."""
        t = self.QT @ q
        return t[:, None, None] * self.a

    def sparse(self) -> sp.csr_matrix:
        """G assembled (N_p' × 3N, columns node-major 3m + i), 1/cm."""
        n = self.n
        rows = [self.Q @ sum(sp.diags(self.aT[J, :, i]) @ self.B.matrix[J * n:(J + 1) * n] for J in range(3)) for i in range(3)]
        return sp.hstack(rows).tocsr()[:, np.arange(3 * n).reshape(3, n).T.ravel()]

    def T(self, q: np.ndarray) -> np.ndarray:
        """Gᵀ q, (3N,)."""
        t = self.QT @ q
        return (self.BT @ (t[None, :, None] * self.aT).reshape(-1, 3)).reshape(-1)

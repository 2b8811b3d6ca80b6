r"""Projected volumetric energy: a dilatation per patch of cells instead of per node.

Why. With nodal integration every node L carries its own volumetric energy V_L U(J_L),
U = K/2 (J − 1)², so a nearly incompressible body (K/μ ≈ 10²–10⁴ in the paper's tissues) must keep
det F_L ≈ 1 at *every* node. Linear RK fields with a ≈ 1.65 h supports are too smooth to do that
and still deform: the model *locks* (too stiff, more so the larger K/μ), and the same stiff
constraints make the linear systems ill-conditioned.

What. The volumetric energy is evaluated with the mean dilatation of a patch p of neighbouring
cells (a box of ``patch`` voxels on the grid; default 2 × 2 × 3: two by two in-plane, three slices):

    θ_p = (1/V_p) Σ_{L∈p} V_L J_L,    V_p = Σ_{L∈p} V_L,    K̄_p = (1/V_p) Σ_{L∈p} V_L K_L,

    Π = Σ_L V_L Ŵ_L(F_L) + Σ_p V_p K̄_p/2 (θ_p − 1)²,

i.e. the three-field (Hu–Washizu) formulation with a dilatation and a pressure constant on each
patch, condensed patch by patch — the nodal-integration analogue of the mean-dilatation / Q1-P0
element (Nagtegaal, Parks & Rice 1974; Simo, Taylor & Pister 1985) and of the pressure
projection of Chen, Yoon, Wang & Liu (2000, CMAME 181:117–145) for nearly incompressible RKPM.
One volumetric constraint per patch instead of per node removes the locking; a patch of one cell
gives back the nodal formulation exactly. The patches span three slices because the locking of
the voxel models comes from the coarse slice direction (the Example-1 tendon: +5.8 % → +0.2 %
against converged finite elements with 1 × 1 × 3 patches). They span two voxels in-plane because a
1 × 1 × 3 patch pressure is not inf-sup stable on the voxel grid: a pressure alternating between
neighbouring voxel columns (a checkerboard) does not change the displacements, so no
preconditioner of the mixed form (:mod:`.linsolve.mixed`) is robust in K/μ with it; 2 × 2 × 3
patches are stable (``benchmarks/bench_solve.py --infsup``). A 2 × 2 × 3 patch shares one pressure across in-plane interfaces of muscles
and tissues; against 1 × 1 × 3 it moves the forces of the verification cases by at most 0.03 %,
the clamped active block's (α = 0.95) by −4.2 % and the demo's by −0.9 %
(``benchmarks/bench_patch.py``, measured with ``held: own``; ``benchmarks/results/bench_patch.md``).

Equations. With a_L = ∂J/∂F = J F⁻ᵀ at node L and the patch pressure p_p = K̄_p (θ_p − 1):

    f_int,I = Σ_L V_L P̃_L b̃_I(X_L),   P̃_L = P_L + (p_p − K_L (J_L − 1)) a_L,

(P_L the node's own first Piola–Kirchhoff stress, whose volumetric part K_L (J_L − 1) a_L is
replaced by the patch pressure), and the consistent tangent is

    K = Σ_L V_L B̃_Lᵀ Ã_L B̃_L + Σ_p V_p K̄_p g_p g_pᵀ,
    Ã_L = A_L − K_L a_L⊗a_L + (p_p − K_L (J_L − 1)) ∂a_L/∂F,
    g_p = (1/V_p) Σ_{L∈p} V_L B̃_Lᵀ a_L,                      ∂a_iJ/∂F_kL = J (H_iJ H_kL − H_iL H_kJ),

H = F⁻ᵀ. The first sum is the usual nodal form with a per-node tangent; the second is one rank-one
term per patch, cheap in a matrix-free product (:meth:`PatchProjection.apply`) and assembled on
the patch pattern for direct solvers. The energy, residual and tangent are consistent, so Newton
keeps its quadratic convergence (tests check the tangent against finite differences).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import scipy.sparse as sp

#: nodes per block of the per-node moduli work (the material evaluation and :meth:`PatchProjection.tangent`):
#: 21 MB per (block, 81) float64 array
NODE_BLOCK = 1 << 15


def shear_moduli(A0: np.ndarray) -> np.ndarray:
    """Small-strain shear modulus μ of each node from its reference tangent A(F = I), (N,) N/cm².

    The mean of the three shear entries A_iJiJ (i ≠ J) of A0 (N, 3, 3, 3, 3): the scale of the
    pressure mass diag(1/(μ_p V_p)) that measures the patch pressures' inf-sup stability.
    """
    return (A0[:, 0, 1, 0, 1] + A0[:, 0, 2, 0, 2] + A0[:, 1, 2, 1, 2]) / 3.0


@dataclasses.dataclass
class VolumetricState:
    """Patch quantities at one deformation.

    Attributes
    ----------
    J : (N,) float
        det F_L.
    a : (N, 3, 3) float
        a_L = J_L F_L⁻ᵀ (dimensionless).
    dtheta : (N_p,) float
        θ_p − 1 per patch (computed as the mean of J_L − 1, so it is exactly 0 at F = I).
    pressure : (N_p,) float
        Patch pressure p_p = K̄_p (θ_p − 1), N/cm².
    shift : (N,) float
        p_p − K_L (J_L − 1) at each node: the change of the node's mean stress, N/cm².
    """

    J: np.ndarray
    a: np.ndarray
    dtheta: np.ndarray
    pressure: np.ndarray
    shift: np.ndarray


class PatchProjection:
    """Mean dilatation on patches of voxel cells (see the module docstring).

    Parameters
    ----------
    ijk : (N, 3) int
        Voxel indices of the nodes (cells).
    volume : (N,) float
        Cell volumes V_L, cm³.
    bulk : (N,) float
        Bulk modulus K_L of each node's material, N/cm².
    patch : (3,) int
        Patch size in voxels per axis; patches are the boxes ⌊ijk / patch⌋ of the grid. Default
        (2, 2, 3), as ``solve.volumetric.patch``.
    single : (N,) bool, optional
        Nodes that keep a patch of their own (their nodal volumetric energy): the nodes held by a
        boundary condition at the node itself when ``solve.volumetric.held`` is ``own`` (the
        default); none with ``held: patch``. A patch that mixes held nodes with free ones lets
        the free half of a held node's cell trade volume with its neighbours at no volumetric
        cost, a mechanism that an active muscle pulling on its clamp exploits: the clamped
        oblique-fibre block held at its end nodes is 2.8–3.3 % off the finite elements with
        ``held: patch`` against at most 1.2 % with ``own`` (``tests/test_active_block.py``), and
        the demo with ``penalty.at: nodes`` falls from 544 N to 149 N at α = 0.95.

    Attributes
    ----------
    patch_of : (N,) int
        Patch index of every node (0..N_p − 1).
    Q : CSR (N_p, N)
        Volume weights V_L / V_p of the nodes of each patch (θ = Q J).
    kbar : (N_p,) float
        Volume-averaged bulk modulus K̄_p, N/cm².
    vp : (N_p,) float
        Patch volumes V_p, cm³.
    held : (N_p,) bool
        Patches of one held node (``single``).
    """

    def __init__(self, ijk: np.ndarray, volume: np.ndarray, bulk: np.ndarray, patch=(2, 2, 3), single=None):
        ijk = np.asarray(ijk, np.int64)
        patch = np.broadcast_to(np.asarray(patch, np.int64), (3,))
        if np.any(patch < 1):
            raise ValueError(f"patch sizes must be >= 1 voxel, got {patch.tolist()}")
        key = ijk // patch
        key = key - key.min(axis=0)
        flat = np.ravel_multi_index(key.T, key.max(axis=0) + 1)
        single = np.zeros(ijk.shape[0], bool) if single is None else np.asarray(single, bool)
        if np.any(single):
            flat[single] = flat.max() + 1 + np.arange(int(single.sum()))
        _, self.patch_of = np.unique(flat, return_inverse=True)
        self.patch_of = self.patch_of.astype(np.int64).reshape(-1)
        n = ijk.shape[0]
        self.n_nodes = n
        self.n_patches = int(self.patch_of.max()) + 1 if n else 0
        self.held = np.zeros(self.n_patches, bool)
        self.held[self.patch_of[single]] = True
        self.volume = np.asarray(volume, float)
        self.bulk = np.asarray(bulk, float)
        self.vp = np.bincount(self.patch_of, weights=self.volume, minlength=self.n_patches)
        w = self.volume / self.vp[self.patch_of]
        self.Q = sp.csr_matrix((w, (self.patch_of, np.arange(n))), shape=(self.n_patches, n))
        self.kbar = self.Q @ self.bulk
        self.patch = patch

    def restricted(self, keep: np.ndarray) -> PatchProjection:
        """The same patches with the rank-one terms of the patches not in ``keep`` (N_p,) bool removed.

        Used by the mixed solvers: the patch terms of ``keep`` stay in the displacement block,
        the others become pressure unknowns.
        """
        out = object.__new__(PatchProjection)
        out.__dict__.update(self.__dict__)
        out.kbar = np.where(keep, self.kbar, 0.0)
        return out

    def structure(self) -> sp.csr_matrix:
        """Patch–node membership (N_p × N), ones."""
        S = self.Q.copy()
        S.data[:] = 1.0
        return S

    def state(self, F: np.ndarray) -> VolumetricState:
        """Patch dilatation and pressure at the deformation gradients F (N, 3, 3)."""
        J = np.linalg.det(F)
        H = np.linalg.inv(F).transpose(0, 2, 1)
        a = J[:, None, None] * H
        dtheta = self.Q @ (J - 1.0)
        pressure = self.kbar * dtheta
        shift = pressure[self.patch_of] - self.bulk * (J - 1.0)
        return VolumetricState(J=J, a=a, dtheta=dtheta, pressure=pressure, shift=shift)

    def carried(self, vs: VolumetricState, pressure: np.ndarray) -> VolumetricState:
        """``vs`` with the patch pressure ``pressure`` (N_p,) N/cm² in place of K̄_p (θ_p − 1): the
        pressure a Newton iteration carries (:meth:`~..solve.MechanicalSystem.linearised_pressure`)."""
        shift = pressure[self.patch_of] - self.bulk * (vs.J - 1.0)
        return dataclasses.replace(vs, pressure=np.asarray(pressure, float), shift=shift)

    def stress(self, P: np.ndarray, vs: VolumetricState) -> np.ndarray:
        """P̃_L = P_L + (p_p − K_L (J_L − 1)) a_L, N/cm², shape (N, 3, 3)."""
        return P + vs.shift[:, None, None] * vs.a

    def tangent(self, A: np.ndarray, vs: VolumetricState, overwrite: bool = False,
                block: int = NODE_BLOCK) -> np.ndarray:
        """Per-node part Ã_L = A_L − K_L a⊗a + shift_L ∂a/∂F, N/cm², shape (N, 3, 3, 3, 3).

        ``overwrite``: write Ã into ``A`` (else into a new array). The terms are made by blocks of
        ``block`` nodes, so their temporaries are (block, 81), not (N, 81): the same numbers."""
        a, J = vs.a, vs.J
        out = A if overwrite else A.copy()
        for lo in range(0, out.shape[0], block):
            s = slice(lo, lo + block)
            H = a[s] / J[s, None, None]
            out[s] -= self.bulk[s, None, None, None, None] * np.einsum("nij,nkl->nijkl", a[s], a[s])
            # shift · ∂a/∂F = shift · J (H⊗H − H⊙H)
            c = (vs.shift[s] * J[s])[:, None, None, None, None]
            out[s] += c * np.einsum("nij,nkl->nijkl", H, H)
            out[s] -= c * np.einsum("nil,nkj->nijkl", H, H)
        return out

    def energy_correction(self, J: np.ndarray, dtheta: np.ndarray) -> float:
        """Σ_p V_p K̄_p/2 (θ_p − 1)² − Σ_L V_L K_L/2 (J_L − 1)², N·cm (added to the nodal energy)."""
        patch = 0.5 * float(np.sum(self.vp * self.kbar * dtheta**2))
        nodal = 0.5 * float(np.sum(self.volume * self.bulk * (J - 1.0) ** 2))
        return patch - nodal

    def apply(self, grad: np.ndarray, vs: VolumetricState) -> np.ndarray:
        """Stress increment of the rank-one patch terms for a displacement-gradient field.

        For nodal gradients ∇̃x_L (the smoothed gradient of a nodal field x), returns
        V_L K̄_p s̄_p a_L with s̄_p = (1/V_p) Σ_{L∈p} V_L a_L : ∇̃x_L, so that
        Σ_L B̃_Lᵀ (returned)_L = Σ_p V_p K̄_p g_p (g_p · x).

        Parameters
        ----------
        grad : (N, 3, 3) float
            ∇̃x_L[i, J] = ∂x_i/∂X_J at every node, cm⁻¹ × units of x.
        vs : VolumetricState

        Returns
        -------
        (N, 3, 3) float
        """
        s = np.einsum("nij,nij->n", vs.a, grad)
        sbar = self.Q @ s
        coef = (self.kbar * sbar)[self.patch_of] * self.volume
        return coef[:, None, None] * vs.a

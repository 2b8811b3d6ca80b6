"""Finite-element reference for the tendon stretch of Example 1 (scikit-fem).

An independent check of the meshfree solver: total-Lagrangian finite-strain hyperelasticity of
the connective-tissue law, paper eq. (27),

    W(F) = C10 (Ī1 − 3) + C20 (Ī1 − 3)² + C30 (Ī1 − 3)³ + K/2 (J − 1)²,   Ī1 = J^(-2/3) tr(FᵀF),

(constants of Table 1, N/cm²: C10 = 30, C20 = 80, C30 = 800, K = 50 000), on the *voxel domain*
of :mod:`pixmuscle.verify.tendon_geometry` (the same union of voxel boxes the meshfree model is
built from). The constitutive law is written here from scratch, independently of
``pixmuscle.mechanics.materials``.

Discretisation
--------------
Each voxel is one hexahedron, split into ``r_x × r_y × r_z`` equal boxes for refinement
(scikit-fem ``MeshHex``). With K / C10 ≈ 1700 the law is nearly incompressible (ν ≈ 0.4994), so a
displacement element that does not lock is needed:

``element="mixed"`` (default)
    Q2–P1disc: triquadratic displacements (``ElementHex2``, 27 nodes) and a pressure that is linear
    and discontinuous in each element, in a perturbed-Lagrangian u–p form
    ``L = ∫ W_iso + p (J − 1) − p² / (2K)``. Newton iterates on (u, p) together; the element
    pressures are condensed out of each linear system (leaving a symmetric system in u) and
    recovered from it. At convergence p is the element-wise L2 projection of K (J − 1).
    Q2–P1disc satisfies the inf-sup condition: the robust choice. (Iterating on u alone with
    p = K Π_e(J − 1) — a penalty method — needs many more Newton iterations: the second-order
    volume error of each predictor is amplified by K.)
``element="hex27"``
    Pure-displacement triquadratic hexahedra with the full volumetric term (mildly over-stiff at
    coarse meshes; converges to the same limit — a cross-check).

Both use the 3 × 3 × 3 Gauss rule. scikit-fem supplies the mesh, element, quadrature and degree-of-
freedom numbering; the element matrices are formed here with vectorised einsum/matmul over all
elements at once (scikit-fem's ``BilinearForm`` loops over the 81 × 81 local basis pairs of a
vector Q2 element and is ~10 ms per element here, too slow for a Newton loop; the test suite
checks this assembly against a ``BilinearForm`` on a small mesh). All voxel boxes have the same
size, so the reference gradients are the same in every element. Linear systems: SuperLU
(COLAMD) factorisations, each reused as the preconditioner of conjugate gradients on later
tangents until refactoring pays (:class:`_TangentSolver`).

Boundary conditions (``bc``)
----------------------------
``"clamped"`` (Example 1): bottom face z = z_min fixed in x, y, z ("fixed in all directions");
top face z = z_max displaced by ``d`` in +z with u_x = u_y = 0 ("stretched in the axial
direction" — the top is held by the loading grip, so no lateral motion).
``"roller"`` (for the uniaxial check): bottom u_z = 0, top u_z = d, lateral motion free; rigid
motions removed by the symmetry planes (or a pinned node when the mask is not symmetric).

The ends are the outer faces of the first and last occupied slices (``ends="faces"``, the voxel
domain) or, with ``ends="centres"``, the planes through the centres of those slices — where a
voxel-centred meshfree model holding its end node layers effectively grips the body (one slice
shorter: 2.6 % of the default 19-cm tendon, so the choice matters for a 3 % comparison).

If the mask is mirror-symmetric about the grid centre in x and/or y (as the tendon is), only the
half/quarter x ≥ 0, y ≥ 0 is meshed with symmetry conditions (u_x = 0 on x = 0, u_y = 0 on y = 0)
and forces are multiplied back (×2 per plane).

Convergence (default tendon, ``tendon_voxels((0.1, 0.1, 0.5))``, clamped, 2 cm, mixed)
---------------------------------------------------------------------------------------
Final force 16.559 N (refine 1, 23.7 k dofs), 16.564 N (refine (2, 2, 1), 85 k dofs), 16.517 N
((1, 1, 2), 47 k dofs), 16.505 N ((1, 1, 4), 93 k dofs): in-plane refinement changes it by
0.03 %, z refinement by 0.26 % then 0.07 %. ``refine=(1, 1, 2)`` (≈ 3 min on one core) is within
0.1 % of the converged value.

Units: cm, N, N/cm².
"""

import csv
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from pixmuscle.errors import InputError, SolverError
from pixmuscle.mechanics.materials import CONNECTIVE_TISSUE as _TABLE1_CT
from pixmuscle.verify.tendon_geometry import grid_spacing

__all__ = [
    "CONNECTIVE_TISSUE",
    "cubic_energy",
    "cubic_stress_tangent",
    "voxel_hex_mesh",
    "tendon_fem_reaction",
    "convergence_study",
    "reference_table",
    "plot_comparison",
    "write_tendon_reference",
]

#: Table 1, connective tissue: (C10, C20, C30, K) in N/cm² (the constants of the package's law; the
#: energy, stress and tangent below are this module's own).
CONNECTIVE_TISSUE = (_TABLE1_CT.C10, _TABLE1_CT.C20, _TABLE1_CT.C30, _TABLE1_CT.K)

_EYE = np.eye(3)
_I4 = np.einsum("ik,JL->iJkL", _EYE, _EYE)  # δ_ik δ_JL, index order [i, J, k, L]


# ----------------------------------------------------------------------------------------------
# constitutive law, eq. (27)
# ----------------------------------------------------------------------------------------------

def _invariants(F):
    J = np.linalg.det(F)
    if np.any(~(J > 0)):
        raise SolverError(f"inverted or degenerate material point: min det F = {np.nanmin(J):.3g}")
    H = np.linalg.inv(F).swapaxes(-1, -2)  # F^-T
    I1 = np.einsum("...iJ,...iJ->...", F, F)
    return J, H, I1


def cubic_energy(F, C10, C20, C30, K):
    """Strain energy density of eq. (27).

    Parameters
    ----------
    F : ndarray, shape (n, 3, 3)
        Deformation gradients.
    C10, C20, C30, K : float
        Material constants, N/cm².

    Returns
    -------
    ndarray, shape (n,)
        W in N·cm/cm³ (= N/cm²).
    """
    J, _, I1 = _invariants(np.asarray(F, float))
    e = J ** (-2.0 / 3.0) * I1 - 3.0
    return C10 * e + C20 * e**2 + C30 * e**3 + 0.5 * K * (J - 1.0) ** 2


def cubic_stress_tangent(F, C10, C20, C30, K=None, pressure=None):
    """First Piola–Kirchhoff stress and its derivative for eq. (27).

    The volumetric part is either ``K/2 (J − 1)²`` (``pressure=None``) or, in the mixed form, the
    term ``p (J − 1)`` with a given pressure field ``p`` (then ``K`` is not used).

    Parameters
    ----------
    F : ndarray, shape (n, 3, 3)
        Deformation gradients.
    C10, C20, C30 : float
        Isochoric constants, N/cm².
    K : float, optional
        Bulk modulus, N/cm² (displacement formulation).
    pressure : ndarray, shape (n,), optional
        Pressure p, N/cm² (mixed formulation).

    Returns
    -------
    P : ndarray, shape (n, 3, 3)
        ``P_iJ = ∂W/∂F_iJ``, N/cm².
    A : ndarray, shape (n, 3, 3, 3, 3)
        ``A[n, i, J, k, L] = ∂P_iJ / ∂F_kL``, N/cm².
    """
    F = np.asarray(F, float)
    J, H, I1 = _invariants(F)
    j23 = J ** (-2.0 / 3.0)
    e = j23 * I1 - 3.0
    psi1 = C10 + 2.0 * C20 * e + 3.0 * C30 * e**2          # dΨ/dĪ1
    psi2 = 2.0 * C20 + 6.0 * C30 * e                      # d²Ψ/dĪ1²
    G = 2.0 * j23[:, None, None] * (F - (I1 / 3.0)[:, None, None] * H)   # dĪ1/dF
    HH = np.einsum("niJ,nkL->niJkL", H, H)
    HHt = np.einsum("niL,nkJ->niJkL", H, H)
    FH = np.einsum("niJ,nkL->niJkL", F, H)
    dG = j23[:, None, None, None, None] * (
        2.0 * _I4
        - (4.0 / 3.0) * (FH + FH.transpose(0, 3, 4, 1, 2))
        + (4.0 / 9.0) * I1[:, None, None, None, None] * HH
        + (2.0 / 3.0) * I1[:, None, None, None, None] * HHt)
    P = psi1[:, None, None] * G
    A = (psi2[:, None, None, None, None] * np.einsum("niJ,nkL->niJkL", G, G)
         + psi1[:, None, None, None, None] * dG)
    if pressure is None:
        if K is None:
            raise InputError("cubic_stress_tangent(): give either K or pressure")
        # d/dF [K (J-1) J H] = K J (2J - 1) H⊗H - K (J-1) J H_iL H_kJ
        P = P + (K * (J - 1.0) * J)[:, None, None] * H
        A = A + (K * J * (2.0 * J - 1.0))[:, None, None, None, None] * HH \
              - (K * (J - 1.0) * J)[:, None, None, None, None] * HHt
    else:
        pJ = np.asarray(pressure, float) * J
        P = P + pJ[:, None, None] * H
        A = A + pJ[:, None, None, None, None] * (HH - HHt)
    return P, A


# ----------------------------------------------------------------------------------------------
# mesh of the voxel domain
# ----------------------------------------------------------------------------------------------

@dataclass
class VoxelHexMesh:
    """Hexahedral mesh of a voxel domain (possibly one half/quarter by symmetry).

    Attributes
    ----------
    mesh : skfem.MeshHex
        One box per voxel sub-cell, cm.
    planes : dict
        ``{axis: coordinate}`` of the symmetry planes used (axis 0 = x, 1 = y), cm.
    factor : int
        Multiplier from the meshed part to the whole domain (1, 2 or 4).
    cell : ndarray, shape (3,)
        Edge lengths of every element, cm.
    """

    mesh: object
    planes: dict
    factor: int
    cell: np.ndarray


def _refine_tuple(refine):
    r = np.broadcast_to(np.asarray(refine), (3,)).astype(int)
    if np.any(r < 1) or not np.all(np.broadcast_to(np.asarray(refine), (3,)) == r):
        raise InputError(f"refine must be a positive integer or three of them, got {refine}")
    return r


def voxel_hex_mesh(mask, affine_cm, refine=1, symmetry=True, ends="faces"):
    """Hexahedral mesh of the union of the voxel boxes of ``mask``.

    Parameters
    ----------
    mask : ndarray of bool, shape (I, J, K)
        Voxels of the body.
    affine_cm : ndarray, shape (4, 4)
        Grid-aligned voxel index → cm (voxel centres); each voxel is the box of size ``spacing``
        centred there.
    refine : int or sequence of 3 int
        Sub-boxes per voxel edge along x, y, z.
    symmetry : bool
        Mesh only x ≥ x_c (y ≥ y_c) when the mask is mirror-symmetric about the grid centre
        plane x = x_c (y = y_c) and that plane falls on sub-box faces.
    ends : {"faces", "centres"}
        ``"faces"``: the body spans the whole first and last occupied slices (ends on the voxel
        faces). ``"centres"``: the half slices outside the first and last voxel-centre planes are
        left out, so the ends lie on the planes of the end node layers of a voxel-centred
        meshfree model (needs an even refinement in z).

    Returns
    -------
    VoxelHexMesh
    """
    from skfem import MeshHex

    mask = np.asarray(mask)
    if mask.ndim != 3 or mask.dtype != bool:
        raise InputError(f"mask must be a 3-D boolean array, got {mask.dtype} {mask.shape}")
    if not mask.any():
        raise InputError("mask has no voxels: nothing to mesh")
    h = grid_spacing(affine_cm)
    r = _refine_tuple(refine)
    fine = mask
    for a in range(3):
        fine = np.repeat(fine, r[a], axis=a)
    cell = h / r
    lower = np.asarray(affine_cm, float)[:3, 3] - 0.5 * h      # corner of voxel (0, 0, 0)

    planes, factor = {}, 1
    keep = np.ones(fine.shape, bool)
    if ends == "centres":
        if r[2] % 2:
            raise InputError(f"ends='centres' cuts voxels at mid-slice and needs an even "
                             f"refinement in z, got refine {tuple(r)}")
        occupied = np.flatnonzero(mask.any(axis=(0, 1)))
        keep[:, :, :occupied[0] * r[2] + r[2] // 2] = False
        keep[:, :, occupied[-1] * r[2] + r[2] // 2:] = False
    elif ends != "faces":
        raise InputError(f"ends must be 'faces' or 'centres', got {ends!r}")
    if symmetry:
        for a in (0, 1):
            n = fine.shape[a]
            if np.array_equal(mask, np.flip(mask, axis=a)) and n % 2 == 0:
                planes[a] = lower[a] + 0.5 * n * cell[a]
                factor *= 2
                sl = [slice(None)] * 3
                sl[a] = slice(0, n // 2)
                keep[tuple(sl)] = False
    cells = np.argwhere(fine & keep)                           # (nel, 3) lower-corner indices
    offsets = np.array([[0, 0, 0], [0, 0, 1], [0, 1, 0], [1, 0, 0],
                        [0, 1, 1], [1, 0, 1], [1, 1, 0], [1, 1, 1]])   # skfem MeshHex order
    lattice = np.array(fine.shape) + 1
    corners = cells[:, None, :] + offsets[None, :, :]           # (nel, 8, 3)
    lin = np.ravel_multi_index(corners.reshape(-1, 3).T, lattice)
    used, t = np.unique(lin, return_inverse=True)
    p = lower[:, None] + cell[:, None] * np.array(np.unravel_index(used, lattice), float)
    mesh = MeshHex(np.ascontiguousarray(p), np.ascontiguousarray(t.reshape(-1, 8).T, np.int32))
    return VoxelHexMesh(mesh, planes, factor, cell)


# ----------------------------------------------------------------------------------------------
# discretisation and assembly
# ----------------------------------------------------------------------------------------------

class _Discretization:
    """Q2 vector field on a uniform box mesh: dofs, reference gradients, sparsity."""

    def __init__(self, vmesh, element):
        from skfem import CellBasis, ElementHex2

        mesh = vmesh.mesh
        ext = np.ptp(mesh.p[:, mesh.t], axis=1)                 # (3, nel) element extents
        if not np.allclose(ext, vmesh.cell[:, None], rtol=1e-9, atol=0):
            raise InputError("voxel_hex_mesh produced elements of unequal size")
        basis = CellBasis(mesh, ElementHex2(), intorder=5, elements=np.array([0]))
        self.element = element
        self.nsd = basis.N                                     # scalar Q2 dofs
        self.N = 3 * self.nsd
        self.sdofs = basis.dofs.element_dofs.T.astype(np.int64)  # (nel, 27)
        self.nel = self.sdofs.shape[0]
        self.doflocs = basis.doflocs.T                         # (nsd, 3) cm
        # reference gradients and weights, identical in every element (same box, translated)
        self.G = np.stack([b[0].grad[:, 0, :] for b in basis.basis], axis=0).transpose(2, 0, 1)
        self.w = basis.dx[0].copy()                            # (nq,) weight × |det DF|
        # element-local P1 pressure basis 1, ξ-½, η-½, ζ-½ (reference coords ↔ box coords)
        X = basis.X                                            # (3, nq) in [0, 1]^3
        self.Np = np.vstack([np.ones(X.shape[1]), X - 0.5]).T  # (nq, 4)
        self.Minv = np.linalg.inv((self.Np * self.w[:, None]).T @ self.Np)
        self.volume = self.w.sum() * self.nel
        # vector dofs per element: index 3a + i  ↔  global 3 * sdof[a] + i
        self.edofs = (3 * self.sdofs[:, :, None] + np.arange(3)).reshape(self.nel, 81)
        self._pattern()

    def _pattern(self):
        rows = np.repeat(self.edofs, 81, axis=1).ravel()
        cols = np.tile(self.edofs, (1, 81)).ravel()
        keys = rows * self.N + cols
        ukeys, inv = np.unique(keys, return_inverse=True)
        self.map = inv.astype(np.int64 if ukeys.size > 2**31 - 1 else np.int32)
        r = ukeys // self.N
        self.indptr = np.searchsorted(r, np.arange(self.N + 1)).astype(np.int64)
        self.indices = (ukeys % self.N).astype(np.int32)
        self.nnz = ukeys.size

    def gather(self, u):
        """Element displacements (nel, 27, 3) from the global vector (3 N_s,)."""
        return u.reshape(-1, 3)[self.sdofs]

    def pressure_of(self, u, material):
        """Element pressure coefficients (nel, 4) solving R_p = 0: p = K · Π_e(J − 1)."""
        K = material[3]
        J = np.linalg.det(self._F(self.gather(u)).reshape(-1, 3, 3)).reshape(self.nel, -1)
        return K * ((J - 1.0) @ (self.Np * self.w[:, None])) @ self.Minv

    def _F(self, Ue):
        return _EYE + np.einsum("eai,qaJ->eqiJ", Ue, self.G, optimize=True)

    def assemble(self, u, material, pi=None, tangent=True, chunk=512):
        """Internal forces, tangent and stored energy at displacement u (and pressure pi).

        Parameters
        ----------
        u : ndarray, shape (N,)
            Nodal displacements, cm (index ``3 * scalar_dof + component``).
        material : (C10, C20, C30, K)
            N/cm².
        pi : ndarray, shape (nel, 4), optional
            ``"mixed"`` only: element pressure coefficients on the basis ``Np`` (N/cm²). If
            omitted, the pressure solving R_p = 0 for this u is used (``pressure_of``), which
            makes ``f`` and ``K`` the gradient and Hessian of the reduced energy
            ``∫ W_iso + K/2 ∫ Π_e(J − 1)²``.
        tangent : bool
            Also assemble the tangent.

        Returns
        -------
        f : ndarray, shape (N,)
            Internal force ``∫ P : Grad δu``, N.
        K : scipy.sparse.csr_matrix (N, N) or None
            Tangent; for ``"mixed"`` the pressure-condensed ``K_uu + K Bᵀ M⁻¹ B``.
        energy : float
            ``∫ W`` (hex27) or the Lagrangian ``∫ W_iso + p (J − 1) − p²/(2K)`` (mixed), N·cm.
        extra : dict
            ``"mixed"``: ``rp`` (nel, 4) pressure residual ``∫ Np (J − 1 − p/K)``, cm³;
            ``B`` (nel, 4, 81) ``∫ Np J F⁻ᵀ : Grad φ``, cm³/cm (only with ``tangent``);
            ``c`` (N,) the condensed residual correction ``Σ_e K Bᵀ M⁻¹ rp``, N; ``pi``.
        """
        C10, C20, C30, K = material
        G, w, nq = self.G, self.w, self.w.size
        mixed = self.element == "mixed"
        if mixed and pi is None:
            pi = self.pressure_of(u, material)
        f = np.zeros(self.N)
        data = np.empty(self.nel * 81 * 81) if tangent else None
        extra = {}
        if mixed:
            Npw = self.Np * w[:, None]
            M = Npw.T @ self.Np
            extra = dict(pi=pi, rp=np.empty((self.nel, 4)),
                         B=np.empty((self.nel, 4, 81)) if tangent else None,
                         c=np.zeros(self.N) if tangent else None)
        energy = 0.0
        wG = (w[:, None, None] * G).transpose(0, 2, 1).reshape(nq * 3, 27)   # [(q, L), b]
        Uall = self.gather(u)
        for s in range(0, self.nel, chunk):
            e = slice(s, min(s + chunk, self.nel))
            ne = e.stop - e.start
            Ff = self._F(Uall[e]).reshape(-1, 3, 3)
            if mixed:
                J = np.linalg.det(Ff).reshape(ne, nq)
                p = pi[e] @ self.Np.T                                  # (ne, nq)
                P, A = cubic_stress_tangent(Ff, C10, C20, C30, pressure=p.ravel())
                W = cubic_energy(Ff, C10, C20, C30, 0.0).reshape(ne, nq) \
                    + p * (J - 1.0) - p**2 / (2.0 * K)
                extra["rp"][e] = (J - 1.0) @ Npw - pi[e] @ M / K
            else:
                P, A = cubic_stress_tangent(Ff, C10, C20, C30, K=K)
                W = cubic_energy(Ff, C10, C20, C30, K).reshape(ne, nq)
            energy += float(np.sum(W * w))
            P = P.reshape(ne, nq, 3, 3)
            fe = np.einsum("eqiJ,qaJ->eai", P * w[:, None, None], G, optimize=True).reshape(ne, 81)
            np.add.at(f, self.edofs[e].ravel(), fe.ravel())
            if not tangent:
                continue
            A = A.reshape(ne, nq, 3, 3, 3, 3).transpose(0, 1, 3, 2, 4, 5).reshape(ne, nq, 3, 27)
            T = np.matmul(G[None], A)                                  # (ne, nq, a, (i,k,L))
            T = T.reshape(ne, nq, 27, 3, 3, 3).transpose(0, 2, 3, 4, 1, 5).reshape(ne, 243, nq * 3)
            Ke = np.matmul(T, wG).reshape(ne, 27, 3, 3, 27).transpose(0, 1, 2, 4, 3)
            Ke = Ke.reshape(ne, 81, 81)
            if mixed:
                JH = np.linalg.det(Ff)[:, None, None] * np.linalg.inv(Ff).swapaxes(-1, -2)
                B = np.einsum("qm,eqiJ,qaJ->emai", Npw, JH.reshape(ne, nq, 3, 3), G,
                              optimize=True).reshape(ne, 4, 81)
                MiB = np.matmul(self.Minv, B)
                Ke = Ke + K * np.matmul(B.transpose(0, 2, 1), MiB)
                extra["B"][e] = B
                ce = K * np.einsum("emx,em->ex", MiB, extra["rp"][e])
                np.add.at(extra["c"], self.edofs[e].ravel(), ce.ravel())
            data[e.start * 6561:e.stop * 6561] = Ke.ravel()
        Kmat = None
        if tangent:
            vals = np.bincount(self.map, weights=data, minlength=self.nnz)
            Kmat = sp.csr_matrix((vals, self.indices, self.indptr), shape=(self.N, self.N))
        return f, Kmat, energy, extra

    def pressure_update(self, extra, du, material):
        """Condensed pressure increment ``Δπ = K M⁻¹ (rp + B Δu)`` per element, (nel, 4)."""
        Bdu = np.einsum("emx,ex->em", extra["B"], du[self.edofs])
        return material[3] * (extra["rp"] + Bdu) @ self.Minv



# ----------------------------------------------------------------------------------------------
# boundary conditions and Newton solver
# ----------------------------------------------------------------------------------------------

def _constraints(disc, vmesh, bc):
    """Constrained vector dofs and the scalar dof sets of the end faces."""
    x = disc.doflocs
    tol = 1e-6 * vmesh.cell.min()
    zmin, zmax = x[:, 2].min(), x[:, 2].max()
    bottom = np.flatnonzero(np.abs(x[:, 2] - zmin) < tol)
    top = np.flatnonzero(np.abs(x[:, 2] - zmax) < tol)
    fixed = []                                  # vector dofs held at 0
    if bc == "clamped":
        fixed += [3 * bottom + c for c in range(3)] + [3 * top + c for c in range(2)]
    elif bc == "roller":
        fixed.append(3 * bottom + 2)
        # remove rigid motions not already removed by symmetry planes
        xb = x[bottom]
        centre = xb.mean(axis=0)
        pin = bottom[np.argmin(np.sum((xb[:, :2] - centre[:2]) ** 2, axis=1))]
        for a in (0, 1):
            if a not in vmesh.planes:
                fixed.append(np.array([3 * pin + a]))
        if not vmesh.planes:                    # rotation about z
            same_y = bottom[np.abs(x[bottom, 1] - x[pin, 1]) < tol]
            far = same_y[np.argmax(np.abs(x[same_y, 0] - x[pin, 0]))]
            fixed.append(np.array([3 * far + 1]))
    else:
        raise InputError(f"bc must be 'clamped' or 'roller', got {bc!r}")
    for a, c in vmesh.planes.items():
        on = np.flatnonzero(np.abs(x[:, a] - c) < tol)
        fixed.append(3 * on + a)
    fixed = np.unique(np.concatenate(fixed))
    moved = 3 * top + 2
    if np.intersect1d(fixed, moved).size:
        raise InputError("top and bottom faces coincide: the mask must span more than one slice")
    return fixed, moved, bottom, top


class _TangentSolver:
    """Solves tangent systems K_ff x = b, reusing one sparse LU factorisation across iterations.

    The tangent changes slowly along the load path, so the LU of an earlier tangent is a good
    preconditioner for conjugate gradients on the current one (the current, consistent tangent is
    always the operator, solved to ``cg_rtol``). The factorisation is refreshed when CG fails to
    converge in ``max_cg`` iterations or when the CG time since the last factorisation exceeds
    the time that factorisation took — so small systems are effectively solved directly and large
    ones (10⁵ dofs, where one LU costs a minute) need only a few factorisations.
    """

    def __init__(self, max_cg=60, cg_rtol=1e-10):
        self.lu = None
        self.max_cg = max_cg
        self.cg_rtol = cg_rtol
        self.factorizations = 0
        self.cg_iterations = 0
        self._t_factor = 0.0
        self._t_cg = 0.0

    def solve(self, Kff, b):
        if self.lu is not None:
            t0 = time.perf_counter()
            M = spla.LinearOperator(Kff.shape, matvec=self.lu.solve, dtype=float)
            count = [0]

            def tick(_):
                count[0] += 1

            x, info = spla.cg(Kff, b, rtol=self.cg_rtol, atol=0.0, maxiter=self.max_cg, M=M,
                              callback=tick)
            self.cg_iterations += count[0]
            self._t_cg += time.perf_counter() - t0
            if self._t_cg > self._t_factor:
                self.lu = None                  # refactor at the next solve
            if info == 0 and np.all(np.isfinite(x)):
                return x
        t0 = time.perf_counter()
        self.lu = spla.splu(Kff.tocsc(), permc_spec="COLAMD")
        self.factorizations += 1
        x = self.lu.solve(b)
        self._t_factor = time.perf_counter() - t0
        self._t_cg = 0.0
        if not np.all(np.isfinite(x)):
            raise SolverError("linear solve returned non-finite values (singular tangent?)")
        return x


def _newton(disc, material, u, pi, D, uD, free, rtol, max_iter, linsolve):
    """Solve the equilibrium equations at prescribed u[D] = uD by Newton's method.

    ``"mixed"``: Newton on (u, p) together, the element pressures condensed out of each linear
    system and recovered from it (so p is updated by its own linearisation, not recomputed from
    K (J − 1), which keeps the iteration quadratic for K ≫ C10). ``"hex27"``: Newton on u with an
    Armijo backtracking line search on the stored energy once u[D] is in place. The first
    iteration carries the prescribed increment ``uD − u[D]`` through the tangent; any step that
    would invert an element is halved.

    Returns
    -------
    u : ndarray (N,)
    pi : ndarray (nel, 4) or None
    f : ndarray (N,)
        f_int; at the constrained dofs, the force the supports exert on the body.
    iterations : int
    history : list of float
        Relative residual after each iteration: ‖f(free)‖ / ‖f(D)‖, and for "mixed" the larger
        of that and ‖pressure residual‖ / ‖p‖ (as a pressure, N/cm²).
    """
    mixed = disc.element == "mixed"
    f, K, E, ex = disc.assemble(u, material, pi)
    hist = []
    for it in range(1, max_iter + 1):
        du = np.zeros_like(u)
        du[D] = uD - u[D]
        moving = bool(np.any(du[D]))
        rhs = -(f[free] + ex["c"][free]) if mixed else -f[free]
        if moving:
            rhs = rhs - K[free][:, D] @ du[D]
        du[free] = linsolve.solve(K[free][:, free], rhs)
        dpi = disc.pressure_update(ex, du, material) if mixed else None
        slope = float(f @ du)            # dΠ/ds at s = 0 (hex27, u[D] in place)
        s = 1.0
        for _ in range(12):
            trial = u + s * du
            if s == 1.0:
                trial[D] = uD                # exact, free of round-off
            pi_t = pi + s * dpi if mixed else None
            try:
                f_t, K_t, E_t, ex_t = disc.assemble(trial, material, pi_t)
            except SolverError:          # inverted element: shorten
                s *= 0.5
                continue
            if mixed or moving or E_t - E <= 1e-4 * s * min(slope, 0.0) + 1e-12 * abs(E):
                break
            s *= 0.5
        else:
            raise SolverError(f"no acceptable Newton step (line search failed at iteration {it})")
        u, pi, f, K, E, ex = trial, pi_t, f_t, K_t, E_t, ex_t
        res = np.linalg.norm(f[free]) / max(np.linalg.norm(f[D]), 1e-300)
        if mixed:
            p_err = material[3] * ex["rp"] @ disc.Minv        # pressure residual as N/cm²
            res = max(res, np.linalg.norm(p_err) / max(np.linalg.norm(pi), 1e-300))
        hist.append(res)
        if res <= rtol and np.array_equal(u[D], uD):
            return u, pi, f, it, hist
    raise SolverError(f"Newton did not converge in {max_iter} iterations: "
                      f"relative residuals {', '.join(f'{h:.2e}' for h in hist)}")


def tendon_fem_reaction(mask, affine_cm, stretch=2.0, steps=10, refine=1, element="mixed",
                        material=CONNECTIVE_TISSUE, bc="clamped", symmetry=True, ends="faces",
                        rtol=1e-9, max_iter=25, max_cutbacks=4):
    """Reaction force of a stretched voxel body by finite elements (Example 1 reference).

    The top face (z = z_max) is displaced by ``stretch * n / steps`` in +z at load step
    ``n = 0 .. steps``; full Newton with the consistent tangent at each step.

    Parameters
    ----------
    mask : ndarray of bool, shape (I, J, K)
        Voxels of the body (e.g. :func:`pixmuscle.verify.tendon_geometry.tendon_voxels`).
    affine_cm : ndarray, shape (4, 4)
        Grid-aligned voxel index → cm.
    stretch : float
        Final top displacement, cm (paper: 2 cm).
    steps : int
        Number of equal load steps.
    refine : int or sequence of 3 int
        Elements per voxel edge along x, y, z.
    element : {"mixed", "hex27"}
        Q2–P1disc u–p (non-locking) or pure-displacement Q2, see module docstring.
    material : sequence of 4 float
        (C10, C20, C30, K) of eq. (27), N/cm². Default Table 1 connective tissue.
    bc : {"clamped", "roller"}
        End conditions, see module docstring.
    symmetry : bool
        Use mirror symmetry of the mask (half/quarter model) where possible.
    ends : {"faces", "centres"}
        Where the loaded ends are: on the outer faces of the end slices (the voxel domain), or on
        the planes through the end voxel centres (where a voxel-centred meshfree model holds its
        end node layers; the body is then shorter by one slice). See :func:`voxel_hex_mesh`.
    rtol : float
        Newton stops when ‖f_int(free)‖ ≤ rtol ‖f_int(constrained)‖.
    max_iter : int
        Newton iterations per (sub-)step before it is cut back.
    max_cutbacks : int
        A load step whose Newton iterations fail is split in halves, at most this many times
        over; then SolverError is raised.

    Returns
    -------
    dict
        ``displacement`` (steps+1,) cm, top-face displacement;
        ``force`` (steps+1,) N, reaction at the fixed bottom end dotted with its outward normal
        (−z): positive = tension (sign convention of ``docs/architecture.md``);
        ``force_top`` (steps+1,) N, the same at the top end (+z normal), equal to ``force`` by
        equilibrium; ``iterations`` (steps+1,) Newton iterations per step;
        ``residuals`` list of per-step relative residual histories;
        ``nodes`` (n, 3) cm and ``u`` (n, 3) cm: Q2 node positions of the meshed part and their
        final displacement;
        ``dofs`` displacement dofs of the meshed part, ``elements``, ``symmetry_factor``,
        ``volume_cm3`` (whole body), ``refine``, ``element``, ``bc``, ``material``,
        ``factorizations`` and ``cg_iterations`` (linear-solver work), ``wall_time_s``.
    """
    t0 = time.perf_counter()
    if element not in ("mixed", "hex27"):
        raise InputError(f"element must be 'mixed' or 'hex27', got {element!r}")
    material = tuple(float(m) for m in material)
    if len(material) != 4 or not all(np.isfinite(material)) or material[0] <= 0 \
            or material[3] <= 0:
        raise InputError(f"material must be (C10, C20, C30, K) in N/cm² with C10, K > 0, "
                         f"got {material}")
    steps = int(steps)
    if steps < 1:
        raise InputError(f"steps must be >= 1, got {steps}")
    if not np.isfinite(stretch):
        raise InputError(f"stretch must be a finite displacement in cm, got {stretch}")
    vmesh = voxel_hex_mesh(mask, affine_cm, refine, symmetry, ends)
    disc = _Discretization(vmesh, element)
    fixed, moved, bottom, top = _constraints(disc, vmesh, bc)
    D = np.concatenate([fixed, moved])
    free = np.setdiff1d(np.arange(disc.N), D)

    u = np.zeros(disc.N)
    pi = np.zeros((disc.nel, 4)) if element == "mixed" else None
    disp = stretch * np.arange(steps + 1) / steps
    force = np.zeros(steps + 1)
    force_top = np.zeros(steps + 1)
    iters = np.zeros(steps + 1, int)
    residuals = [[]]
    n_fixed = fixed.size
    linsolve = _TangentSolver()
    for n in range(1, steps + 1):
        # reach disp[n] from the converged state at disp[n-1], tangent predictor; if Newton fails,
        # cut the increment in halves (up to 2^max_cutbacks sub-steps). The reported steps stay
        # the requested ones.
        level, frac, it_total, hist_all = 0, 0.0, 0, []
        while frac < 1.0:
            new_frac = min(frac + 0.5**level, 1.0)
            d_to = disp[n - 1] + new_frac * (disp[n] - disp[n - 1])
            uD = np.concatenate([np.zeros(n_fixed), np.full(moved.size, d_to)])
            try:
                u, pi, f, it, hist = _newton(disc, material, u, pi, D, uD, free, rtol,
                                             max_iter, linsolve)
            except SolverError:
                if level == max_cutbacks:
                    raise SolverError(f"load step {n} (top displacement {disp[n]:.4g} cm) did "
                                      f"not converge after {max_cutbacks} cutbacks") from None
                level += 1
                continue
            frac = new_frac
            it_total += it
            hist_all += hist
        fz = f.reshape(-1, 3)[:, 2]
        # f_int at constrained dofs = force the support exerts on the body
        force[n] = -vmesh.factor * fz[bottom].sum()
        force_top[n] = vmesh.factor * fz[top].sum()
        iters[n] = it_total
        residuals.append(hist_all)
    return dict(displacement=disp, force=force, force_top=force_top, iterations=iters,
                nodes=disc.doflocs, u=u.reshape(-1, 3),
                residuals=residuals, dofs=int(disc.N), elements=int(disc.nel),
                symmetry_factor=int(vmesh.factor), volume_cm3=float(disc.volume * vmesh.factor),
                refine=tuple(int(r) for r in _refine_tuple(refine)), element=element, bc=bc,
                material=material, ends=ends, factorizations=linsolve.factorizations,
                cg_iterations=linsolve.cg_iterations, wall_time_s=time.perf_counter() - t0)


def convergence_study(mask, affine_cm, refines=(1, 2), **kwargs):
    """Run :func:`tendon_fem_reaction` at several refinements and compare the final forces.

    Parameters
    ----------
    mask, affine_cm
        Voxel domain, see :func:`tendon_fem_reaction`.
    refines : sequence
        Refinement levels (int or 3-tuples), coarse to fine.
    **kwargs
        Passed to :func:`tendon_fem_reaction`.

    Returns
    -------
    results : list of dict
        One result per level.
    rel_change : ndarray, shape (len(refines) - 1,)
        ``|F_final(level m+1) − F_final(level m)| / |F_final(level m+1)|``; the finest result is
        taken as converged when the last entry is below 0.01.
    """
    results = [tendon_fem_reaction(mask, affine_cm, refine=r, **kwargs) for r in refines]
    final = np.array([r["force"][-1] for r in results])
    return results, np.abs(np.diff(final)) / np.abs(final[1:])


# ----------------------------------------------------------------------------------------------
# output (edge)
# ----------------------------------------------------------------------------------------------

def reference_table(result, path):
    """Write displacement vs reaction force to CSV.

    Columns: ``step, displacement_cm, force_N`` and, when the result has it, ``force_top_N``.

    Parameters
    ----------
    result : dict
        Output of :func:`tendon_fem_reaction` (or any dict with ``displacement`` (n,) cm and
        ``force`` (n,) N).
    path : str or Path
        CSV file to write.

    Returns
    -------
    path
    """
    cols = [np.asarray(result["displacement"], float), np.asarray(result["force"], float)]
    header = ["step", "displacement_cm", "force_N"]
    if "force_top" in result:
        cols.append(np.asarray(result["force_top"], float))
        header.append("force_top_N")
    if any(c.shape != cols[0].shape or c.ndim != 1 for c in cols):
        raise InputError(f"reference_table(): displacement and force must be 1-D arrays of equal "
                         f"length, got shapes {[c.shape for c in cols]}")
    with open(path, "w", newline="") as fh:
        out = csv.writer(fh)
        out.writerow(header)
        for n, row in enumerate(np.stack(cols, axis=1)):
            out.writerow([n, f"{row[0]:.6g}"] + [f"{v:.8g}" for v in row[1:]])
    return path


def plot_comparison(fem, meshfree, path, labels=("FE (scikit-fem)", "meshfree (RKPM)")):
    """Plot reaction force vs top displacement for FE and meshfree, with their relative difference.

    Parameters
    ----------
    fem, meshfree : dict
        Each with ``displacement`` (n,) cm and ``force`` (n,) N (same displacements).
    path : str or Path
        Image file to write (format from the suffix).
    labels : pair of str
        Legend entries.

    Returns
    -------
    ndarray, shape (n,)
        Relative difference ``(meshfree − fem) / fem`` at each step (NaN at zero force).
    """
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    d_fe, f_fe = np.asarray(fem["displacement"], float), np.asarray(fem["force"], float)
    d_mf, f_mf = np.asarray(meshfree["displacement"], float), np.asarray(meshfree["force"], float)
    if d_fe.shape != d_mf.shape or not np.allclose(d_fe, d_mf, atol=1e-9):
        raise InputError("plot_comparison(): FE and meshfree results must share the displacement "
                         f"steps; got {d_fe.tolist()} and {d_mf.tolist()}")
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.where(f_fe != 0, (f_mf - f_fe) / f_fe, np.nan)
    fig, (ax, bx) = plt.subplots(2, 1, figsize=(5.0, 5.5), sharex=True,
                                 gridspec_kw={"height_ratios": [3, 1]})
    ax.plot(d_fe, f_fe, "k-o", ms=4, label=labels[0])
    ax.plot(d_mf, f_mf, "r--s", ms=4, mfc="none", label=labels[1])
    ax.set_ylabel("reaction force at fixed end (N)")
    ax.legend()
    ax.grid(alpha=0.3)
    bx.plot(d_fe[1:], 100 * rel[1:], "r-s", ms=4, mfc="none")
    bx.axhspan(-3, 3, color="0.9")
    bx.set_xlabel("top displacement (cm)")
    bx.set_ylabel("difference (%)")
    bx.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=150)
    plt.close(fig)
    return rel


def write_tendon_reference(outdir="data/synthetic", h=(0.2, 0.2, 0.125), stretch: float = 2.0, steps: int = 10) -> Path:
    """Finite-element reference of the Example 1 tendon: ``tendon_fe_reference.csv`` (step, displacement_cm, force_N,
    force_top_N).

    The reaction of :func:`tendon_fem_reaction` (scikit-fem, Q2–P1disc elements, one
    per voxel, bottom clamped, top clamped laterally and displaced by ``stretch`` cm in ``steps`` equal steps) on
    the voxels of :func:`pixmuscle.synth.write.write_tendon_labels` — the comparison of ``pixmuscle verify tendon``, kept as a file so
    that the report of ``configs/tendon.yaml`` can draw it (``report.reference_curve``).
    """
    from .tendon_geometry import tendon_voxels

    mask, affine = tendon_voxels(h=h)
    fem = tendon_fem_reaction(mask, affine, stretch=stretch, steps=steps, element="mixed", bc="clamped")
    path = Path(outdir) / "tendon_fe_reference.csv"
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    reference_table(fem, tmp)
    os.replace(tmp, path)
    return path

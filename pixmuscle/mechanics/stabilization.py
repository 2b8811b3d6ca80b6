"""Stabilisation of the nodal integration: naturally stabilised nodal integration (NSNI).

Nodal integration samples the strain energy once per cell. SCNI's smoothed gradient
b̃_I(X_L) = (1/V_L) ∮ Ψ_I n dΓ only sees Ψ on the cell faces, and on a regular voxel grid
oscillating coefficient fields (e.g. d_I ∝ (−1)^(i+j+k)) vanish at every face centre by symmetry:
they carry no energy (spurious zero-energy modes). We use the stabilisation of

    M. Hillman and J.-S. Chen (2016), "An accelerated, convergent, and stable nodal integration in
    Galerkin meshfree methods for linear and nonlinear mechanics", IJNME 107:603–630 (NSNI),

which keeps the next term of the Taylor expansion of the displacement gradient about the node,
∇u(X) ≈ ∇u(X_L) + Σ_k (X_k − X_Lk) ∇u_{,k}(X_L). Integrated over a box cell the cross terms vanish
and the energy gains

    Π_stab = ½ Σ_L Σ_k M_Lk ∇u_{,k}(X_L) : A_s : ∇u_{,k}(X_L),   M_Lk = ∫_{Ω_L} (X_k − X_Lk)² dΩ = V_L h_k² / 12.

Choices made here (documented, switchable in ``solve.stabilization``):

* The gradient of the displacement gradient along k is the difference of the RK gradients at the
  cell's two k-faces, ∇u_{,k}(X_L) ≈ [∇u^h(X_L + h_k/2 e_k) − ∇u^h(X_L − h_k/2 e_k)] / h_k, using
  the face centres that SCNI already evaluates (Hillman & Chen use implicit gradients instead).
  It is zero for every linear field, so the linear patch test and the exactness for homogeneous
  deformations are unaffected.
* The term is quadratic with a constant modulus A_s, so its stiffness K_s is assembled once and its
  force is K_s d. ``modulus: shear`` (default) uses A_s = 2 μ_L I (identity on the 9 components,
  μ_L the reference shear modulus of node L's material): it penalises every non-affine field but
  not the volumetric part with the bulk modulus, which would lock the nearly incompressible
  tissues (K/μ up to ~800). ``modulus: tangent`` uses the full reference tangent A(F = I).
* The term vanishes for rigid motions of any size (their displacement gradient is uniform).
* ``coefficient`` scales Π_stab (1 = the Taylor-expansion value).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .assembly import Assembler
from .scni import SCNI


def second_moments(volume: np.ndarray, spacing) -> np.ndarray:
    """Second moments M_Lk = ∫_{Ω_L} (X_k − X_Lk)² dΩ = V_L h_k²/12 of the box cells, cm⁵, shape (N, 3)."""
    h = np.asarray(spacing, float)
    return np.asarray(volume, float)[:, None] * h[None, :] ** 2 / 12.0


def gradient_differences(scni: SCNI) -> list[list[sp.csr_matrix]]:
    """Operators H[k][J] (N × N, cm⁻²) with (H[k][J] @ u)[L] ≈ ∂²u/∂X_J∂X_k at X_L.

    ``H[k][J] = (∂_J Ψ(face⁺_k) − ∂_J Ψ(face⁻_k)) / h_k``: difference of the RK gradients at the
    centres of the two faces of cell L normal to axis k.
    """
    return [[gradient_difference(scni, k, J) for J in range(3)] for k in range(3)]


def gradient_difference(scni: SCNI, k: int, J: int) -> sp.csr_matrix:
    """One operator H[k][J] of :func:`gradient_differences` (N × N CSR, cm⁻²), made on its own (a
    build that needs them one at a time holds one, not nine)."""
    if scni.dpsi_faces is None:
        raise ValueError("SCNI operators were built without face gradients (face_gradients=True is needed)")
    faces = scni.faces
    D = scni.dpsi_faces[J]
    return ((D[faces.plus[k]] - D[faces.minus[k]]) / scni.spacing[k]).tocsr()


def reference_shear_modulus(A0: np.ndarray) -> np.ndarray:
    """Shear modulus per node from a reference tangent: mean of A0[i, J, i, J] over i ≠ J (N/cm²).

    For an isotropic material at F = I this is μ exactly.
    """
    off = [(i, J) for i in range(3) for J in range(3) if i != J]
    return np.mean([A0[:, i, J, i, J] for i, J in off], axis=0)


def stabilization_modulus(A0: np.ndarray, modulus: str = "shear") -> np.ndarray:
    """Modulus A_s of the stabilisation term per node, (N, 3, 3, 3, 3), N/cm².

    ``"shear"``: A_s = 2 μ_L I (μ_L from :func:`reference_shear_modulus`); ``"tangent"``: A_s = A0.
    """
    if modulus == "shear":
        mu = reference_shear_modulus(A0)
        As = np.zeros((A0.shape[0], 3, 3, 3, 3))
        for i in range(3):
            for J in range(3):
                As[:, i, J, i, J] = 2.0 * mu
        return As
    if modulus == "tangent":
        return np.asarray(A0, float)
    raise ValueError(f"unknown stabilisation modulus {modulus!r}: expected 'shear' or 'tangent'")


def stabilization_operators(scni: SCNI, A0: np.ndarray, *, coefficient: float = 1.0,
                            modulus: str = "shear") -> tuple[list, np.ndarray]:
    """The NSNI term in product form, K_s = Σ_k H_kᵀ (c M_k A_s) H_k (for matrix-free products).

    Returns
    -------
    groups : list of 3 lists of 3 CSR (N × N), cm⁻²
        ``groups[k][J] = H[k][J]`` (:func:`gradient_differences`).
    C : (3N, 9, 9) float
        c · M_Lk · A_s,L per axis k (k-major), N·cm³, index 3i + J.
    """
    return gradient_differences(scni), stabilization_moduli(scni, A0, coefficient=coefficient, modulus=modulus)


def stabilization_moduli(scni: SCNI, A0: np.ndarray, *, coefficient: float = 1.0, modulus: str = "shear") -> np.ndarray:
    """C of :func:`stabilization_operators`: c · M_Lk · A_s,L per axis k (k-major), (3N, 9, 9), N·cm³."""
    n = scni.n_nodes
    As = stabilization_modulus(A0, modulus).reshape(n, 9, 9)
    M = second_moments(scni.volume, scni.spacing)
    C = np.empty((3 * n, 9, 9))
    for k in range(3):  # in place: no per-axis temporaries beside C
        np.multiply(coefficient * M[:, k, None, None], As, out=C[k * n:(k + 1) * n])
    return C


def stabilization_stiffness(scni: SCNI, assembler: Assembler, A0: np.ndarray, *, coefficient: float = 1.0,
                            modulus: str = "shear", out: np.ndarray | None = None) -> np.ndarray:
    """Block data of the constant NSNI stiffness K_s (added to ``out``), N/cm.

    Parameters
    ----------
    scni : SCNI
        Built with ``face_gradients=True``.
    assembler : Assembler
        Full or filtered block pattern.
    A0 : (N, 3, 3, 3, 3) float
        Reference tangent A(F = I) per node, N/cm².
    coefficient : float
        Scale of Π_stab.
    modulus : {"shear", "tangent"}
        A_s = 2 μ_L I or A_s = A0 (see module docstring).

    Returns
    -------
    (nnzb, 3, 3) float
    """
    if out is None:
        out = assembler.zeros()
    if coefficient == 0.0:
        return out
    As = stabilization_modulus(A0, modulus)
    H = gradient_differences(scni)
    M = second_moments(scni.volume, scni.spacing)
    for k in range(3):
        g = assembler.on_support(H[k])
        assembler.fill(g, As, coefficient * M[:, k], out=out)
    return out

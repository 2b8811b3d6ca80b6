r"""Strong ellipticity of a material law at given deformations: the smallest acoustic-tensor eigenvalue.

A hyperelastic law with first elasticity tensor A (``A[i, J, k, L] = ∂P_iJ/∂F_kL``) is *strongly
elliptic* at F when the acoustic tensor

    Q_ik(m) = A_iJkL m_J m_L                      (m a unit vector in the reference configuration)

is positive definite for every m (Legendre–Hadamard condition). Where it is not, the continuum
admits deformation gradients that jump across a plane with normal m: equilibrium loses uniqueness
and deformation can localise in a band. A discretisation then concentrates strain in bands as thin
as it can resolve, so forces and fields change with every refinement and converge to nothing
(docs/active-muscle.md shows this for the paper's muscle matrix, whose C01 < 0 loses ellipticity
at a principal stretch of about 1.37).

For a nearly incompressible law the polarisation a ∥ F⁻ᵀm changes the volume and is stiffened by
the bulk modulus K; the check uses the two polarisations a ⊥ F⁻ᵀm, whose 2 × 2 block of Q is the
one that can lose definiteness at a finite K/μ. Directions m are quasi-uniform points on a
half sphere (m and −m give the same Q).

Units: N/cm² (the eigenvalue has the units of A).
"""

from __future__ import annotations

import numpy as np

__all__ = ["directions", "acoustic_minimum"]


def directions(n: int = 600) -> np.ndarray:
    """``n`` quasi-uniform unit vectors on the half sphere z ≥ 0 (Fibonacci lattice), (n, 3)."""
    k = np.arange(n) + 0.5
    z = 1.0 - k / n
    r = np.sqrt(1.0 - z * z)
    phi = np.pi * (1.0 + 5.0**0.5) * k
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def acoustic_minimum(F: np.ndarray, A: np.ndarray, m: np.ndarray | None = None, chunk: int = 256) -> np.ndarray:
    """Smallest eigenvalue of the isochoric acoustic tensor over the directions m, per point.

    Parameters
    ----------
    F : (n, 3, 3) float
        Deformation gradients (det F > 0).
    A : (n, 3, 3, 3, 3) float
        First elasticity tensors at F, ``A[p, i, J, k, L] = ∂P_iJ/∂F_kL`` [N/cm²].
    m : (d, 3) float, optional
        Unit reference directions; default :func:`directions` (600).
    chunk : int
        Points per vectorised block (memory ~ chunk · d · 9 floats).

    Returns
    -------
    (n,) float
        min over m of the smallest eigenvalue of Q(m) restricted to a ⊥ F⁻ᵀm [N/cm²]; the law
        is strongly elliptic at F (for those polarisations) where it is > 0.
    """
    F = np.asarray(F, float)
    A = np.asarray(A, float)
    m = directions() if m is None else np.asarray(m, float)
    out = np.empty(F.shape[0])
    for s in range(0, F.shape[0], chunk):
        e = slice(s, s + chunk)
        Q = np.einsum("niJkL,dJ,dL->ndik", A[e], m, m, optimize=True)        # (c, d, 3, 3)
        v = np.einsum("nJi,dJ->ndi", np.linalg.inv(F[e]), m)                 # F⁻ᵀ m
        v /= np.linalg.norm(v, axis=-1, keepdims=True)
        ref = np.where(np.abs(v[..., :1]) < 0.9, [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])   # not parallel to v
        t1 = np.cross(v, ref)
        t1 /= np.linalg.norm(t1, axis=-1, keepdims=True)
        t2 = np.cross(v, t1)
        a = np.einsum("ndi,ndik,ndk->nd", t1, Q, t1)
        b = 0.5 * (np.einsum("ndi,ndik,ndk->nd", t1, Q, t2) + np.einsum("ndi,ndik,ndk->nd", t2, Q, t1))
        c = np.einsum("ndi,ndik,ndk->nd", t2, Q, t2)
        lam = 0.5 * (a + c) - np.sqrt(0.25 * (a - c) ** 2 + b * b)            # smaller eigenvalue of [[a b] [b c]]
        out[e] = lam.min(axis=1)
    return out

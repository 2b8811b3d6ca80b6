"""Synthetic tendon of the paper's Example 1: a tapered prism and its voxel image.

The paper compares RKPM with finite elements on a manually segmented tendon "about 19 cm long",
bottom face fixed in all directions, top face stretched 2 cm along the axis (Example 1, Fig. 10).
The segmentation is not public, so this module defines a stand-in: a straight prism along z,
``z ∈ [0, length]``, centred on the z axis, whose rectangular cross-section
``(width_x, width_y)`` shrinks linearly from ``base`` at z = 0 to ``top`` at z = length.
Defaults (cm): length 19, base 1.6 × 0.8, top 0.8 × 0.5, i.e. 1.28 cm² at the bottom
(aponeurosis end, where the tendon fans out) down to 0.40 cm² at the top — the order of a human
Achilles tendon (mid-substance area 0.5–0.9 cm²).

Why the comparison uses the *voxelised* prism
---------------------------------------------
The meshfree model is built from a voxel label volume: its domain is the union of the voxel cells
(one node per voxel, integration cell = the voxel box), a staircase approximation of the prism.
A finite-element mesh of the smooth prism would solve a different boundary-value problem, and the
difference (a few % in stiffness at in-plane voxel sizes of 1–2 mm) would swamp the 3 % tolerance.
So both methods solve on the *same* domain: :func:`tendon_voxels` / :meth:`TendonGeometry.voxelize`
label every voxel whose centre lies in the (closed) prism. Because the prism is centred on the z
axis and the grid is laid out symmetrically about it (an even number of voxel columns in x and y,
the axis on a voxel face), each slice k of the label volume is one centred rectangle of
``n_x(k) × n_y(k)`` whole voxels: the domain is a stack of rectangular slabs, one per slice. The
finite-element reference (:mod:`pixmuscle.verify.tendon_fem`) meshes exactly this stack, one
hexahedron per voxel subdivided for refinement, and the domain is also symmetric about the planes
x = 0 and y = 0, which the reference uses to mesh one quarter.

The slab widths come in steps of two voxels (one per side), so the top slab of the default tendon
at spacing (0.1, 0.1, 0.5) cm is 0.8 × 0.6 cm rather than the nominal 0.8 × 0.5 at z = 19 (slice
centre z = 18.75 cm, rounded to whole voxel pairs). What matters for the comparison is only that
both methods see the same voxels.

Units: cm throughout.
"""

from dataclasses import dataclass

import numpy as np

from pixmuscle.errors import InputError

__all__ = ["TendonGeometry", "tendon_prism", "tendon_voxels", "voxel_slab_areas", "grid_spacing"]

# Voxel centres closer than this (cm) to the prism surface count as inside, so that a centre lying
# exactly on the surface in exact arithmetic is not decided by round-off.
_SURFACE_TOL = 1e-9


@dataclass(frozen=True)
class TendonGeometry:
    """Straight tapered prism along z with a centred rectangular cross-section.

    Attributes
    ----------
    length : float
        Length along z, cm; the prism occupies ``0 <= z <= length``.
    base : tuple of float
        Cross-section ``(width_x, width_y)`` at z = 0, cm.
    top : tuple of float
        Cross-section ``(width_x, width_y)`` at z = length, cm.
    """

    length: float
    base: tuple
    top: tuple

    def widths(self, z):
        """Cross-section widths at heights z (linear taper).

        Parameters
        ----------
        z : array_like, shape (n,)
            Heights, cm (clipped to ``[0, length]``).

        Returns
        -------
        ndarray, shape (n, 2)
            ``(width_x, width_y)`` in cm.
        """
        s = np.clip(np.asarray(z, dtype=float) / self.length, 0.0, 1.0)[..., None]
        return (1.0 - s) * np.asarray(self.base, float) + s * np.asarray(self.top, float)

    def cross_section_area(self, z):
        """Area of the smooth prism's cross-section at heights z, cm², shape like ``z``."""
        w = self.widths(z)
        return w[..., 0] * w[..., 1]

    def volume(self):
        """Volume of the smooth prism, cm³ (exact integral of the bilinear area in z)."""
        b = np.asarray(self.base, float)
        t = np.asarray(self.top, float)
        # ∫0^1 ((1-s) b_x + s t_x)((1-s) b_y + s t_y) ds
        return self.length * (b[0] * b[1] / 3 + t[0] * t[1] / 3 + (b[0] * t[1] + t[0] * b[1]) / 6)

    def inside(self, points):
        """Whether points lie in the closed prism.

        Parameters
        ----------
        points : array_like, shape (n, 3)
            Coordinates, cm.

        Returns
        -------
        ndarray of bool, shape (n,)
        """
        p = np.asarray(points, dtype=float)
        if p.ndim != 2 or p.shape[1] != 3:
            raise InputError(f"tendon inside(): points must have shape (n, 3), got {p.shape}")
        z = p[:, 2]
        half = 0.5 * self.widths(z)
        in_z = (z >= -_SURFACE_TOL) & (z <= self.length + _SURFACE_TOL)
        in_xy = np.all(np.abs(p[:, :2]) <= half + _SURFACE_TOL, axis=1)
        return in_z & in_xy

    def voxelize(self, spacing=(0.1, 0.1, 0.5), pad=1):
        """Label the voxels whose centres lie inside the prism.

        The grid has an even number of voxels in x and y, laid out symmetrically about the z axis
        (the axis lies on voxel faces), so each slice is a centred rectangle of whole voxels. In z
        the slices are ``[k hz, (k + 1) hz]`` for ``k = 0 .. round(length / hz) - 1``, so the
        voxel domain spans exactly ``0 <= z <= length`` (``length / hz`` must be a whole number).

        Parameters
        ----------
        spacing : sequence of 3 float
            Voxel edge lengths ``(hx, hy, hz)``, cm.
        pad : int
            Background voxels added on each side along every axis (like an image margin).

        Returns
        -------
        mask : ndarray of bool, shape (I, J, K)
            True for tendon voxels.
        affine_cm : ndarray, shape (4, 4)
            Voxel index → cm: centre of voxel ``ijk`` is ``affine_cm @ (i, j, k, 1)``
            (diagonal, i.e. grid-aligned, as in the model frame of ``docs/architecture.md``).
        """
        h = _check_spacing(spacing)
        pad = int(pad)
        if pad < 0:
            raise InputError(f"tendon voxelize(): pad must be >= 0, got {pad}")
        nz = int(round(self.length / h[2]))
        if nz < 1 or abs(nz * h[2] - self.length) > 1e-6 * self.length:
            raise InputError(
                f"tendon voxelize(): length {self.length} cm is not a whole number of slices of "
                f"hz = {h[2]} cm; choose hz dividing the length")
        wmax = np.maximum(np.asarray(self.base, float), np.asarray(self.top, float))
        # even number of columns covering the widest section, plus padding
        n_xy = 2 * np.ceil(0.5 * wmax / h[:2] - 1e-9).astype(int) + 2 * pad
        shape = (int(n_xy[0]), int(n_xy[1]), nz + 2 * pad)
        origin = np.array([-(shape[0] - 1) / 2 * h[0],
                           -(shape[1] - 1) / 2 * h[1],
                           (0.5 - pad) * h[2]])
        affine = np.eye(4)
        affine[:3, :3] = np.diag(h)
        affine[:3, 3] = origin
        axes = [origin[a] + h[a] * np.arange(shape[a]) for a in range(3)]
        X, Y, Z = np.meshgrid(*axes, indexing="ij")
        pts = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)
        mask = self.inside(pts).reshape(shape)
        return mask, affine


def tendon_prism(length=19.0, base=(1.6, 0.8), top=(0.8, 0.5)):
    """The synthetic tendon of Example 1 as a tapered prism.

    Parameters
    ----------
    length : float
        Length along z, cm (paper: "about 19 cm").
    base, top : sequence of 2 float
        Cross-section ``(width_x, width_y)`` at z = 0 and z = length, cm.

    Returns
    -------
    TendonGeometry
    """
    length = float(length)
    base = tuple(float(v) for v in base)
    top = tuple(float(v) for v in top)
    if not (np.isfinite(length) and length > 0):
        raise InputError(f"tendon_prism(): length must be a positive number of cm, got {length}")
    for name, w in (("base", base), ("top", top)):
        if len(w) != 2 or not all(np.isfinite(v) and v > 0 for v in w):
            raise InputError(f"tendon_prism(): {name} must be two positive widths in cm, got {w}")
    return TendonGeometry(length, base, top)


def tendon_voxels(h=(0.1, 0.1, 0.5), length=19.0, base=(1.6, 0.8), top=(0.8, 0.5), pad=1):
    """Voxel label volume of the default Example-1 tendon (stack of centred rectangular slabs).

    Parameters
    ----------
    h : sequence of 3 float
        Voxel spacing ``(hx, hy, hz)``, cm. ``hz`` must divide ``length``.
    length, base, top
        Prism dimensions, cm, see :func:`tendon_prism`.
    pad : int
        Background margin in voxels on every side.

    Returns
    -------
    mask : ndarray of bool, shape (I, J, K)
    affine_cm : ndarray, shape (4, 4)
        Voxel index → cm (voxel centres).
    """
    return tendon_prism(length, base, top).voxelize(h, pad=pad)


def voxel_slab_areas(mask, affine_cm):
    """Cross-section area of each slice of a voxel domain.

    Parameters
    ----------
    mask : ndarray of bool, shape (I, J, K)
    affine_cm : ndarray, shape (4, 4)
        Grid-aligned voxel index → cm.

    Returns
    -------
    z : ndarray, shape (K,)
        Slice-centre heights, cm.
    area : ndarray, shape (K,)
        ``n_voxels(k) * hx * hy``, cm².
    """
    mask = np.asarray(mask, dtype=bool)
    h = grid_spacing(affine_cm)
    z = affine_cm[2, 3] + h[2] * np.arange(mask.shape[2])
    return z, mask.sum(axis=(0, 1)) * h[0] * h[1]


def grid_spacing(affine_cm):
    """Voxel spacing (3,) in cm of a grid-aligned affine; raises InputError for any other affine."""
    a = np.asarray(affine_cm, dtype=float)
    if a.shape != (4, 4):
        raise InputError(f"affine_cm must be a 4x4 matrix, got shape {a.shape}")
    lin = a[:3, :3]
    h = np.diag(lin).copy()
    if np.any(np.abs(lin - np.diag(h)) > 1e-12 * np.abs(h).max()) or np.any(h <= 0):
        raise InputError(
            "affine_cm must be diagonal with positive spacings (grid-aligned model frame), "
            f"got linear part {lin.tolist()}")
    return h


def _check_spacing(spacing):
    h = np.asarray(spacing, dtype=float).ravel()
    if h.shape != (3,) or not np.all(np.isfinite(h)) or np.any(h <= 0):
        raise InputError(f"voxel spacing must be three positive lengths in cm, got {spacing}")
    return h

"""The :class:`Phantom` container and the renderer shared by all synthetic phantoms.

A phantom's anatomy is a function of position (cm): it returns, for any set of points,
a *signal class* (which tissue and how it looks on MRI), the muscle it belongs to, and the
fibre direction. The renderer samples that function

* at 4x supersampling per voxel (in-plane) and averages the MR signal: partial volume;
* at voxel centres for the ground-truth labels, masks and fibres;
* on the DTI's own, coarser grid for the diffusion tensors.

All phantoms are SYNTHETIC: made by this code, not patient data.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from pixmuscle.errors import InputError
from pixmuscle.imaging.dti import principal_eigenvector, tensor_from_components
from pixmuscle.synth.noise import random_signs, rician, smooth_field

# Signal classes (how a point looks); several map to the same tissue code.
BACKGROUND, MUSCLE, CT, FAT, CORTEX, MARROW, SKIN = range(7)
#: tissue code (docs/architecture.md) of each signal class
CLASS_TO_TISSUE = np.array([0, 1, 2, 3, 4, 4, 2], dtype=np.int16)
#: default T1-weighted (fat-bright) MR intensity of each signal class; fat = 1
T1_INTENSITY = np.array([0.0, 0.42, 0.12, 1.0, 0.03, 0.90, 0.55])

#: muscle diffusivities (mm^2/s): lambda1 (along the fibre), lambda2, lambda3
MUSCLE_DIFFUSIVITY = (2.1e-3, 1.5e-3, 1.2e-3)
#: isotropic diffusivity (mm^2/s) of connective tissue: signal but no fibre meaning
CT_DIFFUSIVITY = 0.6e-3


class Sample(NamedTuple):
    """Anatomy at a set of n points.

    cls : (n,) int8 signal class (BACKGROUND ... SKIN)
    muscle : (n,) int16, 1..M where ``cls == MUSCLE``, else 0
    imat : (n,) bool, intramuscular fat (a subset of ``cls == FAT``)
    apo : (n,) bool, connective tissue that is not IMCT: skin and the deep fascia / aponeurosis
    fiber : (n, 3) float unit fibre direction where ``cls == MUSCLE`` (zeros elsewhere), or None
    """

    cls: np.ndarray
    muscle: np.ndarray
    imat: np.ndarray
    apo: np.ndarray
    fiber: np.ndarray | None


Anatomy = Callable[[np.ndarray, bool], Sample]


@dataclass
class Phantom:
    """A SYNTHETIC MRI + DTI data set with its ground truth.

    Shapes: MRI grid (I, J, K), DTI grid (I', J', K'). Axis 2 is the slice (leg) axis.
    Lengths are in cm, diffusivities in mm^2/s (the unit DTI files use).

    Attributes
    ----------
    mri : (I, J, K) float64
        Magnitude MR image (T1-weighted look: fat bright, muscle grey, connective tissue and
        cortical bone dark), partial volume and Rician noise included. Fat signal = 1.
    affine : (4, 4) float64
        MRI voxel index -> world position (cm), RAS+ axes.
    labels : (I, J, K) int16
        Ground-truth tissue code at voxel centres: 0 background, 1 muscle, 2 connective tissue
        (IMCT, septa, fascia/aponeurosis, interosseous membrane, skin), 3 fat (subcutaneous,
        IMAT), 4 bone (cortex and marrow).
    muscle_id : (I, J, K) int16
        1..M where ``labels == 1``, 0 elsewhere (septa and IMAT belong to no muscle).
    muscle_names : list of str
        Name of muscle ``m`` is ``muscle_names[m - 1]``.
    imct_mask : (I, J, K) bool
        Connective tissue as a specialised sequence would show it: ``labels == 2``.
    imat_mask : (I, J, K) bool
        Intramuscular fat (not subcutaneous fat, not marrow); a subset of ``labels == 3``.
    outer_ct_mask : (I, J, K) bool
        Connective tissue that is not intramuscular: skin, and the deep fascia (leg) or the
        aponeurosis (MG); a subset of ``imct_mask``. Table 3 of the paper counts IMCT without
        the aponeurosis: IMCT = ``imct_mask & ~outer_ct_mask``.
    fiber_true : (I, J, K, 3) float64
        True unit fibre direction where ``labels == 1`` (canonical sign, v_z > 0), else 0.
    dti_tensor : (I', J', K', 6) float64
        Diffusion tensor, mm^2/s, FSL component order (Dxx, Dxy, Dxz, Dyy, Dyz, Dzz) in world
        axes; zero where there is no DTI signal (fat, bone, air).
    dti_affine : (4, 4) float64
        DTI voxel index -> world (cm): coarser and with a different field of view.
    dti_v1 : (I', J', K', 3) float64
        Principal eigenvector of ``dti_tensor`` in world axes with a RANDOM sign per voxel
        (as fitted eigenvectors have); zero where ``dti_mask`` is False.
    dti_mask : (I', J', K') bool
        DTI voxels with signal (muscle or connective tissue fills at least half the voxel).
    noise_sigma : float
        Standard deviation of each Gaussian component of the Rician MRI noise.
    params : dict
        Every parameter used, the seed and ``"synthetic": True``.
    """

    mri: np.ndarray
    affine: np.ndarray
    labels: np.ndarray
    muscle_id: np.ndarray
    muscle_names: list
    imct_mask: np.ndarray
    imat_mask: np.ndarray
    outer_ct_mask: np.ndarray
    fiber_true: np.ndarray
    dti_tensor: np.ndarray
    dti_affine: np.ndarray
    dti_v1: np.ndarray
    dti_mask: np.ndarray
    noise_sigma: float
    params: dict = field(default_factory=dict)

    @property
    def spacing(self) -> np.ndarray:
        """(3,) MRI voxel edge lengths, cm."""
        return np.linalg.norm(self.affine[:3, :3], axis=0)

    @property
    def voxel_volume(self) -> float:
        """MRI voxel volume, cm^3."""
        return float(abs(np.linalg.det(self.affine[:3, :3])))


def check_phantom_args(fn: str, shape, pixel_cm, slice_cm, noise, dti_noise, dti_factor) -> tuple[tuple, int]:
    """Validate the grid and noise arguments shared by the phantom factories.

    Returns the shape as a tuple of ints and ``dti_factor`` as an int; raises InputError naming
    ``fn`` and the bad argument.
    """
    shape = tuple(int(n) for n in shape)
    if len(shape) != 3 or min(shape) < 1:
        raise InputError(f"{fn}: shape must be 3 positive ints, got {shape}")
    for name, val in (("pixel_cm", pixel_cm), ("slice_cm", slice_cm)):
        if not val > 0:
            raise InputError(f"{fn}: {name} must be > 0, got {val}")
    if noise < 0 or dti_noise < 0:
        raise InputError(f"{fn}: noise and dti_noise must be >= 0")
    if int(dti_factor) < 1:
        raise InputError(f"{fn}: dti_factor must be an int >= 1, got {dti_factor}")
    return shape, int(dti_factor)


def grid_affine(spacing, origin) -> np.ndarray:
    """Axis-aligned voxel -> world affine (4, 4) for ``spacing`` (3,) and ``origin`` (3,) cm."""
    a = np.diag(np.r_[np.asarray(spacing, dtype=float), 1.0])
    a[:3, 3] = origin
    return a


def subvoxel_points(affine, shape_ij, k, ss: int, ss_z: int) -> np.ndarray:
    """World points (I*ss, J*ss, ss_z, 3) of the ss x ss x ss_z sub-voxel centres of slice k."""
    o = (np.arange(ss) + 0.5) / ss - 0.5
    oz = (np.arange(ss_z) + 0.5) / ss_z - 0.5
    ii = (np.arange(shape_ij[0])[:, None] + o).ravel()
    jj = (np.arange(shape_ij[1])[:, None] + o).ravel()
    kk = k + oz
    idx = np.stack(np.meshgrid(ii, jj, kk, indexing="ij"), axis=-1)
    return idx @ affine[:3, :3].T + affine[:3, 3]


def _block_mean(values, shape_ij, ss, ss_z):
    """Average (I*ss, J*ss, ss_z, ...) sub-voxel values to (I, J, ...)."""
    i, j = shape_ij
    v = values.reshape((i, ss, j, ss, ss_z) + values.shape[3:])
    return v.mean(axis=(1, 3, 4))


def render_mri(anatomy: Anatomy, shape, affine, *, ss=4, ss_z=2, intensity=T1_INTENSITY,
               muscle_offset=None) -> np.ndarray:
    """Noise-free MR image (I, J, K) with partial volume from ss x ss x ss_z supersampling.

    ``muscle_offset`` (M+1,) adds a per-muscle intensity offset to muscle samples.
    """
    out = np.empty(shape)
    for k in range(shape[2]):
        p = subvoxel_points(affine, shape[:2], k, ss, ss_z)
        s = anatomy(p.reshape(-1, 3), False)
        val = intensity[s.cls]
        if muscle_offset is not None:
            val = val + np.where(s.cls == MUSCLE, muscle_offset[s.muscle], 0.0)
        out[:, :, k] = _block_mean(val.reshape(p.shape[:3]), shape[:2], ss, ss_z)
    return out


def voxel_centres(affine, shape) -> np.ndarray:
    """World positions (I, J, K, 3) of the voxel centres, cm."""
    idx = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), axis=-1)
    return idx @ affine[:3, :3].T + affine[:3, 3]


def fiber_tensor(fiber: np.ndarray, evals=MUSCLE_DIFFUSIVITY) -> np.ndarray:
    """Muscle diffusion tensors (n, 6) FSL order with principal axis ``fiber`` (n, 3).

    ``D = l3 I + (l1 - l3) f f^T + (l2 - l3) g g^T`` with g the unit vector orthogonal
    to f nearest to the coordinate axis least aligned with f.
    """
    l1, l2, l3 = evals
    f = fiber
    axis = np.eye(3)[np.argmin(np.abs(f), axis=1)]
    g = axis - np.sum(axis * f, axis=1, keepdims=True) * f
    g /= np.linalg.norm(g, axis=1, keepdims=True)
    d = (l1 - l3) * f[:, :, None] * f[:, None, :] + (l2 - l3) * g[:, :, None] * g[:, None, :]
    d += l3 * np.eye(3)
    return np.stack([d[:, 0, 0], d[:, 0, 1], d[:, 0, 2], d[:, 1, 1], d[:, 1, 2], d[:, 2, 2]], axis=1)


def render_dti(anatomy: Anatomy, shape, affine, *, ss=4, ss_z=2) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free DTI tensors (I', J', K', 6) FSL order, mm^2/s, and the signal mask.

    Each voxel's tensor is the mean of the sub-voxel tensors of the tissues that give DTI
    signal (muscle: anisotropic along the fibre; connective tissue: isotropic). Fat, bone
    and air give none. Voxels where signal-giving tissue fills less than half are zero.
    """
    out = np.zeros(tuple(shape) + (6,))
    mask = np.zeros(shape, dtype=bool)
    iso = np.array([1.0, 0.0, 0.0, 1.0, 0.0, 1.0]) * CT_DIFFUSIVITY
    for k in range(shape[2]):
        p = subvoxel_points(affine, shape[:2], k, ss, ss_z)
        s = anatomy(p.reshape(-1, 3), True)
        n = len(s.cls)
        t = np.zeros((n, 6))
        m = s.cls == MUSCLE
        t[m] = fiber_tensor(s.fiber[m])
        c = s.cls == CT
        t[c] = iso
        has = (m | c).astype(float)
        tsum = _block_mean(t.reshape(p.shape[:3] + (6,)), shape[:2], ss, ss_z)
        frac = _block_mean(has.reshape(p.shape[:3]), shape[:2], ss, ss_z)
        ok = frac >= 0.5
        out[:, :, k][ok] = tsum[ok] / frac[ok, None]
        mask[:, :, k] = ok
    return out, mask


def add_tensor_noise(tensor, mask, level, rng) -> np.ndarray:
    """Add Gaussian noise of std ``level * mean diffusivity`` to each component where ``mask``."""
    out = tensor.copy()
    if level > 0:
        sd = level * np.mean(MUSCLE_DIFFUSIVITY)
        out[mask] += sd * rng.standard_normal((int(mask.sum()), 6))
    return out


def check_fits(name, lo, hi, affine, shape, what="MRI"):
    """Raise InputError unless the box [lo, hi] (cm, world) lies inside the grid's field of view."""
    c0 = affine[:3, 3] - 0.5 * np.diag(affine)[:3]
    c1 = c0 + np.asarray(shape) * np.diag(affine)[:3]
    if np.any(np.asarray(lo)[:2] < c0[:2]) or np.any(np.asarray(hi)[:2] > c1[:2]):
        raise InputError(
            f"{name}: the anatomy (x {lo[0]:.2f}..{hi[0]:.2f} cm, y {lo[1]:.2f}..{hi[1]:.2f} cm) "
            f"does not fit the {what} field of view (x {c0[0]:.2f}..{c1[0]:.2f}, "
            f"y {c0[1]:.2f}..{c1[1]:.2f} cm); increase shape or pixel_cm, or make it smaller"
        )


def dti_grid(shape, affine, factor, *, fov_fraction=1.0, shift_cm=(0.0, 0.0)):
    """The DTI grid of a phantom: shape (I', J', K+1) and its affine.

    In-plane voxels ``factor`` times the MRI pixel, in-plane field of view ``fov_fraction``
    times the MRI's and centred ``shift_cm`` (x, y) away from it; the same slice spacing with
    slices offset by half a slice, one more slice so that the MRI slices are covered.
    """
    spacing = np.diag(affine)[:3]
    dspacing = np.array([factor * spacing[0], factor * spacing[1], spacing[2]])
    dshape = (int(np.ceil(fov_fraction * shape[0] / factor)), int(np.ceil(fov_fraction * shape[1] / factor)),
              shape[2] + 1)
    centre = affine[:2, 3] + 0.5 * (np.array(shape[:2]) - 1) * spacing[:2] + np.asarray(shift_cm)
    dorigin = np.r_[centre - 0.5 * (np.array(dshape[:2]) - 1) * dspacing[:2], affine[2, 3] - 0.5 * spacing[2]]
    return dshape, grid_affine(dspacing, dorigin)


def render_phantom(anatomy, shape, affine, dshape, dti_affine, rng, *, noise, dti_noise, ss, ss_z, bias,
            muscle_contrast, names, params) -> Phantom:
    """Render MRI (with noise), ground truth and DTI of ``anatomy`` into a :class:`Phantom`.

    Shared by the leg and MG phantoms; ``rng`` continues the phantom's random stream.
    """
    m = len(names)
    offsets = np.zeros(m + 1)
    if m > 1:
        offsets[1:] = muscle_contrast * rng.permutation(np.linspace(-1.0, 1.0, m))
    clean = render_mri(anatomy, shape, affine, ss=ss, ss_z=ss_z, intensity=T1_INTENSITY,
                       muscle_offset=offsets)
    centres = voxel_centres(affine, shape)
    truth = anatomy(centres.reshape(-1, 3), True)
    if bias > 0:
        bfield = smooth_field(rng, (8.0, 8.0, 20.0), 6)
        clean = clean * (1.0 + bias * bfield(centres))
    mri = rician(clean, noise, rng)

    labels = CLASS_TO_TISSUE[truth.cls].reshape(shape)
    muscle_id = truth.muscle.reshape(shape).astype(np.int16)
    fiber_true = truth.fiber.reshape(shape + (3,))

    tensor, dmask = render_dti(anatomy, dshape, dti_affine, ss=ss, ss_z=ss_z)
    tensor = add_tensor_noise(tensor, dmask, dti_noise, rng)
    v1, _, _ = principal_eigenvector(tensor_from_components(tensor, "fsl"))
    v1 = v1 * random_signs(dshape, rng)[..., None]
    v1[~dmask] = 0.0

    params = dict(params, synthetic=True, noise_sigma=noise,
                  note="SYNTHETIC phantom generated by pixmuscle.synth; not patient data")
    return Phantom(
        mri=mri, affine=affine, labels=labels, muscle_id=muscle_id, muscle_names=list(names),
        imct_mask=labels == 2, imat_mask=truth.imat.reshape(shape),
        outer_ct_mask=truth.apo.reshape(shape), fiber_true=fiber_true,
        dti_tensor=tensor, dti_affine=dti_affine, dti_v1=v1, dti_mask=dmask, noise_sigma=float(noise),
        params=params,
    )

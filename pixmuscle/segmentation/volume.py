"""Segmentation of a limb volume: outer boundary, bones, individual muscles, tissue labels.

The steps (paper §4.1–4.2), all on the MRI grid, per slice (``mode="slice"``, the paper) or
on the whole volume (``mode="3d"``):

1. **Outer boundary**: two-phase Chan–Vese on the MRI (bright leg vs dark air), holes filled,
   largest component per slice.
2. **Bones**: the cortex is dark and the marrow bright like fat, so a single two-class split of
   the leg does not isolate bone. Two-phase Chan–Vese first splits the leg (minus IMCT, when its
   mask is given) into a bright class (fat, marrow) and the rest; a second Chan–Vese splits the
   rest into dark (cortex) and grey (muscle). Holes of the dark class that are mostly bright
   are marrow; the dark voxels within ``max_cortex_cm`` of marrow are its cortex; bone = the
   cortex ring with its holes filled. Subtracting the IMCT mask first keeps the thin dark
   septa, fascia and interosseous membrane out of the cortex class.
3. **Muscles**: multiphase multichannel Vese–Chan (eq. 21) on the MRI plus sign-invariant fibre
   channels over the voxels with fibre data inside the leg minus bone (the IMCT/IMAT masks are
   *not* removed here: the paper separates muscles with the fibre channels and subtracts those
   masks afterwards). Default start: every voxel joins the muscle whose seed-point channel
   values it is closest to, muscle ``m`` in region ``m`` (the same in every slice, so region
   identities agree between slices). Regions are mapped to named muscles by the seed points
   (:func:`pixmuscle.segmentation.multiphase.regions_to_muscles`: connected components in 3-D
   with face connectivity, nearest-seed split of a component that holds several muscles'
   seeds, islands to the nearest assigned muscle).
4. **Labels**: :func:`pixmuscle.segmentation.assemble.assemble_labels`.
5. **Quality checks** of the result (:mod:`pixmuscle.segmentation.qc`): a bone or the outline that
   vanishes or jumps in area between neighbouring slices, a muscle assigned mostly by the
   nearest-seed fall-back; returned as ``findings`` (the segment stage logs them).

Intensity convention: MRI robustly scaled to [0, 255] (0.5 and 99.5 percentiles of the whole
volume), fibre channels = 255 x fibre features (:mod:`.features`). Lengths in the level-set
energies are in pixels (voxel size divided by the smallest voxel edge; the slice spacing only
enters in ``mode="3d"``), areas in pixels: ``mu`` is per pixel of contour and ``lambda`` per
pixel and squared grey level, as on the paper's images. The energies are normalised by the
variance of their data term (``energy_scale="variance"``), so the time step is independent of
contrast.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage as ndi

from pixmuscle.errors import InputError
from pixmuscle.segmentation.assemble import (
    assemble_labels,
    fiber_data,
    fill_holes_per_slice,
    largest_component_per_slice,
)
from pixmuscle.segmentation.chan_vese import chan_vese
from pixmuscle.segmentation.config import SegmentConfig
from pixmuscle.segmentation.features import fiber_channels, normalize_intensity
from pixmuscle.segmentation.multiphase import (
    multiphase_chan_vese,
    regions_to_muscles,
    seed_features,
    seed_regions,
)
from pixmuscle.segmentation.qc import bone_areas, segmentation_findings

__all__ = ["SegmentationResult", "segment_volume", "seeds_to_voxels"]

_LOG = logging.getLogger(__name__)


@dataclass
class SegmentationResult:
    """Output of :func:`segment_volume`; arrays on the MRI grid ``(I, J, K)``.

    Attributes
    ----------
    labels : ndarray of int16
        Tissue code per voxel (0 background, 1 muscle, 2 IMCT, 3 fat, 4 bone).
    muscle_id : ndarray of int16
        1..M on muscle voxels, 0 elsewhere.
    muscle_names : list of str
    fiber : ndarray of float32, shape ``(I, J, K, 3)``
        Unit fibre direction (canonical sign) on muscle voxels, 0 elsewhere.
    qc : dict
        Diagnostics: iterations and convergence per step and slice, voxel counts, muscles
        that shared a region, seed voxels.
    leg, bone, fiber_valid : ndarray of bool
        Intermediate masks.
    regions : ndarray of int16
        Multiphase region index (-1 outside the muscle domain).
    findings : list of :class:`~pixmuscle.segmentation.qc.Finding`
        Quality problems (:func:`pixmuscle.segmentation.qc.segmentation_findings`: a bone or the
        outline vanishing or jumping in area between slices, muscles assigned mostly by the
        nearest-seed fall-back); the segment stage logs them as warnings.
    """

    labels: np.ndarray
    muscle_id: np.ndarray
    muscle_names: list
    fiber: np.ndarray
    qc: dict = field(default_factory=dict)
    leg: np.ndarray | None = None
    bone: np.ndarray | None = None
    fiber_valid: np.ndarray | None = None
    regions: np.ndarray | None = None
    findings: list = field(default_factory=list)


def seeds_to_voxels(seeds, units, affine, shape):
    """Seed points of each muscle as voxel indices ``(i, j, k)`` of the MRI grid.

    Parameters
    ----------
    seeds : dict of str -> list of [x, y, z]
        Muscle name -> points, in world cm (``units="cm"``), world mm (``"mm"``) or voxel
        indices of this (canonical, RAS+) grid (``"voxel"``; the segment stage converts voxel
        indices of the file's own grid to cm first, see :func:`pixmuscle.imaging.nifti.file_affine_cm`).
    units : {"cm", "mm", "voxel"}
    affine : ndarray, shape ``(4, 4)``
        MRI voxel index -> world cm.
    shape : tuple of 3 int

    Returns
    -------
    names : list of str
    points : list of ndarray of int64, each ``(n_m, 3)``
    """
    names, points = [], []
    inv = np.linalg.inv(affine)
    for name, pts in seeds.items():
        p = np.asarray(pts, dtype=float).reshape(-1, 3)
        if units in ("cm", "mm"):
            p = (p * (0.1 if units == "mm" else 1.0)) @ inv[:3, :3].T + inv[:3, 3]
        elif units != "voxel":
            raise InputError(f"segment.seed_units: expected 'cm', 'mm' or 'voxel', got {units!r}")
        ijk = np.rint(p).astype(np.int64)
        bad = np.any((ijk < 0) | (ijk >= np.array(shape)), axis=1)
        if bad.any():
            raise InputError(f"segment.seeds.{name}: point(s) {np.asarray(pts)[bad].tolist()} "
                             f"({units}) fall outside the MRI grid {tuple(shape)}")
        names.append(str(name))
        points.append(ijk)
    return names, points


def _zero_tensor(tensor, covered) -> np.ndarray:
    """Voxels inside the DTI field of view whose tensor is all zero (no diffusion signal)."""
    t = np.asarray(tensor)
    zero = ~np.any(t.reshape(t.shape[:3] + (-1,)) != 0, axis=-1)
    return zero if covered is None else zero & np.asarray(covered, bool)


def muscle_like(candidates, intensity, muscle) -> np.ndarray:
    """The candidate voxels that look like muscle on the MRI, in blobs rather than thin rims.

    Muscle-like: intensity within two standard deviations of the mean over ``muscle`` voxels.
    An in-plane 3 × 3 opening then drops one-voxel rims (partial volume at a fat boundary), so
    what is left are regions that a DTI gap took away from a muscle.

    Parameters
    ----------
    candidates, muscle : ndarray of bool, shape ``(I, J, K)``
    intensity : ndarray of float, shape ``(I, J, K)``
    """
    if not muscle.any() or not candidates.any():
        return np.zeros_like(candidates, dtype=bool)
    mu, sd = float(intensity[muscle].mean()), float(intensity[muscle].std())
    like = candidates & (np.abs(intensity - mu) <= 2.0 * sd)
    plane = np.zeros((3, 3, 3), bool)
    plane[:, :, 1] = True
    return ndi.binary_opening(like, structure=plane)


def no_signal_per_muscle(no_signal, muscle_id, n_muscles, spacing) -> np.ndarray:
    """Voxels without diffusion signal, attributed to the nearest muscle.

    Parameters
    ----------
    no_signal : ndarray of bool, shape ``(I, J, K)``
        Voxels without DTI signal that look like muscle.
    muscle_id : ndarray of int, shape ``(I, J, K)``
        0 or 1..M.
    n_muscles : int
    spacing : (3,) float
        Voxel size (cm) for the distances.

    Returns
    -------
    ndarray of int64, shape ``(M,)``
        Count of no-signal voxels whose nearest muscle voxel belongs to muscle m (0 when there is
        no muscle voxel at all).
    """
    out = np.zeros(n_muscles, np.int64)
    if not no_signal.any() or not (muscle_id > 0).any():
        return out
    _, idx = ndi.distance_transform_edt(muscle_id == 0, sampling=spacing, return_indices=True)
    nearest = muscle_id[tuple(i[no_signal] for i in idx)]
    return np.bincount(nearest, minlength=n_muscles + 1)[1:n_muscles + 1].astype(np.int64)


def no_signal_warnings(no_signal, muscle_voxels, names) -> list[str]:
    """One warning line for muscle-like voxels without DTI signal (see :func:`muscle_like`); none if there are none."""
    no_signal, muscle_voxels = np.asarray(no_signal), np.asarray(muscle_voxels)
    if no_signal.sum() == 0:
        return []
    parts = [f"{n} {int(c)} (it kept {int(m)})"
             for n, c, m in zip(names, no_signal, muscle_voxels, strict=True) if c > 0]
    return [f"DTI has no signal (zero tensor) in {int(no_signal.sum())} voxels that look like muscle on the MRI; "
            f"without fibre data they cannot be muscle and were labelled fat. Voxels per nearest muscle: "
            f"{', '.join(parts)}. Check the DTI (masking, coverage) before trusting volumes and forces"]


def _check_distinct_seeds(names, points_ijk, when=""):
    """Two muscles may not share a seed voxel (one of them would get no voxel at all).

    ``points_ijk``: per muscle, ``(n_m, 3)`` voxel indices (i, j, k). Raises InputError naming both.
    """
    owner: dict = {}
    for name, pts in zip(names, points_ijk, strict=True):  # loop over muscles (a handful)
        for p in {tuple(int(c) for c in q) for q in np.asarray(pts).reshape(-1, 3)}:
            other = owner.setdefault(p, name)
            if other != name:
                raise InputError(f"segment.seeds: '{other}' and '{name}' have a seed in the same voxel (i, j, k) = "
                                 f"{p}{' ' + when if when else ''}; give each muscle a point inside it")


def _snap(points, domain_t, name, max_voxels=3):
    # points (n, 3) in (z, i, j) order; move each to the nearest domain voxel of its slice
    out = points.copy()
    for n, (z, i, j) in enumerate(points):
        if domain_t[z, i, j]:
            continue
        if not domain_t[z].any():
            raise InputError(f"segment.seeds.{name}: slice {z} has no voxel with fibre data")
        dist, idx = ndi.distance_transform_edt(~domain_t[z], return_indices=True)
        if dist[i, j] > max_voxels:
            raise InputError(f"segment.seeds.{name}: seed at voxel (i, j, k) = ({i}, {j}, {z}) "
                             f"is {dist[i, j]:.1f} voxels from the nearest muscle voxel (voxel "
                             "with fibre data inside the leg, not bone); move it into the muscle")
        out[n, 1:] = idx[0][i, j], idx[1][i, j]
    return out


def _two_phase(u, p, mask, mode, spacing, want):
    """Bright or dark class of two-phase Chan–Vese; ``u`` (Z, I, J); returns bool (Z, I, J)."""
    out = np.zeros(u.shape, bool)
    iters, conv = [], []
    kw = dict(mu=p.mu, nu=p.nu, lambda1=p.lambda1, lambda2=p.lambda2, dt=p.dt, eps=p.eps,
              tol=p.tol, max_iter=p.max_iter, reinit_every=p.reinit_every, init="mean",
              stop="regions", window=p.window, energy_scale="variance")
    pieces = [slice(None)] if mode == "3d" else list(range(u.shape[0]))
    for sl in pieces:
        m = None if mask is None else mask[sl]
        if m is not None and np.count_nonzero(m) < 2:
            iters.append(0)
            conv.append(True)
            continue
        img = u[sl]
        if m is not None and np.ptp(img[m]) == 0:
            iters.append(0)
            conv.append(True)
            continue
        sp = _pixel_units(spacing if mode == "3d" else spacing[1:])
        r = chan_vese(img, spacing=sp, mask=m, **kw)
        inside = r.phi > 0
        inside_bright = bool(np.all(r.c1 >= r.c2))
        seg = inside if inside_bright == (want == "bright") else ~inside
        if m is not None:
            seg &= m
        out[sl] = seg
        iters.append(r.n_iter)
        conv.append(r.converged)
    return out, np.array(iters), np.array(conv)


def _bones(dark, bright, spacing, cfg):
    """Bone (cortex + marrow) per slice from the dark and bright classes; bool (Z, I, J)."""
    bone = np.zeros_like(dark)
    for z in range(dark.shape[0]):
        d = dark[z]
        holes = ndi.binary_fill_holes(d) & ~d
        lab, n = ndi.label(holes)
        if n == 0:
            continue
        frac = ndi.mean(bright[z], lab, index=np.arange(1, n + 1))
        marrow = np.isin(lab, 1 + np.flatnonzero(np.asarray(frac) >= cfg.min_marrow_bright))
        if not marrow.any():
            continue
        dist = ndi.distance_transform_edt(~marrow, sampling=spacing[1:])
        cortex = d & (dist <= cfg.max_cortex_cm)
        bone[z] = ndi.binary_fill_holes(cortex | marrow)
    return bone


def _multiphase(ch, domain, seeds_t, spacing, mp, mode):
    """Region map (Z, I, J) int16 (-1 outside the domain) and diagnostics."""
    K = mp.n_levelsets
    P = 2**K
    C = ch.shape[0]
    if mp.lambdas_per_region is not None:
        lam = np.asarray(mp.lambdas_per_region, dtype=float)
        if lam.shape != (P, C):
            raise InputError(f"segment.multiphase.lambdas_per_region: shape {lam.shape}, expected "
                             f"(2^K, channels) = {(P, C)}")
    else:
        lam = np.asarray(mp.lambdas, dtype=float)
        if lam.size not in (1, C):
            raise InputError(f"segment.multiphase.lambdas: expected 1 or {C} values (one per "
                             f"channel), got {lam.size}")
        lam = np.broadcast_to(lam, (P, C))
    lam_ch = lam.mean(axis=0)
    kw = dict(n_levelsets=K, mu=np.asarray(mp.mu), lambdas=lam, dt=mp.dt, eps=mp.eps,
              tol=mp.tol, max_iter=mp.max_iter, reinit_every=mp.reinit_every, stop="regions",
              window=mp.window, energy_scale="variance")
    regions = np.full(domain.shape, -1, dtype=np.int16)
    feats = seed_features(ch, seeds_t, mask=domain) if mp.init == "seeds" else None
    iters = np.zeros(domain.shape[0], dtype=np.int64)
    conv = np.ones(domain.shape[0], dtype=bool)

    def run(u, m, sp, init):
        if isinstance(init, str) and init == "seeds":
            init = seed_regions(u, feats, P, mask=m, lambdas=lam_ch)
        return _mp_call(u, m, sp, init, kw)

    if mode == "3d":
        res = run(ch, domain, spacing, mp.init)
        regions[domain] = res.regions[domain]
        iters[:] = res.n_iter
        conv[:] = res.converged
        return regions, iters, conv
    # per slice; checkerboard / kmeans init: start at the slice with most seeds, then
    # warm-start each slice from its finished neighbour (keeps region identities across slices)
    zs = np.concatenate([s[:, 0] for s in seeds_t])
    z0 = int(np.bincount(zs, minlength=domain.shape[0]).argmax())
    order = [z0] + [z for d in range(1, domain.shape[0]) for z in (z0 + d, z0 - d)
                    if 0 <= z < domain.shape[0]]
    phi_prev: dict[int, np.ndarray] = {}
    for z in order:
        if not domain[z].any():
            continue
        if mp.init == "seeds":
            init = "seeds"
        else:
            nb = phi_prev.get(z - 1 if z > z0 else z + 1)
            init = mp.init if nb is None else nb
        res = run(ch[:, z], domain[z], spacing[1:], init)
        regions[z][domain[z]] = res.regions[domain[z]]
        phi_prev[z] = res.phi
        iters[z] = res.n_iter
        conv[z] = res.converged
    return regions, iters, conv


def _mp_call(u, m, sp, init, kw):
    return multiphase_chan_vese(u, spacing=_pixel_units(sp), mask=m, init=init, **kw)


def _pixel_units(spacing):
    # level-set lengths in units of the smallest (in-plane) voxel edge: mu is per pixel of
    # contour and lambda per pixel of area, as on the paper's images
    spacing = np.asarray(spacing, dtype=float)
    return spacing / spacing.min()


def segment_volume(mri, affine, dti_tensor_on_grid, covered, imct_mask, imat_mask, cfg,
                   progress=None):
    """Segment an MRI + DTI volume into tissue labels and individual muscles (paper §4).

    Parameters
    ----------
    mri : ndarray, shape ``(I, J, K)``
        Anatomical MRI (any intensity units); axis 2 is the slice axis.
    affine : ndarray, shape ``(4, 4)``
        MRI voxel index -> world, cm.
    dti_tensor_on_grid : ndarray, shape ``(I, J, K, 3, 3)`` or ``(I, J, K, 6)`` (FSL order)
        Diffusion tensors resampled onto the MRI grid (world axes).
    covered : ndarray of bool, shape ``(I, J, K)`` or None
        MRI voxels inside the DTI field of view.
    imct_mask, imat_mask : ndarray of bool, shape ``(I, J, K)``, or None
        Connective tissue / intramuscular fat on the MRI grid.
    cfg : SegmentConfig
    progress : object with ``advance(n=1, **fields)`` and ``log(msg)``, optional
        Advanced once per step (5 steps).

    Returns
    -------
    SegmentationResult
    """
    if not isinstance(cfg, SegmentConfig):
        raise InputError(f"segment_volume: cfg must be a SegmentConfig, got {type(cfg).__name__}")
    mri = np.asarray(mri, dtype=float)
    if mri.ndim != 3:
        raise InputError(f"MRI: expected a 3-D volume (I, J, K), got shape {mri.shape}")
    shape = mri.shape
    affine = np.asarray(affine, dtype=float)
    if affine.shape != (4, 4):
        raise InputError(f"MRI affine: expected (4, 4), got {affine.shape}")
    for name, m in (("covered", covered), ("imct_mask", imct_mask), ("imat_mask", imat_mask)):
        if m is not None and np.shape(m) != shape:
            raise InputError(f"{name}: shape {np.shape(m)}, expected the MRI grid {shape}")
    if not cfg.seeds:
        raise InputError("segment.seeds: no seed points; give at least one point per muscle")
    if dti_tensor_on_grid is None:
        raise InputError("segment: DTI tensors on the MRI grid are required (fibre data decide "
                         "which voxels are muscle and separate the muscles)")
    names, seeds_ijk = seeds_to_voxels(cfg.seeds, cfg.seed_units, affine, shape)
    _check_distinct_seeds(names, seeds_ijk)
    spacing_ijk = np.linalg.norm(affine[:3, :3], axis=0)
    spacing = spacing_ijk[[2, 0, 1]]  # (z, i, j) layout used below
    mode = cfg.mode

    def step(msg, **fields):
        _LOG.info(msg)
        if progress is not None:
            progress.advance(1, **fields)

    def t(a):  # (I, J, K, ...) -> (K, I, J, ...)
        return np.moveaxis(np.asarray(a), 2, 0)

    u = t(normalize_intensity(mri))
    imct = np.zeros(u.shape, bool) if imct_mask is None else t(np.asarray(imct_mask, bool))
    imat = None if imat_mask is None else np.asarray(imat_mask, bool)
    qc: dict = {}

    # 1. outer boundary
    leg, it, cv = _two_phase(u, cfg.outer, None, mode, spacing, "bright")
    leg = largest_component_per_slice(fill_holes_per_slice(leg, axis=0), axis=0)
    qc["outer_iterations"], qc["outer_converged"] = it, cv
    step("outer boundary", voxels=int(leg.sum()))

    # 2. bones
    bright, it1, cv1 = _two_phase(u, cfg.bone, leg & ~imct, mode, spacing, "bright")
    rest = leg & ~bright & ~imct
    dark, it2, cv2 = _two_phase(u, cfg.bone, rest, mode, spacing, "dark")
    bone = _bones(dark, bright, spacing, cfg)
    qc["bone_bright_iterations"], qc["bone_dark_iterations"] = it1, it2
    qc["bone_converged"] = cv1 & cv2
    step("bones", voxels=int(bone.sum()))

    # 3. fibre data
    valid, v, _ = fiber_data(dti_tensor_on_grid, covered, min_fa=cfg.fiber_min_fa,
                             min_trace=cfg.fiber_min_trace)
    valid_t, v_t = t(valid), t(v)
    domain = leg & ~bone & valid_t
    if not domain.any():
        raise InputError("segment: no voxel with fibre data inside the leg (check the DTI "
                         "coverage and its affine against the MRI)")
    step("fibre data", voxels=int(domain.sum()))

    # 4. muscles
    seeds_t = [_snap(s[:, [2, 0, 1]], domain, n) for n, s in zip(names, seeds_ijk, strict=True)]
    for n, before, after in zip(names, seeds_ijk, seeds_t, strict=True):  # loop over muscles
        moved = np.flatnonzero(np.any(before[:, [2, 0, 1]] != after, axis=1))
        for q in moved:
            d = np.linalg.norm((after[q] - before[q, [2, 0, 1]]) * spacing)
            _LOG.warning("segment.seeds.%s: seed at voxel (i, j, k) = %s is not on a muscle voxel (fibre data inside "
                         "the leg, not bone); moved %.2g cm to the nearest one, %s", n, tuple(int(c) for c in before[q]),
                         d, tuple(int(c) for c in after[q][[1, 2, 0]]))
    _check_distinct_seeds(names, [s[:, [1, 2, 0]] for s in seeds_t], "after moving seeds into the muscle")
    mp = cfg.multiphase
    chans = []
    if mp.use_mri:
        chans.append(u[None])
    if mp.fiber_channels != "none":
        chans.append(fiber_channels(v_t, valid_t, mode=mp.fiber_channels))
    if not chans:
        raise InputError("segment.multiphase: no channel (use_mri is false and fiber_channels "
                         "is 'none')")
    ch = np.concatenate(chans, axis=0)
    regions, it, cv = _multiphase(ch, domain, seeds_t, spacing, mp, mode)
    region_map = np.where(domain, regions, 0)
    muscle_t, info = regions_to_muscles(region_map, domain, seeds_t, spacing, connectivity=1)
    qc["multiphase_iterations"], qc["multiphase_converged"] = it, cv
    qc["shared_regions"] = info["shared"]
    qc["claimed_fraction"] = info["claimed_fraction"]
    qc["muscle_domain_voxels"], qc["fallback_voxels"] = info["muscle_voxels"], info["fallback_voxels"]
    qc["seed_region"] = np.array(info["seed_region"])
    qc["seed_voxels_ijk"] = [s[:, [1, 2, 0]] for s in seeds_t]
    step("muscles", shared=len(info["shared"]))
    if info["shared"]:
        _LOG.warning("muscles sharing one region were split by nearest seed: %s",
                     ", ".join("+".join(names[m - 1] for m in grp) for grp in info["shared"]))

    # 5. labels
    def back(a):  # (K, I, J, ...) -> (I, J, K, ...)
        return np.moveaxis(a, 0, 2)

    labels, mid, fiber = assemble_labels(back(leg), back(bone), valid, back(muscle_t),
                                         imct_mask=None if imct_mask is None else
                                         np.asarray(imct_mask, bool),
                                         imat_mask=imat, fibers=v)
    qc["muscle_voxels"] = np.bincount(mid.ravel(), minlength=len(names) + 1)[1:]
    qc["tissue_voxels"] = np.bincount(labels.ravel(), minlength=5)
    no_signal = back(leg) & ~back(bone) & ~valid & _zero_tensor(dti_tensor_on_grid, covered) & ~back(imct)
    if imat is not None:
        no_signal &= ~imat
    no_signal = muscle_like(no_signal, back(u), mid > 0)
    qc["no_signal_voxels"] = no_signal_per_muscle(no_signal, mid, len(names), spacing_ijk)
    for w in no_signal_warnings(qc["no_signal_voxels"], qc["muscle_voxels"], names):
        _LOG.warning("%s", w)
    findings = segmentation_findings(labels, affine, fallback_voxels=info["fallback_voxels"],
                                     muscle_voxels=info["muscle_voxels"], names=names)
    qc["outline_voxels_per_slice"] = (labels > 0).reshape(-1, shape[2]).sum(axis=0)
    qc["bone_voxels_per_slice"] = bone_areas(labels == 4)
    step("labels")
    return SegmentationResult(labels=labels, muscle_id=mid, muscle_names=names, fiber=fiber,
                              qc=qc, leg=back(leg), bone=back(bone), fiber_valid=valid,
                              regions=back(regions), findings=findings)

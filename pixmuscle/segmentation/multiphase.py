"""Multiphase multichannel level-set segmentation (Vese & Chan 2002; paper §4.1, eq. 21).

``K`` level sets split the image into ``2**K`` regions (region index from the signs, see
:func:`pixmuscle.segmentation.levelset.region_index`); the energy of eq. (21) is::

    sum_k mu_k |{phi_k = 0}| + sum_p int_{Omega_p} (1/C) sum_i lambda_p^i (u_i - c_p^i)**2

with ``c_p^i`` the mean of channel ``i`` over region ``p`` (updated every sweep). Each sweep
updates every ``phi_k`` semi-implicitly (:func:`pixmuscle.segmentation.levelset.evolve_step`).

Regions are turned into named muscles by seed points (:func:`regions_to_muscles`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage as ndi

from pixmuscle.errors import InputError
from pixmuscle.segmentation.levelset import (
    checkerboard_level_set,
    evolve,
    region_index,
    signed_distance,
)

__all__ = [
    "MultiphaseResult",
    "multiphase_chan_vese",
    "level_sets_from_regions",
    "kmeans_regions",
    "seed_features",
    "seed_regions",
    "regions_to_muscles",
]


@dataclass
class MultiphaseResult:
    """Outcome of :func:`multiphase_chan_vese`.

    Attributes
    ----------
    regions : ndarray of int64, spatial shape
        Region index ``0 .. 2**K - 1`` of every voxel.
    phi : ndarray of float64, shape ``(K, *spatial)``
    means : ndarray of float64, shape ``(2**K, C)``
        Channel means ``c_p^i`` of each region (over ``mask``).
    n_iter : int
    converged : bool
    """

    regions: np.ndarray
    phi: np.ndarray
    means: np.ndarray
    n_iter: int
    converged: bool


def level_sets_from_regions(regions, n_levelsets, spacing=None):
    """Level sets whose signs encode given region indices (bit ``k`` of ``p`` <-> ``phi_k > 0``).

    Parameters
    ----------
    regions : ndarray of int, spatial shape
        Values ``0 .. 2**K - 1``.
    n_levelsets : int
        ``K``.
    spacing : sequence of float, optional
        Voxel size; ``phi`` is the signed distance in units of the smallest spacing.

    Returns
    -------
    phi : ndarray of float64, shape ``(K, *regions.shape)``
    """
    regions = np.asarray(regions)
    if regions.min() < 0 or regions.max() >= 2**n_levelsets:
        raise InputError(f"regions: values must lie in 0..{2**n_levelsets - 1} for "
                         f"{n_levelsets} level sets, got {regions.min()}..{regions.max()}")
    unit = 1.0 if spacing is None else float(np.min(spacing))
    return np.stack([signed_distance((regions >> k) & 1 == 1, spacing) / unit
                     for k in range(n_levelsets)])


def kmeans_regions(channels, n_regions, mask=None, lambdas=1.0, n_iter=30,
                   max_samples=200_000, seed=0, n_init=4):
    """Initial region map by k-means clustering of the channel vectors.

    k-means++ seeding (random generator ``seed``; deterministic) and Lloyd iterations on at
    most ``max_samples`` voxels of ``mask``, best of ``n_init`` starts, in the metric of the
    data term of eq. (21) (``sum_i lambda^i (u_i - c^i)**2``); every voxel then joins its
    nearest centre. Cluster
    ``q`` becomes region ``q``. Vese–Chan's flow moves each voxel across one level set at a
    time, so it can stall in a partition where one class occupies two regions whose bit
    patterns differ in two level sets; starting from the clusters avoids most such traps.

    Parameters
    ----------
    channels : ndarray, shape ``(C, *spatial)``
    n_regions : int
    mask : ndarray of bool, spatial shape, optional
    lambdas : float or ndarray of shape ``(C,)``
    n_iter : int
    max_samples : int
    seed : int
    n_init : int

    Returns
    -------
    regions : ndarray of int64, spatial shape (0 outside ``mask``)
    centres : ndarray, shape ``(n_regions, C)``
    """
    u = np.asarray(channels, float)
    C = u.shape[0]
    w = np.sqrt(np.broadcast_to(np.asarray(lambdas, float), (C,)))
    mask = np.ones(u.shape[1:], bool) if mask is None else np.asarray(mask, bool)
    x = (u[:, mask] * w[:, None]).T  # (N, C)
    rng = np.random.default_rng(seed)
    sample = x if len(x) <= max_samples else x[rng.choice(len(x), max_samples, replace=False)]
    best, best_inertia = None, np.inf
    for _ in range(n_init):
        centres, inertia = _lloyd(sample, _kmeanspp(sample, n_regions, rng), n_iter)
        if inertia < best_inertia:
            best, best_inertia = centres, inertia
    centres = best
    regions = np.zeros(u.shape[1:], dtype=np.int64)
    regions[mask] = _nearest(x, centres)[0]
    return regions, centres / np.where(w > 0, w, 1.0)


def _nearest(pts, centres):
    d = (np.sum(pts**2, axis=1)[:, None] - 2.0 * pts @ centres.T
         + np.sum(centres**2, axis=1)[None, :])
    a = d.argmin(axis=1)
    return a, float(np.maximum(d[np.arange(len(a)), a], 0.0).sum())


def _kmeanspp(sample, n, rng):
    centres = [sample[rng.integers(len(sample))]]
    d2 = np.sum((sample - centres[0]) ** 2, axis=1)
    for _ in range(1, n):
        total = d2.sum()
        nxt = sample[rng.choice(len(sample), p=d2 / total)] if total > 0 else centres[-1]
        centres.append(nxt)
        d2 = np.minimum(d2, np.sum((sample - nxt) ** 2, axis=1))
    return np.array(centres)


def _lloyd(sample, centres, n_iter):
    for _ in range(n_iter):
        a, _ = _nearest(sample, centres)
        counts = np.bincount(a, minlength=len(centres))
        new = np.stack([np.bincount(a, weights=col, minlength=len(centres))
                        for col in sample.T], axis=1)
        empty = counts == 0
        new[~empty] /= counts[~empty, None]
        new[empty] = centres[empty]
        if np.allclose(new, centres):
            break
        centres = new
    return centres, _nearest(sample, centres)[1]


def _initial(init, n_levelsets, spatial, spacing, u=None, mask=None, lam=None):
    if isinstance(init, str):
        if init == "checkerboard":
            # smooth checkerboards of doubling period: every bit pattern occurs everywhere
            return np.stack([checkerboard_level_set(spatial, 5.0 * 2**k)
                             for k in range(n_levelsets)])
        if init == "kmeans":
            regions, _ = kmeans_regions(u, 2**n_levelsets, mask=mask, lambdas=lam)
            return level_sets_from_regions(regions, n_levelsets, spacing)
        raise InputError(f"init: unknown initialisation {init!r}; expected 'checkerboard', "
                         "'kmeans', a region-index array or a (K, ...) level-set array")
    arr = np.asarray(init)
    if arr.shape == tuple(spatial) and np.issubdtype(arr.dtype, np.integer):
        return level_sets_from_regions(arr, n_levelsets, spacing)
    if arr.shape == (n_levelsets, *spatial):
        return arr.astype(float)
    raise InputError(f"init: array of shape {arr.shape}; expected region indices {tuple(spatial)}"
                     f" (integers) or level sets {(n_levelsets, *spatial)}")


def multiphase_chan_vese(channels, *, n_levelsets=3, mu=1.0, lambdas=0.02, dt=0.5, eps=1.0,
                         tol=1e-3, max_iter=300, init="checkerboard", reinit_every=5,
                         spacing=None, mask=None, stop="phi", window=5,
                         energy_scale="range"):
    """Multiphase multichannel Vese–Chan segmentation (paper eq. 21).

    Parameters
    ----------
    channels : ndarray, shape ``(C, Y, X)`` or ``(C, Z, Y, X)``
        Channels on a common intensity scale (see :mod:`.features`).
    n_levelsets : int
        ``K``; ``2**K`` regions.
    mu : float or sequence of K float
        Length weight of each level set (paper: 1 or 100).
    lambdas : float or array_like broadcastable to ``(2**K, C)``
        Data weight per region and channel (paper: 0.02 everywhere); the data term is averaged
        over the ``C`` channels.
    dt, eps, tol, max_iter, reinit_every
        Time step, Dirac width, stopping tolerance, iteration limit, reinitialisation period
        (see :func:`.levelset.evolve`). Without reinitialisation the level sets grow steep on
        one side of a contour and flat on the other, and the discrete curvature then slowly
        shrinks the regions; resetting them to signed distances every few sweeps stops that.
    init : {"checkerboard", "kmeans"} or ndarray
        ``"checkerboard"``: smooth checkerboards of periods ``10 * 2**k`` voxels (Vese & Chan);
        ``"kmeans"``: :func:`kmeans_regions` of the channels; an integer array of region
        indices (spatial shape; e.g. from :func:`seed_regions`); or initial level sets
        ``(K, *spatial)``. Level sets made from regions are signed distances in units of the
        smallest spacing.
    spacing : sequence of float, optional
        Voxel size per spatial axis (curvature); default 1.
    mask : ndarray of bool, spatial shape, optional
        Voxels that carry data: region means and data forces only there.
    stop : {"phi", "regions"}
        Stopping test: RMS level-set change per sweep, or the fraction of voxels changing
        region over ``window`` sweeps (see :func:`.levelset.evolve`).
    window : int
    energy_scale : {"range", "variance"} or float
        Constant the energy is divided by (same minimisers; sets the time scale of ``dt``),
        see :func:`.levelset.evolve`.

    Returns
    -------
    MultiphaseResult
    """
    u = np.asarray(channels, dtype=float)
    if u.ndim not in (3, 4):
        raise InputError(f"channels: expected (C, Y, X) or (C, Z, Y, X), got shape {u.shape}")
    if not np.isfinite(u).all():
        raise InputError("channels: contain NaN or infinite values")
    K = int(n_levelsets)
    if not 1 <= K <= 6:
        raise InputError(f"n_levelsets: expected 1..6, got {n_levelsets}")
    C = u.shape[0]
    spatial = u.shape[1:]
    try:
        lam = np.broadcast_to(np.asarray(lambdas, float), (2**K, C))
    except ValueError:
        raise InputError(f"lambdas: shape {np.shape(lambdas)} does not broadcast to "
                         f"(regions, channels) = {(2**K, C)}") from None
    mu = np.asarray(mu, dtype=float)
    if mu.size not in (1, K):
        raise InputError(f"mu: expected 1 or {K} values, got {mu.size}")
    if (lam < 0).any() or (mu < 0).any():
        raise InputError("lambdas and mu must be >= 0")
    spacing = np.ones(len(spatial)) if spacing is None else np.asarray(spacing, dtype=float)
    if spacing.shape != (len(spatial),) or (spacing <= 0).any():
        raise InputError(f"spacing: expected {len(spatial)} positive numbers, got {spacing}")
    if mask is not None:
        mask = np.asarray(mask, bool)
        if mask.shape != spatial:
            raise InputError(f"mask: shape {mask.shape}, expected {spatial}")
        if not mask.any():
            raise InputError("mask: empty (no voxel to segment)")
    phi0 = _initial(init, K, spatial, spacing, u, mask, lam.mean(axis=0))
    if len(spatial) == 2:
        u3, phi3 = u[:, None], phi0[:, None]
        sp3 = np.concatenate([[1.0], spacing])
        m3 = None if mask is None else mask[None]
    else:
        u3, phi3, sp3, m3 = u, phi0, spacing, mask
    phi, c, n_iter, converged = evolve(u3, phi3, lam, 0.0, mu, dt=dt, eps=eps, tol=tol,
                                       max_iter=int(max_iter), reinit_every=int(reinit_every),
                                       spacing=sp3, mask=m3, stop=stop, window=int(window),
                                       energy_scale=energy_scale)
    phi = phi.reshape((K, *spatial))
    return MultiphaseResult(region_index(phi), phi, c, n_iter, converged)


def seed_features(channels, seeds, mask=None, radius=1):
    """Mean channel vector around each muscle's seed points.

    Parameters
    ----------
    channels : ndarray, shape ``(C, *spatial)``
    seeds : list of ndarray of int, each ``(n_m, ndim)``
        Voxel indices of the seeds of muscle ``m`` (``m = 0 .. M-1``).
    mask : ndarray of bool, spatial shape, optional
        Only voxels in ``mask`` contribute.
    radius : int
        Half-width (voxels) of the cube around each seed; on a 3-D grid only the seed's
        own slice (first spatial axis) is used.

    Returns
    -------
    features : ndarray, shape ``(M, C)``
    """
    u = np.asarray(channels, float)
    spatial = u.shape[1:]
    mask = np.ones(spatial, bool) if mask is None else np.asarray(mask, bool)
    feats = np.empty((len(seeds), u.shape[0]))
    for m, pts in enumerate(seeds):
        sel = np.zeros(spatial, bool)
        for pt in np.atleast_2d(pts):
            sl = tuple(slice(max(int(x) - (0 if (len(spatial) == 3 and a == 0) else radius), 0),
                             int(x) + 1 + (0 if (len(spatial) == 3 and a == 0) else radius))
                       for a, x in enumerate(pt))
            sel[sl] = True
        sel &= mask
        if not sel.any():
            raise InputError(f"seeds of muscle #{m + 1}: no voxel of the segmentation domain "
                             f"within {radius} voxel(s) of {np.atleast_2d(pts).tolist()}")
        feats[m] = u[:, sel].mean(axis=1)
    return feats


def seed_regions(channels, features, n_regions, mask=None, lambdas=1.0, outlier_factor=3.0):
    """Initial region map: each voxel joins the muscle whose seed features it is closest to.

    Muscle ``m`` (0-based) gets region ``m mod n_regions``. The distance is the data term of
    eq. (21), ``(1/C) sum_i lambda^i (u_i - f_m^i)**2``. If there are fewer muscles than
    regions, the last region collects the voxels outside ``mask`` and the masked voxels whose
    distance exceeds ``outlier_factor`` times the median of the nearest-seed distances (tissue
    unlike any seed: septa, fat islands).

    Parameters
    ----------
    channels : ndarray, shape ``(C, *spatial)``
    features : ndarray, shape ``(M, C)``
        From :func:`seed_features`.
    n_regions : int
        ``2**K``.
    mask : ndarray of bool, spatial shape, optional
    lambdas : float or ndarray of shape ``(C,)``
    outlier_factor : float

    Returns
    -------
    regions : ndarray of int64, spatial shape
    """
    u = np.asarray(channels, float)
    feats = np.asarray(features, float)
    lam = np.broadcast_to(np.asarray(lambdas, float), (u.shape[0],))
    n_m = feats.shape[0]
    dist = np.empty((n_m, *u.shape[1:]))
    for m in range(n_m):
        dist[m] = np.tensordot(lam, (u - feats[m].reshape((-1,) + (1,) * (u.ndim - 1)))**2,
                               axes=1) / u.shape[0]
    best = dist.argmin(axis=0)
    regions = (best % n_regions).astype(np.int64)
    if n_m < n_regions:
        other = n_regions - 1
        dmin = dist.min(axis=0)
        inside = np.ones(u.shape[1:], bool) if mask is None else np.asarray(mask, bool)
        med = np.median(dmin[inside]) if inside.any() else 0.0
        regions[~inside] = other
        regions[inside & (dmin > outlier_factor * med)] = other
    return regions


def regions_to_muscles(regions, domain, seeds, spacing=None, connectivity=1):
    """Assign each domain voxel to a muscle from a region map and seed points.

    Rules, in order:

    1. Each muscle claims the connected component(s) of ``domain & (regions == r)`` that
       contain its seeds (``r`` the region at the seed).
    2. A component claimed by several muscles (they fell into one region and touch) is split
       between them by the nearest seed: Euclidean distance in physical units (``spacing``) to
       the claiming muscles' seed points (plain distance transform, not geodesic).
    3. Domain voxels of unclaimed components (islands of a region away from its seeds)
       join the muscle of the nearest claimed voxel (Euclidean, physical units).

    Parameters
    ----------
    regions : ndarray of int, spatial shape
    domain : ndarray of bool, spatial shape
        Voxels to assign (the muscle candidates).
    seeds : list of ndarray of int, each ``(n_m, ndim)``
        Seed voxel indices of muscle ``m = 0 .. M-1``; each must lie in ``domain``.
    spacing : sequence of float, optional
        Voxel size per axis (cm); default 1.
    connectivity : int
        ``scipy.ndimage.generate_binary_structure`` connectivity of the components
        (1: faces only).

    Returns
    -------
    muscle_id : ndarray of int16, spatial shape
        ``1..M`` in ``domain``, 0 elsewhere.
    info : dict
        ``shared`` (list of lists of 1-based muscle ids that shared a component),
        ``claimed_fraction`` (domain fraction assigned by rules 1-2),
        ``seed_region`` (region index at the first seed of each muscle),
        ``muscle_voxels`` (M,) domain voxels of each muscle, ``fallback_voxels`` (M,) those of them
        assigned by the nearest-seed fall-back (rules 2 and 3) rather than by a region of their own.
    """
    regions = np.asarray(regions)
    domain = np.asarray(domain, bool)
    spacing = np.ones(regions.ndim) if spacing is None else np.asarray(spacing, float)
    struct = ndi.generate_binary_structure(regions.ndim, connectivity)
    seeds = [np.atleast_2d(np.asarray(s, dtype=np.int64)) for s in seeds]
    for m, pts in enumerate(seeds):
        if pts.shape[1] != regions.ndim:
            raise InputError(f"seeds of muscle #{m + 1}: expected {regions.ndim} coordinates per "
                             f"point, got {pts.shape[1]}")
        if (pts < 0).any() or (pts >= np.array(regions.shape)).any():
            raise InputError(f"seeds of muscle #{m + 1}: {pts.tolist()} outside the image "
                             f"{regions.shape}")
        if not domain[tuple(pts.T)].all():
            raise InputError(f"seeds of muscle #{m + 1}: {pts[~domain[tuple(pts.T)]].tolist()} "
                             "not in the muscle domain (voxels with fibre data)")
    muscle_id = np.zeros(regions.shape, dtype=np.int16)
    # connected components of every region, numbered globally
    comp = np.zeros(regions.shape, dtype=np.int64)
    n_total = 0
    for r in np.unique(regions[domain]):
        lab, n = ndi.label(domain & (regions == r), structure=struct)
        comp[lab > 0] = lab[lab > 0] + n_total
        n_total += n
    claims: dict[int, list[int]] = {}
    for m, pts in enumerate(seeds):
        for c in np.unique(comp[tuple(pts.T)]):
            claims.setdefault(int(c), [])
            if m not in claims[int(c)]:
                claims[int(c)].append(m)
    shared = []
    objects = ndi.find_objects(comp)
    split = np.zeros(regions.shape, dtype=bool)
    for c, ms in claims.items():
        in_c = comp == c
        if len(ms) == 1:
            muscle_id[in_c] = ms[0] + 1
            continue
        shared.append(sorted(m + 1 for m in ms))
        split |= in_c
        # nearest seed within the component's bounding box
        box = objects[c - 1]
        marker = np.zeros(regions.shape, dtype=np.int16)
        for m in ms:
            marker[tuple(seeds[m].T)] = m + 1
        sub_marker = marker[box]  # the seeds lie in the component, hence in its box
        local = in_c[box]
        _, idx = ndi.distance_transform_edt(sub_marker == 0, sampling=spacing,
                                            return_indices=True)
        nearest = sub_marker[tuple(idx)]
        muscle_id[box][local] = nearest[local]
    claimed = muscle_id > 0
    n_dom = int(domain.sum())
    info = {
        "shared": shared,
        "claimed_fraction": float(claimed.sum() / n_dom) if n_dom else 0.0,
        "seed_region": [int(regions[tuple(pts[0])]) for pts in seeds],
    }
    rest = domain & ~claimed
    if rest.any():
        _, idx = ndi.distance_transform_edt(~claimed, sampling=spacing, return_indices=True)
        muscle_id[rest] = muscle_id[tuple(i[rest] for i in idx)]
    M = len(seeds)
    info["muscle_voxels"] = np.bincount(muscle_id[domain], minlength=M + 1)[1:M + 1].astype(np.int64)
    info["fallback_voxels"] = np.bincount(muscle_id[domain & (split | rest)], minlength=M + 1)[1:M + 1].astype(np.int64)
    return muscle_id, info

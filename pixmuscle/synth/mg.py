"""SYNTHETIC medial gastrocnemius (MG) phantoms of a young and an old subject (paper Example 3).

The paper's MG models (Table 3) are not public; these phantoms reproduce their tissue
*proportions*: IMCT/muscle and IMAT/muscle volume ratios of the young and the old subject,
with IMCT not counting the aponeurosis (as in the paper). See docs/phantoms.md.

Anatomy (cm, +x medio-lateral, +y anterior = deep, +z proximal): a curved ("banana") elliptical
cross-section whose size varies along the muscle (belly shape), wrapped in an aponeurosis
(connective tissue), subcutaneous fat and skin. Inside, IMCT forms sheets along the fascicles:
the cell walls of a random Voronoi pattern, swept along the fibre direction, thickened until
the IMCT fraction matches Table 3. IMAT is a smooth random field thresholded (preferring the
neighbourhood of the IMCT sheets) until its fraction matches Table 3. Fibres are pennate: tilted
by the pennation angle from the muscle axis toward the deep aponeurosis.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from pixmuscle.errors import InputError
from pixmuscle.synth.noise import smooth_field
from pixmuscle.synth.phantom import (
    BACKGROUND,
    CT,
    FAT,
    MUSCLE,
    SKIN,
    Phantom,
    Sample,
    check_fits,
    check_phantom_args,
    dti_grid,
    grid_affine,
    render_phantom,
    voxel_centres,
)

#: paper Table 3 volumes (cm^3): muscle, IMAT, IMCT (IMCT without the aponeurosis)
TABLE3 = {
    "young": {"muscle": 98.93, "imat": 2.83, "imct": 20.86},
    "old": {"muscle": 61.89, "imat": 6.15, "imct": 29.15},
}
#: default pennation angle (deg) per subject: 25 deg, a typical young MG value, and 13 % smaller
#: when old (Narici et al. 2003, J Appl Physiol 95: older MG pennation -13 %, fascicles -10 %)
PENNATION_DEG = {"young": 25.0, "old": 25.0 * 0.87}
#: default fascicle length (cm): the young MG's 2.4 cm thickness / sin(25 deg), 10 % shorter when old
FASCICLE_CM = {"young": 2.4 / np.sin(np.radians(25.0)), "old": 0.90 * 2.4 / np.sin(np.radians(25.0))}


def table3_ratios(subject: str) -> dict:
    """Target ratios ``imct/muscle`` and ``imat/muscle`` of Table 3 for ``subject``."""
    t = TABLE3[subject]
    return {"imct_per_muscle": t["imct"] / t["muscle"], "imat_per_muscle": t["imat"] / t["muscle"]}


def _size_scale(subject: str) -> float:
    """Linear cross-section scale of the subject: old/young area = ratio of Table 3 totals."""
    tot = {s: sum(v.values()) for s, v in TABLE3.items()}
    return float(np.sqrt(tot[subject] / tot["young"]))


def semi_axes(size_scale: float, fascicle_cm: float, pennation_deg: float) -> tuple[float, float]:
    """Semi-axes (a, b) cm of the MG cross-section (inside the aponeurosis, at the belly).

    The thickness 2b is what a straight fascicle of length ``fascicle_cm`` at ``pennation_deg``
    spans between the aponeuroses (2b = L_f sin θ); the width 2a keeps the area of the young
    5.6 × 2.4 cm ellipse scaled by ``size_scale`` squared.
    """
    b = 0.5 * fascicle_cm * np.sin(np.radians(pennation_deg))
    a = 2.8 * 1.2 * size_scale**2 / b
    return float(a), float(b)


class MGAnatomy:
    """Callable anatomy of the MG phantom: ``anatomy(points (n,3) cm, want_fiber) -> Sample``.

    The IMCT and IMAT thresholds are unset until :meth:`calibrate` is called.
    """

    def __init__(self, centre, z_range, rng, *, semi_axes=(2.8, 1.2), bend_cm=0.35, apo_cm=0.12,
                 fat_cm=0.35, skin_cm=0.1, septum_cm=0.12, imct_fraction=0.17, pennation_deg=25.0,
                 fiber_spread_deg=3.0, imct_layout="parallel"):
        self.centre = np.asarray(centre, dtype=float)
        self.z0, self.z1 = z_range
        self.a, self.b = semi_axes
        self.bend = bend_cm
        self.apo, self.fat, self.skin = apo_cm, fat_cm, skin_cm
        pen = np.radians(pennation_deg)
        self.fiber = np.array([0.0, np.sin(pen), np.cos(pen)])
        self.sweep = np.tan(pen)
        # each of the 2 components orthogonal to the fibre has std spread/sqrt(2): rms angle = spread
        self.spread = np.tan(np.radians(fiber_spread_deg)) / np.sqrt(2.0)
        # Voronoi seeds with a density giving walls ~septum_cm thick at the target fraction
        # (Poisson-Voronoi wall length per area = 2 sqrt(density))
        density = (max(imct_fraction, 1e-3) / (2.0 * septum_cm)) ** 2 / 4.0
        length = self.z1 - self.z0
        ext = np.array([self.a + 1.0, self.b + 1.0 + self.sweep * length + 1.0])
        n = max(int(rng.poisson(density * 4 * ext[0] * ext[1])), 4)
        self.seeds = rng.uniform(-1, 1, size=(n, 2)) * ext - np.array([0.0, self.sweep * length / 2])
        self.tree = cKDTree(self.seeds)
        self.layout = imct_layout
        if imct_layout == "series":  # sheets crossing the fibres: planes normal to the fibre, random spacing
            span = self.fiber[1] * 2 * ext[1] + self.fiber[2] * length + 2.0
            mean = septum_cm / max(imct_fraction, 1e-3)
            gaps = rng.uniform(0.5 * mean, 1.5 * mean, size=int(span / (0.5 * mean)) + 2)
            self.layers = np.cumsum(gaps) - self.fiber[1] * ext[1] - 1.0
        self.imat_field = smooth_field(rng, (0.35, 0.35, 1.5), 16)
        self.spread_fields = [smooth_field(rng, (2.0, 2.0, 4.0), 8) for _ in range(3)]
        self.t_imct = -np.inf  # IMCT where wall distance < t_imct
        self.t_imat = np.inf  # IMAT where score > t_imat

    def _scale(self, zeta):
        u = 2.0 * zeta / max(self.z1 - self.z0, 1e-9) - 1.0
        return 1.0 - 0.12 * u**2

    def outer_extent(self):
        """Half-extents (x, y) cm of the phantom (skin included) about its centre."""
        pad = self.apo + self.fat + self.skin
        return np.array([self.a + pad, self.b + self.bend + pad]) * 1.03

    def _layers(self, points):
        """Reference coords q (n, 2), zeta (n,), and approx. distance inside the MG surface (cm)."""
        zeta = points[:, 2] - self.z0
        s = self._scale(zeta)
        x = points[:, 0] - self.centre[0]
        y = points[:, 1] - self.centre[1] - self.bend * ((x / self.a) ** 2 - 0.5)
        u, v = x / (self.a * s), y / (self.b * s)
        r = np.hypot(u, v)
        g = np.hypot(u / (self.a * s), v / (self.b * s)) / np.maximum(r, 1e-12)
        d = (1.0 - r) / np.maximum(g, 1e-12)
        return np.column_stack([x, y]), zeta, d

    def wall_distance(self, q, zeta):
        """Distance (cm) to the nearest IMCT wall: of the Voronoi pattern swept along the fibres
        (``parallel``: sheets containing the fibres), or of the planes normal to the fibre
        (``series``: sheets the fibres cross)."""
        if self.layout == "series":
            s = q[:, 1] * self.fiber[1] + zeta * self.fiber[2]
            i = np.clip(np.searchsorted(self.layers, s), 1, len(self.layers) - 1)
            return np.minimum(np.abs(s - self.layers[i - 1]), np.abs(self.layers[i] - s))
        q0 = q - np.column_stack([np.zeros_like(zeta), self.sweep * (zeta - 0.5 * (self.z1 - self.z0))])
        k = min(5, len(self.seeds))
        d, i = self.tree.query(q0, k=k)
        s1 = self.seeds[i[:, 0]]
        sj = self.seeds[i[:, 1:]]
        sep = np.maximum(np.linalg.norm(sj - s1[:, None, :], axis=-1), 1e-9)
        wall = (d[:, 1:] ** 2 - d[:, :1] ** 2) / (2.0 * sep)
        # the walls are sheets containing the fibre: the in-plane distance shrinks by cos(pennation)
        return wall.min(axis=1) * self.fiber[2]

    def _imat_score(self, points, wall):
        return self.imat_field(points) - wall / 0.25

    def calibrate(self, points, imct_fraction, imat_fraction):
        """Set the IMCT/IMAT thresholds so that, over the interior ``points`` (n, 3) cm, exactly
        ``imct_fraction`` are IMCT and ``imat_fraction`` are IMAT (quantiles)."""
        q, zeta, d = self._layers(points)
        inner = d >= 0
        if inner.sum() < 20:
            raise InputError("make_mg_phantom: fewer than 20 voxels inside the muscle; use a finer grid")
        wall = self.wall_distance(q[inner], zeta[inner])
        self.t_imct = np.quantile(wall, imct_fraction) if imct_fraction > 0 else -np.inf
        rest = wall >= self.t_imct
        score = self._imat_score(points[inner][rest], wall[rest])
        level = 1.0 - imat_fraction / max(rest.mean(), 1e-12)
        self.t_imat = np.quantile(score, np.clip(level, 0.0, 1.0)) if imat_fraction > 0 else np.inf

    def __call__(self, points, want_fiber=False) -> Sample:
        points = np.asarray(points, dtype=float).reshape(-1, 3)
        n = len(points)
        q, zeta, d = self._layers(points)
        cls = np.full(n, BACKGROUND, dtype=np.int8)
        cls[d >= -(self.apo + self.fat + self.skin)] = SKIN
        cls[d >= -(self.apo + self.fat)] = FAT
        cls[d >= -self.apo] = CT
        apo = ((cls == CT) & (d < 0)) | (cls == SKIN)
        inner = np.flatnonzero(d >= 0)
        c = np.full(len(inner), MUSCLE, dtype=np.int8)
        wall = self.wall_distance(q[inner], zeta[inner])
        c[wall < self.t_imct] = CT
        imat_in = (c == MUSCLE) & (self._imat_score(points[inner], wall) > self.t_imat)
        c[imat_in] = FAT
        cls[inner] = c
        imat = np.zeros(n, dtype=bool)
        imat[inner] = imat_in
        muscle = (cls == MUSCLE).astype(np.int16)
        fiber = None
        if want_fiber:
            fiber = np.zeros((n, 3))
            m = muscle > 0
            f = np.broadcast_to(self.fiber, (int(m.sum()), 3)).copy()
            if self.spread > 0:
                delta = self.spread * np.stack([fld(points[m]) for fld in self.spread_fields], axis=1)
                delta -= np.sum(delta * f, axis=1, keepdims=True) * f
                f += delta
                f /= np.linalg.norm(f, axis=1, keepdims=True)
            fiber[m] = f
        return Sample(cls=cls, muscle=muscle, imat=imat, apo=apo, fiber=fiber)


def make_mg_phantom(subject="young", shape=(96, 64, 10), pixel_cm=0.078125, slice_cm=0.5, noise=0.04,
                    dti_factor=2, seed=0, *, length_cm=None, size_scale=None, pennation_deg=None,
                    dti_noise=0.05, supersample=4, supersample_z=2, bias=0.03, septum_cm=None,
                    fiber_spread_deg=3.0, fascicle_cm=None, imct_layout="parallel", tissue_ratios=None,
                    aponeurosis_cm=0.12) -> Phantom:
    """SYNTHETIC medial gastrocnemius of a young or old subject with Table 3 tissue proportions.

    A stand-in for the paper's Example 3 data (not public): see docs/phantoms.md.

    Parameters
    ----------
    subject : {"young", "old"}
        Sets the IMCT/muscle and IMAT/muscle volume ratios of paper Table 3 (young: 0.211,
        0.0286; old: 0.471, 0.0994; IMCT excluding the aponeurosis), the cross-section size
        (old/young area = 0.793, the ratio of the Table 3 totals, so that old/young muscle volume
        is about 0.62 as in Table 3), the default pennation angle (25 / 21.75 deg) and fascicle
        length (5.68 / 5.11 cm): older MG has smaller pennation (-13 %) and shorter fascicles
        (-10 %), Narici et al. 2003.
    shape : (I, J, K) tuple of int
        MRI grid; axes 0 (medio-lateral) and 1 (antero-posterior) in-plane, axis 2 along the muscle.
        The young MG is about 5.6 x 2.8 cm (7 x 3.6 cm with aponeurosis, fat and skin).
    pixel_cm, slice_cm : float
        In-plane pixel size (default 0.078125 cm, the paper's) and slice spacing (cm).
    noise : float
        Rician noise level relative to the fat signal (1.0), as in :func:`make_leg_phantom`.
    dti_factor : int
        DTI in-plane voxel size = ``dti_factor * pixel_cm``; DTI field of view 110 % of the MRI's,
        shifted, slices offset by half a slice.
    seed : int
        Random seed; the phantom is a deterministic function of all arguments.
    length_cm : float, optional
        Length along the muscle; overrides ``shape[2] = round(length_cm / slice_cm)``.
        (The real MG is 15-20 cm long; the default 5 cm keeps tests fast.)
    size_scale : float, optional
        Linear scale of the cross-section (default 1 for young, 0.89 for old).
    pennation_deg : float, optional
        Fibre angle from the muscle axis, tilted toward +y (the deep aponeurosis).
    fascicle_cm : float, optional
        Fascicle length; with the pennation it sets the thickness (:func:`semi_axes`). Default:
        the subject's (5.68 / 5.11 cm) when ``pennation_deg`` is not given; otherwise the length
        that keeps the subject's default thickness.
    imct_layout : {"parallel", "series"}
        IMCT sheets containing the fibres (default: the endomysium/perimysium-like arrangement,
        mechanically in parallel with them) or sheets normal to the fibres, which every fibre
        crosses (in series with them) — for experiments (docs/examples.md).
    tissue_ratios : dict, optional
        ``{"imct_per_muscle": r, "imat_per_muscle": r}``: the target volume ratios instead of
        Table 3's (:func:`table3_ratios`), e.g. to hold the volumes of a phantom whose
        architecture or IMCT layout changed (benchmarks/bench_example3.py).
    aponeurosis_cm : float
        Thickness of the aponeurosis (connective tissue around the muscle), cm.
    dti_noise, supersample, supersample_z, bias, fiber_spread_deg
        As in :func:`make_leg_phantom`.
    septum_cm : float, optional
        Target thickness of the IMCT sheets (sets the density of the Voronoi pattern);
        default 1.5 pixels.

    Returns
    -------
    Phantom
        ``muscle_names == ["medial_gastrocnemius"]``; ``outer_ct_mask`` holds the aponeurosis
        and the skin; IMCT of Table 3 is ``imct_mask & ~outer_ct_mask``. Use
        :func:`tissue_volumes` for the Table 3 quantities.
    """
    if imct_layout not in ("parallel", "series"):
        raise InputError(f"make_mg_phantom: imct_layout must be 'parallel' or 'series', got {imct_layout!r}")
    if subject not in TABLE3:
        raise InputError(f"make_mg_phantom: subject must be 'young' or 'old', got {subject!r}")
    shape = [int(n) for n in shape]
    if length_cm is not None:
        if not length_cm > 0:
            raise InputError(f"make_mg_phantom: length_cm must be > 0, got {length_cm}")
        shape[2] = max(1, int(round(length_cm / slice_cm)))
    shape, dti_factor = check_phantom_args("make_mg_phantom", shape, pixel_cm, slice_cm, noise, dti_noise, dti_factor)
    size_scale = _size_scale(subject) if size_scale is None else float(size_scale)
    pennation_deg = PENNATION_DEG[subject] if pennation_deg is None else float(pennation_deg)
    if fascicle_cm is None:  # the subject's thickness (default fascicle at the default pennation)
        fascicle_cm = FASCICLE_CM[subject] * np.sin(np.radians(PENNATION_DEG[subject])) / np.sin(np.radians(pennation_deg))
    fascicle_cm = float(fascicle_cm)
    if not fascicle_cm > 0 or not 0 < pennation_deg < 90:
        raise InputError(f"make_mg_phantom: fascicle_cm must be > 0 and pennation_deg in (0, 90), got "
                         f"{fascicle_cm}, {pennation_deg}")
    septum_cm = 1.5 * pixel_cm if septum_cm is None else float(septum_cm)
    ratios = dict(table3_ratios(subject), **(tissue_ratios or {}))
    if set(ratios) != {"imct_per_muscle", "imat_per_muscle"} or min(ratios.values()) < 0:
        raise InputError(f"make_mg_phantom: tissue_ratios takes imct_per_muscle and imat_per_muscle >= 0, got "
                         f"{tissue_ratios}")
    if not aponeurosis_cm > 0:
        raise InputError(f"make_mg_phantom: aponeurosis_cm must be > 0, got {aponeurosis_cm}")
    denom = 1.0 + ratios["imct_per_muscle"] + ratios["imat_per_muscle"]
    f_ct, f_at = ratios["imct_per_muscle"] / denom, ratios["imat_per_muscle"] / denom
    rng = np.random.default_rng(seed)

    spacing = np.array([pixel_cm, pixel_cm, slice_cm])
    origin = np.array([-0.5 * (shape[0] - 1) * pixel_cm - 4.3, -0.5 * (shape[1] - 1) * pixel_cm - 6.2, 20.0])
    affine = grid_affine(spacing, origin)
    centre = origin[:2] + 0.5 * (np.array(shape[:2]) - 1) * pixel_cm
    z_range = (origin[2], origin[2] + (shape[2] - 1) * slice_cm)
    anatomy = MGAnatomy(centre, z_range, rng, semi_axes=semi_axes(size_scale, fascicle_cm, pennation_deg),
                        septum_cm=septum_cm, imct_fraction=f_ct, apo_cm=float(aponeurosis_cm), pennation_deg=pennation_deg,
                        fiber_spread_deg=fiber_spread_deg, imct_layout=imct_layout)
    ext = anatomy.outer_extent()
    check_fits("make_mg_phantom", centre - ext, centre + ext, affine, shape)
    anatomy.calibrate(voxel_centres(affine, shape).reshape(-1, 3), f_ct, f_at)
    dshape, dti_affine = dti_grid(shape, affine, dti_factor, fov_fraction=1.1, shift_cm=(0.21, -0.17))
    check_fits("make_mg_phantom", centre - ext, centre + ext, dti_affine, dshape, what="DTI")

    params = dict(kind="mg", subject=subject, shape=list(shape), pixel_cm=pixel_cm, slice_cm=slice_cm,
                  noise=noise, dti_factor=dti_factor, seed=seed, size_scale=size_scale,
                  pennation_deg=pennation_deg, fascicle_cm=fascicle_cm, dti_noise=dti_noise, supersample=supersample,
                  supersample_z=supersample_z, bias=bias, septum_cm=septum_cm,
                  fiber_spread_deg=fiber_spread_deg, imct_layout=imct_layout, table3_target=dict(TABLE3[subject]))
    if tissue_ratios is not None or aponeurosis_cm != 0.12:  # (the shipped samples' parameters unchanged)
        params.update(tissue_ratios=ratios, aponeurosis_cm=float(aponeurosis_cm))
    return render_phantom(anatomy, shape, affine, dshape, dti_affine, rng, noise=noise,
                          dti_noise=dti_noise, ss=supersample, ss_z=supersample_z, bias=bias,
                          muscle_contrast=0.0, names=["medial_gastrocnemius"], params=params)


def tissue_volumes(phantom: Phantom) -> dict:
    """Table 3 quantities of a phantom's ground truth, cm^3.

    ``muscle``: ``labels == 1``; ``imat``: ``imat_mask``; ``imct``: connective tissue other
    than skin and aponeurosis (``imct_mask & ~outer_ct_mask``); ``outer_ct``: skin and
    aponeurosis.
    """
    v = phantom.voxel_volume
    return {
        "muscle": float((phantom.labels == 1).sum() * v),
        "imat": float(phantom.imat_mask.sum() * v),
        "imct": float((phantom.imct_mask & ~phantom.outer_ct_mask).sum() * v),
        "outer_ct": float(phantom.outer_ct_mask.sum() * v),
    }

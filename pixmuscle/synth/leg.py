"""SYNTHETIC lower-leg phantom: MRI, DTI and ground truth of 7 muscles (paper Example 2 stand-in).

The paper's leg scans are not public; this phantom imitates an axial T1-weighted scan of a
right mid-calf with a co-registered, coarser DTI. See docs/phantoms.md.

Reference anatomy (cm, relative to the leg centre; +x lateral, +y anterior, +z proximal, the
RAS+ axes of a right leg): an egg-shaped cross-section, skin, a subcutaneous fat layer of
varying thickness, the deep fascia, tibia (anteromedial, triangular, under the skin) and fibula
(lateral) each with dark cortex and bright marrow, the interosseous membrane, and 7 muscles
partitioning the remaining space as an additively weighted Voronoi diagram of anatomical seed
points with smoothly perturbed (curved) boundaries. A thin connective-tissue septum (one MRI
pixel by default) separates adjacent muscles. Fat (IMAT) islands elongated along the leg sit
inside some muscles. The cross-section tapers and twists slowly along the leg; the seeds drift.
"""

from __future__ import annotations

import numpy as np

from pixmuscle.imaging.dti import canonical_sign
from pixmuscle.synth.noise import smooth_field
from pixmuscle.synth.phantom import (
    BACKGROUND,
    CORTEX,
    CT,
    FAT,
    MARROW,
    MUSCLE,
    SKIN,
    Phantom,
    Sample,
    check_fits,
    check_phantom_args,
    dti_grid,
    grid_affine,
    render_phantom,
)

MUSCLE_NAMES = [
    "tibialis_anterior",
    "extensor_digitorum_longus",
    "peroneus_longus",
    "tibialis_posterior",
    "soleus",
    "medial_gastrocnemius",
    "lateral_gastrocnemius",
]

# seed point (x, y) cm and additive weight (cm) of each muscle, reference cross-section
_SEEDS = np.array([
    [0.3, 2.6], [2.6, 2.3], [4.0, -0.3], [0.7, -0.6], [-0.6, -1.7], [-2.1, -3.7], [2.0, -3.8],
])
_WEIGHTS = np.array([0.3, 0.0, 0.0, 0.0, 0.3, 0.5, 0.35])
# fibre direction of each muscle: tilt from the leg axis (+z) and azimuth from +x toward +y, deg
# (tibialis anterior near the axis, the others on a 38 deg cone 60 deg of azimuth apart:
# every pair of muscles differs by at least 26 deg)
FIBER_TILT_DEG = np.array([15.0, 38.0, 38.0, 38.0, 38.0, 38.0, 38.0])
FIBER_AZIMUTH_DEG = np.array([45.0, 15.0, 255.0, 135.0, 195.0, 75.0, 315.0])

# outer boundary: x semi-axis, y semi-axis anterior, posterior (cm)
_OUTER = (5.0, 4.2, 5.3)
# bones: centre (x, y), mean radius, triangularity, angle of a vertex (deg), cortex thickness
_TIBIA = ((-1.9, 2.0), 1.45, 0.12, 95.0, 0.35)
# the tibia's anteromedial face is covered by skin and fat only: polar-angle range (deg) about it
_TIBIA_SUBCUTANEOUS = (95.0, 200.0)
_FIBULA = ((2.75, 0.1), 0.7, 0.10, 200.0, 0.25)


def fiber_directions() -> np.ndarray:
    """(7, 3) unit fibre direction of each muscle in the reference frame (before the twist)."""
    t = np.radians(FIBER_TILT_DEG)
    a = np.radians(FIBER_AZIMUTH_DEG)
    return np.stack([np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), np.cos(t)], axis=1)


class LegAnatomy:
    """Callable anatomy of the leg phantom: ``anatomy(points (n,3) cm, want_fiber) -> Sample``."""

    def __init__(self, centre, z_range, rng, *, leg_scale=1.0, septum_cm=0.156, skin_cm=0.12,
                 fat_cm=0.6, taper_per_cm=0.015, twist_deg_per_cm=1.0, fiber_spread_deg=3.0,
                 n_imat=6):
        self.centre = np.asarray(centre, dtype=float)
        self.z0, self.z1 = z_range
        self.leg_scale = leg_scale
        self.septum = septum_cm
        self.skin = skin_cm
        self.fat = fat_cm
        self.taper = taper_per_cm
        self.twist = np.radians(twist_deg_per_cm)
        # each of the 2 components orthogonal to the fibre has std spread/sqrt(2): rms angle = spread
        self.spread = np.tan(np.radians(fiber_spread_deg)) / np.sqrt(2.0)
        self.fibers = fiber_directions()
        self.seed_phase = rng.uniform(0, 2 * np.pi, size=(7, 2))
        self.boundary_fields = [smooth_field(rng, (1.5, 1.5, 4.0), 8) for _ in range(7)]
        self.fat_field = smooth_field(rng, (2.0, 2.0, 6.0), 8)
        self.spread_fields = [smooth_field(rng, (2.0, 2.0, 4.0), 8) for _ in range(3)]
        self.imat = self._place_imat(rng, n_imat)

    # -- geometry in the reference frame -------------------------------------------------
    def _reference(self, points):
        """Reference coords (n, 2), scale s (n,), zeta (n,) of world points (n, 3)."""
        zeta = points[:, 2] - self.z0
        zmid = 0.5 * (self.z1 - self.z0)
        s = self.leg_scale * np.clip(1.0 + self.taper * (zeta - zmid), 0.8, 1.2)
        ang = self.twist * (zeta - zmid)
        c, sn = np.cos(ang), np.sin(ang)
        x = points[:, 0] - self.centre[0]
        y = points[:, 1] - self.centre[1]
        xr = (c * x + sn * y) / s
        yr = (-sn * x + c * y) / s
        return np.stack([xr, yr], axis=1), s, zeta

    def bounding_box(self):
        """World (x, y) corners ``lo, hi`` (cm) of a box holding the leg in every slice."""
        zmid = 0.5 * (self.z1 - self.z0)
        smax = self.leg_scale * min(1.2, 1.0 + self.taper * zmid) * 1.03
        a, b_ant, b_post = _OUTER
        return self.centre + smax * np.array([-a, -b_post]), self.centre + smax * np.array([a, b_ant])

    def _seeds(self, zeta):
        """Seed positions (7, n, 2) drifting with zeta."""
        ph = self.seed_phase
        dx = 0.25 * np.sin(zeta[None, :] / 2.5 + ph[:, :1])
        dy = 0.25 * np.cos(zeta[None, :] / 3.0 + ph[:, 1:])
        return _SEEDS[:, None, :] + np.stack([dx, dy], axis=-1)

    @staticmethod
    def _bone(q, bone):
        (cx, cy), r0, tri, vert, cortex = bone
        dx, dy = q[:, 0] - cx, q[:, 1] - cy
        rho = np.hypot(dx, dy)
        th = np.arctan2(dy, dx)
        r = r0 * (1.0 + tri * np.cos(3.0 * (th - np.radians(vert))))
        return rho < r, rho < r - cortex

    def _outer_distance(self, q):
        a, b_ant, b_post = _OUTER
        b = np.where(q[:, 1] >= 0, b_ant, b_post)
        u, v = q[:, 0] / a, q[:, 1] / b
        r = np.hypot(u, v)
        g = np.hypot(u / a, v / b) / np.maximum(r, 1e-12)
        return (1.0 - r) / np.maximum(g, 1e-12)

    def _muscle_partition(self, q, zeta, p3):
        """Muscle index 1..7 and distance (ref. cm) to the nearest muscle-muscle boundary.

        Costs ``|q - seed_m| - w_m + eps f_m(p)``; the boundary distance is the cost gap of
        the two cheapest muscles over the norm of their gradient difference (first order).
        """
        seeds = self._seeds(zeta)  # (7, n, 2)
        diff = q[None, :, :] - seeds
        dist = np.maximum(np.linalg.norm(diff, axis=-1), 1e-9)
        eps = 0.25
        cost = dist - _WEIGHTS[:, None]
        for m, f in enumerate(self.boundary_fields):
            cost[m] += eps * f(p3)
        order = np.argsort(cost, axis=0)[:2]
        n = np.arange(q.shape[0])
        c1, c2 = cost[order[0], n], cost[order[1], n]
        grad = np.zeros((2, q.shape[0], 2))
        for r in range(2):
            grad[r] = diff[order[r], n] / dist[order[r], n][:, None]
            for m, f in enumerate(self.boundary_fields):
                sel = order[r] == m
                if np.any(sel):
                    grad[r, sel] += eps * f.gradient(p3[sel])[:, :2]
        g = np.linalg.norm(grad[1] - grad[0], axis=1)
        dboundary = (c2 - c1) / np.maximum(g, 1e-9)
        return order[0] + 1, dboundary

    def _place_imat(self, rng, n_imat):
        """IMAT ellipsoids: (n, 5) centre x, y (ref cm), zeta (cm), in-plane radius, z radius."""
        out = []
        tries = 0
        while len(out) < n_imat and tries < 50:
            tries += 1
            cand = np.column_stack([rng.uniform(-4.5, 4.5, 64), rng.uniform(-4.8, 3.8, 64)])
            zeta = rng.uniform(0.0, max(self.z1 - self.z0, 1e-6), 64)
            p3 = np.column_stack([cand, zeta])
            cls, _, dbound, _, _ = self._classify(cand, np.ones(64), zeta, p3, imat=False)
            ok = np.flatnonzero((cls == MUSCLE) & (dbound > 0.5))
            for i in ok[: n_imat - len(out)]:
                out.append([cand[i, 0], cand[i, 1], zeta[i], rng.uniform(0.15, 0.35), rng.uniform(1.0, 2.0)])
        return np.array(out).reshape(-1, 5)

    def _classify(self, q, s, zeta, p3, imat=True):
        """Signal class, muscle index, muscle-boundary distance, outer-CT and IMAT flags of points."""
        n = q.shape[0]
        cls = np.full(n, BACKGROUND, dtype=np.int8)
        muscle = np.zeros(n, dtype=np.int16)
        dbound = np.full(n, np.inf)
        apo = np.zeros(n, dtype=bool)
        d_all = self._outer_distance(q) * s
        inside = np.flatnonzero(d_all >= 0)
        q, s, zeta, p3, d_out = q[inside], s[inside], zeta[inside], p3[inside], d_all[inside]
        c = np.full(len(inside), MUSCLE, dtype=np.int8)
        th = np.arctan2(q[:, 1], q[:, 0])
        t_fat = self.fat * (1.0 + 0.35 * np.cos(th - np.radians(235.0)) + 0.15 * self.fat_field(p3))
        fascia = d_out < self.skin + t_fat + self.septum
        c[fascia] = CT
        c[d_out < self.skin + t_fat] = FAT
        c[d_out < self.skin] = SKIN
        a_in = fascia & (c == CT)
        # muscle partition and septa
        mus = np.flatnonzero(c == MUSCLE)
        m_in = np.zeros(len(inside), dtype=np.int16)
        db_in = np.full(len(inside), np.inf)
        if len(mus):
            idx, db = self._muscle_partition(q[mus], zeta[mus], p3[mus])
            m_in[mus] = idx
            db_in[mus] = db * s[mus]
            c[mus[db_in[mus] < 0.5 * self.septum]] = CT
        # interosseous membrane: segment between the bone centres
        a, b = np.array(_TIBIA[0]), np.array(_FIBULA[0])
        t = np.clip((q - a) @ (b - a) / np.dot(b - a, b - a), 0.0, 1.0)
        dmem = np.linalg.norm(q - (a + t[:, None] * (b - a)), axis=1) * s
        c[(c == MUSCLE) & (dmem < 0.5 * self.septum)] = CT
        # the anteromedial face of the tibia is subcutaneous
        (tx, ty) = _TIBIA[0]
        tth = np.degrees(np.arctan2(q[:, 1] - ty, q[:, 0] - tx)) % 360.0
        sub = (tth > _TIBIA_SUBCUTANEOUS[0]) & (tth < _TIBIA_SUBCUTANEOUS[1]) & (c != SKIN)
        c[sub] = FAT
        a_in &= ~sub
        # IMAT islands replace muscle
        imat_in = np.zeros(len(inside), dtype=bool)
        if imat and len(self.imat):
            imat_in = (c == MUSCLE) & self._in_imat(q, zeta)
            c[imat_in] = FAT
        # bones override everything
        for bone in (_TIBIA, _FIBULA):
            whole, marrow = self._bone(q, bone)
            c[whole] = CORTEX
            c[marrow] = MARROW
        m_in[c != MUSCLE] = 0
        cls[inside] = c
        muscle[inside] = m_in
        dbound[inside] = db_in
        apo[inside] = (a_in & (c == CT)) | (c == SKIN)
        is_imat = np.zeros(n, dtype=bool)
        is_imat[inside] = imat_in & (c == FAT)
        return cls, muscle, dbound, apo, is_imat

    def __call__(self, points, want_fiber=False) -> Sample:
        points = np.asarray(points, dtype=float).reshape(-1, 3)
        q, s, zeta = self._reference(points)
        cls, muscle, _, apo, is_imat = self._classify(q, s, zeta, points)
        fiber = None
        if want_fiber:
            fiber = np.zeros((len(cls), 3))
            m = muscle > 0
            f = self.fibers[muscle[m] - 1]
            if self.spread > 0:
                delta = self.spread * np.stack([fld(points[m]) for fld in self.spread_fields], axis=1)
                delta -= np.sum(delta * f, axis=1, keepdims=True) * f
                f = f + delta
                f /= np.linalg.norm(f, axis=1, keepdims=True)
            # rotate with the twist of the cross-section (reference -> world)
            zmid = 0.5 * (self.z1 - self.z0)
            ang = -self.twist * (zeta[m] - zmid)
            c, sn = np.cos(ang), np.sin(ang)
            fx = c * f[:, 0] + sn * f[:, 1]
            fy = -sn * f[:, 0] + c * f[:, 1]
            fiber[m] = canonical_sign(np.column_stack([fx, fy, f[:, 2]]))
        return Sample(cls=cls, muscle=muscle, imat=is_imat, apo=apo, fiber=fiber)

    def _in_imat(self, q, zeta):
        hit = np.zeros(q.shape[0], dtype=bool)
        for cx, cy, cz, r, rz in self.imat:
            hit |= ((q[:, 0] - cx) ** 2 + (q[:, 1] - cy) ** 2) / r**2 + (zeta - cz) ** 2 / rz**2 < 1.0
        return hit


def make_leg_phantom(shape=(128, 128, 12), pixel_cm=0.156, slice_cm=0.5, noise=0.04, dti_factor=2,
                     seed=0, *, dti_noise=0.05, supersample=4, supersample_z=2, bias=0.03,
                     muscle_contrast=0.01, n_imat=6, septum_cm=None, leg_scale=1.0,
                     fiber_spread_deg=3.0) -> Phantom:
    """SYNTHETIC axial MRI + DTI of a right lower leg (mid-calf) with 7 muscles and ground truth.

    A stand-in for the paper's Example 2 data (not public): see docs/phantoms.md.

    Parameters
    ----------
    shape : (I, J, K) tuple of int
        MRI grid; axes 0, 1 in-plane (x lateral, y anterior), axis 2 along the leg (slices).
    pixel_cm : float
        In-plane pixel size, cm (default 0.156). The leg is about 10 x 9.5 cm, so the field
        of view ``shape[:2] * pixel_cm`` must be at least about 12.5 cm (else InputError).
    slice_cm : float
        Slice spacing, cm (default 0.5, several times the pixel size).
    noise : float
        Rician noise level: std of each Gaussian component, relative to the fat signal (1.0).
        Muscle signal is 0.42, connective tissue 0.12, cortical bone 0.03, marrow 0.90, air 0.
    dti_factor : int
        DTI in-plane voxel size = ``dti_factor * pixel_cm``; DTI slices have ``slice_cm`` but
        are offset by half a slice, and the DTI field of view is smaller (92 %) and shifted:
        the two grids are related only through their affines.
    seed : int
        Seed of the random generator; the phantom is a deterministic function of all arguments.
    dti_noise : float
        Gaussian noise on each tensor component, relative to the mean muscle diffusivity.
    supersample, supersample_z : int
        Sub-samples per voxel in-plane / along the slice for partial volume (MRI and DTI).
    bias : float
        Amplitude of a smooth multiplicative intensity (coil) bias field; 0 for none.
    muscle_contrast : float
        Per-muscle intensity offsets are spread over +-muscle_contrast (well below ``noise``:
        the muscles look alike on MRI and differ in fibre direction only).
    n_imat : int
        Number of intramuscular fat islands.
    septum_cm : float, optional
        Thickness of the connective-tissue septa between muscles, of the deep fascia and of the
        interosseous membrane; default one pixel.
    leg_scale : float
        Scales the whole cross-section.
    fiber_spread_deg : float
        RMS angle (deg) of a smooth random variation of the fibre direction (correlation length
        about 2 cm) about each muscle's direction; 0 for uniform fibres per muscle.

    Returns
    -------
    Phantom
        See :class:`pixmuscle.synth.phantom.Phantom`. ``muscle_names`` lists
        tibialis_anterior, extensor_digitorum_longus, peroneus_longus, tibialis_posterior,
        soleus, medial_gastrocnemius, lateral_gastrocnemius (ids 1..7). Fibre directions differ
        between any two muscles by at least 26 deg (tilt 15-38 deg from the leg axis, distinct
        azimuths); see ``FIBER_TILT_DEG``, ``FIBER_AZIMUTH_DEG``.
    """
    shape, dti_factor = check_phantom_args("make_leg_phantom", shape, pixel_cm, slice_cm, noise, dti_noise, dti_factor)
    septum_cm = pixel_cm if septum_cm is None else float(septum_cm)
    rng = np.random.default_rng(seed)

    spacing = np.array([pixel_cm, pixel_cm, slice_cm])
    fov = np.array(shape) * spacing
    origin = np.array([-0.5 * fov[0] + 0.5 * pixel_cm + 1.7, -0.5 * fov[1] + 0.5 * pixel_cm - 3.1, 12.0])
    affine = grid_affine(spacing, origin)
    centre = origin[:2] + 0.5 * (np.array(shape[:2]) - 1) * pixel_cm + np.array([0.0, 0.55])
    z_range = (origin[2], origin[2] + (shape[2] - 1) * slice_cm)

    anatomy = LegAnatomy(centre, z_range, rng, leg_scale=leg_scale, septum_cm=septum_cm,
                         fiber_spread_deg=fiber_spread_deg, n_imat=n_imat)
    lo, hi = anatomy.bounding_box()
    check_fits("make_leg_phantom", lo, hi, affine, shape)

    # DTI grid: coarser, smaller and shifted field of view, slices offset by half a slice
    dshape, dti_affine = dti_grid(shape, affine, dti_factor, fov_fraction=0.92, shift_cm=(0.37, -0.29))
    check_fits("make_leg_phantom", lo, hi, dti_affine, dshape, what="DTI")

    params = dict(kind="leg", shape=list(shape), pixel_cm=pixel_cm, slice_cm=slice_cm, noise=noise,
                  dti_factor=dti_factor, seed=seed, dti_noise=dti_noise, supersample=supersample,
                  supersample_z=supersample_z, bias=bias, muscle_contrast=muscle_contrast,
                  n_imat=n_imat, septum_cm=septum_cm, leg_scale=leg_scale,
                  fiber_spread_deg=fiber_spread_deg)
    return render_phantom(anatomy, shape, affine, dshape, dti_affine, rng, noise=noise,
                          dti_noise=dti_noise, ss=supersample, ss_z=supersample_z, bias=bias,
                          muscle_contrast=muscle_contrast, names=MUSCLE_NAMES, params=params)

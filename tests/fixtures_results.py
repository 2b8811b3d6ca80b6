"""Test fixture factory: a small but realistic ``results.h5`` (schema ``pixmuscle.results`` v1).

The model is a synthetic leg cross-section extruded along z: a bone (not a node) in the middle,
two muscles (x < centre: muscle 1, x > centre: muscle 2), a subcutaneous fat ring, two IMAT pockets
(one inside each muscle), a connective-tissue pocket inside muscle 1 and a connective-tissue patch
inside the fat ring far (> 2 cells) from any muscle. The true counts of every class are known by
construction and returned with the file. The mechanical fields are smooth analytic fields
(not a solve): displacement zero at both ends, Cauchy stress with a fibre tension, reactions that
balance, and a Newton log with quadratic convergence.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from pixmuscle.io.model import write_model_groups
from pixmuscle.model.model import Model
from pixmuscle.store import write_dataset, write_stage

SIGN_CONVENTION = ("reaction/<set> is the force (N) the support exerts on the body; force = reaction . n_out, "
                   "n_out = +z at z_max and -z at z_min; positive = tension")


@dataclasses.dataclass
class Truth:
    """Known answers of the fixture."""

    path: Path
    n_nodes: int
    cell_volume: float
    spacing: np.ndarray
    n_muscle: dict          # muscle id → node count
    n_imat: dict            # muscle id → IMAT node count
    n_imct: dict            # muscle id (0 = not attributed) → CT node count
    n_subcutaneous: int
    f_max: float | None  # largest end force over converged steps, N
    status: str
    imat_nodes: np.ndarray  # (N,) bool


def phantom_model(shape=(20, 20, 6), spacing=(0.25, 0.25, 1.0), origin=(1.0, -2.0, 0.5), scale: float = 1.0):
    """Leg-like pixel model and the class masks it was built from (grid-level, see module doc).

    ``scale`` > 1 enlarges the cross-section (in cells) for timing runs; the shape must be large
    enough (about 20 × scale cells in-plane).
    """
    shape = tuple(shape)
    ii, jj, kk = np.indices(shape)
    cx, cy = (shape[0] - 1) / 2.0, (shape[1] - 1) / 2.0
    dx, dy = (ii - cx) / scale, (jj - cy) / scale
    r = np.hypot(dx, dy)
    body = r <= 9.2
    bone = r <= 1.6
    fat_ring = body & (r > 5.6)
    muscle = body & ~bone & ~fat_ring
    box = lambda x0, x1, y0, y1: (dx >= x0) & (dx <= x1) & (dy >= y0) & (dy <= y1)  # noqa: E731
    pocket1 = box(-4.5, -3.5, -0.5, 0.5) & muscle                   # IMAT in muscle 1, all slices
    pocket2 = box(3.5, 4.5, -0.5, 0.5) & muscle & (kk >= 1) & (kk <= 3)  # IMAT in muscle 2, slices 1-3
    ct_in = box(-2.5, -2.5, 3.5, 4.5) & muscle                       # IMCT next to muscle 1
    ct_far = box(8.5, 8.5, -0.5, 0.5) & fat_ring                     # CT 3 cells from any muscle
    assert not (pocket1 & ct_in).any()
    labels = np.zeros(shape, np.int8)
    labels[muscle] = 1
    labels[fat_ring] = 3
    labels[pocket1 | pocket2] = 3
    labels[ct_in | ct_far] = 2
    mid = np.where(labels == 1, np.where(dx < 0, 1, 2), 0).astype(np.int16)

    node = labels > 0
    ijk = np.argwhere(node).astype(np.int32)           # C order: i, then j, then k
    sel = tuple(ijk.T)
    spacing = np.asarray(spacing, float)
    origin = np.asarray(origin, float)
    X = origin + ijk * spacing
    tissue = labels[sel]
    muscle_id = mid[sel]
    pen = np.deg2rad(15.0)
    fiber = np.zeros((ijk.shape[0], 3))
    fiber[muscle_id == 1] = [np.sin(pen), 0.0, np.cos(pen)]
    fiber[muscle_id == 2] = [-np.sin(pen), 0.0, np.cos(pen)]
    kmin, kmax = ijk[:, 2].min(), ijk[:, 2].max()
    sets = {
        "z_min": np.flatnonzero(ijk[:, 2] == kmin), "z_max": np.flatnonzero(ijk[:, 2] == kmax),
        "x_min": np.flatnonzero(ijk[:, 0] == ijk[:, 0].min()), "x_max": np.flatnonzero(ijk[:, 0] == ijk[:, 0].max()),
        "y_min": np.flatnonzero(ijk[:, 1] == ijk[:, 1].min()), "y_max": np.flatnonzero(ijk[:, 1] == ijk[:, 1].max()),
        "bone_surface": np.flatnonzero((r[sel] > 1.6) & (r[sel] <= 2.7)),
        "outer_surface": np.flatnonzero(r[sel] > 8.2),
    }
    model = Model(X=X, ijk=ijk, tissue=tissue, muscle_id=muscle_id, fiber=fiber, muscle_names=["medial", "lateral"],
                  spacing=spacing, origin=origin, shape=np.asarray(shape, np.int64), rotation=np.eye(3), sets=sets,
                  coarsen_factor=1)
    masks = {"pocket1": pocket1[sel], "pocket2": pocket2[sel], "ct_in": ct_in[sel], "ct_far": ct_far[sel],
             "fat_ring": fat_ring[sel] & ~ct_far[sel]}
    return model, masks


def _voigt(t):
    return np.stack([t[:, 0, 0], t[:, 1, 1], t[:, 2, 2], t[:, 0, 1], t[:, 1, 2], t[:, 0, 2]], axis=-1)


def write_results_fixture(path, *, n_steps: int = 4, alpha_end: float = 0.95, failed: bool = False,
                          newton_layout: str = "group", with_max_principal: bool = True,
                          attrs: dict | None = None, force_scale: float = 68.76, **model_kw) -> Truth:
    """Write a results file following docs/architecture.md and return the known answers.

    Parameters
    ----------
    n_steps : int
        S load steps (S+1 stored states).
    failed : bool
        Last step did not converge and the status is ``"failed: ..."``.
    newton_layout : "group" or "compound"
        How the /newton table is stored.
    with_max_principal : bool
        Leave out /steps/max_principal when False.
    """
    model, masks = phantom_model(**model_kw)
    n = model.n_nodes
    S = n_steps
    alpha = np.linspace(0.0, alpha_end, S + 1)
    load_factor = np.minimum(1.0, np.arange(S + 1) / max(S // 2, 1))
    converged = np.ones(S + 1, bool)
    iterations = np.r_[0, np.full(S, 4)]
    if failed:
        converged[-1] = False
        iterations[-1] = 25
    X = model.X
    z0, z1 = X[:, 2].min(), X[:, 2].max()
    zeta = (X[:, 2] - z0) / (z1 - z0)
    c = X.mean(axis=0)
    ismus = (model.tissue == 1).astype(float)
    shape_u = np.stack([0.05 * (X[:, 0] - c[0]) * np.sin(np.pi * zeta),
                        0.05 * (X[:, 1] - c[1]) * np.sin(np.pi * zeta),
                        -0.1 * np.sin(2 * np.pi * zeta) * (1.0 + 0.2 * ismus)], axis=-1)
    u = alpha[:, None, None] * shape_u[None]
    ff = np.einsum("ni,nj->nij", model.fiber, model.fiber)
    base = 20.0 * ff + ((-2.0 + 0.3 * zeta)[:, None, None] * np.eye(3))
    base[:, 0, 1] += 0.1 * zeta
    base[:, 1, 0] += 0.1 * zeta
    sig = alpha[:, None, None, None] * base[None]
    cauchy = np.stack([_voigt(s) for s in sig])               # (S+1, N, 6), loop over steps
    max_principal = np.linalg.eigvalsh(sig)[..., -1]          # (S+1, N)
    F = force_scale * (alpha / alpha_end) ** 1.3
    r_zmax = np.stack([0.02 * F, -0.01 * F, F], axis=-1)
    r_bone = np.stack([0.03 * F, -0.02 * F, 0.0 * F], axis=-1)
    r_zmin = -(r_zmax + r_bone)
    # Newton log: quadratic convergence, the failed step stagnates
    rows = []
    for s in range(1, S + 1):
        for it in range(int(iterations[s]) + 1):
            res = 10.0 ** (1 - 2 ** it) if converged[s] else 3.2e-2 * (1 + 0.1 * np.sin(it))
            rows.append((s, it, res, res ** 2 * 0.5, 1.0 if converged[s] else 0.5))
    log = np.array(rows, dtype=[("step", "<i8"), ("iteration", "<i8"), ("residual_norm", "<f8"),
                                ("energy_norm", "<f8"), ("line_search", "<f8")])
    status = (f"failed: Newton did not converge in step {S} (residual 3.2e-02 > tol 1.0e-08) after 3 cutbacks"
              if failed else "complete")

    def write(f):
        write_model_groups(f, model)
        st = f.create_group("steps")
        write_dataset(st, "alpha", alpha, units="1")
        write_dataset(st, "load_factor", load_factor, units="1")
        write_dataset(st, "converged", converged)
        write_dataset(st, "iterations", iterations.astype(np.int64))
        write_dataset(st, "u", u, units="cm")
        write_dataset(st, "d", u * 1.01, units="cm")
        write_dataset(st, "cauchy", cauchy, units="N/cm^2")
        if with_max_principal:
            write_dataset(st, "max_principal", max_principal, units="N/cm^2")
        rg = st.create_group("reaction")
        for name, r in (("z_min", r_zmin), ("z_max", r_zmax), ("bone_surface", r_bone)):
            write_dataset(rg, name, r, units="N")
        if newton_layout == "group":
            g = f.create_group("newton")
            for k in log.dtype.names:
                write_dataset(g, k, log[k])
        else:
            f.create_dataset("newton", data=log)

    root_attrs = {"status": status, "sign_convention": SIGN_CONVENTION, **(attrs or {})}
    cfg = {"activation": {"to": alpha_end, "steps": S}, "newton": {"tol": 1e-8, "max_iter": 25}}
    write_stage(path, schema="pixmuscle.results", version=1, write=write, config=cfg, attrs=root_attrs)
    ok = converged
    return Truth(
        path=Path(path), n_nodes=n, cell_volume=float(np.prod(model.spacing)), spacing=model.spacing,
        n_muscle={1: int((model.muscle_id == 1).sum()), 2: int((model.muscle_id == 2).sum())},
        n_imat={1: int(masks["pocket1"].sum()), 2: int(masks["pocket2"].sum())},
        n_imct={1: int(masks["ct_in"].sum()), 0: int(masks["ct_far"].sum())},
        n_subcutaneous=int(masks["fat_ring"].sum()),
        f_max=float(F[ok].max()), status=status, imat_nodes=masks["pocket1"] | masks["pocket2"],
    )


def write_mg_phantom(out: Path) -> tuple[Path, list]:
    """Write a tiny SYNTHETIC medial-gastrocnemius phantom (48 × 32 × 3 voxels, NIfTI) into ``out``.

    Returns ``out`` and a user's seed click: the deepest point of the muscle in the middle slice
    (world cm).
    """
    from scipy import ndimage as ndi

    from pixmuscle.synth import make_mg_phantom, write_phantom

    ph = make_mg_phantom("young", shape=(48, 32, 3), pixel_cm=0.156, seed=3)
    write_phantom(ph, out, "mg")
    k = ph.muscle_id.shape[2] // 2
    dist = ndi.distance_transform_edt(ph.muscle_id[:, :, k] == 1)
    i, j = np.unravel_index(np.argmax(dist), dist.shape)
    return out, (ph.affine @ np.array([i, j, k, 1.0]))[:3].round(3).tolist()

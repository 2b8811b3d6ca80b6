"""The paper's qualitative claims on Example 2 (Figures 12 and 13), measured on a solved leg.

Used by ``benchmarks/fig_examples.py lower_leg`` (and ``lower_leg_elliptic``), which writes the
numbers to ``benchmarks/results/example2_qualitative.json``; no solve, only the results file.

Anatomical axes of the synthetic leg (pixmuscle/synth/leg.py, the RAS+ axes of a right leg, and the
model frame is the scanner frame when ``grid/rotation`` is the identity, as here): +x lateral,
+y anterior, +z proximal. Distal is −z, so u_z < 0 is a distal displacement. The leg's axis is the
centroid (x, y) of each transverse slice's nodes; a node is anterior where its y exceeds the
centroid's of its slice, posterior where it is below.

Claims (paper §5, Example 2):

* Fig. 12, sagittal plane: "the posterior points move distally, the anterior points proximally" —
  on the sagittal plane of the figures (through the centre of the node cloud), the fractions of
  posterior nodes with u_z < 0 and of anterior nodes with u_z > 0, and the mean u_z of each half
  (the held end slices left out: they do not move);
* Fig. 12: "the displacements are not correlated with the fibres" — mean |cos| of the angle between
  the displacement and the fibre at the muscle nodes (those moving more than 1 % of the largest
  displacement), against the same with the fibres shuffled between those nodes (what the two
  fields' own anisotropy gives without any node-wise relation) and against 1/2 (isotropic random
  directions);
* Fig. 13: "the stress is continuous" — the jump of the largest principal Cauchy stress between
  in-plane neighbouring nodes (the same slice, one voxel apart along x or y), inside one region
  (one muscle, connective tissue, fat) against across an interface between regions.
"""

from __future__ import annotations

import numpy as np

#: region code of the non-muscle tissues (a muscle node's region is its muscle id 1..M)
CT_CODE, FAT_CODE = 1000, 1001


def region_codes(model) -> np.ndarray:
    """(N,) int: muscle id (1..M) for muscle nodes, :data:`CT_CODE`, :data:`FAT_CODE` for the others."""
    return np.where(model.tissue == 1, model.muscle_id, np.where(model.tissue == 2, CT_CODE, FAT_CODE)).astype(np.int64)


def _held_ends(model) -> np.ndarray:
    """(N,) bool: nodes of the end sets z_min and z_max."""
    held = np.zeros(model.n_nodes, bool)
    for name in ("z_min", "z_max"):
        if name in model.sets:
            held[np.asarray(model.sets[name], np.int64)] = True
    return held


def slice_centroid_y(model) -> np.ndarray:
    """(N,) float, cm: y of the centroid of each node's transverse slice (the leg's axis there)."""
    k = np.asarray(model.ijk[:, 2], np.int64) - int(model.ijk[:, 2].min())
    y = np.asarray(model.X[:, 1], float)
    return (np.bincount(k, weights=y) / np.bincount(k))[k]


def sagittal_claim(model, u: np.ndarray, x_index: int) -> dict:
    """Fig. 12, sagittal plane ``ijk[:, 0] == x_index``: posterior nodes distal, anterior proximal.

    Parameters
    ----------
    model : Model
    u : (N, 3) float, cm
        Displacement at the nodes.
    x_index : int
        Grid index of the sagittal plane along x.

    Returns
    -------
    dict
        For ``all`` nodes of the plane and for ``muscle`` nodes only: ``posterior`` and ``anterior``
        with ``nodes``, ``fraction_distal`` (u_z < 0), ``fraction_proximal`` (u_z > 0), ``mean_uz_cm``.
    """
    on = (np.asarray(model.ijk[:, 0]) == x_index) & ~_held_ends(model)
    ant = np.asarray(model.X[:, 1]) > slice_centroid_y(model)
    uz = np.asarray(u, float)[:, 2]
    out = {"x_cm": float(model.origin[0] + x_index * model.spacing[0])}
    for name, sel in (("all", on), ("muscle", on & (np.asarray(model.tissue) == 1))):  # two node selections
        out[name] = {}
        for half, h in (("posterior", sel & ~ant), ("anterior", sel & ant)):
            z = uz[h]
            out[name][half] = {"nodes": int(h.sum()), "fraction_distal": float(np.mean(z < 0)) if z.size else None,
                               "fraction_proximal": float(np.mean(z > 0)) if z.size else None,
                               "mean_uz_cm": float(z.mean()) if z.size else None}
    return out


def fibre_correlation(model, u: np.ndarray, seed: int = 0) -> dict:
    """Fig. 12: mean |cos(u, fibre)| at the muscle nodes that move (|u| > 1 % of the largest), against
    shuffled fibres (``seed``) and isotropic random directions (1/2).

    Returns
    -------
    dict
        ``nodes``, ``mean_abs_cos``, ``mean_abs_cos_shuffled``, ``mean_abs_cos_isotropic`` (0.5),
        ``mean_abs_cos_in_plane`` (the same with both vectors projected on the transverse plane),
        ``mean_abs_cos_in_plane_shuffled``.
    """
    u = np.asarray(u, float)
    f = np.asarray(model.fiber, float)
    mag = np.linalg.norm(u, axis=1)
    sel = (np.asarray(model.tissue) == 1) & (mag > 0.01 * mag.max())
    uu, ff = u[sel], f[sel]
    perm = np.random.default_rng(seed).permutation(ff.shape[0])

    def mean_abs_cos(a, b):
        na, nb = np.linalg.norm(a, axis=1), np.linalg.norm(b, axis=1)
        ok = (na > 0) & (nb > 1e-6)
        return float(np.mean(np.abs(np.einsum("ij,ij->i", a[ok], b[ok])) / (na[ok] * nb[ok])))

    xy = slice(0, 2)
    return {"nodes": int(sel.sum()), "mean_abs_cos": mean_abs_cos(uu, ff),
            "mean_abs_cos_shuffled": mean_abs_cos(uu, ff[perm]), "mean_abs_cos_isotropic": 0.5,
            "mean_abs_cos_in_plane": mean_abs_cos(uu[:, xy], ff[:, xy]),
            "mean_abs_cos_in_plane_shuffled": mean_abs_cos(uu[:, xy], ff[perm][:, xy]),
            "mean_abs_cos_in_plane_isotropic": float(2 / np.pi)}


def neighbour_pairs(model) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (a, b) of nodes one voxel apart along x or y in the same slice, (K,) int each."""
    ijk = np.asarray(model.ijk, np.int64)
    lo = ijk.min(axis=0)
    dims = ijk.max(axis=0) - lo + 2
    grid = np.full(tuple(dims), -1, np.int64)
    rel = ijk - lo
    grid[tuple(rel.T)] = np.arange(ijk.shape[0])
    a_all, b_all = [], []
    for axis in (0, 1):  # in-plane neighbours only: equal spacing along x and y
        step = np.zeros(3, np.int64)
        step[axis] = 1
        nb = grid[tuple((rel + step).T)]
        ok = nb >= 0
        a_all.append(np.flatnonzero(ok))
        b_all.append(nb[ok])
    return np.concatenate(a_all), np.concatenate(b_all)


def stress_jumps(model, s1: np.ndarray) -> dict:
    """Fig. 13: |Δσ₁| between in-plane neighbours inside one region against across an interface.

    Parameters
    ----------
    model : Model
    s1 : (N,) float, N/cm²
        Largest principal Cauchy stress at the nodes.

    Returns
    -------
    dict
        Per pair class (``inside`` a region; ``interface`` of any two regions; and by kind:
        ``muscle|muscle`` two muscles, ``muscle|connective_tissue``, ``muscle|fat``,
        ``connective_tissue|fat``): ``pairs``, ``median_jump``, ``p90_jump`` (N/cm²) and
        ``median_relative_jump`` (|Δσ₁| / the median |σ₁| of the body's nodes); ``median_abs_stress``
        (N/cm²); ``interface_over_inside`` (the ratio of the median jumps). The held end slices are left out.
    """
    s1 = np.asarray(s1, float)
    a, b = neighbour_pairs(model)
    held = _held_ends(model)
    keep = ~held[a] & ~held[b]
    a, b = a[keep], b[keep]
    reg = region_codes(model)
    tis = np.asarray(model.tissue)
    names = {1: "muscle", 2: "connective_tissue", 3: "fat"}
    jump = np.abs(s1[a] - s1[b])
    scale = float(np.median(np.abs(s1[~held])))
    same = reg[a] == reg[b]
    classes = {"inside": same, "interface": ~same}
    ta, tb = tis[a], tis[b]
    for p, q in ((1, 1), (1, 2), (1, 3), (2, 3)):  # four kinds of interface
        classes[f"{names[p]}|{names[q]}"] = ~same & (((ta == p) & (tb == q)) | ((ta == q) & (tb == p)))
    out = {"median_abs_stress": scale}
    for name, sel in classes.items():  # six pair classes
        j = jump[sel]
        out[name] = {"pairs": int(sel.sum()), "median_jump": float(np.median(j)) if j.size else None,
                     "p90_jump": float(np.percentile(j, 90)) if j.size else None,
                     "median_relative_jump": float(np.median(j) / scale) if j.size and scale > 0 else None}
    if out["inside"]["median_jump"]:
        out["interface_over_inside"] = out["interface"]["median_jump"] / out["inside"]["median_jump"]
    return out


def ellipticity_counts(model, non_elliptic: np.ndarray, plane_list) -> dict:
    """Nodes where the law is not strongly elliptic: in all, per region and on each plane of the figures."""
    bad = np.asarray(non_elliptic, bool)
    names = list(model.muscle_names)
    reg = region_codes(model)
    by = {(names[c - 1] if c <= len(names) else {CT_CODE: "connective_tissue", FAT_CODE: "fat"}[c]): int(np.sum(bad & (reg == c)))
          for c in np.unique(reg)}
    planes = {p[0]: int(np.sum(bad & (np.asarray(model.ijk[:, p[1]]) == p[4]))) for p in plane_list}
    return {"non_elliptic_nodes": int(bad.sum()), "n_nodes": int(bad.size), "by_region": by, "on_planes": planes}

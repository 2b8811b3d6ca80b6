"""Figures of docs/examples.md, drawn from the results of a finished example run (no solve).

Example 3 (``mg_young_old``): reads each subject's ``results_coarse.h5`` with pixmuscle's results
reader, computes the end force per step as the report does (mean axial reaction of the force
sets, converged steps only) and plots force against activation with the reference F_max of each
subject (``report.reference_values`` of the config: the paper's Table 3) marked at the last
activation.

Example 2 (``lower_leg``, and ``lower_leg_small`` for its small variant): reads every
``results_<model>.h5`` of the run folder (coarse, and fine when it was solved) and draws

* ``<prefix>_force_activation.png``: end force against α for each model (the paper's Figure 11),
  with the coarse − fine difference when both were solved;
* ``<prefix>_displacement.png``: in-plane displacement vectors on the transverse plane at
  mid-length and the coronal and sagittal planes through the leg's centre (Figure 12), at the last
  converged state (α = 0.95), on the reference configuration. The arrows are the model's own RK
  field u(x) = Σ_J Ψ_J(x) d_J evaluated on a regular grid of each plane (the solve's shape
  functions and coefficients, as the report's ParaView point data), coloured by |u|;
* ``<prefix>_stress.png``: the largest principal Cauchy stress (N/cm², the smoothed SCNI stress
  of each node's cell, as in the report) on the same planes with one colour bar (Figure 13), the
  nodes where the material law is not strongly elliptic at that state outlined in magenta and
  hatched: from the results' ``/ellipticity`` field, or computed again from their RK coefficients
  for files written before it was recorded (:func:`pixmuscle.mechanics.node_ellipticity.results_ellipticity`,
  about 20 s and 1 GB for the 68k-node coarse leg).

Tissue outlines (muscles, connective tissue, fat, the body and the bones) are drawn on every plane.
Example 2 also measures the paper's qualitative claims on Figures 12 and 13 (benchmarks/example2_claims.py)
on every model of the run and writes them, with the command, to
``benchmarks/results/example2_qualitative.json`` (one entry per example).

Run:  .venv/bin/python benchmarks/fig_examples.py mg_young_old
      .venv/bin/python benchmarks/fig_examples.py lower_leg [--run-dir out/lower_leg] [--out-dir docs/figures]
      .venv/bin/python benchmarks/fig_examples.py lower_leg_elliptic    (the strongly elliptic muscle matrix)
Writes: docs/figures/example3_force_activation.png; docs/figures/example2_{force_activation,displacement,
stress}.png (example2_elliptic_* for lower_leg_elliptic; under a minute: reads the results files,
evaluates the RK field on a few hundred points and the ellipticity of the coarse model, no solve).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import example2_claims  # noqa: E402
from _record import Run  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
FIGURES = ROOT / "docs" / "figures"
#: example → (config, prefix of its figures)
EXAMPLES = {
    "mg_young_old": ("configs/mg_young_old.yaml", "example3"),
    "lower_leg": ("configs/lower_leg.yaml", "example2"),
    "lower_leg_small": ("configs/lower_leg_small.yaml", "example2_small"),
    "lower_leg_elliptic": ("configs/lower_leg_elliptic.yaml", "example2_elliptic"),
}
#: the measured claims of Figures 12 and 13, one entry per example
CLAIMS_JSON = ROOT / "benchmarks" / "results" / "example2_qualitative.json"


def run_folder(config: Path) -> Path:
    """The output folder of an example config (its ``output_dir``, relative to the config)."""
    import yaml

    raw = yaml.safe_load(config.read_text())
    return (config.parent / raw["output_dir"]).resolve()


def end_force_curve(res) -> np.ndarray:
    """End force per stored state (N; NaN at unconverged states), as the report computes it."""
    from pixmuscle.report.curves import axial_forces, end_force, select_force_sets

    sets = select_force_sets(res.reaction, None, res.constrained_text())
    force = end_force(axial_forces(res.reaction, sets), res.n_states)
    return np.where(np.asarray(res.converged, bool), force, np.nan)


def subject_curves(config: Path, out: Path | None = None) -> list[dict]:
    """Force–activation curve of every subject of a cohort config, read from its coarse results
    (under ``out``, default the config's output folder).

    Returns
    -------
    list of dict
        ``name``, ``alpha`` (S+1,), ``force_N`` (S+1,; NaN at unconverged steps), ``n_nodes``,
        ``reference_F_max_N`` (float or None).
    """
    import yaml

    from pixmuscle.io.results import load_results

    raw = yaml.safe_load(config.read_text())
    out = run_folder(config) if out is None else Path(out)
    curves = []
    for sub in raw["subjects"]:
        path = out / sub["name"] / "results_coarse.h5"
        if not path.exists():
            raise SystemExit(f"{path}: not found — run `python benchmarks/bench_examples.py` for {config.name} first")
        res = load_results(path)
        force = end_force_curve(res)
        ref = ((sub.get("report") or {}).get("reference_values") or {}).get("F_max")
        curves.append({"name": sub["name"], "alpha": np.asarray(res.alpha, float), "force_N": force,
                       "n_nodes": res.model.n_nodes, "reference_F_max_N": ref})
    return curves


def plot(curves: list[dict], title: str, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2), dpi=110)
    for k, c in enumerate(curves):
        color = f"C{k}"
        f_max = np.nanmax(c["force_N"])
        ax.plot(c["alpha"], c["force_N"], "o-", color=color, ms=4,
                label=f"{c['name']}, pixmuscle ({c['n_nodes']:,} nodes): F_max {f_max:.4g} N")
        if c["reference_F_max_N"] is not None:
            a_end = float(c["alpha"][-1])
            ax.plot([a_end], [c["reference_F_max_N"]], "*", color=color, ms=13, mec="k", mew=0.6,
                    label=f"{c['name']}, paper Table 3: F_max {c['reference_F_max_N']:.4g} N")
            ax.axhline(c["reference_F_max_N"], color=color, ls=":", lw=0.9)
    ax.set_xlabel("activation α [-]")
    ax.set_ylabel("end force [N] (mean of both fixed ends)")
    ax.set_xlim(left=0.0)
    ax.set_ylim(bottom=0.0)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7.5, loc="upper left")
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path


# ------------------------------------------------------------------------------------ Example 2
#: tissue outlines: region code of a node = its muscle id (1..M); these for the other tissues
CT_CODE, FAT_CODE = 1000, 1001
PANEL_W = 4.3  # inch per panel column


def model_curves(run_dir: Path) -> list[dict]:
    """Force–activation curve of every model solved in an Example 2 run folder (coarse first).

    Returns
    -------
    list of dict
        ``name`` (model: ``coarse``, ``fine``), ``alpha`` (S+1,), ``force_N`` (S+1,; NaN at
        unconverged steps), ``converged`` (S+1,) bool, ``n_nodes``, ``status``.
    """
    from pixmuscle.io.results import load_results

    paths = sorted(Path(run_dir).glob("results_*.h5"), key=lambda p: (p.stem != "results_coarse", p.stem))
    if not paths:
        raise SystemExit(f"{run_dir}: no results_<model>.h5 — is this the output folder of a finished run?")
    out = []
    for p in paths:  # one or two models
        res = load_results(p)
        out.append({"name": p.stem.removeprefix("results_"), "alpha": np.asarray(res.alpha, float),
                    "force_N": end_force_curve(res), "converged": np.asarray(res.converged, bool),
                    "n_nodes": res.model.n_nodes, "status": res.status})
    return out


def plot_model_curves(curves: list[dict], title: str, path: Path) -> Path:
    """End force against α of each model (paper Figure 11); with two models a lower panel with their
    relative difference, (coarse − fine) / fine, at the coarse model's α."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pixmuscle.report.convergence import force_at

    two = len(curves) > 1
    fig, axes = plt.subplots(2 if two else 1, 1, figsize=(6.4, 6.0 if two else 4.2), squeeze=False, sharex=True,
                             layout="constrained", gridspec_kw={"height_ratios": [3, 1.3] if two else [1]})
    ax = axes[0, 0]
    for k, c in enumerate(curves):
        ok = np.isfinite(c["force_N"])
        f_max = np.nanmax(c["force_N"]) if ok.any() else np.nan
        ax.plot(c["alpha"][ok], c["force_N"][ok], "o-" if k == 0 else "s--", ms=4, color=f"C{k}",
                label=f"{c['name']} model ({c['n_nodes']:,} nodes): F_max {f_max:.4g} N")
        if (~c["converged"]).any():
            ax.plot(c["alpha"][~c["converged"]], np.zeros(int((~c["converged"]).sum())), "x", color="red", ms=8,
                    label=f"{c['name']}: not converged")
    ax.set_ylabel("end force [N] (mean of both fixed ends)")
    ax.set_xlim(left=0.0)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper left")
    ax.set_title(_wrap(title, 80), fontsize=9)
    if two:
        a0, f0 = curves[0]["alpha"], curves[0]["force_N"]
        ref = force_at(curves[1]["alpha"], curves[1]["force_N"], curves[1]["converged"], a0)
        with np.errstate(divide="ignore", invalid="ignore"):
            rel = np.where(np.abs(ref) > 0, (f0 - ref) / np.abs(ref), np.nan)
        keep = np.isfinite(rel) & (a0 > 0)
        r = axes[1, 0]
        r.plot(a0[keep], 100 * rel[keep], "o-", ms=4, color="k")
        r.axhline(0.0, color="0.7", lw=0.8)
        r.set_ylabel(f"({curves[0]['name']} − {curves[1]['name']})\n/ {curves[1]['name']} [%]", fontsize=9)
        r.grid(alpha=0.3)
    axes[-1, 0].set_xlabel("activation α [-]")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def planes(model, at=None) -> list[tuple]:
    """The three planes of the figures: (name, normal axis, horizontal axis, vertical axis, grid index).

    Transverse at mid-length (middle slice), coronal and sagittal through the centre of the node
    cloud (or through grid indices ``at``, (3,) along x, y, z).
    """
    from pixmuscle.report.slices import PLANES, plane_indices

    at = plane_indices(model.ijk, model.origin, model.spacing) if at is None else np.asarray(at, np.int64)
    return [(name, n, h, v, int(at[n])) for name, (n, h, v) in PLANES.items()]


def region_codes(model) -> np.ndarray:
    """(N,) int: a node's muscle id (1..M), ``CT_CODE`` for connective tissue, ``FAT_CODE`` for fat."""
    return np.where(model.tissue == 1, model.muscle_id,
                    np.where(model.tissue == 2, CT_CODE, FAT_CODE)).astype(np.int64)


def plane_displacement(res, step: int, plane: tuple, step_cm: float, support=None) -> tuple[np.ndarray, np.ndarray, int]:
    """The model's displacement field u(x) = Σ_J Ψ_J(x) d_J on a regular grid of one plane.

    Parameters
    ----------
    res : Results
        With RK coefficients ``d`` and the solve configuration (read with
        :func:`pixmuscle.io.results.load_results`).
    step : int
        Stored state.
    plane : tuple
        An entry of :func:`planes`.
    step_cm : float
        Spacing of the grid of points, cm.
    support : (support, options), optional
        :func:`pixmuscle.report.fields.rk_support` of ``res`` (computed when not given).

    Returns
    -------
    points : (P, 3) float64, cm
        In the model frame, inside the nodes' cells of the plane.
    u : (P, 3) float64, cm
    n_fallback : int
        Points where the RK field is not defined (singular moment matrix beside a one-voxel
        strand): there ``u`` is the nearest node's displacement.
    """
    from scipy.spatial import cKDTree

    from pixmuscle.report.fields import rk_support
    from pixmuscle.report.slices import plane_points
    from pixmuscle.rk import rk_evaluate

    m = res.model
    _, n, h, v, idx = plane
    pts = plane_points(m.ijk, m.origin, m.spacing, n, idx, h, v, step_cm)
    if res.d is None:
        raise SystemExit(f"{res.meta.get('path')}: no /steps/d (RK coefficients): cannot evaluate the displacement field")
    support, options = rk_support(res) if support is None else support
    u = rk_evaluate(np.asarray(m.X, float), pts, support, np.asarray(res.d[step], float), singular="nan", **options)
    bad = ~np.isfinite(u).all(axis=1)
    if bad.any():
        nearest = cKDTree(np.asarray(m.X, float)).query(pts[bad])[1]
        u[bad] = np.asarray(res.u[step], float)[nearest]
    return pts, u, int(bad.sum())


def _panels(model, plane_list):
    """Per plane: (label image (nv, nh) int, extent (x0, x1, y0, y1) cm, lower-left corner, bone image)."""
    from pixmuscle.report.slices import plane_image

    codes = region_codes(model)
    sp, org = np.asarray(model.spacing, float), np.asarray(model.origin, float)
    bone = None if model.bone_ijk is None or len(model.bone_ijk) == 0 else np.asarray(model.bone_ijk, np.int64)
    out = []
    for _, n, h, v, idx in plane_list:  # three planes
        img, lo = plane_image(model.ijk, codes.astype(float), n, idx, h, v)
        lab = np.nan_to_num(img, nan=0.0).astype(np.int64)
        x0, y0 = org[h] + (lo[0] - 0.5) * sp[h], org[v] + (lo[1] - 0.5) * sp[v]
        bimg = np.zeros(lab.shape, bool)
        if bone is not None:
            b = bone[bone[:, n] == idx]
            r, c = b[:, v] - lo[1], b[:, h] - lo[0]
            ok = (r >= 0) & (r < lab.shape[0]) & (c >= 0) & (c < lab.shape[1])
            bimg[r[ok], c[ok]] = True
        out.append((lab, (x0, x0 + lab.shape[1] * sp[h], y0, y0 + lab.shape[0] * sp[v]), (x0, y0), bimg))
    return out


def _outline(ax, lab, corner, spacing, h, v, bone, color="0.25"):
    """Bones filled light grey, tissue outlines (pixel edges between regions) as thin lines."""
    from matplotlib.collections import LineCollection

    from pixmuscle.report.slices import region_edges

    x0, y0 = corner
    ext = (x0, x0 + lab.shape[1] * spacing[h], y0, y0 + lab.shape[0] * spacing[v])
    if bone.any():
        ax.imshow(np.ma.masked_where(~bone, bone.astype(float)), origin="lower", extent=ext, cmap="Greys",
                  vmin=0.0, vmax=4.0, interpolation="nearest", aspect="equal")
    seg = region_edges(lab, x0, y0, spacing[h], spacing[v])
    ax.add_collection(LineCollection(seg, colors=color, linewidths=0.45, alpha=0.8))


def _figure(model, plane_list):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = _panels(model, plane_list)
    widths = [e[1] - e[0] for _, e, _, _ in panels]
    heights = [e[3] - e[2] for _, e, _, _ in panels]
    fig_h = min(8.0, max(3.0, 0.8 * 3 * PANEL_W * max(heights) / sum(widths) + 1.5))
    fig, axes = plt.subplots(1, 3, figsize=(3 * PANEL_W, fig_h), layout="constrained",
                             gridspec_kw={"width_ratios": widths})
    fig.get_layout_engine().set(w_pad=0.12, wspace=0.04)  # room for the y labels beside equal-aspect panels
    return plt, fig, axes, panels


def _wrap(text: str, width: int = 150) -> str:
    import textwrap

    return "\n".join(textwrap.fill(line, width) for line in text.splitlines())


def _mark_planes(ax, plane_list, model):
    """Dashed lines on the transverse panel where the coronal and sagittal planes cut it."""
    _, _, h, v, _ = plane_list[0]
    for _, n, _, _, idx in plane_list[1:]:  # coronal, sagittal
        pos = model.origin[n] + idx * model.spacing[n]
        (ax.axhline if n == v else ax.axvline)(pos, color="0.4", ls="--", lw=0.8)


def _label_axes(ax, plane, model):
    from pixmuscle.report.slices import AXIS

    name, n, h, v, idx = plane
    pos = model.origin[n] + idx * model.spacing[n]
    ax.set_title(f"{name}: {AXIS[n]} = {pos:.3g} cm", fontsize=10)
    ax.set_xlabel(f"{AXIS[h]} [cm]")
    ax.set_ylabel(f"{AXIS[v]} [cm]")


def plot_displacement_planes(res, step: int, path: Path, *, title: str, step_cm: float | None = None,
                             plane_list=None) -> dict:
    """Figure 12-style: in-plane displacement vectors on the three planes, coloured by |u| (cm).

    Returns
    -------
    dict
        ``path``; per plane name: ``points`` (P, 3) cm, ``u`` (P, 3) cm, ``n_fallback``; ``u_max_cm``
        (largest |u| of the arrows), ``step_cm``.
    """
    from matplotlib.colors import Normalize

    m = res.model
    plane_list = planes(m) if plane_list is None else plane_list
    plt, fig, axes, panels = _figure(m, plane_list)
    sp = np.asarray(m.spacing, float)
    if step_cm is None:  # about 24 arrows across the widest panel, never closer than one slice spacing
        step_cm = max(float(sp.max()), max(e[1] - e[0] for _, e, _, _ in panels) / 24.0)
    from pixmuscle.report.fields import rk_support

    support = rk_support(res)  # the solve's shape-function options, once for the three planes
    data = {pl[0]: dict(zip(("points", "u", "n_fallback"), plane_displacement(res, step, pl, step_cm, support),
                            strict=True)) for pl in plane_list}
    mags = np.concatenate([np.linalg.norm(d["u"], axis=1) for d in data.values()])
    inplane = np.concatenate([np.linalg.norm(d["u"][:, [pl[2], pl[3]]], axis=1)
                              for pl, d in zip(plane_list, data.values(), strict=True)])
    umax = float(mags.max()) if mags.size else 0.0
    norm = Normalize(0.0, umax if umax > 0 else 1.0)
    # one arrow scale for all panels: the longest in-plane arrow is drawn 1.6 grid steps long
    scale = (float(inplane.max()) / (1.6 * step_cm)) if inplane.size and inplane.max() > 0 else 1.0
    q = None
    for ax, pl, (lab, ext, corner, bone) in zip(axes, plane_list, panels, strict=True):  # three planes
        name, n, h, v, _ = pl
        _outline(ax, lab, corner, sp, h, v, bone)
        d = data[name]
        if d["points"].shape[0]:
            q = ax.quiver(d["points"][:, h], d["points"][:, v], d["u"][:, h], d["u"][:, v],
                          np.linalg.norm(d["u"], axis=1), cmap="viridis", norm=norm, angles="xy",
                          scale_units="xy", scale=scale, width=0.0045, headwidth=3.5, pivot="tail")
        ax.set_xlim(ext[0], ext[1])
        ax.set_ylim(ext[2], ext[3])
        ax.set_aspect("equal")
        _label_axes(ax, pl, m)
    _mark_planes(axes[0], plane_list, m)
    if q is not None:
        key = float(f"{inplane.max():.1g}")
        q.axes.quiverkey(q, 0.01, 0.015, key, f"{key:g} cm in-plane (arrows {1 / scale:.3g}× true length)",
                         labelpos="E", coordinates="figure", color="k", fontproperties={"size": 8})
        fig.colorbar(q, ax=list(axes), label="|u| [cm] (all three components)", fraction=0.025, pad=0.01, aspect=14)
    fig.suptitle(_wrap(title), fontsize=10)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return {"path": path, "u_max_cm": umax, "step_cm": step_cm, **data}


def _zone(ax, zone_img, corner, spacing, h, v):
    """Pixels of ``zone_img`` (nv, nh) bool outlined in magenta (pixel edges) and hatched."""
    from matplotlib.collections import LineCollection

    from pixmuscle.report.slices import region_edges

    if not zone_img.any():
        return
    x0, y0 = corner
    seg = region_edges(zone_img.astype(np.int64), x0, y0, spacing[h], spacing[v])
    ax.add_collection(LineCollection(seg, colors="magenta", linewidths=0.9))
    xs = x0 + (np.arange(zone_img.shape[1]) + 0.5) * spacing[h]
    ys = y0 + (np.arange(zone_img.shape[0]) + 0.5) * spacing[v]
    ax.contourf(xs, ys, zone_img.astype(float), levels=[0.5, 1.5], colors="none", hatches=["////"])


def plot_stress_planes(res, step: int, path: Path, *, title: str, plane_list=None,
                       clip_percentile: float = 0.5, non_elliptic: np.ndarray | None = None) -> dict:
    """Figure 13-style: the largest principal Cauchy stress (N/cm²) on the three planes, one colour bar.

    ``non_elliptic`` (N,) bool, optional: nodes where the material law is not strongly elliptic at
    ``step``, outlined in magenta and hatched.

    The colour range is the ``clip_percentile`` to ``100 − clip_percentile`` percentile of the values
    on the three planes (a few nodes next to the held ends and bones carry much larger stresses);
    values beyond it are drawn in the end colours (the colour bar's arrows) and the figure's
    title gives the full range.

    Returns
    -------
    dict
        ``path``, ``vmin``, ``vmax`` (colour range, N/cm²), ``min``, ``max`` (on the planes, N/cm²),
        and per plane name its image (nv, nh) of nodal values (NaN where no node).
    """
    from pixmuscle.report.slices import plane_image

    m = res.model
    mp = res.step(step).max_principal
    if mp is None:
        raise SystemExit(f"{res.meta.get('path')}: no stress in the results file")
    plane_list = planes(m) if plane_list is None else plane_list
    imgs = {pl[0]: plane_image(m.ijk, mp, pl[1], pl[4], pl[2], pl[3])[0] for pl in plane_list}
    vals = np.concatenate([i[np.isfinite(i)] for i in imgs.values()])
    vmin, vmax = (float(x) for x in np.percentile(vals, [clip_percentile, 100.0 - clip_percentile]))
    plt, fig, axes, panels = _figure(m, plane_list)
    sp = np.asarray(m.spacing, float)
    cmap = plt.get_cmap("turbo").with_extremes(bad=(1, 1, 1, 0))
    im = None
    for ax, pl, (lab, ext, corner, bone) in zip(axes, plane_list, panels, strict=True):
        im = ax.imshow(np.ma.masked_invalid(imgs[pl[0]]), origin="lower", extent=ext, cmap=cmap, vmin=vmin, vmax=vmax,
                       interpolation="nearest", aspect="equal")
        _outline(ax, lab, corner, sp, pl[2], pl[3], bone, color="k")
        if non_elliptic is not None:
            zone = plane_image(m.ijk, np.asarray(non_elliptic, float), pl[1], pl[4], pl[2], pl[3])[0]
            _zone(ax, np.nan_to_num(zone, nan=0.0) > 0.5, corner, sp, pl[2], pl[3])
        _label_axes(ax, pl, m)
    _mark_planes(axes[0], plane_list, m)
    if non_elliptic is not None:
        from matplotlib.patches import Patch

        n_bad = int(np.count_nonzero(non_elliptic))
        fig.legend(handles=[Patch(facecolor="none", edgecolor="magenta", hatch="////",
                                  label=f"material law not strongly elliptic ({n_bad:,} of {m.n_nodes:,} nodes "
                                        "in the model)")],
                   loc="lower left", fontsize=8, frameon=False)
    fig.colorbar(im, ax=list(axes), label="largest principal Cauchy stress [N/cm²]", fraction=0.025, pad=0.01,
                 aspect=14, extend="both")
    fig.suptitle(f"{_wrap(title)}\ncolour range {vmin:.3g} … {vmax:.3g} N/cm² ({clip_percentile:g}–{100 - clip_percentile:g} "
                 f"percentile on the planes); values on the planes {vals.min():.3g} … {vals.max():.3g} N/cm²",
                 fontsize=10)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return {"path": path, "vmin": vmin, "vmax": vmax, "min": float(vals.min()), "max": float(vals.max()), **imgs}


def node_ellipticity(res, step: int):
    """The results' :class:`~pixmuscle.mechanics.results.NodeEllipticity` at ``step`` and how it was
    obtained: as recorded, or computed again from the RK coefficients (files written before it was
    recorded, or another step); None (and why) when the file holds no usable coefficients or configuration."""
    from pixmuscle.errors import InputError
    from pixmuscle.mechanics.node_ellipticity import results_ellipticity

    ell = res.ellipticity
    if ell is not None and ell.step == step:
        return ell, "recorded by the solve"
    try:
        return results_ellipticity(res, step), "computed again from the results' RK coefficients"
    except InputError as exc:
        return None, f"not computed: {exc}"


def model_claims(res, step: int, plane_list, non_elliptic: np.ndarray | None = None) -> dict:
    """The measured claims of Figures 12 and 13 on one model at ``step`` (benchmarks/example2_claims.py)."""
    f = res.step(step)
    out = {"n_nodes": res.model.n_nodes, "step": step, "alpha": float(res.alpha[step]),
           "fig12_sagittal": example2_claims.sagittal_claim(res.model, f.u, plane_list[2][4]),
           "fig12_fibres": example2_claims.fibre_correlation(res.model, f.u),
           "fig13_stress_jumps": example2_claims.stress_jumps(res.model, f.max_principal)}
    if non_elliptic is not None:
        out["non_elliptic"] = example2_claims.ellipticity_counts(res.model, non_elliptic, plane_list)
    else:
        out["non_elliptic"] = {"non_elliptic_nodes": (res.info or {}).get("non_elliptic_nodes"),
                               "n_nodes": res.model.n_nodes, "note": "the solve's count (field not computed)"}
    return out


def write_claims(example: str, run_dir: Path, models: dict, run: Run) -> Path:
    """Add (replace) the entry ``example`` of :data:`CLAIMS_JSON`."""
    data = json.loads(CLAIMS_JSON.read_text()) if CLAIMS_JSON.exists() else {}
    data[example] = {**run.fields(), "run_dir": str(run_dir), "models": models}
    CLAIMS_JSON.parent.mkdir(parents=True, exist_ok=True)
    CLAIMS_JSON.write_text(json.dumps(data, indent=1) + "\n")
    return CLAIMS_JSON


def example2_figures(run_dir: Path, out_dir: Path, prefix: str, label: str, example: str | None = None,
                     run: Run | None = None) -> list[Path]:
    """The three Example 2 figures from the run folder ``run_dir`` (fields of its coarse model) and,
    with ``example`` and ``run``, its entry of :data:`CLAIMS_JSON` (every model of the run)."""
    from pixmuscle.io.results import load_results

    curves = model_curves(run_dir)
    paths = [plot_model_curves(curves, f"{label}: end force against activation (paper Figure 11)",
                               out_dir / f"{prefix}_force_activation.png")]
    res = load_results(Path(run_dir) / f"results_{curves[0]['name']}.h5")
    conv = np.flatnonzero(res.converged)
    if conv.size == 0:
        raise SystemExit(f"{run_dir}: no converged state to draw")
    step = int(conv[-1])
    state = (f"{curves[0]['name']} model ({res.model.n_nodes:,} nodes), step {step}, α = {res.alpha[step]:.3g}, "
             "reference configuration")
    disp = plot_displacement_planes(res, step, out_dir / f"{prefix}_displacement.png",
                                    title=f"{label}: in-plane displacement (paper Figure 12)\n{state}")
    ell, how = node_ellipticity(res, step)
    zone = None if ell is None else ell.non_elliptic
    stress = plot_stress_planes(res, step, out_dir / f"{prefix}_stress.png", non_elliptic=zone,
                                title=f"{label}: largest principal Cauchy stress (paper Figure 13)\n{state}"
                                      + ("" if ell is None else f"; hatched: the law is not strongly elliptic ({how})"))
    print(f"not strongly elliptic at step {step}: {'?' if ell is None else f'{ell.count:,}'} of "
          f"{res.model.n_nodes:,} nodes ({how}; the solve counted {(res.info or {}).get('non_elliptic_nodes')})")
    paths_out = []
    if example is not None and run is not None:
        models = {curves[0]["name"]: model_claims(res, step, planes(res.model), zone)}
        for c in curves[1:]:  # the fine model: its own fields, its solve's count (no 1-GB-per-68k recomputation)
            other = load_results(Path(run_dir) / f"results_{c['name']}.h5")
            k = int(np.flatnonzero(other.converged)[-1])
            e = other.ellipticity if other.ellipticity is not None and other.ellipticity.step == k else None
            models[c["name"]] = model_claims(other, k, planes(other.model), None if e is None else e.non_elliptic)
        paths_out.append(write_claims(example, run_dir, models, run))
        for name, mc in models.items():
            sag, fib, jumps = mc["fig12_sagittal"]["all"], mc["fig12_fibres"], mc["fig13_stress_jumps"]
            print(f"{name}: sagittal posterior distal {sag['posterior']['fraction_distal']:.3f} (mean u_z "
                  f"{sag['posterior']['mean_uz_cm']:.3g} cm), anterior proximal {sag['anterior']['fraction_proximal']:.3f} "
                  f"(mean u_z {sag['anterior']['mean_uz_cm']:.3g} cm); |cos(u, fibre)| {fib['mean_abs_cos']:.3f}, "
                  f"shuffled {fib['mean_abs_cos_shuffled']:.3f}; stress jump median inside "
                  f"{jumps['inside']['median_jump']:.3g}, interface {jumps['interface']['median_jump']:.3g} N/cm²")
    for c in curves:
        print(f"{c['name']}: {c['n_nodes']:,} nodes, F_max {np.nanmax(c['force_N']):.4g} N, status {c['status']}")
    print(f"arrows: largest |u| {disp['u_max_cm']:.3g} cm, grid {disp['step_cm']:.3g} cm, "
          f"{sum(d['n_fallback'] for k, d in disp.items() if isinstance(d, dict))} points without an RK value")
    print(f"stress on the planes {stress['min']:.3g} … {stress['max']:.3g} N/cm², colour range "
          f"{stress['vmin']:.3g} … {stress['vmax']:.3g}")
    return [*paths, disp["path"], stress["path"], *paths_out]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("example", choices=sorted(EXAMPLES))
    ap.add_argument("--run-dir", type=Path, default=None,
                    help="output folder of the finished run (default: the config's output_dir)")
    ap.add_argument("--out-dir", type=Path, default=FIGURES, help="where the PNGs go (default: docs/figures)")
    a = ap.parse_args(argv)
    run = Run()
    config, prefix = EXAMPLES[a.example]
    run_dir = run_folder(ROOT / config) if a.run_dir is None else a.run_dir.resolve()
    if a.example == "mg_young_old":
        curves = subject_curves(ROOT / config, run_dir)
        title = ("Example 3 at the paper's resolution: SYNTHETIC phantoms, coarse models (0.156 cm)\n"
                 "stars and dotted lines: the paper's F_max at the highest activation (Table 3)")
        print(plot(curves, title, a.out_dir / f"{prefix}_force_activation.png"))
        return 0
    label = {"lower_leg": "Example 2, SYNTHETIC lower leg",
             "lower_leg_elliptic": "Example 2 with a strongly elliptic muscle matrix, SYNTHETIC lower leg"}.get(
        a.example, "Example 2 small variant (NOT the paper's resolution), SYNTHETIC lower leg")
    claims = a.example in ("lower_leg", "lower_leg_elliptic")
    for p in example2_figures(run_dir, a.out_dir, prefix, label, a.example if claims else None, run):
        print(p)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

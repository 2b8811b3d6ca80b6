"""Slice figures of nodal fields on the transverse, coronal and sagittal planes (paper Figs. 12–13).

Nodal values are put back on their voxel of the model grid (``nodes/ijk``); voxels without a node
are NaN and drawn blank. Images are drawn on the reference configuration, in cm, with the true
(anisotropic) cell size.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..errors import InputError

#: plane name → (normal axis, horizontal axis, vertical axis)
PLANES = {"transverse": (2, 0, 1), "coronal": (1, 0, 2), "sagittal": (0, 1, 2)}
AXIS = "xyz"


def plane_indices(ijk: np.ndarray, origin, spacing, position: Sequence[float] | None = None) -> np.ndarray:
    """Grid index of the three planes through ``position`` (cm) or through the centre of the nodes.

    Returns
    -------
    (3,) int64 — index along x, y, z.
    """
    ijk = np.asarray(ijk, np.int64)
    lo, hi = ijk.min(axis=0), ijk.max(axis=0)
    if position is None:
        idx = np.floor((lo + hi) / 2.0 + 0.5).astype(np.int64)
    else:
        idx = np.rint((np.asarray(position, float) - np.asarray(origin, float)) / np.asarray(spacing, float)).astype(np.int64)
        if (idx < lo).any() or (idx > hi).any():
            raise InputError(f"report.slice_position: {list(position)} cm lies outside the model "
                             f"(x, y, z from {list(np.asarray(origin) + lo * spacing)} to {list(np.asarray(origin) + hi * spacing)} cm)")
    return idx


def plane_image(ijk: np.ndarray, values: np.ndarray, axis: int, index: int, haxis: int, vaxis: int):
    """Raster the nodal values lying on one grid plane.

    Parameters
    ----------
    ijk : (N, 3) int
    values : (N,) or (N, c) float
    axis, index : int
        Plane normal axis and its grid index.
    haxis, vaxis : int
        Grid axes shown horizontally and vertically.

    Returns
    -------
    img : (nv, nh[, c]) float64
        NaN where the plane has no node; rows follow ``vaxis`` from the node cloud's minimum.
    lo : (2,) int64
        Grid index of img[0, 0] along (haxis, vaxis).
    """
    ijk = np.asarray(ijk, np.int64)
    values = np.asarray(values, float)
    lo = ijk[:, [haxis, vaxis]].min(axis=0)
    hi = ijk[:, [haxis, vaxis]].max(axis=0)
    on = ijk[:, axis] == index
    img = np.full((hi[1] - lo[1] + 1, hi[0] - lo[0] + 1) + values.shape[1:], np.nan)
    img[ijk[on, vaxis] - lo[1], ijk[on, haxis] - lo[0]] = values[on]
    return img, lo


def plot_slices(ijk, origin, spacing, values, path, *, label: str, title: str, planes_at=None,
                vectors: np.ndarray | None = None, cmap: str = "viridis", dpi: int = 120) -> Path:
    """Three-panel figure of a scalar nodal field on the transverse (z), coronal (y) and sagittal (x) planes.

    Parameters
    ----------
    ijk : (N, 3) int; origin, spacing : (3,) cm
        Node grid indices and the grid geometry.
    values : (N,) float
        Field to show (colour bar labelled ``label``, with units).
    planes_at : (3,) int, optional
        Plane indices along x, y, z (default: centre of the node cloud).
    vectors : (N, 3) float, optional
        Drawn as in-plane arrows (e.g. displacement, cm) on a subsampled set of nodes.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    origin, spacing = np.asarray(origin, float), np.asarray(spacing, float)
    values = np.asarray(values, float)
    finite = values[np.isfinite(values)]
    if finite.size == 0:
        raise InputError(f"{title}: no finite values to plot")
    vmin, vmax = float(finite.min()), float(finite.max())
    if vmax <= vmin:
        vmax = vmin + max(abs(vmin), 1.0) * 1e-6
    at = plane_indices(ijk, origin, spacing) if planes_at is None else np.asarray(planes_at)
    cm = plt.get_cmap(cmap).with_extremes(bad="white")
    panels = []
    for pname, (ax_n, h, v) in PLANES.items():  # three planes
        img, lo = plane_image(ijk, values, ax_n, int(at[ax_n]), h, v)
        x0 = origin[h] + (lo[0] - 0.5) * spacing[h]
        y0 = origin[v] + (lo[1] - 0.5) * spacing[v]
        panels.append((pname, ax_n, h, v, img, x0, y0, (x0, x0 + img.shape[1] * spacing[h], y0, y0 + img.shape[0] * spacing[v])))
    widths = [e[1] - e[0] for *_, e in panels]
    height = max(e[3] - e[2] for *_, e in panels)
    # figure height from the panels' true aspect: no empty bands above and below
    fig_h = min(9.0, max(3.0, 11.0 * height / sum(widths) + (2.3 if vectors is not None else 1.9)))
    fig, axes = plt.subplots(1, 3, figsize=(13.0, fig_h), layout="constrained", gridspec_kw={"width_ratios": widths})
    arrow = None
    if vectors is not None:
        vin = np.asarray(vectors, float)
        umax = float(np.nanmax(np.linalg.norm(vin, axis=1))) if np.isfinite(vin).any() else 0.0
        # one scale for all panels: the largest displacement is drawn 1.5 arrow spacings long
        step_cm = max(w / 16 for w in widths)
        arrow = (umax, umax / (1.5 * step_cm)) if umax > 0 else None
    im = None
    for ax, (pname, ax_n, h, v, img, x0, y0, extent) in zip(axes, panels, strict=True):
        im = ax.imshow(np.ma.masked_invalid(img), origin="lower", extent=extent, cmap=cm, vmin=vmin, vmax=vmax,
                       interpolation="nearest", aspect="equal")
        if arrow is not None:
            vec, _ = plane_image(ijk, np.asarray(vectors, float)[:, [h, v]], ax_n, int(at[ax_n]), h, v)
            sh = max(1, img.shape[1] // 16)
            sv = max(1, img.shape[0] // 16)
            jj, ii = np.meshgrid(np.arange(0, img.shape[1], sh), np.arange(0, img.shape[0], sv))
            vx, vy = vec[ii, jj, 0], vec[ii, jj, 1]
            ok = np.isfinite(vx) & np.isfinite(vy)
            if ok.any():
                q = ax.quiver(x0 + (jj[ok] + 0.5) * spacing[h], y0 + (ii[ok] + 0.5) * spacing[v], vx[ok], vy[ok],
                              color="k", width=0.004, alpha=0.8, angles="xy", scale_units="xy", scale=arrow[1])
                if ax is axes[0]:
                    key = float(f"{arrow[0]:.1g}")
                    ax.quiverkey(q, 0.02, -0.24, key, f"{key:g} cm displacement (arrows {1 / arrow[1]:.3g}× true length)",
                                 labelpos="E", coordinates="axes", fontproperties={"size": 8})
        pos = origin[ax_n] + at[ax_n] * spacing[ax_n]
        ax.set_title(f"{pname}: {AXIS[ax_n]} = {pos:.3g} cm")
        ax.set_xlabel(f"{AXIS[h]} [cm]")
        ax.set_ylabel(f"{AXIS[v]} [cm]")
    cb = fig.colorbar(im, ax=list(axes), label=label, fraction=0.025, pad=0.01, aspect=12)
    cb.ax.tick_params(labelsize=9)
    fig.suptitle(title)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return Path(path)

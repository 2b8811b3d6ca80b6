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
#: the same for a body much longer along z than across (a tendon): z horizontal, one panel per row
PLANES_LONG = {"transverse": (2, 0, 1), "coronal": (1, 2, 0), "sagittal": (0, 2, 1)}
#: z extent / largest in-plane extent above which a body is drawn as long
LONG_RATIO = 3.0
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


def region_edges(labels: np.ndarray, x0: float, y0: float, dh: float, dv: float) -> np.ndarray:
    """Pixel edges between differently labelled pixels of an image: outlines of its regions.

    Parameters
    ----------
    labels : (nv, nh) int
        Region label of each pixel (e.g. muscle id, tissue code; 0 for no node). Pixels outside
        the image count as 0, so regions touching the border are closed.
    x0, y0 : float, cm
        Lower-left corner of pixel [0, 0] (row index along the vertical axis).
    dh, dv : float, cm
        Pixel size along the horizontal and vertical axes.

    Returns
    -------
    (K, 2, 2) float64, cm
        Segments ``[[x_a, y_a], [x_b, y_b]]``, one per unit pixel edge between two different labels
        (for a ``matplotlib.collections.LineCollection``).
    """
    lab = np.pad(np.asarray(labels), 1)  # (nv + 2, nh + 2), 0 around
    # vertical edges: pixel (i, j) and its right neighbour differ; padded index j is the edge's left pixel
    i, j = np.nonzero(lab[1:-1, :-1] != lab[1:-1, 1:])
    x = x0 + j * dh
    vert = np.stack([np.stack([x, y0 + i * dv], -1), np.stack([x, y0 + (i + 1) * dv], -1)], axis=1)
    # horizontal edges: pixel (i, j) and the one above differ
    i, j = np.nonzero(lab[:-1, 1:-1] != lab[1:, 1:-1])
    y = y0 + i * dv
    horiz = np.stack([np.stack([x0 + j * dh, y], -1), np.stack([x0 + (j + 1) * dh, y], -1)], axis=1)
    return np.concatenate([vert, horiz]).astype(np.float64)


def plane_points(ijk: np.ndarray, origin, spacing, axis: int, index: int, haxis: int, vaxis: int,
                 step_cm: float) -> np.ndarray:
    """Points of a regular grid on one grid plane, kept where they fall in a node's cell.

    The grid has spacing ``step_cm`` along both in-plane axes (at least one cell), centred on the
    middle of the nodes' extent on the plane, so arrows drawn at these points are evenly spaced
    in cm whatever the cell size (e.g. 0.156 cm in-plane, 0.5 cm between slices).

    Parameters
    ----------
    ijk : (N, 3) int; origin, spacing : (3,) cm
    axis, index : int
        Plane normal axis and its grid index.
    haxis, vaxis : int
        In-plane axes.
    step_cm : float
        Grid spacing, cm.

    Returns
    -------
    (P, 3) float64, cm
        Model-frame coordinates, on the plane (coordinate ``origin[axis] + index * spacing[axis]``).
    """
    ijk = np.asarray(ijk, np.int64)
    origin, spacing = np.asarray(origin, float), np.asarray(spacing, float)
    on = ijk[ijk[:, axis] == index]
    if on.shape[0] == 0:
        return np.zeros((0, 3))
    axes = (haxis, vaxis)
    lo, hi = on[:, axes].min(axis=0), on[:, axes].max(axis=0)
    coords = []
    for k, a in enumerate(axes):  # two in-plane axes
        c = origin[a] + 0.5 * (lo[k] + hi[k]) * spacing[a]
        half = 0.5 * (hi[k] - lo[k] + 1) * spacing[a]
        step = max(float(step_cm), float(spacing[a]))
        n = int(np.floor(half / step))
        coords.append(c + step * np.arange(-n, n + 1))
    gh, gv = np.meshgrid(*coords, indexing="ij")
    pts = np.empty((gh.size, 3))
    pts[:, axis] = origin[axis] + index * spacing[axis]
    pts[:, haxis], pts[:, vaxis] = gh.ravel(), gv.ravel()
    # keep the points whose cell (nearest voxel) holds a node of the plane
    cell = np.rint((pts[:, axes] - origin[list(axes)]) / spacing[list(axes)]).astype(np.int64)
    dims = hi - lo + 1
    inside = ((cell >= lo) & (cell <= hi)).all(axis=1)
    occupied = np.zeros(int(np.prod(dims)), bool)
    occupied[np.ravel_multi_index(tuple((on[:, axes] - lo).T), tuple(dims))] = True
    keep = np.zeros(pts.shape[0], bool)
    keep[inside] = occupied[np.ravel_multi_index(tuple((cell[inside] - lo).T), tuple(dims))]
    return pts[keep]


def _samples(n: int, step: int) -> np.ndarray:
    """Indices 0..n-1 every ``step``, placed symmetrically about the middle (so a thin body gets its centre line)."""
    c = (n - 1) // 2
    return c + step * np.arange(-(c // step), (n - 1 - c) // step + 1)


def plot_slices(ijk, origin, spacing, values, path, *, label: str, title: str, planes_at=None,
                vectors: np.ndarray | None = None, cmap: str = "viridis", dpi: int = 120) -> Path:
    """Three-panel figure of a scalar nodal field on the transverse (z), coronal (y) and sagittal (x) planes.

    Side by side with z vertical; a body more than ``LONG_RATIO`` times longer along z than across
    (a tendon) one panel per row with z horizontal, so that titles and tick labels have room.

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
    from matplotlib.ticker import MaxNLocator

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
    extent_cm = (np.ptp(np.asarray(ijk), axis=0) + 1) * spacing
    long = extent_cm[2] > LONG_RATIO * max(extent_cm[0], extent_cm[1])
    panels = []
    for pname, (ax_n, h, v) in (PLANES_LONG if long else PLANES).items():  # three planes
        img, lo = plane_image(ijk, values, ax_n, int(at[ax_n]), h, v)
        x0 = origin[h] + (lo[0] - 0.5) * spacing[h]
        y0 = origin[v] + (lo[1] - 0.5) * spacing[v]
        panels.append((pname, ax_n, h, v, img, x0, y0, (x0, x0 + img.shape[1] * spacing[h], y0, y0 + img.shape[0] * spacing[v])))
    widths = [e[1] - e[0] for *_, e in panels]
    heights = [e[3] - e[2] for *_, e in panels]
    if long:  # one panel per row, z along the rows; each row tall enough for its title and tick labels
        scale = 11.0 / max(widths)  # inch per cm
        rows = [max(hh * scale, 1.1) for hh in heights]
        fig_h = min(9.0, sum(rows) + 3 * 0.75 + 0.5)
        fig = plt.figure(figsize=(13.0, fig_h), layout="constrained")
        # the transverse panel at the left of its row, as wide as its aspect needs at the row's height
        a = float(np.clip(widths[0] / heights[0] * rows[0] / 11.5, 0.15, 0.95))
        gs = fig.add_gridspec(3, 2, height_ratios=rows, width_ratios=[a, 1.0 - a])
        axes = [fig.add_subplot(gs[0, 0]), fig.add_subplot(gs[1, :]), fig.add_subplot(gs[2, :])]
    else:
        # figure height from the panels' true aspect: no empty bands above and below
        fig_h = min(9.0, max(3.0, 11.0 * max(heights) / sum(widths) + (2.3 if vectors is not None else 1.9)))
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
            if long:  # the same spacing in cm along both axes of the long panels
                sh, sv = (max(1, int(round(step_cm / spacing[a]))) for a in (h, v))
            else:
                sh, sv = max(1, img.shape[1] // 16), max(1, img.shape[0] // 16)
            jj, ii = np.meshgrid(*(_samples(n, st) if long else np.arange(0, n, st)
                                   for n, st in ((img.shape[1], sh), (img.shape[0], sv))))
            vx, vy = vec[ii, jj, 0], vec[ii, jj, 1]
            ok = np.isfinite(vx) & np.isfinite(vy)
            if ok.any():
                q = ax.quiver(x0 + (jj[ok] + 0.5) * spacing[h], y0 + (ii[ok] + 0.5) * spacing[v], vx[ok], vy[ok],
                              color="k", width=0.004, alpha=0.8, angles="xy", scale_units="xy", scale=arrow[1])
                if ax is axes[1 if long else 0]:  # long: the key on a panel at the scale of the arrows
                    key = float(f"{arrow[0]:.1g}")
                    ax.quiverkey(q, *((0.06, 1.12) if long else (0.02, -0.24)), key,
                                 f"{key:g} cm displacement (arrows {1 / arrow[1]:.3g}× true length)",
                                 labelpos="E", coordinates="axes", fontproperties={"size": 8})
        pos = origin[ax_n] + at[ax_n] * spacing[ax_n]
        ax.set_title(f"{pname}: {AXIS[ax_n]} = {pos:.3g} cm", fontsize=10)
        ax.set_xlabel(f"{AXIS[h]} [cm]")
        ax.set_ylabel(f"{AXIS[v]} [cm]")
        ax.xaxis.set_major_locator(MaxNLocator(nbins=6 if long else 4))  # tick labels never run into each other
        ax.yaxis.set_major_locator(MaxNLocator(nbins=4))
    cb = fig.colorbar(im, ax=list(axes), label=label, fraction=0.025, pad=0.01, aspect=12)
    cb.ax.tick_params(labelsize=9)
    fig.suptitle(title)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return Path(path)

"""Segmentation QC for the report: the MRI with the labels filled in (legend, axes in cm) and the
area of every tissue and muscle per slice.

The report finds the segmentation through the stage records of the results file (the
``segment`` stage's output file and its MRI input); when they are not on disk any more the
section says so.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..model.tissues import TISSUE_NAMES

_TISSUE_COLOURS = {2: (0.20, 0.70, 0.35), 3: (0.95, 0.80, 0.25), 4: (0.35, 0.55, 0.95)}


def find_segmentation(stages: list[dict]) -> tuple[Path | None, Path | None, str]:
    """(segmentation.h5, MRI file, note) from the stage records; None where not found."""
    rec = next((r for r in stages if r.get("stage") == "segment"), None)
    if rec is None:
        return None, None, "the model was not built by the segment stage (labels given directly)"
    seg = Path(rec.get("file", ""))
    if not seg.is_file():
        return None, None, f"segmentation file {seg} is not on disk any more"
    inputs = list((rec.get("provenance") or {}).get("inputs", {}))
    mri = next((Path(p) for p in inputs if "mri" in Path(p).name.lower() and Path(p).is_file()),
               Path(inputs[0]) if inputs and Path(inputs[0]).is_file() else None)
    return seg, mri, ""


def slice_areas(labels: np.ndarray, muscle_id: np.ndarray | None, names: list[str], affine: np.ndarray) -> tuple[list, list]:
    """Area (cm²) of each tissue and each muscle in every slice (axis 2).

    Returns
    -------
    header : list of str
    rows : list of lists, one per slice: slice index, z (cm), tissue areas, muscle areas
    """
    a = np.asarray(affine, float)
    h = np.linalg.norm(a[:3, :3], axis=0)
    pixel = float(h[0] * h[1])
    K = labels.shape[2]
    codes = (1, 2, 3, 4)
    counts = np.stack([(labels == c).reshape(-1, K).sum(axis=0) for c in codes])  # (4, K), loop over 4 codes
    header = ["slice", "z [cm]"] + [f"{TISSUE_NAMES[c]} [cm^2]" for c in codes]
    cols = [np.arange(K), (a @ np.c_[np.zeros((K, 2)), np.arange(K), np.ones(K)].T)[2]] + list(counts * pixel)
    if muscle_id is not None and names:
        m = np.stack([(muscle_id == i).reshape(-1, K).sum(axis=0) for i in range(1, len(names) + 1)])  # per muscle
        header += [f"{n} [cm^2]" for n in names]
        cols += list(m * pixel)
    rows = [[int(c[k]) if j == 0 else float(c[k]) for j, c in enumerate(cols)] for k in range(K)]
    return header, rows


def plot_overlays(mri: np.ndarray | None, seg: dict, path: Path, *, dpi: int = 100, max_slices: int = 6) -> Path:
    """Up to ``max_slices`` slices: MRI in grey with the labels filled in (muscles by id, connective
    tissue, fat, bone), a legend and axes in cm (x, y of the grid, the canonical RAS+ frame)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    labels, mid, names, a = seg["labels"], seg["muscle_id"], seg["muscle_names"], seg["affine"]
    K = labels.shape[2]
    ks = np.unique(np.linspace(0, K - 1, min(K, max_slices)).round().astype(int))
    h = np.linalg.norm(a[:3, :3], axis=0)
    x0, y0 = a[0, 3], a[1, 3]
    extent = (x0 - h[0] / 2, x0 + (labels.shape[0] - 0.5) * h[0], y0 - h[1] / 2, y0 + (labels.shape[1] - 0.5) * h[1])
    cmap = matplotlib.colormaps["tab10" if len(names) <= 10 else "tab20"]
    n = len(ks)
    ncol = min(n, 3)
    nrow = int(np.ceil(n / ncol))
    aspect = (extent[3] - extent[2]) / (extent[1] - extent[0])
    fig, axes = plt.subplots(nrow, ncol, figsize=(4.2 * ncol + 2.4, 4.2 * nrow * aspect + 0.6), squeeze=False,
                             layout="constrained")
    if mri is not None and mri.shape == labels.shape:
        lo, hi = np.percentile(mri, [0.5, 99.5])
    for ax, k in zip(axes.ravel(), ks, strict=False):  # a few slices
        if mri is not None and mri.shape == labels.shape:
            ax.imshow(mri[:, :, k].T, origin="lower", cmap="gray", vmin=lo, vmax=hi, extent=extent,
                      interpolation="nearest")
        rgba = np.zeros(labels.shape[:2] + (4,))
        for code, c in _TISSUE_COLOURS.items():
            rgba[labels[:, :, k] == code] = (*c, 0.55)
        if mid is not None:
            for i in range(1, len(names) + 1):  # loop over muscles
                rgba[mid[:, :, k] == i] = (*cmap((i - 1) % cmap.N)[:3], 0.55)
        ax.imshow(np.transpose(rgba, (1, 0, 2)), origin="lower", extent=extent, interpolation="nearest")
        z = float((a @ [0, 0, k, 1])[2])
        ax.set_title(f"slice {k} (z = {z:.3g} cm)", fontsize=9)
        ax.set_xlabel("x [cm]")
        ax.set_ylabel("y [cm]")
    for ax in axes.ravel()[n:]:
        ax.set_axis_off()
    handles = [Patch(color=cmap((i - 1) % cmap.N), label=nm) for i, nm in enumerate(names, 1)]
    handles += [Patch(color=c, label=TISSUE_NAMES[code]) for code, c in _TISSUE_COLOURS.items()]
    fig.legend(handles=handles, loc="outside right upper", fontsize=8, frameon=False)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path

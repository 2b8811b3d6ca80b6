"""Interactive 3-D view of the model for the report page, drawn in the browser with plotly.js.

The nodes (voxel centres) are shown as a point cloud on the deformed body of a chosen load step,
coloured by a chosen field: displacement magnitude, largest principal Cauchy stress, tissue (with
IMAT and subcutaneous fat apart), muscle, or the fibre direction's angle to the long (z) axis.
The reader rotates and zooms with the mouse, picks the field from a list and the step with a
slider. Large models are decimated in-plane to at most ``max_points`` nodes (every k-th voxel
in x and y, all slices).

Three files are written beside ``index.html`` (no network is needed where the report is opened):
``plotly.min.js`` (shipped inside the ``plotly`` Python package), ``view3d.js`` (the viewer, shipped
with pixmuscle) and ``view3d_data.js`` (this model's arrays). ``plotly`` is optional
(``pip install 'pixmuscle[view]'``); without it :func:`write_view` says so and the page shows why.
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np

from ..mechanics.results import Results
from ..model.tissues import CONNECTIVE_TISSUE, FAT, MUSCLE

#: files written beside index.html
FILES = ("plotly.min.js", "view3d.js", "view3d_data.js")

#: legend classes of the tissue field: (name, colour)
TISSUE_CLASSES = (("muscle", "#c0392b"), ("connective tissue (IMCT, aponeurosis)", "#27ae60"),
                  ("intermuscular fat (IMAT)", "#f39c12"), ("other fat (subcutaneous)", "#f7dc6f"))


def decimate(ijk: np.ndarray, max_points: int) -> np.ndarray:
    """Indices of the nodes kept: every k-th voxel in x and y (all slices), the smallest k ≥ 1 that
    keeps at most ``max_points``.

    Parameters
    ----------
    ijk : (N, 3) int
        Voxel index of each node.
    max_points : int
        Upper bound on the nodes kept (≥ 1).

    Returns
    -------
    (M,) int64
        Sorted node indices, M ≤ max_points (M = N when N ≤ max_points).
    """
    ijk = np.asarray(ijk)
    n = ijk.shape[0]
    if n <= max_points:
        return np.arange(n, dtype=np.int64)
    k = max(2, int(math.floor(math.sqrt(n / max_points))))
    while True:
        keep = np.flatnonzero((ijk[:, 0] % k == 0) & (ijk[:, 1] % k == 0))
        if keep.size <= max_points:
            return keep.astype(np.int64)
        k += 1


def tissue_class(tissue: np.ndarray, imat: np.ndarray | None) -> np.ndarray:
    """(N,) int8 index into :data:`TISSUE_CLASSES`: muscle, connective tissue, IMAT, other fat."""
    tissue = np.asarray(tissue)
    imat = np.zeros(tissue.shape, bool) if imat is None else np.asarray(imat, bool)
    out = np.full(tissue.shape, 3, np.int8)
    out[tissue == MUSCLE] = 0
    out[tissue == CONNECTIVE_TISSUE] = 1
    out[(tissue == FAT) & imat] = 2
    return out


def fibre_angle_deg(fiber: np.ndarray) -> np.ndarray:
    """Angle between the fibre direction and the z (long) axis, degrees in [0, 90] (fibres have no
    sign); NaN where the fibre vector is zero. (N, 3) → (N,)."""
    f = np.asarray(fiber, float)
    norm = np.linalg.norm(f, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        c = np.abs(f[:, 2]) / norm
    return np.degrees(np.arccos(np.clip(c, 0.0, 1.0)))


def _rounded(a: np.ndarray, step: float) -> list:
    """Values rounded to the decimal place of ``step`` (a small file), flattened; NaN stays NaN
    (written as JavaScript's ``NaN``)."""
    digits = max(0, -int(math.floor(math.log10(step))))
    return np.round(np.asarray(a, float), digits).ravel().tolist()


def view_data(res: Results, steps: np.ndarray, *, imat: np.ndarray | None = None, max_points: int = 20000) -> dict:
    """The arrays the browser draws (plain JSON-ready data).

    Parameters
    ----------
    res : Results
    steps : (S,) int
        Stored states offered on the step slider (converged ones).
    imat : (N,) bool, optional
        Fat nodes counted as IMAT (the report's tissue table), shown apart from other fat.
    max_points : int
        Decimate larger models to at most this many nodes (:func:`decimate`).

    Returns
    -------
    dict
        ``X`` (flat 3M reference coordinates, cm), ``u`` (S lists of 3M displacements, cm), ``umag``
        and ``s1`` (S lists of M: |u| cm, largest principal Cauchy stress N/cm²; ``s1`` entries None
        when the results hold no stress), ``tissue`` (M class indices), ``tissue_classes`` (names,
        colours), ``muscle`` (M ids, 0 = none), ``muscle_names``, ``fibre_angle`` (M degrees, NaN off
        muscle), ``steps``, ``alpha``, ``n_nodes``, ``n_shown``.
    """
    m = res.model
    keep = decimate(m.ijk, max_points)
    spacing = float(np.min(m.spacing))
    ustep = max(spacing * 1e-4, 1e-7)
    u_all, umag, s1 = [], [], []
    for k in steps:
        f = res.step(int(k))
        u = np.asarray(f.u, float)[keep]
        u_all.append(_rounded(u, ustep))
        umag.append(_rounded(np.linalg.norm(u, axis=1), ustep))
        if f.max_principal is not None:
            sp = np.asarray(f.max_principal, float)[keep]
            scale = float(np.nanmax(np.abs(sp))) if np.isfinite(sp).any() else 1.0
            s1.append(_rounded(sp, max(scale * 1e-4, 1e-9)))
        else:
            s1.append(None)
    fib = np.asarray(m.fiber, float)[keep]
    angle = fibre_angle_deg(fib)
    angle[np.asarray(m.tissue)[keep] != MUSCLE] = np.nan
    names = list(m.muscle_names)
    return {
        "X": _rounded(np.asarray(m.X, float)[keep], ustep),
        "u": u_all, "umag": umag, "s1": s1,
        "tissue": tissue_class(np.asarray(m.tissue)[keep], None if imat is None else np.asarray(imat)[keep]).tolist(),
        "tissue_classes": [{"name": n, "color": c} for n, c in TISSUE_CLASSES],
        "muscle": np.asarray(m.muscle_id)[keep].astype(int).tolist(),
        "muscle_names": [str(n).replace("_", " ") for n in names],
        "fibre_angle": _rounded(angle, 0.1),
        "steps": [int(k) for k in steps],
        "alpha": [float(res.alpha[int(k)]) for k in steps],
        "n_nodes": int(m.n_nodes), "n_shown": int(keep.size),
    }


def plotly_js() -> tuple[str, str]:
    """(plotly.min.js text, plotly version) from the installed ``plotly`` package; ImportError without it."""
    import plotly
    from plotly.offline import get_plotlyjs

    return get_plotlyjs(), plotly.__version__


def write_view(res: Results, outdir: str | Path, steps: np.ndarray, *, imat: np.ndarray | None = None,
               max_points: int = 20000) -> dict:
    """Write the viewer's files beside the report page.

    Returns
    -------
    dict
        ``files`` (names of the files written in ``outdir``), ``plotly`` (version), ``n_nodes``, ``n_shown``, ``steps``; or
        ``{"error": why}`` when plotly is not installed (nothing written).
    """
    outdir = Path(outdir)
    try:
        js, version = plotly_js()
    except ImportError:
        return {"error": "plotly is not installed (pip install 'pixmuscle[view]')"}
    data = view_data(res, steps, imat=imat, max_points=max_points)
    paths = [outdir / name for name in FILES]
    paths[0].write_text(js, encoding="utf-8")
    shutil.copyfile(Path(__file__).with_name("view3d.js"), paths[1])
    # a script, not JSON: NaN is a JavaScript literal
    paths[2].write_text("window.PIXMUSCLE_VIEW3D = " + json.dumps(data, separators=(",", ":")) + ";\n",
                        encoding="utf-8")
    return {"files": list(FILES), "plotly": version, "n_nodes": data["n_nodes"],
            "n_shown": data["n_shown"], "steps": data["steps"]}

"""Nodal fields for ParaView: one VTU file per load step plus a PVD collection (via meshio).

Nodes are written as a point cloud (one VTK ``vertex`` cell per node) on the **reference**
coordinates; use ParaView's "Warp By Vector" with ``displacement`` to see the deformed shape.
Point data:

``displacement`` (N, 3) cm; ``fiber_direction`` (N, 3) unit; ``tissue`` (N,) code 1 muscle,
2 connective tissue, 3 fat; ``muscle_id`` (N,) 0 or 1..M; ``imat`` (N,) 1 where the fat node is
counted as IMAT by the tissue table; ``max_principal_cauchy`` (N,) N/cm²; ``cauchy`` (N, 6)
N/cm² in Voigt order xx yy zz xy yz xz (ParaView's symmetric-tensor order).

Frames: ``"model"`` writes the grid-aligned model frame (cm). ``"rotated"`` applies
``grid/rotation`` R about the frame origin: points and vectors become ``R x``, stresses ``R σ Rᵀ``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from .inputs import StepFields, voigt_to_tensor


def rotate_voigt(v: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Rotate symmetric tensors given in Voigt order: ``R σ Rᵀ``.

    Parameters
    ----------
    v : (N, 6) float64
        xx yy zz xy yz xz.
    R : (3, 3) float64

    Returns
    -------
    (N, 6) float64
    """
    t = np.einsum("ij,njk,lk->nil", R, voigt_to_tensor(v), R)
    return np.stack([t[:, 0, 0], t[:, 1, 1], t[:, 2, 2], t[:, 0, 1], t[:, 1, 2], t[:, 0, 2]], axis=-1)


def step_mesh(X: np.ndarray, fields: StepFields, *, fiber: np.ndarray, tissue: np.ndarray, muscle_id: np.ndarray,
              imat: np.ndarray | None = None, rotation: np.ndarray | None = None):
    """A meshio point-cloud mesh of one step.

    Parameters
    ----------
    X : (N, 3) float64
        Reference node coordinates, cm.
    fields : StepFields
        Displacement (cm) and stresses (N/cm²) of the step.
    fiber : (N, 3); tissue, muscle_id : (N,)
        Model data.
    imat : (N,) bool, optional
    rotation : (3, 3), optional
        Applied to points, vectors and tensors when given.
    """
    import meshio

    n = X.shape[0]
    u, fib, cau = fields.u, np.asarray(fiber, float), fields.cauchy
    if rotation is not None:
        R = np.asarray(rotation, float)
        X, u, fib = X @ R.T, u @ R.T, fib @ R.T
        cau = rotate_voigt(cau, R) if cau is not None else None
    pd = {
        "displacement": np.ascontiguousarray(u, np.float64),
        "fiber_direction": np.ascontiguousarray(fib, np.float64),
        "tissue": np.asarray(tissue, np.int32),
        "muscle_id": np.asarray(muscle_id, np.int32),
    }
    if imat is not None:
        pd["imat"] = np.asarray(imat, np.int32)
    if fields.max_principal is not None:
        pd["max_principal_cauchy"] = np.asarray(fields.max_principal, np.float64)
    if cau is not None:
        pd["cauchy"] = np.ascontiguousarray(cau, np.float64)
    cells = [("vertex", np.arange(n, dtype=np.int64)[:, None])]
    return meshio.Mesh(np.ascontiguousarray(X, np.float64), cells, point_data=pd)


def write_pvd(path: str | Path, files: Sequence[str], times: Sequence[float]) -> Path:
    """Write a ParaView collection file listing ``files`` (paths relative to the PVD) at ``times``."""
    lines = ['<?xml version="1.0"?>',
             '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">',
             "  <Collection>"]
    for f, t in zip(files, times, strict=True):
        lines.append(f'    <DataSet timestep="{float(t)!r}" group="" part="0" file={quoteattr(str(f))}/>')
    lines += ["  </Collection>", "</VTKFile>", ""]
    Path(path).write_text("\n".join(lines))
    return Path(path)


def vtu_steps(converged: np.ndarray, every_nth: int) -> np.ndarray:
    """Steps to export: converged steps whose index is a multiple of ``every_nth``, plus the last
    converged step.

    Returns
    -------
    (k,) int64, ascending
    """
    conv = np.flatnonzero(np.asarray(converged, bool))
    if conv.size == 0:
        return conv
    keep = conv[conv % every_nth == 0]
    return np.union1d(keep, conv[-1:])


def write_vtu_series(outdir: str | Path, steps: Sequence[int], times: Sequence[float],
                     load_fields: Callable[[int], StepFields], *, X, fiber, tissue, muscle_id, imat=None,
                     rotation=None, compression: str | None = "zlib", progress=None) -> tuple[Path, list[Path]]:
    """Write ``fields/step_XXXX.vtu`` for each step and ``fields.pvd`` listing them at ``times``.

    Returns
    -------
    pvd : Path
    vtus : list of Path
    """
    import meshio

    outdir = Path(outdir)
    (outdir / "fields").mkdir(parents=True, exist_ok=True)
    rel, paths = [], []
    for s in steps:  # loop over load steps
        name = f"fields/step_{int(s):04d}.vtu"
        mesh = step_mesh(X, load_fields(int(s)), fiber=fiber, tissue=tissue, muscle_id=muscle_id, imat=imat, rotation=rotation)
        meshio.write(outdir / name, mesh, file_format="vtu", compression=None if compression in (None, "none") else compression)
        rel.append(name)
        paths.append(outdir / name)
        if progress is not None:
            progress.advance()
    return write_pvd(outdir / "fields.pvd", rel, times), paths

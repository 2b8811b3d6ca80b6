"""Fields for ParaView: the model as voxel cells, one VTU per load step, a PVD collection, and the
same series as XDMF + HDF5 for large models (both through meshio).

Every node of the pixel-point model owns an axis-aligned integration cell of size ``grid/spacing``
centred on it (docs/architecture.md, "Model frame"); the files hold exactly these cells as VTK
hexahedra, so ParaView's Slice, Clip, Threshold and Contour return pieces of the body at any
plane. Nodal values are **cell data** (one value per node = per cell); displacement and the
stresses are also given as **point data** at the cell corners (mean of the body cells sharing the
corner) for *Warp By Vector* and smooth colouring. Coordinates are the **reference**
configuration, cm.

Arrays (units in the names and in the field-data array ``units``):

``displacement [cm]`` (3), ``fiber_direction [1]`` (3, cells), ``tissue`` (cells: 1 muscle,
2 connective tissue, 3 fat; names in field data ``tissue_names``), ``muscle_id`` (cells: 0 or 1..M;
names in ``muscle_names``, index = id), ``imat`` (cells: 1 where the fat node counts as IMAT),
``max_principal_cauchy [N/cm^2]``, ``cauchy [N/cm^2]`` (6 components XX YY ZZ XY YZ XZ, ParaView's
symmetric-tensor order; component names stored).

Frames: ``"model"`` writes the grid-aligned model frame (cm). ``"rotated"`` applies
``grid/rotation`` R about the frame origin: points and vectors become ``R x``, stresses ``R σ Rᵀ``.
"""

from __future__ import annotations

import io
import re
from collections.abc import Callable, Sequence
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from ..mechanics.results import StepFields
from ..model.tissues import TISSUE_NAMES

#: corner offsets of a voxel in VTK_HEXAHEDRON order
HEX_CORNERS = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]])
CAUCHY_COMPONENTS = ("XX", "YY", "ZZ", "XY", "YZ", "XZ")
DISPLACEMENT = "displacement [cm]"
FIBER = "fiber_direction [1]"
CAUCHY = "cauchy [N/cm^2]"
MAX_PRINCIPAL = "max_principal_cauchy [N/cm^2]"
UNITS = (f"{DISPLACEMENT}: cm", f"{CAUCHY}: N/cm^2 (Voigt XX YY ZZ XY YZ XZ)", f"{MAX_PRINCIPAL}: N/cm^2",
         f"{FIBER}: unit vector", "tissue: code, see tissue_names", "muscle_id: index into muscle_names",
         "imat: 1 = fat counted as IMAT", "coordinates: cm, reference configuration", "time: activation alpha")


def voigt_to_tensor(v: np.ndarray) -> np.ndarray:
    """(N, 6) Voigt (xx yy zz xy yz xz) → (N, 3, 3) symmetric tensors."""
    xx, yy, zz, xy, yz, xz = np.moveaxis(np.asarray(v, float), -1, 0)
    return np.stack([np.stack([xx, xy, xz], -1), np.stack([xy, yy, yz], -1), np.stack([xz, yz, zz], -1)], -2)


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


def voxel_hexahedra(ijk: np.ndarray, origin, spacing) -> tuple[np.ndarray, np.ndarray]:
    """The integration cells of the nodes as hexahedra sharing their corners.

    Parameters
    ----------
    ijk : (N, 3) int
        Voxel index of each node.
    origin, spacing : (3,) float, cm

    Returns
    -------
    points : (P, 3) float64, cm
        Cell corners, ``origin + (corner - 1/2) * spacing``.
    hexa : (N, 8) int64
        Corner indices of each node's cell, VTK_HEXAHEDRON order; cell n belongs to node n.
    """
    ijk = np.asarray(ijk, np.int64)
    lo = ijk.min(axis=0) if ijk.size else np.zeros(3, np.int64)
    corner = (ijk - lo)[:, None, :] + HEX_CORNERS[None]          # (N, 8, 3)
    dims = corner.reshape(-1, 3).max(axis=0) + 1 if ijk.size else np.ones(3, np.int64)
    flat = np.ravel_multi_index(tuple(corner.reshape(-1, 3).T), tuple(dims))
    uniq, inv = np.unique(flat, return_inverse=True)
    pts = np.stack(np.unravel_index(uniq, tuple(dims)), axis=-1) + lo
    points = np.asarray(origin, float) + (pts - 0.5) * np.asarray(spacing, float)
    return points, inv.reshape(-1, 8).astype(np.int64)


def cells_to_points(hexa: np.ndarray, values: np.ndarray, n_points: int) -> np.ndarray:
    """Mean of the cell values around each corner point.

    Parameters
    ----------
    hexa : (N, 8) int
    values : (N,) or (N, c) float
    n_points : int

    Returns
    -------
    (P,) or (P, c) float64
    """
    v = np.asarray(values, float)
    flat = v.reshape(v.shape[0], -1)
    idx = hexa.ravel()
    count = np.bincount(idx, minlength=n_points).astype(float)
    out = np.stack([np.bincount(idx, weights=np.repeat(flat[:, c], 8), minlength=n_points) for c in range(flat.shape[1])],
                   axis=-1)  # loop over components (≤ 6)
    out /= np.maximum(count, 1.0)[:, None]
    return out.reshape((n_points, *v.shape[1:]))


def step_mesh(ijk: np.ndarray, origin, spacing, fields: StepFields, *, fiber: np.ndarray, tissue: np.ndarray,
              muscle_id: np.ndarray, imat: np.ndarray | None = None, rotation: np.ndarray | None = None,
              cells: tuple | None = None):
    """A meshio mesh of one step: the model's voxel cells with cell and point data.

    Parameters
    ----------
    ijk : (N, 3) int; origin, spacing : (3,) cm
        The model grid.
    fields : StepFields
        Displacement (cm) and stresses (N/cm²) of the step.
    fiber : (N, 3); tissue, muscle_id : (N,)
        Model data.
    imat : (N,) bool, optional
    rotation : (3, 3), optional
        Applied to points, vectors and tensors when given.
    cells : (points, hexa), optional
        The output of :func:`voxel_hexahedra` (computed when not given).
    """
    import meshio

    points, hexa = cells if cells is not None else voxel_hexahedra(ijk, origin, spacing)
    u, fib, cau = np.asarray(fields.u, float), np.asarray(fiber, float), fields.cauchy
    if rotation is not None:
        R = np.asarray(rotation, float)
        points, u, fib = points @ R.T, u @ R.T, fib @ R.T
        cau = rotate_voigt(cau, R) if cau is not None else None
    n_pts = points.shape[0]
    cd = {DISPLACEMENT: u, FIBER: fib, "tissue": np.asarray(tissue, np.int32), "muscle_id": np.asarray(muscle_id, np.int32)}
    pd = {DISPLACEMENT: cells_to_points(hexa, u, n_pts)}
    if imat is not None:
        cd["imat"] = np.asarray(imat, np.int32)
    if fields.max_principal is not None:
        cd[MAX_PRINCIPAL] = np.asarray(fields.max_principal, np.float64)
        pd[MAX_PRINCIPAL] = cells_to_points(hexa, cd[MAX_PRINCIPAL], n_pts)
    if cau is not None:
        cd[CAUCHY] = np.asarray(cau, np.float64)
        pd[CAUCHY] = cells_to_points(hexa, cd[CAUCHY], n_pts)
    return meshio.Mesh(np.ascontiguousarray(points, np.float64), [("hexahedron", hexa)],
                       point_data={k: np.ascontiguousarray(v) for k, v in pd.items()},
                       cell_data={k: [np.ascontiguousarray(v)] for k, v in cd.items()})


def _string_array(name: str, values: Sequence[str]) -> str:
    codes = " ".join(" ".join(str(b) for b in s.encode("utf-8")) + " 0" for s in values)
    return f'      <Array type="String" Name={quoteattr(name)} NumberOfTuples="{len(values)}" format="ascii">{codes}</Array>\n'


def field_data_xml(muscle_names: Sequence[str]) -> str:
    """The ``<FieldData>`` block: ``units``, ``tissue_names`` (index = code), ``muscle_names`` (index = id)."""
    tissues = ["background", *[TISSUE_NAMES.get(c, str(c)) for c in (1, 2, 3)]]
    return ("    <FieldData>\n" + _string_array("units", UNITS) + _string_array("tissue_names", tissues)
            + _string_array("muscle_names", ["(not muscle)", *muscle_names]) + "    </FieldData>\n")


def annotate_vtu(path: str | Path, muscle_names: Sequence[str]) -> Path:
    """Add the field data (units and names) and the Cauchy component names to a VTU written by meshio."""
    path = Path(path)
    text = path.read_text(encoding="utf-8")
    text = text.replace("<UnstructuredGrid>", "<UnstructuredGrid>\n" + field_data_xml(muscle_names).rstrip("\n"), 1)
    names = " ".join(f'ComponentName{i}="{c}"' for i, c in enumerate(CAUCHY_COMPONENTS))
    text = re.sub(r'(<DataArray[^>]*Name="' + re.escape(CAUCHY) + r'")', r"\1 " + names, text)
    path.write_text(text, encoding="utf-8")
    return path


class XdmfSeries:
    """A time series of one mesh as XDMF 3 + HDF5 (``fields.xdmf`` beside ``fields.h5``).

    Written here rather than with ``meshio.xdmf.TimeSeriesWriter``, which puts the HDF5 file in
    the current working directory instead of beside the XDMF file. meshio's
    ``TimeSeriesReader`` and ParaView (XDMF3 reader) read it.
    """

    def __init__(self, path: str | Path, points: np.ndarray, hexa: np.ndarray):
        import h5py

        self.path = Path(path)
        self.h5_path = self.path.with_suffix(".h5")
        # built in memory and written on close (pixmuscle.store.write_bytes_atomic): HDF5 closing a
        # file on a full disk can crash the interpreter; a Python write raises a clean error
        self._buf = io.BytesIO()
        self._h5 = h5py.File(self._buf, "w")
        self._h5["points"] = np.asarray(points, float)
        self._h5["hexahedra"] = np.asarray(hexa, np.int64)
        self._n_points, self._n_cells = points.shape[0], hexa.shape[0]
        self._steps: list[str] = []

    def _item(self, ds: str, shape: tuple, dtype) -> str:
        kind, prec = ("Int", 8) if np.dtype(dtype).kind in "iu" else ("Float", 8)
        dims = " ".join(map(str, shape))
        return (f'<DataItem DataType="{kind}" Precision="{prec}" Dimensions="{dims}" Format="HDF">'
                f"{self.h5_path.name}:/{ds}</DataItem>")

    def write(self, t: float, point_data: dict, cell_data: dict) -> None:
        """Append one time step (``cell_data`` values as meshio gives them: lists of one array)."""
        k = len(self._steps)
        attrs = []
        for centre, data in (("Node", point_data), ("Cell", cell_data)):
            for name, v in data.items():
                v = np.asarray(v[0] if isinstance(v, list) else v)
                ds = f"step_{k:04d}/{centre.lower()}/{name}"
                self._h5[ds] = v
                typ = {1: "Scalar", 3: "Vector", 6: "Tensor6"}.get(1 if v.ndim == 1 else v.shape[1], "Matrix")
                attrs.append(f'<Attribute Name={quoteattr(name)} AttributeType="{typ}" Center="{centre}">'
                             f"{self._item(ds, v.shape, v.dtype)}</Attribute>")
        topo = (f'<Topology TopologyType="Hexahedron" NumberOfElements="{self._n_cells}">'
                f'{self._item("hexahedra", (self._n_cells, 8), np.int64)}</Topology>')
        geo = f'<Geometry GeometryType="XYZ">{self._item("points", (self._n_points, 3), float)}</Geometry>'
        self._steps.append(f'<Grid Name="step {k}" GridType="Uniform"><Time Value="{float(t)!r}"/>{topo}{geo}'
                           + "".join(attrs) + "</Grid>")

    def close(self) -> Path:
        from ..store import write_bytes_atomic

        self._h5.close()
        write_bytes_atomic(self.h5_path, self._buf.getbuffer())
        body = "\n".join(f"      {g}" for g in self._steps)
        self.path.write_text('<?xml version="1.0"?>\n<Xdmf Version="3.0">\n  <Domain>\n'
                             '    <Grid Name="fields" GridType="Collection" CollectionType="Temporal">\n'
                             f"{body}\n    </Grid>\n  </Domain>\n</Xdmf>\n")
        return self.path


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
                     load_fields: Callable[[int], StepFields], *, ijk, origin, spacing, fiber, tissue, muscle_id,
                     muscle_names: Sequence[str] = (), imat=None, rotation=None, compression: str | None = "zlib",
                     xdmf: bool = False, progress=None) -> dict:
    """Write ``fields/step_XXXX.vtu`` for each step, ``fields.pvd`` listing them at ``times`` and,
    with ``xdmf``, the same series as ``fields.xdmf`` + ``fields.h5``.

    Returns
    -------
    dict
        ``pvd`` (Path), ``vtu`` (list of Path), ``xdmf`` (Path or None).
    """
    import meshio

    outdir = Path(outdir)
    (outdir / "fields").mkdir(parents=True, exist_ok=True)
    cells = voxel_hexahedra(ijk, origin, spacing)
    rel, paths = [], []
    writer = None
    try:
        for s, t in zip(steps, times, strict=True):  # loop over load steps
            name = f"fields/step_{int(s):04d}.vtu"
            mesh = step_mesh(ijk, origin, spacing, load_fields(int(s)), fiber=fiber, tissue=tissue, muscle_id=muscle_id,
                             imat=imat, rotation=rotation, cells=cells)
            meshio.write(outdir / name, mesh, file_format="vtu",
                         compression=None if compression in (None, "none") else compression)
            annotate_vtu(outdir / name, muscle_names)
            if xdmf:
                if writer is None:
                    writer = XdmfSeries(outdir / "fields.xdmf", mesh.points, mesh.cells[0].data)
                writer.write(float(t), mesh.point_data, mesh.cell_data)
            rel.append(name)
            paths.append(outdir / name)
            if progress is not None:
                progress.advance()
    finally:
        xdmf_path = writer.close() if writer is not None else None
    return {"pvd": write_pvd(outdir / "fields.pvd", rel, times), "vtu": paths, "xdmf": xdmf_path}

"""Writer of XDMF 3 time series (``<name>.xdmf`` beside ``<name>.h5``): one unstructured hexahedral
mesh, point and cell arrays per time step.

Array kinds follow their number of components: 1 Scalar, 3 Vector, 6 Tensor6 (a symmetric tensor),
anything else Matrix. A 6-component array is given in VTK's symmetric-tensor order
``XX YY ZZ XY YZ XZ`` (the order of the VTU files, :data:`VTK_TENSOR6`) and stored in the order
the XDMF readers expect for ``Tensor6``, ``XX XY XZ YY YZ ZZ`` (the upper triangle row by row;
VTK's ``vtkXdmfReader`` expands it to the full 3 × 3 tensor that way).

Written here rather than with ``meshio.xdmf.TimeSeriesWriter``, which puts the HDF5 file in the
current working directory instead of beside the XDMF file and keeps a tensor's components in
the order given. VTK's XDMF reader (ParaView) and meshio's ``TimeSeriesReader`` read it.
"""

from __future__ import annotations

import io
from collections.abc import Mapping
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

#: component order of a symmetric tensor as given to :meth:`XdmfSeries.write` (VTK's, the VTU files')
VTK_TENSOR6 = ("XX", "YY", "ZZ", "XY", "YZ", "XZ")
#: component order of an XDMF ``Tensor6`` attribute
XDMF_TENSOR6 = ("XX", "XY", "XZ", "YY", "YZ", "ZZ")
#: columns of a VTK-ordered (N, 6) array in XDMF ``Tensor6`` order
TO_XDMF_TENSOR6 = np.array([VTK_TENSOR6.index(c) for c in XDMF_TENSOR6])


class XdmfSeries:
    """A time series of one hexahedral mesh as XDMF 3 + HDF5 (``path`` and ``path.with_suffix(".h5")``).

    Parameters
    ----------
    path : path-like
        The ``.xdmf`` file; the heavy data goes to the ``.h5`` file of the same name beside it.
    points : (P, 3) float64
        Mesh points (cm).
    hexa : (C, 8) int
        Point indices of each cell, VTK_HEXAHEDRON order.

    Notes
    -----
    Nothing is written before :meth:`close`: the HDF5 file is built in memory and written
    atomically (HDF5 closing a file on a full disk can crash the interpreter; a Python write
    raises a clean error).
    """

    def __init__(self, path: str | Path, points: np.ndarray, hexa: np.ndarray):
        import h5py

        self.path = Path(path)
        self.h5_path = self.path.with_suffix(".h5")
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

    def write(self, t: float, point_data: Mapping, cell_data: Mapping) -> None:
        """Append one time step.

        Parameters
        ----------
        t : float
            Time value of the step.
        point_data, cell_data : mapping name → array
            (P, c) and (C, c) arrays (``cell_data`` values may also be lists of one array, as
            meshio gives them); c = 6 arrays are symmetric tensors in :data:`VTK_TENSOR6` order.
        """
        k = len(self._steps)
        attrs = []
        for centre, data in (("Node", point_data), ("Cell", cell_data)):
            for name, v in data.items():
                v = np.asarray(v[0] if isinstance(v, list) else v)
                ncomp = 1 if v.ndim == 1 else v.shape[1]
                typ = {1: "Scalar", 3: "Vector", 6: "Tensor6"}.get(ncomp, "Matrix")
                if typ == "Tensor6":
                    v = v[:, TO_XDMF_TENSOR6]
                ds = f"step_{k:04d}/{centre.lower()}/{name}"
                self._h5[ds] = v
                attrs.append(f'<Attribute Name={quoteattr(name)} AttributeType="{typ}" Center="{centre}">'
                             f"{self._item(ds, v.shape, v.dtype)}</Attribute>")
        topo = (f'<Topology TopologyType="Hexahedron" NumberOfElements="{self._n_cells}">'
                f'{self._item("hexahedra", (self._n_cells, 8), np.int64)}</Topology>')
        geo = f'<Geometry GeometryType="XYZ">{self._item("points", (self._n_points, 3), float)}</Geometry>'
        self._steps.append(f'<Grid Name="step {k}" GridType="Uniform"><Time Value="{float(t)!r}"/>{topo}{geo}'
                           + "".join(attrs) + "</Grid>")

    def close(self) -> Path:
        """Write the ``.h5`` and ``.xdmf`` files; returns the path of the ``.xdmf`` file."""
        from ..store import write_bytes_atomic

        self._h5.close()
        write_bytes_atomic(self.h5_path, self._buf.getbuffer())
        body = "\n".join(f"      {g}" for g in self._steps)
        self.path.write_text('<?xml version="1.0"?>\n<Xdmf Version="3.0">\n  <Domain>\n'
                             '    <Grid Name="fields" GridType="Collection" CollectionType="Temporal">\n'
                             f"{body}\n    </Grid>\n  </Domain>\n</Xdmf>\n")
        return self.path

"""Writer of VTK XML unstructured grids (``.vtu``, through meshio) with field data and tensor
component names, and of ParaView collection files (``.pvd``) that list them as a time series.

meshio writes the points, cells, point and cell data; this module adds what meshio leaves out and
ParaView shows: string arrays in the grid's ``<FieldData>`` (units, names of codes, notes) and
the component names of chosen arrays (e.g. ``XX YY ZZ XY YZ XZ`` of a symmetric tensor, VTK's
order for 6-component arrays).
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from xml.sax.saxutils import quoteattr


def _string_array(name: str, values: Sequence[str]) -> str:
    codes = " ".join(" ".join(str(b) for b in s.encode("utf-8")) + " 0" for s in values)
    return f'      <Array type="String" Name={quoteattr(name)} NumberOfTuples="{len(values)}" format="ascii">{codes}</Array>\n'


def field_data_xml(field_data: Mapping[str, Sequence[str]]) -> str:
    """A ``<FieldData>`` block of string arrays (name → list of strings)."""
    return "    <FieldData>\n" + "".join(_string_array(k, v) for k, v in field_data.items()) + "    </FieldData>\n"


def write_vtu(path: str | Path, mesh, *, field_data: Mapping[str, Sequence[str]] | None = None,
              component_names: Mapping[str, Sequence[str]] | None = None, compression: str | None = "zlib") -> Path:
    """Write a meshio mesh as ``.vtu`` with string field data and array component names.

    Parameters
    ----------
    path : path-like
    mesh : meshio.Mesh
    field_data : mapping name → list of str, optional
        String arrays of the grid's field data.
    component_names : mapping array name → list of str, optional
        Component names of point or cell arrays.
    compression : {"zlib", "lzma", None}
        Compression of the binary arrays.
    """
    import meshio

    path = Path(path)
    meshio.write(path, mesh, file_format="vtu", compression=None if compression in (None, "none") else compression)
    text = path.read_text(encoding="utf-8")
    if field_data:
        text = text.replace("<UnstructuredGrid>", "<UnstructuredGrid>\n" + field_data_xml(field_data).rstrip("\n"), 1)
    for name, comps in (component_names or {}).items():
        names = " ".join(f"ComponentName{i}={quoteattr(c)}" for i, c in enumerate(comps))
        text = re.sub(r'(<DataArray[^>]*Name="' + re.escape(name) + r'")', lambda m, n=names: f"{m.group(1)} {n}", text)
    path.write_text(text, encoding="utf-8")
    return path


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

"""Label maps with names: 3D Slicer segmentations (``.seg.nrrd``), NRRD label maps and ITK-SNAP label
NIfTI with its label description file; and a writer of ``.seg.nrrd`` for correcting a segmentation by hand.

A label map is integer labels on a grid plus a name for each label value. Reading gives
:class:`LabelMap`: labels (I, J, K) in the file's voxel order (NIfTI: closest-canonical RAS+ order), the voxel → world affine in cm on RAS axes
(None when the file has no geometry), and ``names`` (label value → name).

* NRRD (pynrrd): geometry from ``space`` (LPS or RAS; converted to RAS), ``space directions``,
  ``space origin`` and ``space units`` (mm when absent).
* Slicer ``.seg.nrrd``: segments from the header's ``Segment<N>_Name``, ``Segment<N>_LabelValue`` and
  ``Segment<N>_Layer``. Layers (a leading ``list`` axis, one per layer) are merged into one label map in
  which segment ``N`` gets the value ``N + 1``; where segments of different layers overlap the later
  segment wins (the count is reported). Files from before label values (one binary layer per segment)
  read the same way.
* ITK-SNAP: a NIfTI label image and its label description file (lines
  ``IDX R G B A VIS MSH "LABEL"``).

Which tissue or muscle a name stands for is decided by the build-model stage, not here.

References
----------
NRRD file format: https://teem.sourceforge.net/nrrd/format.html
3D Slicer segmentation file format (``Segment<N>_*`` header fields), Slicer documentation.
"""

from __future__ import annotations

import os
import re
import uuid
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pixmuscle.errors import InputError, OutputError

__all__ = ["LabelMap", "read_label_map", "read_itksnap_descriptions", "write_seg_nrrd", "is_nrrd"]

_MM_PER = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "um": 1e-3, "µm": 1e-3}
_LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0])
_SPACES = {"left-posterior-superior": _LPS_TO_RAS, "lps": _LPS_TO_RAS, "right-anterior-superior": np.eye(3),
           "ras": np.eye(3)}


@dataclass
class LabelMap:
    """Integer labels with a name per value.

    Attributes
    ----------
    labels : ndarray of int, shape (I, J, K)
    affine : (4, 4) ndarray or None
        Voxel index → RAS world position, cm; None when the file holds no geometry.
    names : dict of int → str
        Label value → name (0 is background and needs no name).
    path : Path
    notes : list of str
        What reading had to decide (overlaps merged), for the log.
    """

    labels: np.ndarray
    affine: np.ndarray | None
    names: dict[int, str]
    path: Path
    notes: list[str] = field(default_factory=list)


def is_nrrd(path) -> bool:
    """True for ``.nrrd`` / ``.seg.nrrd`` / ``.nhdr`` files."""
    return str(path).lower().endswith((".nrrd", ".nhdr"))


def _nrrd():
    try:
        import nrrd
    except ImportError:
        raise InputError("reading NRRD label maps needs pynrrd: pip install 'pixmuscle[scanner]'") from None
    return nrrd


def _nrrd_affine(header: Mapping, path: Path, spatial: list[int]) -> np.ndarray | None:
    dirs = header.get("space directions")
    if dirs is None:
        return None
    dirs = np.asarray(dirs, dtype=float)
    dirs = dirs[spatial] if dirs.shape[0] != 3 else dirs
    if dirs.shape != (3, 3) or not np.isfinite(dirs).all():
        raise InputError(f"{path}: 'space directions' must give 3 spatial axes, got {header.get('space directions')}")
    space = str(header.get("space", "left-posterior-superior")).lower()
    if space not in _SPACES:
        raise InputError(f"{path}: NRRD space {space!r} is not supported; expected left-posterior-superior or "
                         "right-anterior-superior")
    units = header.get("space units") or ["mm"] * 3
    scale = np.array([_MM_PER.get(str(u).strip('"').lower(), np.nan) for u in units])
    if not np.isfinite(scale).all():
        raise InputError(f"{path}: unknown 'space units' {units}; expected mm, cm, m or um")
    origin = np.asarray(header.get("space origin", np.zeros(3)), dtype=float)
    to_ras = _SPACES[space]
    a = np.eye(4)
    a[:3, :3] = to_ras @ (dirs * scale[:, None]).T * 0.1        # columns: one per voxel axis, cm
    a[:3, 3] = to_ras @ (origin * scale.mean()) * 0.1
    return a


def _segments(header: Mapping) -> list[dict]:
    """Slicer's segment fields, in segment order: name, label value, layer."""
    found = []
    n = 0
    while f"Segment{n}_Name" in header or f"Segment{n}_ID" in header:
        name = str(header.get(f"Segment{n}_Name", header.get(f"Segment{n}_ID"))).strip()
        value = header.get(f"Segment{n}_LabelValue")
        layer = header.get(f"Segment{n}_Layer")
        found.append({"name": name, "value": int(value) if value is not None else 1,
                      "layer": int(layer) if layer is not None else n})
        n += 1
    return found


def _read_nrrd(path: Path) -> LabelMap:
    nrrd = _nrrd()
    try:
        data, header = nrrd.read(str(path))
    except Exception as exc:  # pynrrd raises several types for a broken file
        raise InputError(f"{path}: not a readable NRRD file ({type(exc).__name__}: {exc})") from None
    kinds = [str(k).lower() for k in header.get("kinds", ["domain"] * data.ndim)]
    spatial = [i for i, k in enumerate(kinds) if k in ("domain", "space")]
    if len(spatial) != 3:
        raise InputError(f"{path}: expected 3 spatial axes (kinds 'domain'/'space'), got kinds {kinds}")
    if data.ndim == 4:
        layer_axis = next(i for i in range(4) if i not in spatial)
        layers = np.moveaxis(data, layer_axis, 0)
    elif data.ndim == 3:
        layers = data[None]
    else:
        raise InputError(f"{path}: expected a 3-D label map or a 4-D stack of layers, got shape {data.shape}")
    if not np.issubdtype(layers.dtype, np.integer):
        if not np.all(np.isfinite(layers)) or not np.all(layers == np.round(layers)):
            raise InputError(f"{path}: expected integer labels, got non-integer values ({layers.dtype})")
        layers = layers.astype(np.int64)
    affine = _nrrd_affine(header, path, spatial)
    segments = _segments(header)
    notes: list[str] = []
    if not segments:                                        # a plain label map: its values, unnamed
        if layers.shape[0] != 1:
            raise InputError(f"{path}: {layers.shape[0]} layers but no Segment<N>_* fields naming them")
        labels = layers[0].astype(np.int32)
        return LabelMap(labels, affine, {}, path, notes)
    labels = np.zeros(layers.shape[1:], dtype=np.int32)
    names = {}
    for n, seg in enumerate(segments):
        if not 0 <= seg["layer"] < layers.shape[0]:
            raise InputError(f"{path}: Segment{n}_Layer = {seg['layer']} but the file has {layers.shape[0]} layer(s)")
        inside = layers[seg["layer"]] == seg["value"]
        overlap = int(np.count_nonzero(inside & (labels != 0)))
        if overlap:
            notes.append(f"{path.name}: segment {seg['name']!r} overlaps earlier segments in {overlap} voxels "
                         "(it takes them)")
        labels[inside] = n + 1
        names[n + 1] = seg["name"]
    return LabelMap(labels, affine, names, path, notes)


def read_itksnap_descriptions(path) -> dict[int, str]:
    """Label value → name from an ITK-SNAP label description file (``IDX R G B A VIS MSH "LABEL"``)."""
    path = Path(path)
    try:
        text = path.read_text(errors="replace")
    except OSError as exc:
        raise InputError(f"{path}: cannot read the label description file ({exc.strerror})") from None
    names = {}
    for i, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        m = re.match(r'^(\d+)\s+(?:[-\d.]+\s+){6}"(.*)"\s*$', line)
        if m is None:
            raise InputError(f"{path}:{i}: expected 'IDX R G B A VIS MSH \"LABEL\"' (ITK-SNAP label description), "
                             f"got {line!r}")
        names[int(m.group(1))] = m.group(2).strip()
    if not names:
        raise InputError(f"{path}: no labels in this label description file")
    return names


def read_label_map(path, *, descriptions=None) -> LabelMap:
    """Read a label map with its names.

    Parameters
    ----------
    path : path-like
        ``.seg.nrrd`` / ``.nrrd`` (Slicer or any NRRD label map), or NIfTI.
    descriptions : path-like, optional
        ITK-SNAP label description file naming the values of a NIfTI (or NRRD) label map.

    Returns
    -------
    LabelMap
    """
    path = Path(path)
    if is_nrrd(path):
        lm = _read_nrrd(path)
    else:
        from pixmuscle.imaging.nifti import load_volume

        vol = load_volume(path, kind="labels")
        lm = LabelMap(np.asarray(vol.data, dtype=np.int32), vol.affine, {}, path)
    if descriptions is not None:
        lm.names = {v: n for v, n in read_itksnap_descriptions(descriptions).items() if v != 0}
    return lm


def write_seg_nrrd(path, labels, affine_cm, names: Mapping[int, str], *, colors: Mapping[int, tuple] | None = None) -> Path:
    """Write a label map as a 3D Slicer segmentation (one layer, ``.seg.nrrd``), atomically.

    Parameters
    ----------
    path : path-like
        Destination, ending in ``.seg.nrrd``.
    labels : ndarray of int, shape (I, J, K)
        0 background, other values the segments of ``names``.
    affine_cm : (4, 4) array
        Voxel index → RAS world position, cm (written in LPS, mm, as Slicer writes).
    names : mapping of int → str
        Label value → segment name; every non-zero value present must have one.
    colors : mapping of int → (r, g, b) in [0, 1], optional

    Returns
    -------
    Path
    """
    nrrd = _nrrd()
    path = Path(path)
    labels = np.asarray(labels)
    present = {int(v) for v in np.unique(labels) if v != 0}
    if present - set(names):
        raise InputError(f"write_seg_nrrd: label values {sorted(present - set(names))} have no name")
    a = np.asarray(affine_cm, float)
    header = {
        "type": "unsigned char" if labels.max(initial=0) < 256 else "unsigned short",
        "dimension": 3, "space": "left-posterior-superior", "kinds": ["domain"] * 3,
        "space directions": (_LPS_TO_RAS @ a[:3, :3] * 10.0).T, "space origin": _LPS_TO_RAS @ a[:3, 3] * 10.0,
        "encoding": "gzip", "Segmentation_MasterRepresentation": "Binary labelmap",
        "Segmentation_ContainedRepresentationNames": "Binary labelmap|",
    }
    cmap = colors or {}
    for n, (value, name) in enumerate(sorted(names.items())):
        r, g, b = cmap.get(value, (0.5, 0.5, 0.5))
        ext = np.argwhere(labels == value)
        extent = " ".join(f"{lo} {hi}" for lo, hi in zip(ext.min(0), ext.max(0), strict=True)) if ext.size else "0 -1 0 -1 0 -1"
        header.update({f"Segment{n}_ID": f"Segment_{value}", f"Segment{n}_Name": name,
                       f"Segment{n}_LabelValue": str(value), f"Segment{n}_Layer": "0",
                       f"Segment{n}_Color": f"{r:.4f} {g:.4f} {b:.4f}", f"Segment{n}_Extent": extent,
                       f"Segment{n}_NameAutoGenerated": "0", f"Segment{n}_ColorAutoGenerated": "0"})
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.tmp.nrrd")
    dtype = np.uint8 if header["type"] == "unsigned char" else np.uint16
    try:
        nrrd.write(str(tmp), labels.astype(dtype), header, index_order="F")
        os.replace(tmp, path)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise OutputError(f"{path}: cannot write ({exc.strerror})") from None
    return path

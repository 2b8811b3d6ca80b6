"""``segmentation.h5`` (schema ``pixmuscle.segmentation`` v1): the one writer and reader.

Written by the segment stage, read by the build-model stage and the report's segmentation QC.
Layout: ``/labels`` (I,J,K) int16 tissue codes, ``/muscle_id`` (I,J,K) int16, ``/muscle_names``
(M,) str, ``/fiber`` (I,J,K,3) float32, ``/affine`` (4,4) voxel → cm, ``/qc/*`` diagnostics and
``/masks/<name>`` (I,J,K) uint8 node-set masks.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..store import open_stage, read_strings, write_dataset, write_stage

SCHEMA = "pixmuscle.segmentation"
VERSION = 1

__all__ = ["SCHEMA", "VERSION", "read_segmentation", "write_segmentation"]


def write_segmentation(path, res, affine, *, config=None, inputs=(), attrs=None, masks=None):
    """Write a :class:`pixmuscle.segmentation.volume.SegmentationResult` as ``pixmuscle.segmentation`` v1 (atomic).

    Layout: ``/labels`` (I,J,K) int16, ``/muscle_id`` (I,J,K) int16, ``/muscle_names`` (M,) str,
    ``/fiber`` (I,J,K,3) float32, ``/affine`` (4,4) cm, ``/qc/*`` diagnostics, and
    ``/masks/<name>`` (I,J,K) uint8 for each of ``masks`` (name → bool array; the build-model stage
    turns each into a node set of that name).
    """
    affine = np.asarray(affine, dtype=float)

    def write(f):
        write_dataset(f, "labels", res.labels.astype(np.int16),
                      codes="0 background, 1 muscle, 2 connective_tissue, 3 fat, 4 bone")
        write_dataset(f, "muscle_id", res.muscle_id.astype(np.int16))
        write_dataset(f, "muscle_names", np.array(res.muscle_names, dtype=str))
        write_dataset(f, "fiber", res.fiber.astype(np.float32), units="1",
                      sign="canonical: v_z >= 0 (ties: v_y > 0, then v_x > 0)")
        write_dataset(f, "affine", affine, units="cm")
        if masks:
            g = f.create_group("masks")
            for name, m in masks.items():
                write_dataset(g, name, np.asarray(m, bool).astype(np.uint8))
        qc = f.create_group("qc")
        for key, val in res.qc.items():
            if key == "seed_voxels_ijk":
                g = qc.create_group(key)
                for name, pts in zip(res.muscle_names, val, strict=True):
                    write_dataset(g, name, np.asarray(pts, dtype=np.int64))
            elif key == "shared_regions":
                qc.attrs[key] = repr([[res.muscle_names[m - 1] for m in grp] for grp in val])
            elif np.ndim(val) == 0:
                qc.attrs[key] = val
            else:
                write_dataset(qc, key, np.asarray(val))

    return write_stage(path, schema=SCHEMA, version=VERSION, write=write, config=config,
                       inputs=inputs, units={"length": "cm"}, attrs=attrs)


def read_segmentation(path: str | Path) -> dict[str, Any]:
    """Read the arrays of a ``segmentation.h5`` (schema ``pixmuscle.segmentation`` v1).

    Returns
    -------
    dict
        ``labels`` (I, J, K) int, ``muscle_id`` (I, J, K) int or None, ``muscle_names`` list of
        str, ``fiber`` (I, J, K, 3) float or None, ``affine`` (4, 4) float (voxel → cm), ``masks``
        (name → (I, J, K) bool: node sets kept by the segment stage, e.g. ``aponeurosis``).
    """
    path = Path(path)
    with open_stage(path, schema=SCHEMA, version=VERSION) as f:
        missing = [k for k in ("labels", "affine") if k not in f]
        if missing:
            raise InputError(f"{path}: segmentation file lacks dataset(s) {', '.join('/' + k for k in missing)}")
        out = {
            "labels": f["labels"][()],
            "affine": np.asarray(f["affine"][()], dtype=float),
            "muscle_id": f["muscle_id"][()] if "muscle_id" in f else None,
            "muscle_names": read_strings(f["muscle_names"]) if "muscle_names" in f else [],
            "fiber": f["fiber"][()] if "fiber" in f else None,
            "masks": {k: f["masks"][k][()] != 0 for k in f["masks"]} if "masks" in f else {},
        }
    if out["affine"].shape != (4, 4):
        raise InputError(f"{path}: /affine: expected a (4, 4) voxel → cm matrix, got shape {out['affine'].shape}")
    return out

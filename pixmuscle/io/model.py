"""Reader and writer of ``model.h5`` (schema ``pixmuscle.model`` v1; layout in docs/architecture.md).

The one place that knows the HDF5 layout of a :class:`~pixmuscle.model.model.Model`; the model
groups are also embedded in results files (:mod:`pixmuscle.io.results`).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..model.model import Model
from ..store import open_stage, read_strings, write_dataset, write_stage

SCHEMA = "pixmuscle.model"
VERSION = 1


def write_model_groups(f: Any, model: Model) -> None:
    """Write the model's groups (``nodes``, ``muscles``, ``grid``, ``sets``) into an open HDF5 file."""
    g = f.create_group("nodes")
    write_dataset(g, "X", model.X.astype(np.float64), units="cm")
    write_dataset(g, "ijk", model.ijk.astype(np.int32))
    write_dataset(g, "tissue", model.tissue.astype(np.int8), codes="1 muscle, 2 connective_tissue, 3 fat")
    write_dataset(g, "muscle_id", model.muscle_id.astype(np.int16))
    write_dataset(g, "fiber", model.fiber.astype(np.float64), units="1")
    m = f.create_group("muscles")
    write_dataset(m, "names", np.array(list(model.muscle_names), dtype=object).astype(str) if model.muscle_names else np.array([], dtype="S1"))
    gr = f.create_group("grid")
    write_dataset(gr, "spacing", np.asarray(model.spacing, float), units="cm")
    write_dataset(gr, "origin", np.asarray(model.origin, float), units="cm")
    write_dataset(gr, "shape", np.asarray(model.shape, np.int64))
    write_dataset(gr, "rotation", np.asarray(model.rotation, float))
    if model.bone_ijk is not None:
        write_dataset(gr, "bone_ijk", np.asarray(model.bone_ijk, np.int32).reshape(-1, 3))
    s = f.create_group("sets")
    for name, idx in model.sets.items():
        write_dataset(s, name, np.asarray(idx, np.int64))
    f.attrs["coarsen_factor"] = int(model.coarsen_factor)


#: datasets (and groups) every model has; ``muscles/names`` and ``grid/bone_ijk`` are optional
REQUIRED_DATASETS = ("nodes/X", "nodes/ijk", "nodes/tissue", "nodes/muscle_id", "nodes/fiber", "grid/spacing",
                     "grid/origin", "grid/shape", "grid/rotation", "sets")


def read_model_groups(f: Any) -> Model:
    """Read a :class:`Model` from the groups of an open HDF5 file (model or results file).

    Raises
    ------
    InputError
        A required dataset is missing (the message names it and the file).
    """
    missing = [k for k in REQUIRED_DATASETS if k not in f]
    if missing:
        raise InputError(f"{f.filename}: dataset '/{missing[0]}' is missing (a pixmuscle.model v1 file has "
                         f"{', '.join('/' + k for k in REQUIRED_DATASETS)}); rebuild it with build-model")
    n = f["nodes"]
    names = read_strings(f["muscles/names"]) if "muscles/names" in f else []
    return Model(
        X=n["X"][()], ijk=n["ijk"][()], tissue=n["tissue"][()], muscle_id=n["muscle_id"][()],
        fiber=n["fiber"][()], muscle_names=names,
        spacing=f["grid/spacing"][()], origin=f["grid/origin"][()], shape=f["grid/shape"][()],
        rotation=f["grid/rotation"][()], sets={k: v[()] for k, v in f["sets"].items()},
        coarsen_factor=int(f.attrs.get("coarsen_factor", 1)),
        bone_ijk=f["grid/bone_ijk"][()] if "grid/bone_ijk" in f else None,
    )


def save_model(path: str | Path, model: Model, *, config: Any = None, inputs: Sequence[str | Path] = (),
               attrs: dict | None = None) -> Path:
    """Write ``model.h5`` atomically (schema ``pixmuscle.model`` v1); ``attrs``: more root attributes."""
    return write_stage(path, schema=SCHEMA, version=VERSION, write=lambda f: write_model_groups(f, model),
                       config=config, inputs=inputs, attrs=attrs)


def load_model(path: str | Path) -> Model:
    """Read ``model.h5``; raises SchemaError for another schema or version."""
    with open_stage(path, schema=SCHEMA, version=VERSION) as f:
        return read_model_groups(f)

"""``force_length_<model>.h5`` (schema ``pixmuscle.force_length`` v1): the one writer and reader.

Written by the force–length stage (:mod:`pixmuscle.stages.force_length`), read by the report.
Datasets (m,) per length change: ``delta``, ``length`` (cm), ``stretch`` (1), ``total``,
``passive``, ``active`` = total − passive, ``fibre_law`` (N); attributes ``L0_cm``, ``nodes``,
``component`` and ``activation``, ``force_sets``, ``runs`` (JSON).
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..store import open_stage, write_dataset, write_stage

SCHEMA = "pixmuscle.force_length"
VERSION = 1

__all__ = ["SCHEMA", "VERSION", "load_force_length", "write_force_length"]


def write_force_length(path, *, delta, L0: float, total, passive, fibre_law, attrs: Mapping[str, Any],
                       config: Any = None, inputs: Sequence = ()) -> Path:
    """Write a force–length curve (atomic): length changes ``delta`` (m,) cm from ``L0`` cm, forces (m,) N."""
    delta = np.asarray(delta, float)
    total, passive = np.asarray(total, float), np.asarray(passive, float)

    def write(f):
        write_dataset(f, "delta", delta, units="cm")
        write_dataset(f, "length", L0 + delta, units="cm")
        write_dataset(f, "stretch", (L0 + delta) / L0, units="1")
        write_dataset(f, "total", total, units="N")
        write_dataset(f, "passive", passive, units="N")
        write_dataset(f, "active", total - passive, units="N")
        write_dataset(f, "fibre_law", fibre_law, units="N")

    write_stage(path, schema=SCHEMA, version=VERSION, write=write, config=config, inputs=inputs, attrs=attrs)
    return Path(path)


def load_force_length(path) -> dict:
    """Read ``force_length_<model>.h5``: arrays and decoded attributes."""
    with open_stage(path, schema=SCHEMA, version=VERSION) as f:
        out = {k: f[k][()] for k in ("delta", "length", "stretch", "total", "passive", "active", "fibre_law")}
        out.update(L0_cm=float(f.attrs["L0_cm"]), nodes=str(f.attrs["nodes"]), component=str(f.attrs["component"]),
                   activation=json.loads(f.attrs["activation"]), force_sets=json.loads(f.attrs["force_sets"]),
                   runs=json.loads(f.attrs["runs"]))
    return out

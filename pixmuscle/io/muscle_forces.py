"""``muscle_forces_<model>.h5`` (schema ``pixmuscle.muscle_forces`` v1): the one writer and reader.

Written by the muscle-forces stage (:mod:`pixmuscle.stages.muscle_forces`), read by the report.
Layout: ``/steps/alpha``, ``/steps/load_factor`` (n,); ``/force/total``, ``/force/baseline``,
``/force/alone/<muscle>``, ``/contribution/<muscle>``, ``/interaction`` (n,) in N; attributes
``muscles``, ``force_sets``, ``runs`` (JSON) and ``method``.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..store import open_stage, write_dataset, write_stage

SCHEMA = "pixmuscle.muscle_forces"
VERSION = 1

__all__ = ["SCHEMA", "VERSION", "load_muscle_forces", "write_muscle_forces"]


def write_muscle_forces(path, *, alpha, load_factor, total, baseline, alone: Mapping[str, np.ndarray],
                        contribution: Mapping[str, np.ndarray], interaction, attrs: Mapping[str, Any],
                        config: Any = None, inputs: Sequence = ()) -> Path:
    """Write the per-muscle force decomposition (atomic); arrays (n,) per load step, forces in N.

    ``alone`` and ``contribution`` map muscle name → force; ``attrs`` are the stage attributes
    (``force_sets``, ``runs`` as JSON, ``method``, lineage); ``muscles`` is added here.
    """

    def write(f):
        st = f.create_group("steps")
        write_dataset(st, "alpha", alpha, units="1")
        write_dataset(st, "load_factor", load_factor, units="1")
        fo = f.create_group("force")
        write_dataset(fo, "total", total, units="N")
        write_dataset(fo, "baseline", baseline, units="N")
        al = fo.create_group("alone")
        co = f.create_group("contribution")
        for name in alone:
            write_dataset(al, name, alone[name], units="N")
            write_dataset(co, name, contribution[name], units="N")
        write_dataset(f, "interaction", interaction, units="N")

    attrs = {"muscles": json.dumps(list(alone)), **attrs}
    write_stage(path, schema=SCHEMA, version=VERSION, write=write, config=config, inputs=inputs, attrs=attrs)
    return Path(path)


def load_muscle_forces(path) -> dict:
    """Read ``muscle_forces_<model>.h5``: the datasets as arrays, attrs decoded."""
    with open_stage(path, schema=SCHEMA, version=VERSION) as f:
        muscles = json.loads(f.attrs["muscles"])
        return {
            "alpha": f["steps/alpha"][()], "load_factor": f["steps/load_factor"][()],
            "total": f["force/total"][()], "baseline": f["force/baseline"][()],
            "alone": {m: f[f"force/alone/{m}"][()] for m in muscles},
            "contribution": {m: f[f"contribution/{m}"][()] for m in muscles},
            "interaction": f["interaction"][()], "muscles": muscles,
            "force_sets": json.loads(f.attrs["force_sets"]), "runs": json.loads(f.attrs["runs"]),
            "method": str(f.attrs["method"]),
        }

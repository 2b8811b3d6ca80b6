"""The one reader and writer of a solve's checkpoint (schema ``pixmuscle.checkpoint`` v1).

A solve writes its converged load steps as it goes to ``<results>.checkpoint`` beside its results
file (``results_coarse.h5.checkpoint``), rewritten atomically after every converged step
(:func:`pixmuscle.store.write_stage`): a kill at any moment leaves either the previous checkpoint
or the new one. Running the same command again resumes after the last converged step
(:func:`pixmuscle.stages.solve.run_solve`); the checkpoint is removed once the results file is
written. Layout:

``/steps/step``, ``t``, ``alpha`` (k+1,)
    step number, load factor and activation (ramp parameter) of each converged step;
``/steps/state_t``, ``state_alpha`` (k+1,)
    load factor and α at which the converged state was evaluated (they differ from ``t``, ``alpha``
    by round-off after cutbacks);
``/steps/iterations``, ``cutbacks`` (k+1,); ``/steps/d`` (k+1, N, 3) cm
    Newton iterations, cutbacks and RK coefficients of each step;
``/increment/d`` (N, 3) cm, ``/increment/dt``
    the last converged load increment (the predictor of the next one extrapolates it); absent
    before the first increment;
``/newton/<column>``
    Newton log rows of the converged steps (columns of :data:`pixmuscle.mechanics.results.NEWTON_COLUMNS`);
``/solver/d`` (N, 3) cm, ``t``, ``alpha``, ``pressure`` (N_p,) N/cm² where Newton carried one, attributes ``counters`` (JSON) and ``backend``
    the linear solver's memory after the last step (:class:`~pixmuscle.mechanics.linsolve.SolverMemory`):
    the state whose tangent its preconditioner or factors were built from, and its rebuild rule's
    counters; a resumed solve rebuilds them there and decides as the uninterrupted one. Absent for
    a backend that keeps nothing.

Root attribute ``key``: :func:`checkpoint_key` of the model file, the ``solve`` section and the
package version. A checkpoint whose key differs belongs to another model or configuration and is
never used.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from .. import __version__
from ..errors import InputError
from ..mechanics.linsolve.base import SolverMemory
from ..mechanics.newton import NewtonRow, SavedState, StepRecord
from ..mechanics.results import NEWTON_COLUMNS
from ..store import config_hash, open_stage, sha256_file, write_stage

SCHEMA = "pixmuscle.checkpoint"
VERSION = 1
SUFFIX = ".checkpoint"

_STEP_COLUMNS = ("step", "t", "alpha", "state_t", "state_alpha", "iterations", "cutbacks")


@dataclasses.dataclass
class Checkpoint:
    """Converged steps 0..k of a solve and the key of the model and configuration that made them."""

    key: str
    n_steps: int
    records: list  # StepRecord with SavedState states


def checkpoint_path(results_path: str | Path) -> Path:
    """The checkpoint file of a results file: ``<results>.checkpoint`` in the same folder."""
    p = Path(results_path)
    return p.with_name(p.name + SUFFIX)


def checkpoint_key(config, inputs: Sequence[str | Path]) -> str:
    """SHA-256 of the ``solve`` section, the SHA-256 of every input file (model, activation image)
    and the package version: what must not change for a checkpoint to be resumed."""
    text = json.dumps({"config": config_hash(config), "inputs": [sha256_file(p) for p in inputs],
                       "version": __version__}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()


def save_checkpoint(path: str | Path, records: Sequence[StepRecord], *, key: str, n_steps: int) -> Path:
    """Write the converged steps ``records`` (0..k, in order) atomically.

    Parameters
    ----------
    path : path-like
        Usually :func:`checkpoint_path` of the results file.
    records : sequence of StepRecord
        States need ``d`` (N, 3) cm, ``t`` and ``alpha``; the last one's ``increment`` is kept.
    key : str
        :func:`checkpoint_key`.
    n_steps : int
        Planned load steps S.

    Raises
    ------
    OutputError
        The file system refused the write.
    """
    def write(f):
        st = f.create_group("steps")
        cols = {
            "step": [r.step for r in records], "t": [r.t for r in records], "alpha": [r.alpha for r in records],
            "state_t": [r.state.t for r in records], "state_alpha": [r.state.alpha for r in records],
            "iterations": [r.iterations for r in records], "cutbacks": [r.cutbacks for r in records],
        }
        for name, v in cols.items():
            st.create_dataset(name, data=np.asarray(v, np.int64 if name in ("step", "iterations", "cutbacks") else float))
        d = st.create_dataset("d", shape=(len(records), *np.shape(records[0].state.d)), dtype=float)
        for i, r in enumerate(records):  # row by row: no (S, N, 3) copy of the records' d
            d[i] = np.asarray(r.state.d, float)
        inc = records[-1].increment if records else None
        if inc is not None:
            g = f.create_group("increment")
            g.create_dataset("d", data=np.asarray(inc[0], float))
            g.create_dataset("dt", data=float(inc[1]))
        mem = records[-1].solver if records else None
        if mem is not None:
            g = f.create_group("solver")
            g.create_dataset("d", data=np.asarray(mem.d, float))
            g.create_dataset("t", data=float(mem.t))
            g.create_dataset("alpha", data=float(mem.alpha))
            g.attrs["counters"] = json.dumps({k: float(v) for k, v in mem.counters.items()})
            g.attrs["backend"] = mem.backend
            if mem.pressure is not None:
                g.create_dataset("pressure", data=np.asarray(mem.pressure, float))
        rows = [row for r in records for row in r.rows]
        ng = f.create_group("newton")
        for c in NEWTON_COLUMNS:
            ng.create_dataset(c, data=np.array([getattr(row, c) for row in rows],
                                               np.int64 if c in ("step", "iteration") else float))

    return write_stage(path, schema=SCHEMA, version=VERSION, write=write,
                       attrs={"key": key, "n_steps_planned": int(n_steps), "converged_steps": len(records)})


def load_checkpoint(path: str | Path) -> Checkpoint:
    """Read a checkpoint written by :func:`save_checkpoint`.

    Raises
    ------
    InputError
        Missing or unreadable file, or missing or inconsistent datasets (the message names them).
    SchemaError
        Not a checkpoint file.
    """
    path = Path(path)
    with open_stage(path, schema=SCHEMA, version=VERSION) as f:
        try:
            st = f["steps"]
            cols = {c: np.asarray(st[c][()]) for c in _STEP_COLUMNS}
            d = np.asarray(st["d"][()], float)
            newton = {c: np.asarray(f["newton"][c][()]) for c in NEWTON_COLUMNS}
            inc = (np.asarray(f["increment/d"][()], float), float(f["increment/dt"][()])) if "increment" in f else None
            mem = None
            if "solver" in f:
                g = f["solver"]
                mem = SolverMemory(d=np.asarray(g["d"][()], float), t=float(g["t"][()]), alpha=float(g["alpha"][()]),
                                   counters=json.loads(g.attrs["counters"]), backend=str(g.attrs["backend"]),
                                   pressure=np.asarray(g["pressure"][()], float) if "pressure" in g else None)
            key = f.attrs["key"]
            n_steps = int(f.attrs["n_steps_planned"])
        except (KeyError, ValueError) as exc:
            raise InputError(f"{path}: incomplete checkpoint ({exc})") from None
    key = key.decode() if isinstance(key, bytes) else str(key)
    n = cols["step"].shape[0]
    if d.ndim != 3 or d.shape[0] != n or d.shape[2] != 3 or any(v.shape != (n,) for v in cols.values()):
        raise InputError(f"{path}: /steps/d has shape {d.shape}, expected ({n}, N, 3) like /steps/step")
    if not np.array_equal(cols["step"], np.arange(n)):
        raise InputError(f"{path}: /steps/step is {cols['step'].tolist()}, expected 0..{n - 1}")
    records = []
    for i in range(n):
        sel = newton["step"] == i
        rows = [NewtonRow(**{c: (int if c in ("step", "iteration") else float)(newton[c][j]) for c in NEWTON_COLUMNS})
                for j in np.flatnonzero(sel)]
        state = SavedState(d=d[i], t=float(cols["state_t"][i]), alpha=float(cols["state_alpha"][i]))
        records.append(StepRecord(step=i, t=float(cols["t"][i]), alpha=float(cols["alpha"][i]), state=state,
                                  iterations=int(cols["iterations"][i]), cutbacks=int(cols["cutbacks"][i]), rows=rows,
                                  increment=inc if i == n - 1 else None, solver=mem if i == n - 1 else None))
    return Checkpoint(key=key, n_steps=n_steps, records=records)

"""The one reader and writer of ``results.h5`` (schema ``pixmuscle.results`` v1).

:func:`save_results` writes a :class:`~pixmuscle.mechanics.results.Results` atomically through
:func:`pixmuscle.store.write_stage`; :func:`load_results` reads it back into the same structure
(the solver's tests, the report and the cohort table all use it). Per-step fields
(``(S+1, N, ...)``: displacement, RK coefficients, stresses) are large: by default they are read
lazily, one state at a time, through :class:`StepArray` (``res.u[k]``, ``res.step(k)``).
Layout: :mod:`pixmuscle.mechanics.results` and docs/architecture.md.
"""

from __future__ import annotations

import json
import logging
import shutil
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from ..errors import InputError, OutputError
from ..mechanics.results import NEWTON_COLUMNS, NodeEllipticity, Results
from ..model.tissues import NODE_TISSUES
from ..store import open_stage, temporary_path, write_dataset, write_stage
from .model import read_model_groups, write_model_groups

_LOG = logging.getLogger(__name__)
#: free space a step store keeps beside twice a step's arrays before it writes them (HDF5's metadata), bytes
STORE_SLACK_BYTES = 1 << 20

SCHEMA = "pixmuscle.results"
VERSION = 1

_STRESS_UNITS = {"N/cm^2", "N/cm2", "N/cm²", "N cm^-2"}
_NEWTON_UNITS = {"residual_norm": "N", "energy_norm": "N*cm", "load_factor": "1", "relative_residual": "1",
                 "line_search": "1"}
#: root attributes that have their own field in Results (everything else goes to meta["attrs"])
_KNOWN_ATTRS = {"schema", "schema_version", "units", "config", "provenance", "status", "sign_convention",
                "n_steps_planned", "solver_info", "constraint_gap", "warnings", "stage", "stages", "synthetic",
                "coarsen_factor"}


class StepArray:
    """A per-step dataset of a results file, read one state at a time.

    ``a[k]`` reads state ``k`` (numpy array); ``np.asarray(a)`` reads everything. The file is
    opened for each read, so the object stays valid after the reader returned.
    """

    def __init__(self, path: Path, name: str, shape: tuple, dtype):
        self.path, self.name, self.shape, self.dtype = Path(path), name, tuple(shape), np.dtype(dtype)

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, key):
        with open_stage(self.path, schema=SCHEMA, version=VERSION) as f:
            return np.asarray(f[self.name][key])

    def __array__(self, dtype=None, copy=None):
        a = self[()]
        return a if dtype is None else a.astype(dtype)

    def __repr__(self) -> str:
        return f"StepArray({self.path.name}:{self.name}, shape={self.shape})"


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, Mapping):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def _text(v) -> str:
    if isinstance(v, bytes):
        return v.decode()
    if isinstance(v, np.ndarray):
        return json.dumps(v.tolist())
    if isinstance(v, np.generic):
        return str(v.item())
    return str(v)


def _json_attr(attrs, key: str, default):
    raw = attrs.get(key)
    if raw is None:
        return default
    try:
        return json.loads(_text(raw))
    except json.JSONDecodeError:
        return default


class StepStore:
    """The nodal fields of a running solve's converged steps, on disk until the results are made.

    A solve that is given a store appends each step's ``u``, ``cauchy`` and ``max_principal`` to it
    as soon as the step has converged (:func:`pixmuscle.mechanics.solve.solve`), so that the
    memory a sweep holds does not grow with its load steps by 10 float64 per node and step
    (0.24 GB over the 11 states of a 295k-node sweep). One HDF5 file, a hidden temporary beside the
    results file (:func:`pixmuscle.store.temporary_path`: one a killed run leaves is removed by the
    next write of the results), one dataset per field with a row per step. Where the disk has no room
    for a step (twice its arrays and :data:`STORE_SLACK_BYTES`) or the file cannot be written, the
    steps stored so far are read back, the file is removed and the store keeps every step in memory
    from then on, with a warning: the solve goes on, and only the results file's own write can then
    fail, with its own message.

    Parameters
    ----------
    results_path : path-like
        The results file the steps are for.
    """

    def __init__(self, results_path: str | Path):
        self.path = temporary_path(results_path, "steps")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.rows = 0
        self._memory: list[dict] | None = None  # the steps, once the file could not take them
        try:
            with h5py.File(self.path, "w"):
                pass
        except (OSError, RuntimeError) as exc:
            self._to_memory(exc)

    def append(self, fields: Mapping[str, np.ndarray]) -> None:
        """Store one step's arrays (the same names and shapes at every step), float64."""
        fields = {name: np.asarray(value, float) for name, value in fields.items()}
        need = 2 * sum(v.nbytes for v in fields.values()) + STORE_SLACK_BYTES
        if self._memory is None and shutil.disk_usage(self.path.parent).free < need:
            # not left to HDF5 to find out: its error paths on a full disk are not safe to go on from
            self._to_memory(f"not enough free disk space for a step: {need / 1e6:.1f} MB needed")
        if self._memory is None:
            try:
                with h5py.File(self.path, "a") as f:
                    for name, value in fields.items():
                        if name not in f:
                            f.create_dataset(name, shape=(0, *value.shape), maxshape=(None, *value.shape),
                                             chunks=(1, *value.shape), dtype=float)
                        ds = f[name]
                        ds.resize(self.rows + 1, axis=0)
                        ds[self.rows] = value
            except (OSError, RuntimeError) as exc:
                self._to_memory(exc)
        if self._memory is not None:
            self._memory.append(fields)
        self.rows += 1

    def _to_memory(self, exc: Exception | str) -> None:
        """Take the rows stored so far into memory and remove the file (it could not be written)."""
        kept = []
        if self.rows:
            try:
                with h5py.File(self.path, "r") as f:
                    kept = [{name: np.asarray(f[name][i]) for name in f} for i in range(self.rows)]
            except (OSError, RuntimeError) as err:
                raise OutputError(f"{self.path}: the solve's step store could not be written ({exc}) nor read "
                                  f"back ({err}); the converged steps are in the checkpoint: free some space and "
                                  "run the same command again") from err
        self.remove()
        self._memory = kept
        _LOG.warning("the solve's step store %s could not be written (%s); the steps' nodal fields are kept in "
                     "memory instead", self.path, exc)

    def read(self, name: str) -> np.ndarray:
        """Every stored step's ``name``, stacked: (S, ...)."""
        if self._memory is not None:
            return np.stack([step[name] for step in self._memory])
        with h5py.File(self.path, "r") as f:
            return np.asarray(f[name][()])

    def remove(self) -> None:
        self.path.unlink(missing_ok=True)


def write_results_groups(f, res: Results) -> None:
    """Write the groups of a results file into an open HDF5 file."""
    write_model_groups(f, res.model)
    st = f.create_group("steps")
    write_dataset(st, "alpha", res.alpha, units="1")
    write_dataset(st, "load_factor", res.load_factor, units="1")
    write_dataset(st, "converged", res.converged)
    write_dataset(st, "iterations", res.iterations)
    write_dataset(st, "cutbacks", res.cutbacks)
    write_dataset(st, "u", np.asarray(res.u), units="cm", description="u(X_I) = sum_J Psi_J(X_I) d_J at the nodes")
    if res.d is not None:
        write_dataset(st, "d", np.asarray(res.d), units="cm", description="RK coefficients d_J")
    if res.cauchy is not None:
        write_dataset(st, "cauchy", np.asarray(res.cauchy), units="N/cm^2", order="xx yy zz xy yz xz")
    if res.max_principal is not None:
        write_dataset(st, "max_principal", np.asarray(res.max_principal), units="N/cm^2")
    rg = st.create_group("reaction")
    for k, v in res.reaction.items():
        write_dataset(rg, k, v, units="N", description="force the support exerts on the body")
    pg = st.create_group("prescribed")
    constrained = res.constrained_text()
    for k, v in res.prescribed.items():
        write_dataset(pg, k, v, units="cm", constrained=constrained.get(k, ""))
    ell = res.ellipticity
    if ell is not None:
        eg = f.create_group("ellipticity")
        write_dataset(eg, "acoustic_minimum", np.asarray(ell.minimum, float), units="N/cm^2",
                      description="smallest acoustic-tensor eigenvalue of the material law; not strongly "
                                  "elliptic where < 0", step=int(ell.step), n_directions=int(ell.n_directions))
    ng = f.create_group("newton")
    for c in NEWTON_COLUMNS:
        if c in res.newton:
            write_dataset(ng, c, res.newton[c], units=_NEWTON_UNITS.get(c))


def save_results(path: str | Path, res: Results, *, config: Any = None, inputs: Sequence[str | Path] = (),
                 attrs: Mapping[str, Any] | None = None) -> Path:
    """Write ``results.h5`` atomically (schema ``pixmuscle.results`` v1).

    Parameters
    ----------
    path : path-like
    res : Results
    config : SolveConfig or mapping, optional
        Stored as the ``config`` attribute.
    inputs : sequence of path-like
        Input files (their SHA-256 go into the provenance).
    attrs : mapping, optional
        More root attributes (the stage records of :func:`pixmuscle.io.lineage.stage_attrs`).
        ``warnings`` given here are merged with ``res.warnings``.
    """
    extra = dict(attrs or {})
    warnings = list(res.warnings) + [w for w in json.loads(extra.pop("warnings", "[]")) if w not in res.warnings]
    root = {"status": res.status, "sign_convention": res.sign_convention, "n_steps_planned": int(res.n_steps_planned),
            "solver_info": json.dumps(_jsonable(res.info)), "warnings": json.dumps(warnings), **extra}
    if res.constraint_gap:
        root["constraint_gap"] = json.dumps(_jsonable(res.constraint_gap))
    return write_stage(path, schema=SCHEMA, version=VERSION, write=lambda f: write_results_groups(f, res),
                       config=config, inputs=inputs, attrs=root)


def _table(node) -> dict:
    """A table stored either as a group of column datasets or as one compound dataset."""
    if hasattr(node, "keys") and not hasattr(node, "dtype"):
        return {k: np.asarray(node[k][()]) for k in node.keys()}
    arr = node[()]
    if arr.dtype.names is None:
        raise InputError(f"{node.file.filename}: /newton: expected a table (group of columns or compound dataset)")
    return {k: np.asarray(arr[k]) for k in arr.dtype.names}


def _warning_list(raw) -> list[str]:
    if raw is None:
        return []
    text = _text(raw)
    if text.strip().startswith("["):
        try:
            return [str(w) for w in json.loads(text)]
        except json.JSONDecodeError:
            return [text]
    return [w for w in text.splitlines() if w.strip()]


def _ellipticity(f, name: str, n: int, s1: int) -> NodeEllipticity | None:
    """``/ellipticity`` of an open results file (None when the file has none: written before it was recorded)."""
    if "ellipticity/acoustic_minimum" not in f:
        return None
    ds = f["ellipticity/acoustic_minimum"]
    if ds.shape != (n,):
        raise InputError(f"{name}: /ellipticity/acoustic_minimum has shape {ds.shape}, expected ({n},) (N nodes)")
    if _text(ds.attrs.get("units", "N/cm^2")) not in _STRESS_UNITS:
        raise InputError(f"{name}: /ellipticity/acoustic_minimum has units {ds.attrs['units']!r}, expected 'N/cm^2'")
    step = int(ds.attrs.get("step", s1 - 1))
    if not 0 <= step < s1:
        raise InputError(f"{name}: /ellipticity/acoustic_minimum is of step {step}, the file stores states 0..{s1 - 1}")
    return NodeEllipticity(step=step, minimum=np.asarray(ds[()], float), n_directions=int(ds.attrs.get("n_directions", 0)))


def load_results(path: str | Path, *, lazy: bool = True) -> Results:
    """Read a ``pixmuscle.results`` v1 file into a :class:`Results`.

    Parameters
    ----------
    path : path-like
    lazy : bool
        Per-step fields as :class:`StepArray` (read on access) instead of numpy arrays.

    Raises
    ------
    InputError
        Missing file, wrong schema, missing datasets, or inconsistent shapes or units (the
        message names the file and the dataset).
    """
    path = Path(path)
    name = str(path)
    with open_stage(path, schema=SCHEMA, version=VERSION) as f:
        for req in ("nodes", "grid", "sets", "steps/alpha", "steps/load_factor", "steps/converged", "steps/iterations",
                    "steps/u"):
            if req not in f:
                raise InputError(f"{name}: missing /{req} (expected by schema {SCHEMA} v{VERSION})")
        model = read_model_groups(f)
        n = model.n_nodes
        units = _json_attr(f.attrs, "units", {})
        if units.get("length", "cm") != "cm" or units.get("force", "N") != "N":
            raise InputError(f"{name}: units {units} — expected length in cm and force in N")
        st = f["steps"]
        alpha = np.asarray(st["alpha"][()], float)
        s1 = alpha.shape[0]
        arrays = {}
        for key in ("load_factor", "converged", "iterations", "cutbacks"):
            if key in st:
                arrays[key] = np.asarray(st[key][()])
                if arrays[key].shape != (s1,):
                    raise InputError(f"{name}: /steps/{key} has shape {arrays[key].shape}, expected ({s1},) like /steps/alpha")
        fields = {}
        for key, tail in (("u", (n, 3)), ("d", (n, 3)), ("cauchy", (n, 6)), ("max_principal", (n,))):
            if key not in st:
                fields[key] = None
                continue
            ds = st[key]
            if ds.shape != (s1, *tail):
                raise InputError(f"{name}: /steps/{key} has shape {ds.shape}, expected {(s1, *tail)} (S+1 steps, N={n} nodes)")
            fields[key] = StepArray(path, f"steps/{key}", ds.shape, ds.dtype) if lazy else np.asarray(ds[()])
        if _text(st["u"].attrs.get("units", "cm")) != "cm":
            raise InputError(f"{name}: /steps/u has units {st['u'].attrs['units']!r}, expected 'cm'")
        if "cauchy" in st and _text(st["cauchy"].attrs.get("units", "N/cm^2")) not in _STRESS_UNITS:
            raise InputError(f"{name}: /steps/cauchy has units {st['cauchy'].attrs['units']!r}, expected 'N/cm^2'")
        reaction = {}
        for k, ds in (st["reaction"].items() if "reaction" in st else ()):
            r = np.asarray(ds[()], float)
            if r.shape != (s1, 3):
                raise InputError(f"{name}: /steps/reaction/{k} has shape {r.shape}, expected ({s1}, 3)")
            if _text(ds.attrs.get("units", "N")) != "N":
                raise InputError(f"{name}: /steps/reaction/{k} has units {ds.attrs['units']!r}, expected 'N'")
            reaction[k] = r
        prescribed, constrained = {}, {}
        for k, ds in (st["prescribed"].items() if "prescribed" in st else ()):
            prescribed[k] = np.asarray(ds[()], float)
            if "constrained" in ds.attrs:
                c = _text(ds.attrs["constrained"])
                constrained[k] = np.array([a in c for a in "xyz"])
        newton = _table(f["newton"]) if "newton" in f else {}
        ellipticity = _ellipticity(f, name, n, s1)
        a = f.attrs
        status = _text(a.get("status", "")).strip() or "unknown (no status attribute)"
        provenance = _json_attr(a, "provenance", {})
        stages = _json_attr(a, "stages", [])
        synthetic = _text(a.get("synthetic", "")).strip().lower() in ("1", "true", "yes") or bool(provenance.get("synthetic"))
        meta = {
            "path": path, "config": _text(a.get("config", "")), "provenance": provenance, "units": units,
            "stages": stages if isinstance(stages, list) else [], "synthetic": synthetic,
            "attrs": {k: _text(v) for k, v in a.items() if k not in _KNOWN_ATTRS},
        }
        res = Results(
            model=model, alpha=alpha, load_factor=np.asarray(arrays["load_factor"], float),
            converged=np.asarray(arrays["converged"], bool), iterations=np.asarray(arrays["iterations"], np.int64),
            cutbacks=np.asarray(arrays["cutbacks"], np.int64) if "cutbacks" in arrays else None,
            u=fields["u"], d=fields["d"], reaction=reaction, prescribed=prescribed, constrained=constrained,
            cauchy=fields["cauchy"], max_principal=fields["max_principal"], newton=newton, status=status,
            n_steps_planned=int(_json_attr(a, "n_steps_planned", 0) or 0), info=_json_attr(a, "solver_info", {}),
            sign_convention=_text(a.get("sign_convention", "")), constraint_gap=_json_attr(a, "constraint_gap", {}),
            warnings=_warning_list(a.get("warnings")), meta=meta, ellipticity=ellipticity,
        )
    if not np.isin(model.tissue, NODE_TISSUES).all():
        raise InputError(f"{name}: /nodes/tissue holds codes outside {NODE_TISSUES}")
    return res

"""Reading a results file (schema ``pixmuscle.results`` v1) for the report.

All reading of ``results.h5`` by the report goes through :func:`load_results`, so that switching
to :mod:`pixmuscle.mechanics.results` once it exists touches this one function. Per-step fields
(displacement and stress at every node, ``(S+1, N, ...)``) are large, so they are read one step at
a time through :attr:`ReportInput.fields`; everything else is read eagerly.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..model.model import Model, read_model_groups
from ..model.tissues import NODE_TISSUES
from ..store import open_stage

SCHEMA = "pixmuscle.results"
VERSION = 1

_STRESS_UNITS = {"N/cm^2", "N/cm2", "N/cm²", "N cm^-2"}


@dataclasses.dataclass
class StepFields:
    """Nodal fields of one load step.

    Attributes
    ----------
    u : (N, 3) float64
        Displacement at the nodes, cm.
    cauchy : (N, 6) float64 or None
        Cauchy stress, N/cm², Voigt order xx yy zz xy yz xz.
    max_principal : (N,) float64 or None
        Largest principal Cauchy stress, N/cm².
    """

    u: np.ndarray
    cauchy: np.ndarray | None
    max_principal: np.ndarray | None


@dataclasses.dataclass
class ReportInput:
    """Everything the report needs from one results file.

    Attributes
    ----------
    path : Path
        The results file.
    model : Model
        The pixel-point model the results belong to.
    alpha, load_factor : (S+1,) float64
        Activation and prescribed-displacement ramp at the end of each step (step 0 = initial).
    converged : (S+1,) bool
    iterations : (S+1,) int64
        Newton iterations of each step.
    reactions : dict of str → (S+1, 3) float64
        Force (N) the support of each constrained set exerts on the body.
    constrained : dict of str → str
        Constrained components of each set (e.g. ``"xyz"``, ``"xy"``) where the file records them
        (attribute ``constrained`` of ``/steps/prescribed/<set>``).
    newton : dict of str → (R,) arrays
        Newton log table: step, iteration, residual_norm, energy_norm, line_search (as present).
    cutbacks : (S+1,) int64 or None
        Step cutbacks per step when the solver recorded them.
    status : str
        ``"complete"`` or ``"failed: <message>"``.
    info : dict of str → str
        Other root attributes as text (sign convention, ...).
    config_yaml : str
        YAML of the solve config that produced the file.
    provenance : dict
    units : dict
    solver_warnings : list of str
        Warnings the solver stored in the file (root attribute ``warnings``).
    has_stress : bool
        Whether stress fields are available.
    fields : callable
        ``fields(step) -> StepFields``.
    """

    path: Path
    model: Model
    alpha: np.ndarray
    load_factor: np.ndarray
    converged: np.ndarray
    iterations: np.ndarray
    reactions: dict
    constrained: dict
    newton: dict
    cutbacks: np.ndarray | None
    status: str
    info: dict
    config_yaml: str
    provenance: dict
    units: dict
    solver_warnings: list
    has_stress: bool
    fields: Callable[[int], StepFields]

    @property
    def n_steps(self) -> int:
        """Number of stored states S+1 (including the initial state)."""
        return int(self.alpha.shape[0])

    @property
    def failed(self) -> bool:
        return self.status.lower().startswith("failed")

    @property
    def synthetic(self) -> bool:
        """True when the file says its inputs are synthetic phantoms."""
        flag = self.info.get("synthetic", "")
        return str(flag).strip().lower() in ("1", "true", "yes") or bool(self.provenance.get("synthetic", False))


def _text(v) -> str:
    if isinstance(v, bytes):
        return v.decode()
    if isinstance(v, np.ndarray):
        return json.dumps(v.tolist())
    if isinstance(v, np.generic):
        return str(v.item())
    return str(v)


def _table(node) -> dict:
    """A table stored either as a group of column datasets or as one compound dataset."""
    if hasattr(node, "keys") and not hasattr(node, "dtype"):
        return {k: np.asarray(node[k][()]) for k in node.keys()}
    arr = node[()]
    if arr.dtype.names is None:
        raise InputError(f"{node.file.filename}: /newton: expected a table (group of columns or compound dataset)")
    return {k: np.asarray(arr[k]) for k in arr.dtype.names}


def max_principal_from_voigt(cauchy: np.ndarray) -> np.ndarray:
    """Largest eigenvalue of symmetric tensors given in Voigt order xx yy zz xy yz xz.

    Parameters
    ----------
    cauchy : (N, 6) float64

    Returns
    -------
    (N,) float64
    """
    return np.linalg.eigvalsh(voigt_to_tensor(cauchy))[:, -1]


def voigt_to_tensor(v: np.ndarray) -> np.ndarray:
    """(N, 6) Voigt (xx yy zz xy yz xz) → (N, 3, 3) symmetric tensors."""
    xx, yy, zz, xy, yz, xz = np.moveaxis(np.asarray(v, float), -1, 0)
    return np.stack([np.stack([xx, xy, xz], -1), np.stack([xy, yy, yz], -1), np.stack([xz, yz, zz], -1)], -2)


def load_results(path: str | Path) -> ReportInput:
    """Read a ``pixmuscle.results`` v1 file (layout in docs/architecture.md).

    Raises
    ------
    InputError
        Missing file, wrong schema, missing datasets, or inconsistent shapes/units.
    """
    path = Path(path)
    name = str(path)
    with open_stage(path, schema=SCHEMA, version=VERSION) as f:
        for req in ("nodes", "grid", "sets", "steps/alpha", "steps/load_factor", "steps/converged", "steps/iterations", "steps/u"):
            if req not in f:
                raise InputError(f"{name}: missing /{req} (expected by schema {SCHEMA} v{VERSION})")
        model = read_model_groups(f)
        n = model.n_nodes
        units = json.loads(_text(f.attrs.get("units", "{}")) or "{}")
        if units.get("length", "cm") != "cm" or units.get("force", "N") != "N":
            raise InputError(f"{name}: units {units} — the report expects length in cm and force in N")
        st = f["steps"]
        alpha = np.asarray(st["alpha"][()], float)
        s1 = alpha.shape[0]
        arrays = {}
        for key in ("load_factor", "converged", "iterations"):
            arrays[key] = np.asarray(st[key][()])
            if arrays[key].shape != (s1,):
                raise InputError(f"{name}: /steps/{key} has shape {arrays[key].shape}, expected ({s1},) like /steps/alpha")
        for key, tail in (("u", (n, 3)), ("cauchy", (n, 6)), ("max_principal", (n,))):
            if key in st and st[key].shape != (s1, *tail):
                raise InputError(f"{name}: /steps/{key} has shape {st[key].shape}, expected {(s1, *tail)} (S+1 steps, N={n} nodes)")
        if st["u"].attrs.get("units", "cm") != "cm":
            raise InputError(f"{name}: /steps/u has units {st['u'].attrs['units']!r}, expected 'cm'")
        if "cauchy" in st and _text(st["cauchy"].attrs.get("units", "N/cm^2")) not in _STRESS_UNITS:
            raise InputError(f"{name}: /steps/cauchy has units {st['cauchy'].attrs['units']!r}, expected 'N/cm^2'")
        reactions = {}
        if "reaction" in st:
            for k, ds in st["reaction"].items():
                r = np.asarray(ds[()], float)
                if r.shape != (s1, 3):
                    raise InputError(f"{name}: /steps/reaction/{k} has shape {r.shape}, expected ({s1}, 3)")
                if _text(ds.attrs.get("units", "N")) != "N":
                    raise InputError(f"{name}: /steps/reaction/{k} has units {ds.attrs['units']!r}, expected 'N'")
                reactions[k] = r
        constrained = {}
        if "prescribed" in st:
            for k, ds in st["prescribed"].items():
                if "constrained" in ds.attrs:
                    constrained[k] = _text(ds.attrs["constrained"])
        newton = _table(f["newton"]) if "newton" in f else {}
        cutbacks = np.asarray(st["cutbacks"][()]) if "cutbacks" in st else None
        attrs = {k: _text(v) for k, v in f.attrs.items()}
        has_cauchy, has_mp = "cauchy" in st, "max_principal" in st
    status = attrs.pop("status", "").strip() or "unknown (no status attribute)"
    config_yaml = attrs.pop("config", "")
    provenance = json.loads(attrs.pop("provenance", "{}") or "{}")
    warns = attrs.pop("warnings", "")
    try:
        solver_warnings = [str(w) for w in json.loads(warns)] if warns.strip().startswith("[") else [w for w in warns.splitlines() if w.strip()]
    except json.JSONDecodeError:
        solver_warnings = [warns]
    for k in ("units", "schema", "schema_version", "coarsen_factor"):
        attrs.pop(k, None)
    if cutbacks is None and "cutbacks" in attrs:
        try:
            cutbacks = np.asarray(json.loads(attrs["cutbacks"]))
        except (json.JSONDecodeError, TypeError):
            cutbacks = None
    if not np.isin(model.tissue, NODE_TISSUES).all():
        raise InputError(f"{name}: /nodes/tissue holds codes outside {NODE_TISSUES}")

    def fields(step: int) -> StepFields:
        with open_stage(path, schema=SCHEMA, version=VERSION) as g:
            s = g["steps"]
            u = np.asarray(s["u"][step], float)
            cauchy = np.asarray(s["cauchy"][step], float) if has_cauchy else None
            mp = np.asarray(s["max_principal"][step], float) if has_mp else None
        if mp is None and cauchy is not None:
            mp = max_principal_from_voigt(cauchy)
        return StepFields(u=u, cauchy=cauchy, max_principal=mp)

    return ReportInput(
        path=path, model=model, alpha=alpha, load_factor=np.asarray(arrays["load_factor"], float),
        converged=np.asarray(arrays["converged"], bool), iterations=np.asarray(arrays["iterations"], np.int64),
        reactions=reactions, constrained=constrained, newton=newton, cutbacks=cutbacks, status=status, info=attrs,
        config_yaml=config_yaml, provenance=provenance, units=units, solver_warnings=solver_warnings,
        has_stress=has_cauchy or has_mp, fields=fields,
    )

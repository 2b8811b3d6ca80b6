"""Results of a solve and the ``results.h5`` file (schema ``pixmuscle.results`` v1).

Layout (docs/architecture.md)::

    /nodes, /muscles, /grid, /sets   copy of the model (the report needs only this file)
    /steps/alpha            (S+1,)        activation α at the end of each step (step 0 = initial state)
    /steps/load_factor      (S+1,)        0..1 ramp of the prescribed displacements
    /steps/converged        (S+1,) bool
    /steps/iterations       (S+1,) int    Newton iterations (all sub-steps of the step)
    /steps/cutbacks         (S+1,) int    load-increment halvings
    /steps/u                (S+1,N,3) cm  displacement at the nodes u(X_I) = Σ_J Ψ_J(X_I) d_J
    /steps/d                (S+1,N,3) cm  RK coefficients
    /steps/reaction/<set>   (S+1,3) N     force the support exerts on the body (sum over the set)
    /steps/prescribed/<set> (S+1,3) cm    prescribed displacement (0 on fixed and free components);
                                          attribute ``constrained`` = the constrained components
    /steps/cauchy           (S+1,N,6) N/cm²  Cauchy stress at the nodes, Voigt xx yy zz xy yz xz
    /steps/max_principal    (S+1,N) N/cm²    largest principal Cauchy stress
    /newton/<column>        Newton log: step, load_factor, iteration, residual_norm (N),
                            relative_residual, energy_norm (N·cm), line_search
    attrs: status ("complete" | "failed: ..."), sign_convention, n_steps_planned, solver_info (JSON)

When a solve fails, only the converged steps are stored (S+1 is then the number of converged
states) and ``status`` says which step failed and why.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..model.model import Model, read_model_groups, write_model_groups
from ..store import open_stage, write_dataset, write_stage

SCHEMA = "pixmuscle.results"
VERSION = 1

NEWTON_COLUMNS = ("step", "load_factor", "iteration", "residual_norm", "relative_residual", "energy_norm", "line_search")
#: outward normal of the end sets (for the axial force of a reaction)
END_NORMALS = {"x_min": (-1, 0, 0), "x_max": (1, 0, 0), "y_min": (0, -1, 0), "y_max": (0, 1, 0), "z_min": (0, 0, -1),
               "z_max": (0, 0, 1)}


def cauchy_voigt(sigma: np.ndarray) -> np.ndarray:
    """(N, 3, 3) symmetric tensors → (N, 6) Voigt order xx yy zz xy yz xz."""
    s = 0.5 * (sigma + np.swapaxes(sigma, -1, -2))
    return np.stack([s[..., 0, 0], s[..., 1, 1], s[..., 2, 2], s[..., 0, 1], s[..., 1, 2], s[..., 0, 2]], axis=-1)


def max_principal(voigt: np.ndarray) -> np.ndarray:
    """Largest eigenvalue of symmetric tensors in Voigt order xx yy zz xy yz xz, shape (N,)."""
    xx, yy, zz, xy, yz, xz = np.moveaxis(np.asarray(voigt, float), -1, 0)
    T = np.stack([np.stack([xx, xy, xz], -1), np.stack([xy, yy, yz], -1), np.stack([xz, yz, zz], -1)], -2)
    return np.linalg.eigvalsh(T)[..., -1]


@dataclasses.dataclass
class Results:
    """Per-step results of a solve (shapes with S+1 stored states and N nodes; see module docstring)."""

    model: Model
    alpha: np.ndarray
    load_factor: np.ndarray
    converged: np.ndarray
    iterations: np.ndarray
    cutbacks: np.ndarray
    u: np.ndarray
    d: np.ndarray
    reaction: dict
    prescribed: dict
    constrained: dict
    cauchy: np.ndarray
    max_principal: np.ndarray
    newton: dict
    status: str = "complete"
    n_steps_planned: int = 0
    info: dict = dataclasses.field(default_factory=dict)
    sign_convention: str = ""

    @property
    def n_states(self) -> int:
        """Number of stored states (S+1 when complete)."""
        return int(self.alpha.shape[0])

    @property
    def failed(self) -> bool:
        return self.status.startswith("failed")

    def force(self, name: str, normal=None) -> np.ndarray:
        """Axial force of a reaction, R · n_out (N, (S+1,)): positive = the body pulls on the support.

        ``normal`` defaults to the outward normal of an end set (z_max → +z, z_min → −z).
        """
        n = END_NORMALS.get(name) if normal is None else normal
        if n is None:
            raise KeyError(f"no outward normal known for reaction {name!r}; pass normal=")
        return self.reaction[name] @ np.asarray(n, float)

    @classmethod
    def from_steps(cls, model: Model, steps: list[dict], *, failed_rows: Sequence = (), status: str = "complete",
                   n_steps: int = 0, constrained: dict | None = None, info: dict | None = None,
                   sign_convention: str = "") -> Results:
        """Collect the per-step dictionaries of :func:`pixmuscle.mechanics.solve.solve`."""
        n = model.n_nodes
        s1 = len(steps)
        names = list(steps[0]["reaction"]) if steps else list(constrained or {})
        rows = [r for s in steps for r in s["rows"]] + list(failed_rows)
        newton = {c: np.array([getattr(r, c) for r in rows], dtype=np.int64 if c in ("step", "iteration") else float)
                  for c in NEWTON_COLUMNS}
        return cls(
            model=model,
            alpha=np.array([s["alpha"] for s in steps], float),
            load_factor=np.array([s["t"] for s in steps], float),
            converged=np.ones(s1, bool),
            iterations=np.array([s["iterations"] for s in steps], np.int64),
            cutbacks=np.array([s["cutbacks"] for s in steps], np.int64),
            u=np.array([s["u"] for s in steps], float).reshape(s1, n, 3),
            d=np.array([s["d"] for s in steps], float).reshape(s1, n, 3),
            reaction={k: np.array([s["reaction"][k] for s in steps], float).reshape(s1, 3) for k in names},
            prescribed={k: np.array([s["prescribed"][k] for s in steps], float).reshape(s1, 3) for k in names},
            constrained={k: np.asarray(v, bool) for k, v in (constrained or {}).items()},
            cauchy=np.array([s["cauchy"] for s in steps], float).reshape(s1, n, 6),
            max_principal=np.array([s["max_principal"] for s in steps], float).reshape(s1, n),
            newton=newton, status=status, n_steps_planned=int(n_steps), info=dict(info or {}),
            sign_convention=sign_convention,
        )


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def write_results_groups(f, res: Results) -> None:
    """Write the groups of a results file into an open HDF5 file."""
    write_model_groups(f, res.model)
    st = f.create_group("steps")
    write_dataset(st, "alpha", res.alpha, units="1")
    write_dataset(st, "load_factor", res.load_factor, units="1")
    write_dataset(st, "converged", res.converged)
    write_dataset(st, "iterations", res.iterations)
    write_dataset(st, "cutbacks", res.cutbacks)
    write_dataset(st, "u", res.u, units="cm", description="u(X_I) = sum_J Psi_J(X_I) d_J at the nodes")
    write_dataset(st, "d", res.d, units="cm", description="RK coefficients d_J")
    write_dataset(st, "cauchy", res.cauchy, units="N/cm^2", order="xx yy zz xy yz xz")
    write_dataset(st, "max_principal", res.max_principal, units="N/cm^2")
    rg = st.create_group("reaction")
    for k, v in res.reaction.items():
        write_dataset(rg, k, v, units="N", description="force the support exerts on the body")
    pg = st.create_group("prescribed")
    for k, v in res.prescribed.items():
        comp = "".join(a for a, m in zip("xyz", res.constrained.get(k, np.zeros(3, bool)), strict=True) if m)
        write_dataset(pg, k, v, units="cm", constrained=comp)
    ng = f.create_group("newton")
    units = {"residual_norm": "N", "energy_norm": "N*cm", "load_factor": "1", "relative_residual": "1", "line_search": "1"}
    for c in NEWTON_COLUMNS:
        write_dataset(ng, c, res.newton[c], units=units.get(c))


def save_results(path: str | Path, res: Results, *, config: Any = None, inputs: Sequence[str | Path] = ()) -> Path:
    """Write ``results.h5`` atomically (schema ``pixmuscle.results`` v1)."""
    attrs = {"status": res.status, "sign_convention": res.sign_convention, "n_steps_planned": int(res.n_steps_planned),
             "solver_info": json.dumps(_jsonable(res.info))}
    return write_stage(path, schema=SCHEMA, version=VERSION, write=lambda f: write_results_groups(f, res),
                       config=config, inputs=inputs, attrs=attrs)


def load_results(path: str | Path) -> Results:
    """Read a results file written by :func:`save_results` (schema checked)."""
    with open_stage(path, schema=SCHEMA, version=VERSION) as f:
        model = read_model_groups(f)
        st = f["steps"]
        pres = st["prescribed"] if "prescribed" in st else {}
        constrained = {}
        for k in pres:
            c = pres[k].attrs.get("constrained", "")
            c = c.decode() if isinstance(c, bytes) else str(c)
            constrained[k] = np.array([a in c for a in "xyz"])
        a = f.attrs
        status = a.get("status", "")
        return Results(
            model=model, alpha=st["alpha"][()], load_factor=st["load_factor"][()], converged=st["converged"][()],
            iterations=st["iterations"][()],
            cutbacks=st["cutbacks"][()] if "cutbacks" in st else np.zeros(st["alpha"].shape[0], np.int64),
            u=st["u"][()], d=st["d"][()], reaction={k: v[()] for k, v in st["reaction"].items()},
            prescribed={k: v[()] for k, v in pres.items()}, constrained=constrained, cauchy=st["cauchy"][()],
            max_principal=st["max_principal"][()], newton={k: v[()] for k, v in f["newton"].items()},
            status=status.decode() if isinstance(status, bytes) else str(status),
            n_steps_planned=int(a.get("n_steps_planned", 0)), info=json.loads(a.get("solver_info", "{}")),
            sign_convention=str(a.get("sign_convention", "")),
        )

"""Results of a solve: the :class:`Results` container (pure data, no file I/O).

The file ``results.h5`` (schema ``pixmuscle.results`` v1) is written and read by
:mod:`pixmuscle.io.results`, the one reader of that file. Its layout (docs/architecture.md)::

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
    /ellipticity/acoustic_minimum (N,) N/cm²  optional: smallest acoustic-tensor eigenvalue of the
                            material law at the nodes at one state (the last converged one); the law is
                            not strongly elliptic where it is < 0; attributes ``step`` (the state) and
                            ``n_directions`` (:mod:`pixmuscle.mechanics.ellipticity`)
    /newton/<column>        Newton log: step, load_factor, iteration, residual_norm (N),
                            relative_residual, energy_norm (N·cm), line_search
    attrs: status ("complete" | "failed: ..."), sign_convention, n_steps_planned, solver_info (JSON),
           constraint_gap (JSON, optional), warnings (JSON list), stages (JSON, upstream stage records)

When a solve fails, only the converged steps are stored (S+1 is then the number of converged
states) and ``status`` says which step failed and why.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from ..model.model import Model

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


def _moved(steps: list[dict], key: str, shape: tuple) -> np.ndarray:
    """The per-step arrays ``steps[i][key]`` (each ``shape``) stacked as (S, *shape) float; each is
    set to None in its step as soon as it is copied."""
    out = np.empty((len(steps), *shape))
    for i, step in enumerate(steps):
        out[i] = np.reshape(step[key], shape)
        step[key] = None
    return out


@dataclasses.dataclass
class NodeEllipticity:
    """Strong ellipticity of the material law at the nodes, at one stored state.

    Attributes
    ----------
    step : int
        The stored state (the solve records the last converged one).
    minimum : (N,) float64
        Smallest eigenvalue of the isochoric acoustic tensor over ``n_directions`` reference
        directions (:func:`pixmuscle.mechanics.ellipticity.acoustic_minimum`), N/cm².
    n_directions : int
    """

    step: int
    minimum: np.ndarray
    n_directions: int = 300

    @property
    def non_elliptic(self) -> np.ndarray:
        """(N,) bool: the law is not strongly elliptic at the node (``minimum < 0``)."""
        return np.asarray(self.minimum) < 0.0

    @property
    def count(self) -> int:
        """Number of nodes where the law is not strongly elliptic."""
        return int(np.count_nonzero(self.non_elliptic))


@dataclasses.dataclass
class StepFields:
    """Nodal fields of one stored state.

    Attributes
    ----------
    u : (N, 3) float64
        Displacement at the nodes, cm.
    cauchy : (N, 6) float64 or None
        Cauchy stress, N/cm², Voigt order xx yy zz xy yz xz.
    max_principal : (N,) float64 or None
        Largest principal Cauchy stress, N/cm².
    acoustic_minimum : (N,) float64 or None
        Smallest acoustic-tensor eigenvalue, N/cm² (:class:`NodeEllipticity`), at the state the
        results record it for; None at the other states.
    """

    u: np.ndarray
    cauchy: np.ndarray | None
    max_principal: np.ndarray | None
    acoustic_minimum: np.ndarray | None = None


@dataclasses.dataclass
class Results:
    """Per-step results of a solve (shapes with S+1 stored states and N nodes; see module docstring).

    The per-step arrays ``u``, ``d``, ``cauchy`` and ``max_principal`` are numpy arrays after a
    solve; read from a file they may be lazy (anything indexable by step with a ``shape``, see
    :class:`pixmuscle.io.results.StepArray`), so use :meth:`step` to get one state's fields.
    ``cauchy``, ``max_principal`` and ``d`` may be None for files that do not store them.

    ``constraint_gap`` maps each constrained node set to the largest error of its constrained
    displacement components (``{"max_cm": float, "relative": float}``, relative to the largest
    displacement); empty when the solver did not record it. ``warnings`` are the solver's own
    warnings (text). ``meta`` is empty after a solve; read from a file it holds the file's
    metadata: ``path``, ``config`` (YAML text), ``provenance``, ``units``, ``stages`` (records of
    the upstream stage files: stage, file, config, provenance, warnings, synthetic), ``synthetic``
    (bool) and the other root attributes (``attrs``). ``ellipticity`` is the material law's
    acoustic-tensor minimum at the nodes of the last converged state (:class:`NodeEllipticity`);
    None for files written before it was recorded.
    """

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
    constraint_gap: dict = dataclasses.field(default_factory=dict)
    warnings: list = dataclasses.field(default_factory=list)
    meta: dict = dataclasses.field(default_factory=dict)
    ellipticity: NodeEllipticity | None = None

    @property
    def n_states(self) -> int:
        """Number of stored states (S+1 when complete)."""
        return int(self.alpha.shape[0])

    @property
    def failed(self) -> bool:
        return self.status.lower().startswith("failed")

    @property
    def has_stress(self) -> bool:
        return self.cauchy is not None or self.max_principal is not None

    def step(self, k: int) -> StepFields:
        """Displacement and stresses of stored state ``k`` as numpy arrays (the largest principal
        stress is computed from ``cauchy`` when it is not stored), and the acoustic-tensor minimum
        when ``k`` is the state of :attr:`ellipticity`."""
        u = np.asarray(self.u[k], float)
        cauchy = None if self.cauchy is None else np.asarray(self.cauchy[k], float)
        mp = None if self.max_principal is None else np.asarray(self.max_principal[k], float)
        if mp is None and cauchy is not None:
            mp = max_principal(cauchy)
        ell = self.ellipticity
        q = np.asarray(ell.minimum, float) if ell is not None and int(ell.step) == int(k) else None
        return StepFields(u=u, cauchy=cauchy, max_principal=mp, acoustic_minimum=q)

    def constrained_text(self) -> dict:
        """Constrained components of each set as text, e.g. ``{"z_min": "xyz", "bone_surface": "xy"}``."""
        return {k: "".join(a for a, m in zip("xyz", np.asarray(v, bool), strict=True) if m)
                for k, v in self.constrained.items()}

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
                   sign_convention: str = "", constraint_gap: dict | None = None,
                   warnings: Sequence[str] = (), ellipticity: NodeEllipticity | None = None,
                   stacked: dict | None = None) -> Results:
        """Collect the per-step dictionaries of :func:`pixmuscle.mechanics.solve.solve`; their nodal
        arrays (``u``, ``d``, ``cauchy``, ``max_principal``) are moved into the results (set to None
        in the dictionaries as they are copied, so that they are not held twice). ``stacked`` gives
        some of them for all steps at once instead, (S, N, …) (read back from a step store)."""
        n = model.n_nodes
        stacked = dict(stacked or {})

        def field(key, shape):
            if key in stacked:
                return np.asarray(stacked.pop(key), float).reshape(len(steps), *shape)
            return _moved(steps, key, shape)

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
            u=field("u", (n, 3)),
            d=field("d", (n, 3)),
            reaction={k: np.array([s["reaction"][k] for s in steps], float).reshape(s1, 3) for k in names},
            prescribed={k: np.array([s["prescribed"][k] for s in steps], float).reshape(s1, 3) for k in names},
            constrained={k: np.asarray(v, bool) for k, v in (constrained or {}).items()},
            cauchy=field("cauchy", (n, 6)),
            max_principal=field("max_principal", (n,)),
            newton=newton, status=status, n_steps_planned=int(n_steps), info=dict(info or {}),
            sign_convention=sign_convention, constraint_gap=dict(constraint_gap or {}), warnings=list(warnings),
            ellipticity=ellipticity,
        )

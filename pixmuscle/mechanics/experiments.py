"""Experiments made of several solves: per-muscle force contributions and force–length sweeps.

Pure helpers: they build the activation ramps and solve configurations of each run and combine
the end forces of the runs; the stage layer (:mod:`pixmuscle.stages.muscle_forces`,
:mod:`pixmuscle.stages.force_length`) runs the solves and writes the files.

Per-muscle force contributions
------------------------------
The end force of a model with several active muscles is not a sum of per-muscle terms that the
solve itself defines: the muscles share the tissue between them, and the split of the reaction
by material point depends on a test field chosen in the interior. The contribution of a muscle
is therefore defined by solves (M + 2 of them, same load steps and boundary conditions):

* **all**: the configured activation (the ``solve`` stage's own run), end force F_all(t);
* **baseline**: every muscle held at its ``from`` activation (the passive response to the
  prescribed displacements plus any initial activation), F_0(t);
* **m alone**: muscle m ramped as configured, every other muscle held at its ``from`` value,
  F_m(t).

Contribution of muscle m: C_m(t) = F_m(t) − F_0(t); interaction: I(t) = F_all − F_0 − Σ_m C_m,
so that F_all = F_0 + Σ_m C_m + I exactly. I measures how much the muscles help (I > 0) or
hinder (I < 0) each other through the shared tissue; it vanishes when the muscles are
mechanically independent (e.g. parallel columns along the fibres, where the state stays
homogeneous).

Force–length sweep
------------------
The prescribed displacement δ of one end along one axis is swept over shortening (δ < 0) and
lengthening (δ > 0) values at a fixed activation α and at α = 0. Active runs are one solve per
δ, ramping α and δ together from the reference state (robust; hyperelastic equilibria do not
depend on the path); passive runs are one solve per branch, ``steps`` load steps per δ, read at
each δ. The
muscle length is L = L0 + δ with L0 the reference distance between the outer faces of the two
end sets along the axis; active force = total − passive at the same δ.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import field
from typing import Literal

import numpy as np

from .activation import ActivationRamp
from .config import AXES, MAX_STEPS, BoundaryCondition, SolveConfig

__all__ = ["ForceLengthConfig", "MuscleForcesConfig", "decompose", "force_length_cases", "muscle_force_ramps",
           "reference_length"]


@dataclasses.dataclass(frozen=True)
class MuscleForcesConfig:
    """Section ``muscle_forces``: split the end force by muscle (M + 2 extra solves per model)."""

    muscles: list[str] | None = field(default=None, metadata={
        "doc": "muscles to solve alone (default: every muscle of the model with nodes); the others count in the "
               "interaction term"})


@dataclasses.dataclass(frozen=True)
class ForceLengthConfig:
    """Section ``force_length``: sweep the prescribed displacement of one end at fixed activation and at α = 0."""

    nodes: str = field(default="z_max", metadata={"doc": "end set whose displacement is swept (it must have a "
                                                          "boundary condition in solve.boundary_conditions)"})
    component: Literal["x", "y", "z"] = field(default="z", metadata={"doc": "axis of the swept displacement"})
    shortening: float = field(default=0.2, metadata={"range": (0.0, None), "doc": "largest shortening, cm"})
    lengthening: float = field(default=0.2, metadata={"range": (0.0, None), "doc": "largest lengthening, cm"})
    points: int = field(default=4, metadata={"range": (1, None), "doc": "displacements per branch "
                                                                         "(equally spaced up to the largest)"})
    activation: float | dict[str, float] = field(default=1.0, metadata={
        "doc": "fixed activation of the active curve: a number or a mapping muscle → α with optional 'default' "
               "(solve.activation.image, if any, multiplies it)"})
    steps: int = field(default=4, metadata={"range": (1, MAX_STEPS), "doc": "load steps of each active solve (α and δ "
                                                                        "ramped together), and per point of a passive branch"})

    def __post_init__(self):
        if self.shortening == 0.0 and self.lengthening == 0.0:
            raise ValueError("force_length: shortening and lengthening are both 0; nothing to sweep")
        vals = self.activation.values() if isinstance(self.activation, dict) else [self.activation]
        for v in vals:
            if not 0.0 <= float(v) <= 1.0:
                raise ValueError(f"force_length.activation: expected values in [0, 1], got {v!r}")

    def displacements(self) -> tuple[np.ndarray, np.ndarray]:
        """Shortening (negative, ascending magnitude) and lengthening displacements, cm: (p,), (p,)."""
        k = np.arange(1, self.points + 1) / self.points
        return -self.shortening * k if self.shortening > 0 else np.zeros(0), \
            self.lengthening * k if self.lengthening > 0 else np.zeros(0)


def muscle_force_ramps(ramp: ActivationRamp, muscle_id: np.ndarray, names, muscles=None) -> dict[str, ActivationRamp]:
    """Activation ramps of the baseline and the single-muscle runs.

    Parameters
    ----------
    ramp : ActivationRamp
        The configured (all-muscle) ramp.
    muscle_id : (N,) int
        1..M per muscle node.
    names : list of str
        Muscle names 1..M.
    muscles : list of str, optional
        Muscles to run alone (default: all with nodes).

    Returns
    -------
    dict
        ``"baseline"`` → every node held at its start value; each muscle name → that muscle
        ramped as configured, the others held at their start values.
    """
    from ..errors import InputError

    mid = np.asarray(muscle_id)
    names = [str(n) for n in names]
    if muscles is None:
        muscles = [n for i, n in enumerate(names, 1) if np.any(ramp.muscle & (mid == i))]
    unknown = [m for m in muscles if m not in names]
    if unknown:
        raise InputError(f"muscle_forces.muscles: unknown muscle {unknown[0]!r}; the model's muscles are: "
                         f"{', '.join(names) or 'none'}")
    out = {"baseline": ActivationRamp(start=ramp.start, end=ramp.start.copy(), muscle=ramp.muscle)}
    for name in muscles:
        sel = mid == names.index(name) + 1
        out[name] = ActivationRamp(start=ramp.start, end=np.where(sel, ramp.end, ramp.start), muscle=ramp.muscle)
    return out


def decompose(total: np.ndarray, baseline: np.ndarray, alone: Mapping[str, np.ndarray]) -> dict:
    """Per-muscle contributions C_m = F_m − F_0 and interaction I = F_all − F_0 − Σ C_m (see the module notes).

    Parameters
    ----------
    total, baseline : (S+1,) float
        End force of the all-muscle and the baseline runs, N.
    alone : mapping name → (S+1,) float
        End force with only that muscle ramped, N.

    Returns
    -------
    dict with ``contribution`` (name → (S+1,)), ``interaction`` (S+1,), ``baseline`` (S+1,),
    ``total`` (S+1,); F_all = baseline + Σ contribution + interaction.
    """
    total = np.asarray(total, float)
    baseline = np.asarray(baseline, float)
    contribution = {k: np.asarray(v, float) - baseline for k, v in alone.items()}
    summed = np.sum(list(contribution.values()), axis=0) if contribution else np.zeros_like(total)
    return {"contribution": contribution, "interaction": total - baseline - summed, "baseline": baseline,
            "total": total}


def reference_length(model, nodes: str, component: str) -> float:
    """Reference muscle length L0 along ``component``: from the outer face of the opposite end set to ``nodes``, cm."""
    from ..errors import InputError

    axis = AXES.index(component)
    if nodes not in model.sets:
        raise InputError(f"force_length.nodes: the model has no node set {nodes!r} "
                         f"(sets: {', '.join(sorted(model.sets))})")
    other = nodes.replace("_max", "_min") if nodes.endswith("_max") else nodes.replace("_min", "_max")
    if other == nodes or other not in model.sets or nodes[0] != component:
        raise InputError(f"force_length.nodes: expected an end set along the swept axis ({component}_min or "
                         f"{component}_max), got {nodes!r}")
    X = np.asarray(model.X, float)[:, axis]
    h = float(np.asarray(model.spacing, float)[axis])
    return float(abs(X[model.sets[nodes]].mean() - X[model.sets[other]].mean()) + h)


def force_length_cases(solve: SolveConfig, fl: ForceLengthConfig) -> list[dict]:
    """The solves of a force–length sweep.

    Returns
    -------
    list of dict
        ``name`` (``active_ref``, ``active_short_2``, ``passive_long``...), ``kind``
        (active/passive), ``branch`` (ref/short/long), ``delta`` (cm; the final one for passive
        branches), ``deltas`` (the δ read back, cm), ``read_steps`` (passive: the load steps at
        those δ, ``steps`` apart), ``cfg`` (SolveConfig with the swept displacement and
        the activation of that run; from = 0 and to = the fixed α for active runs).

    Raises
    ------
    ValueError
        ``fl.nodes`` has no boundary condition in ``solve.boundary_conditions``.
    """
    bcs = list(solve.boundary_conditions)
    hits = [i for i, bc in enumerate(bcs) if bc.nodes == fl.nodes]
    if not hits:
        raise ValueError(f"force_length.nodes: {fl.nodes!r} has no boundary condition in solve.boundary_conditions "
                         f"(the swept end must be constrained)")

    def with_delta(delta: float, steps: int, act_to) -> SolveConfig:
        new = []
        for i, bc in enumerate(bcs):
            if i in hits:
                fix = [c for c in bc.fix if c != fl.component]
                disp = {k: v for k, v in bc.displace.items() if k != fl.component}
                disp[fl.component] = float(delta)
                bc = BoundaryCondition(nodes=bc.nodes, fix=fix, displace=disp, name=bc.name)
            new.append(bc)
        act = {"from": 0.0, "to": act_to, "image": solve.activation.get("image")}
        return dataclasses.replace(solve, boundary_conditions=new, steps=steps, activation=act)

    short, long_ = fl.displacements()
    cases = [dict(name="active_ref", kind="active", branch="ref", delta=0.0, deltas=[0.0],
                  cfg=with_delta(0.0, fl.steps, fl.activation))]
    for branch, ds in (("short", short), ("long", long_)):
        if not ds.size:
            continue
        cases.append(dict(name=f"passive_{branch}", kind="passive", branch=branch, delta=float(ds[-1]),
                          deltas=ds.tolist(), read_steps=[fl.steps * j for j in range(1, ds.size + 1)],
                          cfg=with_delta(ds[-1], int(ds.size) * fl.steps, 0.0)))
        for j, d in enumerate(ds, 1):
            cases.append(dict(name=f"active_{branch}_{j}", kind="active", branch=branch, delta=float(d),
                              deltas=[float(d)], cfg=with_delta(d, fl.steps, fl.activation)))
    return cases

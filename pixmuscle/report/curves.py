"""Force–activation curves (paper Figs. 11 and 15c) and Newton convergence plots.

Sign convention (docs/architecture.md): ``reaction/<set>`` is the force (N) the support exerts on
the body; the muscle force at an end set is ``F = R · n_out`` with ``n_out`` the outward normal of
that end (+z for ``z_max``, −z for ``z_min``). F > 0 means the body pulls on the support (tension).
"""

from __future__ import annotations

import csv
import re
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from ..errors import InputError

_END = re.compile(r"^([xyz])_(min|max)$")
#: default force sets, in order of preference
DEFAULT_FORCE_SETS = ("z_min", "z_max")


def end_normal(name: str) -> np.ndarray | None:
    """Outward unit normal of an end set named ``x_min`` ... ``z_max``; None for other sets.

    Returns
    -------
    (3,) float64 or None
    """
    m = _END.match(name)
    if m is None:
        return None
    n = np.zeros(3)
    n["xyz".index(m.group(1))] = 1.0 if m.group(2) == "max" else -1.0
    return n


def _axis_constrained(name: str, constrained: Mapping[str, str] | None) -> bool:
    """Whether the normal component of end set ``name`` is constrained (True when unknown)."""
    if not constrained or name not in constrained:
        return True
    return name[0] in constrained[name]


def select_force_sets(reactions: Mapping[str, np.ndarray], requested: Sequence[str] | None = None,
                      constrained: Mapping[str, str] | None = None) -> list[str]:
    """The end sets whose axial reaction is reported as the muscle force.

    Parameters
    ----------
    reactions : mapping of set name → (S+1, 3)
    requested : list of str, optional
        Set names from the config; default: ``z_min``/``z_max`` where constrained along z, else
        every ``x|y|z_min|max`` set constrained along its normal.
    constrained : mapping of set name → constrained components (e.g. ``"xyz"``), optional

    Raises
    ------
    InputError
        A requested set has no reaction in the file, is not an end set, or is free along its normal.
    """
    if requested:
        for s in requested:
            if s not in reactions:
                raise InputError(f"report.force_sets: set '{s}' has no reaction in the results file "
                                 f"(constrained sets: {', '.join(sorted(reactions)) or 'none'})")
            if end_normal(s) is None:
                raise InputError(f"report.force_sets: '{s}' is not an end set (expected x_min, x_max, y_min, y_max, z_min or z_max)")
            if not _axis_constrained(s, constrained):
                raise InputError(f"report.force_sets: set '{s}' is not constrained along {s[0]} "
                                 f"(constrained components: '{constrained[s]}'), so its axial reaction is zero")
        return list(requested)
    ends = [s for s in reactions if end_normal(s) is not None and _axis_constrained(s, constrained)]
    chosen = [s for s in DEFAULT_FORCE_SETS if s in ends]
    return chosen or sorted(ends)


def axial_forces(reactions: Mapping[str, np.ndarray], sets: Sequence[str]) -> dict[str, np.ndarray]:
    """Axial force ``F = R · n_out`` (N) at each end set, per step.

    Returns
    -------
    dict of set name → (S+1,) float64, N (positive = tension)
    """
    return {s: np.asarray(reactions[s], float) @ end_normal(s) for s in sets}


def end_force(forces: Mapping[str, np.ndarray], n_steps: int) -> np.ndarray:
    """Muscle force per step: mean of the axial forces of the force sets (they agree in equilibrium).

    Returns
    -------
    (S+1,) float64, N; NaN where no force set exists.
    """
    if not forces:
        return np.full(n_steps, np.nan)
    return np.mean(np.stack(list(forces.values())), axis=0)


def force_table(alpha, load_factor, converged, iterations, reactions: Mapping[str, np.ndarray],
                force_sets: Sequence[str]) -> tuple[list[str], list[list]]:
    """Rows of ``force_activation.csv``: step, α, load factor, Rx Ry Rz [N] of every constrained set,
    the axial force of every end set [N], the end force [N], Newton iterations, converged.

    Returns
    -------
    header : list of str
    rows : list of lists (one per stored step)
    """
    alpha = np.asarray(alpha, float)
    names = sorted(reactions)
    ends = [s for s in names if end_normal(s) is not None]
    axial = axial_forces(reactions, ends)
    fend = end_force({s: axial[s] for s in force_sets}, alpha.shape[0])
    header = ["step", "alpha", "load_factor"]
    cols = [np.arange(alpha.shape[0]), alpha, np.asarray(load_factor, float)]
    for s in names:
        header += [f"{s}.Rx [N]", f"{s}.Ry [N]", f"{s}.Rz [N]"]
        cols += [reactions[s][:, 0], reactions[s][:, 1], reactions[s][:, 2]]
        if s in axial:
            header.append(f"{s}.F [N]")
            cols.append(axial[s])
    header += ["end_force [N]", "iterations", "converged"]
    cols += [fend, np.asarray(iterations), np.asarray(converged, bool)]
    rows = [[_cell(c[i]) for c in cols] for i in range(alpha.shape[0])]
    return header, rows


def _cell(v):
    if isinstance(v, (bool, np.bool_)):
        return int(bool(v))
    if isinstance(v, (int, np.integer)):
        return int(v)
    v = float(v)
    return "" if np.isnan(v) else repr(v)


def write_csv(path: str | Path, header: Sequence[str], rows: Sequence[Sequence]) -> Path:
    """Write a CSV file with a header row."""
    path = Path(path)
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        w.writerows(rows)
    return path


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def load_factor_label(activation: Mapping[str, Sequence[float]] | None) -> str | None:
    """x-axis label naming each muscle's α when the muscles ramp differently (then a single α, the
    mean over the muscle nodes, would hide what each muscle reached): the curves are drawn against
    the load factor s, muscle m's α being a_m + s (b_m − a_m). None when one α describes every muscle.

    Parameters
    ----------
    activation : mapping muscle → (a_m, b_m), optional
        Mean α of each muscle at load factor 0 and 1 (``solver_info["activation"]``).
    """
    if not activation or len({tuple(np.round(np.asarray(v, float), 12)) for v in activation.values()}) < 2:
        return None
    ramps = ", ".join(f"{m} {float(a):.3g}→{float(b):.3g}" for m, (a, b) in activation.items())
    return f"load factor s [-]; α of each muscle ramps linearly with s: {ramps}"


def plot_force_activation(curves: Mapping[str, Sequence], path: str | Path, *, dpi: int = 120,
                          title: str = "Isometric force vs activation", ylabel: str = "force at fixed end [N]",
                          xlabel: str = "activation α [-]") -> Path:
    """Plot one or more force–activation curves on one axes (paper Figs. 11, 15c).

    Parameters
    ----------
    curves : mapping label → (alpha, force) or (alpha, force, converged)
        α (S+1,), force (S+1,) in N; non-converged points are drawn as red crosses.
        Use several labels to overlay ends, coarse and fine models, or subjects.
    path : path-like
        PNG file to write.
    xlabel : str
        Label of the x axis (e.g. :func:`load_factor_label` when the curves are given against the
        load factor).
    """
    import textwrap

    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6.0, 4.2), layout="constrained")
    markers = "osD^v<>ph*"
    styles = ["-", "--", "-.", ":"]
    flagged = False
    for n, (label, c) in enumerate(curves.items()):
        a, fo = np.asarray(c[0], float), np.asarray(c[1], float)
        if a.shape != fo.shape:
            raise InputError(f"curve '{label}': alpha has shape {a.shape} but force has shape {fo.shape}")
        ok = np.asarray(c[2], bool) if len(c) > 2 else np.ones(a.shape, bool)
        ax.plot(a[ok], fo[ok], linestyle=styles[n % len(styles)], marker=markers[n % len(markers)],
                markersize=4, label=label)
        if (~ok).any():
            ax.plot(a[~ok], fo[~ok], "x", color="red", markersize=8,
                    label=None if flagged else "not converged")
            flagged = True
    ax.set_xlabel(textwrap.fill(xlabel, 80), fontsize=9 if len(xlabel) > 60 else None)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.axhline(0.0, color="0.7", linewidth=0.8)
    ax.grid(alpha=0.3)
    if curves:
        ax.legend(fontsize=8)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return Path(path)


def newton_per_step(newton: Mapping[str, np.ndarray], n_steps: int) -> dict[str, np.ndarray]:
    """Final residual and energy norm of every step from the Newton log.

    Returns
    -------
    dict with ``final_residual``, ``final_relative_residual`` and ``final_energy`` (S+1,) float64,
    NaN where the step has no Newton record (e.g. step 0) or the log lacks the column.
    """
    out = {k: np.full(n_steps, np.nan) for k in ("final_residual", "final_relative_residual", "final_energy")}
    if not newton or "step" not in newton:
        return out
    step = np.asarray(newton["step"], np.int64)
    it = np.asarray(newton.get("iteration", np.arange(step.size)), float)
    order = np.lexsort((it, step))  # last row of each step = its final iteration
    step_o = step[order]
    last = order[np.r_[step_o[1:] != step_o[:-1], True]] if step.size else order
    valid = (step[last] >= 0) & (step[last] < n_steps)
    for key, col in (("final_residual", "residual_norm"), ("final_relative_residual", "relative_residual"),
                     ("final_energy", "energy_norm")):
        if col in newton:
            out[key][step[last][valid]] = np.asarray(newton[col], float)[last][valid]
    return out


def plot_newton(newton: Mapping[str, np.ndarray], path: str | Path, *, dpi: int = 120) -> Path | None:
    """Residual norm vs Newton iteration for every step (semilog); None when no log exists."""
    if not newton or "step" not in newton or "residual_norm" not in newton or len(newton["step"]) == 0:
        return None
    plt = _pyplot()
    step = np.asarray(newton["step"], np.int64)
    it = np.asarray(newton.get("iteration", np.zeros_like(step)), float)
    res = np.asarray(newton["residual_norm"], float)
    fig, ax = plt.subplots(figsize=(6.0, 4.0), layout="constrained")
    steps = np.unique(step)
    cmap = plt.get_cmap("viridis")
    for n, s in enumerate(steps):  # loop over load steps (a handful)
        m = step == s
        o = np.argsort(it[m])
        y = np.where(res[m][o] > 0, res[m][o], np.nan)
        ax.semilogy(it[m][o], y, marker="o", markersize=3, color=cmap(n / max(len(steps) - 1, 1)),
                    label=f"step {s}" if len(steps) <= 12 else None)
    ax.xaxis.get_major_locator().set_params(integer=True)
    ax.set_xlabel("Newton iteration")
    ax.set_ylabel("residual norm (as logged by the solver)")
    ax.set_title("Newton convergence per load step")
    ax.grid(alpha=0.3, which="both")
    if len(steps) <= 12:
        ax.legend(fontsize=7, ncol=2)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return Path(path)

"""Stage ``muscle_forces``: the end force split by muscle (:mod:`pixmuscle.mechanics.experiments`).

``model.h5`` (+ the solve stage's ``results_<model>.h5``, reused as the all-muscle run) →
``muscle_forces_<model>.h5``, schema ``pixmuscle.muscle_forces`` v1::

    /steps/alpha            (S+1,)  mean α of the muscle nodes in the all-muscle run
    /steps/load_factor      (S+1,)
    /force/total            (S+1,)  N   end force, all muscles as configured
    /force/baseline         (S+1,)  N   every muscle held at its `from` activation
    /force/alone/<muscle>   (S+1,)  N   only <muscle> ramped
    /contribution/<muscle>  (S+1,)  N   alone − baseline
    /interaction            (S+1,)  N   total − baseline − Σ contributions
    attrs: muscles (JSON list), force_sets (JSON list), runs (JSON: run → status), method (text)

Forces of steps a run did not reach are NaN.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from ..errors import InputError, SolverError
from ..io.lineage import capture_warnings, stage_attrs
from ..io.model import load_model
from ..io.muscle_forces import write_muscle_forces
from ..mechanics.activation import ActivationRamp
from ..mechanics.experiments import MuscleForcesConfig, decompose, muscle_force_ramps
from ..mechanics.solve import solve
from ..model.tissues import MUSCLE
from .solve import model_activation

METHOD = ("contribution of a muscle = end force with only that muscle ramped (the others held at their 'from' "
          "activation) minus the baseline with every muscle held at 'from'; interaction = all-muscle force − "
          "baseline − Σ contributions (pixmuscle.mechanics.experiments)")
_LOG = logging.getLogger(__name__)

__all__ = ["end_force_of", "run_muscle_forces"]


def end_force_of(results, n_steps: int, force_sets=None) -> tuple[np.ndarray, list[str]]:
    """End force per step (mean axial force of the force sets), NaN-padded to ``n_steps`` (S+1) entries."""
    from ..report.curves import select_force_sets

    sets = list(force_sets) if force_sets else select_force_sets(results.reaction, None, results.constrained_text())
    f = np.full(n_steps, np.nan)
    if sets:
        vals = np.mean([results.force(s) for s in sets], axis=0)
        ok = np.asarray(results.converged, bool)
        vals = np.where(ok, vals, np.nan)
        f[:min(n_steps, vals.shape[0])] = vals[:n_steps]
    return f, sets


def _solve_quiet(model, cfg, ramp, label):
    try:
        return solve(model, cfg, activation=ramp), "complete"
    except SolverError as exc:
        _LOG.warning("muscle_forces: run '%s' failed: %s", label, exc)
        return getattr(exc, "results", None), f"failed: {exc}"


def run_muscle_forces(model_path, solve_cfg, cfg: MuscleForcesConfig | None, out_path, results_path=None, *,
                      synthetic: bool = False) -> Path:
    """Run the baseline and the single-muscle solves and write the decomposition.

    Parameters
    ----------
    model_path : path
        The model that the solve stage solved.
    solve_cfg : SolveConfig
        The ``solve`` section (load steps, boundary conditions, activation).
    cfg : MuscleForcesConfig or None
        The ``muscle_forces`` section.
    out_path : path
        ``muscle_forces_<model>.h5``.
    results_path : path, optional
        The solve stage's results of the same model and config, used as the all-muscle run
        (solved again when not given).
    synthetic : bool
        The inputs are synthetic phantoms (recorded in the file).
    """
    with capture_warnings() as warnings:
        return _run(model_path, solve_cfg, cfg, out_path, results_path, warnings, synthetic)


def _run(model_path, solve_cfg, cfg, out_path, results_path, warnings, synthetic) -> Path:
    from ..io.results import load_results

    cfg = cfg or MuscleForcesConfig()
    model = load_model(model_path)
    if not np.any(model.tissue == MUSCLE):
        raise InputError(f"muscle_forces: {model_path} has no muscle node")
    ramp = model_activation(model, solve_cfg)
    if ramp is None:
        ramp = ActivationRamp.uniform(solve_cfg.alpha_from, solve_cfg.alpha_to, model.tissue == MUSCLE)
    runs = muscle_force_ramps(ramp, model.muscle_id, model.muscle_names, cfg.muscles)
    n = solve_cfg.steps + 1
    status = {}
    if results_path is not None and Path(results_path).is_file():
        full = load_results(results_path)
        status["all"] = full.status
    else:
        full, status["all"] = _solve_quiet(model, solve_cfg, ramp, "all")
    if full is None:
        raise InputError("muscle_forces: the all-muscle solve failed before its first step")
    total, sets = end_force_of(full, n)
    alpha = np.full(n, np.nan)
    alpha[:len(full.alpha)] = full.alpha[:n]
    forces = {}
    for i, (name, r) in enumerate(runs.items(), 1):
        _LOG.info("muscle_forces: run %d of %d (%s)", i, len(runs), "baseline" if name == "baseline" else f"{name} alone")
        res, status[name] = _solve_quiet(model, solve_cfg, r, name)
        forces[name] = end_force_of(res, n, sets)[0] if res is not None else np.full(n, np.nan)
    base = forces.pop("baseline")
    dec = decompose(total, base, forces)
    load_factor = np.arange(n) / solve_cfg.steps

    inputs = [Path(model_path)] + ([Path(results_path)] if results_path is not None and Path(results_path).is_file()
                                   else [])
    attrs = {"force_sets": json.dumps(sets), "runs": json.dumps(status), "method": METHOD,
             **stage_attrs("muscle_forces", inputs, warnings, synthetic=synthetic)}
    write_muscle_forces(out_path, alpha=alpha, load_factor=load_factor, total=total, baseline=base, alone=forces,
                        contribution=dec["contribution"], interaction=dec["interaction"], attrs=attrs,
                        config={"solve": solve_cfg, "muscle_forces": cfg}, inputs=inputs)
    _LOG.info("muscle_forces: %s", ", ".join(f"{k} {v[-1]:.4g} N" for k, v in dec["contribution"].items()))
    return Path(out_path)

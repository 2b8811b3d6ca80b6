"""Stage ``force_length``: active, passive and total end force against muscle length.

``model.h5`` → ``force_length_<model>.h5``, schema ``pixmuscle.force_length`` v1
(method: :mod:`pixmuscle.mechanics.experiments`)::

    /delta     (P,) cm   prescribed displacement of the swept end (shortening < 0, lengthening > 0, 0)
    /length    (P,) cm   muscle length L0 + δ
    /stretch   (P,)      L / L0
    /total     (P,) N    end force at the fixed activation
    /passive   (P,) N    end force at α = 0
    /active    (P,) N    total − passive
    /fibre_law (P,) N    ᾱ σ_max A f_active(L/(L0 λ̂0)), A = muscle volume / L0 (:func:`fibre_law_force`)
    attrs: L0_cm, nodes, component, activation (JSON), force_sets (JSON), runs (JSON: run → status)

Points are sorted by length; NaN where a run did not converge.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from ..errors import InputError, SolverError
from ..io.force_length import write_force_length
from ..io.lineage import capture_warnings, stage_attrs
from ..io.model import load_model
from ..mechanics.experiments import ForceLengthConfig, force_length_cases, reference_length
from ..mechanics.solve import solve
from .muscle_forces import end_force_of
from .solve import model_activation

_LOG = logging.getLogger(__name__)

__all__ = ["fibre_law_force", "run_force_length"]


def run_force_length(model_path, solve_cfg, cfg: ForceLengthConfig, out_path, *, synthetic: bool = False) -> Path:
    """Run the sweep's solves and write the curves.

    Parameters
    ----------
    model_path : path
    solve_cfg : SolveConfig
        The ``solve`` section: boundary conditions (the swept end's entry is changed), materials,
        numerics; its activation is replaced by 0 → ``cfg.activation`` (active runs) and 0 (passive).
    cfg : ForceLengthConfig
    out_path : path
        ``force_length_<model>.h5``.
    synthetic : bool
        The inputs are synthetic phantoms (recorded in the file).
    """
    with capture_warnings() as warnings:
        return _run(model_path, solve_cfg, cfg, out_path, warnings, synthetic)


def _run(model_path, solve_cfg, cfg, out_path, warnings, synthetic) -> Path:
    model = load_model(model_path)
    L0 = reference_length(model, cfg.nodes, cfg.component)
    try:
        cases = force_length_cases(solve_cfg, cfg)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    sets = None
    status, passive, active = {}, {}, {}
    for i, case in enumerate(cases, 1):
        _LOG.info("force_length: run %d of %d (%s, δ = %.4g cm)", i, len(cases), case["name"], case["delta"])
        ramp = model_activation(model, case["cfg"])
        try:
            res = solve(model, case["cfg"], activation=ramp)
            status[case["name"]] = "complete"
        except SolverError as exc:
            _LOG.warning("force_length: run '%s' failed: %s", case["name"], exc)
            res = getattr(exc, "results", None)
            status[case["name"]] = f"failed: {exc}"
        n = case["cfg"].steps + 1
        f = np.full(n, np.nan) if res is None else None
        if res is not None:
            f, sets = end_force_of(res, n, sets)
        if case["kind"] == "passive":
            # step read_steps[j] reaches deltas[j]; step 0 is the reference state
            passive.update({round(d, 12): float(f[k]) for d, k in zip(case["deltas"], case["read_steps"], strict=True)})
            passive[0.0] = float(f[0])
        else:
            active[round(case["delta"], 12)] = float(f[-1])
    deltas = np.array(sorted(set(active) | set(passive)))
    tot = np.array([active.get(d, np.nan) for d in deltas])
    pas = np.array([passive.get(d, np.nan) for d in deltas])
    law = fibre_law_force(model, solve_cfg, cases[0]["cfg"], L0, (L0 + deltas) / L0)

    act = cfg.activation if isinstance(cfg.activation, dict) else float(cfg.activation)
    attrs = {"L0_cm": L0, "nodes": cfg.nodes, "component": cfg.component, "activation": json.dumps(act),
             "force_sets": json.dumps(sets or []), "runs": json.dumps(status)}
    image = solve_cfg.activation.get("image")
    inputs = [Path(model_path)] + ([image] if image is not None else [])
    attrs.update(stage_attrs("force_length", inputs, warnings, synthetic=synthetic))
    return write_force_length(out_path, delta=deltas, L0=L0, total=tot, passive=pas, fibre_law=law, attrs=attrs,
                              config={"solve": solve_cfg, "force_length": cfg}, inputs=inputs)


def fibre_law_force(model, solve_cfg, active_cfg, L0: float, stretch) -> np.ndarray:
    """Reference: the fibre force–length law (eqs. 24–26) of the model's muscle as one homogeneous bar, (P,) N.

    ᾱ σ_max A f_active(λ/λ̂0), with A = muscle volume / L0 (mean muscle cross-section), ᾱ the mean
    end-of-ramp α of the active runs over the muscle nodes and λ = L/L0. Exact for a homogeneous
    muscle block between roller ends (nearly incompressible); elsewhere a yardstick only.
    """
    from ..mechanics.activation import ActivationRamp
    from ..mechanics.materials import f_active
    from ..model.tissues import MUSCLE

    muscle = np.asarray(model.tissue) == MUSCLE
    ramp = model_activation(model, active_cfg) or ActivationRamp.uniform(active_cfg.alpha_from, active_cfg.alpha_to,
                                                                          muscle)
    m = solve_cfg.materials.muscle
    if not all(hasattr(m, k) for k in ("sigma_max", "lambda_opt")):
        raise InputError(f"force_length: the Hill-type yardstick needs the muscle law's sigma_max and lambda_opt; "
                         f"solve.materials.muscle is {type(m).__name__}")
    area = float(muscle.sum()) * model.cell_volume / L0
    return ramp.mean(1.0) * m.sigma_max * area * f_active(np.asarray(stretch, float) / m.lambda_opt)

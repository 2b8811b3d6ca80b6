"""The report's domain summary of one solve: end force, F_max, tissue volumes, Newton statistics,
the warnings of every stage, and the configuration and provenance of every stage.

Pure: takes a :class:`~pixmuscle.mechanics.results.Results` (as read by
:func:`pixmuscle.io.results.load_results`), returns JSON-ready data.
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np

from ..mechanics.results import Results
from ..store import _plain
from .config import ReportConfig
from .curves import axial_forces, end_force, end_normal, newton_per_step, select_force_sets
from .displacement import ACTIVATION, run_protocol
from .tables import tissue_table

#: relative constraint gap above which the report warns
CONSTRAINT_GAP_WARN = 0.01

_STAGE_ORDER = ("segment", "build-model", "coarsen", "solve")


def _jsonable(obj: Any) -> Any:
    try:
        return json.loads(json.dumps(_plain(obj), default=str))
    except (TypeError, ValueError):
        return str(obj)


def _floats(a) -> list:
    return [None if not np.isfinite(x) else float(x) for x in np.asarray(a, float)]


def stage_records(res: Results) -> list[dict]:
    """Records of every stage that led to ``res`` (upstream files, then the solve itself), each with
    ``stage``, ``file``, ``config`` (YAML text), ``provenance`` and ``warnings``."""
    meta = res.meta or {}
    records = [dict(r) for r in meta.get("stages", [])]
    records.append({"stage": "solve", "file": str(meta.get("path", "")), "config": meta.get("config", ""),
                    "provenance": meta.get("provenance", {}), "warnings": list(res.warnings),
                    "synthetic": bool(meta.get("synthetic"))})
    return records


def stage_warnings(res: Results) -> list[str]:
    """Warnings recorded by every stage, each prefixed with its stage, plus those the solver's
    statistics imply (enlarged RK supports, a constraint gap above 1 %)."""
    out = []
    for r in stage_records(res):
        out += [f"{r['stage']}: {w}" for w in r.get("warnings", [])]
    n_enl = int(res.info.get("supports_enlarged", 0) or 0)
    if n_enl and not any("enlarged" in w for w in out):
        out.append(f"solve: RK supports enlarged at {n_enl} of {res.model.n_nodes} nodes to cover thin features")
    for name, gap in sorted((res.constraint_gap or {}).items()):
        rel = gap.get("relative") if isinstance(gap, dict) else None
        if rel is not None and np.isfinite(rel) and gap.get("significant", rel > CONSTRAINT_GAP_WARN):
            out.append(f"solve: constraint gap of node set '{name}' is {100 * rel:.2g} % of the largest displacement "
                       f"({gap.get('max_cm', float('nan')):.3g} cm): raise solve.penalty.factor")
    return out


def newton_table(summary: dict) -> tuple[list[str], list[list]]:
    """Per-step solver table of the page: a column is left out when it holds no information
    (always zero or not recorded); a residual of exactly 0 reads "below round-off"."""
    c, nw = summary["curve"], summary["newton"]
    cols = {"step": c["step"], "α [-]": c["alpha"], "load factor [-]": c["load_factor"],
            "Newton iterations": nw["iterations"]}
    if (summary.get("protocol") or {}).get("kind") == "displacement":  # α is constant: the displacement instead
        p = summary["protocol"]
        del cols["α [-]"]
        cols = {"step": cols.pop("step"), f"{p['set']}.u{p['component']} [cm]": c["displacement_cm"], **cols}
    if nw["cutbacks"] is not None and len(nw["cutbacks"]) == len(c["step"]) and any(nw["cutbacks"]):
        cols["cutbacks"] = nw["cutbacks"]
    for key, head in (("final_residual", "final residual [N]"), ("final_relative_residual", "final relative residual"),
                      ("final_energy", "final energy norm [N·cm]")):
        v = nw.get(key)
        if v is not None and any(x not in (None, 0.0) for x in v):
            cols[head] = ["below round-off" if x == 0.0 else x for x in v]
    cols["end force [N]"] = c["end_force_N"]
    cols["converged"] = c["converged"]
    return list(cols), [list(r) for r in zip(*cols.values(), strict=True)]


def compared_quantities(summary: dict) -> dict:
    """The quantities a cohort compares (and ``report.reference_values`` may give), from a summary:
    volumes cm^3 (paper Table 3: IMCT without the aponeurosis; ``table3_total`` = muscle + IMAT +
    IMCT + aponeurosis, the paper's total volume; ``total`` = the whole model), F_max N, forces per
    volume N/cm^3 (``force_per_total_volume``: per whole-model volume)."""
    v = summary.get("volumes_cm3") or {}
    return {"muscle": v.get("muscle"), "imat": v.get("imat"), "imct": v.get("imct"), "aponeurosis": v.get("aponeurosis"),
            "subcutaneous_fat": v.get("subcutaneous_fat"), "total": v.get("total"), "table3_total": v.get("table3_total"),
            "F_max": summary.get("F_max_N"), "force_per_total_volume": summary.get("force_per_whole_model_volume_N_per_cm3"),
            "force_per_table3_volume": summary.get("force_per_table3_volume_N_per_cm3"),
            "force_per_muscle_volume": summary.get("force_per_muscle_volume_N_per_cm3")}


def compute_summary(res: Results, cfg: ReportConfig | None = None, extra: dict | None = None) -> tuple[dict, dict]:
    """Everything the report shows that does not need per-step fields.

    Parameters
    ----------
    res : Results
    cfg : ReportConfig, optional
    extra : dict, optional
        Run information from the caller (``title``, ``subject`` or ``label``, ``synthetic``, ...).

    Returns
    -------
    summary : dict
        JSON-ready: ``label``, ``title``, ``status``, ``failed``, ``synthetic``, ``curve`` (per-step
        α, load factor, converged, axial force per end set and end force, N; ``displacement_cm`` of
        the driving set in a displacement-driven run), ``force_sets``, ``protocol`` (``kind``
        "activation" or "displacement", :func:`~pixmuscle.report.displacement.run_protocol`; the
        activation quantities below are None for a displacement-driven run),
        ``F_max_N``, ``alpha_at_F_max``, ``volumes_cm3``, ``force_per_volume_N_per_cm3`` (F_max per
        unit total volume, the paper's: muscle + IMAT + IMCT + aponeurosis; the same as
        ``force_per_table3_volume_N_per_cm3``), ``force_per_whole_model_volume_N_per_cm3``,
        ``force_per_muscle_volume_N_per_cm3``, ``tissue_table`` (rows), ``newton`` statistics,
        ``constraint_gap``, ``stages`` (config, provenance and warnings of every stage),
        ``warnings`` (all of them), ...
    tissue : dict
        Output of :func:`pixmuscle.report.tables.tissue_table`.
    """
    cfg = cfg or ReportConfig()
    extra = dict(extra or {})
    meta = res.meta or {}
    path = meta.get("path")
    warnings = stage_warnings(res)
    if res.failed:
        warnings.append(f"the solve did not complete — {res.status}")
    s1 = res.n_states
    conv = np.asarray(res.converged, bool)
    bad = np.flatnonzero(~conv)
    if bad.size:
        warnings.append(f"{bad.size} stored step(s) did not converge: {', '.join(map(str, bad[:20]))}"
                        + (" ..." if bad.size > 20 else "") + "; they are excluded from F_max and from the field outputs")
    constrained = res.constrained_text()
    force_sets = select_force_sets(res.reaction, cfg.force_sets, constrained)
    if not force_sets:
        warnings.append("no constrained end set (z_min/z_max) has a reaction in the results file: no muscle force reported")
    ends = [s for s in sorted(res.reaction) if end_normal(s) is not None]
    axial = axial_forces(res.reaction, ends)
    fend = end_force({s: axial[s] for s in force_sets}, s1)
    for s in force_sets:
        nonfinite = conv & ~np.isfinite(axial[s])
        if nonfinite.any():
            warnings.append(f"reaction of set {s} is not finite at converged step(s) {np.flatnonzero(nonfinite).tolist()}")
    if len(force_sets) >= 2:
        stack = np.stack([axial[s] for s in force_sets])
        spread = np.where(conv, np.ptp(stack, axis=0), 0.0)
        scale = np.nanmax(np.abs(np.where(conv, fend, np.nan))) if conv.any() else 0.0
        if np.isfinite(spread).all() and scale > 0 and spread.max() > 0.05 * scale:
            k = int(np.argmax(spread))
            warnings.append(f"end forces of {', '.join(force_sets)} differ by {spread[k]:.4g} N at step {k} "
                            f"({100 * spread[k] / scale:.1f}% of the largest force): other supports carry axial load "
                            "or equilibrium is not reached; the mean is reported")
    ok = conv & np.isfinite(fend)
    f_max = a_at = None
    if ok.any():
        k = np.flatnonzero(ok)[np.argmax(fend[ok])]
        f_max, a_at = float(fend[k]), float(res.alpha[k])
        if res.failed:
            warnings.append(f"F_max comes from the converged states only (α ≤ {float(res.alpha[ok].max()):.4g}); "
                            "the solve stopped before the planned activation, so F_max understates the force")
        if np.flatnonzero(ok).max() == 0:
            warnings.append("only the initial state (step 0) converged: F_max is the initial end force")
    elif force_sets:
        warnings.append("no converged step with a finite end force: F_max not available")

    protocol = run_protocol(res.alpha, res.prescribed)
    by_activation = protocol["kind"] == ACTIVATION
    m = res.model
    apo = None
    if "aponeurosis" in m.sets:  # node set of segment.aponeurosis_mask: not IMCT (paper Table 3)
        apo = np.zeros(m.n_nodes, bool)
        apo[np.asarray(m.sets["aponeurosis"], np.int64)] = True
    tissue = tissue_table(m.ijk, m.tissue, m.muscle_id, m.shape, m.spacing, m.muscle_names, f_max=f_max if by_activation else None,
                          rule=cfg.imat_rule, attach_distance=cfg.attach_distance, aponeurosis=apo)
    vol = tissue["volumes_cm3"]
    per_step = newton_per_step(res.newton, s1)
    cut = None if res.cutbacks is None else np.asarray(res.cutbacks).ravel()
    label = str(extra.get("subject") or extra.get("label") or (path.stem if path is not None else "results"))
    stages = [{k: r.get(k) for k in ("stage", "file", "config", "provenance", "warnings")} for r in stage_records(res)]
    stages.sort(key=lambda r: _STAGE_ORDER.index(r["stage"]) if r["stage"] in _STAGE_ORDER else len(_STAGE_ORDER))
    summary = {
        "label": label,
        "title": str(extra.get("title") or f"pixmuscle report — {label}"),
        "results": str(path) if path is not None else "",
        "status": res.status,
        "failed": res.failed,
        "synthetic": bool(extra.get("synthetic", False)) or bool(meta.get("synthetic"))
                     or any(r.get("synthetic") for r in meta.get("stages", [])),
        "n_nodes": m.n_nodes,
        "n_muscles": len(m.muscle_names),
        "muscle_names": list(m.muscle_names),
        "cell_volume_cm3": tissue["cell_volume_cm3"],
        "coarsen_factor": m.coarsen_factor,
        "force_sets": list(force_sets),
        "curve": {
            "step": list(range(s1)), "alpha": _floats(res.alpha), "load_factor": _floats(res.load_factor),
            "converged": [bool(c) for c in conv], "axial_force_N": {s: _floats(axial[s]) for s in ends},
            "end_force_N": _floats(fend),
        },
        "protocol": {k: v for k, v in protocol.items() if k != "displacement_cm"},
        "F_max_N": f_max,
        "alpha_at_F_max": a_at if by_activation else None,
        "volumes_cm3": vol,
        "force_per_volume_N_per_cm3": tissue["force_per_volume_N_per_cm3"] if by_activation else None,
        "force_per_muscle_volume_N_per_cm3": tissue["force_per_muscle_volume_N_per_cm3"] if by_activation else None,
        "force_per_table3_volume_N_per_cm3": tissue["force_per_table3_volume_N_per_cm3"] if by_activation else None,
        "force_per_whole_model_volume_N_per_cm3":
            tissue["force_per_whole_model_volume_N_per_cm3"] if by_activation else None,
        "tissue_table": [dict(r) for r in tissue["rows"]],
        "tissue_footnote": tissue["footnote"],
        "newton": {
            "n_steps": s1, "n_converged": int(conv.sum()), "n_steps_planned": int(res.n_steps_planned) or None,
            "iterations": [int(i) for i in res.iterations], "total_iterations": int(np.sum(res.iterations)),
            "max_iterations": int(np.max(res.iterations)) if s1 else 0,
            "final_residual": _floats(per_step["final_residual"]), "final_energy": _floats(per_step["final_energy"]),
            "final_relative_residual": _floats(per_step["final_relative_residual"]),
            "cutbacks": None if cut is None else [int(c) for c in cut],
            "cutbacks_total": None if cut is None else int(cut.sum()),
        },
        "solver_info": _jsonable(res.info),
        "constraint_gap": _jsonable(res.constraint_gap),
        "sign_convention": res.sign_convention,
        "stages": _jsonable(stages),
        "file_attributes": _jsonable(meta.get("attrs", {})),
        "warnings": warnings,
        "extra": _jsonable(extra),
        "outputs": {},
    }
    if not by_activation:
        summary["curve"]["displacement_cm"] = _floats(protocol["displacement_cm"])
    summary["compared"] = compared_quantities(summary)
    if cfg.reference_values:
        summary["reference_values"] = {"label": cfg.reference_values_label, "values": dict(cfg.reference_values)}
    return summary, tissue

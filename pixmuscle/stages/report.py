"""Report stage: results.h5 → curves, tissue table, ParaView fields, slice figures, index.html.

Outputs in ``outdir``:

``force_activation.csv`` / ``.png``   force at the fixed ends vs activation (paper Figs. 11, 15c)
``tissue_table.csv``                  volumes of muscle, IMAT, IMCT per muscle and total, F_max (Table 3)
``newton.png``                        residual history of every load step
``fields.pvd`` + ``fields/step_XXXX.vtu``   nodal fields for ParaView
``slices_displacement.png`` / ``slices_stress.png``   paper Figs. 12–13 equivalents
``summary.json``                      the plot-ready summary returned by :func:`make_report`
``index.html``                        self-contained page with all of the above
"""

from __future__ import annotations

import json
import logging
import platform
from pathlib import Path
from typing import Any

import numpy as np

from .. import __version__
from ..errors import InputError
from ..report import curves as C
from ..report.config import ReportConfig
from ..report.inputs import ReportInput, load_results
from ..report.tables import table_csv_rows, tissue_table
from ..store import _plain, sha256_file

_LOG = logging.getLogger(__name__)


def _versions() -> dict:
    import h5py
    import matplotlib
    import meshio
    import scipy

    return {"pixmuscle": __version__, "python": platform.python_version(), "numpy": np.__version__,
            "scipy": scipy.__version__, "h5py": h5py.__version__, "meshio": meshio.__version__,
            "matplotlib": matplotlib.__version__}


def _jsonable(obj: Any) -> Any:
    try:
        return json.loads(json.dumps(_plain(obj), default=str))
    except (TypeError, ValueError):
        return str(obj)


def _floats(a) -> list:
    return [None if not np.isfinite(x) else float(x) for x in np.asarray(a, float)]


def compute_summary(inp: ReportInput, cfg: ReportConfig, extra: dict | None = None) -> tuple[dict, dict]:
    """Everything the report shows that does not need per-step fields.

    Returns
    -------
    summary : dict
        JSON-ready: ``label``, ``title``, ``status``, ``failed``, ``synthetic``, ``curve`` (per-step
        α, load factor, converged, axial force per end set and end force, N), ``force_sets``,
        ``F_max_N``, ``alpha_at_F_max``, ``volumes_cm3``, ``force_per_volume_N_per_cm3``,
        ``force_per_muscle_volume_N_per_cm3``, ``tissue_table`` (rows), ``newton`` statistics,
        ``warnings``, ...
    tissue : dict
        Output of :func:`pixmuscle.report.tables.tissue_table`.
    """
    extra = dict(extra or {})
    warnings = [f"solver: {w}" for w in inp.solver_warnings]
    if inp.failed:
        warnings.append(f"the solve did not complete — {inp.status}")
    s1 = inp.n_steps
    conv = inp.converged
    bad = np.flatnonzero(~conv)
    if bad.size:
        warnings.append(f"{bad.size} stored step(s) did not converge: {', '.join(map(str, bad[:20]))}"
                        + (" ..." if bad.size > 20 else "") + "; they are excluded from F_max and from the field outputs")
    force_sets = C.select_force_sets(inp.reactions, cfg.force_sets, inp.constrained)
    if not force_sets:
        warnings.append("no constrained end set (z_min/z_max) has a reaction in the results file: no muscle force reported")
    ends = [s for s in sorted(inp.reactions) if C.end_normal(s) is not None]
    axial = C.axial_forces(inp.reactions, ends)
    fend = C.end_force({s: axial[s] for s in force_sets}, s1)
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
        f_max, a_at = float(fend[k]), float(inp.alpha[k])
        if inp.failed:
            warnings.append(f"F_max comes from the converged states only (α ≤ {float(inp.alpha[ok].max()):.4g}); "
                            "the solve stopped before the planned activation, so F_max understates the force")
        if np.flatnonzero(ok).max() == 0:
            warnings.append("only the initial state (step 0) converged: F_max is the initial end force")
    elif force_sets:
        warnings.append("no converged step with a finite end force: F_max not available")

    m = inp.model
    tissue = tissue_table(m.ijk, m.tissue, m.muscle_id, m.shape, m.spacing, m.muscle_names, f_max=f_max,
                          rule=cfg.imat_rule, attach_distance=cfg.attach_distance)
    vol = tissue["volumes_cm3"]
    per_step = C.newton_per_step(inp.newton, s1)
    cut = None if inp.cutbacks is None else np.asarray(inp.cutbacks).ravel()
    label = str(extra.get("subject") or extra.get("label") or inp.path.stem)
    summary = {
        "label": label,
        "title": str(extra.get("title") or f"pixmuscle report — {label}"),
        "results": str(inp.path),
        "status": inp.status,
        "failed": inp.failed,
        "synthetic": bool(extra.get("synthetic", False)) or inp.synthetic,
        "n_nodes": m.n_nodes,
        "n_muscles": len(m.muscle_names),
        "muscle_names": list(m.muscle_names),
        "cell_volume_cm3": tissue["cell_volume_cm3"],
        "coarsen_factor": m.coarsen_factor,
        "force_sets": list(force_sets),
        "curve": {
            "step": list(range(s1)), "alpha": _floats(inp.alpha), "load_factor": _floats(inp.load_factor),
            "converged": [bool(c) for c in conv], "axial_force_N": {s: _floats(axial[s]) for s in ends},
            "end_force_N": _floats(fend),
        },
        "F_max_N": f_max,
        "alpha_at_F_max": a_at,
        "volumes_cm3": vol,
        "force_per_volume_N_per_cm3": tissue["force_per_volume_N_per_cm3"],
        "force_per_muscle_volume_N_per_cm3": (f_max / vol["muscle"]) if f_max is not None and vol["muscle"] > 0 else None,
        "tissue_table": [{k: v for k, v in r.items()} for r in tissue["rows"]],
        "tissue_footnote": tissue["footnote"],
        "newton": {
            "n_steps": s1, "n_converged": int(conv.sum()), "n_steps_planned": _int_or_none(inp.info.get("n_steps_planned")),
            "iterations": [int(i) for i in inp.iterations], "total_iterations": int(inp.iterations.sum()),
            "max_iterations": int(inp.iterations.max()) if s1 else 0,
            "final_residual": _floats(per_step["final_residual"]), "final_energy": _floats(per_step["final_energy"]),
            "cutbacks": None if cut is None else [int(c) for c in cut],
            "cutbacks_total": None if cut is None else int(cut.sum()),
        },
        "warnings": warnings,
        "extra": _jsonable(extra),
        "outputs": {},
    }
    return summary, tissue


def _int_or_none(v) -> int | None:
    try:
        return int(v)
    except (TypeError, ValueError):
        return None


def _steps_table(summary: dict) -> tuple[list[str], list[list]]:
    c, nw = summary["curve"], summary["newton"]
    header = ["step", "α [-]", "load factor [-]", "Newton iterations", "final residual", "final energy norm",
              "end force [N]", "converged"]
    cols = [c["step"], c["alpha"], c["load_factor"], nw["iterations"], nw["final_residual"], nw["final_energy"],
            c["end_force_N"], c["converged"]]
    if nw["cutbacks"] is not None and len(nw["cutbacks"]) == len(c["step"]):
        header.insert(4, "cutbacks")
        cols.insert(4, nw["cutbacks"])
    return header, [list(r) for r in zip(*cols, strict=True)]


def _compare_curves(extra: dict, main: Path, force_sets_cfg) -> tuple[dict, list[str]]:
    """End-force curves of other results files named in ``extra['compare']`` (label → path)."""
    curves, warns = {}, []
    for lab, p in dict(extra.get("compare") or {}).items():
        p = Path(p)
        try:
            if p.resolve() == main.resolve():
                continue
            other = load_results(p)
            sets = C.select_force_sets(other.reactions, force_sets_cfg, other.constrained)
            f = C.end_force(C.axial_forces(other.reactions, sets), other.n_steps)
            if sets:
                curves[f"{lab} (mean of {', '.join(sets)})"] = (other.alpha, f, other.converged)
        except (InputError, OSError) as exc:
            warns.append(f"comparison curve '{lab}' not drawn: {exc}")
    return curves, warns


def make_report(results_path: str | Path, outdir: str | Path, cfg: ReportConfig | None = None,
                extra: dict | None = None) -> dict:
    """Write every report output for one results file and return the summary.

    Parameters
    ----------
    results_path : path-like
        ``results.h5`` (schema ``pixmuscle.results`` v1).
    outdir : path-like
        Output folder (created).
    cfg : ReportConfig, optional
    extra : dict, optional
        Run information from the caller: ``title``, ``subject`` (or ``label``), ``synthetic``
        (bool), ``compare`` (label → other results.h5 whose end force is overlaid, e.g. the coarse
        and fine models), ``curves`` (label → (alpha, force) overlaid as given). Everything in it
        is shown on the page.

    Returns
    -------
    dict
        The summary of :func:`compute_summary` plus ``outputs`` (paths of the written files),
        ``results_sha256`` and ``versions``. Also written to ``summary.json``.
    """
    cfg = cfg or ReportConfig()
    extra = dict(extra or {})
    results_path, outdir = Path(results_path), Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    inp = load_results(results_path)
    summary, tissue = compute_summary(inp, cfg, extra)
    warnings = summary["warnings"]
    out = summary["outputs"]
    summary["results_sha256"] = sha256_file(results_path)
    summary["versions"] = _versions()

    # force–activation ---------------------------------------------------------------------------
    header, rows = C.force_table(inp.alpha, inp.load_factor, inp.converged, inp.iterations, inp.reactions,
                                 summary["force_sets"])
    out["force_activation_csv"] = str(C.write_csv(outdir / "force_activation.csv", header, rows))
    curve = summary["curve"]
    main_label = next((lab for lab, p in dict(extra.get("compare") or {}).items()
                       if Path(p).resolve() == Path(results_path).resolve() and len(extra["compare"]) > 1), None)
    prefix = f"{main_label}: " if main_label else ""
    curves = {f"{prefix}{s} end": (inp.alpha, np.array(curve["axial_force_N"][s], float), inp.converged)
              for s in summary["force_sets"]}
    more, w = _compare_curves(extra, results_path, cfg.force_sets)
    curves.update(more)
    warnings.extend(w)
    for lab, c in dict(extra.get("curves") or {}).items():
        curves[str(lab)] = tuple(c)
    figures: dict[str, Path | None] = {}
    figures["force_activation"] = C.plot_force_activation(curves, outdir / "force_activation.png", dpi=cfg.dpi,
                                                          title=f"Isometric force vs activation — {summary['label']}")
    out["force_activation_png"] = str(figures["force_activation"])

    # tissue table -------------------------------------------------------------------------------
    out["tissue_table_csv"] = str(C.write_csv(outdir / "tissue_table.csv", tissue["header"], table_csv_rows(tissue)))

    # Newton ---------------------------------------------------------------------------------------
    figures["newton"] = C.plot_newton(inp.newton, outdir / "newton.png", dpi=cfg.dpi)
    if figures["newton"] is not None:
        out["newton_png"] = str(figures["newton"])

    # fields -------------------------------------------------------------------------------------------
    m = inp.model
    steps = _field_steps(inp, cfg, warnings)
    if cfg.vtu and steps.size:
        from ..progress import progress
        from ..report.fields import write_vtu_series

        a = inp.alpha[steps]
        times = a if np.all(np.diff(a) > 0) else steps.astype(float)
        if not np.all(np.diff(a) > 0):
            warnings.append("α does not increase over the exported steps: fields.pvd uses the step number as time")
        with progress(len(steps), "writing VTU") as bar:
            pvd, vtus = write_vtu_series(outdir, steps, times, inp.fields, X=m.X, fiber=m.fiber, tissue=m.tissue,
                                         muscle_id=m.muscle_id, imat=tissue["imat_mask"],
                                         rotation=m.rotation if cfg.vtu_frame == "rotated" else None,
                                         compression=cfg.vtu_compression, progress=bar)
        out["fields_pvd"] = str(pvd)
        out["vtu"] = [str(p) for p in vtus]
        out["vtu_steps"] = [int(s) for s in steps]
    if cfg.slices:
        figures.update(_slices(inp, cfg, summary, outdir, warnings))
        for k in ("slices_displacement", "slices_stress"):
            if figures.get(k):
                out[f"{k}_png"] = str(figures[k])

    # summary + page --------------------------------------------------------------------------------
    for w in warnings:
        _LOG.warning("report: %s", w)
    if cfg.html:
        out["index_html"] = str(outdir / "index.html")
    out["summary_json"] = str(outdir / "summary.json")
    if cfg.html:
        from ..report.html import report_page

        sh, sr = _steps_table(summary)
        text = report_page(summary, figures, tissue=tissue, steps_header=sh, steps_rows=sr,
                           solve_config_yaml=inp.config_yaml, report_config=_plain(cfg), provenance=inp.provenance,
                           info=inp.info)
        (outdir / "index.html").write_text(text, encoding="utf-8")
    (outdir / "summary.json").write_text(json.dumps(summary, indent=2, default=str))
    return summary


def _field_steps(inp: ReportInput, cfg: ReportConfig, warnings: list) -> np.ndarray:
    from ..report.fields import vtu_steps

    steps = vtu_steps(inp.converged, cfg.every_nth_step)
    if steps.size == 0 and (cfg.vtu or cfg.slices):
        warnings.append("no converged step: no field outputs (VTU, slices)")
    return steps


def _slices(inp: ReportInput, cfg: ReportConfig, summary: dict, outdir: Path, warnings: list) -> dict:
    from ..report.slices import plane_indices, plot_slices

    conv = np.flatnonzero(inp.converged)
    if cfg.slice_step is not None:
        if cfg.slice_step >= inp.n_steps:
            raise InputError(f"report.slice_step: {cfg.slice_step} but the results file has steps 0..{inp.n_steps - 1}")
        step = int(cfg.slice_step)
        if not inp.converged[step]:
            warnings.append(f"report.slice_step {step} did not converge: the slice figures show a non-converged state")
    elif conv.size:
        step = int(conv[-1])
    else:
        return {}
    m = inp.model
    fields = inp.fields(step)
    at = plane_indices(m.ijk, m.origin, m.spacing, cfg.slice_position)
    a = float(inp.alpha[step])
    figs = {}
    umag = np.linalg.norm(fields.u, axis=1)
    if not np.isfinite(umag).all():
        warnings.append(f"displacement at step {step} has {int((~np.isfinite(umag)).sum())} non-finite values (blank on the slices)")
    if np.isfinite(umag).any():
        figs["slices_displacement"] = plot_slices(
            m.ijk, m.origin, m.spacing, umag, outdir / "slices_displacement.png", label="|u| [cm]",
            title=f"Displacement magnitude, step {step} (α = {a:.3g}), on the reference configuration",
            planes_at=at, vectors=fields.u if cfg.arrows else None, cmap="viridis", dpi=cfg.dpi)
    if fields.max_principal is None:
        warnings.append("no stress in the results file: no stress slices")
    elif np.isfinite(fields.max_principal).any():
        if not np.isfinite(fields.max_principal).all():
            warnings.append(f"max principal stress at step {step} has non-finite values (blank on the slices)")
        figs["slices_stress"] = plot_slices(
            m.ijk, m.origin, m.spacing, fields.max_principal, outdir / "slices_stress.png",
            label="max principal Cauchy stress [N/cm²]",
            title=f"Maximum principal Cauchy stress, step {step} (α = {a:.3g}), on the reference configuration",
            planes_at=at, cmap="magma", dpi=cfg.dpi)
    summary["slices"] = {"step": step, "alpha": a, "plane_index_xyz": [int(i) for i in at],
                         "plane_position_cm": [float(v) for v in np.asarray(m.origin) + at * np.asarray(m.spacing)]}
    return figs


def run_report(results_path: str | Path, outdir: str | Path, cfg: ReportConfig | None = None,
               extra: dict | None = None) -> Path:
    """CLI/pipeline entry point: write the report and return the path of ``index.html``
    (of ``summary.json`` when ``cfg.html`` is false). See :func:`make_report`."""
    summary = make_report(results_path, outdir, cfg, extra)
    return Path(summary["outputs"].get("index_html") or summary["outputs"]["summary_json"])


def summarize_results(results_path: str | Path, cfg: ReportConfig | None = None, extra: dict | None = None) -> dict:
    """Summary of a results file without writing anything (used by the cohort table)."""
    return compute_summary(load_results(results_path), cfg or ReportConfig(), extra)[0]


__all__ = ["make_report", "run_report", "compute_summary", "summarize_results"]

"""Report stage: results.h5 → curves, tissue table, ParaView fields, figures, index.html.

Outputs in ``outdir``:

``force_activation.csv`` / ``.png``   force at the fixed ends vs activation (paper Figs. 11, 15c)
``tissue_table.csv``                  volumes of muscle, IMAT, IMCT per muscle and total, F_max (Table 3)
``force_displacement.csv`` / ``.png`` instead of the two above when the run is displacement-driven (α constant,
                                      a set displaced: paper Example 1), with ``report.reference_curve`` beside it
``fields.pvd`` + ``fields/step_XXXX.vtu``   the model's voxel cells with the fields, for ParaView
``fields.xdmf`` + ``fields.h5``       the same series as XDMF + HDF5
``slices_*.png``, ``newton.png``   the figures of :mod:`pixmuscle.report.figures`
``plotly.min.js``, ``view3d.js``, ``view3d_data.js``   the interactive 3-D view (:mod:`pixmuscle.report.view3d`)
``summary.json``                      the plot-ready summary returned by :func:`make_report`
``index.html``                        self-contained page with all of the above

The results file is read by :func:`pixmuscle.io.results.load_results` (the one reader); the
summary is :func:`pixmuscle.report.summary.compute_summary`.
"""

from __future__ import annotations

import json
import logging
import platform
from pathlib import Path

import numpy as np

from .. import __version__
from ..errors import InputError
from ..io.results import load_results
from ..report.config import ReportConfig
from ..report.curves import _cell, force_table, write_csv
from ..report.displacement import displacement_csv, read_reference_curve, reference_entry
from ..report.figures import Context, field_step, make_figures
from ..report.sections import ReportInputs, render
from ..report.summary import compute_summary
from ..report.tables import table_csv_rows
from ..store import _plain, sha256_file

_LOG = logging.getLogger(__name__)

#: keys that open summary.json: what the case is and its answer (the finest model's), then the rest
FIRST_KEYS = ("title", "label", "status", "synthetic", "F_max_N", "alpha_at_F_max", "discretisation",
              "force_per_volume_N_per_cm3", "force_per_muscle_volume_N_per_cm3", "n_nodes", "warnings")


def _versions() -> dict:
    """pixmuscle (with its git commit when run from a checkout) and the libraries the report used."""
    import matplotlib

    from ..store import library_versions, source_commit

    git = source_commit()
    out = {"pixmuscle": __version__}
    if git is not None:
        out["pixmuscle git commit"] = git["commit"] + (" (with local changes)" if git["modified"] else "")
    out.update(library_versions())
    out["python"] = platform.python_version()
    out["matplotlib"] = matplotlib.__version__
    return out


def default_report_dir(results_path: str | Path) -> Path:
    """Where ``pixmuscle report RESULTS`` writes without ``-o``: ``<results stem>_report`` next to the file."""
    p = Path(results_path)
    return p.with_name(f"{p.stem}_report")


def make_report(results_path: str | Path, outdir: str | Path, cfg: ReportConfig | None = None,
                extra: dict | None = None) -> dict:
    """Write every report output for one results file and return the summary.

    Parameters
    ----------
    results_path : path-like
        ``results.h5`` (schema ``pixmuscle.results`` v1).
    outdir : path-like
        Output folder, written as a unit: built under a hidden temporary name beside it and put in
        place when complete (:func:`pixmuscle.store.atomic_folder`), so a failure or a kill
        half-way leaves the previous report as it was.
    cfg : ReportConfig, optional
    extra : dict, optional
        Run information from the caller: ``title``, ``subject`` (or ``label``), ``synthetic``
        (bool), ``compare`` (label → other results.h5 whose end force is overlaid, e.g. the coarse
        and fine models), ``curves`` (label → (alpha, force) overlaid as given), the files of the
        report sections (``muscle_forces``, ``force_length``, ``dwi_qc``: see
        :class:`~pixmuscle.report.sections.ReportInputs`). Everything in it is shown on the page.

    Returns
    -------
    dict
        The summary of :func:`~pixmuscle.report.summary.compute_summary` plus ``outputs`` (paths
        of the written files), ``results_sha256`` and ``versions``. Also written to ``summary.json``.
    """
    from ..store import atomic_folder

    results_path, final = Path(results_path), Path(outdir)
    res = load_results(results_path)
    with atomic_folder(final) as work:  # written as a unit: a reader never sees two runs mixed
        return _write_report(res, results_path, work, final, cfg or ReportConfig(), dict(extra or {}))


def _write_report(res, results_path: Path, outdir: Path, final: Path, cfg: ReportConfig, extra: dict) -> dict:
    """The body of :func:`make_report`: writes into ``outdir``, records the paths under ``final``."""
    summary, tissue = compute_summary(res, cfg, extra)
    warnings = summary["warnings"]
    summary["field_step"] = field_step(res, cfg, warnings)
    if summary["field_step"] is None and (cfg.vtu or cfg.slices or cfg.view3d):
        warnings.append("no converged step: no field outputs (VTU, slices, 3-D view)")
    if cfg.slice_position is not None:
        from ..report.slices import plane_indices

        plane_indices(res.model.ijk, res.model.origin, res.model.spacing, cfg.slice_position)  # validates
    out = summary["outputs"]
    summary["results_sha256"] = sha256_file(results_path)

    header, rows = force_table(res.alpha, res.load_factor, res.converged, res.iterations, res.reaction,
                                 summary["force_sets"])
    model_parts: list[str] = []
    by_activation = summary["protocol"]["kind"] == "activation"
    if by_activation:
        others = _other_models(extra, results_path)
        if others:  # several models of one case (coarse and fine): every output for each, and their difference
            model_parts = _models(res, summary, tissue, others, outdir, final, cfg, header, rows)
        out["force_activation_csv"] = str(write_csv(outdir / "force_activation.csv", header, rows))
    else:  # displacement-driven (report/displacement.py): force vs displacement, a reference beside it
        _reference(summary, cfg)
        header, rows = displacement_csv(header, rows, summary)
        out["force_displacement_csv"] = str(write_csv(outdir / "force_displacement.csv", header, rows))
    # the registered sections (activation, per-muscle forces, force-length, DWI): fills the tissue table's per-muscle F_max
    sections = render(ReportInputs.build(res, extra, summary, tissue, outdir, cfg.dpi))
    if by_activation:
        out["tissue_table_csv"] = str(write_csv(outdir / "tissue_table.csv", tissue["header"], table_csv_rows(tissue)))

    if cfg.vtu and summary["field_step"] is not None:
        out.update(_fields(res, cfg, tissue, outdir, warnings, displacement=summary["curve"].get("displacement_cm")))

    figures = make_figures(Context(res=res, summary=summary, cfg=cfg, outdir=outdir, warnings=warnings, extra=extra))
    for key, (_, p) in figures.items():
        out[f"{key}_png"] = str(p)
    if cfg.view3d and summary["field_step"] is not None:
        from ..report.view3d import write_view

        steps = np.flatnonzero(np.asarray(res.converged, bool))
        summary["view3d"] = write_view(res, outdir, steps, imat=tissue.get("imat_mask"), max_points=cfg.view3d_max_points)
        out["view3d"] = [str(outdir / name) for name in summary["view3d"].get("files", [])]
        if "error" in summary["view3d"]:
            warnings.append(f"no interactive 3-D view: {summary['view3d']['error']}")
    summary["versions"] = _versions()
    if summary["field_step"] is not None:
        m = res.model
        from ..report.slices import plane_indices

        at = plane_indices(m.ijk, m.origin, m.spacing, cfg.slice_position)
        summary["slices"] = {"step": summary["field_step"], "alpha": float(res.alpha[summary["field_step"]]),
                             "plane_index_xyz": [int(i) for i in at],
                             "plane_position_cm": [float(v) for v in np.asarray(m.origin) + at * np.asarray(m.spacing)]}

    upstream = ("segment: ", "build-model: ", "coarsen: ", "solve: ")
    for w in warnings:  # the upstream stages' warnings were shown when those stages ran
        if not w.startswith(upstream):
            _LOG.warning("report: %s", w)
    def reroot(v):  # a path inside the folder being written → where it will be once the folder is in place
        if isinstance(v, list):
            return [reroot(x) for x in v]
        if isinstance(v, str) and Path(v).is_relative_to(outdir):
            return str(final / Path(v).relative_to(outdir))
        return v

    out.update({k: reroot(v) for k, v in out.items()})
    if cfg.html:
        out["index_html"] = str(final / "index.html")
    out["summary_json"] = str(final / "summary.json")
    if cfg.html:
        from ..report.html import report_page

        text = report_page(summary, figures, tissue=tissue, report_config=_plain(cfg),
                           sections=model_parts + list(sections))
        (outdir / "index.html").write_text(text, encoding="utf-8")
    summary = {**{k: summary[k] for k in FIRST_KEYS if k in summary}, **summary}  # the headline first
    (outdir / "summary.json").write_text(json.dumps(summary, indent=2, default=str))
    return summary


def _reference(summary: dict, cfg: ReportConfig) -> None:
    """``summary["reference"]`` from ``report.reference_curve`` (a displacement-driven run)."""
    if cfg.reference_curve is None:
        return
    d = np.array(summary["curve"]["displacement_cm"], float)
    curve = read_reference_curve(cfg.reference_curve)
    summary["reference"] = reference_entry(summary, d, cfg.reference_label, cfg.reference_curve, curve)
    if (d > curve[0].max() + 1e-9).any() or (d < curve[0].min() - 1e-9).any():
        summary["warnings"].append(f"report.reference_curve covers {curve[0].min():.3g}–{curve[0].max():.3g} cm, the run "
                                   f"{d.min():.3g}–{d.max():.3g} cm: no comparison outside")


def _other_models(extra: dict, results_path: Path) -> dict[str, Path]:
    """The other models' results files of ``extra["compare"]`` (label → path), and the main one's label
    under the key ``None``; empty when there is no other model."""
    compare = {str(k): Path(v) for k, v in dict(extra.get("compare") or {}).items()}
    main = next((k for k, p in compare.items() if p.resolve() == results_path.resolve()), None)
    others = {k: p for k, p in compare.items() if k != main}
    if not others:
        return {}
    return {None: main or results_path.stem, **others}


def _models(res, summary: dict, tissue: dict, others: dict, outdir: Path, final: Path, cfg: ReportConfig,
            header: list, rows: list) -> list[str]:
    """Outputs of the other models (``<label>/``: force_activation.csv, tissue_table.csv, fields,
    slice figures, summary.json), their end force added to the main CSV rows, ``summary["models"]``
    and ``summary["convergence"]`` (+ ``convergence.csv``); returns the page's HTML fragment."""
    from ..report.convergence import convergence_table, discretisation_estimate, force_at
    from ..report.html import models_section

    main = others.pop(None)
    warnings = summary["warnings"]
    per_model = {main: _model_entry(summary, res, ".")}
    curves = {main: (res.alpha, np.asarray(summary["curve"]["end_force_N"], float), res.converged)}
    tissues, slice_figs = {main: tissue}, {}
    for label, path in others.items():
        try:
            other = load_results(path)
        except (InputError, OSError) as exc:
            warnings.append(f"model '{label}' not reported: {exc}")
            continue
        sub = outdir / label
        sub.mkdir(parents=True, exist_ok=True)
        s2, t2 = compute_summary(other, cfg, {**summary.get("extra", {}), "label": label})
        warnings += [f"model {label}: {w}" for w in s2["warnings"] if not w.startswith(("segment: ", "build-model: "))]
        s2["field_step"] = field_step(other, cfg, warnings)
        h2, r2 = force_table(other.alpha, other.load_factor, other.converged, other.iterations, other.reaction,
                               s2["force_sets"])
        o2 = s2["outputs"]
        o2["force_activation_csv"] = str(write_csv(sub / "force_activation.csv", h2, r2))
        o2["tissue_table_csv"] = str(write_csv(sub / "tissue_table.csv", t2["header"], table_csv_rows(t2)))
        if cfg.vtu and s2["field_step"] is not None:
            o2.update(_fields(other, cfg, t2, sub, warnings))
        figs = make_figures(Context(res=other, summary=s2, cfg=cfg, outdir=sub, warnings=warnings, extra={}),
                            sections=("slices",))
        for key, (_, p) in figs.items():
            o2[f"{key}_png"] = str(p)
        (sub / "summary.json").write_text(json.dumps(s2, indent=2, default=str))
        o2["summary_json"] = str(sub / "summary.json")
        per_model[label] = _model_entry(s2, other, label)
        curves[label] = (other.alpha, np.asarray(s2["curve"]["end_force_N"], float), other.converged)
        tissues[label], slice_figs[label] = t2, figs
    if len(curves) < 2:
        return []
    # every model's end force in the main CSV, at the main model's α (interpolated between converged states)
    alpha = np.asarray(res.alpha, float)
    for label in curves:
        f = force_at(*curves[label], alpha)
        header.append(f"end_force {label} [N]")
        for row, v in zip(rows, f, strict=True):
            row.append(_cell(v))
    nodes = {k: v["n_nodes"] for k, v in per_model.items()}
    conv = convergence_table(curves, nodes)
    summary["convergence"] = conv
    est = summary["discretisation"] = discretisation_estimate(conv, main, nodes)
    if not est["headline_is_finest"]:
        warnings.append(f"the report's headline is the {main} model, not the finest ({est['finest']}): "
                        "its numbers are the less resolved ones")
    if est["large"]:
        warnings.append(f"discretisation estimate: F_max of the {main} model differs by {100 * est['relative']:+.2g} % "
                        f"from the {est['compared_with']} model's (more than {100 * est['threshold']:g} %): the force "
                        "still depends on the resolution; a finer model would change it further")
    summary["models"] = per_model
    summary["outputs"]["convergence_csv"] = str(write_csv(outdir / "convergence.csv", conv["header"], conv["rows"]))
    def reroot(v):
        if isinstance(v, list):
            return [reroot(x) for x in v]
        return str(final / Path(v).relative_to(outdir)) if isinstance(v, str) and Path(v).is_relative_to(outdir) else v

    for entry in per_model.values():
        entry["outputs"] = {n: reroot(v) for n, v in entry["outputs"].items()}
    return [models_section(summary, tissues, slice_figs)]


def _model_entry(s: dict, res, folder: str) -> dict:
    """The per-model part of ``summary["models"]``."""
    return {"label": s["label"], "results": s["results"], "folder": folder, "n_nodes": s["n_nodes"],
            "cell_volume_cm3": s["cell_volume_cm3"], "coarsen_factor": s["coarsen_factor"],
            "spacing_cm": [float(x) for x in res.model.spacing], "status": s["status"],
            "F_max_N": s["F_max_N"], "alpha_at_F_max": s["alpha_at_F_max"], "volumes_cm3": s["volumes_cm3"],
            "force_per_volume_N_per_cm3": s["force_per_volume_N_per_cm3"],
            "force_per_muscle_volume_N_per_cm3": s["force_per_muscle_volume_N_per_cm3"],
            "curve": {"alpha": s["curve"]["alpha"], "end_force_N": s["curve"]["end_force_N"],
                      "converged": s["curve"]["converged"]},
            "outputs": s["outputs"] if folder != "." else {}}


def _fields(res, cfg: ReportConfig, tissue: dict, outdir: Path, warnings: list, displacement=None) -> dict:
    """VTU/XDMF series; time = α, or the prescribed displacement (cm) of a displacement-driven run
    (``displacement``: per state), or the step number when that does not increase."""
    from ..progress import progress
    from ..report.fields import corner_displacements, vtu_steps, write_vtu_series

    m = res.model
    steps = vtu_steps(res.converged, cfg.every_nth_step)
    a = res.alpha[steps] if displacement is None else np.abs(np.asarray(displacement, float)[steps])
    increasing = bool(np.all(np.diff(a) > 0))
    times = a if increasing else steps.astype(float)
    if not increasing:
        warnings.append(f"{'α' if displacement is None else 'the prescribed displacement'} does not increase over "
                        "the exported steps: fields.pvd uses the step number as time")
    def point_u(points, hexa):  # the RK field at the cell corners, or no point data (a warning says why)
        try:
            u, n_fallback = corner_displacements(res, steps, points, hexa)
        except InputError as exc:
            warnings.append(f"ParaView files: displacement as cell data only, no point data ({exc})")
            return None
        if n_fallback:
            warnings.append(f"ParaView files: at {n_fallback} of {points.shape[0]} cell corners the RK field is not "
                            "defined (thin features); the point displacement there is the mean of the adjacent cells")
        return u

    with progress(len(steps), "writing fields") as bar:
        written = write_vtu_series(outdir, steps, times, res.step, ijk=m.ijk, origin=m.origin, spacing=m.spacing,
                                   fiber=m.fiber, tissue=m.tissue, muscle_id=m.muscle_id,
                                   muscle_names=m.muscle_names, imat=tissue["imat_mask"],
                                   rotation=m.rotation if cfg.vtu_frame == "rotated" else None,
                                   compression=cfg.vtu_compression, xdmf=cfg.xdmf, point_u=point_u, progress=bar)
    out = {"fields_pvd": str(written["pvd"]), "vtu": [str(p) for p in written["vtu"]],
           "vtu_steps": [int(s) for s in steps]}
    if written["xdmf"] is not None:
        out["fields_xdmf"] = str(written["xdmf"])
    return out


def run_report(results_path: str | Path, outdir: str | Path | None = None, cfg: ReportConfig | None = None,
               extra: dict | None = None) -> Path:
    """CLI/pipeline entry point: write the report and return the path of ``index.html``
    (of ``summary.json`` when ``cfg.html`` is false). ``outdir`` defaults to
    :func:`default_report_dir`. See :func:`make_report`."""
    outdir = default_report_dir(results_path) if outdir is None else outdir
    summary = make_report(results_path, outdir, cfg, extra)
    return Path(summary["outputs"].get("index_html") or summary["outputs"]["summary_json"])


def summarize_results(results_path: str | Path, cfg: ReportConfig | None = None, extra: dict | None = None) -> dict:
    """Summary of a results file without writing anything (used by the cohort table)."""
    return compute_summary(load_results(results_path), cfg or ReportConfig(), extra)[0]


__all__ = ["make_report", "run_report", "compute_summary", "summarize_results", "default_report_dir"]

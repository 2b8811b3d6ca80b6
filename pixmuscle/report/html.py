"""Self-contained HTML pages: figures embedded as base64 PNG, plain tables, tiny inline CSS, no scripts."""

from __future__ import annotations

import base64
import html
import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import yaml

from .figures import SECTIONS

CSS = """
body{font-family:system-ui,sans-serif;max-width:1100px;margin:1.5em auto;padding:0 1em;color:#222}
h1{font-size:1.6em}h2{font-size:1.25em;border-bottom:1px solid #ccc;padding-bottom:.2em;margin-top:1.6em}
table{border-collapse:collapse;margin:.5em 0;font-size:.9em;display:block;max-width:100%;overflow-x:auto}
th,td{border:1px solid #bbb;padding:.25em .6em;text-align:right}th{background:#eee}
td:first-child,th:first-child{text-align:left}
.note{background:#fff6d5;border:1px solid #e0c060;padding:.6em 1em;margin:1em 0}
.fail{background:#fde2e2;border:1px solid #d66;padding:.6em 1em;margin:1em 0}
.ok{background:#e4f5e4;border:1px solid #6a6;padding:.6em 1em;margin:1em 0}
.foot{font-size:.85em;color:#444;max-width:60em}
pre{background:#f6f6f6;border:1px solid #ddd;padding:.6em;overflow-x:auto;font-size:.85em}
img{max-width:100%;display:block}
figure{margin:.6em 0}figcaption{font-size:.85em;color:#444}
h3{font-size:1.05em;margin-bottom:.2em}
""".strip()


def esc(x: Any) -> str:
    """HTML-escaped text."""
    return html.escape(str(x), quote=True)


def fmt(v: Any, digits: int = 4) -> str:
    """Short display text of a table cell (numbers to ``digits`` significant figures, '—' for none)."""
    if v is None or v == "":
        return "—"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "—"
        return f"{v:.{digits}g}"
    return str(v)


def img_tag(path: str | Path, alt: str) -> str:
    """``<img>`` with the PNG embedded as a data URI."""
    data = base64.b64encode(Path(path).read_bytes()).decode("ascii")
    return f'<img alt="{esc(alt)}" src="data:image/png;base64,{data}">'


def table(header: Sequence[str], rows: Sequence[Sequence[Any]], *, digits: int = 4) -> str:
    """Plain HTML table."""
    head = "".join(f"<th>{esc(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{esc(fmt(c, digits))}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def kv_table(items: Mapping[str, Any]) -> str:
    """Two-column key/value table."""
    return table(["item", "value"], [[k, v] for k, v in items.items()])


def page(title: str, parts: Sequence[str]) -> str:
    """A complete HTML document."""
    return ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<title>{esc(title)}</title><style>{CSS}</style></head><body>\n"
            + "\n".join(parts) + "\n</body></html>\n")


def html_units(h: str) -> str:
    """Header text with ^3/^2 shown as superscripts."""
    return h.replace("cm^3", "cm³").replace("cm^2", "cm²")


def status_box(status: str) -> str:
    cls = "fail" if status.lower().startswith("failed") else "ok" if status == "complete" else "note"
    return f'<div class="{cls}"><b>Solver status:</b> {esc(status)}</div>'


def discretisation_box(est: Mapping[str, Any]) -> str:
    """The headline model and its discretisation estimate (:func:`~pixmuscle.report.convergence.discretisation_estimate`),
    shown on the first screen; a warning box when the estimate is large or the headline is not the finest."""
    f, other = est.get("F_max_N"), est.get("compared_with")
    text = f"<b>Headline: the {esc(est['headline'])} model</b> (F_max {esc(fmt(f))} N)"
    if other is not None and est.get("relative") is not None:
        h, o = esc(est["headline"]), esc(other)
        text += (f"; discretisation estimate (F_{h} − F_{o}) / F_{h} = {100 * est['relative']:+.2g} % "
                 f"({est['difference_N']:+.4g} N; the {o} model gives {esc(fmt(est['compared_F_max_N']))} N).")
    else:
        text += "."
    warn = []
    if est.get("large"):
        warn.append(f" <b>The estimate is larger than {100 * est['threshold']:g} %</b>: the force still depends on the "
                    "resolution, and a finer model would change it further.")
    if not est.get("headline_is_finest"):
        warn.append(f" <b>This is not the finest model</b> ({esc(est['finest'])}).")
    return f'<div class="{"note" if warn else "ok"}">{text}{"".join(warn)}</div>'


def _warning_groups(warnings: Sequence[str]) -> dict[str, list[str]]:
    groups: dict[str, list[str]] = {}
    for w in warnings:
        head, _, rest = w.partition(": ")
        if head in ("segment", "build-model", "coarsen", "solve") and rest:
            groups.setdefault(head, []).append(rest)
        else:
            groups.setdefault("report", []).append(w)
    return groups


def _figures(figures: Mapping[str, Any], section: str) -> list[str]:
    out = []
    for spec, path in figures.values():
        if spec.section == section:
            out.append(f"<figure>{img_tag(path, spec.caption)}<figcaption>{esc(spec.caption)}</figcaption></figure>")
    return out


def _short(v: Any) -> Any:
    """A solver_info value for a table cell (long lists summarised)."""
    if isinstance(v, list):
        nums = [x for x in v if isinstance(x, (int, float)) and not isinstance(x, bool)]
        if len(v) > 8 and len(nums) == len(v):
            return f"{len(v)} values, total {fmt(float(sum(nums)))}, max {fmt(float(max(nums)))}"
        return ", ".join(fmt(x) for x in v)
    if isinstance(v, dict):
        return json.dumps(v, default=str)
    return v


def _unit_of(key: str) -> str:
    if key.endswith("_s"):
        return "s"
    return ""


def solver_info_table(info: Mapping[str, Any]) -> str:
    """``solver_info`` as a three-column table (quantity, value, unit)."""
    rows = [[k.replace("_", " "), _short(v), _unit_of(k)] for k, v in info.items()]
    return table(["quantity", "value", "unit"], rows)


def _provenance_rows(stages: Sequence[Mapping[str, Any]]) -> list[list]:
    rows = []
    for r in stages:
        prov = r.get("provenance") or {}
        relative = list((prov.get("inputs_relative") or {}).keys())
        for i, (p, sha) in enumerate((prov.get("inputs") or {}).items()):
            rows.append([r["stage"], relative[i] if i < len(relative) else p, sha])  # relative to the config
        git = prov.get("git") or {}
        made = f"pixmuscle {prov.get('version', '?')}" + (f" (git {git['commit'][:12]}{', modified' if git.get('modified') else ''})"
                                                          if git.get("commit") else "")
        rows.append([r["stage"], f"(output) {r.get('file', '')}", f"{made}, {prov.get('created_utc', '?')}"])
    return rows


def models_section(summary: Mapping[str, Any], tissues: Mapping[str, Mapping[str, Any]],
                   slice_figures: Mapping[str, Mapping[str, Any]]) -> str:
    """HTML fragment of a case solved on several models (coarse and fine): one facts column per
    model, the difference table against the finest (``summary["convergence"]``), each model's
    tissue table and the other models' slice figures.

    Parameters
    ----------
    summary : mapping
        With ``models`` (label → entry) and ``convergence`` (:func:`~pixmuscle.report.convergence.convergence_table`).
    tissues : mapping label → tissue table (:func:`~pixmuscle.report.tables.tissue_table`)
    slice_figures : mapping label → figures made for that model (key → (FigureSpec, PNG path))
    """
    models, conv = summary["models"], summary["convergence"]
    labels = conv["models"]
    rows = [
        ["nodes"] + [models[k]["n_nodes"] for k in labels],
        ["in-plane spacing [cm]"] + [models[k]["spacing_cm"][0] for k in labels],
        ["slice spacing [cm]"] + [models[k]["spacing_cm"][2] for k in labels],
        ["status"] + [models[k]["status"] for k in labels],
        ["F_max [N]"] + [models[k]["F_max_N"] for k in labels],
        ["α at F_max"] + [models[k]["alpha_at_F_max"] for k in labels],
        ["muscle volume [cm³]"] + [models[k]["volumes_cm3"]["muscle"] for k in labels],
        ["total volume: muscle + IMAT + IMCT + aponeurosis [cm³]"] + [models[k]["volumes_cm3"]["table3_total"]
                                                                      for k in labels],
        ["whole model volume [cm³]"] + [models[k]["volumes_cm3"]["total"] for k in labels],
        ["F_max / total volume [N/cm³]"] + [models[k]["force_per_volume_N_per_cm3"] for k in labels],
        ["F_max / muscle volume [N/cm³]"] + [models[k]["force_per_muscle_volume_N_per_cm3"] for k in labels],
        ["outputs"] + [("this page's files" if models[k]["folder"] == "." else f"folder {models[k]['folder']}/")
                       for k in labels],
    ]
    ref = conv["reference"]
    parts = ["<h2>Models compared (discretisation check, paper Example 2)</h2>",
             f'<p class="foot">The same case solved on {len(labels)} models; the reference is the finest, '
             f"<b>{esc(ref)}</b>. Relative difference = (F − F_{esc(ref)}) / |F_{esc(ref)}|.</p>",
             table(["quantity"] + labels, rows)]
    worst = conv.get("max_relative_difference") or {}
    for k in labels[:-1]:
        r, w = (conv.get("F_max_relative_difference") or {}).get(k), worst.get(k)
        parts.append(f"<p><b>{esc(k)} vs {esc(ref)}:</b> F_max differs by "
                     f"{'—' if r is None else f'{100 * r:+.3g} %'}; the largest |relative difference| over the "
                     f"activation steps is {'—' if w is None else f'{100 * w:.3g} %'}.</p>")
    parts.append("<h3>End force at each activation</h3>")
    parts.append(table(conv["header"], conv["rows"]))
    parts.append('<p class="foot">Data: <code>convergence.csv</code>; every model\'s end force is also a column of '
                 "<code>force_activation.csv</code>, and each other model has its own <code>force_activation.csv</code>, "
                 "<code>tissue_table.csv</code>, <code>fields.pvd</code> and <code>summary.json</code> in its folder.</p>")
    for k in labels:
        t = tissues.get(k)
        if t is None:
            continue
        keys = [h for h in t["header"] if not h.endswith("nodes")]
        parts.append(f"<h3>Tissue volumes — {esc(k)} model</h3>")
        parts.append(table([html_units(h) for h in keys], [[r[h] for h in keys] for r in t["rows"]]))
    for k, figs in slice_figures.items():
        if figs:
            parts.append(f"<h3>Fields on slices — {esc(k)} model</h3>")
            for spec, path in figs.values():
                parts.append(f"<figure>{img_tag(path, spec.caption)}<figcaption>{esc(k)} model: "
                             f"{esc(spec.caption)}</figcaption></figure>")
    return "\n".join(parts)


def _displacement_facts(summary: Mapping[str, Any]) -> dict:
    """Facts of a displacement-driven run (:mod:`pixmuscle.report.displacement`): what was displaced, the
    end force at the last converged state and the reference there."""
    p, c = summary["protocol"], summary["curve"]
    ok = [k for k, v in enumerate(c["converged"]) if v and c["end_force_N"][k] is not None]
    facts = {"loading": f"{p['set']} displaced along {p['component']} (prescribed displacement; no activation)",
             "volume [cm³]": summary["volumes_cm3"].get("total")}
    if ok:
        k = ok[-1]
        facts[f"end force at {p['component']} displacement {fmt(c['displacement_cm'][k])} cm [N] (step {k})"] = \
            c["end_force_N"][k]
    ref = summary.get("reference") or {}
    if ref.get("final"):
        fin = ref["final"]
        facts[f"{ref['label']} there [N]"] = fin["reference_N"]
        facts["relative difference there"] = f"{100 * fin['relative']:+.2f} %"
    if ref.get("max_abs_relative") is not None:
        facts["largest |relative difference| over the steps"] = f"{100 * ref['max_abs_relative']:.2f} %"
    return facts


def _displacement_section(summary: Mapping[str, Any], figures: Mapping[str, Any]) -> list[str]:
    """The force section of a displacement-driven run: the figure, the per-step table, the reference."""
    from .displacement import displacement_table

    ref = summary.get("reference")
    parts = ["<h2>Force–displacement</h2>",
             '<p class="foot">Displacement-driven run: the activation is constant and the end set named below is '
             "moved by a prescribed displacement, ramped over the load steps. Force at each fixed end = reaction · "
             "outward normal (N); positive = tension. Data: <code>force_displacement.csv</code>.</p>"]
    parts += _figures(figures, "force")
    h, rows = displacement_table(summary)
    parts.append(table(h, rows))
    if ref:
        parts.append(f'<p class="foot">Reference: <b>{esc(ref["label"])}</b>, from <code>{esc(ref["file"])}</code> '
                     "(report.reference_curve), interpolated linearly at the run's displacements.</p>")
    else:
        parts.append('<p class="foot">No reference curve (set <code>report.reference_curve</code> to a CSV with the '
                     "columns displacement_cm and force_N to draw one beside the force).</p>")
    return parts


def view3d_section(info: Mapping[str, Any]) -> str:
    """The interactive 3-D view (:mod:`pixmuscle.report.view3d`): controls, the plot, and a message
    that stays visible when the scripts beside the page are missing or plotly was not installed."""
    if "error" in info:
        return f'<p class="note">Interactive 3-D view not written: {esc(info["error"])}.</p>'
    shown = (f"all {info['n_nodes']} nodes" if info["n_shown"] == info["n_nodes"]
             else f"{info['n_shown']} of {info['n_nodes']} nodes (every k-th voxel in-plane)")
    options = "".join(f'<option value="{k}"{" selected" if k == "umag" else ""}>{esc(v)}</option>' for k, v in (
        ("umag", "displacement magnitude |u| [cm]"), ("s1", "largest principal stress [N/cm²]"), ("tissue", "tissue"),
        ("muscle", "muscle"), ("fibre", "fibre angle to the long axis [°]")))
    return (
        '<div id="view3d">'
        '<p class="view3d-missing note">The interactive view needs the files <code>plotly.min.js</code>, '
        '<code>view3d.js</code> and <code>view3d_data.js</code> beside this page, and JavaScript.</p>'
        '<div class="view3d-controls" hidden>'
        f'<label>field <select id="view3d-field">{options}</select></label> '
        '<label>load step <input id="view3d-step" type="range" step="1"></label> '
        '<span id="view3d-step-label"></span></div>'
        '<div id="view3d-plot" style="width:100%;height:640px"></div></div>'
        f'<p class="foot">Nodes (voxel centres) on the deformed body, displacements to scale: {esc(shown)}. '
        "Drag to rotate, scroll to zoom; the camera button saves a PNG. Colour scales are fixed over all "
        f"steps. Drawn with plotly.js {esc(info['plotly'])} (written beside the page: no network needed).</p>"
        '<script src="plotly.min.js"></script><script src="view3d_data.js"></script>'
        '<script src="view3d.js"></script>')


def report_page(summary: Mapping[str, Any], figures: Mapping[str, Any], *, tissue: Mapping[str, Any],
                report_config: Mapping[str, Any], sections: Sequence[str] = ()) -> str:
    """The report page of one results file.

    Parameters
    ----------
    summary : mapping
        The report summary (:func:`pixmuscle.report.summary.compute_summary` plus ``outputs``,
        ``results_sha256`` and ``versions``).
    figures : mapping key → (FigureSpec, PNG path)
        The figures made (:func:`pixmuscle.report.figures.make_figures`), shown in their sections.
    tissue : mapping
        Output of :func:`pixmuscle.report.tables.tissue_table`.
    report_config : mapping
        The report section as plain data.
    sections : list of str
        Further HTML fragments (the per-model comparison and the registered sections of
        :mod:`pixmuscle.report.sections`), placed before the solver statistics.
    """
    parts = _page_head(summary) + _warnings_section(summary) + _main_result_section(summary, figures, tissue)
    parts += _segmentation_section(summary, figures) + _model_and_slices_section(summary, figures)
    parts += list(sections)
    parts += _solver_section(summary, figures) + _configuration_section(summary, report_config)
    parts += _provenance_section(summary)
    return page(summary["title"], parts)


def _page_head(summary: Mapping[str, Any]) -> list[str]:
    """Title, notes on the inputs, the status and the key facts of the results."""
    parts = [f"<h1>{esc(summary['title'])}</h1>"]
    if summary.get("synthetic"):
        parts.append('<div class="note"><b>Synthetic inputs.</b> This model was built from synthetic phantom '
                     "images generated by pixmuscle, not from subject MRI/DTI. Numbers illustrate the method only.</div>")
    parts.append(status_box(summary["status"]))
    stale = (summary.get("extra") or {}).get("stale_inputs")
    if stale:
        parts.append('<div class="fail"><b>Inputs made under another configuration</b> (run with '
                     "<code>--allow-stale</code>): " + "; ".join(esc(s) for s in stale) + ". The numbers and the "
                     "configuration below are those of the files as they were made, not of the current config file.</div>")
    if summary.get("discretisation"):
        parts.append(discretisation_box(summary["discretisation"]))
    fmax = summary.get("F_max_N")
    nw = summary["newton"]
    by_displacement = _by_displacement(summary)
    facts = {
        "results file": summary["results"],
        "nodes": summary["n_nodes"],
        "muscles": ", ".join(summary.get("muscle_names") or []) or "none",
        "cell volume [cm³]": summary["cell_volume_cm3"],
        "coarsen factor": summary.get("coarsen_factor"),
        "force sets (axial reaction R·n_out)": ", ".join(summary["force_sets"]) or "none",
    }
    if by_displacement:
        facts.update(_displacement_facts(summary))
    else:
        facts.update({"F_max [N] (converged steps)": fmax, "α at F_max": summary.get("alpha_at_F_max"),
                      "F_max / total volume (muscle + IMAT + IMCT + aponeurosis) [N/cm³]":
                          summary.get("force_per_volume_N_per_cm3")})
    facts["converged states"] = (f"{nw['n_converged']} of {nw['n_steps']} stored"
                                 + (f" (load steps planned: {nw['n_steps_planned']}, plus the initial state)"
                                    if nw.get("n_steps_planned") else ""))
    parts.append(kv_table(facts))
    return parts


def _warnings_section(summary: Mapping[str, Any]) -> list[str]:
    """Every stage's warnings."""
    parts = []
    parts.append("<h2>Warnings</h2>")
    groups = _warning_groups(summary["warnings"])
    if groups:
        for stage in ("segment", "build-model", "coarsen", "solve", "report"):
            if stage in groups:
                parts.append(f"<h3>{esc(stage)}</h3><ul>" + "".join(f"<li>{esc(w)}</li>" for w in groups[stage]) + "</ul>")
    else:
        parts.append("<p>None, in any stage.</p>")
    return parts


def _main_result_section(summary: Mapping[str, Any], figures: Mapping[str, Any], tissue: Mapping[str, Any]) -> list[str]:
    """The force against activation and the tissue table, or the displacement-driven protocol's section."""
    parts = []
    if _by_displacement(summary):
        parts += _displacement_section(summary, figures)
    else:
        parts.append(f"<h2>{esc(SECTIONS['force'])}</h2>")
        parts.append('<p class="foot">Force at each fixed end = reaction · outward normal (N); positive = the muscle '
                     "pulls on the support. Data: <code>force_activation.csv</code>.</p>")
        parts += _figures(figures, "force")

        parts.append("<h2>Tissue volumes and force (paper Table 3)</h2>")
        hdr = [html_units(h) for h in tissue["header"] if not h.endswith("nodes")]
        keys = [h for h in tissue["header"] if not h.endswith("nodes")]
        parts.append(table(hdr, [[r[k] for k in keys] for r in tissue["rows"]]))
        parts.append(f'<p class="foot">{esc(tissue["footnote"])} Cell volume {fmt(tissue["cell_volume_cm3"])} cm³. '
                     "Data (with node counts): <code>tissue_table.csv</code>.</p>")
    return parts


def _segmentation_section(summary: Mapping[str, Any], figures: Mapping[str, Any]) -> list[str]:
    """Segmentation figures, warnings and areas per slice, where there are any."""
    parts = []
    qc = summary.get("segmentation_qc") or {}
    seg_figs = _figures(figures, "segmentation")
    if seg_figs or qc:
        parts.append(f"<h2>{esc(SECTIONS['segmentation'])}</h2>")
        parts += seg_figs
        if qc.get("note"):
            parts.append(f'<p class="foot">{esc(qc["note"])}</p>')
        seg_w = _warning_groups(summary["warnings"]).get("segment", [])
        if seg_w:
            parts.append("<p><b>Warnings of the segment stage:</b></p><ul>"
                         + "".join(f"<li>{esc(w)}</li>" for w in seg_w) + "</ul>")
        if qc.get("areas"):
            parts.append("<h3>Area per slice [cm²]</h3>")
            parts.append(table([html_units(h) for h in qc["areas_header"]], qc["areas"]))
            parts.append(f'<p class="foot">From <code>{esc(qc["file"])}</code>; data: '
                         "<code>segmentation_areas.csv</code>.</p>")
    return parts


def _model_and_slices_section(summary: Mapping[str, Any], figures: Mapping[str, Any]) -> list[str]:
    """The 3-D view, the slice figures and the ParaView note."""
    parts = []
    if summary.get("view3d"):
        parts.append(f"<h2>{esc(SECTIONS['model'])}</h2>")
        parts.append(view3d_section(summary["view3d"]))

    parts.append(f"<h2>{esc(SECTIONS['slices'])}</h2>")
    slice_figs = _figures(figures, "slices")
    parts += slice_figs or ["<p>Not made (disabled or no converged step with data).</p>"]
    if slice_figs and (summary.get("slices") or {}).get("plane_position_cm"):
        pos = summary["slices"]["plane_position_cm"]
        parts.append(f'<p class="foot">Planes through x = {pos[0]:.3g} cm, y = {pos[1]:.3g} cm, z = {pos[2]:.3g} cm. '
                     "Arrows: in-plane displacement, drawn to the length scale given in the figure key.</p>")
    if summary["outputs"].get("fields_pvd"):
        clock = ("the prescribed displacement in cm, or step number when it does not increase" if _by_displacement(summary)
                 else "activation α, or step number when α does not increase")
        parts.append(f'<p class="foot">ParaView: open <code>fields.pvd</code> (time = {clock}) '
                     "or <code>fields.xdmf</code>. The files hold the model's voxel cells "
                     "(reference configuration, cm): Slice, Clip and Threshold return cells; apply <i>Warp By Vector</i> "
                     "with <code>displacement [cm]</code> for the deformed body: its point data is the model's own "
                     "field at the cell corners (the RK approximation Σ Ψ_J(x) d_J); stresses are cell data (each "
                     "node's cell). Units, the tissue and muscle names and these notes are in the field data.</p>")
    return parts


def _solver_section(summary: Mapping[str, Any], figures: Mapping[str, Any]) -> list[str]:
    """Newton's statistics, the constraint gap and the solver's information."""
    parts = []
    from .summary import newton_table

    nw = summary["newton"]
    parts.append(f"<h2>{esc(SECTIONS['solver'])}</h2>")
    parts.append(kv_table({"status": summary["status"], "total Newton iterations": nw["total_iterations"],
                           "max iterations in a step": nw["max_iterations"],
                           "cutbacks": nw["cutbacks_total"] if nw["cutbacks_total"] is not None else "not recorded"}))
    sh, sr = newton_table(summary)
    parts.append(table(sh, sr))
    parts += _figures(figures, "solver")
    gap = summary.get("constraint_gap") or {}
    if gap:
        parts.append("<h3>Constraint gap (penalty boundary conditions)</h3>")
        rows = [[k, v.get("max_cm"), None if v.get("relative") is None else 100 * v["relative"]] for k, v in sorted(gap.items())]
        parts.append(table(["node set", "max error of the constrained components [cm]",
                            "relative to the largest displacement [%]"], rows))
    if summary.get("solver_info"):
        parts.append("<h3>Solver information</h3>")
        parts.append(solver_info_table(summary["solver_info"]))
    if summary.get("file_attributes"):
        parts.append("<h3>Other attributes of the results file</h3>")
        parts.append(kv_table(summary["file_attributes"]))
    if summary.get("sign_convention"):
        parts.append(f'<p class="foot"><b>sign convention:</b> {esc(summary["sign_convention"])}</p>')
    return parts


def _configuration_section(summary: Mapping[str, Any], report_config: Mapping[str, Any]) -> list[str]:
    """Each stage's configuration, the report's and the run information."""
    parts = []
    parts.append("<h2>Configuration</h2>")
    for r in summary.get("stages", []):
        parts.append(f"<h3>{esc(r['stage'])}</h3>")
        parts.append(f"<pre>{esc(r.get('config') or '(not recorded)')}</pre>")
    parts.append("<h3>report</h3>")
    parts.append(f"<pre>{esc(yaml.safe_dump(dict(report_config), sort_keys=False))}</pre>")
    if summary.get("extra"):
        parts.append("<h3>run information</h3>")
        parts.append(f"<pre>{esc(json.dumps(summary['extra'], indent=2, default=str))}</pre>")
    return parts


def _provenance_section(summary: Mapping[str, Any]) -> list[str]:
    """The results' SHA-256, versions and every stage's input files."""
    parts = []
    parts.append("<h2>Provenance</h2>")
    parts.append(kv_table({"results SHA-256": summary["results_sha256"], **summary["versions"]}))
    prov_rows = _provenance_rows(summary.get("stages", []))
    if prov_rows:
        parts.append(table(["stage", "input file (relative to the config file where recorded)", "SHA-256"], prov_rows))
    return parts


def _by_displacement(summary: Mapping[str, Any]) -> bool:
    """Whether the results are of a displacement-driven protocol (not an activation ramp)."""
    return (summary.get("protocol") or {}).get("kind") == "displacement"

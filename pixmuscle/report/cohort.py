"""Cohort comparison (paper Example 3, Table 3 and Fig. 15c): volumes and force of several subjects.

The first subject is the reference: every quantity is also given as a ratio to it (Table 3's
"Old normalized by Young" column).
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from .curves import plot_force_activation, write_csv
from .html import esc, html_units, img_tag, page, table

#: (column header, key of the summary's ``compared`` quantities) of the quantities compared
QUANTITIES = (
    ("muscle [cm^3]", "muscle"),
    ("IMAT [cm^3]", "imat"),
    ("IMCT, without aponeurosis [cm^3]", "imct"),
    ("aponeurosis [cm^3]", "aponeurosis"),
    ("subcutaneous fat [cm^3]", "subcutaneous_fat"),
    ("Table 3 total: muscle + IMAT + IMCT + aponeurosis [cm^3]", "table3_total"),
    ("model total volume [cm^3]", "total"),
    ("F_max [N]", "F_max"),
    ("F_max / Table 3 total volume [N/cm^3]", "force_per_table3_volume"),
    ("F_max / muscle volume [N/cm^3]", "force_per_muscle_volume"),
    ("F_max / model total volume [N/cm^3]", "force_per_total_volume"),
)


def _compared(s: Mapping[str, Any]) -> dict:
    from .summary import compared_quantities

    return dict(s.get("compared") or compared_quantities(dict(s)))


def resolve_summary(entry: Mapping[str, Any], where: str = "report") -> dict:
    """The report summary of one cohort entry.

    An entry is either a summary returned by :func:`pixmuscle.stages.report.make_report` (or
    read from a report's ``summary.json``), or a mapping with ``report``: the path of a report's
    ``index.html`` or folder, next to which ``summary.json`` lies. ``name`` (if present) becomes
    the label. Nothing is computed here: a results file without a report is summarised by the
    caller (the pipeline) first.
    """
    if not isinstance(entry, Mapping):
        raise InputError(f"{where}: expected a mapping (report summary or pipeline summary), got {type(entry).__name__}")
    if "volumes_cm3" in entry and "F_max_N" in entry:
        s = dict(entry)
    elif entry.get("report"):
        p = Path(entry["report"])
        js = p / "summary.json" if p.is_dir() else p.with_name("summary.json")
        if not js.exists():
            raise InputError(f"{where}: report summary {js} not found (run the report stage first)")
        s = json.loads(js.read_text())
    else:
        raise InputError(f"{where}: has neither report data (volumes_cm3, F_max_N) nor a 'report' path")
    if entry.get("name"):
        s["label"] = str(entry["name"])
    return s


def _rel(path: str | Path, start: Path) -> str:
    """Link target relative to the cohort folder (POSIX separators)."""
    return Path(os.path.relpath(Path(path).resolve(), start.resolve())).as_posix()


def _ratio(v, ref):
    if v is None or ref is None or not np.isfinite(ref) or ref == 0:
        return None
    return float(v) / float(ref)


def cohort_summary(reports: Sequence[Mapping[str, Any]], outdir: str | Path, *, failures: Sequence[Mapping] | None = None,
                   dpi: int = 120, title: str = "Cohort comparison") -> Path:
    """Write ``cohort.csv``, ``cohort_force_activation.png`` and ``cohort.html`` comparing subjects.

    Parameters
    ----------
    reports : list of mappings
        One entry per subject (see :func:`resolve_summary`); the first is the reference.
    outdir : path-like
    failures : list of {"name", "error"}, optional
        Subjects that failed before a report existed; listed on the page.

    Returns
    -------
    Path of ``cohort.html``.
    """
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    failures = list(failures or [])
    if not reports and not failures:
        raise InputError("cohort_summary: no subjects given")
    sums = [resolve_summary(r, f"cohort entry {i}") for i, r in enumerate(reports)]
    values = [[_compared(s).get(q) for _, q in QUANTITIES] for s in sums]
    refs = [(s.get("reference_values") or {}) for s in sums]
    ref_values = [[(r.get("values") or {}).get(q) for _, q in QUANTITIES] for r in refs]
    has_ref = any(r.get("values") for r in refs)
    ref = values[0] if values else []
    header = ["subject", "status"] + [h for h, _ in QUANTITIES] + [f"{h.split(' [')[0]} (ratio to first)" for h, _ in QUANTITIES]
    if has_ref:
        header += [f"{h} ({refs[0].get('label') or 'reference'})" for h, _ in QUANTITIES]
        header += [f"{h.split(' [')[0]} (ratio to first, reference)" for h, _ in QUANTITIES]
    rows = []
    for i, (s, v) in enumerate(zip(sums, values, strict=True)):
        ratios = [_ratio(x, r) for x, r in zip(v, ref, strict=True)]
        row = [s["label"], s["status"]] + v + ratios
        if has_ref:
            row += ref_values[i] + [_ratio(x, r) for x, r in zip(ref_values[i], ref_values[0], strict=True)]
        rows.append(row)
    csv_rows = [[("" if c is None else repr(float(c)) if isinstance(c, (float, np.floating)) else c) for c in r] for r in rows]
    write_csv(outdir / "cohort.csv", header, csv_rows)

    curves = {}
    for s in sums:
        c = s.get("curve", {})
        if c.get("alpha") and s.get("force_sets"):
            f = np.array([np.nan if x is None else x for x in c["end_force_N"]], float)
            curves[s["label"]] = (np.array(c["alpha"], float), f, np.array(c["converged"], bool))
    png = None
    if curves:
        png = plot_force_activation(curves, outdir / "cohort_force_activation.png", dpi=dpi,
                                    title="Force vs activation by subject")

    parts = [f"<h1>{esc(title)}</h1>"]
    if any(s.get("synthetic") for s in sums):
        parts.append('<div class="note"><b>Synthetic inputs.</b> At least one subject was built from synthetic '
                     "phantom images, not subject MRI/DTI.</div>")
    if sums:
        labels = [s["label"] for s in sums]
        rl = (refs[0].get("label") or "reference") if has_ref else ""
        t_head = ["quantity"]
        for lab in labels:
            t_head += [lab] + ([f"{lab} ({rl})"] if has_ref else [])
        for lab in labels[1:]:
            t_head += [f"{lab} / {labels[0]}"] + ([f"{lab} / {labels[0]} ({rl})"] if has_ref else [])
        t_rows = []

        def pct(x, r0):
            return None if (r := _ratio(x, r0)) is None else f"{100 * r:.1f}%"

        for qi, (h, _) in enumerate(QUANTITIES):
            row = [html_units(h)]
            for i in range(len(sums)):
                row += [values[i][qi]] + ([ref_values[i][qi]] if has_ref else [])
            for i in range(1, len(sums)):
                row += [pct(values[i][qi], ref[qi])] + ([pct(ref_values[i][qi], ref_values[0][qi])] if has_ref else [])
            t_rows.append(row)
        t_rows.append(["status"] + sum(([s["status"]] + ([""] if has_ref else []) for s in sums), [])
                      + [""] * ((len(labels) - 1) * (2 if has_ref else 1)))
        parts.append("<h2>Volumes and force (paper Table 3 layout)</h2>")
        parts.append(table(t_head, t_rows))
        parts.append('<p class="foot">Volumes = node count × cell volume. F_max = largest end force over converged '
                     "steps (whole model). Ratios are to the first subject. IMCT excludes the aponeurosis (when the "
                     "segment stage had an aponeurosis mask) and the skin, as paper Table 3; the Table 3 total is the muscle "
                     "with its outer connective tissue, without subcutaneous fat and skin (the paper's 'total volume "
                     "including the outer layer of connective tissue'). Per-subject definitions are in each subject's "
                     "report. Data: <code>cohort.csv</code>.</p>")
    if png is not None:
        parts.append("<h2>Force–activation</h2>")
        parts.append(img_tag(png, "force vs activation by subject"))
    warn = [(s["label"], w) for s in sums for w in s.get("warnings", [])]
    if failures or warn:
        parts.append("<h2>Failures and warnings</h2><ul>")
        parts += [f'<li class="fail">{esc(f.get("name", "?"))}: {esc(f.get("error", ""))}</li>' for f in failures]
        parts += [f"<li>{esc(lab)}: {esc(w)}</li>" for lab, w in warn]
        parts.append("</ul>")
    links = [(s["label"], s.get("outputs", {}).get("index_html")) for s in sums]
    if any(p for _, p in links):
        parts.append("<h2>Subject reports</h2><ul>")
        parts += [f'<li><a href="{esc(_rel(p, outdir))}">{esc(lab)}</a></li>' for lab, p in links if p]
        parts.append("</ul>")
    out = outdir / "cohort.html"
    out.write_text(page(title, parts), encoding="utf-8")
    return out

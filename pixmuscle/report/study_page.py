"""Parameter-study summary: F_max and force per unit volume of every case against each varied key.

Input: one row per case (subject × combination of the varied values) with the case's report
summary (``summary.json`` data, see :func:`pixmuscle.stages.report.make_report`). Output, in
``outdir``: ``study.csv`` (one line per case), ``study_<key>.png`` (F_max and F_max / total volume
against that key, one line per subject and combination of the other keys), ``study_ratio.png``
(with several subjects: each subject's force per unit volume divided by the first subject's at the
same combination) and ``study.html`` which states how much that ratio changes over the study.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..study import format_value, short_names
from .curves import _pyplot, write_csv
from .html import esc, html_units, img_tag, page, table

#: a relative change of the subject ratio below this is reported as "does not depend"
RATIO_TOLERANCE = 0.02

_FPV = "force_per_volume_N_per_cm3"


def _num(v) -> float:
    return float("nan") if v is None else float(v)


def _numeric(values: Sequence[Any]) -> bool:
    return all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values)


def ratio_table(rows: Sequence[Mapping[str, Any]], keys: Sequence[str], subjects: Sequence[str]) -> list[dict]:
    """Per combination and per subject after the first: force per volume ÷ the first subject's.

    Returns
    -------
    list of dict
        ``case``, ``params`` (key → value), ``subject``, ``ratio`` (float or None).
    """
    ref = subjects[0]
    fpv = {(r["case"], r["subject"]): (r["summary"] or {}).get(_FPV) for r in rows}
    params = {r["case"]: r["params"] for r in rows}
    out = []
    for case in dict.fromkeys(r["case"] for r in rows):
        for s in subjects[1:]:
            a, b = fpv.get((case, s)), fpv.get((case, ref))
            ratio = float(a) / float(b) if a is not None and b not in (None, 0) else None
            out.append({"case": case, "params": params[case], "subject": s, "ratio": ratio})
    return out


def ratio_dependence(ratios: Sequence[Mapping[str, Any]], keys: Sequence[str]) -> dict:
    """How much the subject ratio changes over the study, overall and along each key.

    Returns
    -------
    dict
        subject → {``min``, ``max``, ``mean``, ``spread`` ((max − min) / mean), ``per_key``: key →
        largest relative change of the ratio when only that key varies}. Cases without a
        ratio are left out.
    """
    out = {}
    for s in dict.fromkeys(r["subject"] for r in ratios):
        rs = [r for r in ratios if r["subject"] == s and r["ratio"] is not None]
        if not rs:
            continue
        v = np.array([r["ratio"] for r in rs])
        mean = float(v.mean())
        per_key = {}
        for k in keys:
            groups: dict[tuple, list[float]] = {}
            for r in rs:
                other = tuple(format_value(r["params"][o]) for o in keys if o != k)
                groups.setdefault(other, []).append(r["ratio"])
            change = max((max(g) - min(g) for g in groups.values() if len(g) > 1), default=0.0)
            per_key[k] = change / abs(mean) if mean else float("nan")
        out[s] = {"min": float(v.min()), "max": float(v.max()), "mean": mean,
                  "spread": float((v.max() - v.min()) / abs(mean)) if mean else float("nan"), "per_key": per_key,
                  "n": len(rs)}
    return out


def _plot_against(rows, key: str, keys, path: Path, dpi: int) -> Path:
    """F_max and F_max / total volume against ``key``: one line per subject × other-key values."""
    plt = _pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(10.0, 4.0), layout="constrained")
    others = [k for k in keys if k != key]
    tails = dict(zip(keys, short_names(list(keys)), strict=True))
    values = list(dict.fromkeys(r["params"][key] for r in rows))
    numeric = _numeric(values)
    pos = {format_value(v): (float(v) if numeric else i) for i, v in enumerate(values)}
    lines: dict[str, list] = {}
    for r in rows:
        label = r["subject"] + "".join(f", {tails[o]}={format_value(r['params'][o])}" for o in others)
        lines.setdefault(label, []).append(r)
    markers = "osD^v<>ph*"
    for n, (label, rs) in enumerate(lines.items()):
        rs = sorted(rs, key=lambda r: pos[format_value(r["params"][key])])
        x = [pos[format_value(r["params"][key])] for r in rs]
        s = [r["summary"] or {} for r in rs]
        for ax, q in zip(axes, ("F_max_N", _FPV), strict=True):
            ax.plot(x, [_num(si.get(q)) for si in s], marker=markers[n % len(markers)], markersize=4, label=label)
    for ax, yl in zip(axes, ("F_max [N]", "F_max / total volume [N/cm³]"), strict=True):
        ax.set_xlabel(tails[key])
        ax.set_ylabel(yl)
        ax.grid(alpha=0.3)
        if not numeric:
            ax.set_xticks(range(len(values)), [format_value(v) for v in values])
    axes[1].legend(fontsize=7)
    fig.suptitle(f"F_max and force per unit volume vs {key}")
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def _plot_ratio(ratios, keys, ref: str, path: Path, dpi: int) -> Path:
    plt = _pyplot()
    fig, axes = plt.subplots(1, len(keys), figsize=(5.0 * len(keys), 3.8), layout="constrained", squeeze=False)
    tails = dict(zip(keys, short_names(list(keys)), strict=True))
    for ax, key in zip(axes[0], keys, strict=True):
        values = list(dict.fromkeys(r["params"][key] for r in ratios))
        numeric = _numeric(values)
        pos = {format_value(v): (float(v) if numeric else i) for i, v in enumerate(values)}
        lines: dict[str, list] = {}
        for r in ratios:
            label = r["subject"] + "".join(f", {tails[o]}={format_value(r['params'][o])}" for o in keys if o != key)
            lines.setdefault(label, []).append(r)
        for label, rs in lines.items():
            rs = sorted(rs, key=lambda r: pos[format_value(r["params"][key])])
            ax.plot([pos[format_value(r["params"][key])] for r in rs], [_num(r["ratio"]) for r in rs], marker="o",
                    markersize=4, label=label)
        ax.set_xlabel(tails[key])
        ax.set_ylabel(f"force per volume ÷ {ref}'s [-]")
        ax.grid(alpha=0.3)
        if not numeric:
            ax.set_xticks(range(len(values)), [format_value(v) for v in values])
        ax.legend(fontsize=7)
    fig.suptitle(f"Force per unit volume relative to {ref}")
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def _answer(dep: Mapping[str, Any], keys: Sequence[str], ref: str) -> list[str]:
    parts = [f"<h2>Does the ratio of force per unit volume to {esc(ref)}'s depend on the varied parameters?</h2>"]
    for s, d in dep.items():
        big = d["spread"] >= RATIO_TOLERANCE
        verdict = (f"<b>Yes, by {100 * d['spread']:.1f} %</b> of its mean over these {d['n']} combinations" if big else
                   f"<b>Hardly</b>: it changes by only {100 * d['spread']:.2f} % of its mean over these {d['n']} combinations")
        per = "; ".join(f"{esc(k)} alone: up to {100 * v:.2f} %" for k, v in d["per_key"].items())
        parts.append(f"<p>{esc(s)} / {esc(ref)}: {verdict} (from {d['min']:.4g} to {d['max']:.4g}, mean "
                     f"{d['mean']:.4g}). Changing one key with the others fixed: {per}.</p>")
    parts.append(f'<p class="foot">Force per unit volume = F_max / total volume, the paper\'s total volume: muscle + '
                 "IMAT + IMCT + aponeurosis (without subcutaneous fat and skin). "
                 f"A change below {100 * RATIO_TOLERANCE:.0f} % of the mean is called “hardly”; the numbers are given "
                 "so that a reader can apply another threshold. Cases that failed are left out.</p>")
    return parts


def _rel(path: str | Path, start: Path) -> str:
    return Path(os.path.relpath(Path(path).resolve(), start.resolve())).as_posix()


def study_summary(rows: Sequence[Mapping[str, Any]], keys: Sequence[str], outdir: str | Path, *,
                  subjects: Sequence[str], cohort_pages: Mapping[str, str] | None = None, dpi: int = 110,
                  title: str = "Parameter study") -> Path:
    """Write ``study.csv``, the study plots and ``study.html``.

    Parameters
    ----------
    rows : list of mappings
        One per case: ``subject``, ``case`` (folder name of the combination), ``params`` (key →
        value), ``summary`` (report summary dict, or None when the case failed), ``error`` (str or
        None), ``output_dir``.
    keys : list of str
        The varied dotted keys, in order.
    outdir : path-like
    subjects : list of str
        Subject names in config order; the first is the reference of the ratios.
    cohort_pages : mapping case → path of its cohort.html, optional

    Returns
    -------
    Path of ``study.html``.
    """
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    keys = list(keys)
    ok = [r for r in rows if r.get("summary")]
    header = ["case", "subject", *keys, "status", "F_max [N]", "F_max / total volume [N/cm^3]",
              "F_max / muscle volume [N/cm^3]", "muscle [cm^3]", "total volume: muscle + IMAT + IMCT + aponeurosis [cm^3]",
              "error"]
    table_rows = []
    for r in rows:
        s = r.get("summary") or {}
        vol = s.get("volumes_cm3", {})
        table_rows.append([r["case"], r["subject"], *[r["params"][k] for k in keys],
                           s.get("status", "failed" if r.get("error") else ""), s.get("F_max_N"), s.get(_FPV),
                           s.get("force_per_muscle_volume_N_per_cm3"), vol.get("muscle"), vol.get("table3_total"),
                           r.get("error") or ""])
    csv_rows = [[("" if c is None else repr(float(c)) if isinstance(c, (float, np.floating)) else c) for c in row]
                for row in table_rows]
    write_csv(outdir / "study.csv", header, csv_rows)

    parts = [f"<h1>{esc(title)}</h1>",
             f"<p>{len(rows)} cases: {len(subjects)} subject(s) × {len(dict.fromkeys(r['case'] for r in rows))} "
             f"combination(s) of {', '.join(f'<code>{esc(k)}</code>' for k in keys)}.</p>"]
    if any((r.get("summary") or {}).get("synthetic") for r in rows):
        parts.append('<div class="note"><b>Synthetic inputs.</b> At least one case was built from synthetic '
                     "phantom images, not subject MRI/DTI.</div>")
    if len(subjects) > 1 and ok:
        ratios = ratio_table(rows, keys, subjects)
        dep = ratio_dependence(ratios, keys)
        if dep:
            parts += _answer(dep, keys, subjects[0])
            png = _plot_ratio([r for r in ratios if r["ratio"] is not None], keys, subjects[0],
                              outdir / "study_ratio.png", dpi)
            parts.append(img_tag(png, "force per volume ratio vs each varied key"))
            rt_head = ["case", *short_names(keys), "subject", f"force per volume ÷ {subjects[0]}'s"]
            rt_rows = [[r["case"], *[r["params"][k] for k in keys], r["subject"], r["ratio"]] for r in ratios]
            parts.append(table(rt_head, rt_rows))
    parts.append("<h2>Cases</h2>")
    parts.append(table([html_units(h) for h in header], table_rows))
    parts.append('<p class="foot">F_max = largest end force over converged steps. Data: <code>study.csv</code>.</p>')
    if ok:
        parts.append("<h2>F_max and force per unit volume against each varied key</h2>")
        for k, tail in zip(keys, short_names(keys), strict=True):
            png = _plot_against(ok, k, keys, outdir / f"study_{format_value(tail)}.png", dpi)
            parts.append(img_tag(png, f"F_max and force per volume vs {k}"))
    fails = [r for r in rows if r.get("error")]
    warn = [(r["subject"], r["case"], w) for r in ok for w in r["summary"].get("warnings", [])]
    if fails or warn:
        parts.append("<h2>Failures and warnings</h2><ul>")
        parts += [f'<li class="fail">{esc(r["subject"])} [{esc(r["case"])}]: {esc(r["error"])}</li>' for r in fails]
        parts += [f"<li>{esc(s)} [{esc(c)}]: {esc(w)}</li>" for s, c, w in warn]
        parts.append("</ul>")
    links = [(r, (r["summary"].get("outputs") or {}).get("index_html")) for r in ok]
    if any(p for _, p in links) or cohort_pages:
        parts.append("<h2>Case reports</h2><ul>")
        parts += [f'<li><a href="{esc(_rel(p, outdir))}">{esc(r["subject"])} [{esc(r["case"])}]</a></li>'
                  for r, p in links if p]
        parts += [f'<li><a href="{esc(_rel(p, outdir))}">cohort comparison [{esc(c)}]</a></li>'
                  for c, p in (cohort_pages or {}).items()]
        parts.append("</ul>")
    out = outdir / "study.html"
    out.write_text(page(title, parts), encoding="utf-8")
    return out

"""The force's uncertainty from the scan: F_max of the noisy realisations against the noise-free case.

Input: one row per case of an uncertainty run (each subject's noise-free case, realisation 0, and its
realisations 1..N) with the case's report summary (``summary.json`` data). Output:

* in each subject's folder (``<output_dir>`` for a single subject): ``uncertainty.csv`` (one row per
  realisation: ``realisation``, ``F_max_N``, and what the realisation changed), ``uncertainty.json``
  (``realisations``, ``F_max_mean_N``, ``ci95_low_N``, ``ci95_high_N``, ``noise_free_F_max_N`` and
  more) and ``uncertainty_curves.png`` (the realisations' force–activation curves and their F_max);
* ``uncertainty.html`` in the run's top folder: the interval of every subject, the figures, the
  table, and with several subjects whether their difference is larger than the uncertainty.

The interval is :func:`pixmuscle.uncertainty.prediction_interval`: where one more realisation's F_max
falls with 95 % probability (normal theory), the spread of F_max — not the standard error of its mean.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..uncertainty.interval import INTERVAL_TEXT, prediction_interval
from .curves import _pyplot, write_csv
from .html import esc, img_tag, kv_table, page, table

_FPMV = "force_per_muscle_volume_N_per_cm3"

#: columns of uncertainty.csv after realisation and F_max_N (keys of perturbation.json)
_PERTURBATION = ("voxels_relabelled", "muscle_voxels_relabelled", "largest_boundary_shift_voxels",
                 "fibre_angle_median_deg", "fibre_angle_rms_deg")


def _perturbation(row: Mapping[str, Any]) -> dict:
    p = Path(row.get("output_dir") or "") / "perturbation.json"
    try:
        return json.loads(p.read_text())
    except (OSError, ValueError):
        return {}


def _num(v) -> float:
    return float("nan") if v is None else float(v)


def subject_uncertainty(rows: Sequence[Mapping[str, Any]], cfg: Any = None) -> dict:
    """The uncertainty record of one subject (``uncertainty.json``).

    Parameters
    ----------
    rows : sequence of mappings
        The subject's cases: ``realisation`` (0: noise-free), ``summary`` (report summary or None),
        ``error`` (str or None), ``output_dir``.
    cfg : pixmuscle.uncertainty.UncertaintyConfig, optional
        Recorded with the numbers.
    """
    import dataclasses

    noise_free = next((r for r in rows if not r["realisation"]), None)
    nf = (noise_free or {}).get("summary") or {}
    real = sorted((r for r in rows if r["realisation"]), key=lambda r: r["realisation"])
    per = []
    for r in real:
        s = r.get("summary") or {}
        ok = bool(s) and not s.get("failed") and s.get("F_max_N") is not None
        per.append({"realisation": r["realisation"], "F_max_N": s.get("F_max_N") if ok else None,
                    _FPMV: s.get(_FPMV) if ok else None,
                    "muscle_volume_cm3": (s.get("volumes_cm3") or {}).get("muscle") if ok else None,
                    "status": s.get("status") if s else "failed", "error": r.get("error") or (None if ok else s.get("status")),
                    **{k: _perturbation(r).get(k) for k in _PERTURBATION}})
    f = prediction_interval([_num(p["F_max_N"]) for p in per])
    fv = prediction_interval([_num(p[_FPMV]) for p in per])
    nf_f = nf.get("F_max_N")
    angles = [p["fibre_angle_median_deg"] for p in per if p["fibre_angle_median_deg"] is not None]
    return {
        "realisations": f["n"], "realisations_planned": len(real), "failed": [p["realisation"] for p in per if p["F_max_N"] is None],
        "F_max_mean_N": f["mean"], "F_max_sd_N": f["sd"], "ci95_low_N": f["low"], "ci95_high_N": f["high"],
        "F_max_min_N": f["min"], "F_max_max_N": f["max"], "t": f["t"], "interval": INTERVAL_TEXT,
        "noise_free_F_max_N": nf_f,
        "shift_N": None if nf_f is None or f["mean"] is None else f["mean"] - nf_f,
        "shift_percent": None if not nf_f or f["mean"] is None else 100.0 * (f["mean"] - nf_f) / nf_f,
        "noise_free_inside": (None if nf_f is None or f["low"] is None else bool(f["low"] <= nf_f <= f["high"])),
        "force_per_muscle_volume_mean_N_per_cm3": fv["mean"], "force_per_muscle_volume_ci95_low_N_per_cm3": fv["low"],
        "force_per_muscle_volume_ci95_high_N_per_cm3": fv["high"], "noise_free_force_per_muscle_volume_N_per_cm3": nf.get(_FPMV),
        "fibre_angle_median_deg": float(np.median(angles)) if angles else None,
        "config": {} if cfg is None else {k: v for k, v in dataclasses.asdict(cfg).items()},
        "per_realisation": per,
    }


def _plot(rows: Sequence[Mapping[str, Any]], rec: Mapping[str, Any], subject: str, path: Path, dpi: int) -> Path:
    """Force–activation curves of the realisations and the noise-free case; F_max and the interval."""
    plt = _pyplot()
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(10.0, 4.0), layout="constrained", gridspec_kw={"width_ratios": [2, 1]})
    for r in sorted(rows, key=lambda r: r["realisation"]):
        c = (r.get("summary") or {}).get("curve") or {}
        a, fe = np.asarray(c.get("alpha", []), float), np.asarray(c.get("end_force_N", []), float)
        conv = np.asarray(c.get("converged", [True] * len(a)), bool)[:len(a)]
        if not len(a):
            continue
        if r["realisation"]:
            ax.plot(a[conv], fe[conv], color="tab:blue", alpha=0.45, linewidth=1.0)
        else:
            ax.plot(a[conv], fe[conv], color="black", linewidth=2.0, label="noise-free", zorder=5)
    ax.plot([], [], color="tab:blue", alpha=0.45, label="noisy realisations")
    ax.set_xlabel("activation α [-]")
    ax.set_ylabel("end force [N]")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    per = [p for p in rec["per_realisation"] if p["F_max_N"] is not None]
    bx.plot([p["realisation"] for p in per], [p["F_max_N"] for p in per], "o", color="tab:blue", label="realisation")
    if rec["ci95_low_N"] is not None:
        bx.axhspan(rec["ci95_low_N"], rec["ci95_high_N"], color="tab:blue", alpha=0.12, label="95 % prediction interval")
        bx.axhline(rec["F_max_mean_N"], color="tab:blue", linewidth=1.0, label="mean")
    if rec["noise_free_F_max_N"] is not None:
        bx.axhline(rec["noise_free_F_max_N"], color="black", linestyle="--", linewidth=1.2, label="noise-free")
    bx.set_xticks([p["realisation"] for p in rec["per_realisation"]])
    bx.set_xlabel("realisation")
    bx.set_ylabel("F_max [N]")
    bx.grid(alpha=0.3)
    bx.legend(fontsize=7)
    fig.suptitle(f"{subject}: force–activation curves of {rec['realisations']} noisy realisations")
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def _rel(path: str | Path, start: Path) -> str:
    return Path(os.path.relpath(Path(path).resolve(), start.resolve())).as_posix()


def _headline(rec: Mapping[str, Any]) -> str:
    if rec["ci95_low_N"] is None:
        return f"<p>Fewer than two realisations finished: no interval ({rec['realisations']} of {rec['realisations_planned']}).</p>"
    half = (rec["ci95_high_N"] - rec["ci95_low_N"]) / 2.0
    nf = rec["noise_free_F_max_N"]
    rel = f" (± {100 * half / rec['F_max_mean_N']:.2g} %)" if rec["F_max_mean_N"] else ""
    inside = ("" if rec["noise_free_inside"] is None else " — inside the interval" if rec["noise_free_inside"]
              else " — <b>outside the interval</b>")
    return (f"<p class=\"big\"><b>F_max = {rec['F_max_mean_N']:.4g} ± {half:.3g} N</b>{rel}: 95 % prediction interval "
            f"{rec['ci95_low_N']:.4g} – {rec['ci95_high_N']:.4g} N over {rec['realisations']} noisy realisations "
            f"(range {rec['F_max_min_N']:.4g} – {rec['F_max_max_N']:.4g} N, s = {rec['F_max_sd_N']:.3g} N). "
            f"Noise-free F_max: {_fmt(nf)} N{inside}; the realisations' mean is "
            f"{_signed(rec['shift_percent'])} % from it (the noise's systematic effect on F_max).</p>")


def _signed(v) -> str:
    return "—" if v is None else f"{float(v):+.2g}"


def _fmt(v) -> str:
    return "—" if v is None else f"{float(v):.4g}"


def _describe(cfg: Any) -> str:
    if cfg is None:
        return ""
    dti = ("no DTI noise" if cfg.dti_snr is None else
           f"DTI noise at SNR {cfg.dti_snr:g} (S0/σ of the b = 0 signal; Rician noise on the signals of a "
           f"{cfg.dti_directions}-direction b = {cfg.dti_bvalue:g} s/mm² acquisition with {cfg.dti_b0_volumes} b = 0 "
           "volume(s), tensors fitted again, fibres = their principal eigenvectors)")
    seg = ("boundaries not moved" if cfg.boundary_voxels == 0 else
           f"segmentation boundaries moved in-plane by up to {cfg.boundary_voxels:g} voxels (a smooth random field "
           f"of correlation length {cfg.boundary_length_cm:g} cm)")
    return f"<p>Each realisation: {esc(dti)}; {esc(seg)}; seed {cfg.seed}. Method: docs/uncertainty.md.</p>"


def uncertainty_summary(rows: Sequence[Mapping[str, Any]], cfg: Any, outdir: str | Path, *,
                        subject_dirs: Mapping[str, str | Path], subjects: Sequence[str], dpi: int = 110,
                        title: str = "") -> Path:
    """Write each subject's ``uncertainty.csv`` / ``.json`` / ``_curves.png`` and ``uncertainty.html``.

    Parameters
    ----------
    rows : sequence of mappings
        One per case: ``subject``, ``realisation`` (0: noise-free), ``case``, ``summary`` (report
        summary or None), ``error`` (str or None), ``output_dir``.
    cfg : pixmuscle.uncertainty.UncertaintyConfig
    outdir : path-like
        Folder of ``uncertainty.html``.
    subject_dirs : mapping subject → folder
        Where each subject's files go (its noise-free case's folder).
    subjects : sequence of str
        In config order; the first is the reference of the comparison.

    Returns
    -------
    Path of ``uncertainty.html``.
    """
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    parts = [f"<h1>{esc(title or 'Force uncertainty from the scan')}</h1>", _describe(cfg),
             f"<p class=\"foot\">The interval: {esc(INTERVAL_TEXT)}.</p>"]
    if any((r.get("summary") or {}).get("synthetic") for r in rows):
        parts.append('<div class="note"><b>Synthetic inputs.</b> The cases were built from synthetic phantom '
                     "images, not subject MRI/DTI.</div>")
    recs = {}
    for subject in subjects:
        srows = [r for r in rows if r["subject"] == subject]
        if not srows:
            continue
        folder = Path(subject_dirs.get(subject, outdir))
        folder.mkdir(parents=True, exist_ok=True)
        rec = recs[subject] = subject_uncertainty(srows, cfg)
        header = ["realisation", "F_max_N", _FPMV, "muscle_volume_cm3", *_PERTURBATION, "status", "error"]
        write_csv(folder / "uncertainty.csv", header,
                  [["" if p[k] is None else p[k] for k in header] for p in rec["per_realisation"]])
        (folder / "uncertainty.json").write_text(json.dumps(rec, indent=2, default=str))
        png = _plot(srows, rec, subject, folder / "uncertainty_curves.png", dpi)
        if len(subjects) > 1:
            parts.append(f"<h2>{esc(subject)}</h2>")
        parts.append(_headline(rec))
        parts.append(img_tag(png, f"force-activation curves of the realisations, {subject}"))
        parts.append(table(["realisation", "F_max [N]", "F_max / muscle volume [N/cm³]", "muscle [cm³]",
                            "voxels relabelled", "muscle voxels relabelled", "largest boundary shift [voxels]",
                            "fibre angle to noise-free, median [°]", "fibre angle, RMS [°]", "status", "error"],
                           [[p[k] for k in header] for p in rec["per_realisation"]]))
        files = ", ".join(f"<code>{esc(_rel(folder / n, outdir))}</code>" for n in
                          ("uncertainty.csv", "uncertainty.json", "uncertainty_curves.png"))
        links = [(r, ((r.get("summary") or {}).get("outputs") or {}).get("index_html")) for r in srows]
        reps = " ".join(f'<a href="{esc(_rel(p, outdir))}">{"noise-free" if not r["realisation"] else esc(r["case"])}</a>'
                        for r, p in sorted(links, key=lambda x: x[0]["realisation"]) if p)
        parts.append(f'<p class="foot">Data: {files}. Reports: {reps or "—"}.</p>')
    if len(recs) > 1:
        parts += _comparison(recs, subjects)
    fails = [r for r in rows if r.get("error")]
    if fails:
        parts.append("<h2>Failed cases</h2><ul>")
        parts += [f'<li class="fail">{esc(r["subject"])} [{esc(r["case"] or "noise-free")}]: {esc(r["error"])}</li>'
                  for r in fails]
        parts.append("</ul>")
    out = outdir / "uncertainty.html"
    out.write_text(page(title or "Force uncertainty from the scan", parts), encoding="utf-8")
    return out


def _comparison(recs: Mapping[str, Mapping[str, Any]], subjects: Sequence[str]) -> list[str]:
    """Force per unit muscle volume of each subject with its interval, and whether it differs from the first's."""
    ref = subjects[0]
    r0 = recs.get(ref)
    parts = ["<h2>Is the difference between subjects larger than the uncertainty?</h2>"
             "<p>Force per unit muscle volume (F_max / muscle volume), mean and 95 % prediction interval over each "
             f"subject's realisations, against {esc(ref)}'s.</p>"]
    rows = []
    for s in subjects:
        rec = recs.get(s)
        if rec is None:
            continue
        lo, hi, m = (rec["force_per_muscle_volume_ci95_low_N_per_cm3"], rec["force_per_muscle_volume_ci95_high_N_per_cm3"],
                     rec["force_per_muscle_volume_mean_N_per_cm3"])
        verdict = ""
        if s != ref and r0 is not None and None not in (lo, hi, r0["force_per_muscle_volume_ci95_low_N_per_cm3"]):
            apart = hi < r0["force_per_muscle_volume_ci95_low_N_per_cm3"] or lo > r0["force_per_muscle_volume_ci95_high_N_per_cm3"]
            verdict = "yes: the intervals do not overlap" if apart else "no: the intervals overlap"
        ratio = m / r0["force_per_muscle_volume_mean_N_per_cm3"] if (
            r0 is not None and m is not None and r0["force_per_muscle_volume_mean_N_per_cm3"]) else None
        rows.append([s, m, lo, hi, rec["noise_free_force_per_muscle_volume_N_per_cm3"], ratio, verdict])
    parts.append(table(["subject", "mean [N/cm³]", "95 % low [N/cm³]", "95 % high [N/cm³]", "noise-free [N/cm³]",
                        f"mean ÷ {ref}'s", "different from the first?"], rows))
    parts.append(kv_table({"reading": "non-overlapping prediction intervals are a conservative test: the difference "
                                      "is larger than what the scan's noise moves either subject by"}))
    return parts

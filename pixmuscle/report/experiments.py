"""Report sections of the multi-solve experiments: per-muscle force contributions and force–length curves.

Inputs are the dictionaries of :func:`pixmuscle.io.muscle_forces.load_muscle_forces` and
:func:`pixmuscle.io.force_length.load_force_length`; outputs are PNG/CSV files and HTML
fragments (see :mod:`pixmuscle.report.html`).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from .curves import write_csv
from .html import esc, fmt, img_tag, table

__all__ = ["fill_muscle_forces", "force_length_section", "muscle_forces_section", "plot_force_length",
           "plot_muscle_forces"]


def _figure(width=7.0, height=4.2):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height))
    FigureCanvasAgg(fig)
    return fig, fig.add_subplot(1, 1, 1)


def fill_muscle_forces(rows: list[dict], mf: Mapping, k: int) -> dict:
    """Put each muscle's force contribution at step ``k`` (the step of F_max) into the tissue-table rows.

    ``F_max [N]`` of a muscle row = its contribution C_m at step k; ``F_max / total volume`` =
    that over the row's total volume (muscle + IMAT + IMCT + aponeurosis). Rows of muscles that
    were not solved alone keep "—".

    Returns
    -------
    dict
        ``step``, ``contribution_N`` (name → value), ``interaction_N``, ``baseline_N``, ``total_N``.
    """
    from .tables import FORCE_PER_TOTAL, TOTAL

    c = {m: float(v[k]) for m, v in mf["contribution"].items()}
    for r in rows:
        if r["region"] in c:
            r["F_max [N]"] = c[r["region"]]
            vol = r.get(TOTAL) or 0.0
            r[FORCE_PER_TOTAL] = c[r["region"]] / vol if vol > 0 else None
    return {"step": int(k), "contribution_N": c, "interaction_N": float(mf["interaction"][k]),
            "baseline_N": float(mf["baseline"][k]), "total_N": float(mf["total"][k])}


def plot_muscle_forces(mf: Mapping, path, *, dpi: int = 120, title: str = "", activation: Mapping | None = None) -> Path:
    """Stacked per-muscle contributions (+ baseline, + interaction) against α, with the all-muscle force.

    ``activation`` (muscle → mean α at load factor 0 and 1): when the muscles ramp differently the
    x axis is the load factor, with each muscle's α named (:func:`~pixmuscle.report.curves.load_factor_label`).
    """
    from .curves import load_factor_label

    by_load = load_factor_label(activation)
    fig, ax = _figure()
    a = np.asarray(mf["load_factor"] if by_load else mf["alpha"], float)
    ok = np.isfinite(a) & np.isfinite(mf["total"])
    layers = [("passive / baseline", mf["baseline"])] + list(mf["contribution"].items())
    pos = np.zeros(a.shape)
    for name, v in layers:
        v = np.nan_to_num(np.asarray(v, float))
        ax.fill_between(a[ok], pos[ok], (pos + v)[ok], label=name, alpha=0.75, linewidth=0)
        pos = pos + v
    inter = np.nan_to_num(np.asarray(mf["interaction"], float))
    ax.plot(a[ok], (pos + inter)[ok], "k-", lw=1.8, label="all muscles (solve)")
    ax.plot(a[ok], pos[ok], "k--", lw=1.0, label="sum of parts (without interaction)")
    ax.set_xlabel(by_load or "mean activation α of the muscle nodes [-]", fontsize=7 if by_load else None)
    ax.set_ylabel("end force [N]")
    ax.set_title(title or "End force split by muscle")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    return Path(path)


def muscle_forces_section(mf: Mapping, outdir, *, rows: list[dict], k: int | None, dpi: int = 120,
                          warnings: list | None = None, activation: Mapping | None = None) -> tuple[list[str], dict]:
    """Figure, CSV and HTML of the per-muscle contributions; fills the tissue-table rows at step ``k``.

    Returns
    -------
    parts : list of str
        HTML fragments.
    info : dict
        What :func:`fill_muscle_forces` returned (empty when ``k`` is None) plus ``outputs``.
    """
    outdir = Path(outdir)
    names = list(mf["contribution"])
    header = ["step", "alpha", "total [N]", "baseline [N]"] + [f"{m} [N]" for m in names] + ["interaction [N]"]
    cols = [np.arange(len(mf["alpha"])), mf["alpha"], mf["total"], mf["baseline"],
            *[mf["contribution"][m] for m in names], mf["interaction"]]
    csv = write_csv(outdir / "muscle_forces.csv", header, [list(r) for r in zip(*cols, strict=True)])
    png = plot_muscle_forces(mf, outdir / "muscle_forces.png", dpi=dpi, activation=activation)
    info = fill_muscle_forces(rows, mf, k) if k is not None else {}
    failed = {r: s for r, s in mf["runs"].items() if s != "complete"}
    if failed and warnings is not None:
        warnings.extend(f"muscle_forces: run '{r}' {s}" for r, s in failed.items())
    parts = ["<h2>Force by muscle</h2>",
             f'<p class="foot">{esc(mf["method"])}. End force = mean axial reaction of '
             f'{esc(", ".join(mf["force_sets"]) or "—")}. Data: <code>muscle_forces.csv</code>.</p>',
             img_tag(png, "end force split by muscle")]
    if info:
        parts.append(table(["part", "force at the step of F_max [N]"],
                           [["passive / baseline", info["baseline_N"]],
                            *[[m, v] for m, v in info["contribution_N"].items()],
                            ["interaction", info["interaction_N"]], ["all muscles (solve)", info["total_N"]]]))
        parts.append(f'<p class="foot">Step {info["step"]}; the tissue table\'s F_max column shows these '
                     "contributions per muscle.</p>")
    info["outputs"] = {"muscle_forces_csv": str(csv), "muscle_forces_png": str(png)}
    return parts, info


def plot_force_length(fl: Mapping, path, *, dpi: int = 120, title: str = "") -> Path:
    """Active, passive and total end force against muscle length."""
    fig, ax = _figure()
    L = np.asarray(fl["length"], float)
    if "fibre_law" in fl:
        ax.plot(L, fl["fibre_law"], color="0.55", ls="--", lw=3.0, alpha=0.6, zorder=1,
                label="fibre law ᾱ σ_max A f_active(L/L0) (homogeneous muscle)")
    for key, style in (("total", "k-o"), ("active", "C3-s"), ("passive", "C0-^")):
        ax.plot(L, fl[key], style, ms=4, label=key, zorder=2)
    ax.axvline(fl["L0_cm"], color="0.5", lw=0.8, ls=":")
    ax.set_xlabel(f"muscle length along {fl['component']} [cm] (reference L0 = {fl['L0_cm']:.4g} cm)")
    ax.set_ylabel("end force [N]")
    act = fl["activation"]
    ax.set_title(title or f"Force–length at α = {act if not isinstance(act, dict) else 'per muscle'} and α = 0")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    return Path(path)


def force_length_section(fl: Mapping, outdir, *, dpi: int = 120, warnings: list | None = None) -> tuple[list[str], dict]:
    """Figure, CSV and HTML of a force–length sweep."""
    outdir = Path(outdir)
    header = ["delta [cm]", "length [cm]", "stretch [-]", "total [N]", "passive [N]", "active [N]",
              "fibre law [N]"]
    keys = ["delta", "length", "stretch", "total", "passive", "active", "fibre_law"]
    rows = [list(r) for r in zip(*[fl[k] for k in keys], strict=True)]
    csv = write_csv(outdir / "force_length.csv", header, rows)
    png = plot_force_length(fl, outdir / "force_length.png", dpi=dpi)
    failed = {r: s for r, s in fl["runs"].items() if s != "complete"}
    if failed and warnings is not None:
        warnings.extend(f"force_length: run '{r}' {s}" for r, s in failed.items())
    act = fl["activation"]
    parts = ["<h2>Force–length</h2>",
             f'<p class="foot">End {esc(fl["nodes"])} displaced along {esc(fl["component"])} (shortening &lt; 0, '
             f"lengthening &gt; 0) at activation {esc(fmt(act) if not isinstance(act, dict) else act)} and at α = 0; "
             "active = total − passive at the same length; fibre law = mean α · σ_max · (muscle volume / L0) · "
             "f_active(L/L0), eqs. 24–26, exact for a homogeneous muscle block. Method: pixmuscle.mechanics.experiments. "
             "Data: <code>force_length.csv</code>.</p>",
             img_tag(png, "force-length curves"), table(header, rows)]
    return parts, {"outputs": {"force_length_csv": str(csv), "force_length_png": str(png)}}

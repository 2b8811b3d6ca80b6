"""Displacement-driven runs: what drove a solve, and its force against the prescribed displacement.

A solve is *displacement-driven* when the activation α is the same at every step and a node set is
moved by a prescribed displacement (paper Example 1: a tendon stretched 2 cm); it is an *activation
sweep* when α changes (Examples 2 and 3). :func:`run_protocol` decides from the results file itself
(its per-step α and prescribed displacements), not from the configuration's name, and the report
picks its template from the answer: for a displacement-driven run the end force is shown against
the prescribed displacement, beside a reference curve when ``report.reference_curve`` names one
(e.g. the finite-element solution of ``pixmuscle verify tendon``), and nothing about activation.

Reference curves are CSV files with a header row and the columns ``displacement_cm`` and ``force_N``
(what :func:`pixmuscle.verify.tendon_fem.reference_table` writes).
"""

from __future__ import annotations

import csv
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from ..errors import InputError

__all__ = ["ACTIVATION", "DISPLACEMENT", "compare_to_reference", "displacement_csv", "displacement_table",
           "plot_force_displacement", "read_reference_curve", "reference_entry", "run_protocol"]

ACTIVATION, DISPLACEMENT = "activation", "displacement"


def run_protocol(alpha, prescribed: Mapping[str, np.ndarray], *, tol: float = 1e-12) -> dict:
    """Whether a solve swept the activation or prescribed a displacement.

    Parameters
    ----------
    alpha : (S+1,) array_like
        Activation at each stored state.
    prescribed : mapping set name → (S+1, 3) array, cm
        Prescribed displacement of each constrained set (0 on fixed components).
    tol : float
        Changes of α and displacements (cm) up to this are zero.

    Returns
    -------
    dict
        ``kind``: ``"activation"`` when α changes over the steps, or when nothing is displaced;
        ``"displacement"`` when α is constant and some set is displaced. For the latter also
        ``set`` (the set moved farthest), ``component`` (``"x"``, ``"y"`` or ``"z"``: its largest
        component), ``displacement_cm`` ((S+1,) that component per state) and ``alpha`` (the
        constant activation).
    """
    a = np.asarray(alpha, float)
    a = a[np.isfinite(a)]
    if a.size and np.ptp(a) > tol:
        return {"kind": ACTIVATION}
    best = None
    for name in sorted(prescribed):  # a few node sets
        p = np.asarray(prescribed[name], float).reshape(-1, 3)
        if p.size == 0 or not np.isfinite(p).any():
            continue
        reach = np.nanmax(np.abs(p), axis=0)
        c = int(np.argmax(reach))
        if reach[c] > tol and (best is None or reach[c] > best[2]):
            best = (name, c, reach[c])
    if best is None:
        return {"kind": ACTIVATION}
    name, c, _ = best
    return {"kind": DISPLACEMENT, "set": name, "component": "xyz"[c],
            "displacement_cm": np.asarray(prescribed[name], float).reshape(-1, 3)[:, c],
            "alpha": float(a[0]) if a.size else 0.0}


def read_reference_curve(path) -> tuple[np.ndarray, np.ndarray]:
    """Displacement (cm) and force (N) of a reference CSV (columns ``displacement_cm``, ``force_N``).

    Returns
    -------
    displacement, force : (n,) float64, sorted by displacement

    Raises
    ------
    InputError
        Naming the file when a column is missing or a value is not a finite number.
    """
    path = Path(path)
    try:
        with open(path, newline="") as fh:
            rows = list(csv.DictReader(fh))
    except OSError as exc:
        raise InputError(f"report.reference_curve: cannot read {path}: {exc.strerror or exc}") from None
    if not rows or not {"displacement_cm", "force_N"} <= set(rows[0]):
        raise InputError(f"report.reference_curve: {path} needs a header with the columns displacement_cm and force_N, "
                         f"got {list(rows[0]) if rows else 'no rows'}")
    try:
        d = np.array([float(r["displacement_cm"]) for r in rows])
        f = np.array([float(r["force_N"]) for r in rows])
    except (TypeError, ValueError):
        raise InputError(f"report.reference_curve: {path}: displacement_cm and force_N must be numbers") from None
    if not (np.isfinite(d).all() and np.isfinite(f).all()):
        raise InputError(f"report.reference_curve: {path}: displacement_cm and force_N must be finite")
    order = np.argsort(d, kind="stable")
    return d[order], f[order]


def compare_to_reference(displacement, force, ref_displacement, ref_force) -> tuple[np.ndarray, np.ndarray]:
    """Reference force at the run's displacements (linear interpolation) and the relative difference.

    Parameters
    ----------
    displacement, force : (S+1,) array_like, cm and N
        The run's prescribed displacement and end force per state.
    ref_displacement, ref_force : (n,) array_like, cm and N
        The reference curve, sorted by displacement.

    Returns
    -------
    ref_at : (S+1,) float64, N
        NaN outside the reference's displacement range.
    relative : (S+1,) float64
        ``(force − ref_at) / |ref_at|``; NaN where the reference is 0 or not available.
    """
    d = np.asarray(displacement, float)
    dr, fr = np.asarray(ref_displacement, float), np.asarray(ref_force, float)
    inside = (d >= dr.min() - 1e-9) & (d <= dr.max() + 1e-9)
    ref_at = np.where(inside, np.interp(d, dr, fr), np.nan)
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.where(np.abs(ref_at) > 0, (np.asarray(force, float) - ref_at) / np.abs(ref_at), np.nan)
    return ref_at, rel


def reference_entry(summary: Mapping, displacement, label: str, path, curve: tuple) -> dict:
    """``summary["reference"]``: the reference curve and its comparison with the run's end force.

    Parameters
    ----------
    summary : mapping
        The report summary (``curve.end_force_N``).
    displacement : (S+1,) array_like, cm
    label : str
    path : path-like
        The reference CSV (recorded).
    curve : (displacement (n,), force (n,))
        As read by :func:`read_reference_curve`.
    """
    f = np.array([np.nan if v is None else v for v in summary["curve"]["end_force_N"]], float)
    ref_at, rel = compare_to_reference(displacement, f, *curve)
    conv = np.asarray(summary["curve"]["converged"], bool) & np.isfinite(rel)
    worst = float(np.max(np.abs(rel[conv]))) if conv.any() else None
    last = int(np.flatnonzero(conv)[-1]) if conv.any() else None

    def floats(a):
        return [None if not np.isfinite(x) else float(x) for x in np.asarray(a, float)]

    return {"label": str(label), "file": str(path), "curve": {"displacement_cm": floats(curve[0]), "force_N": floats(curve[1])},
            "force_N": floats(ref_at), "relative": floats(rel), "max_abs_relative": worst,
            "final": None if last is None else {"step": last, "displacement_cm": float(np.asarray(displacement)[last]),
                                                "force_N": float(f[last]), "reference_N": float(ref_at[last]),
                                                "relative": float(rel[last])}}


def displacement_csv(header: Sequence[str], rows: Sequence[Sequence], summary: Mapping) -> tuple[list[str], list[list]]:
    """``force_displacement.csv`` from the rows of :func:`pixmuscle.report.curves.force_table`: the α column
    replaced by the driving set's displacement (cm), and the reference force and relative difference
    appended when there is a reference."""
    header = list(header)
    k = header.index("alpha")
    p = summary["protocol"]
    d = summary["curve"]["displacement_cm"]
    new_header = header[:k] + [f"{p['set']}.u{p['component']} [cm]"] + header[k + 1:]
    new_rows = [list(r[:k]) + [repr(float(d[i]))] + list(r[k + 1:]) for i, r in enumerate(rows)]
    ref = summary.get("reference")
    if ref:
        new_header += [f"reference_force [N] ({ref['label']})", "relative_difference"]
        for r, f, e in zip(new_rows, ref["force_N"], ref["relative"], strict=True):
            r += ["" if f is None else repr(f), "" if e is None else repr(e)]
    return new_header, new_rows


def displacement_table(summary: Mapping) -> tuple[list[str], list[list]]:
    """Per-state rows of the page's force–displacement table: step, displacement, each end's force,
    the end force and, with a reference, its force and the relative difference."""
    c, proto = summary["curve"], summary["protocol"]
    cols = {"step": c["step"], f"{proto['set']}.u{proto['component']} [cm]": c["displacement_cm"]}
    for s in summary["force_sets"]:
        cols[f"{s} force [N]"] = c["axial_force_N"][s]
    cols["end force [N]"] = c["end_force_N"]
    ref = summary.get("reference")
    if ref:
        cols[f"{ref['label']} [N]"] = ref["force_N"]
        cols["relative difference [%]"] = [None if r is None else 100 * r for r in ref["relative"]]
    cols["converged"] = c["converged"]
    return list(cols), [list(r) for r in zip(*cols.values(), strict=True)]


def plot_force_displacement(curves: Mapping[str, Sequence], path, *, reference: tuple | None = None,
                            relative=None, xlabel: str = "prescribed displacement [cm]", title: str = "",
                            dpi: int = 120) -> Path:
    """End force against prescribed displacement, with a reference curve and the relative difference.

    Parameters
    ----------
    curves : mapping label → (displacement (S+1,) cm, force (S+1,) N, converged (S+1,) bool)
    path : path-like
        PNG file to write.
    reference : (label, displacement (n,) cm, force (n,) N), optional
    relative : (S+1,) array_like, optional
        Relative difference to the reference at the first curve's states (drawn in a second panel, %).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rel = None if relative is None else np.asarray(relative, float)
    two = rel is not None and np.isfinite(rel).any()
    fig, axes = plt.subplots(2 if two else 1, 1, figsize=(6.4, 6.2 if two else 4.2), squeeze=False, sharex=True,
                             layout="constrained", gridspec_kw={"height_ratios": [3, 1.3] if two else [1]})
    ax = axes[0, 0]
    if reference is not None:
        lab, dr, fr = reference
        ax.plot(dr, fr, "-", color="0.35", linewidth=2.2, label=lab)
    markers = "osD^v"
    first = None
    for n, (label, c) in enumerate(curves.items()):
        d, f = np.asarray(c[0], float), np.asarray(c[1], float)
        ok = np.asarray(c[2], bool) if len(c) > 2 else np.ones(d.shape, bool)
        first = first if first is not None else (d, ok)
        ax.plot(d[ok], f[ok], linestyle="--" if n else "-", marker=markers[n % len(markers)], markersize=4, label=label)
        if (~ok).any():
            ax.plot(d[~ok], f[~ok], "x", color="red", markersize=8, label="not converged")
    ax.set_ylabel("end force [N]")
    ax.set_title(title)
    ax.axhline(0.0, color="0.7", linewidth=0.8)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    if two:
        d, ok = first
        r = axes[1, 0]
        keep = ok & np.isfinite(rel)
        r.plot(d[keep], 100 * rel[keep], "o-", markersize=4)
        r.axhline(0.0, color="0.7", linewidth=0.8)
        r.set_ylabel("relative difference [%]")
        r.grid(alpha=0.3)
    axes[-1, 0].set_xlabel(xlabel)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return Path(path)

"""Discretisation check of one case solved on several models (paper Example 2: coarse vs fine).

Pure: end-force curves in, a difference table out. The *reference* is the finest model (the one
with the most nodes); every other model is compared with it at the reference's activation levels
and at F_max:

    difference = F_model − F_reference   [N]
    relative difference = (F_model − F_reference) / |F_reference|   [-]

A model's force at an α it did not store exactly is linearly interpolated between its converged
states; outside its converged range the cell is empty (None).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np


def force_at(alpha: np.ndarray, force: np.ndarray, converged: np.ndarray, at: np.ndarray) -> np.ndarray:
    """Force of a curve at the activations ``at``, interpolated between converged states.

    Parameters
    ----------
    alpha, force : (S,) float
        Activation [-] and end force [N] per stored state.
    converged : (S,) bool
    at : (n,) float
        Activations wanted [-].

    Returns
    -------
    (n,) float64, N; NaN outside the converged, finite range of the curve.
    """
    alpha, force = np.asarray(alpha, float), np.asarray(force, float)
    ok = np.asarray(converged, bool) & np.isfinite(alpha) & np.isfinite(force)
    at = np.asarray(at, float)
    out = np.full(at.shape, np.nan)
    if not ok.any():
        return out
    a, f = alpha[ok], force[ok]
    order = np.argsort(a, kind="stable")
    a, f = a[order], f[order]
    inside = (at >= a[0] - 1e-12) & (at <= a[-1] + 1e-12)
    out[inside] = np.interp(at[inside], a, f)
    return out


def f_max(force: np.ndarray, converged: np.ndarray) -> float | None:
    """Largest end force [N] over the converged, finite states, or None."""
    f = np.where(np.asarray(converged, bool), np.asarray(force, float), np.nan)
    return float(np.nanmax(f)) if np.isfinite(f).any() else None


def _rel(value, ref):
    if value is None or ref is None or not np.isfinite(value) or not np.isfinite(ref) or ref == 0:
        return None
    return (value - ref) / abs(ref)


def _num(x):
    return None if x is None or not np.isfinite(x) else float(x)


def convergence_table(curves: Mapping[str, tuple], n_nodes: Mapping[str, int]) -> dict:
    """Compare the end-force curves of several models of one case with the finest.

    Parameters
    ----------
    curves : mapping label → (alpha (S,), end force (S,) N, converged (S,) bool)
        One curve per model (at least two).
    n_nodes : mapping label → int
        Node count of each model; the reference is the model with the most nodes.

    Returns
    -------
    dict with ``reference`` (label), ``models`` (labels, reference last), ``F_max_N`` (label →
    N or None), ``F_max_relative_difference`` (label → - or None, reference excluded),
    ``header`` and ``rows`` of the table (one row per converged α of the reference, then one
    "F_max" row; columns: α, the force of every model, then for every other model its
    difference [N] and relative difference [%]), and ``max_relative_difference`` (label →
    largest |relative difference| over the α rows where the reference force exceeds 1 % of its
    F_max, or None).
    """
    if len(curves) < 2:
        raise ValueError("convergence_table: needs the curves of at least two models")
    ref = max(curves, key=lambda k: (int(n_nodes.get(k, 0)), k))
    others = [k for k in curves if k != ref]
    models = others + [ref]
    ra, rf, rc = (np.asarray(x) for x in curves[ref])
    ok = np.asarray(rc, bool) & np.isfinite(np.asarray(ra, float)) & np.isfinite(np.asarray(rf, float))
    at = np.asarray(ra, float)[ok]
    ref_force = np.asarray(rf, float)[ok]
    forces = {k: force_at(*curves[k], at) for k in others}
    forces[ref] = ref_force
    fmax = {k: f_max(curves[k][1], curves[k][2]) for k in models}

    header = ["alpha"] + [f"F {k} [N]" for k in models]
    for k in others:
        header += [f"F {k} - F {ref} [N]", f"relative difference {k} [%]"]
    rows = []
    for i, a in enumerate(at):
        row = [float(a)] + [_num(forces[k][i]) for k in models]
        for k in others:
            d = forces[k][i] - ref_force[i]
            r = _rel(forces[k][i], ref_force[i])
            row += [_num(d), None if r is None else 100.0 * r]
        rows.append(row)
    fm_row = ["F_max"] + [fmax[k] for k in models]
    for k in others:
        r = _rel(fmax[k], fmax[ref])
        fm_row += [None if fmax[k] is None or fmax[ref] is None else fmax[k] - fmax[ref],
                   None if r is None else 100.0 * r]
    rows.append(fm_row)

    big = np.abs(ref_force) > 0.01 * abs(fmax[ref]) if fmax[ref] else np.zeros(ref_force.shape, bool)
    worst = {}
    for k in others:
        r = (forces[k] - ref_force)[big] / np.abs(ref_force[big]) if big.any() else np.array([])
        r = r[np.isfinite(r)]
        worst[k] = float(np.max(np.abs(r))) if r.size else None
    return {"reference": ref, "models": models, "F_max_N": fmax,
            "F_max_relative_difference": {k: _rel(fmax[k], fmax[ref]) for k in others},
            "max_relative_difference": worst, "header": header, "rows": rows}


#: a discretisation estimate of F_max larger than this (relative) is worth a plain warning
ESTIMATE_WARN = 0.02


def discretisation_estimate(conv: Mapping, headline: str, n_nodes: Mapping[str, int],
                            warn_above: float = ESTIMATE_WARN) -> dict:
    """The headline model's F_max with the difference to the next coarser model as its
    discretisation estimate.

    Parameters
    ----------
    conv : mapping
        Output of :func:`convergence_table`.
    headline : str
        Label of the model whose numbers the report shows first.
    n_nodes : mapping label → int
    warn_above : float
        Relative estimate above which ``large`` is true.

    Returns
    -------
    dict with ``headline``, ``finest`` (labels), ``headline_is_finest``, ``F_max_N`` (headline's),
    ``compared_with`` (label of the next coarser model, or None), ``compared_F_max_N``,
    ``difference_N`` (F_max of the headline − F_max of the coarser, N), ``relative`` (that over
    |F_max of the headline|), ``threshold`` and ``large`` (|relative| > threshold).
    """
    fmax = conv["F_max_N"]
    finest = conv["reference"]
    nh = int(n_nodes.get(headline, 0))
    coarser = [k for k in fmax if k != headline and int(n_nodes.get(k, 0)) < nh]
    other = max(coarser, key=lambda k: (int(n_nodes.get(k, 0)), k)) if coarser else None
    out = {"headline": headline, "finest": finest, "headline_is_finest": headline == finest,
           "F_max_N": fmax.get(headline), "compared_with": other, "compared_F_max_N": None, "difference_N": None,
           "relative": None, "threshold": float(warn_above), "large": False}
    if other is not None and fmax.get(headline) is not None and fmax.get(other) is not None:
        d = fmax[headline] - fmax[other]
        rel = d / abs(fmax[headline]) if fmax[headline] else None
        out.update(compared_F_max_N=fmax[other], difference_N=float(d), relative=rel,
                   large=bool(rel is not None and abs(rel) > warn_above))
    return out


__all__ = ["convergence_table", "discretisation_estimate", "force_at", "f_max"]

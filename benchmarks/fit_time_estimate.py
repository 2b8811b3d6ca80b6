"""Fit the solve-time estimate of :mod:`pixmuscle.preflight` to the sweeps at today's defaults.

The estimate is ``c·n^q + steps · (a·n^p + b·n²)`` seconds with ``n = nodes / NODES_REF``
(``SETUP_SECONDS = (c, q)``, ``STEP_SECONDS = (a, p, b)``). The fit takes every whole sweep of
``benchmarks/results/bench_solve.json`` made at the shipped defaults (``"defaults": true``,
complete, not ``superseded``): ``c·n^q`` is fitted to their system build (``build_s``), ``a·n^p + b·n²``
to the rest of their time per load step, each minimising the sum of squared differences of the
logarithms (so that a 20 % miss weighs the same at 20 s and at 30 min), with a, b, c ≥ 0.

Usage::

    .venv/bin/python benchmarks/fit_time_estimate.py            # the rows, the fit, each row's ratio
    .venv/bin/python benchmarks/fit_time_estimate.py --check    # exit 1 unless STEP_SECONDS, SETUP_SECONDS are this fit
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

RECORD = Path(__file__).resolve().parent / "results" / "bench_solve.json"


def current_default_sweeps(path: Path = RECORD) -> list[dict]:
    """The complete whole sweeps at the shipped defaults that no later change of them superseded."""
    cases = json.loads(path.read_text())["cases"]
    return [c for c in cases if c.get("defaults") and c.get("status") == "complete" and not c.get("superseded")]


def model_seconds(params, nodes, steps, nodes_ref: float, setup=(0.0, 1.0)):
    """The estimate, s: ``c·n^q + steps · (a·n^p + b·n²)``, ``n = nodes / nodes_ref``, ``setup = (c, q)``."""
    a, p, b = params
    c, q = setup
    n = np.asarray(nodes, float) / nodes_ref
    return c * n**q + np.asarray(steps, float) * (a * n**p + b * n**2)


def fit_setup(rows: list[dict], nodes_ref: float) -> tuple[float, float]:
    """(c, q) of the system build ``c·n^q``: a straight line in log–log through the rows' ``build_s``."""
    n = np.log(np.array([r["nodes"] for r in rows], float) / nodes_ref)
    q, logc = np.polyfit(n, np.log(np.array([r["build_s"] for r in rows], float)), 1)
    return round(float(np.exp(logc)), 3), round(float(q), 3)


def fit(rows: list[dict], nodes_ref: float) -> tuple[float, float, float]:
    """(a, p, b) of a load step, least squares in log over ``rows``' time less their system build, per step
    (rounded as ``STEP_SECONDS`` holds them)."""
    from scipy.optimize import least_squares

    nodes = np.array([r["nodes"] for r in rows], float)
    steps = np.array([r["steps"] for r in rows], float)
    secs = np.array([r["sweep_s"] - r["build_s"] for r in rows], float)

    def residual(x):
        return np.log(model_seconds(x, nodes, steps, nodes_ref)) - np.log(secs)

    best = min((least_squares(residual, x0, bounds=([1e-9, 0.1, 0.0], [np.inf, 3.0, np.inf]))
                for x0 in ([4.0, 0.8, 0.02], [1.0, 1.0, 0.0], [10.0, 0.5, 0.1])), key=lambda r: r.cost)
    a, p, b = best.x
    return round(float(a), 3), round(float(p), 3), round(float(b), 3)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="exit 1 unless preflight.STEP_SECONDS equals the fit")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from pixmuscle.preflight import NODES_REF, SETUP_SECONDS, STEP_SECONDS

    rows = current_default_sweeps()
    if len(rows) < 3:
        print(f"only {len(rows)} sweeps at today's defaults in {RECORD.name}: three or more are needed")
        return 1
    params, setup = fit(rows, NODES_REF), fit_setup(rows, NODES_REF)
    print(f"{len(rows)} sweeps at today's defaults ({RECORD.relative_to(RECORD.parents[2])}):")
    nodes, steps = [r["nodes"] for r in rows], [r["steps"] for r in rows]
    for r, shipped, new in zip(rows, model_seconds(STEP_SECONDS, nodes, steps, NODES_REF, SETUP_SECONDS),
                               model_seconds(params, nodes, steps, NODES_REF, setup), strict=True):
        print(f"  {r['nodes']:>7} nodes  {r['sweep_s']:>7.1f} s recorded   fit {new:7.1f} s ({new / r['sweep_s']:.2f})"
              f"   STEP_SECONDS {shipped:7.1f} s ({shipped / r['sweep_s']:.2f})")
    print(f"fit: STEP_SECONDS = {params}, SETUP_SECONDS = {setup}   (pixmuscle/preflight.py holds {STEP_SECONDS}, "
          f"{SETUP_SECONDS})")
    if args.check and (tuple(params) != tuple(STEP_SECONDS) or tuple(setup) != tuple(SETUP_SECONDS)):
        print("STEP_SECONDS or SETUP_SECONDS differs from the fit: copy the fit into pixmuscle/preflight.py")
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

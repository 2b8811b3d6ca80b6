"""Fit the solve-time estimate of :mod:`pixmuscle.preflight` to the sweeps at today's defaults.

The estimate is ``steps · (a·n^p + b·n²)`` seconds with ``n = nodes / NODES_REF``
(``STEP_SECONDS = (a, p, b)``). The fit takes every whole sweep of
``benchmarks/results/bench_solve.json`` made at the shipped defaults (``"defaults": true``,
complete, not ``superseded``) and minimises the sum of squared differences of the logarithms of
the estimate and the recorded ``sweep_s`` (so that a 20 % miss weighs the same at 20 s and at
30 min), with a, b ≥ 0.

Usage::

    .venv/bin/python benchmarks/fit_time_estimate.py            # the rows, the fit, each row's ratio
    .venv/bin/python benchmarks/fit_time_estimate.py --check    # exit 1 unless STEP_SECONDS is this fit
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


def model_seconds(params, nodes, steps, nodes_ref: float):
    """The estimate, s: ``steps · (a·n^p + b·n²)``, ``n = nodes / nodes_ref``."""
    a, p, b = params
    n = np.asarray(nodes, float) / nodes_ref
    return np.asarray(steps, float) * (a * n**p + b * n**2)


def fit(rows: list[dict], nodes_ref: float) -> tuple[float, float, float]:
    """(a, p, b), least squares in log over ``rows`` (rounded as ``STEP_SECONDS`` holds them)."""
    from scipy.optimize import least_squares

    nodes = np.array([r["nodes"] for r in rows], float)
    steps = np.array([r["steps"] for r in rows], float)
    secs = np.array([r["sweep_s"] for r in rows], float)

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
    from pixmuscle.preflight import NODES_REF, STEP_SECONDS

    rows = current_default_sweeps()
    if len(rows) < 3:
        print(f"only {len(rows)} sweeps at today's defaults in {RECORD.name}: three or more are needed")
        return 1
    params = fit(rows, NODES_REF)
    print(f"{len(rows)} sweeps at today's defaults ({RECORD.relative_to(RECORD.parents[2])}):")
    for r, shipped, new in zip(rows, model_seconds(STEP_SECONDS, [r["nodes"] for r in rows], [r["steps"] for r in rows],
                                                   NODES_REF),
                               model_seconds(params, [r["nodes"] for r in rows], [r["steps"] for r in rows], NODES_REF),
                               strict=True):
        print(f"  {r['nodes']:>7} nodes  {r['sweep_s']:>7.1f} s recorded   fit {new:7.1f} s ({new / r['sweep_s']:.2f})"
              f"   STEP_SECONDS {shipped:7.1f} s ({shipped / r['sweep_s']:.2f})")
    print(f"fit: STEP_SECONDS = {params}   (pixmuscle/preflight.py holds {STEP_SECONDS})")
    if args.check and tuple(params) != tuple(STEP_SECONDS):
        print("STEP_SECONDS differs from the fit: copy the fit into pixmuscle/preflight.py")
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

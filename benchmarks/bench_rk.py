"""Speed benchmark of the RK shape functions on a pixel-model-sized 3-D node cloud.

Node cloud: an elliptical cross-section mask of about 3000 pixels (semi-axes 36 × 26.5 pixels,
in-plane spacing h = 0.078125 cm) stacked on 25 slices 3h apart: ~75,000 nodes, as a muscle
pixel model of paper §5. Shape functions: cubic B-spline box kernel, linear basis,
a = 1.65 h in-plane and 1.65 × 3h across slices (paper §5 and ERRATA), values and exact
gradients at the nodes.

Run:  .venv/bin/python benchmarks/bench_rk.py [--out benchmarks/results]
Writes <out>/bench_rk.json and <out>/bench_rk.md; target: <= 15 s and <= 4 GB peak.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import resource
import sys
import time

import numpy as np

from pixmuscle.rk import shape_functions

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from _record import Run  # noqa: E402

H = 0.078125  # cm, one pixel (paper Fig. 7 caption)
TARGET_S = 15.0
TARGET_GB = 4.0


def pixel_cloud(semi_axes=(36.0, 26.5), n_slices=25, h=H, slice_factor=3.0):
    """Node coordinates (N, 3) in cm of an elliptical mask repeated over slices."""
    ra, rb = semi_axes
    i, j = np.meshgrid(np.arange(-int(ra) - 1, int(ra) + 2), np.arange(-int(rb) - 1, int(rb) + 2), indexing="ij")
    inside = (i / ra) ** 2 + (j / rb) ** 2 <= 1.0
    ij = np.column_stack([i[inside], j[inside]]).astype(float) * h
    k = np.repeat(np.arange(n_slices) * slice_factor * h, ij.shape[0])
    return np.column_stack([np.tile(ij, (n_slices, 1)), k]), int(inside.sum())


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=pathlib.Path, default=pathlib.Path("benchmarks/results"))
    args = parser.parse_args(argv)

    record = Run(defaults=True)
    nodes, n_pixels = pixel_cloud()
    support = np.array([1.65 * H, 1.65 * H, 1.65 * 3.0 * H])
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.perf_counter()
    psi, dpsi = shape_functions(nodes, nodes, support, kernel="cubic", order=1, gradient=True)
    wall = time.perf_counter() - t0
    peak_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # Linux: kB

    # sanity: linear reproduction at the nodes (eq. 5)
    repro = max(np.abs(psi @ nodes[:, k] - nodes[:, k]).max() for k in range(3))
    grad = max(np.abs(dpsi[k] @ nodes[:, k] - 1.0).max() for k in range(3))
    result = {
        "benchmark": "rk.shape_functions 3-D pixel cloud, cubic box kernel, linear basis, gradient",
        "n_nodes": int(nodes.shape[0]),
        "pixels_per_slice": n_pixels,
        "slices": 25,
        "h_cm": H,
        "support_cm": support.tolist(),
        "nnz": int(psi.nnz),
        "neighbours_per_node_mean": float(psi.nnz / nodes.shape[0]),
        "wall_s": round(wall, 3),
        "peak_rss_gb": round(peak_kb / 1024**2, 3),
        "rss_before_gb": round(rss0 / 1024**2, 3),
        "max_reproduction_error_cm": float(repro),
        "max_gradient_reproduction_error": float(grad),
        "target_wall_s": TARGET_S,
        "target_peak_gb": TARGET_GB,
        "meets_target": bool(wall <= TARGET_S and peak_kb / 1024**2 <= TARGET_GB),
        "python": sys.version.split()[0],
        "numpy": np.__version__,
        **record.fields(),
    }
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "bench_rk.json").write_text(json.dumps(result, indent=2) + "\n")
    line = (
        f"| rk.shape_functions (3-D, {result['n_nodes']} nodes, cubic box, n=1, +grad) "
        f"| {result['wall_s']:.2f} s | {result['peak_rss_gb']:.2f} GB peak RSS "
        f"| nnz {result['nnz']} | target ≤ {TARGET_S:g} s, ≤ {TARGET_GB:g} GB: "
        f"{'met' if result['meets_target'] else 'NOT met'} |"
    )
    (args.out / "bench_rk.md").write_text(line + "\n")
    print(line)
    return 0 if result["meets_target"] else 1


if __name__ == "__main__":
    raise SystemExit(main())

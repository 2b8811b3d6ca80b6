"""Material-law speed: stress and consistent tangent on 75,000 points (one Newton iteration's worth).

Run: ``python benchmarks/bench_materials.py``; writes ``benchmarks/results/bench_materials.{json,md}``.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from pixmuscle.mechanics import materials as m

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _record import Run  # noqa: E402

OUT = Path(__file__).resolve().parent / "results"


def main(n: int = 75_000, repeats: int = 7) -> dict:
    record = Run(defaults=True)
    rng = np.random.default_rng(0)
    F = np.eye(3) + 0.1 * rng.standard_normal((n, 3, 3))
    fiber = rng.standard_normal((n, 3))
    rows = {}
    for name, mat, kw in [("connective_tissue", m.CONNECTIVE_TISSUE, {}),
                          ("muscle", m.MUSCLE, {"fiber": fiber, "activation": 0.7})]:
        for fn in ("stress", "stress_tangent"):
            getattr(mat, fn)(F[:10], **({k: (v[:10] if k == "fiber" else v) for k, v in kw.items()}))  # JIT warm-up
            ts = []
            for _ in range(repeats):
                t = time.perf_counter()
                getattr(mat, fn)(F, **kw)
                ts.append(time.perf_counter() - t)
            rows[f"{name}.{fn}"] = {"min_s": min(ts), "median_s": float(np.median(ts))}
    OUT.mkdir(exist_ok=True)
    (OUT / "bench_materials.json").write_text(json.dumps({"points": n, "results": rows, **record.fields()}, indent=2))
    md = [f"Materials on {n} points (min / median of {repeats}):", "", "| law.function | min (ms) | median (ms) |", "|---|---|---|"]
    md += [f"| {k} | {v['min_s'] * 1e3:.0f} | {v['median_s'] * 1e3:.0f} |" for k, v in rows.items()]
    (OUT / "bench_materials.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))
    return rows


if __name__ == "__main__":
    main()

"""The patch of the projected pressure: forces with 1 × 1 × 3 and 2 × 2 × 3 patches on the verification cases.

The 1 × 1 × 3 patch pressure is not inf-sup stable on the voxel grid (``bench_solve.py --infsup``),
2 × 2 × 3 is; a larger patch shares one pressure across more tissue, so it may cost accuracy where
tissues meet. Each case is solved with the former default, 1 × 1 × 3 patches with nodes held at the
node in single-node patches (``volumetric.held: own``), and the default, 2 × 2 × 3 patches with held
nodes in their patches (``held: patch``); every other setting at its default, direct solver:

``locking``
    Clamped, stretched connective-tissue bar (``bench_locking.py``) at K/μ = 83, 833, 8,333 against
    scikit-fem mixed Q2–P1disc finite elements on the same voxels.
``tendon``
    The Example-1 tendon at 0.2 × 0.2 × 0.5 cm stretched 2 cm (``bench_vs_fe.py``) against its converged
    finite-element force (read from ``results/bench_vs_fe.json``).
``columns``
    Two muscle columns side by side (2 × 2 voxels each), activated to α = 0.9 and 0.4, roller ends: the
    total force against the sum of the two homogeneous blocks (closed form, ``mechanics.homogeneous``).
``block``
    The clamped 2 × 1.5 × 6 cm muscle block with fibres at 25° in the xz plane, h = 0.5 cm, α 0 → 0.95.
``leg5k``
    The synthetic Example-2 leg at ~5k nodes (``bench_solve.py``'s geometry and boundary conditions),
    α 0 → 0.95 in 10 steps.
``demo``
    ``pixmuscle run configs/demo.yaml`` with ``solve.volumetric.patch`` set (F_max of the report).

Writes ``benchmarks/results/bench_patch.json`` and ``bench_patch.md``.

Usage::

    .venv/bin/python benchmarks/bench_patch.py                  # every case
    .venv/bin/python benchmarks/bench_patch.py --cases tendon columns
"""

from __future__ import annotations

import argparse
import json
import pathlib
import subprocess
import sys
import tempfile
import time

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from _record import Run  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parent.parent
OUT = ROOT / "benchmarks" / "results"
#: label → (patch, volumetric.held)
PATCHES = {"1x1x3": ((1, 1, 3), "own"), "2x2x3": ((2, 2, 3), "patch")}
CASES = ("locking", "tendon", "columns", "block", "leg5k", "demo")


def _volumetric(patch) -> dict:
    shape, held = patch
    return {"method": "projected", "patch": list(shape), "held": held}


def _solve(model, patch, **keys):
    from pixmuscle.mechanics.solve import solve
    from pixmuscle.verify.mechanics import _cfg

    t = time.perf_counter()
    res = solve(model, _cfg(volumetric=_volumetric(patch), **keys))
    return res, round(time.perf_counter() - t, 2)


def case_locking(patch):
    from pixmuscle.verify.mechanics import mask_model
    from pixmuscle.verify.tendon_fem import tendon_fem_reaction

    h, stretch, mu = (0.2, 0.2, 0.5), 0.3, 60.0
    mask = np.ones((4, 4, 12), bool)
    model = mask_model(mask, h)
    bcs = [{"nodes": "z_min", "fix": ["x", "y", "z"]}, {"nodes": "z_max", "fix": ["x", "y"], "displace": {"z": stretch}}]
    rows = []
    for kmu in (83.3, 833.3, 8333.3):
        K = kmu * mu
        ref = float(tendon_fem_reaction(mask, np.diag([*h, 1.0]), stretch=stretch, steps=1, refine=(2, 2, 4), element="mixed",
                                        bc="clamped", material=(30.0, 80.0, 800.0, K))["force"][-1])
        res, s = _solve(model, patch, steps=1, activation={"from": 0.0, "to": 0.0}, boundary_conditions=bcs,
                        materials={"connective_tissue": {"K": K}})
        f = float(res.force("z_min")[-1])
        rows.append({"K_over_mu": kmu, "force_N": f, "reference_N": ref, "rel_error": f / ref - 1.0, "s": s})
    return {"rows": rows, "reference": "scikit-fem Q2-P1disc, each voxel 2 x 2 x 4 elements"}


def case_tendon(patch):
    from pixmuscle.verify.mechanics import tendon_model

    ref = json.loads((OUT / "bench_vs_fe.json").read_text())["reference"]
    model, _, _ = tendon_model((0.2, 0.2, 0.5))
    res, s = _solve(model, patch, steps=4, activation={"from": 0.0, "to": 0.0}, boundary_conditions=[
        {"nodes": "z_min", "fix": ["x", "y", "z"]}, {"nodes": "z_max", "fix": ["x", "y"], "displace": {"z": 2.0}}])
    f = float(res.force("z_min")[-1])
    return {"force_N": f, "reference_N": ref["force_N"], "rel_error": f / ref["force_N"] - 1.0, "s": s,
            "newton_iterations_per_step": res.iterations.tolist()[1:], "reference": ref["method"]}


def case_columns(patch):
    from pixmuscle.mechanics import homogeneous
    from pixmuscle.mechanics.solve import make_materials
    from pixmuscle.model.tissues import MUSCLE
    from pixmuscle.verify.mechanics import _cfg, mask_model, roller_bcs

    model = mask_model(np.ones((4, 2, 4), bool), (0.2, 0.2, 0.3), tissue=MUSCLE)
    model.muscle_id = np.where(model.ijk[:, 0] < 2, 1, 2).astype(np.int16)
    model.muscle_names = ["medial", "lateral"]
    res, s = _solve(model, patch, steps=2, boundary_conditions=roller_bcs(model, 0.0),
                    activation={"from": 0.0, "to": {"medial": 0.9, "lateral": 0.4}})
    mat = make_materials(_cfg().materials)[MUSCLE]
    ref = sum(homogeneous.isometric_block(mat, a, 0.4 * 0.4)["force"] for a in (0.9, 0.4))
    f = abs(float(res.force("z_max")[-1]))
    return {"force_N": f, "reference_N": ref, "rel_error": f / ref - 1.0, "s": s,
            "reference": "sum of two homogeneous isometric blocks (closed form)"}


def case_block(patch):
    from pixmuscle.model.tissues import MUSCLE
    from pixmuscle.verify.mechanics import mask_model

    th = np.radians(25.0)
    model = mask_model(np.ones((4, 3, 12), bool), (0.5, 0.5, 0.5), tissue=MUSCLE, fiber=(np.sin(th), 0.0, np.cos(th)))
    res, s = _solve(model, patch, steps=10, activation={"from": 0.0, "to": 0.95}, boundary_conditions=[
        {"nodes": "z_min", "fix": ["x", "y", "z"]}, {"nodes": "z_max", "fix": ["x", "y", "z"]}])
    return {"force_curve_N": [float(abs(f)) for f in res.force("z_max")], "force_N": float(abs(res.force("z_max")[-1])),
            "s": s, "newton_iterations_per_step": res.iterations.tolist()[1:]}


def case_leg5k(patch):
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from bench_solve import leg_case

    from pixmuscle.mechanics.solve import solve

    model, cfg = leg_case("5k", None, volumetric=_volumetric(patch),
                          steps=10, activation={"from": 0.0, "to": 0.95}, solver={"backend": "direct"})
    t = time.perf_counter()
    res = solve(model, cfg)
    return {"nodes": model.n_nodes, "force_curve_N": [float(abs(f)) for f in res.force("z_max")],
            "force_N": float(abs(res.force("z_max")[-1])), "s": round(time.perf_counter() - t, 1),
            "newton_iterations_per_step": res.iterations.tolist()[1:], "nnz_per_row": res.info.get("nnz_per_row"),
            "factor_nnz": res.info.get("factor_nnz")}


def case_demo(patch):
    with tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        proc = subprocess.run([sys.executable, "-m", "pixmuscle.cli", "-q", "run", "configs/demo.yaml", "-o", tmp,
                               "--set", f"solve.volumetric.patch=[{','.join(map(str, patch[0]))}]",
                               "--set", f"solve.volumetric.held={patch[1]}"],
                              cwd=ROOT, capture_output=True, text=True)
        if proc.returncode:
            return {"error": proc.stderr.strip().splitlines()[-1:]}
        summary = json.loads(next(pathlib.Path(tmp).rglob("summary.json")).read_text())
        return {"force_N": summary["F_max_N"], "n_nodes": summary.get("n_nodes"), "s": round(time.perf_counter() - t, 1)}


def write(results: dict, run: Run) -> None:
    meta = run.fields()
    OUT.mkdir(parents=True, exist_ok=True)
    path = OUT / "bench_patch.json"
    old = json.loads(path.read_text())["cases"] if path.exists() else {}
    old.update(results)
    path.write_text(json.dumps({"meta": meta, "cases": old}, indent=1))
    made = {k: v for k, v in old.items() if isinstance(v, dict) and v.get("command")}
    lines = ["# Patch of the projected pressure: 1 × 1 × 3 (held: own) against 2 × 2 × 3 (held: patch)", "",
             "Each case is its own record in `bench_patch.json` (command, commit, load average); made by:", "",
             *[f"- `{v['command']}` — {v['utc']}, commit {v['commit'][:10]}, load average "
               f"{v['load_average']['before'][0]} → {v['load_average']['after'][0]}" for v in made.values()], "",
             "| case | 1 × 1 × 3 | 2 × 2 × 3 | 2 × 2 × 3 vs 1 × 1 × 3 |", "|---|---|---|---|"]
    for name in CASES:
        if name not in old:
            continue
        a, b = old[name].get("1x1x3", {}), old[name].get("2x2x3", {})
        if name == "locking":
            for ra, rb in zip(a.get("rows", []), b.get("rows", []), strict=False):
                lines.append(f"| locking K/μ = {ra['K_over_mu']:g} (FE {ra['reference_N']:.4f} N) | {100 * ra['rel_error']:+.2f} % "
                             f"| {100 * rb['rel_error']:+.2f} % | {100 * (rb['force_N'] / ra['force_N'] - 1):+.2f} % |")
            continue
        def cell(r):
            if "force_N" not in r:
                return r.get("error", "—")
            err = f" ({100 * r['rel_error']:+.2f} % vs reference)" if "rel_error" in r else ""
            return f"{r['force_N']:.4f} N{err}"
        rel = (f"{100 * (b['force_N'] / a['force_N'] - 1):+.3f} %" if "force_N" in a and "force_N" in b else "—")
        lines.append(f"| {name} | {cell(a)} | {cell(b)} | {rel} |")
    (OUT / "bench_patch.md").write_text("\n".join(lines) + "\n")


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--cases", nargs="+", default=list(CASES), choices=CASES)
    args = p.parse_args(argv)
    results = {}
    for name in args.cases:
        record = Run(defaults=False, command=".venv/bin/python benchmarks/bench_patch.py --cases " + name)
        results[name] = {}
        for label, patch in PATCHES.items():
            results[name][label] = globals()[f"case_{name}"](patch)
            print(name, label, json.dumps(results[name][label])[:300], flush=True)
        results[name].update(record.fields())
        write({name: results[name]}, record)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

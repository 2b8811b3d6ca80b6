"""Benchmark of the meshfree solver against hexahedral finite elements on the same voxels (paper Example 1).

Case: the Example 1 tendon of :func:`pixmuscle.verify.mechanics.tendon_model` at voxel size
h = (0.2, 0.2, 0.5) cm (800 voxels); connective tissue, paper eq. (27),
W = C10 (Ī1 − 3) + C20 (Ī1 − 3)² + C30 (Ī1 − 3)³ + K/2 (J − 1)², Ī1 = J^(−2/3) I1, with C10 = 30,
C20 = 80, C30 = 800, K = 50 000 N/cm². Bottom end z_min fixed in x, y, z; top end z_max held in
x, y and displaced +2 cm in z over ``--steps`` equal load steps. Measured: the reaction force at
the fixed end at 2 cm (N, tension positive), its error against a converged reference, wall time
and peak RSS of each case.

Methods (``--cases``):

``pixmuscle:nodal`` / ``pixmuscle:projected``
    pixmuscle's SCNI–RKPM solver, one node per voxel, with ``solve.volumetric.method`` ``nodal``
    (K/2 (J − 1)² at every node, as in the paper) or ``projected`` (mean dilatation per patch of
    voxels, the default: 2 × 2 × 3 voxels; the record's +0.36 % was measured with 1 × 1 × 3); every
    other setting at its default.
``felupe:RXxRYxRZ`` (e.g. ``felupe:1x1x1``, ``felupe:2x2x2``)
    FElupe's trilinear hexahedra (hex8) in the mixed Q1/P0/P0 (u, p, J̄) form of
    ``SolidBodyNearlyIncompressible`` (mean dilatation per element, pressure and dilatation
    condensed out), with FElupe's isochoric Yeoh law on Ī1 (tensortrax differentiates it) and
    bulk modulus K. The mesh is the voxel domain itself: each voxel of the mask split into
    RX × RY × RZ boxes, nodes at the box corners (from the affine), so the ends are the outer faces
    of the end slices. Newton by ``felupe.newtonraphson`` to a relative residual of 1e-4 (pixmuscle's default) with
    PARDISO (``pypardiso``, FElupe's recommended solver; SciPy's SuperLU when it is missing).

The reference is the scikit-fem mixed Q2–P1disc solution on the same voxel domain,
:func:`pixmuscle.verify.tendon_fem.tendon_fem_reaction` with ``refine=(1, 1, 4)``, 2 load steps
(15.467 N; 15.483 N at refine (1, 1, 2) and 15.485 N at (2, 2, 2), so converged to about 0.1 %). It is
computed in the run and kept in the results file; ``--reuse-reference`` takes it from there instead.

Every case runs in its own process (so its peak RSS is its own, imports included) with
``--threads`` threads for MKL/OpenMP/numba (default 1: on a machine shared with other jobs
oversubscribed MKL threads make the direct solves several times slower, and one thread gives
both methods the same footing).

Writes ``benchmarks/results/bench_vs_fe.json`` and ``bench_vs_fe.md``.

Usage (FElupe is in the optional extra ``bench``: ``.venv/bin/pip install -e '.[bench]'``)::

    .venv/bin/python benchmarks/bench_vs_fe.py                      # the DEFAULT_CASES and the reference
    .venv/bin/python benchmarks/bench_vs_fe.py --reuse-reference --append --cases felupe:3x3x3
    .venv/bin/python benchmarks/bench_vs_fe.py --tables             # only rewrite the .md from the .json
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import platform
import resource
import subprocess
import sys
import time

import numpy as np

OUT = pathlib.Path(__file__).parent / "results"
STEM = "bench_vs_fe"
H = (0.2, 0.2, 0.5)          # voxel size, cm
STRETCH = 2.0                # top displacement, cm
REFERENCE = {"refine": (1, 1, 4), "steps": 2, "element": "mixed", "bc": "clamped"}
DEFAULT_CASES = ["pixmuscle:nodal", "pixmuscle:projected", "felupe:1x1x1", "felupe:1x1x2", "felupe:1x1x4", "felupe:2x2x2"]
NEWTON_TOL = 1e-4            # FElupe: ‖f(free)‖ / ‖f(prescribed)‖, as pixmuscle's default residual tolerance
SHARED_NOTE = ("measured on a machine shared with other jobs (load average in meta): wall times are "
               "upper bounds and comparable only within one run")
THREAD_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS")


def parse_case(spec: str) -> tuple[str, object]:
    """``pixmuscle:nodal|projected`` → ("pixmuscle", method); ``felupe:RXxRYxRZ`` → ("felupe", (rx, ry, rz));
    ``reference`` → ("reference", None)."""
    if spec == "reference":
        return "reference", None
    method, _, arg = spec.partition(":")
    if method == "pixmuscle" and arg in ("nodal", "projected"):
        return method, arg
    if method == "felupe":
        parts = arg.split("x")
        if len(parts) == 3 and all(p.isdigit() and int(p) >= 1 for p in parts):
            return method, tuple(int(p) for p in parts)
    raise ValueError(f"case {spec!r}: expected pixmuscle:nodal, pixmuscle:projected or felupe:RXxRYxRZ "
                     f"(whole numbers >= 1, e.g. felupe:2x2x2)")


def voxel_hex8_mesh(mask: np.ndarray, affine: np.ndarray, refine=(1, 1, 1)) -> tuple[np.ndarray, np.ndarray]:
    """Hexahedral mesh of the union of the voxel boxes of ``mask``, each split into ``refine`` boxes.

    Parameters
    ----------
    mask : ndarray of bool, shape (I, J, K)
        Voxels of the body.
    affine : ndarray, shape (4, 4)
        Grid-aligned voxel index → cm of the voxel centres (diagonal spacing).
    refine : sequence of 3 int
        Boxes per voxel edge along x, y, z.

    Returns
    -------
    points : ndarray, shape (n, 3)
        Box corners, cm.
    cells : ndarray of int, shape (m, 8)
        Corner indices per box in VTK hexahedron order (bottom face counter-clockwise, then top).
    """
    r = np.asarray(refine, int)
    h = np.diag(affine)[:3]
    fine = mask
    for a in range(3):
        fine = np.repeat(fine, r[a], axis=a)
    corner = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]])
    lattice = np.array(fine.shape) + 1
    boxes = np.argwhere(fine)
    flat = np.ravel_multi_index((boxes[:, None, :] + corner).reshape(-1, 3).T, lattice)
    used, cells = np.unique(flat, return_inverse=True)
    points = (affine[:3, 3] - 0.5 * h) + (h / r) * np.column_stack(np.unravel_index(used, lattice))
    return points, cells.reshape(-1, 8)


def peak_rss_gb() -> float:
    return round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2, 3)


def run_pixmuscle(method: str, steps: int) -> dict:
    """pixmuscle's solve of the tendon with ``solve.volumetric.method = method``."""
    from pixmuscle.mechanics.solve import solve
    from pixmuscle.verify.mechanics import _cfg, tendon_model

    model, _, _ = tendon_model(H)
    cfg = _cfg(steps=steps, activation={"from": 0.0, "to": 0.0}, volumetric={"method": method}, boundary_conditions=[
        {"nodes": "z_min", "fix": ["x", "y", "z"]},
        {"nodes": "z_max", "fix": ["x", "y"], "displace": {"z": STRETCH}},
    ])
    t0 = time.perf_counter()
    res = solve(model, cfg)
    wall = time.perf_counter() - t0
    return {"method": f"pixmuscle SCNI-RKPM, volumetric {method}", "nodes": model.n_nodes, "dofs": 3 * model.n_nodes,
            "elements_per_voxel": None, "status": res.status, "force_N": float(res.force("z_min")[-1]),
            "force_top_N": float(res.force("z_max")[-1]), "force_curve_N": [float(f) for f in res.force("z_min")],
            "newton_iterations_per_step": res.iterations.tolist()[1:], "linear_engine": res.info.get("linear_engine"),
            "wall_s": round(wall, 2), "peak_rss_GB": peak_rss_gb()}


def run_felupe(refine: tuple[int, int, int], steps: int) -> dict:
    """FElupe hex8 Q1/P0/P0 solve of the tendon on its voxel domain, each voxel split into ``refine`` boxes."""
    os.environ.setdefault("FELUPE_VERBOSE", "false")
    try:
        import felupe as fem
        fem.Hyperelastic  # noqa: B018  (present only with tensortrax)
    except (ImportError, AttributeError):
        raise SystemExit("bench_vs_fe: felupe with tensortrax is needed for the felupe cases: "
                         ".venv/bin/pip install -e '.[bench]'") from None
    from scipy.sparse.linalg import spsolve

    from pixmuscle.verify.mechanics import tendon_model
    from pixmuscle.verify.tendon_fem import CONNECTIVE_TISSUE

    try:
        from pypardiso import spsolve as solver
        engine = "pardiso (pypardiso)"
    except ImportError:
        solver, engine = spsolve, "superlu (scipy)"
    C10, C20, C30, K = CONNECTIVE_TISSUE
    _, mask, affine = tendon_model(H)
    t0 = time.perf_counter()
    points, cells = voxel_hex8_mesh(mask, affine, refine)
    field = fem.FieldContainer([fem.Field(fem.RegionHexahedron(fem.Mesh(points, cells, "hexahedron")), dim=3)])
    umat = fem.Hyperelastic(fem.yeoh, C10=C10, C20=C20, C30=C30)     # isochoric: Ī1 = J^(-2/3) tr C
    solid = fem.SolidBodyNearlyIncompressible(umat, field, bulk=K)
    z = points[:, 2]
    bottom = fem.Boundary(field[0], mask=np.isclose(z, z.min()))                   # x, y, z fixed
    top_xy = fem.Boundary(field[0], mask=np.isclose(z, z.max()), skip=(0, 0, 1))   # x, y held
    top_z = fem.Boundary(field[0], mask=np.isclose(z, z.max()), skip=(1, 1, 0))    # z displaced
    bounds = {"bottom": bottom, "top_xy": top_xy, "top_z": top_z}
    dof0, dof1 = fem.dof.partition(field, bounds)
    curve, top, iterations = [0.0], 0.0, []
    for n in range(1, steps + 1):
        top_z.update(STRETCH * n / steps)
        res = fem.newtonraphson(items=[solid], x0=field, dof1=dof1, dof0=dof0, ext0=fem.dof.apply(field, bounds, dof0),
                                solver=solver, tol=NEWTON_TOL, verbose=0)
        # the residual at prescribed dofs is the force the support exerts on the body; at the bottom
        # (outward normal -z) tension is -f_z
        curve.append(float(-fem.tools.force(field, res.fun, bottom)[2]))
        top = float(fem.tools.force(field, res.fun, top_z)[2])
        iterations.append(int(res.iterations))
    wall = time.perf_counter() - t0
    return {"method": f"FElupe hex8 Q1/P0/P0, {'x'.join(map(str, refine))} per voxel", "nodes": len(points),
            "dofs": 3 * len(points), "elements": len(cells), "elements_per_voxel": list(refine), "status": "complete",
            "force_N": curve[-1], "force_top_N": top, "force_curve_N": curve, "newton_iterations_per_step": iterations,
            "linear_engine": engine, "felupe_version": fem.__version__, "wall_s": round(wall, 2),
            "peak_rss_GB": peak_rss_gb()}


def run_reference() -> dict:
    """The scikit-fem Q2–P1disc reference (:data:`REFERENCE` settings) on the voxel domain."""
    from pixmuscle.verify.mechanics import tendon_model
    from pixmuscle.verify.tendon_fem import tendon_fem_reaction

    _, mask, affine = tendon_model(H)
    t0 = time.perf_counter()
    res = tendon_fem_reaction(mask, affine, stretch=STRETCH, **REFERENCE)
    return {"method": "scikit-fem Q2-P1disc (reference)", "refine": list(REFERENCE["refine"]),
            "steps": REFERENCE["steps"], "dofs": res["dofs"], "symmetry_factor": res["symmetry_factor"],
            "force_N": float(res["force"][-1]), "force_top_N": float(res["force_top"][-1]),
            "wall_s": round(time.perf_counter() - t0, 2), "peak_rss_GB": peak_rss_gb()}


def run_one(spec: str, steps: int) -> dict:
    method, arg = parse_case(spec)
    if method == "reference":
        return run_reference()
    return run_pixmuscle(arg, steps) if method == "pixmuscle" else run_felupe(arg, steps)


def in_subprocess(spec: str, steps: int, threads: int) -> dict:
    """Run one case in a fresh process with ``threads`` threads; its result, or its last error line."""
    env = dict(os.environ, FELUPE_VERBOSE="false", **{v: str(threads) for v in THREAD_VARS})
    proc = subprocess.run([sys.executable, __file__, "--one", spec, "--steps", str(steps)],
                          capture_output=True, text=True, env=env)
    got = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
    if got:
        return json.loads(got[-1][7:])
    return {"error": (proc.stderr.strip().splitlines() or [f"exit status {proc.returncode}"])[-1]}


def with_errors(cases: list[dict], ref: dict | None) -> list[dict]:
    """Add the relative error of each final force against the reference."""
    for c in cases:
        if ref and "force_N" in c:
            c["rel_error"] = (c["force_N"] - ref["force_N"]) / ref["force_N"]
    return cases


def write_results(cases: list[dict], ref: dict | None, meta: dict) -> None:
    (OUT / f"{STEM}.json").write_text(json.dumps({"meta": meta, "reference": ref, "cases": cases}, indent=1))
    lines = [f"# {STEM}: meshfree vs hexahedral finite elements on the same voxels (paper Example 1 tendon)", "",
             f"{meta['date_utc']}, {meta['platform']}, Python {meta['python']}, {meta['cpus']} CPUs, "
             f"{meta['threads']} thread(s) per case, load average {meta['load_average']} at start; {SHARED_NOTE}.", "",
             f"Command: `{meta['command']}`", "",
             f"Tendon at voxel size {tuple(H)} cm, top displaced {STRETCH:g} cm in {meta['steps']} load steps. "
             "Error: final reaction force against the reference below.", ""]
    if ref:
        lines += [f"Reference: {ref['method']}, refine {tuple(ref['refine'])}, {ref['steps']} steps, {ref['dofs']} dofs "
                  f"(quarter model, ×{ref['symmetry_factor']}): **{ref['force_N']:.4f} N** "
                  f"({ref['wall_s']} s, {ref['peak_rss_GB']} GB).", ""]
    lines += ["| case | method | voxel (cm) | nodes | dofs | F_z at 2 cm (N) | error vs ref. | within 1 % | "
              "Newton its / step | wall (s) | peak RSS (GB) |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for c in cases:
        if "error" in c:
            lines.append(f"| {c['case']} | failed: {c['error'][:80]} | | | | | | | | | |")
            continue
        err = c.get("rel_error")
        lines.append(f"| {c['case']} | {c['method']} | {' × '.join(f'{x:g}' for x in c['voxel_size_cm'])} | "
                     f"{c['nodes']} | {c['dofs']} | {c['force_N']:.4f} | "
                     + ("—" if err is None else f"{100 * err:+.2f} %") + " | "
                     + ("—" if err is None else ("yes" if abs(err) <= 0.01 else "no")) + f" | "
                     f"{c['newton_iterations_per_step']} | {c['wall_s']} | {c['peak_rss_GB']} |")
    lines += ["", "Wall time: pixmuscle's `solve()` (RK/SCNI build included, the model from the mask not); FElupe "
              "from the voxel mask to the last step (mesh, region and field included). Peak RSS: of the case's own "
              "process, imports included. FElupe dofs: displacements only (the element pressure and dilatation are "
              "condensed). Commands per case in bench_vs_fe.json."]
    (OUT / f"{STEM}.md").write_text("\n".join(lines) + "\n")


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--cases", nargs="+", default=DEFAULT_CASES,
                   help="pixmuscle:nodal, pixmuscle:projected, felupe:RXxRYxRZ (default: %(default)s)")
    p.add_argument("--steps", type=int, default=4, help="load steps to the 2-cm stretch (default: %(default)s)")
    p.add_argument("--threads", type=int, default=1, help="MKL/OpenMP/numba threads per case (default: %(default)s)")
    p.add_argument("--reuse-reference", action="store_true",
                   help="take the reference force from the existing results file instead of computing it")
    p.add_argument("--append", action="store_true",
                   help="merge into the existing results file (cases measured again are replaced)")
    p.add_argument("--tables", action="store_true", help=f"only rewrite {STEM}.md from {STEM}.json")
    p.add_argument("--one", default=None, help=argparse.SUPPRESS)  # internal: run one case, print JSON
    args = p.parse_args(argv)
    if args.one:
        print("RESULT " + json.dumps(run_one(args.one, args.steps)), flush=True)
        return 0
    path = OUT / f"{STEM}.json"
    old = json.loads(path.read_text()) if path.exists() else None
    if args.tables:
        if old is None:
            p.error(f"--tables: {path} does not exist")
        write_results(old["cases"], old["reference"], old["meta"])
        return 0
    for spec in args.cases:
        try:
            parse_case(spec)
        except ValueError as exc:
            p.error(str(exc))
    if args.steps < 1 or args.threads < 1:
        p.error("--steps and --threads must be >= 1")
    OUT.mkdir(parents=True, exist_ok=True)
    command = " ".join([".venv/bin/python benchmarks/bench_vs_fe.py", *argv])
    meta = {"python": platform.python_version(), "machine": platform.machine(), "platform": platform.platform(),
            "cpus": os.cpu_count(), "load_average": [round(x, 1) for x in os.getloadavg()],
            "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "command": command,
            "steps": args.steps, "threads": args.threads, "voxel_size_cm": list(H), "stretch_cm": STRETCH,
            "note": SHARED_NOTE}
    ref = old.get("reference") if (args.reuse_reference and old) else None
    if ref is None:
        print("== reference", flush=True)
        ref = in_subprocess("reference", args.steps, args.threads)
        ref.update(command=command, date_utc=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                   platform=meta["platform"], cpus=meta["cpus"], threads=args.threads)
        print(json.dumps(ref), flush=True)
        if "error" in ref:
            ref = None
    cases = []
    if args.append and old:
        cases = [c for c in old["cases"] if c.get("case") not in set(args.cases)]
    for spec in args.cases:
        print(f"== {spec}", flush=True)
        res = in_subprocess(spec, args.steps, args.threads)
        res.update(case=spec, voxel_size_cm=list(H), steps=args.steps, threads=args.threads,
                   date_utc=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), platform=meta["platform"],
                   cpus=meta["cpus"], note=SHARED_NOTE,
                   command=f".venv/bin/python benchmarks/bench_vs_fe.py --cases {spec} --steps {args.steps} "
                           f"--threads {args.threads} --reuse-reference --append")
        cases.append(res)
        print(json.dumps(res)[:600], flush=True)
        write_results(with_errors(cases, ref), ref, meta)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

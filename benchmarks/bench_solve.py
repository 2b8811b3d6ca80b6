"""Benchmark of the whole SCNI–RKPM activation sweep (paper Example 2 set-up) at growing size.

Model: the SYNTHETIC lower leg of :mod:`pixmuscle.synth.leg` (muscles with fibre fields,
connective tissue, skin, fat; tibia and fibula are holes) sampled at voxel centres of the paper's
Example 2 grid, 0.156 × 0.156 cm in-plane and 0.5 cm between slices. The leg is scaled down for
the smaller sizes: ~5k nodes = (leg scale 0.50, 8 slices), ~20k = (0.72, 15), ~75k = (1.04, 25,
the paper's 73,659-node model has 25 slices). Smaller legs hold relatively more fat and
connective tissue. ``295k`` is the 75k leg at the paper's refined resolution, every 0.078125-cm
pixel in-plane and the same 25 slices (Fig. 9a); ``20k-fine`` and ``75k-fine`` are legs half as
wide on those pixels with the node counts of ``20k`` and ``75k``.

Solve: α 0 → 0.95 in 10 load steps, both ends fixed, bone surfaces fixed in-plane, cubic
kernel, linear basis, a/h = 1.65, every other setting at its default. Each case runs in its own
process, so its peak RSS (:func:`_record.peak_rss_GB`, BoomerAMG workers included) is its own.
Every row carries the fields of :mod:`_record` (command, commit, utc, machine, load average
before and after, defaults, peak_rss_GB), ``ranks`` (1: these sweeps run in one process) and
``peak_rss_GB_per_rank_max`` (the largest rank's own tree: here the whole tree).

Records per case: RK + SCNI build, pattern/assembly time per Newton iteration, linear set-up and
solve time per Newton iteration, CG iterations, Newton iterations per step, whole sweep, peak RSS,
non-zeros per row, the final reaction force; then the growth exponent of each quantity between
the sizes (least-squares slope of log(quantity) against log(nodes)).

Writes ``benchmarks/results/bench_solve.json`` and ``bench_solve.md``.

Usage::

    .venv/bin/python benchmarks/bench_solve.py                       # the DEFAULT_CASES below
    .venv/bin/python benchmarks/bench_solve.py --cases 5k:cg_amg 5k:direct 20k:direct_reuse
    .venv/bin/python benchmarks/bench_solve.py --append --cases 75k:cg_amg:1e-2   # Newton tolerance 1e-2
    .venv/bin/python benchmarks/bench_solve.py --append --cases 295k:auto --checkpoint ckpt   # resumable

With ``--checkpoint DIR`` each sweep writes its converged load steps to DIR as it goes; the same
command after a kill (a session's end) resumes it from the last converged step. The record then
lists the runs under ``segments`` (wall time up to each run's last converged step, its own build
and set-up included) and ``sweep_s`` is their sum; its Krylov counts are the last run's.

Backends (``--cases SIZE:BACKEND``): ``direct`` (PARDISO when MKL is installed, else SuperLU; factorised at
every Newton iteration), ``direct_reuse`` (the default: kept factors precondition CG), ``superlu``, ``cg_amg``. An optional third
field sets the Newton residual tolerance (default 1e-8; the energy tolerance follows as 100·tol²),
e.g. ``75k:cg_amg:1e-2``; such cases are labelled "cg_amg, Newton 0.01" in the tables. A fourth sets
``newton.forcing_max`` (η_max, default 1e-2), e.g. ``5k:cg_amg:1e-2:0.1``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import pathlib
import platform
import subprocess
import sys
import time

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from _record import Run, peak_rss_GB  # noqa: E402

OUT = pathlib.Path(__file__).parent / "results"
SPACING = (0.15625, 0.15625, 0.5)
FINE = (0.078125, 0.078125, 0.5)  # the paper's refined model: every pixel, the same slices
# size → (leg scale, slices[, spacing (cm), SPACING when not given])
SIZES = {"1.5k": (0.45, 3), "2k": (0.40, 5), "5k": (0.50, 8), "10k": (0.62, 11), "20k": (0.72, 15), "75k": (1.04, 25),
         "295k": (1.04, 25, FINE),
         # the 20k and 75k node counts on the refined pixels (a leg half as wide): the fine pixels' own growth in N
         "20k-fine": (0.36, 15, FINE), "75k-fine": (0.52, 25, FINE)}
# the records of docs/performance.md; about 2 h in all, 40 min of it the 74k sweep
DEFAULT_CASES = ["5k:direct", "5k:direct_reuse", "5k:cg_amg", "10k:direct_reuse", "10k:cg_amg", "20k:direct_reuse",
                 "5k:direct_reuse:1e-3", "5k:direct_reuse:1e-2", "5k:cg_amg:1e-2", "5k:cg_amg:1e-2:0.1",
                 "10k:cg_amg:1e-2", "20k:cg_amg:1e-2", "75k:cg_amg:1e-2"]
# backend tokens of --cases → solve.solver settings
BACKENDS = {
    "direct": {"backend": "direct", "reuse_factorization": False},           # PARDISO if MKL is installed; factorise every time
    "direct_reuse": {"backend": "direct", "reuse_factorization": True},      # kept factors precondition CG
    "superlu": {"backend": "direct", "engine": "superlu"},
    "cg_amg": {"backend": "cg_amg"},                                          # hypre BoomerAMG where installed
    "mixed_amg": {"backend": "mixed_amg"},
    "auto": {"backend": "auto"},                                              # the shipped default
    "auto_1p": {"backend": "auto", "amg_processes": 1},                       # BoomerAMG on this process only
    "auto_2p": {"backend": "auto", "amg_processes": 2},                       # BoomerAMG on two processes
    "auto_rebuild100": {"backend": "auto", "rebuild_cost": 100},             # the rebuild rule before mixed_amg's 40
    "mixed_amg_pyamg": {"backend": "mixed_amg", "amg": "pyamg"},
    "auto_pyamg": {"backend": "auto", "amg": "pyamg"},
}


def leg_labels(scale: float, n_slices: int, spacing=SPACING, seed: int = 0):
    """SYNTHETIC leg label volume (0 background, 1 muscle, 2 connective tissue, 3 fat, 4 bone) and fibres,
    sampled at the centres of voxels of ``spacing`` (cm)."""
    from pixmuscle.synth import phantom as ph
    from pixmuscle.synth.leg import LegAnatomy

    h = np.asarray(spacing)
    rng = np.random.default_rng(seed)
    anat = LegAnatomy((0.0, 0.0), (0.0, (n_slices - 1) * h[2]), rng, leg_scale=scale, fat_cm=0.6 * scale)
    lo, hi = anat.bounding_box()
    nx, ny = (np.ceil((hi - lo) / h[:2]).astype(int) + 3)
    i, j, k = np.meshgrid(np.arange(nx), np.arange(ny), np.arange(n_slices), indexing="ij")
    pts = np.column_stack([lo[0] - h[0] + i.ravel() * h[0], lo[1] - h[1] + j.ravel() * h[1], k.ravel() * h[2]])
    s = anat(pts, want_fiber=True)
    code = np.zeros(len(pts), np.int16)
    code[s.cls == ph.MUSCLE] = 1
    code[(s.cls == ph.CT) | (s.cls == ph.SKIN)] = 2
    code[s.cls == ph.FAT] = 3
    code[(s.cls == ph.CORTEX) | (s.cls == ph.MARROW)] = 4
    fib = np.where(code[:, None] == 1, s.fiber, 0.0)
    return code.reshape(nx, ny, n_slices), fib.reshape(nx, ny, n_slices, 3), h


def leg_case(size: str, penalty: float | None, refine=(1, 1, 1), **solve_keys):
    """(model, SolveConfig) of the SYNTHETIC leg at ``size`` with the Example 2 boundary conditions
    (both ends fixed, bone surfaces fixed in-plane); ``solve_keys`` add to the ``solve`` section.
    ``refine`` (rx, ry, rz) splits every voxel of the leg into rx × ry × rz voxels of the same
    tissue and fibre (the same voxel domain, ``rx · ry · rz`` times the nodes)."""
    from pixmuscle.config import parse_section
    from pixmuscle.mechanics.config import SolveConfig
    from pixmuscle.model.build import model_from_labels

    labels, fibers, h = leg_labels(*SIZES[size])
    for axis, r in enumerate(refine):
        labels, fibers = np.repeat(labels, r, axis=axis), np.repeat(fibers, r, axis=axis)
    h = np.asarray(h, float) / np.asarray(refine)
    model = model_from_labels(labels, h, fibers=fibers, fiber_fallback="muscle_mean")
    sec = {"boundary_conditions": [{"nodes": "z_min", "fix": ["x", "y", "z"]}, {"nodes": "z_max", "fix": ["x", "y", "z"]},
                                   {"nodes": "bone_surface", "fix": ["x", "y"]}], **solve_keys}
    if penalty is not None:
        sec["penalty"] = {"factor": penalty}
    return model, parse_section(SolveConfig, sec, "solve")


def newton_tolerances(rtol: float | None, eta_max: float | None = None) -> dict:
    """``solve.newton`` keys for a Newton residual tolerance ``rtol`` (None: the defaults, 1e-8 and
    1e-14; the energy tolerance keeps the default ratio, 100 · rtol²) and the cap ``eta_max`` of
    the linear tolerance (None: default 1e-2)."""
    out = {} if rtol is None else {"residual_tol": rtol, "energy_tol": 100.0 * rtol**2}
    if eta_max is not None:
        out["forcing_max"] = eta_max
    return {"newton": out} if out else {}


def parse_case(spec: str) -> tuple[str, str, float | None, float | None]:
    """``SIZE:BACKEND[:NEWTON_TOL[:ETA_MAX]]`` → (size, backend, Newton residual tolerance, largest
    linear tolerance η_max); None where not given (the defaults)."""
    parts = spec.split(":")
    if not 2 <= len(parts) <= 4 or parts[0] not in SIZES or parts[1] not in BACKENDS:
        raise ValueError(f"case {spec!r}: expected SIZE:BACKEND[:NEWTON_TOL[:ETA_MAX]] with SIZE in {', '.join(SIZES)} "
                         f"and BACKEND in {', '.join(BACKENDS)}")
    nums = [float(x) for x in parts[2:]] + [None, None]
    return parts[0], parts[1], nums[0], nums[1]


def case_label(backend: str, newton_tol: float | None, eta_max: float | None = None) -> str:
    """Backend name in the tables, with the Newton tolerance and η_max where not the defaults."""
    out = backend if newton_tol is None else f"{backend}, Newton {newton_tol:g}"
    return out if eta_max is None else f"{out}, η_max {eta_max:g}"


def final_residuals(newton: dict) -> np.ndarray:
    """Relative residual of the converged state of each load step (the last Newton row of each step)."""
    step = np.asarray(newton["step"])
    last = np.flatnonzero(np.r_[step[1:] != step[:-1], True])
    return np.asarray(newton["relative_residual"])[last]


def run_case(size: str, backend: str, steps: int, alpha_to: float, penalty: float | None,
             newton_tol: float | None = None, eta_max: float | None = None, checkpoint: pathlib.Path | None = None) -> dict:
    """One sweep; with ``checkpoint`` (a file stem) its converged load steps are written as it goes
    (``STEM.checkpoint``, :mod:`pixmuscle.io.checkpoint`, and ``STEM.segments.json``: the wall time,
    steps and peak memory of each run so far), so that the same call after a kill
    resumes from the last converged step. The record then sums the runs (``segments``)."""
    from pixmuscle.mechanics.solve import solve

    model, cfg = leg_case(size, penalty, steps=steps, activation={"from": 0.0, "to": alpha_to}, solver=BACKENDS[backend],
                          **newton_tolerances(newton_tol, eta_max))
    t1 = time.perf_counter()
    resume, earlier, save = (None, [], None) if checkpoint is None else _sweep_checkpoint(checkpoint, model, cfg, t1)
    res = solve(model, cfg, resume=resume, on_checkpoint=save)
    wall = time.perf_counter() - t1
    info = res.info
    n_it = int(np.sum(res.iterations))
    n_run = int(np.sum(res.iterations[len(resume or ()):]))  # Newton iterations of this run
    tissue = np.bincount(model.tissue, minlength=4)
    lin = info["linear_iterations"]  # of this run only (a resumed sweep's earlier runs are not counted)
    if checkpoint is not None:
        for path in _checkpoint_files(checkpoint):
            path.unlink(missing_ok=True)
    wall += sum(seg["wall_s"] for seg in earlier)
    return {
        "size": size, "backend": backend, "nodes": model.n_nodes, "dofs": 3 * model.n_nodes,
        "tissue_nodes": {"muscle": int(tissue[1]), "connective_tissue": int(tissue[2]), "fat": int(tissue[3])},
        "spacing_cm": [float(x) for x in model.spacing], "steps": steps, "alpha_to": alpha_to, "status": res.status,
        "penalty_factor": cfg.penalty.factor, "beta_N_per_cm3": info["beta"],
        "newton_residual_tol": cfg.newton.residual_tol, "newton_energy_tol": cfg.newton.energy_tol,
        "forcing_max": cfg.newton.forcing_max,
        "build_s": round(info["build_s"], 2),
        "pattern_s": round(info.get("pattern_s", 0.0), 2),
        "assembly_s_per_iteration": round(info["assembly_s"] / max(info["n_assembly"], 1), 3),
        "n_assembly": int(info["n_assembly"]),
        "linear_setup_s_total": round(info["linear_setup_s"], 2),
        "linear_s_per_iteration": round((info["linear_setup_s"] + info["linear_solve_s"]) / max(n_run, 1), 3),
        "cg_iterations_total": int(np.sum(lin)) if backend != "direct" else None,
        "cg_iterations_per_newton": round(float(np.mean(lin)), 1) if backend != "direct" else None,
        "cg_s_per_iteration": round(info["linear_solve_s"] / max(np.sum(lin), 1), 4) if backend == "cg_amg" else None,
        "preconditioner_builds": info.get("preconditioner_builds"),
        "preconditioner_build_s": info.get("preconditioner_build_s"),
        "amg": info.get("amg"),
        "amg_processes": info.get("amg_processes"),
        "boomeramg": boomeramg_settings() if info.get("amg") == "hypre" else None,
        "factorizations": info.get("factorizations"),
        "direct_engine": info.get("linear_engine"),
        "factor_nnz_per_row": round(info["factor_nnz"] / (3 * model.n_nodes), 1) if info.get("factor_nnz") else None,
        "krylov_iterations_total": info.get("krylov_iterations"),
        "krylov_iterations_per_system": [int(i) for i in lin] if backend != "direct" else None,
        "nnz_per_row": info.get("nnz_per_row"),
        "preconditioner_nnz_per_row": info.get("preconditioner_nnz_per_row"),
        "newton_iterations_per_step": res.iterations.tolist(), "newton_iterations_total": n_it,
        "cutbacks": int(np.sum(res.cutbacks)),
        "final_relative_residual_max": float(np.max(final_residuals(res.newton))) if len(res.newton["step"]) else None,
        "material_s_per_evaluation": round(info["material_s"] / max(info["n_evaluate"], 1), 3),
        "sweep_s": round(wall, 1),
        # every setting shipped: backend auto, default Newton tolerances and penalty
        "defaults": (backend == "auto" and newton_tol is None and eta_max is None and penalty is None
                     and steps == 10 and alpha_to == 0.95),
        "force_z_max_N": [float(f) for f in res.force("z_max")],
        "peak_rss_GB": max([peak_rss_gb()] + [seg["peak_rss_GB"] for seg in earlier]),
        # one process (with its BoomerAMG workers): the whole tree is the largest rank's own tree
        "ranks": 1,
        "peak_rss_GB_per_rank_max": max([peak_rss_gb()] + [seg["peak_rss_GB"] for seg in earlier]),
        # a resumed sweep: each run's wall time (its own build and set-up included), steps and peak memory
        # (the iteration counts above are then the last run's only)
        "segments": earlier
                    + [{"wall_s": round(time.perf_counter() - t1, 1), "steps_done": len(res.iterations) - 1,
                        "peak_rss_GB": peak_rss_gb()}] if earlier else None,
    }


def peak_rss_gb() -> float:
    """Peak resident memory of this process tree, GB, BoomerAMG workers included (:func:`_record.peak_rss_GB`)."""
    return peak_rss_GB()


def _checkpoint_files(stem: pathlib.Path) -> tuple[pathlib.Path, pathlib.Path]:
    """The checkpoint and the runs' log of a sweep checkpointed at ``stem``."""
    return stem.parent / (stem.name + ".checkpoint"), stem.parent / (stem.name + ".segments.json")


def _sweep_checkpoint(stem: pathlib.Path, model, cfg, t_start: float):
    """(resume records or None, earlier runs, on_checkpoint) of a sweep checkpointed at ``stem``."""
    import hashlib

    from pixmuscle import __version__
    from pixmuscle.io.checkpoint import load_checkpoint, save_checkpoint
    from pixmuscle.store import config_hash, write_bytes_atomic

    key = hashlib.sha256(json.dumps({"solve": config_hash(cfg), "nodes": model.n_nodes, "version": __version__},
                                    sort_keys=True).encode()).hexdigest()
    ckpt, segs = _checkpoint_files(stem)
    resume, earlier = None, []
    if ckpt.exists() and segs.exists():
        got = load_checkpoint(ckpt)
        seg = json.loads(segs.read_text())
        if got.key == key and seg["key"] == key and got.records:
            resume, earlier = got.records, seg["segments"]

    def save(records):
        save_checkpoint(ckpt, records, key=key, n_steps=cfg.steps)
        now = {"wall_s": round(time.perf_counter() - t_start, 1), "steps_done": records[-1].step, "peak_rss_GB": peak_rss_gb()}
        write_bytes_atomic(segs, json.dumps({"key": key, "segments": earlier + [now]}).encode())

    return resume, earlier, save


def probe(size: str, penalty: float | None) -> dict:
    """One Newton system of the first load step at ``size`` without the sweep: build, preconditioner
    set-up, matrix-free product, V-cycle, and CG to the loosest (1e-2) and a tight (1e-8) tolerance.

    For sizes whose whole sweep does not fit the session; the sweep time is then estimated from
    the measured per-iteration costs (docs/performance.md says how).
    """
    from pixmuscle.mechanics.linsolve import make_solver, pcg
    from pixmuscle.mechanics.solve import build_system

    out = {"size": size, "probe": True}
    t = time.perf_counter()
    model, cfg = leg_case(size, penalty)
    out.update(nodes=model.n_nodes, dofs=3 * model.n_nodes, model_s=round(time.perf_counter() - t, 1))
    t = time.perf_counter()
    system, info = build_system(model, cfg)
    out["build_s"] = round(time.perf_counter() - t, 1)
    state = system.evaluate(np.zeros((model.n_nodes, 3)), 0.1, 0.095)
    t = time.perf_counter()
    system.evaluate(np.zeros((model.n_nodes, 3)), 0.1, 0.095)
    out["residual_evaluation_s"] = round(time.perf_counter() - t, 2)
    solver = make_solver("cg_amg", model.X, ijk=model.ijk)
    t = time.perf_counter()
    solver.prepare(system, state)
    out["preconditioner_setup_s"] = round(time.perf_counter() - t, 1)
    out.update(amg_processes=solver.amg_processes, levels=solver.info["levels"], operator_complexity=round(solver.info["operator_complexity"], 2),
               preconditioner_nnz_per_row=round(solver.info["preconditioner_nnz_per_row"], 1),
               pattern_s=round(system.timings.get("pattern_s", 0.0), 1))
    v = np.random.default_rng(0).standard_normal(3 * model.n_nodes)
    A, M = solver._A, solver._M
    for name, f in (("matvec_s", lambda: A @ v), ("vcycle_s", lambda: M @ v)):
        f()
        t = time.perf_counter()
        for _ in range(3):
            f()
        out[name] = round((time.perf_counter() - t) / 3, 3)
    r = state.r.ravel()
    for tol in (1e-2, 1e-8):
        t = time.perf_counter()
        _, its, status = pcg(A, r, M, tol, 3000)
        out[f"cg_{tol:g}"] = {"iterations": its, "status": status, "s": round(time.perf_counter() - t, 1)}
    out["peak_rss_GB"] = peak_rss_gb()
    return out


#: the tissues' bulk moduli of Tables 1–2 (N/cm²), scaled by --conditioning
BULK = {"muscle": 5000.0, "connective_tissue": 50000.0, "fat": 5000.0}
#: the iterative backend that ``solve.solver.backend: auto`` takes above its direct limit
AUTO_ITERATIVE = "mixed_amg"


#: --conditioning variants, VOLUMETRIC[:PATCH]:BACKEND (the first two are the earlier records' rows)
CONDITIONING_VARIANTS = ("nodal:cg_amg", "projected:1,1,3:cg_amg", "projected:2,2,3:cg_amg", "projected:2,2,3:mixed_amg",
                         "projected:2,2,3:mixed_amg:patch")


def parse_variant(spec: str) -> tuple[str, tuple[int, int, int] | None, str, str]:
    """``nodal:BACKEND`` or ``projected:PX,PY,PZ:BACKEND[:HELD]`` → (method, patch, backend, held).

    HELD is ``volumetric.held`` (``own``, the default, or ``patch``).
    """
    parts = spec.split(":")
    if parts[0] == "nodal" and len(parts) == 2:
        return "nodal", None, parts[1], "own"
    if parts[0] == "projected" and len(parts) in (3, 4) and (len(parts) == 3 or parts[3] in ("own", "patch")):
        return "projected", tuple(int(x) for x in parts[1].split(",")), parts[2], parts[3] if len(parts) == 4 else "own"
    raise ValueError(f"variant {spec!r}: expected nodal:BACKEND or projected:PX,PY,PZ:BACKEND[:own|patch]")


def boomeramg_settings() -> dict:
    """The BoomerAMG options of this code (``pc_hypre_boomeramg_`` left out), for a record's provenance."""
    from pixmuscle.mechanics.linsolve.multigrid import BOOMERAMG_OPTIONS

    return {k.removeprefix("pc_hypre_boomeramg_"): v for k, v in BOOMERAMG_OPTIONS.items()}


def conditioning(size: str, penalty: float | None, scales=(0.1, 1.0, 10.0), rtol: float = 1e-6,
                 variants=CONDITIONING_VARIANTS, on_row=None, previous=()) -> dict:
    """Krylov iterations of one Newton system (first load step, α = 0.095) against near-incompressibility.

    Every tissue's bulk modulus K is multiplied by each of ``scales`` (K/μ ≈ 95, 950, 9,500 for the
    paper's constants), for each variant (volumetric energy, patch, backend); the backend solves
    the system to ``rtol``. A formulation and solver whose iterations stay flat as K/μ grows are
    robust where the cost of the nearly incompressible tissues comes from. ``krylov_iterations``
    stop on the condensed residual; for ``mixed_amg`` the row also has ``krylov_iterations_mixed``,
    the same system solved in mixed form and stopped on the mixed residual, which is the update
    Newton takes at the defaults (``solve.newton.pressure_update: mixed``). Rows of the shipped
    defaults (:class:`~pixmuscle.mechanics.config.VolumetricConfig`, the backend ``auto`` picks
    above its direct limit) carry ``"default": true``. ``on_row(record)`` is called with the
    record so far after every row (a long run keeps what it measured); ``previous`` rows (an
    earlier record's, e.g. at another penalty number) come first in it.

    The penalty number β of the end and bone constraints is the default one of the paper's tissues
    (K × 1) in every row: the default β grows with K, and a stiffer penalty slows every iterative
    solver whatever the tissue, which is not what this measures.
    """
    from pixmuscle.errors import SolverError
    from pixmuscle.mechanics.config import SolveConfig
    from pixmuscle.mechanics.linsolve import make_solver
    from pixmuscle.mechanics.solve import build_system

    shipped = SolveConfig()
    rows, previous = [], list(previous)
    beta = None
    for spec in variants:
        method, patch, backend, held = parse_variant(spec)
        for scale in scales:
            mats = {k: {"K": v * scale} for k, v in BULK.items()}
            vol = {"method": method} if patch is None else {"method": method, "patch": list(patch), "held": held}
            model, cfg = leg_case(size, penalty, materials=mats, volumetric=vol)
            if beta is None:  # β of the tissues' own K (the first system built at scale 1)
                beta = build_system(*leg_case(size, penalty, volumetric=vol))[1]["beta"]
            cfg = dataclasses.replace(cfg, penalty=dataclasses.replace(cfg.penalty, beta=beta))
            system, _ = build_system(model, cfg)
            state = system.evaluate(np.zeros((model.n_nodes, 3)), 0.1, 0.095)
            solver = make_solver(backend, model.X, ijk=model.ijk, rtol=rtol, maxiter=5000)
            t = time.perf_counter()
            solver.prepare(system, state)
            setup = time.perf_counter() - t
            t = time.perf_counter()
            try:
                solver.solve(state.r.ravel(), rtol=rtol)
                status = "converged"
            except SolverError as exc:
                status = str(exc).split(":")[1].strip()[:60]
            its = int(solver.info["iterations"])
            mixed = None  # the update Newton takes at the defaults: the mixed system, stopping on its residual
            if hasattr(solver, "solve_mixed") and getattr(solver, "_mixed", None) is not None:
                t = time.perf_counter()
                try:
                    solver.solve_mixed(state.r.ravel(), np.zeros(system.volumetric.n_patches), rtol=rtol)
                    mixed = {"krylov_iterations_mixed": int(solver.info["iterations"]),
                             "mixed_solve_s": round(time.perf_counter() - t, 1)}
                except SolverError as exc:
                    mixed = {"krylov_iterations_mixed": None, "mixed_status": str(exc).split(":")[1].strip()[:60]}
            default = (method == shipped.volumetric.method and backend == AUTO_ITERATIVE and held == shipped.volumetric.held
                       and (patch is None or list(patch) == list(shipped.volumetric.patch)))
            rows.append({"volumetric": method, "patch": None if patch is None else list(patch), "held": held,
                         "backend": backend, "penalty_beta": beta,
                         "bulk_scale": scale, "K_over_mu_muscle": round(BULK["muscle"] * scale / 5.26),
                         "region_solves": bool(getattr(solver, "region_solves", False) and solver.info.get("region_nodes")),
                         "schur": getattr(solver, "schur", None), "restart": getattr(solver, "restart", None),
                         "probe_spacing": getattr(solver, "probe_spacing", None),
                         "amg_processes": getattr(solver, "amg_processes", None),
                         "boomeramg": boomeramg_settings() if getattr(solver, "amg", None) == "hypre" else None,
                         "krylov_iterations": its, "status": status, "solve_s": round(time.perf_counter() - t, 1),
                         "setup_s": round(setup, 1), **(mixed or {}), "default": bool(default)})
            print(json.dumps(rows[-1]), flush=True)
            same = ("volumetric", "patch", "held", "backend", "bulk_scale")
            for r in previous:  # an earlier row of a case measured again, or of a bulk scale with a new default row,
                # is no longer the shipped default
                if any(all(r.get(k) == n[k] for k in same) or (n["default"] and r.get("bulk_scale") == n["bulk_scale"])
                       for n in rows):
                    r["default"] = False
            record = {"size": size, "nodes": model.n_nodes, "rtol": rtol, "penalty_beta": beta, "rows": previous + rows,
                      "load_avg": os.getloadavg()[0],
                      "peak_rss_GB": peak_rss_gb()}
            if on_row is not None:
                on_row(record)
    return record


def infsup(size: str, penalty: float | None, patch=(1, 1, 3), held: str = "pressure", dense: bool | None = None,
           thresholds=(1e-3, 1e-2, 5e-2)) -> dict:
    """Is the patch pressure of the projected energy stable? The spectrum of its Schur complement.

    The projected energy is the condensed form of a mixed problem with one pressure per patch,
    [K_d Gᵀ; G −D⁻¹], where K_d is the tangent without the patch terms, G (N_p × 3N) the patch
    dilatation rates g_pᵀ and D = diag(V_p K̄_p). A solver whose iterations do not grow with K/μ
    (a Krylov method with multigrid on K_d and a diagonal Schur complement) needs
    S_G = G K_d⁻¹ Gᵀ to be spectrally equivalent to the pressure mass scaled by 1/μ,
    M = diag(1/(μ_p V_p)) — the discrete inf-sup condition. Generalised eigenvalues of (S_G, M)
    near 0 are pressure modes that the displacement field can hardly produce; they make the
    iterations grow with K. Computed at F = I, α = 0.095 for patches of ``patch`` voxels.

    ``held="pressure"``: the single-node patches of held nodes (``volumetric.held: own``) are
    pressure unknowns too; ``held="displacement"``: their terms stay in K_d; ``held="patch"``:
    ``volumetric.held: patch`` (the default), held nodes stay in their ordinary patches.

    Small models (``dense``, default up to 2,000 nodes) get the whole spectrum from dense
    matrices. Any size gets the counts of eigenvalues below each threshold σ without computing
    one: by Sylvester's law of inertia and the Haynsworth formula, the symmetric matrix
    [K_d Gᵀ; G σM] has In(K_d) + In(σM − S_G) as inertia, so the number of its positive pivots
    in an LDLᵀ factorisation (PARDISO), minus those of K_d, is the number of eigenvalues below σ.
    """
    import scipy.linalg as sl
    import scipy.sparse as sp

    from pixmuscle.mechanics.pressure import PatchDivergence
    from pixmuscle.mechanics.solve import build_system

    model, cfg = leg_case(size, penalty, volumetric={"method": "projected", "patch": list(patch),
                                                     "held": "patch" if held == "patch" else "own"})
    system, _ = build_system(model, cfg)
    state = system.evaluate(np.zeros((model.n_nodes, 3)), 0.1, 0.095)
    n, vol = model.n_nodes, system.volumetric
    press = np.ones(vol.n_patches, bool) if held in ("pressure", "patch") else ~vol.held
    if held in ("pressure", "patch"):  # K_d without any patch term
        asm = system.assembler(None, patches=False)
        data = system.constant_stiffness(asm)
        asm.fill(system._g, state.A, system.scni.volume, out=data)
        Kd = asm.matrix(data).tocsr()
    else:
        Kd = system.stiffness(state, pressure_free=True).tocsr()
    main = system.tangent_operator(state).main
    Q = vol.Q[np.flatnonzero(press)]
    G = PatchDivergence(main.B, main.BT, state.vol.a, Q).sparse()
    mass = 1.0 / ((Q @ system.shear0) * vol.vp[press])
    out = {"size": size, "nodes": n, "patch": list(patch), "held_single_patches_in": held,
           "patches": vol.n_patches, "pressure_unknowns": int(press.sum()),
           "held_single_patches": int(vol.held.sum())}
    if dense if dense is not None else n <= 2000:
        Kdd = Kd.toarray()
        Kdd = 0.5 * (Kdd + Kdd.T)
        Gd = G.toarray()
        w, V = sl.eigh(Gd @ np.linalg.solve(Kdd, Gd.T), np.diag(mass))
        single = vol.held[press]
        where = np.abs(V).argmax(axis=0)  # the patch each mode lives on most
        small = w < 1e-2
        out.update({"eig_min": float(w[0]), "eig_max": float(w[-1]),
                    "eig_percentiles_1_5_50_95_99": [float(x) for x in np.percentile(w, [1, 5, 50, 95, 99])],
                    "dense_modes_below": {f"{t:g}": int(np.sum(w < t)) for t in thresholds},
                    "modes_below_0.01_on_single_node_patches": int(np.sum(small & single[where]))})
    counts = {}
    t0 = time.perf_counter()
    Kup = sp.triu(Kd).tocsr()
    base = _positive_pivots(Kup)
    out["Kd_positive_pivots"], out["Kd_size"] = base, 3 * n
    for t in thresholds:
        M = sp.bmat([[Kup, G.T], [None, sp.diags(t * mass)]], format="csr")
        counts[f"{t:g}"] = _positive_pivots(M) - base
    out["modes_below"] = counts
    out["modes_below_0.01"] = counts.get("0.01")
    out["inertia_s"] = round(time.perf_counter() - t0, 1)
    out["peak_rss_GB"] = peak_rss_gb()
    return out


def _positive_pivots(upper) -> int:
    """Positive pivots of the LDLᵀ factorisation (PARDISO) of a symmetric matrix given by its upper triangle."""
    from types import SimpleNamespace

    from pixmuscle.mechanics.pardiso import PardisoLDLT

    upper = upper.tocsr()
    upper.sort_indices()
    pat = SimpleNamespace(n=upper.shape[0], indptr=upper.indptr.astype(np.int32), indices=upper.indices.astype(np.int32))
    f = PardisoLDLT(pat)
    f.factorize(upper.data.astype(np.float64))
    pos, neg = f.info["inertia"]
    f.free()
    return int(pos)


def multigrid(size: str, penalty: float | None, amg: str) -> dict:
    """The first Newton system of load step 1 (d = 0, α = 0.095) at ``size`` solved by ``mixed_amg``
    with the multigrid ``amg`` (pyamg or hypre): preconditioner set-up (stand-in fill, AMG, region
    solves, Schur probe), one application of the displacement block's preconditioner (V-cycle and
    region solves, and each apart), the matrix-free products (tangent, mixed operator), the block
    preconditioner, and FGMRES to 10⁻⁶ (iterations, seconds) on the condensed and on the mixed
    residual; ``threads`` is the thread count of the sparse products."""
    from pixmuscle.mechanics.linsolve import make_solver
    from pixmuscle.mechanics.solve import build_system
    from pixmuscle.mechanics.threaded import thread_count

    model, cfg = leg_case(size, penalty)
    system, _ = build_system(model, cfg)
    state = system.evaluate(np.zeros((model.n_nodes, 3)), 0.1, 0.095)
    solver = make_solver("mixed_amg", model.X, ijk=model.ijk, amg=amg)
    out = {"size": size, "amg": amg, "nodes": model.n_nodes, "amg_processes": solver.amg_processes}
    if amg == "hypre":
        from pixmuscle.mechanics.linsolve.multigrid import BOOMERAMG_OPTIONS

        out["relax"] = {k.rsplit("_", 1)[-1]: v for k, v in BOOMERAMG_OPTIONS.items() if "relax_type" in k}
    t = time.perf_counter()
    solver.prepare(system, state)
    out["setup_s"] = round(time.perf_counter() - t, 1)
    rng = np.random.default_rng(0)
    v = rng.standard_normal(3 * model.n_nodes)
    mixed, block = solver._mixed
    z = rng.standard_normal(mixed.n + mixed.c22.size)
    parts = [("displacement_preconditioner_s", lambda: solver._M @ v), ("matvec_s", lambda: solver._A @ v),
             ("mixed_product_s", lambda: mixed @ z), ("mixed_preconditioner_s", lambda: block @ z)]
    if hasattr(solver._M, "regions"):  # the V-cycle and the region solves after it, apart
        parts += [("v_cycle_s", lambda: solver._M.M @ v), ("region_solves_s", lambda: solver._M.regions.correct(v, v))]
    for name, f in parts:
        f()
        t = time.perf_counter()
        for _ in range(3):
            f()
        out[name] = round((time.perf_counter() - t) / 3, 4)
    t = time.perf_counter()
    solver.solve(state.r.ravel(), rtol=1e-6)
    out["solve_s"] = round(time.perf_counter() - t, 1)
    out.update(fgmres_iterations=solver.info["iterations"], s_per_iteration=round(out["solve_s"] / solver.info["iterations"], 3))
    t = time.perf_counter()  # the update of Newton on the mixed form (the default), stopping on the mixed residual
    solver.solve_mixed(state.r.ravel(), np.zeros(system.volumetric.n_patches), rtol=1e-6)
    out["mixed_solve_s"] = round(time.perf_counter() - t, 1)
    out.update(mixed_fgmres_iterations=solver.info["iterations"],
               mixed_s_per_iteration=round(out["mixed_solve_s"] / solver.info["iterations"], 3), threads=thread_count(),
               peak_rss_GB=peak_rss_gb())
    return out


def probe_direct(size: str, penalty: float | None) -> dict:
    """PARDISO's symbolic analysis of the full tangent at ``size``: predicted factor size and
    flops of one factorisation, without factorising (for sizes where that would not fit)."""
    from pixmuscle.mechanics.pardiso import PardisoLDLT, SymmetricPattern
    from pixmuscle.mechanics.solve import build_system

    out = {"size": size, "probe": "direct"}
    model, cfg = leg_case(size, penalty)
    system, _ = build_system(model, cfg)
    state = system.evaluate(np.zeros((model.n_nodes, 3)), 0.1, 0.095)
    t = time.perf_counter()
    K = system.stiffness(state)
    out.update(nodes=model.n_nodes, dofs=3 * model.n_nodes, assembly_s=round(time.perf_counter() - t, 1),
               nnz_per_row=round(K.nnz / K.shape[0], 1))
    t = time.perf_counter()
    pat = SymmetricPattern(K)
    del K
    out["upper_pattern_s"] = round(time.perf_counter() - t, 1)
    f = PardisoLDLT(pat)
    out.update(analysis_s=round(f.info["analysis_s"], 1), factor_nnz=f.info["factor_nnz"],
               factor_GB=round(8 * f.info["factor_nnz"] / 1e9, 2), factor_gflop=float(f.iparm[18]) / 1e3,
               peak_rss_GB=peak_rss_gb())
    return out


def start_inertia(size: str, penalty: float | None, alphas=(0.0, 0.095)) -> dict:
    """Negative eigenvalues of the condensed tangent at the start of the first load step (d = 0,
    load factor 0.1) for each activation in ``alphas``: the inertia of PARDISO's LDLᵀ factors
    (Sylvester's law). The deviatoric active fibre stress of α > 0, before the pressure has built
    up, compresses the tissue across the fibres and can make the tangent indefinite along soft
    lateral modes (the clamped block of docs/performance.md, "Newton convergence"), which an AMG
    preconditioner built from a positive stand-in would not see. Whether it does on the leg is
    what this counts."""
    import scipy.sparse as sp

    from pixmuscle.mechanics.pardiso import PardisoLDLT, SymmetricPattern
    from pixmuscle.mechanics.solve import build_system

    model, cfg = leg_case(size, penalty)
    system, _ = build_system(model, cfg)
    out = {"size": size, "nodes": model.n_nodes, "dofs": 3 * model.n_nodes, "rows": []}
    pat = factor = None
    for alpha in alphas:
        state = system.evaluate(np.zeros((model.n_nodes, 3)), 0.1, alpha)
        K = sp.bsr_matrix(system.stiffness(state))
        K.sort_indices()
        t = time.perf_counter()
        if factor is None:
            pat = SymmetricPattern(K)
            factor = PardisoLDLT(pat)
        factor.factorize(pat.values(K))
        pos, neg = factor.info["inertia"]
        out["rows"].append({"alpha": alpha, "positive": pos, "negative": neg,
                            "perturbed_pivots": factor.info["perturbed_pivots"], "factor_s": round(time.perf_counter() - t, 1)})
        print(json.dumps(out["rows"][-1]), flush=True)
    out.update(load_avg=os.getloadavg()[0], peak_rss_GB=peak_rss_gb())
    return out


EXPONENT_KEYS = ("build_s", "assembly_s_per_iteration", "linear_s_per_iteration", "cg_iterations_per_newton",
                 "newton_iterations_total", "sweep_s", "peak_rss_GB")


def label(c: dict) -> str:
    return c.get("label", c.get("backend", "?"))


def growth_exponents(cases: list[dict]) -> dict:
    """Least-squares slope of log(quantity) against log(nodes) per backend (needs ≥ 2 sizes)."""
    out = {}
    for be in sorted({label(c) for c in cases}):
        cs = [c for c in cases if label(c) == be and c.get("status") == "complete"]
        if len({c["nodes"] for c in cs}) < 2:
            continue
        n = np.log([c["nodes"] for c in cs])
        out[be] = {}
        for k in EXPONENT_KEYS:
            v = [c.get(k) for c in cs]
            if all(isinstance(x, (int, float)) and x > 0 for x in v):
                out[be][k] = round(float(np.polyfit(n, np.log(v), 1)[0]), 2)
    return out


def force_deviation(case: dict, cases: list[dict]) -> float | None:
    """Largest difference of the force curve F_z(z_max) of ``case`` from that of the direct solver
    (``direct``, else ``direct_reuse``; default tolerances) on the same model, relative to the largest force; None when
    that reference was not run."""
    ref = sorted((c for c in cases if c.get("status") == "complete" and label(c) in ("direct", "direct_reuse")
                  and c["nodes"] == case["nodes"]), key=label)
    if not ref or case.get("status") != "complete":
        return None
    f, f0 = np.asarray(case["force_z_max_N"]), np.asarray(ref[0]["force_z_max_N"])
    if f.shape != f0.shape:
        return None
    return float(np.max(np.abs(f - f0)) / np.max(np.abs(f0)))


def dev_text(x: float | None) -> str:
    return "—" if x is None else f"{x:.1e}"


def write_tables(cases, command: str, meta: dict | None = None):
    """Write bench_solve.json and .md; ``meta`` (the last run's: machine, date, command) is made now unless
    given (``--tables`` keeps the record's)."""
    meta = meta or {"python": platform.python_version(), "machine": platform.machine(), "cpus": os.cpu_count(),
                    "platform": platform.platform(), "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                    "command": command}
    exps = growth_exponents(cases)
    (OUT / "bench_solve.json").write_text(json.dumps({"meta": meta, "cases": cases, "growth_exponents": exps}, indent=1))
    lines = ["# bench_solve: isometric activation sweep of the SYNTHETIC leg (paper Example 2 set-up)", "",
             f"{meta['date_utc']}, {meta['platform']}, Python {meta['python']}, {meta['cpus']} CPUs. "
             f"Command: `{meta['command']}`", "",
             "| nodes | backend | nnz/row (K / precond.) | build (s) | assembly / Newton it (s) | "
             "linear / Newton it (s) | factorisations (factor nnz/row) | CG its / Newton it | Newton its / step | cutbacks | "
             "sweep (s) | peak RSS (GB) | F_z(z_max) at α=0.95 (N) | max ΔF vs direct | status |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for c in sorted(cases, key=lambda c: (label(c), c.get("nodes", 0))):
        if "error" in c:
            lines.append(f"| {c.get('size')} | {label(c)} | | | | | | | | | | {c.get('peak_rss_GB', '')} | | | {c['error'][:60]} |")
            continue
        # rows merged from bench_scaling.py (whole sweeps through the CLI) carry fewer fields: "—"
        c = {k: "—" for k in ("nnz_per_row", "build_s", "assembly_s_per_iteration", "linear_s_per_iteration", "cutbacks")} | c
        pre = c.get("preconditioner_nnz_per_row")
        nnz = f"{c['nnz_per_row'] or '—'} / {round(pre) if pre else '—'}"
        fac = f"{c['factorizations']} ({c['factor_nnz_per_row']})" if c.get("factorizations") else "—"
        lines.append(f"| {c['nodes']} | {label(c)} | {nnz} | {c['build_s']} | "
                     f"{c['assembly_s_per_iteration']} | {c['linear_s_per_iteration']} | {fac} | {c.get('cg_iterations_per_newton') or '—'} | "
                     f"{c['newton_iterations_per_step'][1:]} | {c['cutbacks']} | {c['sweep_s']} | {c['peak_rss_GB']} | "
                     f"{c['force_z_max_N'][-1]:.6f} | {dev_text(force_deviation(c, cases))} | {c['status'][:30]} |")
    lines += ["", "Penalty factor: " + ", ".join(sorted({f"{c['penalty_factor']:g}" for c in cases if "error" not in c and "penalty_factor" in c}))
              + "; commands per case in bench_solve.json. max ΔF vs direct: largest difference of the force curve "
              "(all load steps) from the direct solver (`direct`, else `direct_reuse`, the default up to 15k nodes; Newton "
              "tolerance 1e-8) on the same model, "
              "relative to its largest force."]
    if exps:
        lines += ["", "Growth exponents (slope of log quantity against log nodes):", "",
                  "| backend | " + " | ".join(EXPONENT_KEYS) + " |", "|---|" + "---|" * len(EXPONENT_KEYS)]
        for be, e in exps.items():
            lines.append(f"| {be} | " + " | ".join(str(e.get(k, "—")) for k in EXPONENT_KEYS) + " |")
    (OUT / "bench_solve.md").write_text("\n".join(lines) + "\n")


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--cases", nargs="+", default=DEFAULT_CASES, help="SIZE:BACKEND, SIZE in " + ", ".join(SIZES))
    p.add_argument("--steps", type=int, default=10)
    p.add_argument("--alpha", type=float, default=0.95)
    p.add_argument("--penalty", type=float, default=None, help="penalty factor (default: the solver default)")
    p.add_argument("--append", action="store_true",
                   help="merge into the existing results file (cases measured again are replaced; --conditioning: rows are added)")
    p.add_argument("--tables", action="store_true",
                   help="only rewrite bench_solve.md (and the exponents in bench_solve.json) from bench_solve.json")
    p.add_argument("--one", default=None, help=argparse.SUPPRESS)  # internal: run one case, print JSON
    p.add_argument("--log", default=None, metavar="FILE",
                   help="append the solver's progress (load steps, Newton iterations) of each case to FILE")
    p.add_argument("--checkpoint", default=None, metavar="DIR",
                   help="write each sweep's converged load steps to DIR as it goes; the same command after a kill "
                        "resumes every unfinished case from its last converged step")
    p.add_argument("--probe", default=None, metavar="SIZE",
                   help="measure one Newton system at SIZE (no sweep); writes results/bench_solve_probe_SIZE.json")
    p.add_argument("--probe-direct", default=None, metavar="SIZE",
                   help="PARDISO's symbolic analysis of the full tangent at SIZE (predicted factor size and "
                        "flops); writes results/bench_solve_probe_direct_SIZE.json")
    p.add_argument("--inertia", default=None, metavar="SIZE",
                   help="negative eigenvalues of the tangent at the start of the first load step, α = 0 and 0.095 "
                        "(PARDISO inertia) → results/bench_solve_inertia_SIZE.json")
    p.add_argument("--conditioning", default=None, metavar="SIZE",
                   help="Krylov iterations of one Newton system at SIZE with the bulk moduli x0.1, x1, x10 for each "
                        "--variants; writes results/bench_solve_conditioning_SIZE.json")
    p.add_argument("--multigrid", default=None, metavar="SIZE",
                   help="the first Newton system at SIZE by mixed_amg with --amg: set-up, preconditioner and product "
                        "seconds, FGMRES iterations to 1e-6; adds a row to results/bench_solve_multigrid.json")
    p.add_argument("--amg", default="hypre", choices=("hypre", "pyamg"), help="--multigrid: the multigrid")
    p.add_argument("--infsup", default=None, metavar="SIZE",
                   help="small eigenvalues of the patch-pressure Schur complement against the 1/mu-scaled pressure "
                        "mass (--patch, --held; counts by inertia at any size, whole spectrum up to 2k nodes); "
                        "adds a row to results/bench_solve_infsup.json")
    p.add_argument("--patch", default="1,1,3", help="--infsup: patch size in voxels, PX,PY,PZ")
    p.add_argument("--held", default="pressure", choices=("pressure", "displacement", "patch"),
                   help="--infsup: the single-node patches of held nodes (volumetric.held: own) are pressure unknowns, "
                        "or stay in K_d; patch: volumetric.held: patch (no single-node patches)")
    p.add_argument("--thresholds", type=float, nargs="+", default=[1e-3, 1e-2, 5e-2],
                   help="--infsup: count the eigenvalues below each of these (one LDLᵀ factorisation each)")
    p.add_argument("--scales", type=float, nargs="+", default=[0.1, 1.0, 10.0],
                   help="--conditioning: factors on every tissue's bulk modulus (1: the tissues' own K/mu)")
    p.add_argument("--variants", nargs="+", default=list(CONDITIONING_VARIANTS),
                   help="--conditioning: VOLUMETRIC[:PATCH]:BACKEND[:HELD], e.g. projected:2,2,3:mixed_amg:patch (HELD: volumetric.held)")
    args = p.parse_args(argv)
    command = ".venv/bin/python benchmarks/bench_solve.py " + " ".join(argv)
    run = Run(defaults=False, command=command)
    if args.infsup:  # one row per (size, patch, held) in bench_solve_infsup.json
        patch = tuple(int(x) for x in args.patch.split(","))
        res = infsup(args.infsup, args.penalty, patch=patch, held=args.held, thresholds=tuple(args.thresholds))
        res.update(run.fields())
        path = OUT / "bench_solve_infsup.json"
        rows = json.loads(path.read_text())["rows"] if path.exists() else []
        rows = [r for r in rows if (r["size"], r["patch"], r["held_single_patches_in"]) != (res["size"], res["patch"], res["held_single_patches_in"])]
        path.write_text(json.dumps({"rows": rows + [res]}, indent=1))
        print(json.dumps(res, indent=1))
        return 0
    if args.multigrid:  # one row per (size, amg) in bench_solve_multigrid.json
        res = multigrid(args.multigrid, args.penalty, args.amg)
        res.update(run.fields())
        path = OUT / "bench_solve_multigrid.json"
        rows = json.loads(path.read_text())["rows"] if path.exists() else []
        rows = [r for r in rows if (r["size"], r["amg"]) != (res["size"], res["amg"])]
        path.write_text(json.dumps({"rows": rows + [res]}, indent=1))
        print(json.dumps(res, indent=1))
        return 0
    if args.conditioning:
        path = OUT / f"bench_solve_conditioning_{args.conditioning}.json"
        previous = []
        if args.append and path.exists():  # earlier rows stay, each with the command and load it ran under
            old = json.loads(path.read_text())
            previous = [{"command": old.get("command"), "load_avg": old.get("load_avg"),
                         "penalty_beta": old.get("penalty_beta"), **r} for r in old["rows"]]

        started = {"run": run}

        def keep(record):
            for r in record["rows"]:
                if "commit" not in r and "load_avg" not in r:  # a row of this run: its record fields, then
                    # the next row's load average starts here
                    r.update(started["run"].fields(defaults=r["default"] and r["bulk_scale"] == 1))
                    started["run"] = Run(command=command)
            path.write_text(json.dumps({**record, "command": command}, indent=1))

        conditioning(args.conditioning, args.penalty, scales=tuple(args.scales), variants=args.variants, on_row=keep,
                     previous=previous)
        return 0
    for size, fn, stem in ((args.probe_direct, probe_direct, "bench_solve_probe_direct"), (args.probe, probe, "bench_solve_probe"),
                           (args.inertia, start_inertia, "bench_solve_inertia")):
        if size:
            res = fn(size, args.penalty)
            res.update(run.fields())
            OUT.mkdir(parents=True, exist_ok=True)
            (OUT / f"{stem}_{size}.json").write_text(json.dumps(res, indent=1))
            print(json.dumps(res, indent=1))
            return 0
    if args.one:
        if args.log:
            import logging

            logging.basicConfig(filename=args.log, level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
            logging.getLogger("pixmuscle").setLevel(logging.DEBUG)  # every Newton iteration
        size, backend, tol, eta = parse_case(args.one)
        stem = None
        if args.checkpoint:
            pathlib.Path(args.checkpoint).mkdir(parents=True, exist_ok=True)
            stem = pathlib.Path(args.checkpoint) / (args.one.replace(":", "_") + f"_{args.steps}steps")
        res = run_case(size, backend, args.steps, args.alpha, args.penalty, tol, eta, checkpoint=stem)
        res.update(case=args.one, label=case_label(backend, tol, eta))
        print("RESULT " + json.dumps(res), flush=True)
        return 0
    if args.tables:
        old = json.loads((OUT / "bench_solve.json").read_text())
        write_tables(old["cases"], old["meta"]["command"], old["meta"])
        return 0
    OUT.mkdir(parents=True, exist_ok=True)
    cases = []
    if args.append and (OUT / "bench_solve.json").exists():  # keep earlier cases not measured again now
        again = {(case, args.steps) for case in args.cases}  # a case at another number of steps is another record
        cases = [c for c in json.loads((OUT / "bench_solve.json").read_text())["cases"]
                 if (c.get("case", f"{c.get('size')}:{c.get('backend')}"), c.get("steps", 10)) not in again]
    for case in args.cases:
        print(f"== {case}", flush=True)
        try:
            parse_case(case)
        except ValueError as exc:
            p.error(str(exc))
        cmd = [sys.executable, __file__, "--one", case, "--steps", str(args.steps), "--alpha", str(args.alpha)]
        if args.penalty is not None:
            cmd += ["--penalty", str(args.penalty)]
        if args.log:
            cmd += ["--log", args.log]
        if args.checkpoint:
            cmd += ["--checkpoint", args.checkpoint]
        t0 = time.perf_counter()
        # the command of this case alone; 1, 5 and 15 min load averages before and after it (a timing is a
        # record only on a quiet machine); its peak memory is the child's own (BoomerAMG workers included)
        case_run = Run(command=" ".join([".venv/bin/python benchmarks/bench_solve.py --cases", case]
                                        + [f"--{k} {v}" for k, v in (("steps", args.steps), ("alpha", args.alpha))]
                                        + ([f"--penalty {args.penalty}"] if args.penalty is not None else [])))
        proc = subprocess.run(cmd, capture_output=True, text=True)
        got = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
        if got:
            cases.append(json.loads(got[-1][7:]))
            cases[-1].update(case_run.fields(defaults=cases[-1]["defaults"], peak_rss_GB=cases[-1]["peak_rss_GB"]))
        else:
            size, backend, tol, eta = parse_case(case)
            cases.append({"size": size, "backend": backend, "case": case, "label": case_label(backend, tol, eta), "error": (proc.stderr.strip().splitlines() or ["?"])[-1],
                          "wall_s": round(time.perf_counter() - t0, 1), **case_run.fields(defaults=False)})
        print(json.dumps(cases[-1])[:600], flush=True)
        write_tables(cases, command)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

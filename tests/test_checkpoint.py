"""Checkpoint and resume of a solve: a real SIGKILL half-way, the same command again, the forces of
the uninterrupted run to 1e-10; a checkpoint of another configuration is never used."""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import time

import h5py
import numpy as np
import pytest
import yaml

from pixmuscle.config import parse_section
from pixmuscle.io.checkpoint import checkpoint_path, load_checkpoint, save_checkpoint
from pixmuscle.io.model import save_model
from pixmuscle.io.results import load_results
from pixmuscle.mechanics.config import SolveConfig
from pixmuscle.mechanics.newton import SavedState, StepRecord
from pixmuscle.mechanics.solve import solve
from pixmuscle.plan import Stage, is_up_to_date
from pixmuscle.stages.solve import run_solve
from pixmuscle.verify.mechanics import mask_model

STEPS = 6
BCS = [{"nodes": "z_min", "fix": ["x", "y", "z"]}, {"nodes": "z_max", "fix": ["x", "y", "z"]}]
ACTIVE = {"steps": STEPS, "activation": {"from": 0.0, "to": 0.6}, "boundary_conditions": BCS}
#: a displacement-driven ramp: the predictor extrapolates the last converged increment
PASSIVE = {"steps": 4, "activation": {"from": 0.2, "to": 0.2},
           "boundary_conditions": [BCS[0], {"nodes": "z_max", "fix": ["x", "y"], "displace": {"z": 0.15}}]}


def _model():
    return mask_model(np.ones((4, 4, 8), bool), (0.2, 0.2, 0.3), tissue=1)  # 128 muscle nodes


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    d = tmp_path_factory.mktemp("ckpt")
    save_model(d / "model.h5", _model())
    (d / "c.yaml").write_text(yaml.safe_dump({"solve": ACTIVE}))
    run_solve(d / "model.h5", ACTIVE, d / "full.h5", progress=False)
    return d


def _rel(a, b) -> float:
    return float(np.max(np.abs(np.asarray(a) - np.asarray(b))) / np.max(np.abs(np.asarray(b))))


def test_killed_solve_resumes_with_the_uninterrupted_forces(case):
    d = case
    out, ckpt = d / "r.h5", checkpoint_path(d / "r.h5")
    cmd = [sys.executable, "-m", "pixmuscle.cli", "solve", str(d / "model.h5"), "-c", str(d / "c.yaml"), "-o", str(out)]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        done = 0
        deadline = time.monotonic() + 120
        while done < 3 and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.02)
            try:
                with h5py.File(ckpt, "r") as f:
                    done = int(f.attrs["converged_steps"])
            except (OSError, KeyError):
                pass
        assert proc.poll() is None, "the solve ended before it could be killed"
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == -signal.SIGKILL
    assert not out.exists() and ckpt.exists()
    k = load_checkpoint(ckpt).records[-1].step
    assert 2 <= k < STEPS

    again = subprocess.run(cmd, capture_output=True, text=True)
    assert again.returncode == 0, again.stderr
    assert f"resuming from load step {k} of {STEPS}, checkpoint {ckpt}" in again.stderr
    assert not ckpt.exists()  # removed after the results were written
    res, full = load_results(out, lazy=False), load_results(d / "full.h5", lazy=False)
    assert res.status == "complete" and res.info["resumed_after_step"] == k
    assert len(res.alpha) == STEPS + 1
    np.testing.assert_array_equal(res.alpha, full.alpha)
    for name in full.reaction:  # every step's force
        assert _rel(res.reaction[name], full.reaction[name]) < 1e-10, name
    # coefficients only to the Newton tolerance: two uninterrupted runs already differ this much (the
    # energy test of a step may take one iteration more or less with round-off from threaded kernels)
    assert _rel(res.d, full.d) < 1e-7


def test_interrupted_solve_is_not_up_to_date(case):
    d = case
    cfg = parse_section(SolveConfig, ACTIVE, "solve")
    stage = Stage("solve", "solve", "pixmuscle.stages.solve:run_solve", {}, d / "full.h5", cfg, (d / "model.h5",))
    assert is_up_to_date(stage)
    ckpt = checkpoint_path(d / "full.h5")
    ckpt.write_bytes(b"")
    try:
        assert not is_up_to_date(stage)
    finally:
        ckpt.unlink()


def test_checkpoint_of_another_config_is_ignored(case, caplog):
    d = case
    full = load_results(d / "full.h5", lazy=False)
    out = d / "other.h5"
    ckpt = checkpoint_path(out)
    # converged steps 0..2 whose states would change every force if they were used
    recs = [StepRecord(step=k, t=k / STEPS, alpha=0.6 * k / STEPS, iterations=1, cutbacks=0, rows=[],
                       state=SavedState(full.d[k] + 0.01, k / STEPS, 0.6 * k / STEPS)) for k in range(3)]
    recs[-1].increment = (full.d[2] - full.d[1], 1 / STEPS)
    save_checkpoint(ckpt, recs, key="0" * 64, n_steps=STEPS)
    with caplog.at_level(logging.INFO, logger="pixmuscle"):
        run_solve(d / "model.h5", ACTIVE, out, progress=False)
    assert f"ignoring the checkpoint {ckpt}: it was made with another model file or solve configuration" in caplog.text
    assert "resuming" not in caplog.text
    res = load_results(out, lazy=False)
    assert "resumed_after_step" not in res.info and not ckpt.exists()
    for name in full.reaction:  # a used checkpoint would have kept the shifted states of steps 0..2
        assert _rel(res.reaction[name], full.reaction[name]) < 1e-10, name


@pytest.mark.parametrize("backend", ["direct", "cg_amg", "mixed_amg"])
@pytest.mark.parametrize("ramp", ["active", "passive"])
def test_resume_from_a_checkpoint_file_matches(tmp_path, backend, ramp):
    """Both ways of starting an increment (converged tangent; extrapolated last increment), every
    serial backend. The checkpoint keeps the linear solver's memory (the state its factors or AMG
    hierarchy were built from, its rebuild counters): the resumed solve rebuilds them there and takes
    the uninterrupted solve's decisions, Newton and Krylov iteration for iteration."""
    raw = dict(ACTIVE if ramp == "active" else PASSIVE, steps=3, solver={"backend": backend})
    cfg = parse_section(SolveConfig, raw, "solve")
    model = mask_model(np.ones((3, 3, 4), bool), (0.2, 0.2, 0.3), tissue=1)  # 36 nodes
    recs = []
    full = solve(model, cfg, on_checkpoint=lambda r: recs.append(list(r)))
    save_checkpoint(tmp_path / "c", recs[1], key="k", n_steps=cfg.steps)
    ck = load_checkpoint(tmp_path / "c")
    last = ck.records[-1]
    assert last.step == 1 and last.increment is not None and last.solver is not None
    np.testing.assert_array_equal(last.solver.d, recs[1][-1].solver.d)
    res = solve(model, cfg, resume=ck.records)
    assert res.info["resumed_after_step"] == 1
    np.testing.assert_array_equal(res.iterations, full.iterations)
    tail = len(res.info["linear_iterations"])  # the resumed solve's linear solves are the last ones
    assert res.info["linear_iterations"] == full.info["linear_iterations"][-tail:]
    rel = {name: _rel(res.reaction[name], full.reaction[name]) for name in full.reaction}
    assert max(rel.values()) < 1e-12, rel
    assert _rel(res.cauchy, full.cauchy) < 1e-12


def test_solver_memory_of_another_backend_is_not_used(caplog):
    """``auto`` can pick another backend on another machine (with or without MKL, with or without
    petsc4py for the multigrid) for the same config: the memory is then not recalled, the solve says
    so and resumes afresh."""
    raw = dict(ACTIVE, steps=3)
    model = mask_model(np.ones((3, 3, 4), bool), (0.2, 0.2, 0.3), tissue=1)
    recs = []
    full = solve(model, parse_section(SolveConfig, dict(raw, solver={"backend": "cg_amg", "amg": "pyamg"}), "solve"),
                 on_checkpoint=lambda r: recs.append(list(r)))
    assert recs[1][-1].solver.backend == "cg_amg/pyamg"
    with caplog.at_level(logging.WARNING, logger="pixmuscle"):
        res = solve(model, parse_section(SolveConfig, dict(raw, solver={"backend": "direct"}), "solve"), resume=recs[1])
    assert "the checkpoint's linear-solver memory is of backend cg_amg/pyamg, this solve uses direct" in caplog.text
    assert res.status == "complete" and res.info["resumed_after_step"] == 1
    rel = max(_rel(res.reaction[name], full.reaction[name]) for name in full.reaction)
    assert rel < 1e-5  # the Newton tolerance (10⁻⁴) lets two solvers differ this much, no more


def test_unreadable_checkpoint_is_ignored(tmp_path, caplog):
    from pixmuscle.stages.solve import _resume

    ckpt = checkpoint_path(tmp_path / "r.h5")
    ckpt.write_bytes(b"killed while the file system was full")
    with caplog.at_level(logging.WARNING, logger="pixmuscle"):
        assert _resume(ckpt, "k", STEPS) is None
    assert f"ignoring the checkpoint {ckpt}: it cannot be read" in caplog.text

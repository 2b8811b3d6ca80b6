"""The distributed system: the partition, the exactness of a rank's rows built from its nodes plus
halo, and real ``mpiexec -n 2`` / ``-n 3`` solves (the serial forces, no rank holding the whole
model, resume after a killed rank, every rank ending when one is killed). The mpiexec tests are
skipped, with the reason, without petsc4py or mpiexec."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml
from test_petsc import SWEEP, _body, _env, _mpiexec

from pixmuscle.config import parse_section
from pixmuscle.io.checkpoint import checkpoint_path, load_checkpoint
from pixmuscle.io.model import save_model
from pixmuscle.io.results import load_results
from pixmuscle.mechanics.config import SolveConfig
from pixmuscle.mechanics.distributed import bisection_partition, cell_depth, halo, halo_depth, needed, reach
from pixmuscle.mechanics.distributed.system import held_part, held_system
from pixmuscle.mechanics.solve import build_system, solve

SLICES = 32  # long enough that a rank's halo is not the whole body
STEPS = 6


def test_bisection_cuts_the_longest_axis_into_balanced_parts_of_any_count():
    ijk = np.indices((30, 12, 6)).reshape(3, -1).T
    for parts in (2, 3, 5):
        rank = bisection_partition(ijk, parts)
        counts = np.bincount(rank, minlength=parts)
        assert counts.min() > 0 and counts.max() - counts.min() <= 12 * 6  # at most one grid plane apart
    rank = bisection_partition(ijk, 2)
    assert np.ptp(ijk[rank == 0, 0]) < 29 and np.ptp(ijk[rank == 0, 2]) == 5  # cut across i (30 voxels), not k
    rank = bisection_partition(np.indices((12, 12, 4)).reshape(3, -1).T, 4)
    assert np.unique(rank).size == 4  # more ranks than slices would allow whole-slice slabs of 2


def test_points_without_a_regular_moment_matrix_can_be_left_empty():
    """``singular="empty"`` (the cut edge of a rank's part): a point with too few nodes gets an empty
    row, the others the shape functions they get alone (which still reproduce linear fields)."""
    from pixmuscle.rk import shape_functions

    nodes = np.indices((4, 4, 4)).reshape(3, -1).T.astype(float)
    good = np.array([[1.5, 1.5, 1.5], [2.0, 1.0, 1.5]])
    lonely = np.array([[9.0, 9.0, 9.0]])  # no node in its support
    with pytest.raises(Exception, match="singular"):
        shape_functions(nodes, np.vstack([good, lonely]), 1.65)
    psi, dpsi = shape_functions(nodes, np.vstack([good, lonely]), 1.65, gradient=True, singular="empty")
    ref, dref = shape_functions(nodes, good, 1.65, gradient=True)
    assert psi[2].nnz == 0 and all(g[2].nnz == 0 for g in dpsi)
    assert abs(psi[:2] - ref).max() == 0.0 and all(abs(g[:2] - r).max() == 0.0 for g, r in zip(dpsi, dref, strict=True))
    np.testing.assert_allclose(psi[:2] @ nodes, good, atol=1e-12)


def test_halo_depth_and_halo():
    assert halo_depth(1.65, (2, 2, 3)).tolist() == [5, 5, 6]  # cells 2 voxels away, their patches, their nodes
    assert halo_depth(1.65, (1, 1, 1)).tolist() == [4, 4, 4]
    assert halo_depth(1.65, (2, 2, 3), enlarged=1.56).tolist() == [7, 7, 8]
    assert cell_depth(1.65, (2, 2, 3)).tolist() == [3, 3, 4]
    ijk = np.indices((10, 1, 1)).reshape(3, -1).T
    inner = np.zeros(10, bool)
    inner[0] = True
    assert np.flatnonzero(halo(ijk, inner, (2, 0, 0))).tolist() == [0, 1, 2]


def test_the_cells_and_nodes_a_rank_needs_follow_each_nodes_support():
    """With every node's reach the same, :func:`needed` is the halo at the cell depth and at the halo
    depth; one enlarged node far off adds only itself where it reaches a needed cell."""
    ijk = np.indices((40, 6, 5)).reshape(3, -1).T
    owned = ijk[:, 0] < 10
    c = reach(np.full((len(ijk), 3), 1.65))
    assert c[0].tolist() == [2, 2, 2]
    cells, nodes = needed(ijk, owned, c, (2, 2, 3))
    np.testing.assert_array_equal(cells, halo(ijk, owned, cell_depth(1.65, (2, 2, 3))))
    np.testing.assert_array_equal(nodes, halo(ijk, owned, halo_depth(1.65, (2, 2, 3))))
    assert np.ptp(ijk[nodes, 0]) == 9 + 5  # 5 voxels beyond the last owned plane
    far = np.flatnonzero((ijk[:, 0] == 18) & (ijk[:, 1] == 2) & (ijk[:, 2] == 2))  # 6 beyond the last needed cells
    wide = c.copy()
    wide[far] = reach(np.full(3, 1.65 * 4))  # c = 6
    cells2, nodes2 = needed(ijk, owned, wide, (2, 2, 3))
    np.testing.assert_array_equal(cells2, cells)
    assert np.flatnonzero(nodes2 & ~nodes).tolist() == far.tolist()


@pytest.mark.parametrize("parts", [2, 3, 4])
def test_a_ranks_rows_from_its_nodes_plus_halo_are_the_whole_systems(parts):
    """For every rank of a P-way cut: the residual and the tangent product at its own nodes, computed
    from the system of its held nodes alone (with the model's supports and β), equal the whole
    system's to round-off (penalty, NSNI, projected patches and enlarged supports beside the strand
    included), and it holds fewer nodes than the model."""
    model = _body(SLICES)
    cfg = parse_section(SolveConfig, SWEEP, "solve")
    whole, _ = build_system(model, cfg)
    rng = np.random.default_rng(1)
    d = 0.01 * rng.standard_normal((model.n_nodes, 3))
    state = whole.evaluate(d, 0.5, 0.6)
    v = rng.standard_normal((model.n_nodes, 3))
    Kv = (whole.tangent_operator(state) @ v.ravel()).reshape(-1, 3)
    part = bisection_partition(model.ijk, parts)
    spared = 0
    for rank in range(parts):
        owned = part == rank
        held, sup, largest = held_part(model, cfg, owned)
        held, sup, _ = held_part(model, cfg, owned, largest)  # the depth of the model's largest support
        assert held.size < model.n_nodes
        spared += np.count_nonzero(halo(model.ijk, owned, halo_depth(1.65, (2, 2, 3), largest))) - held.size
        np.testing.assert_array_equal(sup, whole.scni.support[held])
        system, _ = held_system(model, cfg, held, sup, whole.constraints.beta, owned[held])
        assert 0 < np.count_nonzero(system.inert) < held.size - np.count_nonzero(owned)
        st = system.evaluate(d[held], 0.5, 0.6)
        own = np.flatnonzero(owned[held])
        assert np.abs(st.r[own] - state.r[held[own]]).max() <= 1e-12 * np.abs(state.r).max()
        y = (system.tangent_operator(st) @ v[held].ravel()).reshape(-1, 3)[own]
        assert np.abs(y - Kv[held[own]]).max() <= 1e-12 * np.abs(Kv).max()
    assert spared > 0  # node by node, the few enlarged supports do not deepen the whole halo


@pytest.fixture(scope="module")
def leg(tmp_path_factory):
    """The model, configs of 1-, 3- and 6-step sweeps with petsc_mixed (``c<steps>.yaml``), and the
    serial default solves of the 1- and 3-step ones."""
    tmp = tmp_path_factory.mktemp("dist")
    model = _body(SLICES)
    save_model(tmp / "model.h5", model)
    solver = {"backend": "petsc_mixed", "rtol": 1e-12}
    refs = {}
    for steps in (1, 3, STEPS):
        (tmp / f"c{steps}.yaml").write_text(yaml.safe_dump({"solve": dict(SWEEP, steps=steps, solver=solver)}))
        if steps < STEPS:
            refs[steps] = solve(model, parse_section(SolveConfig, dict(SWEEP, steps=steps), "solve"))
            assert refs[steps].status == "complete"
    return tmp, model, refs


def _cmd(launcher, ranks: int, tmp: Path, out: Path, config: str) -> list[str]:
    return launcher + ["-n", str(ranks), sys.executable, "-m", "pixmuscle.cli", "solve", str(tmp / "model.h5"),
                       "--config", str(tmp / config), "-o", str(out)]


@pytest.mark.parametrize("ranks, steps", [(2, 3), (3, 1)])
def test_mpiexec_distributed_solve_gives_the_serial_forces(leg, ranks, steps):
    """``mpiexec -n P pixmuscle solve`` with petsc_mixed on the distributed system: forces of every
    step equal the serial default solver's to 1e-6 (measured ~1e-13), displacements to 1e-6 of the
    largest; rank 0 held fewer than all nodes; one results file. (Three ranks on two cores wait for
    each other at every collective, 20× slower than two: one load step, α 0 → 0.95, for them.)"""
    launcher = _mpiexec()
    tmp, model, refs = leg
    ref = refs[steps]
    out = tmp / f"n{ranks}.h5"
    proc = subprocess.run(_cmd(launcher, ranks, tmp, out, f"c{steps}.yaml"), capture_output=True, text=True, env=_env(), timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    res = load_results(out, lazy=False)
    assert res.status == "complete" and res.info["ranks"] == ranks
    assert res.info["owned_nodes"] < res.info["held_nodes"] < model.n_nodes
    for name in ref.reaction:
        f, f_ref = np.asarray(res.reaction[name]), np.asarray(ref.reaction[name])
        assert np.abs(f - f_ref).max() <= 1e-6 * np.abs(f_ref).max(), name
    assert np.abs(np.asarray(res.u) - np.asarray(ref.u)).max() <= 1e-6 * np.abs(np.asarray(ref.u)).max()
    assert sorted(p.name for p in tmp.iterdir() if p.name.startswith(f"n{ranks}")) == [out.name]


def _rank_pids(parent: int) -> dict[int, int]:
    """Rank → PID of the processes that ``mpiexec`` (PID ``parent``) started (from their environment)."""
    out = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            env = (entry / "environ").read_bytes().split(b"\0")
            ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            continue
        if ppid != parent:
            continue
        for item in env:
            if item.startswith(b"OMPI_COMM_WORLD_RANK="):
                out[int(item.split(b"=")[1])] = int(entry.name)
    return out


def test_mpiexec_killed_rank_ends_every_rank_and_the_same_command_resumes(leg):
    """A rank killed (SIGKILL) after step 2 of a ``mpiexec -n 2`` solve: mpiexec and the other rank end
    within seconds, non-zero, with a line naming the killed rank; the checkpoint that rank 0 wrote
    holds the converged steps; the same command resumes from it and gives every step's forces of the
    uninterrupted ``-n 2`` run to 1e-8."""
    launcher = _mpiexec()
    if not Path("/proc/self/environ").exists():
        pytest.skip("needs /proc to find the ranks' processes")
    tmp, _, _ = leg
    full = tmp / "full2.h5"
    proc = subprocess.run(_cmd(launcher, 2, tmp, full, f"c{STEPS}.yaml"), capture_output=True, text=True, env=_env(), timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out, ckpt = tmp / "killed.h5", checkpoint_path(tmp / "killed.h5")
    cmd = _cmd(launcher, 2, tmp, out, f"c{STEPS}.yaml")
    run = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=_env())
    try:
        done, deadline = 0, time.monotonic() + 240
        while done < 3 and run.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
            try:
                with h5py.File(ckpt, "r") as f:
                    done = int(f.attrs["converged_steps"])
            except (OSError, KeyError):
                pass
        assert run.poll() is None, "the solve ended before it could be killed"
        pids = _rank_pids(run.pid)
        assert sorted(pids) == [0, 1], pids
        os.kill(pids[1], signal.SIGKILL)
        t0 = time.monotonic()
        _, err = run.communicate(timeout=60)
        ended = time.monotonic() - t0
    finally:
        if run.poll() is None:
            run.kill()
            run.wait()
    assert run.returncode != 0 and ended < 30
    assert any("rank 1" in line and "signal 9" in line for line in err.splitlines()), err[-2000:]
    assert not _rank_pids(run.pid)  # no rank left behind
    assert not out.exists() and ckpt.exists()
    k = load_checkpoint(ckpt).records[-1].step
    assert 2 <= k < STEPS

    again = subprocess.run(cmd, capture_output=True, text=True, env=_env(), timeout=300)
    assert again.returncode == 0, again.stderr[-3000:]
    assert f"resuming from load step {k} of {STEPS}" in again.stderr
    assert not ckpt.exists()
    res, ref = load_results(out, lazy=False), load_results(full, lazy=False)
    assert res.status == "complete" and res.info["resumed_after_step"] == k
    for name in ref.reaction:
        f, f_ref = np.asarray(res.reaction[name]), np.asarray(ref.reaction[name])
        assert np.abs(f - f_ref).max() <= 1e-8 * np.abs(f_ref).max(), name

"""The two multigrid V-cycles of the iterative backends (linsolve/multigrid.py): each is a fixed
symmetric positive operator (so CG may use it) and makes CG on a 3-D elasticity-like operator
converge in few iterations to the sparse direct solution."""

import os

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from pixmuscle.mechanics.linsolve import amg_processes, multigrid, pcg, rigid_body_modes, voxel_aggregates

needs_hypre = pytest.mark.skipif(not multigrid.hypre_available(), reason="petsc4py with hypre is not installed")
needs_workers = pytest.mark.skipif(not (multigrid.hypre_available() and amg_processes.available()),
                                   reason="petsc4py with hypre and mpi4py are not installed")


def _vector_laplacian(n=12):
    """−Δ on an n³ grid of unit spacing with Dirichlet ends, on each of 3 components plus a weak
    coupling of the components (node-major, 3 × 3 blocks), its nodes' (i, j, k)."""
    lap = sp.diags([-1.0, 2.0, -1.0], [-1, 0, 1], shape=(n, n))
    eye = sp.identity(n)
    L = sp.kron(sp.kron(lap, eye), eye) + sp.kron(sp.kron(eye, lap), eye) + sp.kron(sp.kron(eye, eye), lap)
    couple = np.full((3, 3), 0.2) + 0.8 * np.eye(3)
    K = sp.kron(L, couple).tocsr()
    ijk = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    return K, ijk


def _cycles():
    K, ijk = _vector_laplacian()
    B = rigid_body_modes(ijk.astype(float))
    out = {"pyamg": multigrid.SmoothedAggregation(K.tobsr(blocksize=(3, 3)), B, voxel_aggregates(ijk), 0.1)}
    if multigrid.hypre_available():
        out["hypre"] = multigrid.BoomerAMG(K)
        if amg_processes.available():  # on this process and a spawned MPI worker (amg_processes: 2)
            out["hypre_2p"] = multigrid.v_cycle("hypre", lambda: K.tobsr(blocksize=(3, 3)), None, None, 0.1, processes=2)
    return K, out


@pytest.mark.parametrize("name", ["pyamg", pytest.param("hypre", marks=needs_hypre),
                                  pytest.param("hypre_2p", marks=needs_workers)])
def test_v_cycle_is_symmetric_positive_and_preconditions_cg(name):
    K, cycles = _cycles()
    M = cycles[name]
    rng = np.random.default_rng(0)
    v, w = rng.standard_normal((2, K.shape[0]))
    assert np.isclose(v @ (M @ w), w @ (M @ v), rtol=1e-10)
    assert v @ (M @ v) > 0
    b = rng.standard_normal(K.shape[0])
    x, its, status = pcg(K, b, M, 1e-10, 200)
    assert status == "converged" and its <= 25
    _, plain, _ = pcg(K, b, sp.identity(K.shape[0]), 1e-10, 2000)
    assert plain > 3 * its
    assert np.allclose(x, spla.spsolve(K.tocsc(), b), rtol=0, atol=1e-8 * np.abs(x).max())


def test_auto_takes_hypre_where_it_is_installed():
    assert multigrid.resolve("auto") == ("hypre" if multigrid.hypre_available() else "pyamg")
    assert multigrid.resolve("pyamg") == "pyamg"


@needs_hypre
def test_boomeramg_takes_blocks_or_rows_alike():
    """The stand-in given as 3 × 3 blocks (straight into PETSc's block matrix) or as a function that
    makes it gives the same V-cycle as the CSR path, to the last bit."""
    K, _ = _vector_laplacian(8)
    v = np.random.default_rng(1).standard_normal(K.shape[0])
    ref = multigrid.BoomerAMG(K) @ v
    assert np.array_equal(multigrid.BoomerAMG(K.tobsr(blocksize=(3, 3))) @ v, ref)
    M = multigrid.BoomerAMG(lambda: K.tobsr(blocksize=(3, 3)))
    assert np.array_equal(M @ v, ref)
    assert M.nnz_per_row == K.nnz / K.shape[0]


@needs_workers
def test_boomeramg_on_two_processes_converges_as_on_one():
    """BoomerAMG on this process and a spawned worker (amg_processes: 2; symmetric, positive and
    converging to the direct solution: the test above) holds about half the rows in the worker and
    makes CG converge within three iterations of the one-process cycle; every hierarchy reuses the
    process's one worker group, and the worker reports its memory."""
    K, cycles = _cycles()
    M = cycles["hypre_2p"]
    assert isinstance(M, amg_processes.SpreadBoomerAMG) and M.nnz_per_row == K.nnz / K.shape[0]
    assert 0.4 < M.bounds[1] / (K.shape[0] // 3) < 0.6
    b = np.random.default_rng(1).standard_normal(K.shape[0])
    _, its, status = pcg(K, b, M, 1e-10, 200)
    _, serial, _ = pcg(K, b, cycles["hypre"], 1e-10, 200)
    assert status == "converged" and its <= serial + 3
    assert amg_processes.group(2) is M._workers
    (kb,) = amg_processes.workers_peak_rss_kb()
    assert kb > 10_000


@needs_workers
def test_a_dropped_hierarchy_is_freed_on_every_process_before_the_next_stand_in_is_made():
    """A hierarchy let go (a rebuild drops the old V-cycle) is only queued for freeing, since a
    finaliser may not talk MPI; the next set-up frees it on every process before it makes its
    stand-in, so that a rebuild's peak does not hold both."""
    K, _ = _vector_laplacian(6)
    Kb = K.tobsr(blocksize=(3, 3))
    M = multigrid.v_cycle("hypre", Kb, None, None, 0.1, processes=2)
    workers = M._workers
    del M
    queued_then = []

    def stand_in():
        queued_then.append(len(workers._unfreed))
        return Kb

    assert len(workers._unfreed) >= 1
    M = multigrid.v_cycle("hypre", stand_in, None, None, 0.1, processes=2)
    assert queued_then == [0]
    b = np.random.default_rng(2).standard_normal(K.shape[0])
    _, its, status = pcg(K, b, M, 1e-10, 100)
    assert status == "converged"


def test_more_processes_need_hypre_and_as_many_cores():
    from pixmuscle.errors import InputError

    with pytest.raises(InputError, match="solve.solver.amg_processes"):
        multigrid.resolve("pyamg", 2)
    assert multigrid.resolve("pyamg", 1) == "pyamg"
    cores = len(os.sched_getaffinity(0))
    with pytest.raises(InputError, match=rf"solve.solver.amg_processes: {cores + 1} processes, but this run has {cores} cores"):
        multigrid.resolve("auto", cores + 1)


def test_auto_processes_two_from_fifty_thousand_nodes_on_where_the_run_has_two_cores(monkeypatch):
    """``amg_processes: auto``: two where the run has two threads and two cores of its own; one below
    the size where two pay, with pyamg, without mpi4py, under mpiexec, where numba has one thread or
    the process one core, and in a Dask worker (a real one, in this process) given no thread count."""
    from distributed import Client, LocalCluster

    n = multigrid.AUTO_PROCESSES_NODES
    monkeypatch.setattr(multigrid, "amg_processes_available", lambda: True)
    monkeypatch.setattr(multigrid, "thread_count", lambda: 8)
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(8)))
    monkeypatch.delenv("NUMBA_NUM_THREADS", raising=False)
    assert multigrid.auto_processes("hypre", n) == multigrid.AUTO_PROCESSES == 2
    assert multigrid.auto_processes("hypre", n - 1) == 1
    assert multigrid.auto_processes("pyamg", 10 * n) == 1
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as cluster, \
            Client(cluster) as client:
        assert client.submit(multigrid.auto_processes, "hypre", 10 * n, pure=False).result() == 1
        monkeypatch.setenv("NUMBA_NUM_THREADS", "8")  # a cohort's worker with its share of the cores
        assert client.submit(multigrid.auto_processes, "hypre", 10 * n, pure=False).result() == 2
        monkeypatch.delenv("NUMBA_NUM_THREADS")
    monkeypatch.setenv("OMPI_COMM_WORLD_SIZE", "2")  # one of two ranks of an mpiexec launch
    assert multigrid.auto_processes("hypre", 10 * n) == 1
    monkeypatch.delenv("OMPI_COMM_WORLD_SIZE")
    monkeypatch.setattr(multigrid, "thread_count", lambda: 1)  # NUMBA_NUM_THREADS=1: a cohort with a model per core
    assert multigrid.auto_processes("hypre", 10 * n) == 1
    monkeypatch.setattr(multigrid, "thread_count", lambda: 8)
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0})  # taskset -c 0, a batch job's CPU set
    assert multigrid.auto_processes("hypre", 10 * n) == 1
    monkeypatch.setattr(multigrid, "amg_processes_available", lambda: False)  # no mpi4py
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(8)))
    assert multigrid.auto_processes("hypre", 10 * n) == 1


@needs_workers
@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="auto takes one process on one core")
def test_auto_processes_fall_back_to_one_where_the_workers_do_not_start(tmp_path):
    """``amg_processes: auto`` chose two processes but MPI refuses the worker (a host file with one
    slot, as in a batch allocation of one task): the solve runs on one process with a warning (logged
    and in the results) and gives the one-process solution; asked for explicitly, two processes are
    an error naming the key (MPI is not asked again)."""
    import subprocess
    import sys

    from mpi4py import MPI

    if not MPI.Get_library_version().startswith("Open MPI v4"):
        pytest.skip("the one-slot host file is Open MPI 4's (orte_default_hostfile)")
    hostfile = tmp_path / "hosts"
    hostfile.write_text("localhost slots=1\n")
    env = {k: v for k, v in os.environ.items() if "oversubscribe" not in k.lower()}
    env.update(OMPI_MCA_orte_default_hostfile=str(hostfile), NUMBA_NUM_THREADS="2")
    code = """if True:
        import logging, numpy as np
        from pixmuscle.config import parse_section
        from pixmuscle.errors import SolverError
        from pixmuscle.mechanics.config import SolveConfig
        from pixmuscle.mechanics.linsolve import multigrid
        from pixmuscle.mechanics.solve import solve
        from pixmuscle.verify.mechanics import mask_model

        logging.basicConfig()
        multigrid.AUTO_PROCESSES_NODES = 0  # auto takes two processes for this small model
        model = mask_model(np.ones((4, 4, 5), bool), (0.15, 0.15, 0.4), tissue=1)
        bcs = [{"nodes": "z_min", "fix": ["x", "y", "z"]}, {"nodes": "z_max", "fix": ["x", "y", "z"]}]
        solver = {"backend": "mixed_amg", "amg": "hypre"}
        cfg = lambda p: parse_section(SolveConfig, {"steps": 2, "boundary_conditions": bcs, "activation": {"from": 0.0, "to": 0.5},
                                                   "solver": solver | {"amg_processes": p}}, "solve")
        auto, one = solve(model, cfg("auto")), solve(model, cfg(1))
        print(auto.info["amg_processes"], auto.status, abs(auto.force("z_max")[-1] / one.force("z_max")[-1] - 1),
              sum("BoomerAMG runs on this process only" in w for w in auto.warnings))
        try:
            solve(model, cfg(2))
        except SolverError as exc:
            print(exc)
    """
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=env)
    assert run.returncode == 0, run.stderr
    first, asked = run.stdout.splitlines()[:2]
    procs, status, diff, warned = first.split()
    assert procs == "1" and status == "complete" and float(diff) < 1e-12 and warned == "1", run.stdout
    assert "auto chose 2 processes, but MPI did not start the worker" in run.stderr
    assert "BoomerAMG runs on this process only" in run.stderr
    assert "linear solver: solve.solver.amg_processes: could not start 1 MPI worker(s)" in asked, asked


@needs_workers
def test_a_run_with_workers_ends_cleanly():
    """A process that spawned BoomerAMG workers exits at once and with status 0 (the workers are
    stopped and disconnected at exit), also when it ends with an error."""
    import subprocess
    import sys

    code = ("import numpy as np, scipy.sparse as sp; from pixmuscle.mechanics.linsolve import multigrid; "
            "K = sp.kron(sp.diags([-1.0, 2.1, -1.0], [-1, 0, 1], shape=(60, 60)), sp.identity(3)).tobsr(blocksize=(3, 3)); "
            "M = multigrid.v_cycle('hypre', K, None, None, 0.1, processes=2); print(float((M @ np.ones(180)).sum()) > 0); ")
    ok = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert ok.returncode == 0 and ok.stdout.strip() == "True", ok.stderr
    failed = subprocess.run([sys.executable, "-c", code + "raise SystemExit('stop here')"], capture_output=True,
                            text=True, timeout=120)
    assert failed.returncode == 1 and "stop here" in failed.stderr


@needs_workers
@pytest.mark.parametrize("how", ["error", "killed"])
def test_a_dead_worker_ends_the_run_instead_of_hanging_it(how):
    """A worker that fails (asked to apply a hierarchy it does not hold: it prints its traceback and
    aborts) or is killed from outside (SIGKILL, as for memory) while the run waits for its answer:
    the run ends with exit status 3 and one error line naming the key, instead of waiting for ever."""
    import subprocess
    import sys

    kill = "g.command(1, 'apply', 12345)" if how == "error" else "import os; os.kill(g.pids[0], 9)"
    code = (f"from pixmuscle.mechanics.linsolve import amg_processes as ap; g = ap.group(2); {kill}; "
            "print(g.comm.recv(source=1, tag=ap._DATA))")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert run.returncode == 3, run.stderr
    assert "error: solve.solver.amg_processes: the BoomerAMG worker process" in run.stderr
    assert ("KeyError: 12345" in run.stderr) == (how == "error")


def test_drop_weak_blocks_keeps_the_diagonal_and_the_strong_blocks():
    """Blocks weaker than tol √(‖K_aa‖ ‖K_bb‖) go, the rest stay as they were: checked block by
    block against the dense matrix."""
    K, _ = _vector_laplacian(5)
    rng = np.random.default_rng(2)
    K = (K + sp.random(K.shape[0], K.shape[0], density=0.05, random_state=3) * 0.05).tobsr(blocksize=(3, 3))
    K.data *= rng.uniform(0.5, 1.5, K.data.shape[0])[:, None, None]
    assert multigrid.drop_weak_blocks(K, 0.0) is K
    D = K.toarray()
    n = D.shape[0] // 3
    blk = lambda a, b: D[3 * a:3 * a + 3, 3 * b:3 * b + 3]  # noqa: E731
    for tol in (0.05, 0.3):
        F = multigrid.drop_weak_blocks(K, tol).toarray()
        for a in range(n):
            for b in range(n):
                strong = np.linalg.norm(blk(a, b)) >= tol * np.sqrt(np.linalg.norm(blk(a, a)) * np.linalg.norm(blk(b, b)))
                expect = blk(a, b) if (a == b or strong) else 0.0
                assert np.array_equal(F[3 * a:3 * a + 3, 3 * b:3 * b + 3], np.broadcast_to(expect, (3, 3)))
        assert 0 < np.count_nonzero(F) < np.count_nonzero(D)

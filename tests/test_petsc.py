"""PETSc/MPI backend: the rows one rank assembles, and real ``mpiexec -n 2`` runs
of ``pixmuscle solve`` against the serial default solver (skipped, with the reason, without petsc4py
or mpiexec)."""

import dataclasses
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp
import yaml

from pixmuscle.config import parse_section
from pixmuscle.io.model import save_model
from pixmuscle.io.results import load_results
from pixmuscle.mechanics.config import SolveConfig
from pixmuscle.mechanics.distributed import bisection_partition
from pixmuscle.mechanics.linsolve import petsc
from pixmuscle.mechanics.rows import RowAssembler
from pixmuscle.mechanics.solve import build_system, solve
from pixmuscle.verify.mechanics import _cfg, mask_model

BCS = [{"nodes": "z_min", "fix": ["x", "y", "z"]}, {"nodes": "z_max", "fix": ["x", "y", "z"]}]
# a tight Newton tolerance: the tests compare linear solvers, whose answers then agree to 1e-6 in force
SWEEP = {"steps": 3, "activation": {"from": 0.0, "to": 0.95}, "boundary_conditions": BCS,
         "newton": {"residual_tol": 1e-8, "energy_tol": 1e-14}}


def _body(slices: int = 14):
    """Irregular muscle/connective-tissue body: oblique-fibre muscle core, connective-tissue rim,
    a notch and a one-voxel strand (enlarged RK supports)."""
    mask = np.ones((7, 6, slices), bool)
    mask[5:, 4:, :] = False
    mask[0, 0, 3:] = False
    mask = np.pad(mask, ((0, 2), (0, 0), (0, 0)))
    mask[7:9, 2, :] = True
    model = mask_model(mask, (0.15, 0.15, 0.4), tissue=2)
    tissue = np.asarray(model.tissue).copy()
    tissue[np.all((model.ijk >= [1, 1, 0]) & (model.ijk <= [5, 4, slices - 1]), axis=1)] = 1
    fiber = np.tile(np.array([np.sin(0.4), 0.0, np.cos(0.4)]), (model.n_nodes, 1))
    return dataclasses.replace(model, tissue=tissue, fiber=fiber)


@pytest.mark.parametrize("volumetric", ["projected", "nodal"])
def test_owned_rows_equal_the_rows_of_the_whole_tangent(volumetric):
    """Rows assembled from the cells around one rank's nodes (plus halo) are the rows of the full assembly
    (penalty, NSNI stabilisation and the projected patch terms included)."""
    model = _body()
    system = build_system(model, parse_section(SolveConfig, dict(SWEEP, volumetric={"method": volumetric}), "solve"))[0]
    rng = np.random.default_rng(0)
    state = system.evaluate(0.01 * rng.standard_normal((model.n_nodes, 3)), 0.5, 0.6)
    K = system.stiffness(state).tocsr()
    part = bisection_partition(model.ijk, 2)
    for r in range(2):
        owned = np.flatnonzero(part == r)
        rows = RowAssembler(system, owned)
        assert rows.cells.size < model.n_nodes  # a halo, not the whole body
        assert np.count_nonzero(np.diff(rows.asm.indptr)) == owned.size  # and only the owned block rows
        dofs = (3 * owned[:, None] + np.arange(3)).ravel()
        diff = rows.rows(state) - K[dofs]
        assert abs(diff).max() < 1e-12 * abs(K).max()


def _config(tmp_path: Path, solver: dict) -> Path:
    path = tmp_path / f"{solver['backend']}.yaml"
    path.write_text(yaml.safe_dump({"solve": dict(SWEEP, solver=solver)}))
    return path


def _mpiexec() -> list[str]:
    exe = shutil.which("mpiexec")
    if not petsc.available():
        pytest.skip(f"petsc4py not importable ({petsc.INSTALL_HINT})")
    if exe is None:
        pytest.skip("mpiexec not found (apt-get install openmpi-bin)")
    return [exe, "--oversubscribe"]


def _env():
    return dict(os.environ, OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1", OMPI_MCA_rmaps_base_oversubscribe="1",
                OMPI_MCA_mpi_yield_when_idle="1")  # more ranks than cores: a waiting rank gives its core up


@pytest.fixture(scope="module")
def serial(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("petsc")
    model = _body(6)
    save_model(tmp / "model.h5", model)
    ref = solve(model, parse_section(SolveConfig, SWEEP, "solve"))
    assert ref.status == "complete" and abs(ref.force("z_max")[-1]) > 1.0
    return tmp, ref


@pytest.mark.parametrize("backend", ["petsc", "petsc_mixed"])
@pytest.mark.parametrize("ranks", [1, 2])
def test_mpiexec_solve_matches_the_serial_default_solver(serial, ranks, backend):
    """``mpiexec -n P pixmuscle solve`` (real processes), condensed and mixed (Schur field split):
    the forces of the 3-step sweep equal the serial default (direct) solver to 1e-6, the
    displacements to 1e-4 of the largest |u|; one results file, written by rank 0."""
    launcher = _mpiexec()
    tmp, ref = serial
    cfg = _config(tmp, {"backend": backend, "rtol": 1e-12})
    out = tmp / f"results_{backend}_{ranks}.h5"
    cmd = launcher + ["-n", str(ranks), sys.executable, "-m", "pixmuscle.cli", "solve", str(tmp / "model.h5"),
                      "--config", str(cfg), "-o", str(out)]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=_env(), timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    res = load_results(out)
    assert res.status == "complete"
    assert res.info["linear_solver"] == backend and res.info["krylov_iterations"] > 0
    f, f_ref = res.force("z_max"), ref.force("z_max")
    assert np.allclose(f, f_ref, rtol=1e-6, atol=1e-9 * abs(f_ref).max())
    u_ref = np.asarray(ref.u)
    assert np.abs(np.asarray(res.u) - u_ref).max() <= 1e-4 * np.abs(u_ref).max()
    assert sorted(p.name for p in tmp.iterdir() if p.name.startswith(f"results_{backend}_{ranks}")) == [out.name]


def _first_newton_iterations(backend, bulk_scale, options=None, beta=3.0e4, **solver):
    """Krylov iterations of ``backend`` on the first Newton system (zero displacement, α = 0.6) of the
    clamped body of tests/test_mixed_solver.py with every bulk modulus × ``bulk_scale``, to 10⁻⁸ of
    the condensed residual, and the solution's error against SciPy's direct solve; None for the
    iterations when the solve fails. The penalty β is fixed at ``beta`` N/cm³ unless ``beta`` is
    None: its default scales with the largest modulus, i.e. with K, and puts a K-scaled term into the
    displacement block. ``solver``: further backend options (``region_solves``)."""
    import scipy.sparse.linalg as spla
    from test_mixed_solver import _system  # the same body as the serial mixed solver's K/μ test

    from pixmuscle.errors import SolverError
    from pixmuscle.mechanics.linsolve import make_solver

    penalty = {} if beta is None else {"penalty": {"at": "nodes", "beta": beta}}
    model, system = _system(held="patch", **penalty,
                            muscle={"K": 5000.0 * bulk_scale}, connective_tissue={"K": 50000.0 * bulk_scale})
    state = system.evaluate(np.zeros((model.n_nodes, 3)), 0.5, 0.6)
    r = state.r.ravel()
    solver = make_solver(backend, model.X, ijk=model.ijk, rtol=1e-10, maxiter=3000, petsc_options=options or {},
                         **solver)
    solver.prepare(system, state)
    try:
        x = solver.solve(r, rtol=1e-8)
    except SolverError:
        return None, None
    K = system.stiffness(state).tocsc()
    # both stop on the true condensed residual (of the matrix-free product: the assembled one differs in round-off);
    # the condensed GMRES's residual, updated through 500+ iterations and restarts, drifts from the true one (GAMG's
    # random eigenvalue estimates make the count depend on what ran before: 6e-8 measured after other backends)
    assert np.linalg.norm(K @ x - r) <= (1.05e-8 if backend == "petsc_mixed" else 1e-7) * np.linalg.norm(r)
    ref = spla.spsolve(K, r)
    return solver.info["iterations"], np.linalg.norm(x - ref) / np.linalg.norm(ref)


def test_mixed_field_split_iterations_do_not_grow_with_the_bulk_modulus():
    """PETSc FGMRES with the Schur field split (BoomerAMG, or GAMG without hypre, on K_d; the probed
    Schur diagonal; region solves on, the defaults), refinement passes for the condensed residual
    included: ≤ 1.5× the iterations when every bulk modulus is ×10 (measured 35 and 39 with
    BoomerAMG; with the pressure mass 48 and 53, 82 and 75 with GAMG), while the condensed GMRES + GAMG needs more than
    1.5× as many or fails (measured 680 at K × 1, breakdown at K × 10)."""
    if not petsc.available():
        pytest.skip(f"petsc4py not importable ({petsc.INSTALL_HINT})")
    its, condensed = {}, {}
    for scale in (1.0, 10.0):
        its[scale], err = _first_newton_iterations("petsc_mixed", scale)
        assert its[scale] is not None and err <= 1e-6
        condensed[scale], _ = _first_newton_iterations("petsc", scale)
    assert its[10.0] <= 1.5 * its[1.0]
    assert condensed[1.0] is None or condensed[1.0] > its[1.0]
    assert condensed[10.0] is None or (condensed[1.0] is not None and condensed[10.0] > 1.5 * condensed[1.0])


def test_mixed_region_solves_keep_iterations_flat_in_the_bulk_modulus_with_the_default_penalty():
    """With the default penalty number (β ∝ the largest modulus, so ∝ K) the penalty rows put a
    K-scaled term into K_d. With the exact solves on the boundary-condition regions after the
    multigrid (the default) the iterations stay ≤ 1.5× from K × 1 to K × 10 (measured 48 and 53
    with BoomerAMG and the probed Schur diagonal; 96 and 102 with GAMG and the pressure mass);
    GAMG alone grows by more than 1.5× (measured 362 and 1,862)."""
    if not petsc.available():
        pytest.skip(f"petsc4py not importable ({petsc.INSTALL_HINT})")
    its = {}
    for regions in (True, False):
        for scale in (1.0, 10.0):
            its[regions, scale], err = _first_newton_iterations("petsc_mixed", scale, beta=None, region_solves=regions)
            assert its[regions, scale] is not None and err <= 1e-6
    assert its[True, 10.0] <= 1.5 * its[True, 1.0]
    assert its[True, 1.0] < its[False, 1.0]
    assert its[False, 10.0] > 1.5 * its[False, 1.0]


def test_mixed_probed_schur_diagonal_takes_fewer_iterations_than_the_pressure_mass():
    """``schur: probed`` (the default, as in ``mixed_amg``): the diagonal of w² G M Gᵀ probed with the
    displacement split's own preconditioner M gives the Schur split a better diagonal than the
    scaled pressure mass, so FGMRES needs fewer iterations at the tissues' K/μ and at K × 10 (default
    penalty, region solves), and the solution is still the direct one."""
    if not petsc.available():
        pytest.skip(f"petsc4py not importable ({petsc.INSTALL_HINT})")
    its = {}
    for schur in ("probed", "mass"):
        for scale in (1.0, 10.0):
            its[schur, scale], err = _first_newton_iterations("petsc_mixed", scale, beta=None, schur=schur)
            assert its[schur, scale] is not None and err <= 1e-6
    assert its["probed", 1.0] < its["mass", 1.0] and its["probed", 10.0] < its["mass", 10.0]
    assert its["probed", 10.0] <= 1.5 * its["probed", 1.0]


def test_mixed_probed_schur_diagonal_is_exact_with_an_exact_displacement_solve():
    """With the displacement split solved exactly (``fieldsplit_u_pc_type: lu``) and every patch
    its own colour (8 patches, the 8 parity colours), the probed −Ŝ that PETSc's Schur split gets
    is −(w² D⁻¹ + w² diag(G K_d⁻¹ Gᵀ)) computed densely from the same blocks."""
    if not petsc.available():
        pytest.skip(f"petsc4py not importable ({petsc.INSTALL_HINT})")
    from test_mixed_solver import CLAMPED

    from pixmuscle.mechanics.linsolve import make_solver

    model = mask_model(np.ones((4, 4, 6), bool), (0.15, 0.15, 0.4), tissue=1,
                       fiber=np.array([np.sin(0.4), 0.0, np.cos(0.4)]))
    cfg = _cfg(boundary_conditions=CLAMPED, volumetric={"method": "projected", "patch": [2, 2, 3], "held": "patch"})
    system = build_system(model, cfg)[0]
    assert system.volumetric.n_patches == 8
    state = system.evaluate(np.zeros((model.n_nodes, 3)), 0.5, 0.6)
    solver = make_solver("petsc_mixed", model.X, ijk=model.ijk, probe_spacing=2,
                         petsc_options={"fieldsplit_u_pc_type": "lu"})
    solver.prepare(system, state)
    A00, _, A10, A11, S = solver._mixed["blocks"]

    def dense(M):
        indptr, indices, data = M.getValuesCSR()
        return sp.csr_matrix((data, indices, indptr), shape=M.getSize()).toarray()

    Kd, wG, c22 = dense(A00), dense(A10), -np.diag(dense(A11))
    exact = c22 + np.diag(wG @ np.linalg.solve(Kd, wG.T))
    assert np.allclose(-np.diag(dense(S)), exact, rtol=1e-8)


def test_mpiexec_failure_on_one_rank_ends_all_ranks(serial, tmp_path):
    """A bad PETSc option set on every rank: all ranks end with the message, nothing is written."""
    launcher = _mpiexec()
    tmp, _ = serial
    cfg = _config(tmp_path, {"backend": "petsc", "petsc_options": {"ksp_type": "no_such_krylov"}})
    out = tmp_path / "results.h5"
    cmd = launcher + ["-n", "2", sys.executable, "-m", "pixmuscle.cli", "solve", str(tmp / "model.h5"),
                      "--config", str(cfg), "-o", str(out)]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=_env(), timeout=300)
    assert proc.returncode != 0
    assert "no_such_krylov" in proc.stderr
    assert not out.exists()


def test_petsc_backend_without_petsc4py_is_a_config_error_with_install_hint(monkeypatch):
    monkeypatch.setattr(petsc, "available", lambda: False)
    with pytest.raises(Exception, match=r"solve\.solver: backend: petsc.*petsc4py.*make venv"):
        parse_section(SolveConfig, dict(SWEEP, solver={"backend": "petsc"}), "solve")


def test_petsc_leaves_a_closed_pipe_to_python():
    """With PETSc started by pixmuscle, a write to a pipe closed by its reader (a Dask or browser
    connection at shutdown, a CI log reader) raises BrokenPipeError as in plain Python: PETSc's own
    SIGPIPE handler would abort the interpreter through MPI (exit 59, seen as 'Broken pipe' in CI)."""
    if not petsc.available():
        pytest.skip(f"petsc4py not importable ({petsc.INSTALL_HINT})")
    script = ("import os\n"
              "from pixmuscle.parallel import import_petsc\n"
              "PETSc = import_petsc()\n"
              "assert PETSc.Sys.getVersion()\n"
              "r, w = os.pipe()\n"
              "os.close(r)\n"
              "try:\n"
              "    os.write(w, b'x')\n"
              "except BrokenPipeError:\n"
              "    print('BrokenPipeError')\n")
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stderr[-2000:]
    assert run.stdout.strip() == "BrokenPipeError"


def test_mixed_newton_system_frees_the_petsc_objects_of_the_last_one():
    """Each prepare destroys the last Newton system's KSP, blocks and vectors: left to Python's collector
    they lived on (the K_d block's context holds the tangent's moduli), and a 10-step sweep of the 10k
    leg grew by 65 MB per load step."""
    if not petsc.available():
        pytest.skip(f"petsc4py not importable ({petsc.INSTALL_HINT})")
    from pixmuscle.mechanics.linsolve import make_solver

    model = _body(6)
    system = build_system(model, parse_section(SolveConfig, SWEEP, "solve"))[0]
    state = system.evaluate(np.zeros((model.n_nodes, 3)), 0.5, 0.6)
    solver = make_solver("petsc_mixed", model.X, ijk=model.ijk)
    solver.prepare(system, state)
    first = solver._mixed
    objects = [first["ksp"], first["A"], *first["blocks"], first["b"], first["z"], first["t"]]
    assert all(obj.handle for obj in objects)
    solver.prepare(system, state)
    assert not any(obj.handle for obj in objects)
    assert solver._mixed["ksp"].handle


def test_mixed_finished_solve_destroys_its_operators_and_the_next_system_keeps_the_preconditioner():
    """finish() (the driver's call after each solve) destroys the solved system's PETSc objects, whose
    K_d block reads the state's moduli, so that release_moduli lets them go; the displacement
    preconditioner stays, and the next system's update equals SciPy's direct solve of its tangent."""
    if not petsc.available():
        pytest.skip(f"petsc4py not importable ({petsc.INSTALL_HINT})")
    from test_mixed_solver import _system, next_system_keeps_the_preconditioner

    from pixmuscle.mechanics.linsolve import make_solver

    model, system = _system(held="patch")
    s0 = system.evaluate(np.zeros((model.n_nodes, 3)), 0.5, 0.6)
    solver = make_solver("petsc_mixed", model.X, ijk=model.ijk, rtol=1e-10)
    solver.prepare(system, s0)
    solver.solve(s0.r.ravel(), rtol=1e-9)
    mx = solver._mixed
    objects = [mx["ksp"], mx["A"], *mx["blocks"], mx["b"], mx["z"], mx["t"]]
    del mx
    solver.finish()
    system.release_moduli(s0)
    assert solver._mixed is None and s0.A is None
    assert not any(obj.handle for obj in objects)
    assert solver.info["preconditioner_builds"] == 1
    next_system_keeps_the_preconditioner(solver, model, system)

"""Finite-strain solver: configuration, homogeneous reference solutions, penalty BCs and reactions,
failure handling, the solve stage and its results file, linear-solver backends."""

import dataclasses
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import yaml

from pixmuscle.config import parse_section
from pixmuscle.errors import InputError, SolverError
from pixmuscle.io.model import save_model
from pixmuscle.io.results import load_results
from pixmuscle.mechanics import pardiso
from pixmuscle.mechanics.config import SolveConfig
from pixmuscle.mechanics.linsolve import DirectSolver, make_solver, multigrid, voxel_aggregates
from pixmuscle.mechanics.solve import solve
from pixmuscle.store import write_bytes_atomic
from pixmuscle.verify.mechanics import isometric_check, mask_model, oblique_check, roller_bcs, uniaxial_check

needs_hypre = pytest.mark.skipif(not multigrid.hypre_available(), reason="petsc4py with hypre is not installed")

EXAMPLE = """
solve:
  steps: 10
  activation: {from: 0.0, to: 0.95}
  boundary_conditions:
    - {nodes: z_min, fix: [x, y, z]}
    - {nodes: z_max, displace: {z: 2.0}}
    - {nodes: bone_surface, fix: [x, y]}
"""


def _cfg(**kw):
    return parse_section(SolveConfig, kw, "solve")


def test_config_example_parses():
    cfg = parse_section(SolveConfig, yaml.safe_load(EXAMPLE)["solve"], "solve")
    assert cfg.steps == 10 and cfg.alpha_from == 0.0 and cfg.alpha_to == 0.95
    bcs = cfg.boundary_conditions
    assert [b.nodes for b in bcs] == ["z_min", "z_max", "bone_surface"]
    assert bcs[0].components() == ([0, 1, 2], [0.0, 0.0, 0.0])
    assert bcs[1].components() == ([2], [2.0])
    assert bcs[2].components() == ([0, 1], [0.0, 0.0])
    # defaults from the paper
    assert cfg.support.kernel == "cubic" and cfg.support.order == 1 and cfg.support.a_over_h == (1.65, 1.65, 1.65)
    assert cfg.materials.connective_tissue.C30 == 800.0 and cfg.materials.fat.K == 5000.0
    assert cfg.materials.muscle.C10 == 6.43 and cfg.materials.muscle.sigma_max == 30.0


@pytest.mark.parametrize("data, match", [
    ({"activation": {"from": 0.0, "too": 1.0}}, "activation"),
    ({"activation": {"to": 1.5}}, r"activation\.to"),
    ({"boundary_conditions": [{"nodes": "z_min", "fix": ["w"]}]}, r"boundary_conditions\[0\]\.fix\[0\]"),
    ({"boundary_conditions": [{"nodes": "z_min", "fix": ["z"], "displace": {"z": 1.0}}]}, "both fixed and displaced"),
    ({"boundary_conditions": [{"fix": ["z"]}]}, "exactly one of"),
    ({"boundary_conditions": [{"point": [0, 0], "fix": ["z"]}]}, "3 coordinates"),
    ({"stabilization": {"method": "mscni"}}, "nsni"),
    ({"support": {"a_over_h": [1.65, 1.65]}}, "3 values"),
    ({"penalty": {"factr": 10}}, "did you mean 'factor'"),
])
def test_config_errors_name_the_key(data, match):
    with pytest.raises(InputError, match=match):
        parse_section(SolveConfig, data, "solve")


def test_uniaxial_bar_matches_homogeneous_reference():
    for row in uniaxial_check(stretches=(1.02, 1.05, 1.10), steps_per_case=1):
        assert abs(row["rel_error"]) < 5e-3, row
        assert abs(row["balance"]) < 1e-6  # both ends carry the same tension


def test_isometric_block_matches_homogeneous_reference():
    for row in isometric_check(alphas=(0.25, 0.5, 0.95), steps=20):
        assert abs(row["rel_error"]) < 5e-3, row


def test_oblique_fibres_against_min_energy_state():
    # u_z held at every node: the homogeneous problem, nodal stress equals the min-energy state.
    # (With free lateral faces the block shears inhomogeneously and pulls 25-60 % less than the
    # homogeneous state: reported by verify_mechanics, not a test of correctness.)
    rows = oblique_check(alphas=(0.25, 0.5, 0.95), steps=20, variants=("uz",))
    assert len(rows) == 3
    for r in rows:
        assert abs(r["rel_error"]) < 1e-2, r
        assert r["stress_spread"] < 1e-3


@pytest.mark.parametrize("at", ["auto", "centres"])
def test_reaction_sign_convention_and_point_constraint(at):
    """A homogeneous roller stretch, end sets held at their end-face vertices (default) or centres: both
    rules are SCNI's own boundary rules, so the stretch is reproduced up to the penalty gap (∝ 1/β)."""
    model = mask_model(np.ones((3, 3, 6), bool), (0.2, 0.2, 0.3))
    L = 6 * 0.3
    # stiff penalty: the displacement check below is at 1e-4 (the gap is traction / β)
    cfg = _cfg(steps=1, activation={"from": 0.0, "to": 0.0}, boundary_conditions=roller_bcs(model, 0.02 * L),
               penalty={"factor": 1.0e3, "at": at})
    res = solve(model, cfg)
    # tension: the support pulls the body outwards at both ends
    assert res.reaction["z_max"][-1][2] > 0 and res.reaction["z_min"][-1][2] < 0
    assert res.force("z_max")[-1] > 0 and res.force("z_min")[-1] > 0
    # a homogeneous stretch needs no lateral reaction at the pins
    assert np.abs(res.reaction["pin"][-1]).max() < 1e-6 * res.force("z_max")[-1]
    # the RK-interpolated displacement at the top end face reaches the prescribed value
    top = model.sets["z_max"]
    assert np.allclose(res.prescribed["z_max"][-1], [0, 0, 0.02 * L])
    assert res.constrained["z_max"].tolist() == [False, False, True]
    # nodes sit half a cell inside the end face: u_z(X) = ε (z − z_bottom_face)
    zb = model.X[:, 2].min() - 0.15
    assert np.allclose(res.u[-1][top, 2], 0.02 * (model.X[top, 2] - zb), rtol=1e-4)
    # and everywhere the field is affine (the patch test)
    A = np.c_[model.X, np.ones(model.n_nodes)]
    fit = A @ np.linalg.lstsq(A, res.u[-1], rcond=None)[0]
    assert np.abs(fit - res.u[-1]).max() < 1e-8 * np.abs(res.u[-1]).max()


def test_unknown_node_set_is_an_input_error():
    model = mask_model(np.ones((3, 3, 4), bool), (0.2, 0.2, 0.3))
    cfg = _cfg(steps=1, boundary_conditions=[{"nodes": "tibia", "fix": ["x"]}])
    with pytest.raises(InputError, match="tibia"):
        solve(model, cfg)


def test_failed_solve_keeps_converged_steps(tmp_path):
    """A load step that cannot converge raises SolverError naming the step and α; run_solve still writes
    the converged steps with status 'failed: ...'."""
    from pixmuscle.stages.solve import run_solve

    model = mask_model(np.ones((3, 3, 5), bool), (0.2, 0.2, 0.3))
    L = 5 * 0.3
    # the second step compresses the bar to 10 % of its length in one increment with no cutbacks
    cfg = _cfg(steps=2, activation={"from": 0.0, "to": 0.0},
               boundary_conditions=roller_bcs(model, -1.8 * L),
               newton={"max_iterations": 3, "max_cutbacks": 0})
    with pytest.raises(SolverError, match=r"load step 1 of 2 \(α = 0"):
        solve(model, cfg)
    mpath = tmp_path / "model.h5"
    save_model(mpath, model)
    out = tmp_path / "results.h5"
    with pytest.raises(SolverError):
        run_solve(mpath, cfg, out, progress=False)
    res = load_results(out)
    assert res.status.startswith("failed: load step 1 of 2")
    assert res.n_states == 1 and res.n_steps_planned == 2  # only the initial state converged
    assert len(res.newton["residual_norm"]) > 0


def test_results_take_the_step_arrays_over_without_holding_them_twice():
    """Results.from_steps stacks each step's nodal arrays as numpy.stack does, and lets each step's
    own array go (None in its dictionary) as soon as it is copied."""
    from pixmuscle.mechanics.results import Results

    model = mask_model(np.ones((2, 2, 3), bool), (0.2, 0.2, 0.3), tissue=1)
    n, rng = model.n_nodes, np.random.default_rng(0)
    shapes = {"u": (n, 3), "d": (n, 3), "cauchy": (n, 6), "max_principal": (n,)}
    steps = [dict(alpha=0.1 * k, t=0.5 * k, iterations=2, cutbacks=0, rows=[], reaction={"z_max": np.ones(3)},
                  prescribed={"z_max": np.zeros(3)}, **{key: rng.standard_normal(shape) for key, shape in shapes.items()})
             for k in range(3)]
    ref = {key: np.stack([s[key] for s in steps]) for key in shapes}
    res = Results.from_steps(model, steps, n_steps=2)
    for key in shapes:
        np.testing.assert_array_equal(getattr(res, key), ref[key])
        assert all(s[key] is None for s in steps)


def test_step_store_gives_back_the_steps_it_took(tmp_path):
    """StepStore: rows appended one step at a time read back as numpy.stack of them; the file is a
    hidden temporary beside the results file, gone after remove()."""
    from pixmuscle.io.results import StepStore

    rng = np.random.default_rng(1)
    steps = [{"u": rng.standard_normal((7, 3)), "max_principal": rng.standard_normal(7)} for _ in range(4)]
    store = StepStore(tmp_path / "results.h5")
    assert store.path.parent == tmp_path and store.path.name.startswith(".results.h5.")
    for fields in steps:
        store.append(fields)
    for key in ("u", "max_principal"):
        np.testing.assert_array_equal(store.read(key), np.stack([f[key] for f in steps]))
    store.remove()
    assert not store.path.exists()
    # a store left by a process that has gone (a killed solve) goes with the next write of the results
    code = f"from pixmuscle.io.results import StepStore; print(StepStore({str(tmp_path / 'results.h5')!r}).path)"
    left = Path(subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True).stdout.strip())
    assert left.exists()
    write_bytes_atomic(tmp_path / "results.h5", b"results")
    assert not left.exists()


def test_run_solve_writes_results_schema(tmp_path):
    """End to end: model file → solve stage → results file readable by the report's reader."""
    from pixmuscle.stages.solve import run_solve

    model = mask_model(np.ones((3, 3, 5), bool), (0.2, 0.2, 0.3), tissue=1)
    mpath = tmp_path / "model.h5"
    save_model(mpath, model)
    cfg = {"steps": 2, "activation": {"from": 0.0, "to": 0.5},
           "boundary_conditions": [{"nodes": "z_min", "fix": ["x", "y", "z"]}, {"nodes": "z_max", "fix": ["x", "y", "z"]}]}
    out = run_solve(mpath, cfg, tmp_path / "results.h5", progress=False)
    res = load_results(out, lazy=False)
    n = model.n_nodes
    assert res.status == "complete"
    assert res.u.shape == (3, n, 3) and res.d.shape == (3, n, 3) and res.cauchy.shape == (3, n, 6)
    assert np.allclose(res.alpha, [0.0, 0.25, 0.5]) and np.allclose(res.load_factor, [0, 0.5, 1])
    # isometric activation: global equilibrium, and the ends pull (tension) on the supports
    assert np.allclose(res.reaction["z_max"][-1], -res.reaction["z_min"][-1], atol=1e-6 * abs(res.reaction["z_max"][-1]).max())
    assert res.force("z_max")[-1] > 0
    # max principal stress is the largest eigenvalue of the stored Cauchy tensor
    s = res.cauchy[-1]
    T = np.array([[s[:, 0], s[:, 3], s[:, 5]], [s[:, 3], s[:, 1], s[:, 4]], [s[:, 5], s[:, 4], s[:, 2]]]).transpose(2, 0, 1)
    assert np.allclose(res.max_principal[-1], np.linalg.eigvalsh(T)[:, -1])
    # the stage's steps went through a step store (a file, removed): the same fields as a solve in memory
    assert not list(tmp_path.glob(".*.partial"))
    mem = solve(model, parse_section(SolveConfig, cfg, "solve"))
    for key in ("u", "d", "cauchy", "max_principal"):
        np.testing.assert_array_equal(getattr(res, key), getattr(mem, key))
    assert res.constraint_gap == mem.constraint_gap
    lazy = load_results(out)
    assert lazy.n_states == 3 and set(lazy.reaction) == {"z_min", "z_max"}
    np.testing.assert_array_equal(lazy.u[2], res.u[2])
    np.testing.assert_array_equal(lazy.step(1).cauchy, res.cauchy[1])
    import h5py

    with h5py.File(out) as f:
        assert f["steps/u"].attrs["units"] == "cm" and f["steps/reaction/z_max"].attrs["units"] == "N"
        assert f["steps/cauchy"].attrs["units"] == "N/cm^2" and "nodes/X" in f and "sets/z_min" in f
        assert "tension" in f.attrs["sign_convention"]


def _spd_system(n=300, seed=0):
    rng = np.random.default_rng(seed)
    X = rng.uniform(0, 1, (n // 3, 3))
    A = sp.random(n, n, density=0.02, random_state=seed)
    K = (A @ A.T + sp.eye(n) * 0.5).tocsr()
    return X, K, rng.standard_normal(n)


def test_nested_dissection_is_a_permutation_with_separators():
    from pixmuscle.mechanics.linsolve import nested_dissection

    ijk = np.argwhere(np.ones((20, 9, 6), bool))
    order = nested_dissection(ijk, (4, 4, 4), leaf=40)
    assert np.array_equal(np.sort(order), np.arange(len(ijk)))
    # the last block is the top separator: a slab 4 cells thick across the longest axis (x)
    top = ijk[order[-9 * 6 * 4:]]
    assert np.ptp(top[:, 0]) == 3 and np.ptp(top[:, 1]) == 8


def test_direct_solver_nested_dissection_and_pivoting_fallback():
    from pixmuscle.verify.mechanics import linear_stiffness

    model = mask_model(np.ones((6, 5, 7), bool), (0.1, 0.1, 0.2))
    K, _ = linear_stiffness(model, lam=100.0, mu=10.0)
    n = K.shape[0]
    rng = np.random.default_rng(0)
    r = rng.standard_normal(n)
    for shift in (1e-2, -3.0):  # SPD, then indefinite (a diagonal shift inside the spectrum)
        Ks = (K + shift * sp.eye(n)).tocsr()
        s = make_solver("direct", model.X, ijk=model.ijk)
        s.factorize(Ks)
        x = s.solve(r)
        assert np.linalg.norm(Ks @ x - r) < 1e-8 * np.linalg.norm(r)


def test_direct_solver_reuse_is_exact():
    X, K, r = _spd_system()
    s = DirectSolver(reuse=True, rtol=1e-12)
    s.factorize(K)
    x = s.solve(r)
    assert np.linalg.norm(K @ x - r) < 1e-10 * np.linalg.norm(r)
    K2 = (K + sp.diags(np.linspace(0.0, 0.05, K.shape[0]))).tocsr()
    s.factorize(K2)
    x2 = s.solve(r)
    assert np.linalg.norm(K2 @ x2 - r) < 1e-10 * np.linalg.norm(r)
    assert s.info["factorizations"] == 1 and s.info["iterations"] > 1  # GMRES with the kept factors
    assert make_solver("auto", X).name == "direct"


def _mixed_leg_like_model():
    """Irregular voxel body: muscle core with oblique fibres, connective-tissue rim, a notch and a
    one-voxel strand (enlarged RK supports), so every term and code path is exercised."""
    mask = np.ones((7, 6, 5), bool)
    mask[5:, 4:, :] = False  # notch
    mask[0, 0, 2:] = False
    mask = np.pad(mask, ((0, 2), (0, 0), (0, 0)))
    mask[7:9, 2, :] = True  # one-voxel strand sticking out in x
    model = mask_model(mask, (0.15, 0.15, 0.4), tissue=2)
    tissue = np.asarray(model.tissue).copy()
    core = np.all((model.ijk >= [1, 1, 0]) & (model.ijk <= [5, 4, 4]), axis=1)
    tissue[core] = 1
    fiber = np.tile(np.array([np.sin(0.4), 0.0, np.cos(0.4)]), (model.n_nodes, 1))
    return dataclasses.replace(model, tissue=tissue, fiber=fiber)


def _system(model, **solve_kw):
    from pixmuscle.mechanics.solve import build_system

    bcs = [{"nodes": "z_min", "fix": ["x", "y", "z"]}, {"nodes": "z_max", "fix": ["x", "y", "z"]}]
    return build_system(model, _cfg(boundary_conditions=bcs, **solve_kw))[0]


def test_matrix_free_tangent_is_the_derivative_of_the_residual():
    """K v from the matrix-free operator against central differences of the residual (independent)."""
    model = _mixed_leg_like_model()
    system = _system(model)
    rng = np.random.default_rng(1)
    d = 0.01 * rng.standard_normal((model.n_nodes, 3))
    state = system.evaluate(d, 0.5, 0.6)
    op = system.tangent_operator(state)
    v = rng.standard_normal(3 * model.n_nodes)
    eps = 1e-6
    rp = system.evaluate(d + eps * v.reshape(-1, 3), 0.5, 0.6).r.ravel()
    rm = system.evaluate(d - eps * v.reshape(-1, 3), 0.5, 0.6).r.ravel()
    fd = -(rp - rm) / (2 * eps)
    Kv = op @ v
    assert np.linalg.norm(Kv - fd) < 1e-6 * np.linalg.norm(fd)
    # and the assembled tangent is the same operator to round-off
    assert np.linalg.norm(system.stiffness(state) @ v - Kv) < 1e-12 * np.linalg.norm(Kv)


def test_filtered_preconditioner_matrix_is_near_positive_and_carries_the_nodal_volumetric_term():
    """The stand-in couples nodes at most 2 voxels apart (every pair of a node with an enlarged RK
    support), is positive definite, and approximates the tangent; with the projected volumetric
    energy it carries each node's own volumetric stiffness, i.e. at d = 0 it is the nodal energy's."""
    model = _mixed_leg_like_model()
    nodal = _system(model, volumetric={"method": "nodal"})
    state = nodal.evaluate(np.zeros((model.n_nodes, 3)), 0.0, 0.0)
    K = sp.bsr_matrix(nodal.stiffness(state), blocksize=(3, 3))  # at α = 0 every node tangent is positive
    Kn = sp.bsr_matrix(nodal.preconditioner_matrix(state, reach=2), blocksize=(3, 3))
    system = _system(model)  # projected (default)
    Kf = sp.bsr_matrix(system.preconditioner_matrix(system.evaluate(np.zeros((model.n_nodes, 3)), 0.0, 0.0), reach=2),
                       blocksize=(3, 3))
    assert abs(Kf - Kn).max() < 1e-12 * abs(K).max()
    n = model.n_nodes
    wide = np.any(system.scni.support > system.scni.support.min(axis=0) * (1 + 1e-9), axis=1)
    assert wide.any()  # the strand's nodes have enlarged supports
    rows = np.repeat(np.arange(n), np.diff(Kf.indptr))
    far = np.abs(model.ijk[rows] - model.ijk[Kf.indices]).max(axis=1) > 2
    assert far.any() and not np.any(far & ~wide[rows] & ~wide[Kf.indices])
    assert Kf.nnz < K.nnz
    assert np.linalg.eigvalsh(Kf.toarray())[0] > 0.0
    rng = np.random.default_rng(1)  # smooth fields: quadratic in the node positions
    X = np.asarray(model.X)
    for _ in range(3):
        c = rng.standard_normal((10, 3))
        v = (np.column_stack([np.ones(n), X, X**2, X[:, [0]] * X[:, [1]], X[:, [1]] * X[:, [2]], X[:, [0]] * X[:, [2]]])
             @ c).ravel()
        assert abs(v @ (Kf @ v) / (v @ (K @ v)) - 1.0) < 0.05


def test_voxel_aggregates_group_boxes():
    ijk = np.array([[0, 0, 0], [1, 2, 0], [3, 0, 0], [2, 2, 1], [4, 1, 0]])
    A = voxel_aggregates(ijk, (3, 3, 1)).toarray()
    assert A.shape == (5, 3) and np.all(A.sum(axis=1) == 1)
    assert np.array_equal(A[0], A[1]) and not np.array_equal(A[0], A[3]) and np.array_equal(A[2], A[4])


def test_every_backend_gives_the_direct_solution():
    """Every backend at Newton 10⁻⁸ reproduces the SuperLU solution of an activation sweep at 10⁻¹⁰,
    forces to 1e-6 relative and displacement fields to 1e-4 of the largest |u| at every
    load step: cg_amg and mixed_amg with pyamg and (where petsc4py is installed) hypre BoomerAMG,
    PARDISO (when MKL is installed), PARDISO and SuperLU with factor reuse (CG on the matrix-free
    tangent) and any other registered backend; the shipped defaults (Newton
    10⁻⁴) give the forces to 1e-5."""
    from pixmuscle.mechanics.linsolve import BACKENDS

    model = _mixed_leg_like_model()
    bcs = [{"nodes": "z_min", "fix": ["x", "y", "z"]}, {"nodes": "z_max", "fix": ["x", "y", "z"]}]
    tight = {"residual_tol": 1e-10, "energy_tol": 1e-18}
    variants = {"superlu": {"backend": "direct", "engine": "superlu", "reuse_factorization": False},
                "superlu_reuse": {"backend": "direct", "engine": "superlu"},
                "cg_amg": {"backend": "cg_amg", "amg": "pyamg"},
                "mixed_amg_pyamg": {"backend": "mixed_amg", "amg": "pyamg"}}
    from pixmuscle.mechanics.linsolve import amg_processes, petsc

    if multigrid.hypre_available():
        variants["cg_amg_hypre"] = {"backend": "cg_amg", "amg": "hypre"}
        variants["mixed_amg_hypre"] = {"backend": "mixed_amg", "amg": "hypre"}
        if amg_processes.available():  # BoomerAMG on this process and a spawned worker
            variants["mixed_amg_hypre_2p"] = {"backend": "mixed_amg", "amg": "hypre", "amg_processes": 2}
    if pardiso.available():
        variants["pardiso"] = {"backend": "direct", "engine": "pardiso", "reuse_factorization": False}
        variants["pardiso_reuse"] = {"backend": "direct", "engine": "pardiso", "reuse_factorization": True}

    for name in sorted(set(BACKENDS.names()) - {"direct", "cg_amg"}):  # auto, optional and test-defined backends
        if name.startswith("petsc") and not petsc.available():
            continue  # petsc4py not installed here (tests/test_petsc.py says so)
        variants[name] = {"backend": name}
    out = {}
    # the backends at a tight Newton tolerance (what differs is the linear solver); "defaults" is the
    # shipped configuration, Newton at 1e-4: within 1e-5 of the tight forces
    variants["defaults"] = {}
    for name, solver in variants.items():
        newton = tight if name == "superlu" else {"residual_tol": 1e-8, "energy_tol": 1e-14}
        keys = {"solver": solver, "newton": newton} if solver else {}
        res = solve(model, _cfg(steps=3, activation={"from": 0.0, "to": 0.95}, boundary_conditions=bcs, **keys))
        out[name] = res
        assert res.status == "complete"
    ref = out["superlu"]
    f_d = ref.force("z_max")
    u_d = np.asarray(ref.u)
    umax = np.abs(u_d).max()
    assert abs(f_d[-1]) > 1.0 and umax > 1e-3
    for name in variants:
        rtol = 1e-5 if name == "defaults" else 1e-6
        assert np.allclose(out[name].force("z_max"), f_d, rtol=rtol, atol=1e-9 * abs(f_d).max()), name
        assert np.abs(np.asarray(out[name].u) - u_d).max() <= 1e-4 * umax, name
    if "pardiso_reuse" in out:
        info = out["pardiso_reuse"].info
        assert info["linear_engine"] == "pardiso" and info["krylov_iterations"] > 0
        assert info["factorizations"] < out["pardiso"].info["factorizations"]
    assert out["cg_amg"].info["linear_solver"] == "cg_amg" and out["cg_amg"].info["preconditioner_builds"] >= 1


def test_cg_amg_rebuilds_when_stale_iterations_cost_a_build():
    """Ski-rental rule in iterations: the first solve after a build of more than one iteration per
    decade sets the rate; iterations beyond it are charged; the hierarchy is rebuilt once they
    exceed ``rebuild_cost``, and not before; a single solve that exceeds it is stopped, the
    hierarchy rebuilt and the solve finished with the new one."""
    from pixmuscle.mechanics.linsolve import KrylovAMGSolver

    model = _mixed_leg_like_model()
    system = _system(model)
    state = system.evaluate(np.zeros((model.n_nodes, 3)), 1.0, 0.5)
    r = state.r.ravel()
    K = system.tangent_operator(state)
    s = KrylovAMGSolver(model.X, model.ijk, rebuild_cost=10**6)
    s.prepare(system, state)
    s.solve(np.zeros_like(r), rtol=1e-8)  # solved without an iteration: shows no rate (it was taken as 1 per decade)
    assert s.info["iterations"] == 0 and s.policy.rate0 is None
    s.solve(r, rtol=1e-8)
    its = s.info["iterations"]
    assert s.info["preconditioner_builds"] == 1 and s.policy.rate0 == pytest.approx(its / 8)
    s.policy.rate0 = 0.1  # pretend the hierarchy was much better right after its build: every solve now costs extra
    s.solve(r, rtol=1e-8)
    s.prepare(system, state)
    assert s.info["preconditioner_builds"] == 1 and s.policy.excess == pytest.approx(its - 0.8)  # a build costs far more
    s.policy.rebuild_cost = its - 1  # the next solve's extra iterations exceed a build: rebuilt at the next prepare
    s.policy.excess = 0.0
    x = s.solve(r, rtol=1e-8)
    assert s.info["preconditioner_builds"] == 1 and s.policy.stale
    s.prepare(system, state)
    assert s.info["preconditioner_builds"] == 2 and not s.policy.stale
    assert np.linalg.norm(K @ x - r) <= 1e-8 * np.linalg.norm(r) * 1.01
    # within a solve: 0.8 predicted + its/2 of budget, then a rebuild, and CG goes on from its
    # iterate with the new hierarchy, well short of a full solve; the next solve sets the new rate
    s.solve(r, rtol=1e-8)  # fresh: sets the rate
    s.policy.rate0, s.policy.rebuild_cost = 0.1, its // 2
    stale = its // 2 + 1
    s.prepare(system, state)  # keeps the hierarchy
    x = s.solve(r, rtol=1e-8)
    assert s.info["preconditioner_builds"] == 3 and stale < s.info["iterations"] < stale + 0.8 * its
    assert s.policy.rate0 is None
    assert np.linalg.norm(K @ x - r) <= 1e-8 * np.linalg.norm(r) * 1.01


def test_a_fresh_hierarchy_gives_up_on_a_system_far_harder_than_the_earlier_ones():
    """Right after a build, a solve may take ``give_up`` × the last measured rate × decades +
    ``rebuild_cost`` iterations; beyond, it fails (SolverGaveUp: Newton then cuts the increment
    back) instead of running to ``maxiter``, and the next system gets a new hierarchy."""
    from pixmuscle.errors import SolverGaveUp
    from pixmuscle.mechanics.linsolve import KrylovAMGSolver

    model = _mixed_leg_like_model()
    system = _system(model)
    state = system.evaluate(np.zeros((model.n_nodes, 3)), 1.0, 0.5)
    r = state.r.ravel()
    s = KrylovAMGSolver(model.X, model.ijk, give_up=4.0, rebuild_cost=1)
    s.prepare(system, state)
    s.solve(r, rtol=1e-8)  # no rate known yet: up to maxiter
    its = s.info["iterations"]
    s.policy.stale = True
    s.prepare(system, state)  # a fresh hierarchy of the same tangent: within 4 × the rate
    s.solve(r, rtol=1e-8)
    assert s.info["preconditioner_builds"] == 2 and s.info["iterations"] == its
    s.policy.give_up, s.policy.stale = 0.1, True  # now the same system counts as ten times harder than allowed
    s.prepare(system, state)
    with pytest.raises(SolverGaveUp, match="gave up after .* far more than the earlier ones"):
        s.solve(r, rtol=1e-8)
    assert s.info["iterations"] == int(np.ceil(0.1 * its + 1))
    s.prepare(system, state)  # Newton leaves the state the hierarchy was built for: a new one
    assert s.info["preconditioner_builds"] == 4


@pytest.mark.parametrize("amg", ["pyamg", pytest.param("hypre", marks=needs_hypre)])
def test_cg_amg_solves_an_indefinite_tangent_by_fgmres(amg):
    """Negative curvature stops CG; the same system is then solved by FGMRES with the same AMG
    preconditioner, to the requested residual (checked against a dense solve). The shifted system
    (591 unknowns, three negative eigenvalues) is far from what either multigrid is built for, so
    FGMRES keeps a full basis (with BoomerAMG and restarts at 100 it stalls)."""
    from pixmuscle.mechanics.linsolve import KrylovAMGSolver

    model = _mixed_leg_like_model()
    # the condensed tangent of 1 × 1 × 3 patches, whose nodal AMG stand-in is close enough for
    # restarted FGMRES on the shifted (indefinite) system
    system = _system(model, volumetric={"patch": [1, 1, 3], "held": "own"})
    state = system.evaluate(np.zeros((model.n_nodes, 3)), 1.0, 0.5)
    K = system.tangent_operator(state) @ np.eye(3 * model.n_nodes)
    lam = np.linalg.eigvalsh(0.5 * (K + K.T))
    shift = 0.5 * (lam[2] + lam[3])  # three negative eigenvalues, none near zero
    A = K - shift * np.eye(K.shape[0])
    s = KrylovAMGSolver(model.X, model.ijk, amg=amg, restart=600)
    s.prepare(system, state)
    s._A = spla.aslinearoperator(A)
    b = np.random.default_rng(3).standard_normal(K.shape[0])
    x = s.solve(b, rtol=1e-9)
    assert s.info["indefinite_solves"] == 1
    assert np.linalg.norm(A @ x - b) <= 1e-9 * np.linalg.norm(b) * 1.01
    assert np.allclose(x, np.linalg.solve(A, b), rtol=1e-6, atol=1e-8 * np.abs(np.linalg.solve(A, b)).max())


@pytest.mark.skipif(not pardiso.available(), reason="MKL PARDISO not installed")
def test_pardiso_ldlt_matches_scipy_and_counts_negative_eigenvalues():
    """PARDISO's solution equals SciPy's sparse LU solve; its inertia equals numpy's eigenvalue count;
    after its factors are released it refuses to solve, and a new factorisation on the kept
    analysis gives the same solution. The pattern keeps an int32 gather map and a digest of the block
    pattern (matched again, and not by another pattern); PARDISO reports the memory it holds. The
    values are let go after a factorisation without perturbed pivots (a solve reads them only to
    refine after those) and kept after one with them (a singular K), whose solves then refine."""
    from pixmuscle.mechanics.pardiso import PardisoError, PardisoLDLT, SymmetricPattern
    from pixmuscle.verify.mechanics import linear_stiffness

    model = mask_model(np.ones((4, 3, 3), bool), (0.1, 0.1, 0.2))
    K, _ = linear_stiffness(model, lam=100.0, mu=10.0)
    n = K.shape[0]
    r = np.random.default_rng(1).standard_normal((n, 2))
    ev = np.linalg.eigvalsh(K.toarray())
    k = n // 3
    for shift in (1e-2, -0.5 * (ev[k] + ev[k + 1])):  # SPD, then k + 1 negative eigenvalues
        Ks = sp.bsr_matrix((K + shift * sp.eye(n)).tocsr(), blocksize=(3, 3))
        pat = SymmetricPattern(Ks)
        assert np.array_equal(pat.values(Ks), sp.triu(Ks.tocsr()).tocsr().sorted_indices().data)
        assert pat.take.dtype == np.int32 and pat.matches(Ks.copy())
        assert not pat.matches(sp.bsr_matrix(sp.identity(n).tocsr(), blocksize=(3, 3)))
        f = PardisoLDLT(pat)
        f.factorize(pat.values(Ks))
        assert f.info["memory_kB"] > 0 and f.info["peak_memory_kB"] >= f.info["memory_kB"]
        assert f.info["perturbed_pivots"] == 0 and f._data[0].size == 1
        x = f.solve(r)
        x_ref = spla.spsolve(Ks.tocsc(), r)
        assert np.allclose(x, x_ref, rtol=1e-8, atol=1e-10 * np.abs(x_ref).max())
        neg = int(np.sum(ev + shift < 0))
        assert f.info["inertia"] == (n - neg, neg)
        f.release_factors()
        with pytest.raises(PardisoError, match="before a successful factorisation"):
            f.solve(r)
        f.factorize(pat.values(Ks))
        assert np.allclose(f.solve(r), x, rtol=1e-12, atol=1e-14 * np.abs(x).max())
        f.free()
    Kb = sp.bsr_matrix(K.tocsr(), blocksize=(3, 3))  # free rigid-body motions: zero pivots, perturbed
    pat = SymmetricPattern(Kb)
    f = PardisoLDLT(pat)
    f.factorize(pat.values(Kb))
    assert f.info["perturbed_pivots"] > 0 and f._data[0].size == pat.indices.size
    b = K @ r[:, 0]  # consistent: K x = b has the solutions x = r + rigid-body motions
    assert np.linalg.norm(K @ f.solve(b) - b) <= 1e-6 * np.linalg.norm(b)
    f.free()


@pytest.mark.skipif(not pardiso.available(), reason="MKL PARDISO not installed")
def test_component_factors_share_one_pardiso_analysis_and_solve_each_block_exactly():
    """The three component blocks of a 3 × 3-block matrix factorised by PARDISO under one shared
    analysis (maxfct = 3) solve as SciPy's LU of each block does, before and after their factors are
    released and made again, and the handle holds less than three analyses of the same blocks."""
    from pixmuscle.mechanics.linsolve.factorization import ComponentFactors, PardisoFactor
    from pixmuscle.verify.mechanics import linear_stiffness

    model = mask_model(np.ones((5, 4, 4), bool), (0.1, 0.1, 0.2))
    K, _ = linear_stiffness(model, lam=100.0, mu=10.0)
    K = sp.bsr_matrix((K + 5.0 * sp.eye(K.shape[0])).tocsr(), blocksize=(3, 3))  # well-conditioned blocks
    K.data[:, 1, 1] *= 3.0  # three different component blocks
    K.data[:, 2, 2] *= -0.5  # one of them negative definite
    r = np.random.default_rng(5).standard_normal(K.shape[0])
    ref = np.empty_like(r)
    Kc = K.tocsr()
    for j in range(3):
        ref[j::3] = spla.spsolve(Kc[j::3, j::3].tocsc(), r[j::3])
    shared = ComponentFactors(PardisoFactor)
    apart = ComponentFactors(PardisoFactor)
    apart.parts = [PardisoFactor(block=1) for _ in range(3)]
    assert all(p._handle()[1] is None for p in shared.parts) and shared.parts[2]._owner is shared.parts[0]
    for f in (shared, apart):
        f.factorize(K)
        assert np.allclose(f.solve(r), ref, rtol=1e-9, atol=1e-12 * np.abs(ref).max())
    assert len({id(p._handle()[1]) for p in shared.parts}) == 1
    assert not shared.definite and shared.info["negative_pivots"] == K.shape[0] // 3
    assert shared.info["memory_kB"] < apart.info["memory_kB"]
    shared.release()
    shared.factorize(lambda: K)
    assert np.allclose(shared.solve(r), ref, rtol=1e-9, atol=1e-12 * np.abs(ref).max())
    with pytest.raises(RuntimeError, match="before its first factorisation"):
        shared.parts[0].sibling()


@pytest.mark.skipif(not pardiso.available(), reason="MKL PARDISO not installed")
def test_pardiso_single_precision_is_refined_to_the_double_solution():
    """Single-precision factors (iparm[27]) refined in double precision solve as the double-precision
    factors do (one or several right-hand sides, definite or not), with the same inertia and less
    memory held by PARDISO."""
    from pixmuscle.mechanics.pardiso import PardisoLDLT, SymmetricPattern
    from pixmuscle.verify.mechanics import linear_stiffness

    model = mask_model(np.ones((4, 3, 3), bool), (0.1, 0.1, 0.2))
    K, _ = linear_stiffness(model, lam=100.0, mu=10.0)
    n = K.shape[0]
    r = np.random.default_rng(2).standard_normal((n, 2))
    ev = np.linalg.eigvalsh(K.toarray())
    for shift in (1e-2, -0.5 * (ev[5] + ev[6])):
        Ks = sp.bsr_matrix((K + shift * sp.eye(n)).tocsr(), blocksize=(3, 3))
        pat = SymmetricPattern(Ks)
        f64, f32 = PardisoLDLT(pat), PardisoLDLT(pat, single=True)
        for f in (f64, f32):
            f.factorize(pat.values(Ks))
        assert f32.info["inertia"] == f64.info["inertia"]
        assert f32.info["memory_kB"] < f64.info["memory_kB"]
        for b in (r[:, 0], r):
            x = f64.solve(b)
            assert np.allclose(f32.solve(b), x, rtol=1e-10, atol=1e-11 * np.abs(x).max())
        f32.release_factors()
        f32.factorize(pat.values(Ks))
        assert np.allclose(f32.solve(r[:, 0]), f64.solve(r[:, 0]), rtol=1e-10, atol=1e-11 * np.abs(x).max())
        f64.free()
        f32.free()


def test_forcing_term_follows_eisenstat_walker_with_safeguards():
    """η_k = min(1e-2, max(0.9 (‖r_k‖/‖r_k−1‖)², 0.1 target/‖r_k‖)), η_max at a step's first iteration."""
    from pixmuscle.mechanics.newton import forcing_term

    assert forcing_term(5.0, None, 1e-8) == 1e-2                       # first iteration of a step
    assert forcing_term(1e-3, 1.0, 1e-12) == pytest.approx(0.9e-6)      # quadratic phase: (1e-3)² · 0.9
    assert forcing_term(1e-6, 1e-3, 1e-9) == pytest.approx(0.1 * 1e-9 / 1e-6)  # last iteration: safeguard
    assert forcing_term(0.5, 0.6, 1e-8) == 1e-2                         # slow convergence: capped
    assert forcing_term(0.5, 0.6, 1e-8, eta_max=0.1) == 0.1             # 0.9 (0.5/0.6)² = 0.63: capped
    assert forcing_term(0.1, 1.0, 1e-8, eta_max=0.1) == pytest.approx(0.009)  # below the cap: 0.9 (0.1)²
    assert forcing_term(5.0, None, 1e-8, eta_max=0.1) == 0.1

"""Mixed displacement–pressure solves of the projected-energy tangent (pixmuscle.mechanics.linsolve.mixed).

Independent references: central finite differences of the patch dilatations (the rows of G), the
adjoint identity qᵀ(G x) = (Gᵀ q)ᵀ x, SciPy's sparse direct solve of the assembled condensed tangent,
and the Sylvester/Haynsworth inertia count of the benchmark against a dense eigen-decomposition.
"""

import dataclasses

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from pixmuscle.errors import SolverError
from pixmuscle.mechanics import pardiso
from pixmuscle.mechanics.linsolve import fgmres, make_solver, multigrid, petsc
from pixmuscle.mechanics.pressure import PatchDivergence
from pixmuscle.mechanics.solve import build_system
from pixmuscle.verify.mechanics import _cfg, mask_model

CLAMPED = [{"nodes": "z_min", "fix": ["x", "y", "z"]}, {"nodes": "z_max", "fix": ["x", "y", "z"]}]


def _body():
    """Irregular voxel body, muscle core with oblique fibres in connective tissue, anisotropic voxels."""
    mask = np.ones((6, 6, 7), bool)
    mask[4:, 4:, :] = False
    model = mask_model(mask, (0.15, 0.15, 0.4), tissue=2)
    tissue = np.asarray(model.tissue).copy()
    core = np.all((model.ijk >= [1, 1, 0]) & (model.ijk <= [4, 4, 6]), axis=1)
    tissue[core] = 1
    fiber = np.tile(np.array([np.sin(0.4), 0.0, np.cos(0.4)]), (model.n_nodes, 1))
    return dataclasses.replace(model, tissue=tissue, fiber=fiber)


def _system(patch=(2, 2, 3), held="own", penalty=None, **materials):
    model = _body()
    cfg = _cfg(boundary_conditions=CLAMPED, volumetric={"method": "projected", "patch": list(patch), "held": held},
               materials=materials, **({} if penalty is None else {"penalty": penalty}))
    return model, build_system(model, cfg)[0]


def test_patch_divergence_is_the_derivative_of_the_patch_dilatation():
    model, system = _system()
    rng = np.random.default_rng(0)
    d = 0.02 * rng.standard_normal((model.n_nodes, 3))
    state = system.evaluate(d, 0.5, 0.4)
    vol = system.volumetric
    G = PatchDivergence(system.tangent_operator(state).main.B, system.tangent_operator(state).main.BT,
                        state.vol.a, vol.Q)
    x = rng.standard_normal((model.n_nodes, 3))
    eps = 1e-6
    theta = [vol.Q @ np.linalg.det(system.scni.deformation_gradient(d + s * eps * x)) for s in (1, -1)]
    fd = (theta[0] - theta[1]) / (2 * eps)
    assert np.allclose(G @ x.ravel(), fd, rtol=0, atol=1e-7 * np.abs(fd).max())
    q = rng.standard_normal(vol.n_patches)
    assert np.isclose(q @ (G @ x.ravel()), G.T(q) @ x.ravel(), rtol=1e-12)
    assert np.allclose(G.sparse() @ x.ravel(), G @ x.ravel(), rtol=0, atol=1e-12 * np.abs(fd).max())


def test_mixed_operator_shares_its_gradient_products():
    """The mixed operator's fused product (one gradient and one transposed-gradient product for K_d x,
    w Gᵀ q and w G x) equals the blocks applied one by one, with held single-node patches in K_d."""
    from pixmuscle.mechanics.linsolve.mixed_method import MixedOperator

    model, system = _system(held="own", penalty={"at": "nodes", "beta": 3.0e4})
    rng = np.random.default_rng(3)
    state = system.evaluate(0.02 * rng.standard_normal((model.n_nodes, 3)), 0.5, 0.4)
    vol = system.volumetric
    assert vol.held.any()
    full = system.tangent_operator(state)
    Kd = full.with_volumetric((vol.restricted(vol.held), state.vol))
    free = np.flatnonzero(~vol.held)
    G = PatchDivergence(full.main.B, full.main.BT, state.vol.a, vol.Q[free])
    D = vol.vp[free] * vol.kbar[free]
    w = system.pressure_weight
    A = MixedOperator(system.displacement_operator(state, tangent=full), system.patch_divergence(state, free),
                      w * w / D, w)
    x, q = rng.standard_normal(3 * model.n_nodes), rng.standard_normal(free.size)
    ref = np.concatenate([Kd @ x + w * G.T(q), w * (G @ x) - w * w / D * q])
    assert np.allclose(A @ np.concatenate([x, q]), ref, rtol=0, atol=1e-12 * np.abs(ref).max())


def test_fgmres_solves_a_nonsymmetric_system_with_a_changing_preconditioner():
    rng = np.random.default_rng(1)
    A = np.eye(80) * 4 + rng.standard_normal((80, 80)) / 8
    b = rng.standard_normal(80)
    calls = []

    class Jacobi:  # a preconditioner that changes from call to call (FGMRES allows it)
        def __matmul__(self, v):
            calls.append(1)
            return v / (np.diag(A) * (1.0 + 0.1 * (len(calls) % 3)))

    x, its, status = fgmres(A, b, Jacobi(), 1e-10, 200, restart=15)
    assert status == "converged" and its > 15  # went through restarts
    assert np.linalg.norm(A @ x - b) <= 1e-10 * np.linalg.norm(b)


def test_gmres_with_a_fixed_preconditioner_keeps_no_preconditioned_basis_and_takes_the_same_steps():
    """With a fixed preconditioner (a matrix here) ``flexible=False`` rebuilds the update as M (V y)
    instead of keeping Z = M V: the same iterations as flexible GMRES through restarts, the same
    solution to round-off, and the residual of ``numpy.linalg.solve``'s solution; a ``check`` sees
    the same iterates either way. M is applied once more per restart and per check."""
    rng = np.random.default_rng(4)
    n = 150
    A = np.diag(np.linspace(1.0, 80.0, n)) + rng.standard_normal((n, n)) / 6
    M = np.linalg.inv(A + rng.standard_normal((n, n)) / 3)  # a fixed, inexact inverse
    b = rng.standard_normal(n)

    class Counted:
        calls = 0

        def __matmul__(self, v):
            Counted.calls += 1
            return M @ v

    seen = {True: [], False: []}
    out = {}
    for flexible in (True, False):
        Counted.calls = 0

        def check(x, flexible=flexible):
            seen[flexible].append(x.copy())
            return None if len(seen[flexible]) > 1 else 1e-11

        out[flexible] = (*fgmres(A, b, Counted(), 1e-9, 400, restart=8, check=check, flexible=flexible), Counted.calls)
    (xf, itf, sf, mf), (x, its, status, m) = out[True], out[False]
    assert sf == status == "converged" and its == itf and its > 8
    assert np.linalg.norm(x - xf) <= 1e-9 * np.linalg.norm(xf)
    assert np.linalg.norm(x - np.linalg.solve(A, b)) <= 1e-7 * np.linalg.norm(x)
    assert len(seen[False]) == len(seen[True]) == 2
    assert all(np.allclose(a, c, rtol=0, atol=1e-9 * np.abs(xf).max()) for a, c in zip(seen[True], seen[False], strict=True))
    assert mf == itf and m == its + -(-its // 8) + len(seen[False])


def test_fgmres_check_tightens_the_target_in_the_same_krylov_basis():
    """A caller whose stopping test is another norm of the residual (here: the last rows weighted
    10⁴ times, as the condensed residual of the mixed form weighs the pressure rows) gets an
    iterate that meets it, in one Krylov basis (no restart), where the plain target stops short."""
    rng = np.random.default_rng(2)
    n = 120
    A = np.diag(np.linspace(1.0, 50.0, n)) + rng.standard_normal((n, n)) / 10
    b = np.r_[rng.standard_normal(n - 20), np.zeros(20)]  # as the mixed right-hand side [r; 0]
    w = np.r_[np.ones(n - 20), 1e4 * np.ones(20)]

    def weighted(x):
        return np.linalg.norm(w * (b - A @ x)) / np.linalg.norm(b)

    targets = []

    def check(x):
        err = weighted(x)
        targets.append(np.linalg.norm(b - A @ x) / np.linalg.norm(b) * 0.5e-6 / err)
        return None if err <= 1e-6 else targets[-1]

    x0, its0, _ = fgmres(A, b, np.eye(n), 1e-6, 500, restart=500)
    assert weighted(x0) > 1e-6  # the plain target is not enough for the weighted test
    x, its, status = fgmres(A, b, np.eye(n), 1e-6, 500, restart=500, check=check)
    assert status == "converged" and weighted(x) <= 1e-6
    assert len(targets) >= 2 and its > its0 and its < n


@pytest.mark.parametrize("bulk_scale", [1.0, 100.0])
def test_mixed_solve_gives_the_condensed_newton_update(bulk_scale):
    """Δd of the mixed form equals the direct solution of the assembled condensed tangent K Δd = r
    (the first Newton system of a load step, α = 0.6), at the tissues' K/μ and 100 times more
    incompressible, in a number of iterations that does not grow with K/μ."""
    model, system = _system(muscle={"K": 5000.0 * bulk_scale}, connective_tissue={"K": 50000.0 * bulk_scale})
    state = system.evaluate(np.zeros((model.n_nodes, 3)), 0.5, 0.6)
    solver = make_solver("mixed_amg", model.X, ijk=model.ijk, rtol=1e-10)
    solver.prepare(system, state)
    r = state.r.ravel()
    x = solver.solve(r, rtol=1e-8)
    K = system.stiffness(state).tocsc()
    ref = spla.spsolve(K, r)
    assert np.linalg.norm(K @ x - r) <= 1e-8 * np.linalg.norm(r)
    assert np.linalg.norm(x - ref) <= 1e-6 * np.linalg.norm(ref)
    assert 0 < solver.info["iterations"] < 100


def test_mixed_solve_rebuilds_a_stale_preconditioner_within_the_solve():
    """A kept hierarchy whose iterations on a solve exceed its post-build rate by ``rebuild_cost`` is
    rebuilt there (AMG and probed Schur diagonal, from this system's tangent) and the solve goes on
    from the iterate reached: a first solve at α = 0.6 sets the rate, a second system, at a
    deformed state, then gets the budget, and its answer is the direct one. The continued solve
    needs fewer iterations of the new hierarchy than a solve from zero, and leaves the new rate to
    the next solve."""
    model, system = _system()
    s0 = system.evaluate(np.zeros((model.n_nodes, 3)), 0.5, 0.6)
    solver = make_solver("mixed_amg", model.X, ijk=model.ijk, rtol=1e-10, rebuild_cost=2)
    solver.prepare(system, s0)
    d = solver.solve(s0.r.ravel(), rtol=1e-8).reshape(-1, 3)
    rate = solver.policy.rate0
    assert solver.info["preconditioner_builds"] == 1 and rate > 1.0
    s1 = system.evaluate(d, 0.5, 0.6)
    solver.prepare(system, s1)
    solver.policy.rate0 = 0.1  # as if the kept hierarchy had been far better right after its build
    r = s1.r.ravel()
    x = solver.solve(r, rtol=1e-8)
    assert solver.info["preconditioner_builds"] == 2
    build_s = solver.statistics()["preconditioner_build_s"]  # each build's wall time, the probe's included
    assert len(build_s) == 2 and min(build_s) >= 0.0
    budget = int(np.ceil(0.1 * 8 + 2))
    continued = solver.info["iterations"] - budget
    assert continued > 0 and solver.policy.rate0 is None
    K = system.stiffness(s1).tocsc()
    assert np.linalg.norm(K @ x - r) <= 1e-8 * np.linalg.norm(r)
    x = solver.solve(r, rtol=1e-8)  # the same system from zero, with the same new hierarchy: sets its rate
    cold = solver.info["iterations"]
    assert continued < cold and solver.policy.rate0 == pytest.approx(cold / 8)
    assert np.linalg.norm(K @ x - r) <= 1e-8 * np.linalg.norm(r)


def test_a_released_solver_builds_afresh_and_gives_the_same_update():
    """release() drops the mixed operator, the hierarchy and the region factors (what the driver does
    after the last load step); a later prepare builds them again from the tangent, and the update
    equals the one before the release and the direct solution of the assembled condensed tangent."""
    model, system = _system()
    state = system.evaluate(np.zeros((model.n_nodes, 3)), 0.5, 0.6)
    solver = make_solver("mixed_amg", model.X, ijk=model.ijk, rtol=1e-10)
    solver.prepare(system, state)
    r = state.r.ravel()
    before = solver.solve(r, rtol=1e-9)
    solver.release()
    assert solver._M is None and solver._mixed is None
    assert all(part.C is None for part in solver._regions.parts)
    solver.prepare(system, state)
    assert solver.info["preconditioner_builds"] == 2
    after = solver.solve(r, rtol=1e-9)
    ref = spla.spsolve(system.stiffness(state).tocsc(), r)
    assert np.linalg.norm(after - before) <= 1e-7 * np.linalg.norm(ref)
    assert np.linalg.norm(after - ref) <= 1e-7 * np.linalg.norm(ref)


def test_a_finished_solve_lets_the_moduli_go_and_the_next_system_keeps_the_preconditioner():
    """finish() (the driver's call after each solve) drops the operator that reads the state's moduli,
    and release_moduli the moduli themselves; the hierarchy stays, and the next prepared system's
    update equals the direct solution of its assembled condensed tangent."""
    model, system = _system()
    s0 = system.evaluate(np.zeros((model.n_nodes, 3)), 0.5, 0.6)
    solver = make_solver("mixed_amg", model.X, ijk=model.ijk, rtol=1e-10)
    solver.prepare(system, s0)
    solver.solve(s0.r.ravel(), rtol=1e-9)
    hierarchy = solver._M
    solver.finish()
    system.release_moduli(s0)
    assert solver._A is None and solver._mixed is None and s0.A is None
    assert solver._M is hierarchy and solver.info["preconditioner_builds"] == 1
    next_system_keeps_the_preconditioner(solver, model, system)


def next_system_keeps_the_preconditioner(solver, model, system):
    """The next Newton system (a deformed state) prepared and solved after a finished one: no new
    preconditioner build, and the update equals SciPy's direct solve of its assembled tangent."""
    s1 = system.evaluate(np.full((model.n_nodes, 3), 1e-3), 0.5, 0.6)
    solver.prepare(system, s1)
    r = s1.r.ravel()
    x = solver.solve(r, rtol=1e-9)
    assert solver.info["preconditioner_builds"] == 1
    ref = spla.spsolve(system.stiffness(s1).tocsc(), r)
    assert np.linalg.norm(x - ref) <= 1e-7 * np.linalg.norm(ref)


def test_displacement_moduli_of_some_nodes_are_those_of_the_whole_model():
    """The moduli of K_d at a set of nodes, made without a whole-model array, equal V_L (A_L + K_L a_L⊗a_L
    at the held single-node patches' nodes) written out with the whole model's arrays, and leave the
    state's moduli as they were."""
    model, system = _system(held="own", penalty={"at": "nodes", "beta": 3.0e4})
    rng = np.random.default_rng(5)
    state = system.evaluate(0.02 * rng.standard_normal((model.n_nodes, 3)), 0.5, 0.4)
    vol = system.volumetric
    held = vol.held[vol.patch_of]
    assert held.any() and not held.all()
    A0 = state.A.copy()
    a = state.vol.a
    ref = state.A + np.where(held, vol.bulk, 0.0)[:, None, None, None, None] * np.einsum("nij,nkl->nijkl", a, a)
    ref = system.scni.volume[:, None, None] * ref.reshape(-1, 9, 9)
    cells = rng.permutation(model.n_nodes)[: model.n_nodes // 3]
    assert np.allclose(system.displacement_moduli(state), ref, rtol=1e-14, atol=0)
    assert np.allclose(system.displacement_moduli(state, cells), ref[cells], rtol=1e-14, atol=0)
    assert np.array_equal(state.A, A0)


def _carried_state():
    """A deformed state of the body with single held nodes (``held: own``), evaluated with a patch
    pressure that differs from K̄(θ − 1) at the free patches."""
    model, system = _system(held="own", penalty={"at": "nodes", "beta": 3.0e4})
    rng = np.random.default_rng(1)
    d = 0.02 * rng.standard_normal((model.n_nodes, 3))
    exact = system.evaluate(d, 0.5, 0.4)
    vol = system.volumetric
    assert vol.held.any() and not vol.held.all()
    p = exact.vol.pressure + 3.0 * rng.standard_normal(vol.n_patches)
    return model, system, exact, system.evaluate(d, 0.5, 0.4, pressure=p)


def test_mixed_residual_is_the_residual_of_the_energy_at_the_carried_pressure():
    """r − r_u is the gradient of φ(d) = Σ_p V_p (p_p (θ_p − 1) − K̄_p (θ_p − 1)²/2) over the free
    patches (the mixed energy at the fixed pressure p minus the condensed one), by central finite
    differences of θ; r_p = θ − 1 − p/K̄ there and 0 at held patches; at the pressure of d, r_u = r."""
    model, system, exact, state = _carried_state()
    vol = system.volumetric
    free = ~vol.held
    r_u, r_p = system.mixed_residual(state)
    assert np.array_equal(state.r, exact.r)
    r0, rp0 = system.mixed_residual(exact)
    assert np.array_equal(r0, exact.r) and not rp0.any()

    def phi(d):
        dth = vol.Q @ (np.linalg.det(system.scni.deformation_gradient(d)) - 1.0)
        return float(np.sum((vol.vp * (state.pressure * dth - 0.5 * vol.kbar * dth**2))[free]))

    x = np.random.default_rng(2).standard_normal(state.d.shape)

    def central(eps):
        return (phi(state.d + eps * x) - phi(state.d - eps * x)) / (2 * eps)

    fd = (4.0 * central(1e-6) - central(2e-6)) / 3.0  # Richardson: the K̄-scaled curvature is large
    assert np.vdot(x, exact.r - r_u) == pytest.approx(fd, rel=1e-6)
    assert np.allclose(r_p[free], (state.vol.dtheta - state.pressure / vol.kbar)[free], rtol=1e-14)
    assert not r_p[vol.held].any()


@pytest.mark.parametrize("backend", ["mixed_amg", "petsc_mixed"])
def test_solve_mixed_gives_the_update_of_newton_on_the_mixed_form(backend):
    """From a state with a carried pressure, the mixed solve's (Δd, Δp) is Newton's on the mixed form:
    Δd the direct solution of the condensed K Δd = r (the pressure rows eliminated), and the
    carried pressure plus Δp the linearised K̄(θ − 1 + g·Δd) at the free patches; the same with
    PETSc's field split (one rank; tests/test_petsc.py runs it under mpiexec)."""
    if backend == "petsc_mixed" and not petsc.available():
        pytest.skip("petsc4py is not installed (tests/test_petsc.py says so)")
    model, system, _, state = _carried_state()
    vol = system.volumetric
    free = ~vol.held
    # PETSc: an exact displacement split (its default GAMG cycle is slow on the single held nodes' K-scaled rows)
    extra = {"petsc_options": {"fieldsplit_u_pc_type": "lu"}} if backend == "petsc_mixed" else {}
    solver = make_solver(backend, model.X, ijk=model.ijk, rtol=1e-10, **extra)
    solver.prepare(system, state)
    r_u, r_p = system.mixed_residual(state)
    dd, dp = solver.solve_mixed(r_u.ravel(), r_p, rtol=1e-10)
    ref = spla.spsolve(system.stiffness(state).tocsc(), state.r.ravel())
    assert np.linalg.norm(dd - ref) <= 1e-7 * np.linalg.norm(ref)
    lin = system.linearised_pressure(state, ref.reshape(-1, 3))
    assert np.allclose((state.pressure + dp)[free], lin[free], rtol=0, atol=1e-6 * np.abs(lin).max())
    assert not dp[vol.held].any()


def _mixed_iterations(bulk_scale, held, region_solves=True):
    """FGMRES iterations of the mixed solve to 10⁻⁸ on the body clamped at its end nodes (nodes held
    by the penalty at the node), and the solution's error against the direct solve."""
    model, system = _system(held=held, penalty={"at": "nodes", "beta": 3.0e4},
                            muscle={"K": 5000.0 * bulk_scale}, connective_tissue={"K": 50000.0 * bulk_scale})
    state = system.evaluate(np.zeros((model.n_nodes, 3)), 0.5, 0.6)
    solver = make_solver("mixed_amg", model.X, ijk=model.ijk, rtol=1e-10, maxiter=3000, region_solves=region_solves)
    solver.prepare(system, state)
    r = state.r.ravel()
    x = solver.solve(r, rtol=1e-8)
    ref = spla.spsolve(system.stiffness(state).tocsc(), r)
    return solver.info["iterations"], np.linalg.norm(x - ref) / np.linalg.norm(ref), int(system.volumetric.held.sum())


def test_held_nodes_in_their_patches_keep_the_mixed_solve_robust_in_k():
    """With ``volumetric.held: patch`` the nodes held at the node join their ordinary patches, so the
    displacement block holds no K-scaled term and the iterations stay flat from the tissues' K/μ to
    100 times it. With single-node patches (``own``) their K-scaled terms sit in K_d: the iterations
    grow with K unless the region solves after the V-cycle take them."""
    its = {}
    for held, regions in (("patch", True), ("patch", False), ("own", True), ("own", False)):
        for scale in (1.0, 100.0):
            its[held, regions, scale], err, singles = _mixed_iterations(scale, held, regions)
            assert err <= 1e-6
            assert (singles == 0) == (held == "patch")
    for held, regions in (("patch", True), ("patch", False), ("own", True)):
        assert its[held, regions, 100.0] <= 1.5 * its[held, regions, 1.0]
    assert its["own", False, 100.0] > 1.5 * its["own", False, 1.0]


def test_region_solves_are_exact_on_their_regions_and_take_the_stiff_penalty():
    """The regions' rows of the displacement block applied matrix-free, and their diagonal blocks
    assembled on a pattern of their own, equal those of the assembled K_d; after a correction the
    residual vanishes on the last region (an exact solve there), and regions released (as before a
    rebuild) and updated again give the same correction with SuperLU and PARDISO (and PARDISO's
    single-precision factors, refined in double precision); with a stiff penalty
    (1000 times the default number: on this 224-node body the default one does not yet slow the
    V-cycle) the mixed solve needs far fewer iterations with the region solves than without (pyamg:
    39 against 83; BoomerAMG: 47 against none in 3,000)."""
    from pixmuscle.mechanics.linsolve.subdomains import RegionSolves, constraint_regions
    from pixmuscle.mechanics.rows import RowAssembler

    model, system = _system(held="patch", penalty={"factor": 1000.0})
    state = system.evaluate(np.zeros((model.n_nodes, 3)), 0.5, 0.6)
    regions = constraint_regions(system)
    assert len(regions) == 2 and all(r.size for r in regions)  # z_min and z_max
    solves = RegionSolves(system, regions, model.ijk, engine="superlu", coupling="full")
    solves.update(state)
    Kd = system.stiffness(state, pressure_free=True).tocsr()
    rng = np.random.default_rng(3)
    x = rng.standard_normal(Kd.shape[0])
    for part in solves.parts:
        assert np.abs(part.apply(x.reshape(-1, 3)).ravel() - (Kd @ x)[part.dofs]).max() <= 1e-12 * np.abs(Kd @ x).max()
        block = RowAssembler(system, part.nodes, square=True).block(state, pressure_free=True)
        assert abs(block - Kd[part.dofs][:, part.dofs]).max() <= 1e-12 * abs(Kd).max()
    # with held single-node patches, whose volumetric terms stay in K_d, and their own region
    model_own, system_own = _system(held="own", penalty={"at": "nodes", "beta": 3.0e4})
    state_own = system_own.evaluate(np.zeros((model_own.n_nodes, 3)), 0.5, 0.6)
    vol = system_own.volumetric
    own = RegionSolves(system_own, constraint_regions(system_own, vol.held[vol.patch_of]), model_own.ijk, engine="superlu",
                       coupling="full")
    own.update(state_own)
    Kd_own = system_own.stiffness(state_own, pressure_free=True).tocsr()
    y = Kd_own @ x
    assert len(own.parts) == 3 and vol.held.any()
    for part in own.parts:
        assert np.abs(part.apply(x.reshape(-1, 3)).ravel() - y[part.dofs]).max() <= 1e-12 * np.abs(y).max()
        block = RowAssembler(system_own, part.nodes, square=True).block(state_own, pressure_free=True)
        assert abs(block - Kd_own[part.dofs][:, part.dofs]).max() <= 1e-12 * abs(Kd_own).max()
    r = rng.standard_normal(Kd.shape[0])
    z = solves.correct(r, np.zeros_like(r))
    last = solves.parts[-1].dofs
    assert np.linalg.norm((r - Kd @ z)[last]) <= 1e-10 * np.linalg.norm(r[last])
    # released before a rebuild (moduli and factors) and updated again: the same correction
    engines = ["superlu"] + (["pardiso"] if pardiso.available() else [])
    for engine in engines:
        again = RegionSolves(system, regions, model.ijk, engine=engine, coupling="full")
        again.update(state)
        before = again.correct(r, np.zeros_like(r))
        again.release()
        assert all(part.C is None for part in again.parts)
        again.update(state)
        assert np.allclose(again.correct(r, np.zeros_like(r)), before, rtol=1e-12, atol=1e-14 * np.abs(z).max()), engine
        assert np.allclose(before, z, rtol=1e-6, atol=1e-9 * np.abs(z).max()), engine
    if pardiso.available():  # single-precision factors refined in double precision: the same correction
        single = RegionSolves(system, regions, model.ijk, engine="pardiso", single=True, coupling="full")
        single.update(state)
        assert all(part.factor.single for part in single.parts)
        assert np.allclose(single.correct(r, np.zeros_like(r)), z, rtol=1e-9, atol=1e-11 * np.abs(z).max())
    ref = spla.spsolve(system.stiffness(state).tocsc(), state.r.ravel())
    for amg in ["pyamg"] + (["hypre"] if multigrid.hypre_available() else []):
        its = {}
        for regions_on in (True, False):
            solver = make_solver("mixed_amg", model.X, ijk=model.ijk, rtol=1e-10, maxiter=1000, region_solves=regions_on,
                                 amg=amg, region_coupling="full")
            solver.prepare(system, state)
            try:
                x = solver.solve(state.r.ravel(), rtol=1e-8)
            except SolverError:  # without the region solves BoomerAMG does not get there (measured)
                assert not regions_on
                its[regions_on] = np.inf
                continue
            assert np.linalg.norm(x - ref) <= 1e-6 * np.linalg.norm(ref)
            its[regions_on] = solver.info["iterations"]
        assert its[True] < 0.7 * its[False], amg


def test_component_region_solves_factorise_each_component_block_and_keep_the_penalty():
    """With ``coupling="components"`` (what the default, ``auto``, takes wherever no held single-node
    patch couples the components) a region's correction solves blockdiag(K_xx, K_yy, K_zz) of its
    rows of K_d: equal, with SuperLU and PARDISO (double and single precision), to
    SciPy's solve of the block with every coupling between components removed; the factors hold
    fewer entries than the whole block's; and the stiff penalty, which is per component, is still
    taken: the mixed solve needs as few iterations as with the whole block and far fewer than
    without region solves."""
    from pixmuscle.mechanics.linsolve.factorization import ComponentFactors
    from pixmuscle.mechanics.linsolve.subdomains import RegionSolves, constraint_regions

    model, system = _system(held="patch", penalty={"factor": 1000.0})
    state = system.evaluate(np.zeros((model.n_nodes, 3)), 0.5, 0.6)
    Kd = system.stiffness(state, pressure_free=True).tocsr()
    rng = np.random.default_rng(5)
    r, z0 = rng.standard_normal(Kd.shape[0]), rng.standard_normal(Kd.shape[0])
    region = constraint_regions(system)[:1]
    dofs = (3 * region[0][:, None] + np.arange(3)).ravel()
    block = Kd[dofs][:, dofs].tocoo()
    same = (dofs[block.row] % 3) == (dofs[block.col] % 3)
    D = sp.csc_matrix((block.data[same], (block.row[same], block.col[same])), shape=block.shape)
    expect = z0.copy()
    expect[dofs] += spla.spsolve(D, (r - Kd @ z0)[dofs])
    variants = [("superlu", False)] + ([("pardiso", False), ("pardiso", True)] if pardiso.available() else [])
    for engine, single in variants:
        solves = RegionSolves(system, region, model.ijk, engine=engine, single=single, coupling="components")
        solves.update(state)
        got = solves.correct(r, z0)
        rhs = (r - Kd @ z0)[dofs]  # the stiff penalty makes D ill-conditioned: its residual, then the solution
        assert np.linalg.norm(D @ (got - z0)[dofs] - rhs) <= 1e-10 * np.linalg.norm(rhs), (engine, single)
        assert np.abs(got - expect).max() <= 1e-6 * np.abs(expect).max(), (engine, single)
        assert np.array_equal(np.delete(got, dofs), np.delete(z0, dofs))
        if engine == "pardiso":
            full = RegionSolves(system, region, model.ijk, engine=engine, coupling="full")
            full.update(state)
            assert solves.parts[0].factor.info["factor_nnz"] < 0.6 * full.parts[0].factor.info["factor_nnz"]
    with pytest.raises(ValueError, match="coupling"):
        RegionSolves(system, region, model.ijk, coupling="nodes")
    # the default (auto) takes the whole block where held single-node patches couple the components
    assert all(isinstance(p.factor, ComponentFactors) for p in RegionSolves(system, region, model.ijk).parts)
    model_own, system_own = _system(held="own", penalty={"at": "nodes", "beta": 3.0e4})
    auto = RegionSolves(system_own, system_own.stiff_regions(), model_own.ijk, engine="superlu")
    assert len(auto.parts) == 3 and not any(isinstance(p.factor, ComponentFactors) for p in auto.parts)
    ref = spla.spsolve(system.stiffness(state).tocsc(), state.r.ravel())
    its = {}
    for coupling in ("components", "full"):
        solver = make_solver("mixed_amg", model.X, ijk=model.ijk, rtol=1e-10, maxiter=1000, amg="pyamg",
                             region_coupling=coupling)
        solver.prepare(system, state)
        x = solver.solve(state.r.ravel(), rtol=1e-8)
        assert np.linalg.norm(x - ref) <= 1e-6 * np.linalg.norm(ref)
        its[coupling] = solver.info["iterations"]
    assert its["components"] <= 1.2 * its["full"], its


def test_probed_schur_diagonal_is_exact_when_every_patch_has_its_own_colour():
    """On a body of 2 × 2 × 2 patch boxes the 8 parity colours give every patch its own colour, so
    the probed diagonal equals the diagonal of the dense G M Gᵀ (M: the exact inverse of K_d)."""
    from pixmuscle.mechanics.linsolve.mixed_method import probed_schur_diagonal
    from pixmuscle.verify.mechanics import mask_model

    model = mask_model(np.ones((4, 4, 6), bool), (0.15, 0.15, 0.4), tissue=1,
                       fiber=np.array([np.sin(0.4), 0.0, np.cos(0.4)]))
    cfg = _cfg(boundary_conditions=CLAMPED, volumetric={"method": "projected", "patch": [2, 2, 3], "held": "patch"})
    system = build_system(model, cfg)[0]
    state = system.evaluate(np.zeros((model.n_nodes, 3)), 0.5, 0.6)
    vol = system.volumetric
    assert vol.n_patches == 8
    main = system.tangent_operator(state).main
    G = PatchDivergence(main.B, main.BT, state.vol.a, vol.Q)
    Kd = system.stiffness(state, pressure_free=True).toarray()
    Kinv = np.linalg.inv(0.5 * (Kd + Kd.T))

    class Exact:
        def __matmul__(self, r):
            return Kinv @ r

    box = np.zeros((vol.n_patches, 3), np.int64)
    box[vol.patch_of] = model.ijk // np.array([2, 2, 3])
    Gd = G.sparse().toarray()
    exact = np.diag(Gd @ Kinv @ Gd.T)
    assert np.allclose(probed_schur_diagonal(G, Exact(), box), exact, rtol=1e-10)


def test_probed_schur_diagonal_stays_bounded_where_far_couplings_add_up():
    """A matrix whose couplings all have one sign and fall off like 1/r³ (as those of G K_d⁻¹ Gᵀ):
    the plain colour sum (A 1_c)_p adds every same-colour coupling of p, which grows with the grid
    (median error 50 % on 8³ boxes, 64 % on 10³); with random signs within each colour the probe
    stays near the exact diagonal of the dense matrix, and nearer with 27 colours than with 8."""
    from pixmuscle.mechanics.linsolve.mixed_method import probed_schur_diagonal

    class Identity:  # G = I, so the probe estimates diag(A)
        def __matmul__(self, x):
            return x

        def T(self, q):
            return q

    for n in (8, 10):
        box = np.stack(np.meshgrid(*(np.arange(n),) * 3, indexing="ij"), -1).reshape(-1, 3)
        A = 1.0 / (1.0 + np.linalg.norm(box[:, None, :] - box[None, :, :], axis=-1)) ** 3

        class Dense:
            def __init__(self, matrix):
                self.matrix = matrix

            def __matmul__(self, x):
                return self.matrix @ x

        colour = (box % 2) @ np.array([4, 2, 1])
        plain = np.array([(A @ (colour == c))[p] for p, c in enumerate(colour)])
        signed = probed_schur_diagonal(Identity(), Dense(A), box)
        assert np.median(plain / np.diag(A) - 1.0) > 0.45
        err = np.abs(signed / np.diag(A) - 1.0)
        assert np.median(err) < 0.1 and np.max(err) < 0.5
        # 27 colours (the default spacing of mixed_amg): the nearest same-colour patches are 3 boxes
        # away instead of 2, and the error shrinks with their coupling
        err3 = np.abs(probed_schur_diagonal(Identity(), Dense(A), box, spacing=3) / np.diag(A) - 1.0)
        assert np.median(err3) < 0.6 * np.median(err) and np.max(err3) < np.max(err)

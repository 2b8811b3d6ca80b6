"""Finite-element tendon reference (Example 1): geometry, constitutive law, assembly, solutions.

Independent truths used: finite differences of the energy (stress, tangent, internal forces),
scikit-fem's own form assembly, the analytic homogeneous uniaxial solution of eq. (27) written in
principal stretches, force balance between the two ends, mirror symmetry, mesh refinement.
"""

import csv

import numpy as np
import pytest
from scipy.optimize import brentq

from pixmuscle.errors import InputError
from pixmuscle.verify.tendon_fem import (
    CONNECTIVE_TISSUE,
    _Discretization,
    cubic_energy,
    cubic_stress_tangent,
    plot_comparison,
    reference_table,
    tendon_fem_reaction,
    voxel_hex_mesh,
)
from pixmuscle.verify.tendon_geometry import tendon_prism, tendon_voxels, voxel_slab_areas

MAT = CONNECTIVE_TISSUE


# ---------------------------------------------------------------------------- geometry

def test_voxel_tendon_is_stack_of_centred_slabs():
    h = (0.1, 0.1, 0.5)
    mask, aff = tendon_voxels(h)
    geo = tendon_prism()
    assert np.array_equal(mask, mask[::-1]) and np.array_equal(mask, mask[:, ::-1])
    # every slice is one rectangle: the mask equals the outer product of its row/column occupancy
    rows, cols = mask.any(axis=1), mask.any(axis=0)
    assert np.array_equal(mask, rows[:, None, :] & cols[None, :, :])
    # domain spans exactly z in [0, 19] cm
    z, area = voxel_slab_areas(mask, aff)
    full = np.flatnonzero(area > 0)
    assert np.isclose(z[full[0]] - h[2] / 2, 0.0) and np.isclose(z[full[-1]] + h[2] / 2, 19.0)
    # each slab differs from the prism section at its centre by less than one voxel pair per side
    w = geo.widths(z[full])
    nx, ny = rows.sum(axis=0)[full] * h[0], cols.sum(axis=0)[full] * h[1]
    assert np.all(np.abs(nx - w[:, 0]) <= 2 * h[0] + 1e-12)
    assert np.all(np.abs(ny - w[:, 1]) <= 2 * h[1] + 1e-12)
    assert np.allclose(nx * ny, area[full])
    # voxel centres inside the prism agree with inside(); volume within a few %
    assert abs(mask.sum() * np.prod(h) / geo.volume() - 1) < 0.05
    centres = (aff @ np.c_[np.argwhere(mask), np.ones(mask.sum())].T)[:3].T
    assert geo.inside(centres).all()


def test_prism_inside_and_area():
    geo = tendon_prism(length=10.0, base=(2.0, 1.0), top=(1.0, 0.5))
    assert np.isclose(geo.cross_section_area(5.0), 1.5 * 0.75)
    pts = np.array([[0.74, 0.37, 5.0], [0.76, 0.0, 5.0], [0.0, 0.0, -0.1], [0.0, 0.0, 10.0]])
    assert geo.inside(pts).tolist() == [True, False, False, True]
    zz = np.linspace(0, 10, 20001)
    assert np.isclose(geo.volume(), np.trapezoid(geo.cross_section_area(zz), zz), rtol=1e-7)


def test_geometry_input_errors():
    with pytest.raises(InputError):
        tendon_prism(length=-1)
    with pytest.raises(InputError):
        tendon_voxels((0.1, 0.1, 0.7))            # 19 cm is not whole slices of 0.7 cm
    with pytest.raises(InputError):
        tendon_prism().inside(np.zeros((3, 2)))


# ---------------------------------------------------------------------------- material

def _fd_check(F, kw, eps=1e-6):
    P, A = cubic_stress_tangent(F, *MAT[:3], **kw)
    Pfd, Afd = np.zeros_like(P), np.zeros_like(A)
    for k in range(3):
        for L in range(3):
            dF = np.zeros((3, 3))
            dF[k, L] = eps
            if "K" in kw:
                Pfd[:, k, L] = (cubic_energy(F + dF, *MAT) - cubic_energy(F - dF, *MAT)) / (2 * eps)
            Afd[..., k, L] = (cubic_stress_tangent(F + dF, *MAT[:3], **kw)[0]
                              - cubic_stress_tangent(F - dF, *MAT[:3], **kw)[0]) / (2 * eps)
    return P, A, Pfd, Afd


def test_stress_and_tangent_match_finite_differences():
    rng = np.random.default_rng(1)
    F = np.eye(3) + 0.1 * rng.standard_normal((5, 3, 3))
    P, A, Pfd, Afd = _fd_check(F, {"K": MAT[3]})
    assert np.allclose(P, Pfd, rtol=1e-6, atol=1e-6 * np.abs(P).max())
    assert np.allclose(A, Afd, rtol=1e-5, atol=1e-6 * np.abs(A).max())
    _, A, _, Afd = _fd_check(F, {"pressure": 40 * rng.standard_normal(5)})
    assert np.allclose(A, Afd, rtol=1e-5, atol=1e-6 * np.abs(A).max())
    # stress-free and major-symmetric tangent in the reference state
    P0, A0 = cubic_stress_tangent(np.eye(3)[None], *MAT[:3], K=MAT[3])
    assert np.allclose(P0, 0)
    assert np.allclose(A0, A0.transpose(0, 3, 4, 1, 2))


# ---------------------------------------------------------------------------- assembly

@pytest.mark.parametrize("element", ["hex27", "mixed"])
def test_internal_force_and_tangent_are_energy_derivatives(element):
    """f = ∂Π/∂u and K = ∂f/∂u by central differences (mixed: reduced energy, p = p(u))."""
    mask = np.ones((2, 1, 2), bool)
    vm = voxel_hex_mesh(mask, np.diag([0.3, 0.2, 0.5, 1.0]), symmetry=False)
    disc = _Discretization(vm, element)
    rng = np.random.default_rng(2)
    u = 0.02 * rng.standard_normal(disc.N)
    f, K, E, _ = disc.assemble(u, MAT)
    eps = 1e-7
    for i in rng.choice(disc.N, 5, replace=False):
        e = np.zeros(disc.N)
        e[i] = eps
        fp, _, Ep, _ = disc.assemble(u + e, MAT)
        fm, _, Em, _ = disc.assemble(u - e, MAT)
        assert np.isclose((Ep - Em) / (2 * eps), f[i], rtol=1e-5, atol=1e-5 * np.abs(f).max())
        col = K[:, [i]].toarray().ravel()
        assert np.allclose((fp - fm) / (2 * eps), col, atol=1e-5 * np.abs(col).max())


def test_mixed_residuals_are_lagrangian_derivatives():
    """With an independent pressure: f = ∂L/∂u, rp = ∂L/∂π, and the condensed Newton update
    (Δu, Δπ) solves the linearised (u, p) system (checked against finite differences)."""
    vm = voxel_hex_mesh(np.ones((2, 1, 2), bool), np.diag([0.3, 0.2, 0.5, 1.0]), symmetry=False)
    disc = _Discretization(vm, "mixed")
    rng = np.random.default_rng(5)
    u = 0.01 * rng.standard_normal(disc.N)
    pi = 30 * rng.standard_normal((disc.nel, 4))
    f, K, L, ex = disc.assemble(u, MAT, pi)
    eps = 1e-7
    for i in rng.choice(disc.N, 4, replace=False):
        e = np.zeros(disc.N)
        e[i] = eps
        Lp, Lm = disc.assemble(u + e, MAT, pi)[2], disc.assemble(u - e, MAT, pi)[2]
        assert np.isclose((Lp - Lm) / (2 * eps), f[i], rtol=1e-5, atol=1e-5 * np.abs(f).max())
    for el, m in [(0, 0), (1, 2), (3, 3)]:
        d = np.zeros_like(pi)
        d[el, m] = 1e-4
        Lp, Lm = disc.assemble(u, MAT, pi + d)[2], disc.assemble(u, MAT, pi - d)[2]
        assert np.isclose((Lp - Lm) / 2e-4, ex["rp"][el, m], rtol=1e-6, atol=1e-12)
    # a coupled step (du, dpi) with the condensed pressure update: its linearisation removes the
    # pressure residual (d rp = −rp) and changes f by K_condensed du + c
    du = 1e-3 * rng.standard_normal(disc.N)
    dpi = disc.pressure_update(ex, du, MAT)
    s = 1e-6
    f2, _, _, ex2 = disc.assemble(u + s * du, MAT, pi + s * dpi)
    assert np.allclose((ex2["rp"] - ex["rp"]) / s, -ex["rp"], atol=1e-5 * np.abs(ex["rp"]).max())
    lin = (f2 - f) / s
    assert np.allclose(lin, K @ du + ex["c"], atol=1e-4 * np.abs(lin).max())


def test_assembly_matches_scikit_fem_forms():
    """hex27 internal force and tangent equal scikit-fem's LinearForm / BilinearForm assembly."""
    from skfem import Basis, BilinearForm, ElementHex2, ElementVector, LinearForm, asm
    from skfem.helpers import grad

    vm = voxel_hex_mesh(np.ones((1, 1, 1), bool), np.diag([0.3, 0.2, 0.5, 1.0]),
                        symmetry=False)
    disc = _Discretization(vm, "hex27")
    rng = np.random.default_rng(3)
    u = 0.03 * rng.standard_normal(disc.N)
    f, K, _, _ = disc.assemble(u, MAT)
    vb = Basis(vm.mesh, ElementVector(ElementHex2()), intorder=5)
    # map my dof numbering (3 * scalar dof + component) to scikit-fem's vector numbering
    perm = np.empty(disc.N, int)
    for c, sub in enumerate(vb.split_indices()):
        perm[3 * np.arange(disc.nsd) + c] = sub
    us = np.empty(disc.N)
    us[perm] = u
    Fq = np.eye(3)[:, :, None, None] + grad(vb.interpolate(us))          # (3, 3, nel, nq)
    Ff = Fq.reshape(9, -1).T.reshape(-1, 3, 3)
    P, A = cubic_stress_tangent(Ff, *MAT[:3], K=MAT[3])
    shp = Fq.shape[2:]
    Pw = P.reshape(*shp, 3, 3).transpose(2, 3, 0, 1)
    Aw = A.reshape(*shp, 3, 3, 3, 3).transpose(2, 3, 4, 5, 0, 1)

    @LinearForm
    def internal(v, w):
        return np.einsum("ij...,ij...->...", w["P"], grad(v))

    @BilinearForm
    def tangent(du, v, w):
        return np.einsum("ijkl...,ij...,kl...->...", w["A"], grad(v), grad(du))

    fs = asm(internal, vb, P=Pw)
    Ks = asm(tangent, vb, A=Aw)
    assert np.allclose(f, fs[perm], atol=1e-10 * np.abs(fs).max())
    assert np.allclose(K.toarray(), Ks.toarray()[np.ix_(perm, perm)], atol=1e-10 * abs(Ks).max())


# ---------------------------------------------------------------------------- solutions

def _uniaxial_force(stretch, area, C10, C20, C30, K):
    """Homogeneous uniaxial tension of eq. (27) in principal stretches (λt, λt, λ), N."""
    def P(l1, l2, l3, a):
        lam = np.array([l1, l2, l3])
        J, I1 = lam.prod(), (lam**2).sum()
        e = J ** (-2 / 3) * I1 - 3
        psi1 = C10 + 2 * C20 * e + 3 * C30 * e**2
        return psi1 * J ** (-2 / 3) * (2 * lam[a] - 2 / 3 * I1 / lam[a]) + K * (J - 1) * J / lam[a]

    lt = brentq(lambda t: P(t, t, stretch, 0), 0.5, 1.5, xtol=1e-15)
    return P(lt, lt, stretch, 2) * area, lt


@pytest.mark.parametrize("element,symmetry", [("mixed", True), ("hex27", True),
                                              ("mixed", False)])
def test_roller_box_matches_homogeneous_uniaxial_solution(element, symmetry):
    """Single slab 0.4 × 0.2 × 0.6 cm stretched 5 % with free lateral motion (rollers)."""
    mask = np.zeros((6, 4, 5), bool)
    mask[1:5, 1:3, 1:4] = True
    aff = np.diag([0.1, 0.1, 0.2, 1.0])
    res = tendon_fem_reaction(mask, aff, stretch=0.03, steps=2, element=element, bc="roller",
                              symmetry=symmetry)
    exact, lt = _uniaxial_force(1.05, 0.4 * 0.2, *MAT)
    assert res["force"][-1] == pytest.approx(exact, rel=5e-3)      # brief: within 0.5 %
    assert res["force"][-1] == pytest.approx(exact, rel=1e-6)      # homogeneous: exact in Q2
    assert np.allclose(res["force_top"], res["force"], rtol=1e-7, atol=1e-9)
    # the displacement field is the homogeneous one, stretching about the bottom-face centre
    # (0.25, 0.15, 0.1) cm, which both the symmetry planes and the pinned node keep in place
    X, u = res["nodes"], res["u"]
    expect = (X - [0.25, 0.15, 0.1]) * (np.array([lt, lt, 1.05]) - 1)
    assert np.allclose(u, expect, atol=1e-9)


def test_roller_box_with_ends_at_voxel_centres():
    """ends="centres" drops the outer half slices: a 3-slice box becomes 2 slices long."""
    mask = np.zeros((6, 4, 5), bool)
    mask[1:5, 1:3, 1:4] = True
    aff = np.diag([0.1, 0.1, 0.2, 1.0])
    res = tendon_fem_reaction(mask, aff, stretch=0.02, steps=1, refine=(1, 1, 2), bc="roller",
                              ends="centres")
    exact, _ = _uniaxial_force(1.05, 0.4 * 0.2, *MAT)
    assert res["force"][-1] == pytest.approx(exact, rel=1e-6)
    assert res["volume_cm3"] == pytest.approx(0.4 * 0.2 * 0.4, rel=1e-12)
    assert np.allclose(np.ptp(res["nodes"][:, 2]), 0.4) and np.isclose(res["nodes"][:, 2].min(), 0.2)
    with pytest.raises(InputError):
        tendon_fem_reaction(mask, aff, refine=1, ends="centres")


@pytest.fixture(scope="module")
def coarse_tendon():
    """Default tendon voxelised at 0.4 × 0.4 × 1.0 cm: a coarse stand-in that solves in seconds."""
    return tendon_voxels((0.4, 0.4, 1.0))


def test_clamped_tendon_equilibrium_symmetry_and_refinement(coarse_tendon):
    mask, aff = coarse_tendon
    kw = dict(stretch=2.0, steps=1)
    r1 = tendon_fem_reaction(mask, aff, refine=1, **kw)
    r2 = tendon_fem_reaction(mask, aff, refine=2, **kw)
    full = tendon_fem_reaction(mask, aff, refine=1, symmetry=False, **kw)
    f1, f2 = r1["force"][-1], r2["force"][-1]
    print(f"coarse clamped tendon, 2 cm: refine 1 {f1:.4f} N, refine 2 {f2:.4f} N, "
          f"change {abs(f1 - f2) / f2:.2%}")
    assert r1["symmetry_factor"] == 4 and full["symmetry_factor"] == 1
    assert full["force"][-1] == pytest.approx(f1, rel=1e-8)         # quarter model is exact
    for r in (r1, r2, full):                                          # end forces balance
        assert r["force_top"][-1] == pytest.approx(r["force"][-1], rel=1e-7)
    assert abs(f1 - f2) / f2 < 0.03
    # voxel volume is meshed exactly
    assert r1["volume_cm3"] == pytest.approx(mask.sum() * 0.4 * 0.4 * 1.0, rel=1e-12)
    # tension, and stiffer than the same tendon on rollers (clamped ends restrain contraction)
    roll = tendon_fem_reaction(mask, aff, refine=1, bc="roller", **kw)
    assert 0 < roll["force"][-1] < f1


def test_displacement_element_locks_and_mixed_does_not(coarse_tendon):
    """Pure-displacement Q2 is stiffer than Q2–P1disc and approaches it under refinement."""
    mask, aff = coarse_tendon
    kw = dict(stretch=2.0, steps=2)   # the penalty form needs smaller steps than the mixed one
    m1 = tendon_fem_reaction(mask, aff, refine=1, **kw)["force"][-1]
    d1 = tendon_fem_reaction(mask, aff, refine=1, element="hex27", **kw)["force"][-1]
    d2 = tendon_fem_reaction(mask, aff, refine=2, element="hex27", **kw)["force"][-1]
    print(f"coarse tendon final force: mixed r1 {m1:.4f}, hex27 r1 {d1:.4f}, hex27 r2 {d2:.4f} N")
    assert d1 > d2 > m1 * 0.995


# ---------------------------------------------------------------------------- output

def test_reference_table_and_plot(tmp_path):
    fem = dict(displacement=np.linspace(0, 2, 5), force=np.array([0, 1, 2.5, 4, 6.0]),
               force_top=np.array([0, 1, 2.5, 4, 6.0]))
    path = reference_table(fem, tmp_path / "ref.csv")
    with open(path) as fh:
        rows = list(csv.DictReader(fh))
    assert [float(r["force_N"]) for r in rows] == fem["force"].tolist()
    assert [float(r["displacement_cm"]) for r in rows] == fem["displacement"].tolist()
    mf = dict(displacement=fem["displacement"], force=fem["force"] * 1.02)
    rel = plot_comparison(fem, mf, tmp_path / "cmp.png")
    assert np.allclose(rel[1:], 0.02) and np.isnan(rel[0])
    assert (tmp_path / "cmp.png").stat().st_size > 1000
    with pytest.raises(InputError):
        plot_comparison(fem, dict(displacement=np.arange(3), force=np.arange(3)), tmp_path / "x.png")


def test_fem_input_errors(coarse_tendon):
    mask, aff = coarse_tendon
    with pytest.raises(InputError):
        tendon_fem_reaction(mask, aff, element="hex8")
    with pytest.raises(InputError):
        tendon_fem_reaction(mask, aff, bc="free")
    with pytest.raises(InputError):
        tendon_fem_reaction(np.zeros_like(mask), aff)
    rot = aff.copy()
    rot[0, 1] = 0.1
    with pytest.raises(InputError):
        tendon_fem_reaction(mask, rot)
    with pytest.raises(InputError):
        tendon_fem_reaction(mask, aff, refine=0)

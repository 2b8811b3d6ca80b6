"""Homogeneous reference solutions: stationarity, agreement of the two routes, small-strain and
incompressible limits."""

import numpy as np
import pytest

from pixmuscle.errors import InputError
from pixmuscle.mechanics.homogeneous import homogeneous_min_energy, isometric_block, uniaxial_bar
from pixmuscle.mechanics.materials import CONNECTIVE_TISSUE, FAT, TransverselyIsotropicMuscle

MUSCLE = TransverselyIsotropicMuscle()
FREE = (np.array([0, 0, 0, 1, 1, 1]), np.array([0, 1, 2, 0, 1, 2]))  # rows x, y of P


@pytest.mark.parametrize(
    "material,kw",
    [(CONNECTIVE_TISSUE, {}), (FAT, {}), (MUSCLE, dict(activation=0.0)), (MUSCLE, dict(activation=0.6))],
    ids=["ct", "fat", "muscle_passive", "muscle_active"],
)
@pytest.mark.parametrize("stretch", [0.8, 1.1, 1.3])
def test_uniaxial_bar_is_traction_free_laterally(material, kw, stretch):
    r = uniaxial_bar(material, stretch, 2.5, **kw)
    P, F = r["P"], r["F"]
    np.testing.assert_allclose(F, np.diag([r["lateral_stretch"]] * 2 + [stretch]), rtol=0, atol=0)
    scale = max(abs(P[2, 2]), 1.0)
    np.testing.assert_allclose(P - np.diag([0, 0, P[2, 2]]), 0.0, rtol=0, atol=1e-9 * scale)
    assert r["force"] == pytest.approx(2.5 * P[2, 2], rel=1e-15)
    if not kw.get("activation"):  # passive: tension positive when stretched
        assert np.sign(r["force"]) == np.sign(stretch - 1.0)
    # second route: energy minimisation over the free components gives the same bar
    m = homogeneous_min_energy(material, stretch, 2.5, **kw)
    assert m["force"] == pytest.approx(r["force"], rel=1e-8)
    np.testing.assert_allclose(m["F"], F, rtol=0, atol=1e-10)


@pytest.mark.parametrize("material", [CONNECTIVE_TISSUE, FAT], ids=["ct", "fat"])
@pytest.mark.parametrize("eps", [1e-3, -1e-3, 1e-4, -1e-4])
def test_uniaxial_bar_small_strain_limit(material, eps):
    """Linear elasticity: force = E ε A0 and lateral strain −ν ε with E = 9Kμ/(3K+μ),
    ν = (3K−2μ)/(2(3K+μ)), μ = 2 C10; the nonlinear bar differs at O(ε) relative."""
    mu, K = 2 * material.C10, material.K
    E = 9 * K * mu / (3 * K + mu)
    nu = (3 * K - 2 * mu) / (2 * (3 * K + mu))
    r = uniaxial_bar(material, 1 + eps, 3.0)
    assert abs(r["force"] / (E * eps * 3.0) - 1) <= 2 * abs(eps)
    assert abs((r["lateral_stretch"] - 1) / (-nu * eps) - 1) <= 2 * abs(eps)


@pytest.mark.parametrize("lam0", [1.0, 1.4])
@pytest.mark.parametrize("alpha", [0.3, 1.0])
def test_isometric_block_agrees_with_energy_minimisation(lam0, alpha):
    m = TransverselyIsotropicMuscle(lambda_opt=lam0)
    a = isometric_block(m, alpha, 1.7)
    b = homogeneous_min_energy(m, 1.0, 1.7, fiber=(0, 0, 1), activation=alpha)
    assert b["force"] == pytest.approx(a["force"], rel=1e-8)
    np.testing.assert_allclose(b["F"], a["F"], rtol=0, atol=1e-9)
    assert a["F"][2, 2] == 1.0
    assert a["force"] > 0


@pytest.mark.parametrize("lam0", [1.0, 1.4])
def test_isometric_force_increases_with_activation(lam0):
    m = TransverselyIsotropicMuscle(lambda_opt=lam0)
    alphas = np.linspace(0.0, 1.0, 11)
    force = np.array([isometric_block(m, a, 1.0)["force"] for a in alphas])
    assert np.all(np.diff(force) > 0)
    if lam0 == 1.0:
        assert abs(force[0]) < 1e-10  # the reference state is stress free


@pytest.mark.parametrize("lam0", [1.0, 1.4])
def test_isometric_block_incompressible_limit(lam0):
    """K → ∞: F → I, σ = σ_max α λ* f_a(λ*)(e_z⊗e_z − I/3) + p I with σ_xx = 0, hence
    P_zz = σ_zz = σ_max α λ* f_a(λ*), λ* = 1/λ̂0 (the passive fibre force is zero for λ* ≤ 1)."""
    m = TransverselyIsotropicMuscle(lambda_opt=lam0, K=1e8)
    ls = 1.0 / lam0
    fa = 1 - 4 * (1 - ls) ** 2
    r = isometric_block(m, 0.8, 2.0)
    assert r["force"] == pytest.approx(30.0 * 0.8 * ls * fa * 2.0, rel=1e-5)
    assert r["lateral_stretch"] == pytest.approx(1.0, abs=1e-6)


@pytest.mark.parametrize("stretch", [1.0, 1.1])
@pytest.mark.parametrize("fiber", [(0.5, 0.0, np.sqrt(3) / 2), (1.0, 2.0, 3.0)], ids=["30deg_xz", "general"])
def test_min_energy_oblique_fibres_is_a_stationary_minimum(stretch, fiber):
    rng = np.random.default_rng(0)
    kw = dict(fiber=fiber, activation=0.7)
    r = homogeneous_min_energy(MUSCLE, stretch, 1.3, **kw)
    F, P = r["F"], r["P"]
    np.testing.assert_array_equal(F[2], [0.0, 0.0, stretch])
    # all six free components of P vanish (P_yx by objectivity of the triangular form)
    assert np.abs(P[FREE]).max() <= 1e-9 * np.abs(P).max()
    assert r["force"] == pytest.approx(1.3 * P[2, 2], rel=1e-15)
    # a minimum, not a saddle: random admissible perturbations raise the energy
    d = np.zeros((200, 3, 3))
    d[:, :2, :] = 1e-3 * rng.standard_normal((200, 2, 3))
    W = MUSCLE.energy(F[None] + d, fiber=fiber, activation=0.7)
    assert np.all(W > r["energy"])
    # angular momentum: the lateral faces carry (P_zx, P_zy) = −P_zz M⁻¹ (F_xz, F_yz)
    expected = -P[2, 2] * np.linalg.solve(F[:2, :2], F[:2, 2])
    np.testing.assert_allclose(r["lateral_axial_traction"], expected, rtol=1e-8, atol=1e-10)


def test_min_energy_with_tilted_end_constraint():
    """A prescribed third row with shear (F_zx, F_zy ≠ 0): still stationary in the free components."""
    r = homogeneous_min_energy(CONNECTIVE_TISSUE, (0.05, -0.02, 1.1), 1.0)
    np.testing.assert_array_equal(r["F"][2], [0.05, -0.02, 1.1])
    assert np.abs(r["P"][FREE]).max() <= 1e-9 * np.abs(r["P"]).max()


def test_bad_input():
    with pytest.raises(InputError, match="homogeneous_min_energy"):
        uniaxial_bar(MUSCLE, 1.1, 1.0, fiber=(1.0, 0.0, 1.0))
    with pytest.raises(InputError, match="stretch"):
        uniaxial_bar(FAT, -1.0, 1.0)
    with pytest.raises(InputError, match="area0"):
        isometric_block(MUSCLE, 0.5, 0.0)
    with pytest.raises(InputError, match="F_constraints"):
        homogeneous_min_energy(FAT, (1.0, 2.0), 1.0)
    with pytest.raises(InputError, match="fiber"):
        homogeneous_min_energy(MUSCLE, 1.0, 1.0, fiber=(0.0, 0.0, 0.0))

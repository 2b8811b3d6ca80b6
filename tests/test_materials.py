"""Materials of §5 (eqs. 22–27) against independent truths: finite differences of the energy,
the exact linear-elastic tensor, a hand transcription of eqs. 23–26, objectivity and symmetry."""

import math

import numpy as np
import pytest

from pixmuscle.errors import InputError, SolverError
from pixmuscle.mechanics import materials as mat
from pixmuscle.mechanics.materials import (
    CONNECTIVE_TISSUE,
    FAT,
    TransverselyIsotropicMuscle,
    Yeoh,
    material_from_config,
    tangent9,
    voigt9,
)

EYE = np.eye(3)


def random_rotations(rng, n):
    q = rng.standard_normal((n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        1,
    )


def random_F(rng, n):
    """F = R·U with principal stretches in [0.8, 1.25] along random axes."""
    R, V = random_rotations(rng, n), random_rotations(rng, n)
    s = rng.uniform(0.8, 1.25, (n, 3))
    U = np.einsum("nij,nj,nkj->nik", V, s, V)
    return R @ U


# normalised fibre stretches λ*, one inside each smooth piece of f_active / f_passive
BRANCH_STRETCHES = [0.3, 0.5, 0.8, 1.2, 1.5, 1.8, 2.3]
KINKS = [0.4, 0.6, 1.0, 1.4, 1.6]


def fiber_branch_F(rng, N, lam_f):
    """F = R·(λ_f N⊗N + λ_t (I − N⊗N))·(I + small) so that λ̂ ≈ λ_f, slightly compressible."""
    n = len(N)
    NN = np.einsum("ni,nj->nij", N, N)
    lam_t = 1.02 * lam_f**-0.5
    U = lam_f[:, None, None] * NN + lam_t[:, None, None] * (EYE - NN)
    G = 0.01 * rng.standard_normal((n, 3, 3))
    return random_rotations(rng, n) @ U @ (EYE + G)


def unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


CASES = [
    ("connective_tissue", CONNECTIVE_TISSUE, dict(alpha=None, lam0=1.0)),
    ("fat", FAT, dict(alpha=None, lam0=1.0)),
    ("muscle_passive", TransverselyIsotropicMuscle(), dict(alpha=0.0, lam0=1.0)),
    ("muscle_active", TransverselyIsotropicMuscle(), dict(alpha=0.7, lam0=1.0)),
    ("muscle_lam0_1.4", TransverselyIsotropicMuscle(lambda_opt=1.4), dict(alpha=1.0, lam0=1.4)),
]


def sample(rng, case):
    """About 20 random F plus, for muscle, one F per f_active / f_passive branch."""
    material, opts = case
    n = 20
    F = random_F(rng, n)
    N = unit(rng.standard_normal((n, 3)))
    if opts["alpha"] is None:
        return F, {}
    lam0 = opts["lam0"]
    Nb = unit(rng.standard_normal((len(BRANCH_STRETCHES), 3)))
    Fb = fiber_branch_F(rng, Nb, lam0 * np.array(BRANCH_STRETCHES))
    lam_b = material.fiber_stretch(Fb, fiber=Nb) / lam0
    # every smooth piece of f_active / f_passive is visited, well away from its ends
    pieces = list(zip([0.0] + KINKS, KINKS + [np.inf], strict=True))
    for lo, hi in pieces:
        assert np.any((lam_b > lo + 0.02) & (lam_b < hi - 0.02)), (lo, hi)
    # drop random points that happen to sit on a kink, where A jumps
    lam_r = material.fiber_stretch(F, fiber=N) / lam0
    keep = np.min(np.abs(lam_r[:, None] - np.array(KINKS)[None]), axis=1) > 1e-3
    F, N = np.concatenate([F[keep], Fb]), np.concatenate([N[keep], Nb])
    alpha = np.full(len(F), opts["alpha"])
    return F, dict(fiber=N, activation=alpha)


def central_difference(fun, F, h):
    """∂fun/∂F_kL by central differences, fun: (n,3,3) → (n, ...); returns (n, ..., 3, 3)."""
    out = []
    for k in range(3):
        row = []
        for L in range(3):
            dF = np.zeros((3, 3))
            dF[k, L] = h
            row.append((fun(F + dF) - fun(F - dF)) / (2 * h))
        out.append(np.stack(row, -1))
    return np.stack(out, -2)


@pytest.mark.parametrize("name,material,opts", CASES, ids=[c[0] for c in CASES])
def test_stress_and_tangent_match_finite_differences(name, material, opts):
    rng = np.random.default_rng(sum(name.encode()))
    F, kw = sample(rng, (material, opts))
    P, A = material.stress_tangent(F, **kw)
    np.testing.assert_array_equal(P, material.stress(F, **kw))
    P_fd = central_difference(lambda G: material.energy(G, **kw), F, 1e-6)
    A_fd = central_difference(lambda G: material.stress(G, **kw), F, 1e-6)
    err_P = np.abs(P - P_fd).max(axis=(1, 2)) / np.abs(P).max(axis=(1, 2))
    err_A = np.abs(A - A_fd).max(axis=(1, 2, 3, 4)) / np.abs(A).max(axis=(1, 2, 3, 4))
    assert err_P.max() <= 1e-6
    assert err_A.max() <= 1e-6


@pytest.mark.parametrize("name,material,opts", CASES, ids=[c[0] for c in CASES])
def test_major_symmetry_and_objectivity(name, material, opts):
    rng = np.random.default_rng(1)
    F, kw = sample(rng, (material, opts))
    P, A = material.stress_tangent(F, **kw)
    scale = np.abs(A).max()
    np.testing.assert_allclose(A, A.transpose(0, 3, 4, 1, 2), rtol=0, atol=1e-12 * scale)
    Q = random_rotations(rng, len(F))
    P_Q, A_Q = material.stress_tangent(Q @ F, **kw)
    np.testing.assert_allclose(P_Q, Q @ P, rtol=0, atol=1e-11 * np.abs(P).max())
    np.testing.assert_allclose(A_Q, np.einsum("nia,nkb,naJbL->niJkL", Q, Q, A), rtol=0, atol=1e-11 * scale)
    W = material.energy(F, **kw)
    np.testing.assert_allclose(material.energy(Q @ F, **kw), W, rtol=1e-12, atol=1e-12)


def test_material_symmetry():
    """Isotropy P(FQ) = P(F)Q; for the muscle, rotating the body rotates its fibres:
    P(FQ; N) = P(F; QN)Q."""
    rng = np.random.default_rng(2)
    F = random_F(rng, 15)
    Q = random_rotations(rng, 15)
    for m in (CONNECTIVE_TISSUE, FAT):
        np.testing.assert_allclose(m.stress(F @ Q), m.stress(F) @ Q, atol=1e-10)
    muscle = TransverselyIsotropicMuscle()
    N = unit(rng.standard_normal((15, 3)))
    kw = dict(activation=0.4)
    lhs = muscle.stress(F @ Q, fiber=N, **kw)
    rhs = muscle.stress(F, fiber=np.einsum("nij,nj->ni", Q, N), **kw) @ Q
    np.testing.assert_allclose(lhs, rhs, atol=1e-10)
    # the sign of the fibre vector does not matter, nor its length
    np.testing.assert_allclose(muscle.stress(F, fiber=-3 * N, **kw), muscle.stress(F, fiber=N, **kw), atol=1e-12)


@pytest.mark.parametrize(
    "material", [CONNECTIVE_TISSUE, FAT, TransverselyIsotropicMuscle()], ids=["ct", "fat", "muscle"]
)
def test_reference_state_is_stress_free(material):
    F = np.repeat(EYE[None], 4, 0)
    kw = dict(fiber=np.array([[1.0, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]]), activation=0.0)
    np.testing.assert_allclose(material.stress(F, **kw), 0.0, atol=1e-12)
    np.testing.assert_allclose(material.energy(F, **kw), 0.0, atol=1e-12)
    np.testing.assert_allclose(material.cauchy(F, **kw), 0.0, atol=1e-12)


def lame_tensor(mu, K):
    lam = K - 2 * mu / 3
    d = EYE
    return mu * (np.einsum("ik,JL->iJkL", d, d) + np.einsum("iL,Jk->iJkL", d, d)) + lam * np.einsum("iJ,kL->iJkL", d, d)


def test_small_strain_limit_is_linear_isotropic_elasticity():
    """At F = I, P = 0, so A = ∂σ/∂ε: the Lamé tensor with μ = 2 C10 (Ī1 − 3 ≈ 4 dev ε : dev ε),
    bulk modulus K; for the muscle matrix μ = 2(C10 + C01) (Mooney–Rivlin)."""
    F = EYE[None]
    for m in (CONNECTIVE_TISSUE, FAT, Yeoh(C10=1.0, C20=0.0, C30=0.0, K=7.0)):
        _, A = m.stress_tangent(F)
        np.testing.assert_allclose(A[0], lame_tensor(2 * m.C10, m.K), rtol=0, atol=1e-10 * m.K)
    muscle = TransverselyIsotropicMuscle()
    _, A = muscle.stress_tangent(F, fiber=[0.0, 0.0, 1.0], activation=0.0)
    np.testing.assert_allclose(A[0], lame_tensor(2 * (6.43 - 3.8), 5000.0), rtol=0, atol=1e-9)


# --- hand transcription of eqs. 23–26 (with the ERRATA), scalar, for the tests only ---------


def fa_ref(x):
    if x < 0.4 or x > 1.6:
        return 0.0
    if x <= 0.6:
        return 9 * (x - 0.4) ** 2
    if x <= 1.4:
        return 1 - 4 * (1 - x) ** 2
    return 9 * (x - 1.6) ** 2


def fp_ref(x, g1=0.05, g2=6.6):
    if x <= 1:
        return 0.0
    if x <= 1.4:
        return g1 * (math.exp(g2 * (x - 1)) - 1)
    return g1 * g2 * math.exp(0.4 * g2) * (x - 1.4) + g1 * (math.exp(0.4 * g2) - 1)


def test_force_length_functions_match_equations():
    xs = np.linspace(0.0, 2.5, 1001)
    np.testing.assert_allclose(mat.f_active(xs), [fa_ref(x) for x in xs], atol=1e-14)
    np.testing.assert_allclose(mat.f_passive(xs), [fp_ref(x) for x in xs], rtol=1e-13, atol=1e-15)
    assert mat.f_active(1.0) == 1.0


@pytest.mark.parametrize("lam0", [1.0, 1.4])
@pytest.mark.parametrize("alpha", [0.0, 0.6, 1.0])
def test_uniaxial_isochoric_fibre_stretch_matches_eq24(lam0, alpha):
    """F = diag(λ^-½, λ^-½, λ), N = e_z (J = 1, λ̂ = λ). With the uncoupled energy the Cauchy
    stress is 2 dev[(W1 + Ī1 W2) B̄ − W2 B̄²] + σ_max λ*(α f_a + f_p)(n⊗n − I/3) + U'(J) I, hence

        σ_zz − σ_xx = 2(λ² − λ⁻¹)(W1 + W2/λ) + σ_max λ* (α f_active(λ*) + f_passive(λ*)),

    W1 = C10 + 2 C20 (Ī1−3) + C11 (Ī2−3), W2 = C01 + 2 C02 (Ī2−3) + C11 (Ī1−3),
    Ī1 = λ² + 2/λ, Ī2 = 2λ + 1/λ²; and σ_xx = σ_yy, no shear."""
    m = TransverselyIsotropicMuscle(lambda_opt=lam0)
    lams = lam0 * np.array(BRANCH_STRETCHES + [0.95, 1.05])
    F = np.zeros((len(lams), 3, 3))
    F[:, 0, 0] = F[:, 1, 1] = lams**-0.5
    F[:, 2, 2] = lams
    sig = m.cauchy(F, fiber=[0.0, 0.0, 1.0], activation=alpha)
    for s, lam in zip(sig, lams, strict=True):
        x, y = lam**2 + 2 / lam - 3, 2 * lam + 1 / lam**2 - 3
        W1 = 6.43 + 2 * 0.94 * x - 0.0043 * y
        W2 = -3.8 + 2 * 0.0005 * y - 0.0043 * x
        ls = lam / lam0
        expected = 2 * (lam**2 - 1 / lam) * (W1 + W2 / lam) + 30.0 * ls * (alpha * fa_ref(ls) + fp_ref(ls))
        assert s[2, 2] - s[0, 0] == pytest.approx(expected, rel=1e-10, abs=1e-10)
        assert s[0, 0] == pytest.approx(s[1, 1], abs=1e-10)
        np.testing.assert_allclose(s - np.diag(np.diag(s)), 0.0, atol=1e-10)


def test_active_stress_is_deviatoric_along_the_current_fibre():
    """For any F: σ(α) − σ(0) = J⁻¹ σ_max α λ* f_active(λ*) (n⊗n − I/3), n = FN/|FN|,
    λ* = J^(-1/3)|FN|/λ̂0 — the active fibre stress carries no pressure."""
    rng = np.random.default_rng(3)
    for lam0 in (1.0, 1.4):
        m = TransverselyIsotropicMuscle(lambda_opt=lam0)
        F = random_F(rng, 20)
        N = unit(rng.standard_normal((20, 3)))
        alpha = rng.uniform(0.1, 1.0, 20)
        dsig = m.cauchy(F, fiber=N, activation=alpha) - m.cauchy(F, fiber=N, activation=0.0)
        J = np.linalg.det(F)
        a = np.einsum("nij,nj->ni", F, N)
        ls = J ** (-1 / 3) * np.linalg.norm(a, axis=1) / lam0
        n = unit(a)
        amp = 30.0 * alpha * ls * np.array([fa_ref(x) for x in ls]) / J
        expected = amp[:, None, None] * (np.einsum("ni,nj->nij", n, n) - EYE / 3)
        np.testing.assert_allclose(dsig, expected, rtol=0, atol=1e-10)
        np.testing.assert_allclose(np.trace(dsig, axis1=1, axis2=2), 0.0, atol=1e-10)
    # at optimal length and full activation the fibre pulls with σ_max, J = 1
    m = TransverselyIsotropicMuscle(lambda_opt=1.0)
    d = m.cauchy(EYE[None], fiber=[0, 0, 1.0], activation=1.0)[0]
    np.testing.assert_allclose(d, 30.0 * (np.diag([0, 0, 1.0]) - EYE / 3), atol=1e-12)


@pytest.mark.parametrize("lam0", [1.0, 1.4, 0.8])
def test_fibre_energy_is_the_integral_of_the_stress_across_all_branches(lam0):
    """W(F(λ1)) − W(F(λ0)) = ∫ P : dF/dλ dλ along an isochoric fibre stretch path crossing every
    kink of f_active / f_passive (composite Gauss–Legendre split at the kinks): checks the
    integration constants of the closed-form fibre energy, which local derivatives cannot see."""
    m = TransverselyIsotropicMuscle(lambda_opt=lam0)
    kw = dict(fiber=[0.0, 0.0, 1.0], activation=0.8)
    breaks = np.array([0.2] + KINKS + [2.6]) * lam0
    xg, wg = np.polynomial.legendre.leggauss(20)

    def F_path(lam):
        F = np.zeros((len(lam), 3, 3))
        F[:, 0, 0] = F[:, 1, 1] = lam**-0.5
        F[:, 2, 2] = lam
        dF = np.zeros_like(F)
        dF[:, 0, 0] = dF[:, 1, 1] = -0.5 * lam**-1.5
        dF[:, 2, 2] = 1.0
        return F, dF

    # 4 sub-segments per smooth piece; compare at every sub-segment end (inside every piece)
    ends = np.unique(np.concatenate([np.linspace(a, b, 5) for a, b in zip(breaks[:-1], breaks[1:], strict=True)]))
    work = [0.0]
    for sa, sb in zip(ends[:-1], ends[1:], strict=True):
        lam = 0.5 * (sb - sa) * xg + 0.5 * (sa + sb)
        F, dF = F_path(lam)
        work.append(work[-1] + 0.5 * (sb - sa) * np.sum(wg * np.einsum("nij,nij->n", m.stress(F, **kw), dF)))
    W = m.energy(F_path(ends)[0], **kw)
    np.testing.assert_allclose(W - W[0], work, rtol=1e-10, atol=1e-12 * np.abs(work).max())


def test_inverted_points_raise_solver_error():
    F = np.repeat(EYE[None], 5, 0)
    F[1] = np.diag([1.0, 1.0, -1.0])
    F[3] = np.diag([1.0, 0.0, 1.0])
    for m, kw in [(CONNECTIVE_TISSUE, {}), (TransverselyIsotropicMuscle(), dict(fiber=[1.0, 0, 0]))]:
        for method in ("energy", "stress", "stress_tangent", "cauchy"):
            with pytest.raises(SolverError, match="2 of 5"):
                getattr(m, method)(F, **kw)
    F[3] = np.nan
    with pytest.raises(SolverError, match="non-finite"):
        CONNECTIVE_TISSUE.stress(F)


def test_bad_input_raises_input_error():
    m = TransverselyIsotropicMuscle()
    F = np.repeat(EYE[None], 3, 0)
    with pytest.raises(InputError, match="1 of 3 fibre"):
        m.stress(F, fiber=[[0, 0, 1.0], [0, 0, 0], [1, 0, 0]])
    with pytest.raises(InputError, match="fiber"):
        m.stress(F)
    with pytest.raises(InputError, match="shape"):
        m.stress(F, fiber=np.ones((2, 3)))
    with pytest.raises(InputError, match="activation"):
        m.stress(F, fiber=[0, 0, 1.0], activation=1.5)
    with pytest.raises(InputError, match="activation"):
        m.stress(F, fiber=[0, 0, 1.0], activation=np.ones(2))
    with pytest.raises(InputError, match=r"\(n, 3, 3\)"):
        CONNECTIVE_TISSUE.stress(np.eye(3))
    with pytest.raises(InputError, match="K"):
        Yeoh(1.0, 0.0, 0.0, -1.0)
    with pytest.raises(InputError, match="lambda_opt"):
        TransverselyIsotropicMuscle(lambda_opt=0.0)


def test_material_from_config():
    assert material_from_config("fat") == FAT == Yeoh(3, 8, 80, 5000)
    assert material_from_config("connective_tissue", None) == Yeoh(30, 80, 800, 50000)
    m = material_from_config("muscle", {"lambda_opt": 1.4, "sigma_max": 25})
    assert m == TransverselyIsotropicMuscle(lambda_opt=1.4, sigma_max=25.0)
    assert (m.C10, m.C01, m.C20, m.C02, m.C11, m.K) == (6.43, -3.8, 0.94, 0.0005, -0.0043, 5000.0)
    assert (m.gamma1, m.gamma2) == (0.05, 6.6)
    with pytest.raises(InputError, match=r"'C30'.*allowed: C10, C01, C20, C02, C11, K, sigma_max"):
        material_from_config("muscle", {"C30": 1.0})
    with pytest.raises(InputError, match="unknown tissue 'bone'"):
        material_from_config("bone")
    with pytest.raises(InputError, match="must be a number"):
        material_from_config("fat", {"K": "big"})


def test_voigt9_order_of_eq17():
    P = np.arange(9.0).reshape(3, 3) + 1  # P[i, j] = 3i + j + 1
    np.testing.assert_array_equal(voigt9(P), [1, 5, 9, 2, 4, 3, 7, 6, 8])
    rng = np.random.default_rng(4)
    F = random_F(rng, 3)
    _, A = CONNECTIVE_TISSUE.stress_tangent(F)
    dF = rng.standard_normal((3, 3, 3))
    np.testing.assert_allclose(
        np.einsum("nab,nb->na", tangent9(A), voigt9(dF)),
        voigt9(np.einsum("niJkL,nkL->niJ", A, dF)),
        rtol=1e-13,
    )

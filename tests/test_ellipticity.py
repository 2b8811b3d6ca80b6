"""Strong ellipticity check (pixmuscle.mechanics.ellipticity) against closed forms and the
independent muscle law of benchmarks/bench_active_block.py."""

import numpy as np

from pixmuscle.mechanics.ellipticity import acoustic_minimum, directions
from pixmuscle.mechanics.materials import CONNECTIVE_TISSUE, MUSCLE

FIBER = np.array([np.sin(np.deg2rad(25.0)), 0.0, np.cos(np.deg2rad(25.0))])


def test_undeformed_isotropic_law_gives_the_shear_modulus():
    """At F = I the transverse waves of an isotropic law travel with Q = μ: 2 C10 for eq. 27,
    2 (C10 + C01) for the muscle matrix (the fibre adds nothing at λ̂ = λ̂0 along m ⊥ a)."""
    I = np.eye(3)[None]
    assert np.isclose(acoustic_minimum(I, CONNECTIVE_TISSUE.stress_tangent(I)[1])[0], 2 * CONNECTIVE_TISSUE.C10)
    q = acoustic_minimum(I, MUSCLE.stress_tangent(I, fiber=FIBER, activation=0.95)[1])[0]
    assert np.isclose(q, 2 * (MUSCLE.C10 + MUSCLE.C01))


def test_constructed_negative_stiffness_is_found():
    """A = μ 𝕀 − c (n⊗N)⊗(n⊗N) with n ⊥ N: Q(m) = μ I − c (N·m)² n⊗n, whose smallest transverse
    eigenvalue μ − c (N·m)² is least at m = N (the lattice's pole is 0.1 % off N = e_z)."""
    mu, c = 2.0, 5.0
    N, n = np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0])
    A = mu * np.einsum("ik,JL->iJkL", np.eye(3), np.eye(3)) - c * np.einsum("i,J,k,L->iJkL", n, N, n, N)
    q = acoustic_minimum(np.eye(3)[None], A[None], directions(600))[0]
    assert abs(q - (mu - c)) < 0.01 * c


def test_muscle_matrix_loses_ellipticity_in_uniaxial_tension_near_1_37():
    """The paper's muscle matrix (C01 = −3.8 < 0) is strongly elliptic in isochoric uniaxial tension up
    to a stretch of 1.36 and not from 1.37 on, with or without activation; the independent tensortrax
    law of benchmarks/bench_active_block.py (--ellipticity) puts the limit at 1.365 on a 0.005 grid."""
    for alpha in (0.0, 0.95):
        q = [acoustic_minimum(F[None], MUSCLE.stress_tangent(F[None], fiber=FIBER, activation=alpha)[1])[0]
             for F in (np.diag([s**-0.5, s**-0.5, s]) for s in (1.30, 1.355, 1.375, 1.45))]
        assert q[0] > 0 and q[1] > 0 and q[2] < 0 and q[3] < 0

"""Constraint gap of the penalty boundary conditions, reported for every solve.

Independent checks: the penalty traction is β·gap, so the gap must fall as 1/β while the reaction
force converges; a prescribed displacement must be met to the reported gap.
"""

import numpy as np

from pixmuscle.mechanics.solve import solve
from pixmuscle.verify.mechanics import _cfg, mask_model


def _bar_solve(factor):
    model = mask_model(np.ones((4, 4, 8), bool), (0.2, 0.2, 0.5))
    bcs = [{"nodes": "z_min", "fix": ["x", "y", "z"]}, {"nodes": "z_max", "fix": ["x", "y"], "displace": {"z": 0.2}}]
    cfg = _cfg(steps=1, activation={"from": 0.0, "to": 0.0}, boundary_conditions=bcs, penalty={"factor": factor})
    return solve(model, cfg)


def test_gap_falls_as_one_over_beta_and_forces_converge():
    a, b = _bar_solve(1.0), _bar_solve(10.0)
    for name in ("z_min", "z_max"):
        ga, gb = a.constraint_gap[name], b.constraint_gap[name]
        assert 0 < ga["max_cm"] and ga["relative"] < 0.01  # the default holds to 1 % of the largest displacement
        assert 7 < ga["max_cm"] / gb["max_cm"] < 13  # traction = β gap: ten times β, a tenth of the gap
        assert 0.9 * 0.2 < ga["max_displacement_cm"] <= 0.2 * (1 + ga["relative"])  # nodal u: end nodes sit h/2 inside
    fa, fb = a.force("z_min")[-1], b.force("z_min")[-1]
    assert abs(fa / fb - 1) < 0.005  # tightening the constraint moves the reaction by < 0.5 %
    # the prescribed top displacement is met to the reported gap at the constraint points (end faces)
    top = a.constraint_gap["z_max"]["max_cm"]
    assert top < 0.01 * 0.2
    assert "constraint gap" not in " ".join(a.warnings)

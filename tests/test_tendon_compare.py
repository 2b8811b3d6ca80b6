"""Paper Example 1: tapered tendon (~19 cm) clamped at the bottom, top stretched 2 cm (held laterally),
connective tissue (Table 1). The meshfree reaction force per step is compared with an independent
scikit-fem finite-element solution (Q2–P1disc, :mod:`pixmuscle.verify.tendon_fem`) on the same
voxel domain.

Resolution: the clamped ends create a boundary layer (lateral contraction suppressed in the nearly
incompressible tissue) that the meshfree cells resolve only along the slice direction, so the force
error grows with the slice spacing h_z (measured: +9.6 % at h_z = 1 cm, +4.2 % at 0.5 cm, +2.6 % at
0.25 cm, independent of the in-plane spacing). The test uses h = (0.2, 0.2, 0.25) cm, 1600 nodes.
"""

import numpy as np
import pytest

from pixmuscle.verify.mechanics import tendon_comparison

pytest.importorskip("skfem")


@pytest.mark.slow
def test_tendon_reaction_matches_finite_elements():
    cmp = tendon_comparison(h=(0.2, 0.2, 0.25), stretch=2.0, steps=2)
    fe, mf = cmp["fem"], cmp["meshfree"]
    assert np.allclose(fe["displacement"], mf["displacement"])
    assert np.all(np.diff(mf["force"]) > 0)  # stiffening tension
    rel = cmp["rel_error"][1:]
    assert np.all(np.abs(rel) < 0.03), rel
    # equilibrium of the meshfree solution: both ends carry the same force
    assert np.allclose(mf["force"], mf["force_top"], rtol=1e-6)

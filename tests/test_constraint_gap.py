"""Constraint gap of the penalty boundary conditions, reported for every solve.

Independent check: the penalty theory of :mod:`pixmuscle.mechanics.boundary`. Linearised, the gap
at the constraint points is e = (I + β S W)⁻¹ e₀ (S the body's flexibility at those points), each
mode shrinking by 1 / (1 + β s): the gap falls with β, tenfold β reduces it at most tenfold, and
it falls as 1/β once β is large, while the reaction converges to its constrained limit. A
prescribed displacement must be met to the reported gap.
"""

import numpy as np
import pytest

from pixmuscle.mechanics.solve import solve
from pixmuscle.verify.mechanics import _cfg, mask_model

FACTORS = (1.0, 10.0, 100.0, 1000.0)


def _bar_solve(factor, at):
    model = mask_model(np.ones((4, 4, 8), bool), (0.2, 0.2, 0.5))
    bcs = [{"nodes": "z_min", "fix": ["x", "y", "z"]}, {"nodes": "z_max", "fix": ["x", "y"], "displace": {"z": 0.2}}]
    cfg = _cfg(steps=1, activation={"from": 0.0, "to": 0.0}, boundary_conditions=bcs, penalty={"factor": factor, "at": at})
    return solve(model, cfg)


@pytest.fixture(scope="module", params=["auto", "centres"])
def bars(request):
    """The bar at each penalty factor, end sets held at their end-face vertices (default) or centres."""
    return {f: _bar_solve(f, request.param) for f in FACTORS}


def test_gap_falls_with_beta_as_the_penalty_theory_says(bars):
    for name in ("z_min", "z_max"):
        gap = np.array([bars[f].constraint_gap[name]["max_cm"] for f in FACTORS])
        ratio = gap[:-1] / gap[1:]
        assert np.all(ratio > 1) and np.all(ratio < 10.5), ratio  # each mode: (1 + 10 β s) / (1 + β s) ∈ (1, 10)
        assert ratio[-1] > 9, ratio  # β s ≫ 1: the gap falls as 1/β (no over-constraint)
        g1 = bars[1.0].constraint_gap[name]
        assert 0 < g1["relative"] < 0.01  # the default holds to 1 % of the largest displacement
        assert 0.9 * 0.2 < g1["max_displacement_cm"] <= 0.2 * (1 + g1["relative"])  # nodal u: end nodes sit h/2 inside


def test_reaction_converges_with_beta_and_the_prescribed_displacement_is_met(bars):
    force = np.array([bars[f].force("z_min")[-1] for f in FACTORS])
    assert abs(force[-2] / force[-1] - 1) < 0.002  # converged in β
    assert abs(force[0] / force[-1] - 1) < 0.02  # the default factor is within 2 % of the constrained limit
    a = bars[1.0]
    top = a.constraint_gap["z_max"]["max_cm"]  # at the constraint points (end faces)
    assert top < 0.01 * 0.2
    assert "constraint gap" not in " ".join(a.warnings)


def test_end_sets_can_be_held_at_the_vertices_of_their_end_faces():
    """``penalty.at: vertices``: on an irregular end face the constraint points are the face vertices, each once (the corners of the
    cells written for ParaView, from their own enumeration), with weights that integrate a bilinear field
    over the end surface exactly (trapezoidal rule; the exact integral face by face here)."""
    from pixmuscle.config import parse_section
    from pixmuscle.mechanics.boundary import constraint_points
    from pixmuscle.mechanics.config import BoundaryCondition
    from pixmuscle.mechanics.scni import cell_corners, cell_faces
    from pixmuscle.report.fields import voxel_hexahedra

    mask = np.zeros((5, 4, 3), bool)
    mask[:, :2] = True
    mask[:2, 2:] = True                                  # an L-shaped cross-section
    mask[4, 0, 0] = False                                # and a notch in the bottom end face
    h = np.array([0.2, 0.3, 0.5])
    model = mask_model(mask, h)
    faces = cell_faces(model.X, model.ijk, h)
    bc = parse_section(BoundaryCondition, {"nodes": "z_min", "fix": ["x", "y", "z"]}, "bc")
    _, pts, node, w, *_ = constraint_points(model, [bc], faces, at="vertices")
    bottom = model.ijk[:, 2] == 0
    assert np.all(bottom[node])
    corners, _ = voxel_hexahedra(model.ijk, model.origin, h)
    assert np.allclose(np.sort(cell_corners(model.X, h), axis=0), np.sort(corners, axis=0))
    on_face = np.isclose(corners[:, 2], -h[2] / 2)
    lo = (model.X[bottom] - h / 2)[:, :2]
    inside = np.zeros(on_face.sum(), bool)               # vertices of the bottom cells' lower faces
    for a, b in ((0, 0), (1, 0), (0, 1), (1, 1)):
        hit = np.all(np.isclose(corners[on_face][:, None, :2], (lo + [a * h[0], b * h[1]])[None]), axis=-1).any(axis=1)
        inside |= hit
    expected = corners[on_face][inside]
    assert pts.shape == expected.shape and np.allclose(np.sort(pts, axis=0), np.sort(expected, axis=0))
    assert np.isclose(w.sum(), bottom.sum() * h[0] * h[1])

    def f(x, y):
        return 1 + 2 * x - 3 * y + 5 * x * y

    exact = 0.0
    for x0, y0 in lo:                                    # ∫ over each face [x0, x0 + hx] × [y0, y0 + hy]
        xm, ym = x0 + h[0] / 2, y0 + h[1] / 2
        exact += h[0] * h[1] * f(xm, ym)                 # f is bilinear: its mean over a box is its centre value
    assert np.isclose(np.sum(w * f(pts[:, 0], pts[:, 1])), exact)

"""Support enlargement on thin features: covered points, unchanged supports elsewhere, exact reproduction."""

import numpy as np
import pytest

from pixmuscle.errors import InputError
from pixmuscle.rk import SingularMomentError, covering_supports, shape_functions


def _slab_with_column():
    """A 6×6×4 block of nodes plus a one-node-wide column sticking out diagonally (a skin strand)."""
    g = np.argwhere(np.ones((6, 6, 4), bool)).astype(float)
    col = np.array([[7.0, 7.0, k] for k in range(4)])  # touches the block only diagonally, one node wide
    return np.vstack([g, col])


def test_singular_error_names_points():
    nodes = _slab_with_column()
    pts = nodes + np.array([0.5, 0.0, 0.0])  # +x face centres
    with pytest.raises(SingularMomentError) as exc:
        shape_functions(nodes, pts, 1.65)
    bad = exc.value.point_index
    assert bad.size > 0 and np.all(nodes[bad, 0] >= 6.0)  # only the column's faces are uncovered


def test_covering_supports_fix_thin_column_and_reproduce_linear_fields():
    nodes = _slab_with_column()
    faces = [nodes + s * np.eye(3)[k] * 0.5 for k in range(3) for s in (1, -1)]
    a, n_enlarged = covering_supports(nodes, [*faces, nodes], 1.65)
    assert 0 < n_enlarged < nodes.shape[0] // 2
    # nodes far from the column keep the nominal support exactly
    far = np.linalg.norm(nodes[:, :2] - 7.0, axis=1) > 5
    assert np.all(a[far] == 1.65)
    pts = np.vstack(faces)
    psi, dpsi = shape_functions(nodes, pts, a, gradient=True)
    # linear consistency (eq. 5) holds with the enlarged supports: an independent truth
    np.testing.assert_allclose(psi @ nodes, pts, atol=1e-10)
    for k in range(3):
        np.testing.assert_allclose(dpsi[k] @ nodes[:, k], 1.0, atol=1e-9)


def test_covering_supports_gives_up_cleanly():
    nodes = np.array([[0.0, 0.0], [1.0, 0.0]])  # collinear: no support can fix a 2-D linear basis
    with pytest.raises(InputError, match="could not be made to cover"):
        covering_supports(nodes, [np.array([[0.5, 0.0]])], 1.0, max_rounds=3)

"""RK kernel functions (paper Fig. 1): values against scipy B-splines, derivatives against FD."""

import numpy as np
import pytest
from scipy.interpolate import BSpline

from pixmuscle.errors import InputError
from pixmuscle.rk import KERNELS, kernel

Z = np.linspace(0.0, 1.2, 241)


@pytest.mark.parametrize(
    ("kind", "degree", "scale"),
    [("tent", 1, 1.0), ("cubic", 3, 1.0), ("quintic", 5, 66.0 / 120.0)],
)
def test_bspline_kernels_match_scipy(kind, degree, scale):
    # uniform B-spline of the given degree on [-1, 1]; scipy's is normalised to unit integral
    # of the cardinal spline, ours to phi(0) = 1 (quintic) or the usual 2/3 (cubic)
    knots = np.linspace(-1.0, 1.0, degree + 2)
    ref = BSpline.basis_element(knots, extrapolate=False)(Z)
    ref = np.nan_to_num(ref)
    phi, _ = kernel(Z, kind)
    np.testing.assert_allclose(phi * scale, ref, atol=1e-13)


def test_quartic_is_the_c2_quartic_with_flat_top():
    # truth: the unique quartic with phi(0) = 1, phi'(0) = 0, phi(1) = phi'(1) = phi''(1) = 0
    rows = [
        [1, 0, 0, 0, 0],
        [0, 1, 0, 0, 0],
        [1, 1, 1, 1, 1],
        [0, 1, 2, 3, 4],
        [0, 0, 2, 6, 12],
    ]
    coef = np.linalg.solve(np.array(rows, float), [1.0, 0, 0, 0, 0])
    z = np.linspace(0, 0.999, 50)
    poly = np.polynomial.Polynomial(coef)
    phi, dphi = kernel(z, "quartic")
    np.testing.assert_allclose(phi, poly(z), atol=1e-13)
    np.testing.assert_allclose(dphi, poly.deriv()(z), atol=1e-12)


@pytest.mark.parametrize("kind", KERNELS)
def test_kernel_derivative_matches_finite_differences(kind):
    z = np.linspace(0.013, 0.987, 97)
    eps = 1e-6
    fd = (kernel(z + eps, kind)[0] - kernel(z - eps, kind)[0]) / (2 * eps)
    np.testing.assert_allclose(kernel(z, kind)[1], fd, atol=1e-7)


@pytest.mark.parametrize("kind", KERNELS)
def test_kernel_compact_support_and_symmetry(kind):
    phi, dphi = kernel(np.array([1.0, 1.5, 7.0]), kind)
    assert np.all(phi == 0) and np.all(dphi == 0)
    np.testing.assert_array_equal(kernel(-Z, kind)[0], kernel(Z, kind)[0])
    inside = kernel(np.linspace(0, 0.999, 50), kind)[0]
    assert np.all(inside > 0)
    assert np.all(np.diff(inside) < 0)  # decreasing in the distance


@pytest.mark.parametrize("kind", ["cubic", "quartic", "quintic"])
def test_smooth_kernels_are_c1_at_the_support_edge(kind):
    phi, dphi = kernel(np.array([0.0, 1.0 - 1e-9]), kind)
    assert abs(dphi[0]) < 1e-12  # flat top
    assert abs(dphi[1]) < 1e-6  # derivative vanishes at the support edge


def test_unknown_kernel_raises():
    with pytest.raises(InputError, match="unknown RK kernel"):
        kernel(0.5, "gaussian")

"""The RK approximation of a field at arbitrary points, u(x) = Σ_J Ψ_J(x) d_J (paper eq. 2).

The shape functions of a block of points are built (:func:`pixmuscle.rk.shape_functions`), applied
to the coefficients and dropped before the next block, so memory stays bounded by the block
size whatever the number of points.
"""

from __future__ import annotations

import numpy as np

#: evaluation points per block (about 64 nodes each with a cubic box kernel at a/h = 1.65)
POINTS_PER_BLOCK = 50_000


def rk_evaluate(nodes, points, support, coeffs, *, kernel="cubic", order=1, support_shape="box",
                block: int = POINTS_PER_BLOCK, singular: str = "raise") -> np.ndarray:
    """Values of the RK approximation Σ_J Ψ_J(x_p) d_J at ``points``.

    Parameters
    ----------
    nodes : (N, d) float, cm
        Node coordinates x_J.
    points : (P, d) float, cm
        Evaluation points.
    support : float, (d,), (N,) or (N, d) float, cm
        Kernel support radii, as in :func:`pixmuscle.rk.shape_functions` (use the ones the
        coefficients were computed with).
    coeffs : (N,) or (N, c) float
        RK coefficients d_J (e.g. displacement coefficients in cm, c = 3; several states side by
        side as more columns).
    kernel, order, support_shape
        As in :func:`pixmuscle.rk.shape_functions`.
    block : int
        Points evaluated at once.
    singular : {"raise", "nan"}
        Points whose moment matrix is singular (too few nodes in their support, e.g. beside a
        one-voxel strand): raise :class:`~pixmuscle.rk.SingularMomentError`, or give NaN there.

    Returns
    -------
    (P,) or (P, c) float64
        In the units of ``coeffs``.

    Raises
    ------
    InputError
        As :func:`pixmuscle.rk.shape_functions` (e.g. a point outside the node cloud's cover).
    """
    from .shape import SingularMomentError, shape_functions

    points = np.asarray(points, float)
    d = np.asarray(coeffs, float)
    flat = d.reshape(d.shape[0], -1)
    out = np.empty((points.shape[0], flat.shape[1]))
    for start in range(0, points.shape[0], block):  # loop over blocks of points (memory bound)
        pts = points[start:start + block]
        rows = np.arange(pts.shape[0])
        try:
            psi = shape_functions(nodes, pts, support, kernel=kernel, order=order, support_shape=support_shape)
        except SingularMomentError as exc:
            if singular != "nan":
                raise
            rows = np.setdiff1d(rows, exc.point_index)
            out[start + exc.point_index] = np.nan
            psi = shape_functions(nodes, pts[rows], support, kernel=kernel, order=order, support_shape=support_shape)
        out[start + rows] = psi @ flat
    return out.reshape((points.shape[0], *d.shape[1:]))

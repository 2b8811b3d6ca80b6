"""Per-node supports that cover every evaluation point (thin image features).

Pixel models of real anatomy contain thin features — a one-voxel skin strand, a diagonal chain
left by coarsening — where a point's box support holds nodes on a single line or plane only,
so the moment matrix (eq. 6) of a linear basis is singular. :func:`covering_supports` starts
from the nominal support and enlarges, locally and only where needed, the supports of the
nodes around such points until every point is covered. Elsewhere the supports stay exactly
nominal, so the approximation is unchanged there.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np
from scipy.spatial import cKDTree

from pixmuscle.errors import InputError
from pixmuscle.rk.shape import SingularMomentError, shape_functions

_LOG = logging.getLogger(__name__)


def covering_supports(nodes, point_sets: Sequence[np.ndarray], support, *, kernel: str = "cubic", order: int = 1,
                      support_shape: str = "box", growth: float = 1.25, reach: float = 2.0,
                      max_rounds: int = 8) -> tuple[np.ndarray, int]:
    """Per-node supports (N, d) under which every point of ``point_sets`` has a regular moment matrix.

    Parameters
    ----------
    nodes : (N, d) float
        Node coordinates, cm.
    point_sets : sequence of (P_i, d) float
        Evaluation points that must be covered (e.g. SCNI face centres and the nodes), cm.
    support : float, (d,) or (N, d)
        Nominal support radius a, cm.
    kernel, order, support_shape
        As in :func:`pixmuscle.rk.shape_functions`.
    growth : float
        Factor applied to the supports of the nodes near an uncovered point in each round.
    reach : float
        Nodes within ``reach`` nominal supports (scaled Chebyshev distance) of an uncovered
        point are enlarged.
    max_rounds : int
        Rounds before giving up.

    Returns
    -------
    support : (N, d) float
        Per-node supports, cm (equal to the nominal value wherever no enlargement was needed).
    n_enlarged : int
        Number of nodes whose support was enlarged.

    Raises
    ------
    InputError
        Points still uncovered after ``max_rounds`` (the message of the last attempt).
    """
    nodes = np.asarray(nodes, dtype=float)
    n, d = nodes.shape
    a = np.broadcast_to(np.asarray(support, dtype=float), (n, d)).copy()
    nominal = a.copy()
    scale = nominal.max(axis=0)
    tree = cKDTree(nodes / scale)
    points = np.vstack([np.asarray(p, dtype=float).reshape(-1, d) for p in point_sets])
    for _ in range(max_rounds + 1):
        try:
            shape_functions(nodes, points, a, kernel=kernel, order=order, support_shape=support_shape, check_only=True)
        except SingularMomentError as exc:
            bad = points[exc.point_index]
            near = tree.query_ball_point(bad / scale, r=reach, p=np.inf)
            idx = np.unique(np.concatenate([np.asarray(i, dtype=np.int64) for i in near]))
            if idx.size == 0:
                raise InputError(f"{exc} (no node lies within {reach} supports of these points)") from None
            a[idx] *= growth
            last = exc
            continue
        n_enlarged = int(np.count_nonzero((a > nominal * (1 + 1e-12)).any(axis=1)))
        if n_enlarged:
            _LOG.warning("RK supports enlarged at %d of %d nodes (up to %.2f× nominal) to cover thin features",
                         n_enlarged, n, float((a / nominal).max()))
        return a, n_enlarged
    raise InputError(f"RK supports could not be made to cover all points after {max_rounds} enlargements: {last}")

"""Point–node neighbour search for compactly supported kernels (k-d tree on scaled coordinates)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


class NodeSearch:
    """k-d tree over the nodes in coordinates divided by a per-axis scale.

    With ``scale`` the largest support radius per axis, every node whose kernel support can
    contain a point lies within distance 1 of it in the scaled coordinates: Chebyshev distance
    (p = inf) for a box window, Euclidean (p = 2) for a spherical one. The candidates are a
    superset of the true neighbours when supports differ between nodes; the caller filters them.

    Parameters
    ----------
    nodes : ndarray, shape (N, d), cm
    scale : ndarray, shape (d,), cm
    metric_p : float
        Minkowski p of the search (``np.inf`` or 2).
    """

    def __init__(self, nodes, scale, metric_p):
        self.scale = np.asarray(scale, dtype=float)
        self.p = metric_p
        self.n_nodes = nodes.shape[0]
        self.tree = cKDTree(nodes / self.scale)

    def pairs(self, points):
        """Candidate pairs for a block of points.

        Parameters
        ----------
        points : ndarray, shape (P, d), cm

        Returns
        -------
        rows : ndarray, shape (n,), int64
            Point index (0..P-1), sorted ascending.
        cols : ndarray, shape (n,), int64
            Node index, sorted ascending within each row.
        """
        if points.shape[0] == 0 or self.n_nodes == 0:
            empty = np.zeros(0, dtype=np.int64)
            return empty, empty
        ptree = cKDTree(points / self.scale)
        found = ptree.sparse_distance_matrix(self.tree, 1.0, p=self.p, output_type="ndarray")
        rows = found["i"].astype(np.int64)
        cols = found["j"].astype(np.int64)
        order = np.argsort(rows * self.n_nodes + cols)
        return rows[order], cols[order]

"""Which rank owns which node, and which nodes a rank must hold to compute its own rows exactly.

:func:`bisection_partition` cuts the nodes by recursive coordinate bisection on the voxel grid:
each cut is a plane across the axis with the most voxels, placed so that the two sides get node
counts in proportion to the ranks they go to. The cuts are not limited to whole slices, so any
number of ranks up to the number of nodes can be used, and the cut faces stay small (a leg of
120 × 120 voxels in-plane and 50 slices is cut in-plane first).

:func:`halo` gives the nodes within a box of voxels around a rank's own nodes (Chebyshev distance
per axis on the voxel grid, by dilation of the grid's occupancy): the nodes whose data a rank needs
to evaluate its rows; :func:`halo_depth` is that depth for the pixel-point model, :func:`cell_depth`
the depth of the integration cells those rows need, both for the model's largest support.
:func:`needed` then takes each node's own support: the cells and nodes a rank's rows need when
only a few supports (beside thin features) are enlarged.

References
----------
Berger, M. J. & Bokhari, S. H. (1987). A partitioning strategy for nonuniform problems on
multiprocessors. IEEE Transactions on Computers C-36(5), 570–580.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage


def cell_depth(a_over_h, patch=(1, 1, 1), enlarged: float = 1.0) -> np.ndarray:
    """Voxels (i, j, k) around a rank's nodes within which lie the integration cells its rows need.

    With supports of s = a/h · ``enlarged`` voxels per axis (the largest RK support of the model,
    nominal times its largest enlargement beside thin features), the integration points of a cell
    lie half a voxel from its centre, so the cells that couple to an owned node lie within
    c = ⌈s + ½⌉ − 1 voxels of it, and the volumetric patches (``patch`` voxels, 2 × 2 × 3 by
    default) of those cells reach patch − 1 voxels further: c + patch − 1.
    """
    return _reach(a_over_h, enlarged) + np.broadcast_to(np.asarray(patch, np.int64), (3,)) - 1


def halo_depth(a_over_h, patch=(1, 1, 1), enlarged: float = 1.0) -> np.ndarray:
    """Voxels (i, j, k) of halo around a rank's nodes for the exact rows of its nodes: the cells of
    :func:`cell_depth` and, c voxels further, the nodes their shape functions take (2c + patch − 1;
    nominal a/h = 1.65 and 2 × 2 × 3 patches: (5, 5, 6))."""
    return cell_depth(a_over_h, patch, enlarged) + _reach(a_over_h, enlarged)


def _reach(a_over_h, enlarged: float) -> np.ndarray:
    """c = ⌈s + ½⌉ − 1 per axis: the voxels between a cell and the farthest node its integration
    points (half a voxel from its centre) take, supports of s = a/h · ``enlarged`` voxels."""
    return reach(np.broadcast_to(np.asarray(a_over_h, float), (3,)) * float(enlarged))


def reach(support_voxels: np.ndarray) -> np.ndarray:
    """c = ⌈s + ½⌉ − 1 (same shape as ``support_voxels``): for a node with a support of s voxels
    along an axis, the voxels between it and the farthest cell whose integration points (half a
    voxel from the cell's centre) it reaches."""
    return np.ceil(np.asarray(support_voxels, float) + 0.5 - 1e-9).astype(np.int64) - 1


def needed(ijk: np.ndarray, owned: np.ndarray, node_reach: np.ndarray, patch=(1, 1, 1)) -> tuple[np.ndarray, np.ndarray]:
    """The integration cells and the nodes that the rows of the ``owned`` nodes need, node by node.

    The row of an owned node I takes the cells within its reach c_I (:func:`reach`) and, through
    the volumetric patches, every cell of their patches (``patch`` − 1 voxels further); a cell
    takes every node J whose own reach c_J covers it. With every reach the model's largest this is
    :func:`halo` at :func:`cell_depth` and :func:`halo_depth`; with a few enlarged supports it is less.

    Parameters
    ----------
    ijk : (N, 3) int
        Voxel indices of the nodes (cells sit at the nodes' voxels).
    owned : (N,) bool
    node_reach : (N, 3) int
        c of every node per axis.
    patch : (3,) int
        Voxels of a volumetric patch per axis ((1, 1, 1) without patches).

    Returns
    -------
    cells, nodes : (N,) bool
        The cells (at the nodes' voxels) the owned rows need, and the nodes those cells need (the
        owned nodes among them).
    """
    node_reach = np.asarray(node_reach, np.int64)
    widen = np.broadcast_to(np.asarray(patch, np.int64), (3,)) - 1
    cells = np.zeros(len(ijk), bool)
    for c in np.unique(node_reach[owned], axis=0):
        cells |= halo(ijk, owned & np.all(node_reach == c, axis=1), c + widen)
    nodes = owned.copy()
    for c in np.unique(node_reach, axis=0):
        of_c = np.all(node_reach == c, axis=1)
        nodes |= of_c & halo(ijk, cells, c)
    return cells, nodes


def cover_margin(a_over_h, enlarged: float = 1.0) -> np.ndarray:
    """Voxels beyond :func:`halo_depth` whose nodes take part in the support coverage, so that the
    supports of the halo's nodes are those of the whole model: :func:`pixmuscle.rk.covering_supports`
    enlarges the nodes within 2 nominal supports of a singular point, whose singularity depends on
    the nodes within one (enlarged) support of it."""
    a = np.broadcast_to(np.asarray(a_over_h, float), (3,))
    return np.ceil(2.0 * a + a * float(enlarged)).astype(np.int64) + 1


def bisection_partition(ijk: np.ndarray, parts: int) -> np.ndarray:
    """Rank of every node by recursive coordinate bisection on the voxel grid.

    Parameters
    ----------
    ijk : (N, 3) int
        Voxel indices of the nodes.
    parts : int
        Number of ranks, 1 ≤ parts ≤ N.

    Returns
    -------
    rank : (N,) int64
        0 … parts − 1; the node counts per rank differ by at most the nodes of one grid plane
        per cut (a cut never splits a plane of voxels across the cut axis).
    """
    ijk = np.asarray(ijk, np.int64)
    n = ijk.shape[0]
    if not 1 <= parts <= max(n, 1):
        raise ValueError(f"cannot cut {n} nodes into {parts} parts")
    rank = np.zeros(n, np.int64)
    work = [(np.arange(n), 0, parts)]
    while work:
        idx, first, count = work.pop()
        if count == 1:
            rank[idx] = first
            continue
        pts = ijk[idx]
        extent = pts.max(axis=0) - pts.min(axis=0)
        axis = int(np.argmax(extent))
        left = count // 2
        order = np.argsort(pts[:, axis], kind="stable")
        keys = pts[order, axis]
        want = (idx.size * left) // count
        # the plane boundary nearest to the wanted count (whole planes stay on one side)
        lo = np.searchsorted(keys, keys[max(want - 1, 0)], side="right")
        hi = np.searchsorted(keys, keys[min(want, idx.size - 1)], side="left")
        cut = lo if abs(lo - want) <= abs(hi - want) else hi
        cut = min(max(cut, 1), idx.size - 1)
        work.append((idx[order[:cut]], first, left))
        work.append((idx[order[cut:]], first + left, count - left))
    return rank


def halo(ijk: np.ndarray, inner: np.ndarray, depth) -> np.ndarray:
    """Nodes within ``depth`` voxels (per axis) of the nodes ``inner``.

    Parameters
    ----------
    ijk : (N, 3) int
        Voxel indices of all nodes.
    inner : (N,) bool
        The nodes to grow from.
    depth : int or (3,) int
        Voxels per axis.

    Returns
    -------
    (N,) bool
        ``inner`` and every node whose voxel lies in the box of ``depth`` voxels around one of them.
    """
    ijk = np.asarray(ijk, np.int64)
    depth = np.broadcast_to(np.asarray(depth, np.int64), (3,))
    lo = ijk.min(axis=0)
    shape = tuple(ijk.max(axis=0) - lo + 1)
    grid = np.zeros(shape, bool)
    at = tuple((ijk[inner] - lo).T)
    grid[at] = True
    grown = ndimage.maximum_filter(grid, size=tuple(2 * depth + 1), mode="constant", cval=False)
    return grown[tuple((ijk - lo).T)]

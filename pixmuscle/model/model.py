"""The pixel-point model: nodes on voxel centres with tissue, muscle and fibre data (paper §4.2).

A :class:`Model` is pure data. It is written to and read from ``model.h5`` (schema
``pixmuscle.model`` v1, layout in docs/architecture.md) by :mod:`pixmuscle.io.model`.
"""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass
class Model:
    """Pixel-point model in the grid-aligned model frame (cm).

    Attributes
    ----------
    X : (N, 3) float64
        Node coordinates (voxel centres), cm.
    ijk : (N, 3) int32
        Voxel index of each node in the model grid.
    tissue : (N,) int8
        Tissue code (1 muscle, 2 connective tissue, 3 fat), see :mod:`pixmuscle.model.tissues`.
    muscle_id : (N,) int16
        1..M for muscle nodes (index into ``muscle_names`` + 1), 0 otherwise.
    fiber : (N, 3) float64
        Unit fibre direction in the reference configuration; zero rows where tissue is not muscle.
    muscle_names : list of str
        Names of the M muscles.
    spacing : (3,) float64
        Cell edge lengths, cm. Every node's integration cell is the box ``X ± spacing/2``.
    origin : (3,) float64
        Coordinates of voxel (0, 0, 0), cm.
    shape : (3,) int
        Grid shape.
    rotation : (3, 3) float64
        Residual rotation from the model frame to the scanner frame (identity for non-oblique scans).
    sets : dict of str → (n,) int64
        Named node sets (indices into the node arrays).
    coarsen_factor : int
        1 for the fine model, 2 for the paper's coarse model, ...
    bone_ijk : (B, 3) int32 or None
        Grid indices of the bone voxels (not nodes). Kept so that a coarsened model can recompute
        ``bone_surface`` on its own grid (:func:`pixmuscle.model.coarsen.coarsen_model`).
        Stored as ``/grid/bone_ijk`` when present.
    """

    X: np.ndarray
    ijk: np.ndarray
    tissue: np.ndarray
    muscle_id: np.ndarray
    fiber: np.ndarray
    muscle_names: list
    spacing: np.ndarray
    origin: np.ndarray
    shape: np.ndarray
    rotation: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(3))
    sets: dict = dataclasses.field(default_factory=dict)
    coarsen_factor: int = 1
    bone_ijk: np.ndarray | None = None

    @property
    def n_nodes(self) -> int:
        return int(self.X.shape[0])

    @property
    def cell_volume(self) -> float:
        """Volume of one integration cell, cm³."""
        return float(np.prod(self.spacing))

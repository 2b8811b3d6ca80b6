"""A linear-solver backend added in one file: dense LU of the assembled tangent (registered as ``dense``).

For tiny models only: the tangent is held as a dense (3N × 3N) array and solved by
``numpy.linalg.solve`` (LAPACK gesv). Importing this module registers the backend; nothing else in
pixmuscle changes.
"""

from __future__ import annotations

import dataclasses
from dataclasses import field

import numpy as np

from pixmuscle.mechanics.linsolve import BACKENDS, LinearSolver


@dataclasses.dataclass(frozen=True)
class DenseOptions:
    """Options of ``solve.solver: {backend: dense, …}``."""

    max_dofs: int = field(default=3000, metadata={"range": (1, None), "doc": "most unknowns (3 per node): the matrix is dense"})


@BACKENDS.register("dense", options=DenseOptions)
class DenseSolver(LinearSolver):
    """K x = r by LAPACK on the dense assembled tangent (:meth:`LinearSolver.prepare` assembles it)."""

    name = "dense"

    def __init__(self):
        super().__init__()
        self._K = None
        self.solves = 0

    @classmethod
    def from_options(cls, opts: DenseOptions, X, *, ijk=None, width=(4, 4, 4)) -> DenseSolver:
        if 3 * len(X) > opts.max_dofs:
            raise ValueError(f"solve.solver.max_dofs: {3 * len(X)} unknowns exceed {opts.max_dofs}; use backend: direct")
        return cls()

    def factorize(self, K) -> None:
        self._K = K.toarray()

    def solve(self, r, rtol=None):
        self.solves += 1
        self.info["iterations"] = 1
        return np.linalg.solve(self._K, r)

    def statistics(self) -> dict:
        return super().statistics() | {"dense_solves": self.solves}

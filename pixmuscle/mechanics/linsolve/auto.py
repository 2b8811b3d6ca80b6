"""Backend ``auto``: ``direct`` up to a number of unknowns, ``cg_amg`` above."""

from __future__ import annotations

import dataclasses
from dataclasses import field

import numpy as np

from .base import BACKENDS, Iterative, LinearSolver
from .factorization import engine_name

# direct up to here: PARDISO + reuse is faster than cg_amg at 11.5k nodes (351 s against 626 s for the
# benchmark sweep) and slower at 21k (2,244 s against ~1,200 s extrapolated), docs/performance.md
AUTO_DIRECT_MAX_DOFS = {"pardiso": 45_000, "superlu": 12_000}


@dataclasses.dataclass(frozen=True)
class AutoOptions(Iterative):
    """Options of ``solve.solver: {backend: auto, …}`` (the default): ``rtol`` and ``maxiter`` go to
    the backend chosen."""

    direct_max_dofs: int | None = field(default=None, metadata={"range": (0, None), "doc": "direct solver up to this many unknowns (3 per node), cg_amg above; default 45,000 (15k nodes: the measured cross-over with cg_amg, ~2.5 GB of factors) with PARDISO, 12,000 with SuperLU"})


@BACKENDS.register("auto", options=AutoOptions)
class Auto:
    """Chooses a backend by the size of the model: ``direct`` up to ``direct_max_dofs`` unknowns
    (default :data:`AUTO_DIRECT_MAX_DOFS` of the direct engine: beyond, the factors outgrow the
    memory), ``cg_amg`` above."""

    @staticmethod
    def from_options(opts: AutoOptions, X, *, ijk=None, width=(4, 4, 4)) -> LinearSolver:
        limit = opts.direct_max_dofs
        if limit is None:
            limit = AUTO_DIRECT_MAX_DOFS[engine_name("auto")]
        entry = BACKENDS.get("direct" if 3 * np.asarray(X).shape[0] <= limit else "cg_amg")
        mine = {f.name for f in dataclasses.fields(opts)}
        shared = {f.name: getattr(opts, f.name) for f in dataclasses.fields(entry.options) if f.name in mine}
        return entry.obj.from_options(entry.options(**shared), X, ijk=ijk, width=width)

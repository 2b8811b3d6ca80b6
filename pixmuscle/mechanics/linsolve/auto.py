"""Backend ``auto``: ``direct`` up to a number of unknowns, ``mixed_amg`` above (``cg_amg`` without a projected volumetric energy)."""

from __future__ import annotations

import dataclasses
from dataclasses import field
from typing import Literal

import numpy as np

from .base import BACKENDS, Iterative, LinearSolver
from .factorization import engine_name
from .multigrid import AMG_CHOICES

# direct up to here: PARDISO + reuse is faster than the iterative path at 5k nodes (40 s against 171 s for
# the benchmark sweep with mixed_amg) and its factors outgrow the memory at ~30k nodes, docs/performance.md
AUTO_DIRECT_MAX_DOFS = {"pardiso": 45_000, "superlu": 12_000}


@dataclasses.dataclass(frozen=True)
class AutoOptions(Iterative):
    """Options of ``solve.solver: {backend: auto, …}`` (the default): ``rtol`` and ``maxiter`` go to
    the backend chosen."""

    rebuild_cost: int = field(default=40, metadata={"range": (1, None), "doc": "with mixed_amg (above direct_max_dofs): what a build of the AMG hierarchy costs, in Krylov iterations (see mixed_amg)"})
    give_up: float = field(default=4.0, metadata={"gt": 0, "doc": "with mixed_amg: how many times the last measured iterations per decade a fresh AMG hierarchy may take before the solve fails (see cg_amg)"})
    amg: str = field(default="auto", metadata={"choices": AMG_CHOICES, "doc": "with mixed_amg: the multigrid, hypre BoomerAMG or pyamg (see cg_amg); auto takes hypre where petsc4py with hypre is installed"})
    amg_processes: int | Literal["auto"] = field(default="auto", metadata={"range": (1, None), "doc": "with mixed_amg: processes BoomerAMG runs on, this one and amg_processes − 1 spawned MPI workers; auto: 2 from 50,000 nodes on where the run has 2 cores of its own, else 1 (see cg_amg)"})
    region_precision: str = field(default="double", metadata={"choices": ("double", "single"), "doc": "with mixed_amg: precision of the region factors (see mixed_amg)"})
    region_coupling: str = field(default="auto", metadata={"choices": ("auto", "components", "full"), "doc": "with mixed_amg: what is factorised on a region, each displacement component's block, the whole block, or auto (see mixed_amg)"})
    direct_max_dofs: int | None = field(default=None, metadata={"range": (0, None), "doc": "direct solver up to this many unknowns (3 per node), mixed_amg above (cg_amg with the nodal volumetric energy); default 45,000 (15k nodes) with PARDISO, 12,000 with SuperLU: where the iterative solver overtakes the factorisation (docs/performance.md)"})


@BACKENDS.register("auto", options=AutoOptions)
class Auto:
    """Chooses a backend by the size of the model: ``direct`` up to ``direct_max_dofs`` unknowns
    (default :data:`AUTO_DIRECT_MAX_DOFS` of the direct engine: beyond, the factors outgrow the
    memory), ``mixed_amg`` above (which runs CG as ``cg_amg`` when there is no patch pressure)."""

    @staticmethod
    def from_options(opts: AutoOptions, X, *, ijk=None, width=(4, 4, 4)) -> LinearSolver:
        limit = opts.direct_max_dofs
        if limit is None:
            limit = AUTO_DIRECT_MAX_DOFS[engine_name("auto")]
        entry = BACKENDS.get("direct" if 3 * np.asarray(X).shape[0] <= limit else "mixed_amg")
        mine = {f.name for f in dataclasses.fields(opts)}
        shared = {f.name: getattr(opts, f.name) for f in dataclasses.fields(entry.options) if f.name in mine}
        return entry.obj.from_options(entry.options(**shared), X, ijk=ijk, width=width)

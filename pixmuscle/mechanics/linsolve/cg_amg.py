"""Iterative backend ``cg_amg``: CG on the matrix-free tangent with an algebraic multigrid preconditioner
(hypre BoomerAMG or pyamg smoothed aggregation, :mod:`.multigrid`).

The tangent of activated muscle can be indefinite (an active fibre stress on the descending limb of
the force–length curve, a passive law that loses ellipticity): CG then meets a direction of
negative curvature (pᵀ K p ≤ 0) and cannot go on. That system is solved again by flexible GMRES
(:func:`.fgmres.fgmres`, which needs no definiteness) with the same AMG preconditioner, so Newton
gets its update instead of a cut-back load step.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import field
from typing import Literal

import numpy as np
import scipy.sparse as sp

from ...errors import SolverError, SolverGaveUp
from ..heap import release_free_heap
from .amg_processes import flush_released, group
from .base import BACKENDS, Iterative, LinearSolver, SolverMemory, built_from, memory_state, pcg
from .fgmres import fgmres
from .multigrid import AMG_CHOICES, auto_processes, resolve, v_cycle
from .rebuild import RebuildPolicy

_LOG = logging.getLogger(__name__)


def voxel_aggregates(ijk: np.ndarray, block=(3, 3, 1)) -> sp.csr_matrix:
    """Geometric aggregation of grid nodes into boxes of ``block`` voxels (N × N_agg, 0/1 CSR).

    Used as pyamg's first-level aggregation: on the wide SCNI stiffness (~300 block neighbours
    per node) pyamg's standard aggregation makes very few, very large aggregates and a weak
    two-level method; voxel boxes give a proper hierarchy and halve the iteration count
    (docs/linsolve-research.md §2(b)).
    """
    key = np.asarray(ijk, np.int64) // np.asarray(block, np.int64)
    _, agg = np.unique(key, axis=0, return_inverse=True)
    agg = agg.ravel()
    n = agg.shape[0]
    return sp.csr_matrix((np.ones(n), (np.arange(n), agg)), shape=(n, int(agg.max()) + 1))


@dataclasses.dataclass(frozen=True)
class CGAMGOptions(Iterative):
    """Options of ``solve.solver: {backend: cg_amg, …}``: tolerance, iterations, rebuild cost."""

    rebuild_cost: int = field(default=100, metadata={"range": (1, None), "doc": "what a build of the AMG hierarchy costs, in Krylov iterations: the hierarchy is rebuilt once the iterations beyond its rate right after the last build add up to this many (within a solve too). Counted in iterations, not seconds, so that a run repeats itself exactly"})
    give_up: float = field(default=4.0, metadata={"gt": 0, "doc": "a solve with a hierarchy that has not yet converged a solve stops after give_up × (the last measured iterations per decade) × decades + rebuild_cost iterations: such a system is far harder than the earlier ones (an overshooting Newton update), and Newton does better to cut the load increment back"})
    amg: str = field(default="auto", metadata={"choices": AMG_CHOICES, "doc": "the multigrid: `hypre` (BoomerAMG through petsc4py, compiled; faster set-up and cycle than pyamg), `pyamg` (smoothed aggregation, always installed), `auto` (hypre where petsc4py with hypre is installed, else pyamg)"})
    amg_processes: int | Literal["auto"] = field(default="auto", metadata={"range": (1, None), "doc": "processes BoomerAMG runs on: this one and amg_processes − 1 MPI workers it spawns (mpi4py, no mpiexec needed; hypre only). Each set-up and V-cycle then runs on that many cores (at most the run's cores); the rest of the run stays in one process (linsolve/amg_processes.py). auto: 2 from 50,000 nodes on where the run has 2 cores of its own (not in a Dask cohort that runs a model per core, not under mpiexec), else 1; with auto a failed start of the worker falls back to 1 with a warning"})


@BACKENDS.register("cg_amg", options=CGAMGOptions)
class KrylovAMGSolver(LinearSolver):
    """CG on the matrix-free tangent, preconditioned by algebraic multigrid (:mod:`.multigrid`).

    Parameters
    ----------
    X : (N, 3) float
        Node coordinates, cm (rigid-body modes).
    ijk : (N, 3) int
        Voxel indices (geometric aggregates and the filtered preconditioner matrix).
    rtol : float
        Relative residual when the caller gives none.
    maxiter : int
        CG iterations per solve.
    reach : int
        Blocks of node pairs at most this many voxels apart enter the preconditioner matrix.
    aggregate : (3,) int
        First-level aggregates of pyamg, voxels per axis.
    theta : float
        Strength-of-connection threshold of pyamg.
    restart : int
        FGMRES basis size for an indefinite system (below).
    rebuild_cost : int
        What one build of the hierarchy costs, in Krylov iterations (:class:`.rebuild.RebuildPolicy`).
    give_up : float
        A hierarchy that has not converged a solve yet gets ``give_up`` times the last measured
        rate (:class:`.rebuild.RebuildPolicy`).
    amg : {"auto", "hypre", "pyamg"}
        The multigrid (:func:`.multigrid.resolve`).
    amg_processes : int or "auto"
        Processes BoomerAMG runs on (:mod:`.amg_processes`); more than 1 needs hypre. ``"auto"``:
        :func:`.multigrid.auto_processes` of the model's size, falling back to 1 (with a warning)
        where the workers do not start.
    policy : RebuildPolicy, optional
        When to rebuild the hierarchy (default: the rule of ``rebuild_cost``, ``give_up`` and
        ``maxiter``); the solver holds it as :attr:`policy`.

    Notes
    -----
    Indefinite systems: when CG stops on negative curvature the same system is solved by
    FGMRES (restart ``restart``) with the same preconditioner, from zero, to the same relative
    residual; ``info["indefinite_solves"]`` counts them.

    Rebuild policy: :class:`.rebuild.RebuildPolicy` (the "ski-rental" rule counted in iterations),
    held as :attr:`policy`; a solve the give-up budget stops fails with
    :class:`~pixmuscle.errors.SolverGaveUp`, so that Newton cuts the load increment back.
    What a build costs in iterations depends on the backend: for ``mixed_amg`` at 74k nodes
    (hypre on 2 processes) a rebuild takes 18–19 s (filtered stand-in 2.3 s, BoomerAMG 4.4 s,
    region factors 4.4 s, probed Schur diagonal 7.5 s) against 0.42 s per FGMRES iteration,
    ~44 iterations (its default: 40); a CG iteration here is cheaper and a pyamg set-up dearer
    (62–137 s at 74k), hence 100 for ``cg_amg``. The rule counts
    iterations, not seconds, so that two runs of the same config take the same decisions and give
    the same numbers. The matrix-free operator is always the exact tangent, so a stale
    preconditioner costs iterations, never accuracy.
    """

    name = "cg_amg"

    def __init__(self, X, ijk, rtol: float = 1e-8, maxiter: int = 2000, reach: int = 2, aggregate=(3, 3, 1),
                 theta: float = 0.1, restart: int = 100, rebuild_cost: int = 100, give_up: float = 4.0,
                 amg: str = "auto", amg_processes: int | str = "auto", policy: RebuildPolicy | None = None):
        super().__init__()
        auto = amg_processes == "auto"
        self.amg = resolve(amg, 1 if auto else amg_processes)
        self.amg_processes = auto_processes(self.amg, len(X)) if auto else amg_processes
        if auto and self.amg_processes > 1:  # settled here, before a resumed solve compares memory tags
            try:
                group(self.amg_processes)
            except SolverError as exc:  # chosen, not asked for: one process does the same job, slower
                msg = (f"solve.solver.amg_processes: auto chose {self.amg_processes} processes, but MPI did not start "
                       f"the worker ({exc.reason}); BoomerAMG runs on this process only")
                _LOG.warning(msg)
                self.warnings.append(msg)
                self.amg_processes = 1
        self.policy = RebuildPolicy(rebuild_cost, give_up, maxiter) if policy is None else policy
        self.restart = restart
        self.B = None  # the near-null space of the system (rigid-body modes), taken at the first build
        self.ijk = np.asarray(ijk)
        self.rtol = rtol
        self.maxiter = maxiter
        self.reach = reach
        self.aggregate = aggregate
        self.theta = theta
        self._M = None
        self._system = None
        self._state = None
        self._built_at = None  # (d, t, α, carried pressure) of the state the hierarchy was built from
        self.info.update(preconditioner_builds=0, build_s=[], krylov_iterations=0, levels=0, operator_complexity=0.0,
                         indefinite_solves=0, amg=self.amg)

    @classmethod
    def from_options(cls, opts, X, *, ijk=None, width=(4, 4, 4)):
        if ijk is None:
            raise ValueError(f"{cls.name} needs the voxel indices ijk of the nodes")
        return cls(X, ijk, **dataclasses.asdict(opts))

    def _build(self):
        t0 = time.perf_counter()
        self._M = None  # release the old hierarchy before the new one is built (peak memory)
        release_free_heap()  # and its pages, which the new one would not all reuse
        aggregates = voxel_aggregates(self.ijk, self.aggregate) if self.amg == "pyamg" else None
        if self.B is None:
            self.B = self._system.near_null_space()
        self._M = v_cycle(self.amg, self._stand_in, self.B, aggregates, self.theta, self.amg_processes)  # made and released inside
        self.info["preconditioner_nnz_per_row"] = self._M.nnz_per_row
        self.info["levels"] = self._M.levels
        self.info["operator_complexity"] = self._M.operator_complexity
        self.info["preconditioner_builds"] += 1
        self.info["setup_s"] += time.perf_counter() - t0
        self.info["build_s"].append(time.perf_counter() - t0)
        self.policy.built()
        self._built_at = built_from(self._state)
        release_free_heap()  # the stand-in's and the set-up's temporaries

    def _stand_in(self) -> sp.bsr_matrix:
        """The matrix the AMG hierarchy is built from: a filtered positive stand-in of the tangent."""
        return self._system.preconditioner_matrix(self._state, self.reach)

    def _fail(self, method: str, status: str, total: int, rtol: float) -> SolverError:
        """The error of a solve by ``method`` that ended with ``status`` after ``total`` iterations:
        :class:`~pixmuscle.errors.SolverGaveUp` when the give-up budget stopped it (the hierarchy,
        built for a state Newton will now leave, is then rebuilt at the next system)."""
        if self.policy.gave_up(status, total):
            return SolverGaveUp(
                f"{self.name}: {method} gave up after {total} iterations (relative residual target {rtol:.1e}): this "
                f"system needs far more than the earlier ones (solver.give_up: {self.policy.give_up:g}), e.g. after an "
                "overshooting Newton update; a smaller load increment (solve.steps) helps")
        return SolverError(f"{self.name}: {method} {status} after {total} iterations (relative residual target {rtol:.1e}); "
                           "check the boundary conditions (a free rigid-body motion makes K singular), or use "
                           "solver.backend: direct on small models")

    def prepare(self, system, state):
        self.info["setup_s"] = 0.0
        self._system, self._state = system, state
        self._A = system.tangent_operator(state)
        self.policy.new_system()
        if self.policy.must_build(self._M is not None):
            self._build()

    def solve(self, r, rtol=None):
        t0 = time.perf_counter()
        setup0 = self.info["setup_s"]
        rtol = self.rtol if rtol is None else max(float(rtol), 1e-14)
        b = np.asarray(r, float)
        x, its, status = pcg(self._A, b, self._M, rtol, self.policy.budget(rtol))
        total, method, rebuilt = its, "CG", False
        if self.policy.may_rebuild(status, total):
            _LOG.debug("CG: %d iterations with a kept preconditioner cost more than a rebuild; rebuilding it", its)
            self._build()
            x, its, status = pcg(self._A, b, self._M, rtol, self.policy.retry_budget(rtol, total), x0=x)
            total += its
            rebuilt = True
        if status == "breakdown":  # negative curvature: the tangent is indefinite here
            _LOG.debug("CG met negative curvature after %d iterations; solving by FGMRES", its)
            self.info["indefinite_solves"] += 1
            x, its, status = fgmres(self._A, b, self._M, rtol, self.maxiter, restart=self.restart)
            total += its
            method = "FGMRES (after negative curvature in CG)"
        self.info["iterations"] = total
        self.info["krylov_iterations"] += total
        self.info["solve_s"] = time.perf_counter() - t0 - (self.info["setup_s"] - setup0)
        if status != "converged":
            raise self._fail(method, status, total, rtol)
        if not rebuilt:  # a solve continued after a rebuild does not show the new hierarchy's rate: the next one does
            self.policy.account(its, rtol)
        return x

    def finish(self) -> None:
        """Drop the tangent operator (the hierarchy stays)."""
        self._A = None

    def release(self) -> None:
        """Drop the hierarchy (on the BoomerAMG workers too) and the tangent operator."""
        self._M = None
        self._A = None
        self._system = self._state = None
        flush_released()
        release_free_heap()

    @property
    def memory_tag(self) -> str:
        # hierarchies spread over other numbers of processes differ in round-off: a resume with another one starts afresh
        return f"{self.name}/{self.amg}" + (f"/{self.amg_processes}" if self.amg_processes > 1 else "")

    def memory(self) -> SolverMemory | None:
        """The state the hierarchy was built from and the rebuild rule's counters."""
        if self._built_at is None:
            return None
        d, t, alpha, pressure = self._built_at
        return SolverMemory(d, t, alpha, pressure=pressure, counters=self.policy.counters(), backend=self.memory_tag)

    def recall(self, system, memory: SolverMemory) -> None:
        """Build the hierarchy from the tangent at ``memory``'s state and restore the counters (a
        hierarchy the rule had marked stale is not rebuilt here: the next Newton system rebuilds it).
        The operator of that state is let go at once (:meth:`finish`): the resumed load step
        evaluates its start state without it."""
        self._M = None
        if not memory.counters["stale"]:
            self.prepare(system, memory_state(system, memory))
            self.finish()
        self.policy.restore(memory.counters)

    def statistics(self) -> dict:
        """Name, ``amg`` (the multigrid) and ``amg_processes``, ``preconditioner_builds`` and
        ``preconditioner_build_s`` (the wall time of each build, s), ``krylov_iterations`` (all solves)
        and ``indefinite_solves`` (solves finished by FGMRES after negative curvature in CG)."""
        return super().statistics() | {"amg": self.amg, "amg_processes": self.amg_processes,
                                       "preconditioner_builds": self.info["preconditioner_builds"],
                                       "preconditioner_build_s": [round(t, 2) for t in self.info["build_s"]],
                                       "krylov_iterations": self.info["krylov_iterations"],
                                       "indefinite_solves": self.info["indefinite_solves"]}

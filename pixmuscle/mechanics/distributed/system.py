"""The discrete system of one MPI rank: its own nodes' rows, built from its nodes plus a halo.

Under ``mpiexec -n P`` with a PETSc backend, :func:`build_distributed_system` cuts the model by
recursive coordinate bisection (:func:`.partition.bisection_partition`) and each rank builds an
ordinary :class:`~..system.MechanicalSystem` on its *held* nodes: its own nodes and every node
their rows need (:func:`.partition.needed`: within :func:`.partition.halo_depth` voxels of them
where supports are nominal, further beside the few enlarged ones). Everything that rank keeps — the RK shape
functions and SCNI operators, the materials and their moduli, the stabilisation and penalty
operators, the volumetric patches — is of the held nodes only. Its own nodes' rows of the residual
and the tangent are exact: every integration cell and patch they need, and every node those cells'
shape functions need, is held. Three things of the whole model are made the same on every rank:
the RK supports (covered over a wider box, :func:`.partition.cover_margin`; the halo is deepened
to the model's largest enlarged support), the penalty number β
(the largest modulus over all nodes) and the residual floor (from the total node count).

:class:`DistributedSystem` gives Newton (:mod:`..newton`) and the PETSc backends the owned rows:
vectors of the rank's own nodes (n, 3) and own pressure patches; each evaluation brings the halo's
displacements (and carried pressures) from their owners, evaluates the held system and keeps the
owned rows; norms and slopes are summed over the ranks (:meth:`DistributedSystem.inner`). The
results of a converged step are gathered to rank 0 in model order (:meth:`DistributedSystem.step_output`).
On one rank it is the serial system itself with an identity layout.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from ...errors import InputError, SolverError
from ...model.model import Model
from ..boundary import check_boundary_conditions, end_rule, penalty_number
from ..config import SolveConfig
from ..scni import support_radius
from ..system import MechanicalSystem, State, build_system, reference_moduli, rk_supports, solve_materials
from .layout import Layout, PatchLayout
from .partition import bisection_partition, cover_margin, halo, halo_depth, needed, reach

_LOG = logging.getLogger(__name__)


def submodel(model: Model, keep: np.ndarray) -> Model:
    """The nodes ``keep`` (ascending model indices) of ``model`` as a model of their own (node sets
    renumbered to them and cut to them; the grid, bones and muscle names unchanged)."""
    keep = np.asarray(keep, np.int64)
    local = np.full(model.n_nodes, -1, np.int64)
    local[keep] = np.arange(keep.size)
    sets = {}
    for name, idx in model.sets.items():
        mine = local[np.asarray(idx, np.int64)]
        sets[name] = mine[mine >= 0]
    return dataclasses.replace(model, X=np.asarray(model.X)[keep], ijk=np.asarray(model.ijk)[keep],
                               tissue=np.asarray(model.tissue)[keep], muscle_id=np.asarray(model.muscle_id)[keep],
                               fiber=np.asarray(model.fiber)[keep], sets=sets)


def global_penalty_number(model: Model, cfg: SolveConfig, nodes: np.ndarray, layout: Layout) -> float:
    """β of :func:`..boundary.penalty_number` over the whole model: each rank's largest modulus of
    its own ``nodes``, the largest over the ranks."""
    if cfg.penalty.beta is not None:
        return float(cfg.penalty.beta)
    A0 = reference_moduli(np.asarray(model.tissue)[nodes], np.asarray(model.fiber)[nodes], solve_materials(cfg))
    largest = max((float(np.max(A0[:, i, J, i, J])) for i in range(3) for J in range(3)), default=0.0) if nodes.size else 0.0
    largest = layout.max(largest)
    return penalty_number(np.full((1, 3, 3, 3, 3), largest), model.spacing, cfg.penalty.factor)


def build_distributed_system(model: Model, cfg: SolveConfig, comm=None) -> tuple[DistributedSystem, dict]:
    """This rank's :class:`DistributedSystem` of ``model`` (module docstring); ``comm`` PETSc's
    COMM_WORLD by default. Every rank passes the whole model; what it keeps is its held part.

    Raises
    ------
    InputError
        A boundary condition at a ``point`` (its nearest node is not known to every rank).
    """
    from ...parallel import import_petsc

    PETSc = import_petsc()
    comm = comm or PETSc.COMM_WORLD
    size, rank = comm.getSize(), comm.getRank()
    bcs = list(cfg.boundary_conditions)
    check_boundary_conditions(model, bcs)
    for b, bc in enumerate(bcs):
        if bc.point is not None and size > 1:
            raise InputError(f"solve.boundary_conditions[{b}]: a condition at a point is not supported under mpiexec "
                             "yet; name a node set (nodes: ...) or run on one process")
    n = model.n_nodes
    part = bisection_partition(model.ijk, size)
    owned = part == rank
    mpi = comm.tompi4py()
    from mpi4py import MPI

    # the halo depth follows the largest support of the model: a first cut at nominal supports tells it
    held, supports, largest = held_part(model, cfg, owned)
    largest = mpi.allreduce(largest, op=MPI.MAX)
    if largest > 1.0 + 1e-9:
        held, supports, _ = held_part(model, cfg, owned, largest)
    counts = np.bincount(part, minlength=size)
    order = np.argsort(part, kind="stable")  # PETSc order: by rank, each rank's nodes in model order
    petsc_of = np.empty(n, np.int64)
    petsc_of[order] = np.arange(n)
    own = np.flatnonzero(owned[held])
    layout = Layout(comm, n, own, petsc_of[held], held, np.asarray(model.X)[held], np.asarray(model.ijk)[held],
                    root_order=order if rank == 0 else None)
    del petsc_of, order, counts
    wide = np.any(supports[own] > supports[own].min(axis=0) * (1 + 1e-9), axis=1) if own.size else np.zeros(0, bool)
    enlarged = int(layout.sum(int(np.count_nonzero(wide))))
    if enlarged:
        _LOG.warning("RK supports enlarged at %d of %d nodes to cover thin features", enlarged, n)
    beta = global_penalty_number(model, cfg, np.flatnonzero(owned), layout)
    system, info = held_system(model, cfg, held, supports, beta, owned[held])
    info.update(n_nodes=n, supports_enlarged=enlarged, ranks=size, owned_nodes=int(own.size), held_nodes=int(held.size))
    n_points = layout.sum(int(np.count_nonzero(owned[held][system.constraints.node])))
    info["n_constraint_points"] = int(n_points)
    if not n_points:
        _LOG.warning("no boundary condition constrains any node: the stiffness is singular")
    return DistributedSystem(system, layout), info


def _patch(cfg: SolveConfig) -> tuple:
    """Voxels of a volumetric patch per axis ((1, 1, 1) without patches)."""
    return tuple(cfg.volumetric.patch) if cfg.volumetric.method == "projected" else (1, 1, 1)


def _needed(model: Model, cfg: SolveConfig, ijk: np.ndarray, owned: np.ndarray, supports: np.ndarray):
    """:func:`.partition.needed` for nodes at ``ijk`` with RK ``supports`` (n, 3) cm."""
    return needed(ijk, owned, reach(supports / np.asarray(model.spacing, float)), _patch(cfg))


def held_part(model: Model, cfg: SolveConfig, owned: np.ndarray, enlarged: float = 1.0) -> tuple[np.ndarray, np.ndarray, float]:
    """The nodes a rank holds for the exact rows of its ``owned`` (N,) bool nodes and their RK supports.

    Parameters
    ----------
    enlarged : float
        The largest enlargement of a support (against nominal) that the halo must allow for.

    Returns
    -------
    held : (n_held,) int
        Model indices, ascending, of the owned nodes and of the nodes their rows need
        (:func:`.partition.needed` with each node's support: within :func:`.partition.halo_depth`
        voxels of them where every support is the largest, fewer where only some are enlarged).
    supports : (n_held, 3) float
        Their supports as :func:`..system.node_supports` gives them for the whole model (the
        coverage is computed over :func:`.partition.cover_margin` more voxels), cm.
    largest : float
        The largest enlargement among the supports of the covered nodes.
    """
    ijk = np.asarray(model.ijk)
    a_h = cfg.support.a_over_h
    depth = halo_depth(a_h, _patch(cfg), enlarged)
    held = np.flatnonzero(halo(ijk, owned, depth))
    cover = np.flatnonzero(halo(ijk, owned, depth + cover_margin(a_h, enlarged)))
    with _quiet():  # the coverage of this part warns of its own enlargements: the caller counts the whole model's
        sup, _ = rk_supports(submodel(model, cover), cfg.support, corners=end_rule(cfg.penalty.at) == "vertices")
    largest = float(np.max(sup / support_radius(model.spacing, a_h))) if sup.size else 1.0
    sup = sup[np.searchsorted(cover, held)]
    if largest > enlarged * (1 + 1e-9):  # the caller asks again with the model's largest support
        return held, sup, largest
    keep = _needed(model, cfg, ijk[held], owned[held], sup)[1]
    return held[keep], sup[keep], largest


def held_system(model: Model, cfg: SolveConfig, held: np.ndarray, supports: np.ndarray, beta: float,
                owned: np.ndarray) -> tuple[MechanicalSystem, dict]:
    """The :class:`..system.MechanicalSystem` of the nodes ``held`` of ``model`` with the whole
    model's ``supports`` (n_held, 3) cm and penalty number ``beta`` N/cm³, for the rows of its
    ``owned`` (n_held,) bool nodes: the cells their rows do not need (:func:`.partition.needed`)
    are inert (F = I), and points at the cut edge with a singular moment matrix get no shape functions."""
    part = submodel(model, held)
    with _quiet():  # a part without an end set warns that the set is empty: not the whole model's news
        system, info = build_system(part, cfg, supports=supports, beta=beta, n_total=model.n_nodes, singular="empty")
    system.inert = ~_needed(model, cfg, part.ijk, owned, supports)[0]
    return system, info


class _quiet:
    """Warnings of the per-rank build off (they speak of the rank's part, not of the model)."""

    def __enter__(self):
        self.level = logging.root.manager.disable
        logging.disable(max(self.level, logging.WARNING))

    def __exit__(self, *exc):
        logging.disable(self.level)


@dataclasses.dataclass
class OwnedVolumetric:
    """What Newton reads of the volumetric state of a distributed state: the patch pressure
    K̄_p (θ_p − 1) of the rank's own patches, N/cm²."""

    pressure: np.ndarray


@dataclasses.dataclass
class DistributedState:
    """The state of a distributed system: the owned rows (``d``, ``r`` (n, 3)), the force scale
    over all ranks, the own patches' pressures, and the held system's :class:`~..system.State`
    (``held``) that the linear solvers build from."""

    d: np.ndarray
    t: float
    alpha: float
    r: np.ndarray
    force_scale: float
    held: State
    vol: OwnedVolumetric | None = None
    pressure: np.ndarray | None = None


class DistributedSystem:
    """One rank's rows of the discrete system (module docstring).

    Parameters
    ----------
    held : MechanicalSystem
        The system of the rank's held nodes (own plus halo).
    layout : Layout
        Which held nodes the rank owns, and the exchanges.

    Attributes
    ----------
    n_nodes : int
        The rank's own nodes (Newton's vectors are (n_nodes, 3)).
    n_global : int
        N, the nodes of the whole model.
    """

    def __init__(self, held: MechanicalSystem, layout: Layout):
        self.held = held
        self.layout = layout
        self.n_nodes = layout.n_own
        self.n_global = layout.n_global
        if layout.size > 1:
            held.counted = layout.own
        self._activation = None
        self._weight = None
        space = held.pressure_space()
        if space is not None:
            layout.patches = PatchLayout(layout, space.patch_of)

    @property
    def atol(self) -> float:
        """The residual floor of the whole model, N."""
        return self.held.atol

    @classmethod
    def single(cls, system, X: np.ndarray, ijk: np.ndarray) -> DistributedSystem:
        """The serial ``system`` (any :class:`~..linsolve.operator.SystemOperator`) with nodes at ``X``
        (N, 3) cm and voxel indices ``ijk`` as a distributed system of one rank."""
        return cls(system, Layout.single(X, ijk))

    @property
    def activation(self):
        return self._activation

    @activation.setter
    def activation(self, ramp) -> None:
        """The whole model's :class:`..activation.ActivationRamp`; the held system keeps its nodes' part."""
        self._activation = ramp
        idx = self.layout.model_index
        self.held.activation = None if ramp is None else dataclasses.replace(
            ramp, start=ramp.start[idx], end=ramp.end[idx], muscle=ramp.muscle[idx])

    # -- Newton ---------------------------------------------------------------------------------

    def inner(self, a: np.ndarray, b: np.ndarray) -> float:
        """Σ a·b over every rank's owned unknowns."""
        return float(self.layout.sum(float(np.vdot(a, b))))

    def _own_patches(self, p: np.ndarray | None):
        return None if p is None else np.asarray(p)[self.layout.patches.own]

    def evaluate(self, d: np.ndarray, t: float, alpha: float, pressure: np.ndarray | None = None) -> DistributedState:
        """The state at the owned coefficients ``d`` (n, 3) cm of every rank (collective); raises
        :class:`~pixmuscle.errors.SolverError` on every rank when a material point of any rank inverts."""
        lay = self.layout
        dh = lay.to_held(d)
        ph = None if pressure is None else lay.patches.to_held(pressure)
        try:
            st = self.held.evaluate(dh, t, alpha, ph)
            fail, sq = 0.0, st.norms_sq
        except SolverError as exc:
            st, fail, sq, why = None, 1.0, (0.0, 0.0), str(exc)
        total = lay.sum(np.array([sq[0], sq[1], fail]))
        if total[2] > 0:
            whys = lay.mpi.allgather(why if st is None else None)
            raise SolverError(next(w for w in whys if w is not None))
        own = lay.own
        vol = None if st.vol is None else OwnedVolumetric(self._own_patches(st.vol.pressure))
        return DistributedState(d=np.asarray(d, float).reshape(-1, 3), t=t, alpha=alpha, r=st.r[own],
                                force_scale=float(np.sqrt(max(total[0], total[1]))), held=st, vol=vol,
                                pressure=None if pressure is None else np.asarray(pressure, float))

    @property
    def pressure_weight(self) -> float:
        """w of :attr:`..system.MechanicalSystem.pressure_weight` over the free patches of all ranks."""
        return self.pressure_space().weight

    def pressure_space(self):
        """The held system's :class:`..pressure.PressureSpace` with the scale w of the whole model
        (the mean of μ_p V_p over every rank's own free patches); None without a projected energy."""
        space = self.held.pressure_space()
        if space is None or self._weight is not None or self.layout.size == 1:
            return space
        own = self.layout.patches.own
        free = own[~self.held.volumetric.held[own]]
        total = self.layout.sum(np.array([float(np.sum(space.shear[free] * space.volume[free])), float(free.size)]))
        self._weight = float(total[0] / max(total[1], 1.0)) / float(np.min(self.held.model.spacing))
        space = dataclasses.replace(space, weight=self._weight)
        self.held._pressure_space = space
        return space

    def mixed_residual(self, state: DistributedState):
        """The owned rows of :meth:`..system.MechanicalSystem.mixed_residual`: r_u (n, 3) and r_p of the own patches."""
        r_u, r_p = self.held.mixed_residual(state.held)
        return r_u[self.layout.own], self._own_patches(r_p)

    def linearised_pressure(self, state: DistributedState, dd: np.ndarray) -> np.ndarray:
        """The own patches' pressure after the update ``dd`` (n, 3) cm, linearised (collective)."""
        return self._own_patches(self.held.linearised_pressure(state.held, self.layout.to_held(dd)))

    # -- results --------------------------------------------------------------------------------

    def release_moduli(self, state: DistributedState) -> None:
        """Let go of the held state's moduli once its solve is done (as the serial system's
        :meth:`~..system.MechanicalSystem.release_moduli`); ``petsc_mixed`` has destroyed the
        operators that read them (its ``finish``), the condensed ``petsc`` keeps its own reference."""
        self.held.release_moduli(state.held)

    def gather(self, x: np.ndarray) -> np.ndarray | None:
        """Owned rows of every rank as one model-order array on rank 0 (None elsewhere)."""
        return self.layout.gather(x)

    def owned_of(self, x: np.ndarray) -> np.ndarray:
        """This rank's rows of a whole-model array (model order)."""
        return self.layout.owned_of(x)

    def step_output(self, state: DistributedState) -> dict:
        """:meth:`..system.MechanicalSystem.step_output` of the whole model: the nodal fields on
        rank 0 (None on the others), reactions, prescribed displacements and gaps on every rank."""
        lay, held, st = self.layout, self.held, state.held
        own = lay.own
        c = held.constraints
        mine = np.zeros(lay.n_held, bool)
        mine[own] = True
        points = mine[c.node]  # the constraint points of this rank's own nodes
        u = held.nodal_displacement(st.d)
        names = c.reaction_names
        react = {k: lay.sum(v) for k, v in c.reactions(st.d, st.t, points=points).items()}
        gaps = c.gaps(st.d, st.t, u, points=points)
        gaps = {k: {q: float(lay.max(v[q])) for q in v} for k, v in gaps.items()}
        pres, have = c.prescribed(st.t, points=points), c.present(points=points)
        presc = {k: lay.sum(pres[k] * have[k]) / max(lay.sum(float(have[k])), 1.0) for k in names}
        from ..results import cauchy_voigt

        return dict(d=self.gather(state.d), u=self.gather(u[own]), reaction=react, prescribed=presc, gaps=gaps,
                    cauchy=self.gather(cauchy_voigt(held.cauchy(st))[own]))

    def constrained_components(self) -> dict[str, np.ndarray]:
        """Constrained components per reaction name, (3,) bool, over all ranks."""
        return {k: self.layout.max(v.astype(float)) > 0 for k, v in self.held.constraints.constrained_components().items()}

    def ellipticity_minimum(self, state: DistributedState, directions: np.ndarray) -> np.ndarray | None:
        """The material law's smallest acoustic-tensor eigenvalue per node (N,) on rank 0, N/cm²."""
        q = self.held.ellipticity_minimum(state.held, directions)
        return self.gather(q[self.layout.own])

    def statistics(self) -> dict:
        """The held system's totals (this rank's) with ``ranks`` and the held and owned nodes."""
        return self.held.statistics() | {"ranks": self.layout.size, "owned_nodes": self.layout.n_own,
                                         "held_nodes": self.layout.n_held}

    def memory_for_checkpoint(self, memory):
        """A solver memory with its owned ``d`` gathered to rank 0 (its pressure in PETSc patch order)."""
        if memory is None:
            return None
        pressure = None
        if memory.pressure is not None:
            parts = self.layout.mpi.gather(np.asarray(memory.pressure, float), root=0)
            pressure = None if parts is None else np.concatenate(parts)
        return dataclasses.replace(memory, d=self.gather(memory.d), pressure=pressure)

    def memory_from_checkpoint(self, memory):
        """This rank's share of a checkpoint's solver memory (:meth:`memory_for_checkpoint`'s inverse)."""
        pressure = None
        if memory.pressure is not None:
            pl = self.layout.patches
            pressure = np.asarray(memory.pressure, float)[pl.start:pl.start + pl.n_own]
        return dataclasses.replace(memory, d=self.owned_of(memory.d), pressure=pressure)

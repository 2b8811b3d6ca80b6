r"""Backend ``petsc_mixed``: the projected-energy Newton systems in mixed displacement–pressure form,
solved by PETSc (petsc4py) with a block-triangular (Schur) field-split preconditioner, on one or
several MPI ranks.

Why. The ``petsc`` backend (:mod:`.petsc`) solves the condensed tangent K = K_d + Gᵀ D G,
D = diag(V_p K̄_p), whose patch terms grow with the bulk modulus, so its GAMG-preconditioned
iterations grow with K/μ. This backend solves the same update in the scaled mixed form of
``mixed_amg`` (:mod:`.mixed`, which explains the formulation, the scaling and why it is robust in
K/μ with 2 × 2 × 3 patches):

    [ K_d      w Gᵀ    ] [Δd]   [r]
    [ w G   −w² D⁻¹    ] [ q̃] = [0],        w = mean_p(μ_p V_p) / s

(s the smallest voxel edge, N/cm·cm³/cm = N; q̃ = D G Δd / w, cm). K_d is the tangent without the
patch terms of the patches whose pressure is an unknown (every patch but the single-node patches of
``volumetric.held: own``, whose terms stay in K_d).

What is distributed. Under ``mpiexec`` the system is (:mod:`..distributed`): each rank holds its
own nodes plus a halo. Its displacement rows are its own nodes'; a pressure (a free patch) belongs
to the rank that owns the patch's node of lowest model index, and each rank assembles the rows of G
of its own patches from its held system (:meth:`.operator.SystemOperator.patch_divergence`), whose
columns are displacement unknowns of its own nodes and halo; w Gᵀ is PETSc's transpose of the
distributed w G. The four blocks form a MatNest. Without ``mpiexec`` the serial system is one rank's.

The solver. PETSc's KSP GMRES preconditioned on the right with ``PCFIELDSPLIT``: ``pc_fieldsplit_type schur``,
``pc_fieldsplit_schur_fact_type upper``, i.e. P = [M_A, w Gᵀ; 0, −Ŝ] as in ``mixed_amg``; the
displacement split (options prefix ``fieldsplit_u_``, ``ksp_type preonly``) is M_A, one GAMG cycle on
K_d with the rigid-body modes as near-null space followed by exact solves of K_d on the node regions
of the boundary conditions (``region_solves``, below); the Schur split (``fieldsplit_p_``) is
Jacobi on the user matrix −Ŝ (``pc_fieldsplit_schur_precondition user``),

    Ŝ = w² (D⁻¹ + diag(G M_A Gᵀ))      (``schur: probed``, the default, as in ``mixed_amg``)
    Ŝ = w² (D⁻¹ + c / (μ_p V_p)),    c = ``schur_scale``      (``schur: mass``).

The probed diagonal (:func:`.mixed.probed_schur_diagonal`'s colours; signs from each patch's box,
:func:`.mixed_method.box_signs`) applies the displacement split's own preconditioner outside the
KSP, probe_spacing³ times (27) per Newton system, with PETSc's distributed w G and w Gᵀ.

Region solves. The penalty rows of the boundary conditions, β Ψ(x_c)ᵀ w_c Ψ(x_c), couple every node
in the support of a constraint point; with the default penalty number β scales with the largest
modulus, i.e. with K, and GAMG's point smoother does not reduce these couplings (:mod:`.subdomains`).
As in ``mixed_amg`` the GAMG cycle is followed by exact solves on the regions R_i of
:func:`.subdomains.constraint_regions` (the supports of each condition's constraint points, plus
the gradient supports of held single-node patches):

    z ← GAMG r,    then for each region i in turn:  z ← z + R_i K_i⁻¹ R_iᵀ (r − K_d z)

(a multiplicative Schwarz step, K_i = R_iᵀ K_d R_i, 3n_i × 3n_i, N/cm).

In PETSc: the displacement split's PC is a ``python`` PC, :class:`DisplacementPreconditioner`:
BoomerAMG (GAMG without hypre) on this rank's rows of ``mixed_amg``'s positive stand-in of K_d,
then :class:`.subdomains.RegionSolves` (PARDISO) on the part of each region among this rank's
nodes and :data:`REGION_OVERLAP` voxels beyond them, multiplicative among a rank's regions and
restricted-additive across ranks (each rank keeps the correction of its own nodes). The K_d block of the Krylov
operator is this rank's rows of the matrix-free K_d of its held system (nothing assembled; the
halo's values come from their owners at each product). The multigrid, region
factors and probed Schur diagonal are kept across Newton systems by :class:`.rebuild.RebuildPolicy`
(as ``mixed_amg``'s). A ``petsc_options`` entry for ``fieldsplit_u_pc_type`` (e.g. ``lu``,
``hypre``), or ``region_solves: false`` (GAMG alone), assembles the rows of K_d for that PETSc PC
instead (FGMRES then, rebuilt at each Newton system). docs/petsc.md gives the measurements.

Stopping. With ``solve.newton.pressure_update: mixed`` (the default) Newton runs on the mixed form
(:mod:`..newton`): :meth:`PETScMixedSolver.solve_mixed` takes the force and pressure residuals as the
two blocks, makes one KSP solve to the requested mixed tolerance and gathers (Δd, Δp) on every rank.
A condensed update (:meth:`PETScMixedSolver.solve`) asks for a relative residual of the condensed system. The condensed residual of a
mixed iterate, r − K Δd = r₁ + Gᵀ (D/w) r₂, can exceed the mixed one by up to K/μ (the pressure rows
are weighted by D/w). So the mixed system is solved to the requested tolerance, the condensed
residual of the update is computed with the matrix-free condensed tangent (each rank's own rows,
:meth:`~pixmuscle.mechanics.system.MechanicalSystem.tangent_operator`), and while it is too large the
update is refined: a new mixed solve for the condensed residual so far, to a target tightened by the
lag (condensed residual per mixed residual) the previous pass showed, at most eight passes.

Measured (first Newton system, zero displacement, α = 0.6, of the 224-node clamped body of
tests/test_mixed_solver.py, to 10⁻⁸ of the condensed residual, one rank; iterations at the
tissues' K/μ → at K × 10): with the default penalty (β ∝ K) 96 → 102 with the region solves,
371 → 1,853 with GAMG alone (two ranks: 86 → 109 and 381 → 1,700); with β fixed at 3·10⁴ N/cm³
82 → 75 with the region solves, 96 → 92 without; with an exact solve of K_d
(``fieldsplit_u_pc_type: lu``, fixed β) 25 and 25 in one pass, so the Schur approximation is sound
and the rest of the count is the displacement cycle's. The condensed ``petsc`` backend needs 680
GMRES iterations at K × 1 (fixed β) and breaks down at K × 10.

``solve.solver.petsc_options`` go to the options database over this backend's defaults
(:data:`DEFAULT_OPTIONS`, prefix ``pixmuscle_mixed_``), e.g. ``{fieldsplit_u_pc_type: hypre}``.
Without a projected volumetric energy there is no pressure, and the solver is ``petsc``.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import field

import numpy as np

from ...errors import SolverError, SolverGaveUp
from ...parallel import set_options
from ..heap import release_free_heap
from . import multigrid
from .base import BACKENDS, SolverMemory, built_from, memory_state
from .mixed_method import MixedBlocks, Pass, box_signs, probe_colours, probe_diagonal, refine
from .petsc import DEFAULT_OPTIONS as CONDENSED_OPTIONS
from .petsc import PETScOptions, PETScSolver
from .rebuild import RebuildPolicy
from .subdomains import COUPLINGS

#: PETSc options of the mixed solve unless ``petsc_options`` sets them (prefix ``pixmuscle_mixed_``).
#: GMRES preconditioned on the right, as ``mixed_amg``'s: the preconditioner (one V-cycle, exact region
#: solves, a diagonal Schur approximation) is one fixed linear operator, so no flexible basis is needed.
#: The displacement split's preconditioner is set in code (:class:`DisplacementPreconditioner`) unless
#: ``petsc_options`` names ``fieldsplit_u_pc_type``; the GAMG options under ``fieldsplit_u_`` serve that case.
DEFAULT_OPTIONS = {"ksp_type": "gmres", "ksp_pc_side": "right", "ksp_gmres_restart": 200, "pc_type": "fieldsplit",
                   "pc_fieldsplit_type": "schur", "pc_fieldsplit_schur_fact_type": "upper",
                   "pc_fieldsplit_schur_precondition": "user",
                   "fieldsplit_u_ksp_type": "preonly",
                   **{"fieldsplit_u_" + k: v for k, v in CONDENSED_OPTIONS.items() if k.startswith(("pc_", "mg_"))},
                   "fieldsplit_p_ksp_type": "preonly", "fieldsplit_p_pc_type": "jacobi"}

#: options prefix of the multigrid of :class:`DisplacementPreconditioner` (``petsc_options`` entries
#: ``amg_*`` go there, e.g. ``amg_pc_hypre_boomeramg_strong_threshold``)
_AMG_PREFIX = "pixmuscle_mixedamg_"

_PREFIX = "pixmuscle_mixed_"
_LOG = logging.getLogger(__name__)

#: voxels (per axis) by which a rank's part of a stiff region reaches past its own nodes. The penalty
#: couplings of a region cut by a partition boundary cross the cut; solved without them, each rank's
#: part alone, the first Newton system of the 74k leg (FGMRES to 10⁻⁶, mixed_amg with its regions cut
#: as the four parts of a 4-rank partition) takes 179 iterations instead of 41; with the parts
#: reaching 2 voxels past the cut, 41 again.
REGION_OVERLAP = 2

#: relative target below which a mixed solve is not asked to go (round-off floor); refinement takes over
_FLOOR = 1e-11


@dataclasses.dataclass(frozen=True)
class PETScMixedOptions(PETScOptions):
    """Options of ``solve.solver: {backend: petsc_mixed, …}``."""

    schur_scale: float = field(default=0.5, metadata={"gt": 0, "doc": "c of the diagonal Schur complement w²(c/(μ_p V_p) + 1/(V_p K̄_p)): the typical eigenvalue of G K_d⁻¹ Gᵀ against the pressure mass"})
    schur: str = field(default="probed", metadata={"choices": ("probed", "mass"), "doc": "diagonal Schur approximation: `probed`, the diagonal of G M Gᵀ (M the displacement split's preconditioner) by probing with probe_spacing³ colours of the patch grid at each preconditioner build (as mixed_amg); `mass`, c/(μ_p V_p) with c = schur_scale"})
    probe_spacing: int = field(default=3, metadata={"range": (2, None), "doc": "with schur: probed, same-colour patches of the probe are this many patch boxes apart (spacing³ colours, as many applications of the displacement preconditioner per build)"})
    region_solves: bool = field(default=True, metadata={"doc": "after each multigrid cycle on the displacement block, solve it exactly on the node regions of the boundary conditions (the region solves of mixed_amg, PARDISO or SuperLU, each rank on the part of each region among its own nodes), where the penalty couplings, K-scaled with the default penalty number, live"})
    region_coupling: str = field(default="auto", metadata={"choices": ("auto", "components", "full"), "doc": "as mixed_amg's: what is factorised on a region, each displacement component's diagonal block of K_d, the whole block, or (auto) the whole block only where a held single-node patch couples the components"})
    rebuild_cost: int = field(default=40, metadata={"range": (1, None), "doc": "as mixed_amg's: what a build of the displacement preconditioner (multigrid, region factors, probed Schur diagonal) costs in Krylov iterations; it is kept across Newton systems and rebuilt once the iterations beyond its rate right after the build add up to this many (linsolve/rebuild.py)"})
    give_up: float = field(default=4.0, metadata={"gt": 0, "doc": "as mixed_amg's: a solve with a preconditioner that has not yet converged a solve stops after give_up × (the last measured iterations per decade) × decades + rebuild_cost iterations"})
    reach: int = field(default=2, metadata={"range": (1, 3), "doc": "the multigrid's stand-in holds the blocks of node pairs at most this many voxels apart (as mixed_amg's)"})


class DisplacementPreconditioner:
    """M_A of the displacement split, as ``mixed_amg``'s: one multigrid cycle (hypre BoomerAMG with
    :data:`.multigrid.BOOMERAMG_OPTIONS`, GAMG without hypre) on this rank's rows of the positive
    stand-in of K_d (:meth:`~.operator.SystemOperator.preconditioner_matrix` with ``volumetric="held"``),
    then the exact region solves of :class:`.subdomains.RegionSolves` (PARDISO where MKL is installed)
    on the part of each stiff region among this rank's nodes and :data:`REGION_OVERLAP` voxels past
    them (the held system's rows there): multiplicative among a rank's regions, restricted-additive
    across ranks (each rank keeps its own nodes' correction). A petsc4py ``python`` PC context; :meth:`build` makes both at a state."""

    def __init__(self, solver: PETScMixedSolver):
        self.s = solver
        self.amg = None
        self.regions = None

    def build(self, system, state) -> None:
        s = self.s
        self.release()
        release_free_heap()  # the old multigrid's and factors' pages, which the new ones would not all reuse
        held, lay = system.held, system.layout
        if s.region_solves:  # before the multigrid, so that their assembly and work space do not meet its hierarchy
            if self.regions is None:
                from ..distributed.partition import halo  # not at the top: the distributed package imports the backends

                owned = np.zeros(lay.n_held, bool)
                owned[lay.own] = True
                near = np.flatnonzero(halo(lay.ijk, owned, REGION_OVERLAP))  # own nodes and the overlap
                parts = [np.intersect1d(nodes, near, assume_unique=True) for nodes in held.stiff_regions()
                         if np.any(owned[nodes])]
                self.regions = held.region_solves(parts, lay.ijk, coupling=s.region_coupling)
                s.info["region_nodes"] = int(lay.sum(sum(int(np.count_nonzero(owned[p])) for p in parts)))
            self.regions.update(state.held)
            release_free_heap()  # the region blocks' temporaries
        A = _owned_block_rows(lambda: held.preconditioner_matrix(state.held, s.reach, volumetric="held"), lay, s.PETSc)
        self.amg = _multigrid(A, s, system, s.PETSc)
        release_free_heap()  # the stand-in's temporaries

    def setUp(self, pc) -> None:  # built by build(), not by PETSc
        pass

    def apply(self, pc, x, y) -> None:
        self.amg.apply(x, y)
        if self.regions is None:
            return
        lay = self.s.layout
        z = lay.to_held(y.getArray(readonly=True)).ravel()  # the cycle's result with the halo (collective)
        r = lay.to_held(x.getArray(readonly=True)).ravel()  # and the residual, which the overlap reads
        if not self.regions.parts:
            return
        y.setArray(self.regions.correct(r, z)[self.s.own_dofs])  # each rank keeps its own nodes' correction

    def release(self) -> None:
        """Destroy the multigrid and drop the region factors (the next :meth:`build` makes both)."""
        if self.amg is not None:
            self.amg.destroy()
            self.amg = None
        if self.regions is not None:
            self.regions.release()

    def destroy(self, pc=None) -> None:
        """Nothing: PETSc destroys the split's PC with each Newton system's KSP, and the
        multigrid and region factors outlive it until the next build."""


def _owned_block_rows(make_K, layout, PETSc):
    """The block rows of this rank's own nodes of the held system's BSR ``make_K()`` (3 × 3 blocks),
    columns in the global PETSc node order, as a distributed BAIJ matrix. ``K`` is made here, so
    that it is freed before PETSc copies the rows (the caller would hold an argument to the end)."""
    K = make_K()
    own = layout.own
    counts = np.diff(K.indptr)[own]
    idx = np.repeat(K.indptr[own], counts) + (np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts))
    cols = layout.petsc[K.indices[idx]]
    by = np.lexsort((cols, np.repeat(np.arange(own.size), counts)))
    indptr = np.concatenate([[0], np.cumsum(counts)])
    data = K.data[idx[by]]
    cols = cols[by]
    del K, idx, by
    from ..amg_worker import hypre_matrix

    return hypre_matrix(layout.comm, indptr, cols, data, own.size, layout.n_global)


def _multigrid(A, s, system, PETSc):
    """The multigrid PC on the stand-in rows ``A``: BoomerAMG where PETSc has hypre, else GAMG."""
    from ..amg_worker import hypre_pc

    amg_opts = {k[4:]: v for k, v in (s.user_options or {}).items() if str(k).startswith("amg_")}
    if multigrid.hypre_available():
        A, pc, _, _ = hypre_pc(A, _AMG_PREFIX, {**multigrid.BOOMERAMG_OPTIONS, **amg_opts})
    else:
        lay = system.layout
        coords = PETSc.Vec().createMPI((3 * lay.n_own, 3 * lay.n_global), bsize=3, comm=lay.comm)
        coords.setArray(lay.X[lay.own].ravel())
        A.setNearNullSpace(PETSc.NullSpace().createRigidBody(coords))
        pc = PETSc.PC().create(comm=lay.comm)
        pc.setOptionsPrefix(_AMG_PREFIX)
        pc.setOperators(A)
        set_options(_AMG_PREFIX, {k: v for k, v in CONDENSED_OPTIONS.items() if k.startswith(("pc_", "mg_"))}, amg_opts)
        pc.setFromOptions()
        pc.setUp()
    A.destroy()  # the PC holds its reference
    return pc


@BACKENDS.register("petsc_mixed", options=PETScMixedOptions)
class PETScMixedSolver(PETScSolver):
    """PETSc GMRES + Schur field split on the mixed form (see the module docstring).

    Parameters
    ----------
    X : (N, 3) float
        Node coordinates, cm, of a serial system (a distributed one's layout has its ranks' own).
    ijk : (N, 3) int
        Voxel indices, as ``X``.
    rtol : float
        Relative condensed residual when the caller gives none.
    maxiter : int
        Krylov iterations per linear solve, all refinement passes together.
    options : dict, optional
        PETSc options (names without the dash), over :data:`DEFAULT_OPTIONS` for the mixed solve
        and over :data:`.petsc.DEFAULT_OPTIONS` for the condensed one (no projected energy);
        ``fieldsplit_u_pc_type`` replaces :class:`DisplacementPreconditioner` by that PETSc PC on the
        assembled rows of K_d; ``amg_*`` go to the multigrid of :class:`DisplacementPreconditioner`.
    schur_scale : float
        With ``schur="mass"``: c in Ŝ = w² (D⁻¹ + c/(μ_p V_p)).
    schur : {"probed", "mass"}
        Diagonal Schur approximation (module docstring).
    probe_spacing : int
        With ``schur="probed"``: colour spacing of the probe on the patch grid.
    region_solves : bool
        Displacement split: the multigrid cycle then exact solves on the boundary-condition regions
        (:class:`DisplacementPreconditioner`); without, the multigrid alone.
    region_coupling : {"auto", "components", "full"}
        What the region solves factorise: each displacement component's diagonal block of K_d, or
        the whole block (as ``mixed_amg``'s).
    rebuild_cost, give_up : float
        The rebuild rule of the displacement preconditioner (:class:`.rebuild.RebuildPolicy`).
    reach : int
        Node pairs at most this many voxels apart enter the multigrid's stand-in.
    """

    name = "petsc_mixed"

    def __init__(self, X=None, ijk=None, rtol: float = 1e-10, maxiter: int = 2000, options: dict | None = None,
                 schur_scale: float = 0.5, region_solves: bool = True, schur: str = "probed", probe_spacing: int = 3,
                 rebuild_cost: int = 40, give_up: float = 4.0, reach: int = 2, region_coupling: str = "auto"):
        super().__init__(X, ijk, rtol=rtol, maxiter=maxiter, options=options)
        self.user_options = dict(options or {})
        # the assembled rows of K_d only for a PETSc PC of the displacement split named in petsc_options
        # (or without region solves: GAMG alone on them, its options under fieldsplit_u_)
        self.assembled = not region_solves or "fieldsplit_u_pc_type" in {str(k).lstrip("-") for k in self.user_options}
        # a PETSc PC (GAMG's Chebyshev smoothers) is not a fixed operator: flexible GMRES for it
        defaults = {**DEFAULT_OPTIONS, "ksp_type": "fgmres"} if self.assembled else {
            **{k: v for k, v in DEFAULT_OPTIONS.items() if not k.startswith(("fieldsplit_u_pc_", "fieldsplit_u_mg_"))},
            "fieldsplit_u_pc_type": "none"}  # replaced in code by the python PC
        self.mixed_options = set_options(_PREFIX, defaults,
                                         {k: v for k, v in self.user_options.items() if not str(k).startswith("amg_")})
        self.schur_scale = float(schur_scale)
        self.schur = schur
        self.probe_spacing = int(probe_spacing)
        self.region_solves = bool(region_solves)
        if region_coupling not in COUPLINGS:
            raise ValueError(f"region_coupling must be one of {COUPLINGS}, got {region_coupling!r}")
        self.region_coupling = region_coupling
        self.reach = int(reach)
        self.policy = RebuildPolicy(rebuild_cost, give_up, maxiter)
        self._M = None if self.assembled else DisplacementPreconditioner(self)
        self._probe = None
        self._mixed = None
        self._press = None
        self._space = None
        self._built_at = None
        self.own_dofs = None
        self.info.update(refinements=0, pressures=0, region_nodes=0, build_s=[])

    @classmethod
    def from_options(cls, opts: PETScMixedOptions, X, *, ijk=None, width=(4, 4, 4)) -> PETScMixedSolver:
        return cls(X, ijk, rtol=opts.rtol, maxiter=opts.maxiter, options=dict(opts.petsc_options),
                   schur_scale=opts.schur_scale, region_solves=opts.region_solves, schur=opts.schur,
                   probe_spacing=opts.probe_spacing, rebuild_cost=opts.rebuild_cost, give_up=opts.give_up,
                   reach=opts.reach, region_coupling=opts.region_coupling)

    @property
    def memory_tag(self) -> str:
        # preconditioners spread over other numbers of ranks differ in round-off: a resume with another starts afresh
        return f"{self.name}/{self.size}"

    def memory(self) -> SolverMemory | None:
        """The state the displacement preconditioner was built from (this rank's rows) and the
        rebuild rule's counters."""
        if self._built_at is None:
            return None
        d, t, alpha, pressure = self._built_at
        return SolverMemory(d, t, alpha, pressure=pressure, counters=self.policy.counters(), backend=self.memory_tag)

    def recall(self, system, memory: SolverMemory) -> None:
        """Build the displacement preconditioner at ``memory``'s state and restore the counters (one
        the rule had marked stale is left for the next Newton system to rebuild); that state's PETSc
        objects are let go at once (:meth:`finish`)."""
        if self._M is not None and not memory.counters["stale"]:
            self.prepare(system, memory_state(system, memory))
            self.finish()
        self.policy.restore(memory.counters)

    def _pressures(self, system):
        """This rank's pressure unknowns: its own free patches (held numbering), which of its own
        patches they are, and their first global index."""
        lay = system.layout
        own = lay.patches.own
        sel = np.isin(own, system.pressure_space().free)
        mine = own[sel]
        self.info["pressures"] = int(lay.sum(int(mine.size)))
        return mine, sel, int(lay.mpi.exscan(int(mine.size)) or 0), self.info["pressures"]

    def prepare(self, system, state):
        system, state = self._attach(system, state)
        space = system.pressure_space()
        if space is None or space.free.size == 0:
            self._release()
            super().prepare(system, state)
            return
        PETSc = self.PETSc
        t0 = time.perf_counter()
        self._release()  # the last system's objects (its tangent's moduli among them) before the new ones are made
        lay, held = system.layout, system.held
        if self._press is None:
            self._press = self._pressures(system)
            self.own_dofs = (3 * lay.own[:, None] + np.arange(3)).ravel()
        mine, _, p0, m = self._press
        n_loc, n = 3 * lay.n_own, 3 * lay.n_global
        m_loc = mine.size

        full = held.tangent_operator(state.held)  # the condensed tangent, matrix-free: the stopping test
        if self.assembled:
            if self._rows is None:
                self._rows = held.owned_rows(lay.own)
                self.info["halo_cells"] = int(self._rows.cells.size - lay.n_own)
            A00 = self._displacement_matrix(self._rows.rows(state.held, pressure_free=True), system)
        else:  # K_d matrix-free: this rank's rows of its held system's product (nothing assembled)
            A00 = PETSc.Mat().createPython(((n_loc, n), (n_loc, n)),
                                           _OwnedRows(self, held.displacement_operator(state.held, tangent=full)),
                                           comm=self.comm)
            A00.setUp()
        blocks = MixedBlocks(space, mine)  # w from all ranks' free patches
        w = blocks.w
        G = (w * held.patch_divergence(state.held, mine).sparse()).tocsr()
        G.indices = self._columns(G.indices)
        G.has_sorted_indices = False
        G.sort_indices()
        A10 = PETSc.Mat().createAIJ(size=((m_loc, m), (n_loc, n)), comm=self.comm,
                                    csr=(G.indptr.astype(PETSc.IntType), G.indices.astype(PETSc.IntType), G.data))
        A10.assemble()
        A01 = A10.transpose(PETSc.Mat())  # a new matrix (without one petsc4py transposes in place)
        A11 = self._diagonal(-blocks.c22, p0, m)
        S = self._diagonal(-blocks.schur("mass", self.schur_scale), p0, m)  # −Ŝ: S itself is negative
        A = PETSc.Mat().createNest([[A00, A01], [A10, A11]], comm=self.comm)
        A.assemble()

        isu, isp = A.getNestISs()[0]
        if self.assembled:
            isu.compose("nearnullspace", A00.getNearNullSpace())
        ksp = PETSc.KSP().create(comm=self.comm)
        ksp.setOptionsPrefix(_PREFIX)
        ksp.setOperators(A)
        pc = ksp.getPC()
        pc.setType("fieldsplit")
        pc.setFieldSplitIS(("u", isu), ("p", isp))
        pc.setFieldSplitType(PETSc.PC.CompositeType.SCHUR)
        pc.setFieldSplitSchurFactType(PETSc.PC.SchurFactType.UPPER)
        pc.setFieldSplitSchurPreType(PETSc.PC.SchurPreType.USER, S)
        ksp.setFromOptions()
        pc.setUp()  # creates the split KSPs and their PCs from the options
        upc = pc.getFieldSplitSubKSP()[0].getPC()
        if self._M is not None:
            upc.setType(PETSc.PC.Type.PYTHON)
            upc.setPythonContext(self._M)
        self.policy.new_system()
        build = self._M is not None and self.policy.must_build(self._M.amg is not None)
        if build:
            self._build(system, state)
        if self.schur == "probed":  # with a kept preconditioner, its diagonal probed at its build
            if build or self._M is None or self._probe is None:
                t1 = time.perf_counter()
                self._probe = self._probe_schur(space, pc, A01, A10, mine)
                if build:
                    self.info["build_s"][-1] += time.perf_counter() - t1
            self._set_schur(S, blocks)
        b = PETSc.Vec().createMPI((n_loc + m_loc, PETSc.DECIDE), comm=self.comm)  # per rank: [u; p] owned
        z = b.duplicate()
        start = b.getOwnershipRange()[0]
        self._space = space
        self._mixed = {"ksp": ksp, "A": A, "b": b, "z": z, "t": b.duplicate(), "u": isu.getIndices() - start,
                       "p": isp.getIndices() - start, "w": w, "K": full, "blocks": (A00, A01, A10, A11, S),
                       "system": system, "state": state}
        self.info["setup_s"] = time.perf_counter() - t0
        self.info["nnz_local"] = int(2 * G.nnz)

    def _release(self) -> None:
        """Destroy the PETSc objects of the last Newton system (KSP, blocks, vectors). Left to Python's
        collector they were not freed: the K_d block's python context holds the tangent's moduli, and
        a sweep on the 10k leg grew by 65 MB per load step."""
        mx, self._mixed = self._mixed, None
        if mx is None:
            return
        for obj in (mx["ksp"], mx["A"], *mx["blocks"], mx["b"], mx["z"], mx["t"]):
            obj.destroy()

    def finish(self) -> None:
        """Destroy the solved system's PETSc objects (its K_d block reads the state's moduli); the
        displacement preconditioner and the probed Schur diagonal stay for the next system."""
        self._release()

    def release(self) -> None:
        """Destroy the last Newton system's PETSc objects and the displacement preconditioner."""
        self._release()
        if self._M is not None:
            self._M.release()
        release_free_heap()

    def _build(self, system, state) -> None:
        """Build the displacement preconditioner (multigrid and region factors) at ``state``."""
        t0 = time.perf_counter()
        self._M.build(system, state)
        self._built_at = built_from(state)
        self.policy.built()
        self.info["preconditioner_builds"] += 1
        self.info["build_s"].append(time.perf_counter() - t0)

    def _ksp_solve(self, rtol: float) -> tuple[int, str, int]:
        """One KSP solve of the prepared mixed system (``b`` into ``z``) within the rebuild rule's budget;
        when the budget of a kept preconditioner runs out, rebuild it at the prepared state (and
        its probed Schur diagonal) and go on from the iterate reached. Returns (iterations, status,
        iterations of the stale preconditioner)."""
        mx = self._mixed
        ksp, b, z = mx["ksp"], mx["b"], mx["z"]
        ksp.setInitialGuessNonzero(False)
        ksp.setTolerances(rtol=rtol, atol=0.0, max_it=self.policy.budget(rtol))
        ksp.solve(b, z)
        its, reason = int(ksp.getIterationNumber()), int(ksp.getConvergedReason())
        status = "converged" if reason > 0 else "maxiter" if reason == -3 else f"diverged (PETSc reason {reason})"
        if self._M is None or not self.policy.may_rebuild(status, its):
            return its, status, 0
        _LOG.debug("petsc_mixed: %d iterations with a kept preconditioner cost more than a rebuild; rebuilding it", its)
        self._build(mx["system"], mx["state"])
        if self.schur == "probed":
            A00, A01, A10, A11, S = mx["blocks"]
            self._probe = self._probe_schur(self._space, ksp.getPC(), A01, A10, self._press[0])
            self._set_schur(S, MixedBlocks(self._space, self._press[0]))
        ksp.setInitialGuessNonzero(True)
        ksp.setTolerances(rtol=rtol, atol=0.0, max_it=self.policy.retry_budget(rtol, its))
        ksp.solve(b, z)
        more, reason = int(ksp.getIterationNumber()), int(ksp.getConvergedReason())
        status = "converged" if reason > 0 else "maxiter" if reason == -3 else f"diverged (PETSc reason {reason})"
        return its + more, status, its

    def _failed(self, status: str, total: int, rtol: float, passes: int = 1) -> SolverError:
        if self.policy.gave_up(status, total):
            return SolverGaveUp(f"petsc_mixed: GMRES gave up after {total} iterations (relative residual target "
                                f"{rtol:.1e}): this system needs far more than the earlier ones (solver.give_up: "
                                f"{self.policy.give_up:g}), e.g. after an overshooting Newton update; a smaller load "
                                "increment (solve.steps) helps")
        return SolverError(f"petsc_mixed: GMRES with the Schur field split {status} after {total} iterations in "
                           f"{passes} passes (target {rtol:.1e}); try solver.petsc_options "
                           "{fieldsplit_u_pc_type: hypre} or the condensed backend petsc, or check the boundary conditions")

    def _set_schur(self, S, blocks: MixedBlocks) -> None:
        """−Ŝ into the diagonal of ``S`` with the probed diagonal of the preconditioner's last build."""
        diag = S.createVecLeft()
        diag.setArray(-blocks.schur("probed", self.schur_scale, self._probe))
        S.setDiagonal(diag)
        diag.destroy()

    def _probe_schur(self, space, pc, A01, A10, mine: np.ndarray) -> np.ndarray:
        """The diagonal of w² G M Gᵀ on this rank's patches, probed as in
        :func:`.mixed_method.probed_schur_diagonal` (colours of the patch grid, signs from each
        patch's box: the same whichever rank owns it) with M the displacement split's preconditioner,
        applied outside the KSP."""
        PETSc = self.PETSc
        pc.setUp()
        upc = pc.getFieldSplitSubKSP()[0].getPC()
        upc.setUp()
        colour, _ = probe_colours(space.box[mine], self.probe_spacing)
        sign = box_signs(space.box[mine])
        q, g = A10.createVecLeft(), A10.createVecLeft()
        u, y = A01.createVecLeft(), A01.createVecLeft()

        def product(qv):  # w G M w Gᵀ q on the owned patches (collective)
            q.setArray(qv)
            A01.mult(q, u)
            upc.apply(u, y)
            A10.mult(y, g)
            return g.getArray().copy()

        def largest(out):  # the largest |estimate| over all ranks
            g.setArray(out)
            return g.norm(PETSc.NormType.INFINITY)

        # every rank takes every colour: the products are collective
        probe = probe_diagonal(product, colour, sign, range(self.probe_spacing ** 3), largest)
        for v in (q, g, u, y):
            v.destroy()
        return probe

    def _diagonal(self, values: np.ndarray, start: int, size: int):
        """A distributed diagonal AIJ matrix with the owned ``values`` from global row ``start``."""
        PETSc = self.PETSc
        k = values.size
        M = PETSc.Mat().createAIJ(size=((k, size), (k, size)), comm=self.comm,
                                  csr=(np.arange(k + 1, dtype=PETSc.IntType),
                                       (start + np.arange(k)).astype(PETSc.IntType), np.asarray(values, float)))
        M.assemble()
        return M

    def _owned_product(self, op, x: np.ndarray) -> np.ndarray:
        """This rank's rows of ``op @ x`` for the held system's operator ``op`` and the owned values
        ``x`` (3n,) of every rank (collective: the halo's values come from their owners)."""
        return (op @ self.layout.to_held(x).ravel())[self.own_dofs]

    def _norm(self, v: np.ndarray) -> float:
        return float(np.sqrt(self.layout.sum(float(np.vdot(v, v)))))

    def solve(self, r, rtol=None):
        if self._mixed is None:
            return super().solve(r, rtol)
        t0 = time.perf_counter()
        setup0 = sum(self.info["build_s"])
        rtol = self.rtol if rtol is None else max(float(rtol), 1e-14)
        mx = self._mixed
        A, b, z, t, iu, K = mx["A"], mx["b"], mx["z"], mx["t"], mx["u"], mx["K"]
        rr = np.asarray(r, float).ravel()
        bn = self._norm(rr)
        self.info["passes"] = []  # (mixed target, iterations, condensed relative residual after) per pass
        stale = [0]

        def mixed_pass(res, x, target, lag, budget, attempt) -> Pass:
            barr = b.getArray()
            barr[:] = 0.0
            barr[iu] = res
            b.setArray(barr)
            its, status, stale_its = self._ksp_solve(target)
            stale[0] += stale_its
            if status != "converged":
                return Pass(np.zeros(rr.size), its, status)
            A.mult(z, t)
            t.aypx(-1.0, b)  # t = b − A z, the true mixed residual
            mixed = t.norm()
            dx = z.getArray()[iu].copy()
            left = rr - self._owned_product(K, x + dx)
            new = self._norm(left)
            self.info["passes"].append((target, its, new / max(bn, 1e-300)))
            if new <= rtol * bn:
                return Pass(dx, its, "converged", residual=left)
            return Pass(dx, its, "converged", lag=new / max(mixed, 1e-300), residual=left)  # condensed per mixed

        x, total, status, passes = refine(mixed_pass, lambda x: rr - self._owned_product(K, x), rr, rtol, self.maxiter,
                                          _FLOOR, norm=self._norm)
        self._close(t0, setup0, total, rtol)
        self.info["refinements"] += max(passes - 1, 0)
        if status != "converged":
            raise self._failed(status, total, rtol, passes)
        if not stale[0]:
            self.policy.account(total, rtol)
        return x.reshape(np.shape(r))

    def _close(self, t0, setup0, total, rtol) -> None:
        self.info["iterations"] = total
        self.info["krylov_iterations"] += total
        built = sum(self.info["build_s"]) - setup0  # a rebuild within the solve is set-up time
        self.info["setup_s"] += built
        self.info["solve_s"] = time.perf_counter() - t0 - built

    def solve_mixed(self, r, rp, rtol=None):
        """One update of Newton on the mixed form, as :meth:`.mixed.MixedBlockSolver.solve_mixed`: the
        force residual ``r`` (3n,) N of this rank's nodes and the pressure residual ``rp`` of its own
        patches as the two blocks, one KSP solve stopped on the mixed residual; returns (Δd (3n,) cm,
        Δp of its own patches, N/cm², 0 at held patches)."""
        if self._mixed is None:
            return self.solve(r, rtol), None
        t0 = time.perf_counter()
        setup0 = sum(self.info["build_s"])
        rtol = self.rtol if rtol is None else max(float(rtol), 1e-14)
        mx = self._mixed
        b, z = mx["b"], mx["z"]
        mine, sel, _, _ = self._press
        w = self._space.weight
        barr = b.getArray()
        barr[mx["u"]] = np.asarray(r, float).ravel()
        barr[mx["p"]] = -w * np.asarray(rp, float)[sel]
        b.setArray(barr)
        its, status, stale = self._ksp_solve(rtol)
        zarr = z.getArray()
        x = zarr[mx["u"]].copy()
        dp = np.zeros(sel.size)
        dp[sel] = w * zarr[mx["p"]] / self._space.volume[mine]
        self._close(t0, setup0, its, rtol)
        if status != "converged":
            raise self._failed(status, its, rtol)
        if not stale:
            self.policy.account(its, rtol)
        return x.reshape(np.shape(r)), dp

    def statistics(self) -> dict:
        """As ``petsc``, plus ``refinements`` (mixed re-solves for the condensed residual, all solves)
        and ``preconditioner_build_s`` (the wall time of each build of the displacement preconditioner, s)."""
        return super().statistics() | {"refinements": self.info["refinements"],
                                       "preconditioner_build_s": [round(t, 2) for t in self.info["build_s"]]}


class _OwnedRows:
    """A petsc4py ``python`` Mat context: this rank's rows of its held system's matrix-free operator."""

    def __init__(self, solver: PETScMixedSolver, op):
        self.s, self.op = solver, op

    def mult(self, mat, x, y) -> None:
        y.setArray(self.s._owned_product(self.op, x.getArray(readonly=True)))

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

What is distributed. The displacement rows are those of ``petsc`` (slabs of whole voxel slices,
:func:`.petsc.slab_partition`); each rank assembles its rows of K_d
(:meth:`.rows.RowAssembler.rows` with ``pressure_free``). A pressure (patch) belongs to the rank of
its first node in slab order (the lowest rank among its nodes); each rank assembles the rows of G of
its own patches (:meth:`.mixed.PatchDivergence.sparse` restricted to them: the product still runs
over the replicated (3N × N) smoothed-gradient operator, so this part costs O(N) time and memory per
rank, like the replicated material evaluation), and w Gᵀ is PETSc's transpose of the distributed w G.
The four blocks form a MatNest.

The solver. PETSc's KSP FGMRES (the displacement block's preconditioner is a multigrid cycle, a
preconditioner that need not be fixed) with ``PCFIELDSPLIT``: ``pc_fieldsplit_type schur``,
``pc_fieldsplit_schur_fact_type upper``, i.e. P = [M_A, w Gᵀ; 0, −Ŝ] as in ``mixed_amg``; the
displacement split (options prefix ``fieldsplit_u_``, ``ksp_type preonly``) is M_A, one GAMG cycle on
K_d with the rigid-body modes as near-null space followed by exact solves of K_d on the node regions
of the boundary conditions (``region_solves``, below); the Schur split (``fieldsplit_p_``) is
Jacobi on the user matrix −Ŝ (``pc_fieldsplit_schur_precondition user``),

    Ŝ = w² (D⁻¹ + diag(G M_A Gᵀ))      (``schur: probed``, the default, as in ``mixed_amg``)
    Ŝ = w² (D⁻¹ + c / (μ_p V_p)),    c = ``schur_scale``      (``schur: mass``).

The probed diagonal (:func:`.mixed.probed_schur_diagonal`'s colours and signs) applies the
displacement split's own preconditioner outside the KSP, probe_spacing³ times (27) per Newton
system, with PETSc's distributed w G and w Gᵀ, so one rank and several probe the same diagonal.

Region solves. The penalty rows of the boundary conditions, β Ψ(x_c)ᵀ w_c Ψ(x_c), couple every node
in the support of a constraint point; with the default penalty number β scales with the largest
modulus, i.e. with K, and GAMG's point smoother does not reduce these couplings (:mod:`.subdomains`).
As in ``mixed_amg`` the GAMG cycle is followed by exact solves on the regions R_i of
:func:`.subdomains.constraint_regions` (the supports of each condition's constraint points, plus
the gradient supports of held single-node patches):

    z ← GAMG r,    then for each region i in turn:  z ← z + R_i K_i⁻¹ R_iᵀ (r − K_d z)

(a multiplicative Schwarz step, K_i = R_iᵀ K_d R_i, 3n_i × 3n_i, N/cm).

In PETSc: ``fieldsplit_u_pc_type composite`` with ``pc_composite_type multiplicative`` over two
sub-PCs, the multigrid (options prefix ``fieldsplit_u_sub_0_``: hypre BoomerAMG with the settings
of ``mixed_amg``'s, :data:`.multigrid.BOOMERAMG_OPTIONS`, where PETSc has hypre, else GAMG) and PCASM (``fieldsplit_u_sub_1_``: ``pc_asm_type
basic``, ``pc_asm_overlap 0``, ``pc_asm_local_type multiplicative``, ``sub_pc_type lu``). On several
ranks each rank takes, of each region, the part among its owned rows as one local subdomain, so a
region cut by a slab boundary is solved as two blocks, one per rank, additively across ranks
(multiplicatively among the regions of one rank); a rank without region rows has one empty
subdomain. PCASM rather than a PCSHELL: the whole cycle stays in PETSc (no Python call per
application), and every part of it is a PETSc option that ``petsc_options`` can change. The sub-PCs
are added in code, not by ``pc_composite_pcs``, which PCFIELDSPLIT's two readings of the split's
options (the split's KSP and the Schur complement's inner KSP are one object) would apply twice.
A ``petsc_options`` entry for ``fieldsplit_u_pc_type`` (e.g. ``hypre``, ``lu``) replaces the whole
composite; ``fieldsplit_u_sub_0_pc_type: gamg`` keeps the region solves after a GAMG cycle;
``region_solves: false`` gives GAMG alone, its options under ``fieldsplit_u_`` (:data:`DEFAULT_OPTIONS`).
On the 224-node clamped body of the tests BoomerAMG + region solves needs 48 and 53 FGMRES
iterations at K × 1 and × 10 with the probed Schur diagonal (63 and 70 with the pressure mass),
where GAMG + region solves needs 96 and 102 with the mass (docs/petsc.md).

Stopping. With ``solve.newton.pressure_update: mixed`` (the default) Newton runs on the mixed form
(:mod:`..newton`): :meth:`PETScMixedSolver.solve_mixed` takes the force and pressure residuals as the
two blocks, makes one KSP solve to the requested mixed tolerance and gathers (Δd, Δp) on every rank.
A condensed update (:meth:`PETScMixedSolver.solve`) asks for a relative residual of the condensed system. The condensed residual of a
mixed iterate, r − K Δd = r₁ + Gᵀ (D/w) r₂, can exceed the mixed one by up to K/μ (the pressure rows
are weighted by D/w). So the mixed system is solved to the requested tolerance, the condensed
residual of the update is computed with the matrix-free condensed tangent (replicated on every rank,
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
import time
from dataclasses import field

import numpy as np

from ...errors import SolverError
from . import multigrid
from .base import BACKENDS
from .mixed_method import MixedBlocks, Pass, probe_colours, probe_diagonal, refine
from .petsc import DEFAULT_OPTIONS as CONDENSED_OPTIONS
from .petsc import PETScOptions, PETScSolver, set_options

#: PETSc options of the mixed solve unless ``petsc_options`` sets them (prefix ``pixmuscle_mixed_``)
DEFAULT_OPTIONS = {"ksp_type": "fgmres", "ksp_gmres_restart": 200, "pc_type": "fieldsplit",
                   "pc_fieldsplit_type": "schur", "pc_fieldsplit_schur_fact_type": "upper",
                   "pc_fieldsplit_schur_precondition": "user",
                   "fieldsplit_u_ksp_type": "preonly",
                   **{"fieldsplit_u_" + k: v for k, v in CONDENSED_OPTIONS.items() if k.startswith(("pc_", "mg_"))},
                   "fieldsplit_p_ksp_type": "preonly", "fieldsplit_p_pc_type": "jacobi"}

#: the displacement split with region solves (``region_solves``, the default): a multiplicative
#: PCCOMPOSITE of GAMG (sub-PC 0, options under ``fieldsplit_u_sub_0_``) and exact solves on the
#: boundary-condition regions (sub-PC 1, PCASM with one local subdomain per region, under
#: ``fieldsplit_u_sub_1_``). The two sub-PCs are added in code, not by ``pc_composite_pcs``:
#: PCFIELDSPLIT reads the split's options twice (once for the Schur complement's inner KSP), and
#: PCCOMPOSITE adds the listed PCs at each reading.
REGION_OPTIONS = {**{k: v for k, v in DEFAULT_OPTIONS.items() if not k.startswith(("fieldsplit_u_pc_", "fieldsplit_u_mg_"))},
                  "fieldsplit_u_pc_type": "composite", "fieldsplit_u_pc_composite_type": "multiplicative",
                  **{"fieldsplit_u_sub_0_" + k: v for k, v in CONDENSED_OPTIONS.items() if k.startswith(("pc_", "mg_"))},
                  "fieldsplit_u_sub_1_pc_asm_type": "basic", "fieldsplit_u_sub_1_pc_asm_overlap": 0,
                  "fieldsplit_u_sub_1_pc_asm_local_type": "multiplicative",
                  "fieldsplit_u_sub_1_sub_ksp_type": "preonly", "fieldsplit_u_sub_1_sub_pc_type": "lu"}


def region_options() -> dict:
    """:data:`REGION_OPTIONS` with BoomerAMG as the multigrid where PETSc has hypre."""
    if not multigrid.hypre_available():
        return REGION_OPTIONS
    # GAMG's options stay under the prefix (a hypre PC ignores them), so that petsc_options
    # {fieldsplit_u_sub_0_pc_type: gamg} gets the tuned GAMG back
    return {**REGION_OPTIONS, "fieldsplit_u_sub_0_pc_type": "hypre", "fieldsplit_u_sub_0_pc_hypre_type": "boomeramg",
            **{"fieldsplit_u_sub_0_" + k: v for k, v in multigrid.BOOMERAMG_OPTIONS.items()}}

_PREFIX = "pixmuscle_mixed_"

#: relative target below which a mixed solve is not asked to go (round-off floor); refinement takes over
_FLOOR = 1e-11


@dataclasses.dataclass(frozen=True)
class PETScMixedOptions(PETScOptions):
    """Options of ``solve.solver: {backend: petsc_mixed, …}``."""

    schur_scale: float = field(default=0.5, metadata={"gt": 0, "doc": "c of the diagonal Schur complement w²(c/(μ_p V_p) + 1/(V_p K̄_p)): the typical eigenvalue of G K_d⁻¹ Gᵀ against the pressure mass"})
    schur: str = field(default="probed", metadata={"choices": ("probed", "mass"), "doc": "diagonal Schur approximation: `probed`, the diagonal of G M Gᵀ (M the displacement split's preconditioner) by probing with probe_spacing³ colours of the patch grid at each Newton system (as mixed_amg); `mass`, c/(μ_p V_p) with c = schur_scale"})
    probe_spacing: int = field(default=3, metadata={"range": (2, None), "doc": "with schur: probed, same-colour patches of the probe are this many patch boxes apart (spacing³ colours, as many applications of the displacement preconditioner per Newton system)"})
    region_solves: bool = field(default=True, metadata={"doc": "after each GAMG cycle on the displacement block, solve it exactly on the node regions of the boundary conditions (PCCOMPOSITE multiplicative of GAMG and PCASM, one local subdomain per region on each rank: the region's owned rows), where the penalty couplings, K-scaled with the default penalty number, live"})


@BACKENDS.register("petsc_mixed", options=PETScMixedOptions)
class PETScMixedSolver(PETScSolver):
    """PETSc FGMRES + Schur field split on the mixed form (see the module docstring).

    Parameters
    ----------
    X : (N, 3) float
        Node coordinates, cm.
    ijk : (N, 3) int
        Voxel indices.
    rtol : float
        Relative condensed residual when the caller gives none.
    maxiter : int
        Krylov iterations per linear solve, all refinement passes together.
    options : dict, optional
        PETSc options (names without the dash), over :data:`DEFAULT_OPTIONS` for the mixed solve
        and over :data:`.petsc.DEFAULT_OPTIONS` for the condensed one (no projected energy).
    schur_scale : float
        With ``schur="mass"``: c in Ŝ = w² (D⁻¹ + c/(μ_p V_p)).
    schur : {"probed", "mass"}
        Diagonal Schur approximation (module docstring).
    probe_spacing : int
        With ``schur="probed"``: colour spacing of the probe on the patch grid.
    region_solves : bool
        Displacement split: BoomerAMG (GAMG without hypre) then exact (LU) solves on the
        boundary-condition regions (:func:`region_options`); without, GAMG alone (:data:`DEFAULT_OPTIONS`).
    """

    name = "petsc_mixed"

    def __init__(self, X, ijk, rtol: float = 1e-10, maxiter: int = 2000, options: dict | None = None,
                 schur_scale: float = 0.5, region_solves: bool = True, schur: str = "probed", probe_spacing: int = 3):
        super().__init__(X, ijk, rtol=rtol, maxiter=maxiter, options=options)
        self.mixed_options = set_options(_PREFIX, region_options() if region_solves else DEFAULT_OPTIONS, options)
        self.schur_scale = float(schur_scale)
        self.schur = schur
        self.probe_spacing = int(probe_spacing)
        self.ijk = np.asarray(ijk)
        self.region_solves = bool(region_solves)
        self._mixed = None
        self._press = None
        self._gather = None
        self._pgather = None
        self._regions = None
        self._space = None
        self.info.update(refinements=0, pressures=0, region_rows=0)

    @classmethod
    def from_options(cls, opts: PETScMixedOptions, X, *, ijk=None, width=(4, 4, 4)) -> PETScMixedSolver:
        if ijk is None:
            raise ValueError("petsc_mixed needs the voxel indices ijk of the nodes")
        return cls(X, ijk, rtol=opts.rtol, maxiter=opts.maxiter, options=dict(opts.petsc_options),
                   schur_scale=opts.schur_scale, region_solves=opts.region_solves, schur=opts.schur,
                   probe_spacing=opts.probe_spacing)

    def _pressure_partition(self, space):
        """PETSc order of the pressure unknowns: the free patches by owning rank (the lowest rank
        among their nodes). Returns the free patches in that order and the bounds per rank."""
        rank_of_node = np.empty(self.dof.size // 3, np.int64)
        rank_of_node[self.order] = np.repeat(np.arange(self.size), np.diff(self.bounds))
        owner = np.full(space.n_patches, self.size, np.int64)
        np.minimum.at(owner, space.patch_of, rank_of_node)
        free = space.free
        by_rank = np.argsort(owner[free], kind="stable")
        patches = free[by_rank]
        bounds = np.searchsorted(owner[patches], np.arange(self.size + 1), side="left")
        return patches, bounds

    def prepare(self, system, state):
        space = system.pressure_space()
        if space is None or space.free.size == 0:
            self._mixed = None
            super().prepare(system, state)
            return
        PETSc = self.PETSc
        t0 = time.perf_counter()
        if self._rows is None:
            self._rows = system.owned_rows(self.owned)
            self.info["halo_cells"] = int(self._rows.cells.size - self.owned.size)
        if self._press is None:
            patches, bounds = self._pressure_partition(space)
            self._press = (patches, bounds, patches[bounds[self.rank]:bounds[self.rank + 1]])
            self.info["pressures"] = int(patches.size)
        patches, pbounds, mine = self._press
        n_loc, n = self.hi - self.lo, self.dof.size
        m_loc, m = mine.size, patches.size
        p0 = int(pbounds[self.rank])

        Kd = self._rows.rows(state, pressure_free=True)
        A00 = self._displacement_matrix(Kd)
        full = system.tangent_operator(state)  # the condensed tangent, matrix-free: the stopping test
        blocks = MixedBlocks(space, mine)  # w from all free patches: every rank has the same number
        w = blocks.w
        G = (w * system.patch_divergence(state, mine).sparse()).tocsr()
        G.indices = self.pos[G.indices]
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
        isu.compose("nearnullspace", A00.getNearNullSpace())
        if self._mixed is not None:
            self._mixed["ksp"].destroy()
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
        self._set_region_subdomains(system, pc)
        if self.schur == "probed":
            self._probe_schur(space, pc, A01, A10, S, blocks, mine)
        b = PETSc.Vec().createMPI((n_loc + m_loc, PETSc.DECIDE), comm=self.comm)  # per rank: [u; p] owned
        z = b.duplicate()
        start = b.getOwnershipRange()[0]
        if self._gather is None:  # the displacement part of a solution to every rank
            xu = PETSc.Vec().createMPI((n_loc, n), comm=self.comm)
            self._gather = (xu, *PETSc.Scatter.toAll(xu))
        if self._pgather is None:  # and its pressure part
            xp = PETSc.Vec().createMPI((m_loc, m), comm=self.comm)
            self._pgather = (xp, *PETSc.Scatter.toAll(xp))
        self._space = space
        self._mixed = {"ksp": ksp, "A": A, "b": b, "z": z, "t": b.duplicate(), "u": isu.getIndices() - start,
                       "p": isp.getIndices() - start, "w": w, "K": full, "blocks": (A00, A01, A10, A11, S)}
        self.info["preconditioner_builds"] += 1
        self.info["setup_s"] = time.perf_counter() - t0
        self.info["nnz_local"] = int(Kd.nnz + 2 * G.nnz)

    def _set_region_subdomains(self, system, pc) -> None:
        """With ``region_solves`` (and, as in :func:`region_options`, the displacement split's PC a
        composite whose sub-PCs the options do not list), add the multigrid and PCASM to it and give PCASM
        its subdomains: on this rank, for each region of :func:`.subdomains.constraint_regions`, the
        region's dofs among the owned rows (PETSc displacement numbering); regions without an owned
        row are left out, and a rank without any has one empty subdomain."""
        opts = self.mixed_options
        if (not self.region_solves or str(opts.get("fieldsplit_u_pc_type")) != "composite"
                or "fieldsplit_u_pc_composite_pcs" in opts):
            return
        PETSc = self.PETSc
        if self._regions is None:
            sets = []
            for nodes in system.stiff_regions():
                rows = self.pos[(3 * nodes[:, None] + np.arange(3)).ravel()]
                rows = np.sort(rows[(rows >= self.lo) & (rows < self.hi)])
                if rows.size:
                    sets.append(rows.astype(PETSc.IntType))
            self._regions = sets
            self.info["region_rows"] = int(sum(r.size for r in sets))
        pc.setUp()  # creates the split KSPs (not yet set up) and their PCs from the options
        composite = pc.getFieldSplitSubKSP()[0].getPC()
        composite.addCompositePCType(str(opts.get("fieldsplit_u_sub_0_pc_type", "gamg")))
        composite.addCompositePCType("asm")
        amg, asm = composite.getCompositePC(0), composite.getCompositePC(1)
        amg.setFromOptions()
        asm.setFromOptions()
        # PCASM wants at least one subdomain per rank: a rank without region rows gets an empty one
        subdomains = [PETSc.IS().createGeneral(r, comm=PETSc.COMM_SELF)
                      for r in self._regions or [np.empty(0, PETSc.IntType)]]
        asm.setASMLocalSubdomains(len(subdomains), subdomains)

    def _probe_schur(self, space, pc, A01, A10, S, blocks: MixedBlocks, mine: np.ndarray) -> None:
        """Set −Ŝ in ``S``, the diagonal of w² G M Gᵀ probed as in
        :func:`.mixed_method.probed_schur_diagonal` (same colours and signs, so one rank and several
        give the same numbers) with M the displacement split's preconditioner, applied outside the KSP."""
        PETSc = self.PETSc
        pc.setUp()
        upc = pc.getFieldSplitSubKSP()[0].getPC()
        upc.setUp()
        free = space.free  # mixed_amg's probe colours the free patches, in order
        colour, sign = np.zeros(space.n_patches, np.int64), np.zeros(space.n_patches)
        colour[free], sign[free] = probe_colours(space.box[free], self.probe_spacing)
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
        probe = probe_diagonal(product, colour[mine], sign[mine], range(self.probe_spacing ** 3), largest)
        diag = S.createVecLeft()
        diag.setArray(-blocks.schur("probed", self.schur_scale, probe))
        S.setDiagonal(diag)
        for v in (q, g, u, y, diag):
            v.destroy()

    def _diagonal(self, values: np.ndarray, start: int, size: int):
        """A distributed diagonal AIJ matrix with the owned ``values`` from global row ``start``."""
        PETSc = self.PETSc
        k = values.size
        M = PETSc.Mat().createAIJ(size=((k, size), (k, size)), comm=self.comm,
                                  csr=(np.arange(k + 1, dtype=PETSc.IntType),
                                       (start + np.arange(k)).astype(PETSc.IntType), np.asarray(values, float)))
        M.assemble()
        return M

    def solve(self, r, rtol=None):
        if self._mixed is None:
            return super().solve(r, rtol)
        t0 = time.perf_counter()
        rtol = self.rtol if rtol is None else max(float(rtol), 1e-14)
        mx = self._mixed
        ksp, A, b, z, t, iu, K = mx["ksp"], mx["A"], mx["b"], mx["z"], mx["t"], mx["u"], mx["K"]
        rr = np.asarray(r, float).ravel()
        bn = float(np.linalg.norm(rr))
        own = self.dof[self.lo:self.hi]
        self.info["passes"] = []  # (mixed target, iterations, condensed relative residual after) per pass

        def mixed_pass(res, x, target, lag, budget, attempt) -> Pass:
            barr = b.getArray()
            barr[:] = 0.0
            barr[iu] = res[own]
            b.setArray(barr)
            ksp.setTolerances(rtol=target, atol=0.0, max_it=budget)
            ksp.solve(b, z)
            its, reason = int(ksp.getIterationNumber()), int(ksp.getConvergedReason())
            dx = np.zeros(rr.size)
            if reason < 0:
                return Pass(dx, its, f"diverged (PETSc reason {reason})")
            A.mult(z, t)
            t.aypx(-1.0, b)  # t = b − A z, the true mixed residual
            mixed = t.norm()
            dx[self.dof] = self._gathered(z.getArray()[iu])
            left = rr - K @ (x + dx)
            new = float(np.linalg.norm(left))
            self.info["passes"].append((target, its, new / max(bn, 1e-300)))
            if new <= rtol * bn:
                return Pass(dx, its, "converged", residual=left)
            return Pass(dx, its, "converged", lag=new / max(mixed, 1e-300), residual=left)  # condensed per mixed

        x, total, status, passes = refine(mixed_pass, lambda x: rr - K @ x, rr, rtol, self.maxiter, _FLOOR)
        self.info["iterations"] = total
        self.info["krylov_iterations"] += total
        self.info["refinements"] += max(passes - 1, 0)
        self.info["solve_s"] = time.perf_counter() - t0
        if status != "converged":
            rn = float(np.linalg.norm(rr - K @ x))
            amg = "fieldsplit_u_sub_0_pc_type" if self.region_solves else "fieldsplit_u_pc_type"
            raise SolverError(f"petsc_mixed: KSP fgmres with the Schur field split {status} after {total} iterations "
                              f"in {passes} passes (condensed relative residual {rn / max(bn, 1e-300):.1e}, target "
                              f"{rtol:.1e}); try solver.petsc_options {{{amg}: hypre}} or the "
                              "condensed backend petsc, or check the boundary conditions")
        return x.reshape(np.shape(r))

    def _gathered(self, owned: np.ndarray) -> np.ndarray:
        """The displacement part of a solution (owned rows, PETSc order) on every rank, in PETSc order."""
        xu, gather, xall = self._gather
        xu.setArray(owned)
        gather.scatter(xu, xall, addv=False, mode=self.PETSc.ScatterMode.FORWARD)
        return xall.getArray()

    def solve_mixed(self, r, rp, rtol=None):
        """One update of Newton on the mixed form, as :meth:`.mixed.MixedBlockSolver.solve_mixed`: the
        force residual ``r`` (3N,) N and the pressure residual ``rp`` (N_p,) as the two blocks, one
        KSP solve stopped on the mixed residual; returns (Δd (3N,) cm, Δp (N_p,) N/cm², 0 at held
        patches) on every rank."""
        if self._mixed is None:
            return self.solve(r, rtol), None
        t0 = time.perf_counter()
        rtol = self.rtol if rtol is None else max(float(rtol), 1e-14)
        mx = self._mixed
        ksp, b, z = mx["ksp"], mx["b"], mx["z"]
        patches, _, mine = self._press
        barr = b.getArray()
        barr[mx["u"]] = np.asarray(r, float).ravel()[self.dof[self.lo:self.hi]]
        barr[mx["p"]] = self._space.scaled_rhs(rp, mine)
        b.setArray(barr)
        ksp.setTolerances(rtol=rtol, atol=0.0, max_it=self.maxiter)
        ksp.solve(b, z)
        its, reason = int(ksp.getIterationNumber()), int(ksp.getConvergedReason())
        zarr = z.getArray()
        x = np.zeros(np.asarray(r).size)
        x[self.dof] = self._gathered(zarr[mx["u"]])
        xp, pgather, pall = self._pgather
        xp.setArray(zarr[mx["p"]])
        pgather.scatter(xp, pall, addv=False, mode=self.PETSc.ScatterMode.FORWARD)
        dp = self._space.update(pall.getArray(), patches)
        self.info["iterations"] = its
        self.info["krylov_iterations"] += its
        self.info["solve_s"] = time.perf_counter() - t0
        if reason < 0:
            amg = "fieldsplit_u_sub_0_pc_type" if self.region_solves else "fieldsplit_u_pc_type"
            raise SolverError(f"petsc_mixed: KSP fgmres with the Schur field split diverged (PETSc reason {reason}) "
                              f"after {its} iterations (target {rtol:.1e}); try solver.petsc_options {{{amg}: hypre}} "
                              "or the condensed backend petsc, or check the boundary conditions")
        return x, dp

    def statistics(self) -> dict:
        """As ``petsc``, plus ``refinements`` (mixed re-solves for the condensed residual, all solves)."""
        return super().statistics() | {"refinements": self.info["refinements"]}

r"""Iterative backend ``mixed_amg``: the Newton system in mixed displacement–pressure form, GMRES
with a block-triangular preconditioner.

Why. With the projected volumetric energy (:mod:`..volumetric`) the condensed tangent is

    K = K_d + Gᵀ D G,    D = diag(V_p K̄_p),

with K_d the tangent without the patch terms and G (N_p × 3N) the patch dilatation rates
g_pᵀ. D grows with the bulk modulus, so CG on K with a multigrid preconditioner needs more
iterations the more incompressible the tissue (~3.3× per decade of K/μ on the leg). The same
update solves the mixed system

    [ K_d   Gᵀ   ] [Δd]   [r]
    [ G   −D⁻¹   ] [ q] = [0],        q = D G Δd  (the patch pressure increments times V_p),

whose blocks hold no K-scaled term but D⁻¹ → 0. With an inf-sup stable patch pressure (the
default 2 × 2 × 3 patches; not 1 × 1 × 3, :mod:`..volumetric`) the Schur complement
S = D⁻¹ + G K_d⁻¹ Gᵀ is spectrally equivalent to the scaled pressure mass diag(1/(μ_p V_p)) + D⁻¹,
and a block-triangular preconditioner

    P = [ M_A   Gᵀ ]
        [ 0    −Ŝ  ],   M_A⁻¹ ≈ K_d⁻¹,   Ŝ = D⁻¹ + diag(G M_A⁻¹ Gᵀ),

gives Krylov iterations independent of K/μ and of the model size (Klawonn 1998; Elman,
Silvester & Wathen 2014, ch. 9), provided K_d holds no K-scaled term either. The patches of
single nodes held at the node (``volumetric.held: own``, the default) keep their term in K_d,
which then grows with K; the region solves after the V-cycle take those rows exactly, so the
iterations stay flat. With ``volumetric.held: patch`` every patch pressure is an unknown.

The preconditioner. M_A⁻¹ is one AMG V-cycle on K_d (the hierarchy of ``cg_amg``, built from its
positive definite stand-in on the ±2-voxel pattern, :meth:`~.operator.SystemOperator.preconditioner_matrix`)
followed by
sparse solves of K_d on the node regions of the boundary conditions (``region_solves``,
:mod:`.subdomains`; by default each displacement component's diagonal block, ``region_coupling``): the penalty rows of the end faces and bone surfaces couple every node in the
support of a constraint point, which a point smoother cannot reduce; a multiplicative Schwarz
correction on those thin regions (end-face slabs, bone surfaces) takes them. The diagonal of
G M_A⁻¹ Gᵀ in Ŝ is estimated by probing with 27 colours of the patch grid (``schur: probed``, the
default; :func:`.mixed_method.probed_schur_diagonal`, ``probe_spacing`` = 3), once per build of the hierarchy at
the state it is built from (27 applications of M_A⁻¹), and kept with it; ``schur: mass`` takes
the scaled pressure mass c/(μ_p V_p) instead (c = ``schur_scale``). On the leg with the default
penalty number, FGMRES reaches 10⁻⁶ on the first Newton system (α = 0.095), stopped on the mixed
residual, in 31, 32 and 32 iterations at K/μ ≈ 95, 951 and 9,506 (5,460 nodes; 79, 116 and 131
with ``schur: mass`` and the condensed stop, an earlier version), in 34 on 21,169 nodes, 41 on
73,753 and 46 on the 295,073 of the 0.078-cm pixels at K/μ ≈ 951 (the git history of docs/performance.md).

GMRES. The preconditioner — one V-cycle with fixed sweeps, region solves with fixed factors, a diagonal Ŝ — is
one fixed linear operator, so GMRES preconditioned from the right needs no basis of preconditioned
directions (flexible GMRES keeps one): the update is M (V y) (:func:`.fgmres.fgmres` with
``flexible=False``), the same iterates for half the basis memory (the two bases held 1.5 GB in the longest solve
of the 295k model); docs and records call its iterations FGMRES iterations.

Scaling. The unknowns are Δd (cm) and q̃ = q / w (cm), and the second row is multiplied by w,
w = mean_p(μ_p V_p) / s (N, s the smallest voxel edge): the system stays symmetric,

    [ K_d      w Gᵀ       ] [Δd]   [r]
    [ w G   −w² D⁻¹       ] [ q̃] = [0],

both residual blocks are forces (N) and no block grows with K. (Scaling the second row by D
instead makes the lower-left block K-scaled, and the iterations grow with K.) The condensed
residual is r − K Δd = r₁ + Gᵀ (D/w) r₂ (rᵢ the mixed residual blocks), so it can lag the mixed
one by up to K/μ. :meth:`MixedBlockSolver.solve_mixed`, the update of Newton on the mixed form
(:mod:`..newton`), takes the pressure residual as the second block and stops on the mixed
residual. :meth:`MixedBlockSolver.solve` (the condensed update) stops on the exact condensed residual: each time FGMRES meets its
target, the condensed residual of that iterate is computed, and while it lags FGMRES goes on in
the same Krylov basis with the target tightened by the lag it showed (:func:`.fgmres.fgmres`'s
``check``). Restarting there instead forgets the directions FGMRES has found: on the 20k leg
(load step 1, second Newton system, the first with the muscles active) the residual of a
full-basis run stalls between iterations 70 and 120 and then falls fast (a few outlying
eigenvalues), and FGMRES(60) restarted at each tightened target needed 255–294 iterations where
one basis of 200 needs 120. Where the tightened target would fall below the round-off floor of
the mixed residual, or the true mixed residual has drifted from FGMRES's estimate of it, the
solve refines instead (a new mixed solve for the condensed residual of the update so far, its
target set by the lag of the last pass; :func:`.mixed_method.refine`, which ``petsc_mixed`` shares).
Newton, line search and tolerances are those of the condensed system. The operators, the
block-triangular preconditioner, the probed Schur diagonal and the refinement loop are those of
:mod:`.mixed_method`; the system enters only through :class:`~.operator.SystemOperator`.

References
----------
A. Klawonn, "Block-triangular preconditioners for saddle point problems with a penalty term",
SIAM J. Sci. Comput. 19(1), 172–184, 1998.
H. C. Elman, D. J. Silvester, A. J. Wathen, *Finite Elements and Fast Iterative Solvers*, 2nd ed.,
Oxford University Press, 2014.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import field

import numpy as np

from ..heap import release_free_heap
from .amg_processes import flush_released
from .base import BACKENDS
from .cg_amg import CGAMGOptions, KrylovAMGSolver
from .fgmres import fgmres
from .mixed_method import BlockTriangular, MixedBlocks, MixedOperator, Pass, probed_schur_diagonal, refine
from .multigrid import drop_weak_blocks
from .subdomains import COUPLINGS, CorrectedVCycle

_LOG = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class MixedAMGOptions(CGAMGOptions):
    """Options of ``solve.solver: {backend: mixed_amg, …}``."""

    rebuild_cost: int = field(default=40, metadata={"range": (1, None), "doc": "what a build of the AMG hierarchy with its region factors and Schur diagonal costs, in FGMRES iterations (a build's wall time over one iteration's; the statistics give both as preconditioner_build_s and the solve times): the hierarchy is rebuilt once the iterations beyond its rate right after the last build add up to this many (within a solve too; see cg_amg)"})
    schur_scale: float = field(default=0.5, metadata={"gt": 0, "doc": "with schur: mass, c of the diagonal Schur complement diag(c/(μ_p V_p) + 1/(V_p K̄_p)): the typical eigenvalue of G K_d⁻¹ Gᵀ against the pressure mass"})
    restart: int = field(default=200, metadata={"range": (1, None), "doc": "GMRES basis size (vectors kept before a restart; memory restart × the unknowns)"})
    schur: str = field(default="probed", metadata={"choices": ("probed", "mass"), "doc": "diagonal Schur approximation: `probed`, the diagonal of G M Gᵀ (M the displacement block's preconditioner) by probing with probe_spacing³ colours of the patch grid at each preconditioner build; `mass`, c/(μ_p V_p) with c = schur_scale"})
    probe_spacing: int = field(default=3, metadata={"range": (2, None), "doc": "with schur: probed, same-colour patches of the probe are this many patch boxes apart (spacing³ colours, as many V-cycles at each preconditioner build)"})
    region_solves: bool = field(default=True, metadata={"doc": "after each V-cycle, solve the displacement block exactly on the node regions of the boundary conditions (the supports of their constraint points: end slabs, bone surfaces), where the stiff penalty couplings live (linsolve/subdomains.py)"})
    region_coupling: str = field(default="auto", metadata={"choices": ("auto", "components", "full"), "doc": "with region_solves: what is factorised on a region: `components`, each displacement component's diagonal block of K_d (x–x, y–y, z–z) on its own, the couplings between components left to the multigrid cycle before it (the penalty rows, which are per component, are still solved exactly), in about a third of the memory of `full`, the whole 3 × 3-coupled block; `auto`, the whole block on a region that reaches a held single-node patch (volumetric.held: own, whose K-scaled volumetric term couples the components), each component's block elsewhere (docs/performance.md, region solves)"})
    region_precision: str = field(default="double", metadata={"choices": ("double", "single"), "doc": "with region_solves and PARDISO: the region factors in `double` precision, or in `single` (their values in half the memory, PARDISO iparm[27]; slower: each solve is refined) with every region solve refined in double precision against the block's float64 values to 10⁻¹² (pardiso.py)"})
    drop_tol: float = field(default=0.0, metadata={"range": (0, None), "doc": "the multigrid's stand-in leaves out every off-diagonal node block weaker than drop_tol times the geometric mean of its two diagonal blocks (Frobenius norms; linsolve/multigrid.py drop_weak_blocks); 0 (default) keeps them all: the stand-in is then positive definite; leaving blocks out can make it indefinite and the multigrid a worse preconditioner"})


@BACKENDS.register("mixed_amg", options=MixedAMGOptions)
class MixedBlockSolver(KrylovAMGSolver):
    """FGMRES on the mixed form of the projected-energy tangent (see the module docstring).

    Parameters
    ----------
    X, ijk, rtol, maxiter, reach, aggregate, theta
        As :class:`~.cg_amg.KrylovAMGSolver` (the AMG hierarchy, now of the displacement block
        without patch terms, and its rebuild rule are the same).
    schur_scale : float
        With ``schur="mass"``: c in Ŝ = diag(c/(μ_p V_p) + 1/(V_p K̄_p)), the typical eigenvalue of G K_d⁻¹ Gᵀ against
        the pressure mass (≈ 0.5 for 2 × 2 × 3 patches on the voxel grid).
    restart : int
        FGMRES basis size.
    schur : {"probed", "mass"}
        Diagonal Schur approximation: ``probed`` (default, :func:`.mixed_method.probed_schur_diagonal`) or the
        scaled pressure mass c/(μ_p V_p).
    probe_spacing : int
        With ``schur="probed"``: colour spacing of the probe on the patch grid (spacing³
        applications of M_A at each build of the hierarchy).
    region_solves : bool
        Follow each V-cycle by exact solves of K_d on the regions of the boundary conditions
        (:mod:`.subdomains`).
    region_precision : {"double", "single"}
        Precision of the PARDISO factors of the regions (single: refined in double precision
        at each solve, :class:`~..pardiso.PardisoLDLT`).
    region_coupling : {"auto", "components", "full"}
        What is factorised on a region: each displacement component's diagonal block of K_d
        (:class:`.factorization.ComponentFactors`), the whole block, or (auto) the whole block
        only where a held single-node patch couples the components (:class:`.subdomains.RegionSolves`).
    drop_tol : float
        The multigrid's stand-in leaves out the off-diagonal node blocks weaker than this
        (:func:`.multigrid.drop_weak_blocks`); 0 keeps them all, and only then is the stand-in
        positive definite.

    Notes
    -----
    Without a projected volumetric energy there is no pressure: the solver then runs CG with the
    AMG preconditioner, as ``cg_amg``.
    """

    name = "mixed_amg"

    def __init__(self, X, ijk, rtol: float = 1e-8, maxiter: int = 2000, schur_scale: float = 0.5, restart: int = 200,
                 schur: str = "probed", region_solves: bool = True, probe_spacing: int = 3, drop_tol: float = 0.0,
                 rebuild_cost: int = 40, region_precision: str = "double", region_coupling: str = "auto", **kw):
        super().__init__(X, ijk, rtol=rtol, maxiter=maxiter, rebuild_cost=rebuild_cost, **kw)
        self.drop_tol = drop_tol
        self.schur_scale = schur_scale
        self.restart = restart
        self.region_solves = region_solves
        if region_precision not in ("double", "single"):
            raise ValueError(f"region_precision must be 'double' or 'single', got {region_precision!r}")
        self.region_precision = region_precision
        if region_coupling not in COUPLINGS:
            raise ValueError(f"region_coupling must be one of {COUPLINGS}, got {region_coupling!r}")
        self.region_coupling = region_coupling
        self.schur = schur
        self.probe_spacing = probe_spacing
        self._regions = None
        self._press = None
        self._probe = None
        self._mixed = None  # (mixed operator, preconditioner) of the prepared system
        self._blocks = None  # its MixedBlocks
        self.info.update(region_nodes=0)

    def _stand_in(self):
        return drop_weak_blocks(self._system.preconditioner_matrix(self._state, self.reach, volumetric="held"),
                                self.drop_tol)

    def _patch_divergence(self):
        """G of the free patches at the prepared state."""
        return self._system.patch_divergence(self._state, self._press)

    def prepare(self, system, state):
        super().prepare(system, state)
        space = system.pressure_space()
        self._mixed = None
        if space is None:
            return
        self._press = space.free
        Kd = system.displacement_operator(state, tangent=self._A)
        G = self._patch_divergence()
        blocks = MixedBlocks(space, self._press)
        self._mixed = (MixedOperator(Kd, G, blocks.c22, blocks.w),
                       BlockTriangular(self._M, G, self._schur_diagonal(blocks), blocks.w, Kd.shape[0]))
        self._blocks = blocks

    def _schur_diagonal(self, blocks: MixedBlocks) -> np.ndarray:
        """Ŝ with the diagonal of G M Gᵀ probed at the last build, or the scaled mass."""
        probe = None if self._probe is None else blocks.w * blocks.w * self._probe
        return blocks.schur(self.schur, self.schur_scale, probe)

    def _build(self):
        """The region factors first, then the hierarchy, then the Schur probe with both.

        The old hierarchy and factors are let go before anything new is made. The regions are
        factorised before the hierarchy is set up, not beside it: their assembly and PARDISO's
        work space (beside 1.15 GB of factors at 295k nodes, ``bench_memory.json``) then never
        meet BoomerAMG's hierarchy on both processes, which was each rebuild's peak."""
        if self._mixed is not None:  # the last system's preconditioner holds the old hierarchy: let it go first
            self._mixed[1].MA = None
        self._M = None
        if self._regions is not None:  # and the region factors, which update() makes again
            self._regions.release()
        flush_released()  # the hierarchy on the BoomerAMG workers too
        release_free_heap()
        space = self._system.pressure_space()  # prepare() sets the system before any build
        t0 = time.perf_counter()
        if space is not None and self.region_solves:
            if self._regions is None:
                self._regions = self._system.region_solves(self._system.stiff_regions(), self.ijk,
                                                           single=self.region_precision == "single",
                                                           coupling=self.region_coupling)
                self.info["region_nodes"] = self._regions.n_nodes
            self._regions.update(self._state)
            release_free_heap()  # the region blocks' assembly and factorisation temporaries
        regions_s = time.perf_counter() - t0
        super()._build()
        self.info["setup_s"] += regions_s
        self.info["build_s"][-1] += regions_s
        if space is None:
            return
        t0 = time.perf_counter()
        if self.region_solves:
            self._M = CorrectedVCycle(self._M, self._regions)
        if self.schur == "probed":  # diag(G M Gᵀ) of this hierarchy, at the state it is built from
            self._press = space.free
            self._probe = probed_schur_diagonal(self._patch_divergence(), self._M, space.box[space.free],
                                                self.probe_spacing)
        release_free_heap()  # the probe's temporaries
        self.info["setup_s"] += time.perf_counter() - t0
        self.info["build_s"][-1] += time.perf_counter() - t0

    def finish(self) -> None:
        """Drop the tangent and the mixed operator (the hierarchy, region factors and Schur diagonal stay)."""
        self._mixed = None
        super().finish()

    def release(self) -> None:
        """Drop the mixed operator and its preconditioner, the region factors and the hierarchy."""
        self._mixed = self._blocks = None
        if self._regions is not None:
            self._regions.release()
        super().release()

    def _refresh(self):
        """After a rebuild of the AMG hierarchy the preconditioner must use the new one."""
        if self._mixed is not None:
            P = self._mixed[1]
            P.MA = self._M
            if self.schur == "probed":
                P.shat = self._schur_diagonal(self._blocks)

    def solve(self, r, rtol=None):
        if self._mixed is None:
            return super().solve(r, rtol)
        t0 = time.perf_counter()
        setup0 = self.info["setup_s"]
        rtol = self.rtol if rtol is None else max(float(rtol), 1e-14)
        b = np.asarray(r, float)
        n = b.size
        bn = float(np.linalg.norm(b))
        A, P = self._mixed
        floor = 1e-10  # round-off floor of the mixed residual, relative
        stale = [0]

        def mixed_pass(res, x, target, lag, budget, attempt) -> Pass:
            rhs = np.concatenate([res, np.zeros(A.c22.size)])
            rn = float(np.linalg.norm(rhs))
            verdict = {"lag": lag, "target": target}

            def check(z):
                """The exact condensed residual decides: None accepts z, else the tightened target."""
                new = float(np.linalg.norm(b - self._A @ (x + z[:n])))
                if new <= rtol * bn or bn == 0.0:
                    return None
                mixed = float(np.linalg.norm(rhs - A @ z)) / rn
                verdict["lag"] = new / max(mixed * rn, 1e-300)  # condensed residual per mixed residual
                tight = mixed * 0.5 * rtol * bn / new
                # refine below the round-off floor, or where the true mixed residual has drifted from
                # FGMRES's estimate of it (the basis has lost orthogonality: going on cannot gain)
                if tight < floor or mixed > 10.0 * verdict["target"]:
                    verdict["refine"] = True
                    return None
                verdict["target"] = tight
                return tight

            if attempt:
                z, its, status = fgmres(A, rhs, P, target, budget, restart=self.restart, check=check, flexible=False)
            else:
                def fresh_verdict():
                    verdict.clear()  # the new preconditioner's iterations show their own lag
                    verdict.update(lag=lag, target=target)

                z, its, status, stale[0] = self._fgmres_or_rebuild(rhs, target, rtol, check, fresh_verdict)
            return Pass(z[:n], its, status, verdict["lag"] if verdict.get("refine") else None)

        x, total, status, _ = refine(mixed_pass, lambda x: b - self._A @ x, b, rtol, self.maxiter, floor)
        self._close(t0, setup0, status, total, stale[0], rtol)
        return x

    def solve_mixed(self, r: np.ndarray, rp: np.ndarray, rtol=None) -> tuple[np.ndarray, np.ndarray | None]:
        """One update of Newton on the mixed form: [K_d, Gᵀ; G, −D⁻¹] [Δd; Δq] = [r; −r_p], Δq = V∘Δp.

        The solve stops on the mixed residual ‖[r₁; r₂]‖ ≤ rtol ‖[r; −w r_p]‖ (both blocks in N),
        not on the condensed one, which lags it by up to K/μ (module docstring): the pressure
        rows' residual stays in the pressure equations of the next Newton iteration instead of
        being multiplied by the bulk modulus.

        Parameters
        ----------
        r : (3N,) float
            Force residual with the carried patch pressure, N (:meth:`~..system.MechanicalSystem.mixed_residual`).
        rp : (N_p,) float
            Pressure residual θ_p − 1 − p_p/K̄_p of every patch (0 at held ones), dimensionless.
        rtol : float, optional

        Returns
        -------
        dd : (3N,) float
            Displacement update, cm.
        dp : (N_p,) float or None
            Pressure update of every patch, N/cm² (0 at held patches); None without patches (the
            update is then :meth:`solve`'s).
        """
        if self._mixed is None:
            return self.solve(r, rtol), None
        t0 = time.perf_counter()
        setup0 = self.info["setup_s"]
        rtol = self.rtol if rtol is None else max(float(rtol), 1e-14)
        A, P = self._mixed
        space = self._system.pressure_space()
        rhs = np.concatenate([np.asarray(r, float), space.scaled_rhs(rp, self._press)])
        z, total, status, stale = self._fgmres_or_rebuild(rhs, rtol, rtol)
        self._close(t0, setup0, status, total, stale, rtol)
        return z[:A.n], space.update(z[A.n:], self._press)

    def _fgmres_or_rebuild(self, rhs, target, rtol, check=None, on_rebuild=None):
        """FGMRES on the mixed system with the kept preconditioner, within its budget for ``rtol``;
        when that budget runs out (the kept preconditioner has cost more than a rebuild), rebuild
        it and go on from the iterate reached (a restart from zero would throw its residual
        reduction away). Returns (z, iterations, status, iterations of the stale preconditioner)."""
        A, P = self._mixed
        z, its, status = fgmres(A, rhs, P, target, self.policy.budget(rtol), restart=self.restart, check=check,
                                flexible=False)
        if not self.policy.may_rebuild(status, its):
            return z, its, status, 0
        _LOG.debug("FGMRES: %d iterations with a kept preconditioner cost more than a rebuild; rebuilding it", its)
        self._build()
        self._refresh()
        if on_rebuild is not None:
            on_rebuild()
        z, more, status = fgmres(A, rhs, P, target, self.policy.retry_budget(rtol, its), restart=self.restart,
                                 x0=z, check=check, flexible=False)
        return z, its + more, status, its

    def _close(self, t0, setup0, status, total, stale, rtol):
        """Book-keeping of one solve; raises when it did not converge."""
        self.info["iterations"] = total
        self.info["krylov_iterations"] += total
        self.info["solve_s"] = time.perf_counter() - t0 - (self.info["setup_s"] - setup0)
        if status != "converged":
            raise self._fail("FGMRES", status, total, rtol)
        if not stale:  # a solve continued after a rebuild does not show the new hierarchy's rate: the next one does
            self.policy.account(total, rtol)


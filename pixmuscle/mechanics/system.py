"""The discrete equilibrium equations of a pixel-point model: :class:`MechanicalSystem` (paper §3).

What is built once per model (:func:`build_system`):

1. RK shape functions (cubic B-spline box kernel, linear basis, a = (a/h)·spacing per axis) at the
   unique cell faces → SCNI smoothed gradient operators G_k (:mod:`.scni`);
2. materials per node from the tissue code (muscle: transversely isotropic with per-node fibre and
   activation α; connective tissue and fat: Yeoh), laws and constants from ``solve.materials``;
3. constant parts of the stiffness: NSNI stabilisation (:mod:`.stabilization`) and penalty
   (:mod:`.boundary`), assembled once on the fixed block pattern (:mod:`.assembly`).

At each node L (one integration cell): F_L = I + Σ_I d_I ⊗ b̃_I(X_L) (eq. 16), P_L from the
node's material, f_int,I = Σ_L V_L P_L b̃_I(X_L) (eq. 19) and K = Σ_L V_L B̃_Lᵀ A_L B̃_L (eqs. 17–20).

The linear solvers see a system only through the methods of
:class:`~.linsolve.operator.SystemOperator` (the tangent as an operator, its assembled or owned
rows, the positive stand-in, the pressure space and patch divergence of the mixed form, the stiff
regions of the boundary conditions); :func:`.solve.solve` drives the load steps.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp

from ..errors import InputError
from ..model.model import Model
from ..model.tissues import MUSCLE, NODE_TISSUES, TISSUE_NAMES
from .assembly import (
    Assembler,
    local_operator,
    local_rows_csr,
    nonzero_blocks,
    scatter_support,
    support_pattern,
    support_positions,
)
from .boundary import Constraints, build_constraints, end_rule, penalty_number, shared_by_mask, vertex_rule_faces
from .config import SolveConfig, SupportConfig
from .materials import LAWS, needs
from .pressure import PatchDivergence, PressureSpace, pressure_scale
from .rows import RowAssembler
from .scni import SCNI, build_scni, cell_corners, cell_faces, face_incidence, support_radius
from .stabilization import gradient_difference, gradient_differences, stabilization_moduli, stabilization_stiffness
from .tangent import ConstantStiffness, MatrixFreeTangent, ProductForm, spd_surrogate
from .volumetric import NODE_BLOCK, PatchProjection, VolumetricState, shear_moduli

if TYPE_CHECKING:
    from .linsolve.subdomains import RegionSolves

_LOG = logging.getLogger(__name__)
# the preconditioner's filtered stand-in (assembly.local_rows): each factor keeps its entries at the
# nodes within LOCAL_RADIUS voxels of its cell or point (the stand-in then couples nodes at most 2
# voxels apart) that are at least LOCAL_TOL times its row's largest: ~125 instead of ~335 non-zeros
# per row (the 335-per-row stand-in ran the 295k sweep out of memory); on the 0.078-cm leg at 21k
# nodes 39 FGMRES iterations on the first Newton system, 33 at 0.10 with 316 non-zeros per row,
# 43 at 0.25 with 129 (the git history of docs/performance.md)
LOCAL_RADIUS = 1
LOCAL_TOL = 0.15


def make_materials(cfg_materials, projected: bool = False) -> dict:
    """Material law per tissue code from ``solve.materials`` (defaults: paper Tables 1 and 2).

    ``projected``: the projected volumetric energy replaces each law's K/2 (J − 1)², so every law
    must have that split (a ``bulk_modulus``).
    """
    out = {code: getattr(cfg_materials, TISSUE_NAMES[code]) for code in NODE_TISSUES}
    for code, mat in out.items():
        if projected and getattr(mat, "bulk_modulus", None) is None:
            raise InputError(f"solve.materials.{TISSUE_NAMES[code]}: law {LAWS.entry_of(mat).name!r} has no volumetric "
                             "term K/2 (J - 1)^2 to project; set solve.volumetric.method: nodal")
    return out


def material_kw(mat, fiber: np.ndarray, activation) -> dict:
    """Keywords a law needs (:func:`pixmuscle.mechanics.materials.needs`): fibre (n, 3) and activation α."""
    wanted = needs(mat)
    kw = {}
    if "fiber" in wanted:
        kw["fiber"] = fiber
    if "activation" in wanted:
        kw["activation"] = activation
    return kw


def tissue_groups(tissue: np.ndarray, materials: dict) -> list[tuple]:
    """(code, material, node indices) of each tissue present, in :data:`NODE_TISSUES` order."""
    tissue = np.asarray(tissue)
    out = []
    for code in NODE_TISSUES:
        idx = np.flatnonzero(tissue == code)
        if idx.size:
            out.append((code, materials[code], idx))
    return out


def group_kw(mat, fiber: np.ndarray, idx: np.ndarray, alpha: float, activation=None) -> dict:
    """Keyword arguments of a material's stress functions for the nodes ``idx``: their fibres and α
    (``alpha`` itself, or with an :class:`~.activation.ActivationRamp` its per-node α at ramp
    parameter ``alpha``)."""
    act = alpha if activation is None or "activation" not in needs(mat) else activation.at(alpha)[idx]
    return material_kw(mat, fiber[idx], act)


def material_response(groups: list, fiber: np.ndarray, F: np.ndarray, alpha: float, activation=None,
                      tangent: bool = True, block: int = NODE_BLOCK):
    """P (N, 3, 3), N/cm², and if ``tangent`` A (N, 3, 3, 3, 3), N/cm², at every node, grouped by material.

    Parameters
    ----------
    groups : list
        :func:`tissue_groups` of the model.
    fiber : (N, 3) float
        Unit fibre direction per node.
    F : (N, 3, 3) float
        Deformation gradients.
    alpha : float
        Activation, or the ramp parameter of ``activation``.
    activation : ActivationRamp, optional
    block : int
        Nodes per call of a law (:data:`.volumetric.NODE_BLOCK`).
    """
    n = F.shape[0]
    P = np.empty((n, 3, 3))
    A = np.empty((n, 3, 3, 3, 3)) if tangent else None
    for _, mat, idx in groups:  # ≤ 3 tissues
        # by blocks of nodes: a law's temporaries (several (n, 81) arrays in a tangent) stay the
        # size of a block, not of the model (the laws are pointwise: the same numbers either way)
        for lo in range(0, idx.size, block):
            sub = idx[lo:lo + block]
            kw = group_kw(mat, fiber, sub, alpha, activation)
            if tangent:
                P[sub], A[sub] = mat.stress_tangent(F[sub], **kw)
            else:
                P[sub] = mat.stress(F[sub], **kw)
    return P, A


@dataclasses.dataclass
class State:
    """Mechanical state at coefficients d (cm), load factor t and activation α."""

    d: np.ndarray
    t: float
    alpha: float
    F: np.ndarray
    P: np.ndarray
    A: np.ndarray | None
    r: np.ndarray
    force_scale: float
    vol: VolumetricState | None = None
    #: patch pressure (N_p,) N/cm² of the tangent when Newton carries one (``evaluate``'s ``pressure``);
    #: None: the pressure of d
    pressure: np.ndarray | None = None
    #: (Σ f_int², Σ f_pen²) over the system's :attr:`~MechanicalSystem.counted` rows, N²: the parts of
    #: ``force_scale`` that a distributed system sums over its ranks
    norms_sq: tuple | None = None


class MechanicalSystem:
    """Discrete equilibrium equations of a pixel-point model (see the module docstring).

    The stiffness is available in three forms, each built on first use:

    * :meth:`stiffness`: the assembled consistent tangent (BSR), for direct solvers;
    * :meth:`tangent_operator`: the same tangent as a matrix-free operator (:mod:`.tangent`);
    * :meth:`preconditioner_matrix`: a filtered, node-wise positive stand-in, for AMG.

    Parameters
    ----------
    model : Model
    scni : SCNI
    materials : dict tissue code → material
    constraints : Constraints
    A0 : (N, 3, 3, 3, 3) float
        Reference tangent A(F = I) per node, N/cm² (moduli of the stabilisation). Kept as the
        attribute ``A0`` only where a later assembly needs it (a stabilisation with a non-scalar
        modulus; else None: 0.18 GB at 295k nodes); ``shear0`` (N,) keeps its shear moduli
        (:func:`.volumetric.shear_moduli`, the scale of the pressure mass).
    stabilization : StabilizationConfig or None
        NSNI settings (``None``: no stabilisation).
    patch : (3,) int or None
        Patch size (voxels) of the projected volumetric energy (:mod:`.volumetric`); ``None``:
        the nodal volumetric energy of the paper.
    held_patches : {"patch", "own"}
        ``own`` (default, as ``solve.volumetric.held``): nodes held by a boundary condition at
        the node keep a single-node patch; ``patch``: they stay in their ordinary patch.
    """

    def __init__(self, model: Model, scni: SCNI, materials: dict, constraints: Constraints, A0: np.ndarray,
                 stabilization=None, patch=None, held_patches: str = "own"):
        self.model = model
        self.scni = scni
        self.n_nodes = model.n_nodes
        self.constraints = constraints
        self.fiber = np.asarray(model.fiber, float)
        self.A0 = A0
        self.stabilization = stabilization
        self.groups = tissue_groups(model.tissue, materials)
        self.penalty = constraints.stiffness(self.n_nodes)
        self.volumetric = None
        if patch is not None:
            bulk = np.empty(self.n_nodes)
            for _, mat, idx in self.groups:
                bulk[idx] = mat.bulk_modulus
            held = np.zeros(self.n_nodes, bool)
            at_node = np.all(np.isclose(constraints.points, np.asarray(model.X, float)[constraints.node]), axis=1)
            if held_patches == "own":
                held[constraints.node[at_node & constraints.mask.any(axis=1)]] = True
            self.volumetric = PatchProjection(model.ijk, scni.volume, bulk, patch, single=held)
        self.stab = None
        self._stab_local = None
        self._penalty_local = None
        if stabilization is not None:
            C = stabilization_moduli(scni, A0, coefficient=stabilization.coefficient, modulus=stabilization.modulus)
            if ConstantStiffness.is_scalar(C):  # L holds all of it: the face gradients are not needed again (0.3 GB at 74k)
                self.stab, self._stab_local = self._scalar_stabilization(C)
                scni.dpsi_faces = None
            else:
                self.stab = ConstantStiffness(gradient_differences(scni), C)
            del C
        self.shear0 = shear_moduli(A0)
        if self.stab is None or self.stab.scalar:  # no later assembly reads the reference moduli
            self.A0 = None
        self._main = None
        self._support = None
        self._g_positions = None
        self._assemblers = {}
        self._pressure_space = None
        self._owned_rows = None
        self.activation = None  # ActivationRamp (per-node α), or None: α is the scalar of the load ramp
        self.atol = 0.0
        #: the rows (node indices) whose forces make the force scale: None, all; a rank's own nodes
        #: in a distributed system (:mod:`.distributed`), whose other rows are its halo's
        self.counted = None
        #: keywords of the RK shape functions (kernel, order, support_shape, singular), for the nodal values
        self.rk_kw = {}
        #: (N,) bool or None: cells whose deformation gradient is taken as I (a rank's cells beyond the
        #: integration cells its own rows need, where the cut edge can leave F meaningless)
        self.inert = None
        self._psi_nodes = None
        self.timings = {"material_s": 0.0, "assembly_s": 0.0, "n_evaluate": 0, "n_assembly": 0}

    def _scalar_stabilization(self, C: np.ndarray) -> tuple[ConstantStiffness, sp.csr_matrix]:
        """The NSNI stiffness with a scalar modulus (``C`` of :func:`.stabilization.stabilization_moduli`)
        and the same term made from its operators cut near their cells, for the preconditioner's
        stand-in (:func:`.assembly.local_operator`; L itself cut to near pairs has negative
        eigenvalues). Each of the nine operators H[k][J] is made when the sum asks for it, cut, and let
        go: one is held at a time, not all nine (1.7 GB at 295k nodes)."""
        n, c = self.n_nodes, C[:, 0, 0]
        wide = self._wide()
        own = np.arange(n)
        cut = [[], [], []]

        def terms():
            for k in range(3):
                for J in range(3):
                    H = gradient_difference(self.scni, k, J)
                    yield H, c[k * n:(k + 1) * n]
                    cut[k].append(local_operator(H, own, self.model.ijk, LOCAL_RADIUS, wide, LOCAL_TOL))
                    del H

        stab = ConstantStiffness.scalar_from(terms(), n)
        return stab, ConstantStiffness(cut, C).L.matrix

    def stabilization_force(self, d: np.ndarray) -> np.ndarray | None:
        """K_s d (N, 3), N; ``None`` without stabilisation."""
        if self.stab is None:
            return None
        return self.stab.apply(np.asarray(d, float).reshape(-1, 3))

    @property
    def support(self) -> sp.csr_matrix:
        """Cell–node support pattern (N_cells × N): the nodes of every face point's shape functions
        per integration cell (built once)."""
        if self._support is None:
            self._support = support_pattern(face_incidence(self.scni.faces, self.scni.volume), self.scni.psi_faces)
            self.scni.psi_faces = None  # its structure was all that is needed again (0.36 GB at 295k nodes)
        return self._support

    def assembler(self, reach: int | None = None, patches: bool = True) -> Assembler:
        """Block pattern, full or filtered to ``reach`` voxels (built once, kept).

        The full pattern holds the node pairs of the patch terms of a projected volumetric
        energy unless ``patches`` is false (the displacement block of the mixed form).
        """
        patches = bool(patches and reach is None and self.volumetric is not None)
        key = (reach, patches)
        if key not in self._assemblers:
            t0 = time.perf_counter()
            wide = None if reach is None else self._wide()
            if reach is not None and reach // 2 != LOCAL_RADIUS:
                raise ValueError(f"a filtered pattern needs reach {2 * LOCAL_RADIUS} or {2 * LOCAL_RADIUS + 1}, "
                                 f"got {reach}")
            # the preconditioner (reach) takes the volumetric stiffness node by node: no patch pattern
            asm = Assembler(self.support, ijk=self.model.ijk, reach=reach, wide=wide,
                            patches=self.volumetric.structure() if patches else None, local_tol=LOCAL_TOL,
                            pattern=None if reach is None else self._local_pattern(wide))
            self._gradient_positions()
            self._assemblers[key] = asm
            self.timings["pattern_s"] = self.timings.get("pattern_s", 0.0) + time.perf_counter() - t0
        return self._assemblers[key]

    def _wide(self) -> np.ndarray | None:
        """Nodes with enlarged RK supports (they couple further than the nominal reach), or None."""
        sup = np.atleast_2d(self.scni.support)
        if sup.shape[0] != self.n_nodes:
            return None
        return np.any(sup > sup.min(axis=0) * (1 + 1e-9), axis=1)

    def _local_pattern(self, wide: np.ndarray | None) -> sp.csr_matrix | None:
        """The node pairs that the cut factors of a filtered stand-in couple (cells, NSNI and
        penalty, :func:`.assembly.local_rows`): its fills then hold ~125 rather than ~335 non-zeros
        per row before they are pruned (2.4 GB less at 295k nodes). None with a non-scalar NSNI
        modulus, whose cut rows are made in the fill."""
        if self.stab is not None and not self.stab.scalar:
            return None
        S = sp.csr_matrix(self.support)
        S.sort_indices()
        sptr = np.asarray(S.indptr, np.int64)
        kept, counts = [], []
        for c0, c1 in Assembler.blocks_of(sptr):  # by blocks of cells: one block's gradients at a time
            ptr = sptr[c0:c1 + 1] - sptr[c0]
            cut = local_rows_csr(ptr, S.indices[sptr[c0]:sptr[c1]], self._support_gradients((c0, c1)), self.model.ijk,
                                 LOCAL_RADIUS, wide, LOCAL_TOL, own=np.arange(c0, c1))
            k = np.any(cut != 0.0, axis=1)
            kept.append(k)
            counts.append(np.bincount(np.repeat(np.arange(c1 - c0), np.diff(ptr))[k], minlength=c1 - c0))
            del cut
        kept = np.concatenate(kept)
        indptr = np.concatenate([[0], np.cumsum(np.concatenate(counts))])
        Sc = sp.csr_matrix((np.ones(indptr[-1], np.float32), S.indices[kept], indptr), shape=S.shape)
        del kept
        P = (Sc.T @ Sc).tocsr() + sp.identity(self.n_nodes, np.float32, format="csr")
        for M in [*self._local_penalty(), *([self._stab_local] if self._stab_local is not None else [])]:
            P = P + sp.csr_matrix((np.ones(M.nnz, np.float32), M.indices, M.indptr), shape=M.shape)
        P.data[:] = 1.0
        return P

    def _support_gradients(self, cells: np.ndarray | tuple[int, int] | None = None) -> np.ndarray:
        """The smoothed gradients on the support layout (:meth:`.Assembler.on_support`), (nnz(S), 3),
        cm⁻¹: made for each fill from the compact gradients ``scni.G`` and their positions in the
        layout (kept: 4 bytes per entry of G, where the layout's values took 24 per entry of the
        support, about twice as many: 0.5 GB at 295k nodes).

        ``cells``, an array of cells or a range (c0, c1): the entries of those cells' rows of the
        layout only, one row after the other in the order given (a fill by blocks of cells, or of a
        region's cells, holds those, not the whole layout's 1 GB at 295k nodes)."""
        positions = self._gradient_positions()
        if cells is None:
            return scatter_support(self.support.nnz, self.scni.G, positions)
        cells = np.arange(*cells) if isinstance(cells, tuple) else np.asarray(cells, np.int64)
        sptr = np.asarray(self.support.indptr, np.int64)
        count = sptr[cells + 1] - sptr[cells]
        first = np.cumsum(count) - count  # where each cell's row starts in the result
        out = np.zeros((int(count.sum()), 3))
        for k, (M, pos) in enumerate(zip(self.scni.G, positions, strict=True)):
            gptr = np.asarray(M.indptr, np.int64)
            gc = gptr[cells + 1] - gptr[cells]
            which = np.repeat(np.arange(cells.size), gc)
            idx = np.repeat(gptr[cells] - (np.cumsum(gc) - gc), gc) + np.arange(int(gc.sum()))  # the cells' entries of G[k]
            np.add.at(out[:, k], pos[idx] - sptr[cells][which] + first[which], M.data[idx])
        return out

    def _fill_cells(self, asm: Assembler, A: np.ndarray, out: np.ndarray) -> np.ndarray:
        """Add Σ_L V_L B̃_Lᵀ A_L B̃_L to ``out`` on ``asm``'s pattern, by blocks of cells (their gradients
        made per block, :meth:`_support_gradients`)."""
        for cells in asm.cell_blocks():
            asm.fill(self._support_gradients(cells), A, self.scni.volume, out=out, cells=cells)
        return out

    def _gradient_positions(self) -> list[np.ndarray]:
        """Positions of the entries of ``scni.G`` in the support layout (:func:`.assembly.support_positions`),
        made once."""
        if self._g_positions is None:
            S = sp.csr_matrix(self.support)
            S.sort_indices()
            self._g_positions = support_positions(S.indptr, S.indices, S.shape[1], self.scni.G)
        return self._g_positions

    def _local_penalty(self) -> list[sp.csr_matrix]:
        """Penalty stiffness per component from the constraint points' shape functions cut near the
        points' nodes (:func:`.assembly.local_operator`), for filtered patterns (built once)."""
        if self._penalty_local is None:
            c = self.constraints
            psi = local_operator(c.psi, c.node, self.model.ijk, LOCAL_RADIUS, self._wide(), LOCAL_TOL)
            self._penalty_local = shared_by_mask(c.mask, lambda j: (psi.T @ sp.diags(c.beta * c.weight * c.mask[:, j])
                                                                    @ psi).tocsr())
        return self._penalty_local

    def constant_stiffness(self, asm: Assembler) -> np.ndarray:
        """Block data of the constant part of the stiffness, penalty + NSNI, on the pattern of
        ``asm``, N/cm; shape (nnzb, 3, 3). On a filtered pattern it is made of factors cut near
        their cells and points (:func:`.assembly.local_rows`), so it stays positive semi-definite.

        Made anew for every assembly rather than kept with the pattern: with the default NSNI
        modulus it is a merge of the scalar operators (``stab.L`` and the penalty) into the
        pattern, and not keeping it saves a copy of the pattern's data (0.6 GB at 74k nodes).
        """
        out = asm.zeros()
        filtered = asm.reach >= 0
        for j, Kj in enumerate(self._local_penalty() if filtered else self.penalty):
            asm.align_scalar(Kj, j, j, out)
        if self.stab is not None and self.stab.scalar:
            asm.add_identity_blocks(self._stab_local if filtered else self.stab.L.matrix, out)
        elif self.stab is not None:
            stabilization_stiffness(self.scni, asm, self.A0, coefficient=self.stabilization.coefficient,
                                    modulus=self.stabilization.modulus, out=out)
        return out

    def _material_kw(self, code, idx, alpha):
        mat = next(m for c, m, _ in self.groups if c == code)
        # with per-node activation, ``alpha`` is the ramp parameter s of the ActivationRamp
        return group_kw(mat, self.fiber, idx, alpha, self.activation)

    def material_response(self, F: np.ndarray, alpha: float, tangent: bool = True):
        """P (N, 3, 3) and, if ``tangent``, A (N, 3, 3, 3, 3) per node, grouped by material."""
        return material_response(self.groups, self.fiber, F, alpha, self.activation, tangent)

    def evaluate(self, d: np.ndarray, t: float, alpha: float, pressure: np.ndarray | None = None) -> State:
        """Residual r = −(f_int + f_stab + f_pen) at coefficients d; raises SolverError on inversion.

        ``pressure`` (N_p,) N/cm², projected volumetric energy only: the patch pressure of the
        tangent's geometric term (the pressure Newton carries, :meth:`linearised_pressure`) in
        place of K̄_p (θ_p − 1); the residual, energy and stresses keep the pressure of d."""
        t0 = time.perf_counter()
        F = self.scni.deformation_gradient(d)
        if self.inert is not None:
            F[self.inert] = np.eye(3)
        P, A = self.material_response(F, alpha, tangent=True)
        vs = None
        if self.volumetric is not None:
            vs = self.volumetric.state(F)
            A = self.volumetric.tangent(A, vs if pressure is None else self.volumetric.carried(vs, pressure),
                                        overwrite=True)
            P = self.volumetric.stress(P, vs)
        fi = self.scni.internal_force(P)
        fs = self.stabilization_force(d)
        if fs is not None:
            fi = fi + fs
        fp = self.constraints.force(d, t)
        r = -(fi + fp)
        c = self.counted
        sq = (float(np.sum(np.square(fi if c is None else fi[c]))), float(np.sum(np.square(fp if c is None else fp[c]))))
        scale = float(np.sqrt(max(sq)))
        self.timings["material_s"] += time.perf_counter() - t0
        self.timings["n_evaluate"] += 1
        return State(d=d, t=t, alpha=alpha, F=F, P=P, A=A, r=r, force_scale=scale, vol=vs,
                     pressure=None if pressure is None else np.asarray(pressure, float), norms_sq=sq)

    def inner(self, a: np.ndarray, b: np.ndarray) -> float:
        """Σ a·b over all unknowns (Newton's norms and slopes; a distributed system sums its ranks)."""
        return float(np.vdot(a, b))

    def nodal_displacement(self, d: np.ndarray) -> np.ndarray:
        """u(X_I) = Σ_J Ψ_J(X_I) d_J at every node, (N, 3) cm (the RK interpolant at the nodes)."""
        if self._psi_nodes is None:
            from ..rk import shape_functions

            X = np.asarray(self.model.X, float)
            self._psi_nodes = sp.csr_matrix(shape_functions(X, X, self.scni.support, **self.rk_kw))
        return np.asarray(self._psi_nodes @ d)

    def linearised_pressure(self, state: State, dd: np.ndarray) -> np.ndarray:
        """Patch pressure after the update ``dd`` (N, 3) cm from ``state``, linearised:
        K̄_p (θ_p − 1 + g_p · dd), N/cm², (N_p,) — the pressure increment of Newton on the mixed
        (displacement, pressure) form, whose update of d is the condensed one (:mod:`.newton`)."""
        grad = self.scni.deformation_gradient(dd) - np.eye(3)  # ∇̃dd at every node
        vol = self.volumetric
        return vol.kbar * (state.vol.dtheta + vol.Q @ np.einsum("nij,nij->n", state.vol.a, grad))

    @property
    def pressure_weight(self) -> float:
        """w = mean(μ_p V_p) / s over the free patches, N: the force that a unit pressure residual
        θ_p − 1 − p_p/K̄_p stands for in the mixed form (:attr:`.pressure.PressureSpace.weight`)."""
        return self.pressure_space().weight

    def mixed_residual(self, state: State) -> tuple[np.ndarray, np.ndarray | None]:
        """Residuals of the mixed (displacement, pressure) form at d and the pressure ``state`` carries.

        r_u = r − Σ_L V_L B̃_Lᵀ((p_c − p)_{p(L)} a_L), the residual r with the carried pressure p_c
        of the free patches in place of their pressure p = K̄(θ − 1) of d, N, (N, 3); and
        r_p = θ − 1 − p_c/K̄, dimensionless, (N_p,), 0 at held single-node patches (their pressure
        is no unknown). Without a carried pressure: (r, zeros). Eliminating the pressure rows
        gives back r: r = r_u − Gᵀ(V K̄ r_p).
        """
        vol = self.volumetric
        if vol is None or state.vol is None:
            return state.r, None
        if state.pressure is None:
            return state.r, np.zeros(vol.n_patches)
        dp = np.where(vol.held, 0.0, state.pressure - state.vol.pressure)
        r_u = state.r - self.scni.internal_force(dp[vol.patch_of][:, None, None] * state.vol.a)
        return r_u, np.where(vol.held, 0.0, state.vol.dtheta - state.pressure / vol.kbar)

    def _add_patches(self, asm: Assembler, state: State, out: np.ndarray, g: np.ndarray) -> None:
        """Rank-one patch terms Σ_p V_p K̄_p g_p g_pᵀ of the projected volumetric energy (``g``: the
        gradients on the support layout, :meth:`_support_gradients`)."""
        vol = self.volumetric
        if vol is None:
            return
        wv = vol.volume / vol.vp[vol.patch_of]
        v = asm.patch_vectors(g, state.vol.a, wv, vol.patch_of)
        asm.fill_patches(v, vol.vp * vol.kbar, out)

    def held_volumetric(self, state: State, A: np.ndarray, cells: np.ndarray | None = None) -> np.ndarray:
        """A plus the nodal volumetric tangent K_L a_L⊗a_L at the nodes of held single-node patches:
        their patch terms, which stay in the displacement block of the mixed form.

        Parameters
        ----------
        state : State
        A : (N, 3, 3, 3, 3) float
            Tangent moduli per node, N/cm².
        cells : (n,) int, optional
            The nodes whose moduli are wanted (default: all).

        Returns
        -------
        (n, 3, 3, 3, 3) float
            A new array (A is not changed), N/cm².
        """
        vol = self.volumetric
        nodes = np.arange(A.shape[0]) if cells is None else np.asarray(cells)
        out = np.array(A if cells is None else A[nodes], dtype=np.float64)
        held = np.flatnonzero(vol.held[vol.patch_of[nodes]])  # the terms only where they are not zero
        a = state.vol.a[nodes[held]]
        out[held] += vol.bulk[nodes[held], None, None, None, None] * np.einsum("nij,nkl->nijkl", a, a)
        return out

    def stiffness(self, state: State, pressure_free: bool = False) -> sp.bsr_matrix:
        """Consistent tangent K = Σ_L V_L B̃ᵀ A_L B̃ + K_stab + K_pen (BSR, 3N × 3N), N/cm.

        With ``pressure_free`` (projected volumetric energy only): the displacement block K_d of
        the mixed form instead, i.e. without the patch terms of the patches whose pressure is an
        unknown (all but the held single-node ones, :mod:`.linsolve.mixed`).
        """
        pressure_free = pressure_free and state.vol is not None
        asm = self.assembler(None, patches=not pressure_free)
        t0 = time.perf_counter()
        data = self.constant_stiffness(asm)
        g = self._support_gradients()
        if pressure_free:
            asm.fill(g, self.held_volumetric(state, state.A), self.scni.volume, out=data)
        else:
            asm.fill(g, state.A, self.scni.volume, out=data)
            self._add_patches(asm, state, data, g)
        del g
        K = asm.matrix(data)
        self.timings["assembly_s"] += time.perf_counter() - t0
        self.timings["n_assembly"] += 1
        return K

    @property
    def product_form(self) -> ProductForm:
        """The stacked SCNI gradient operators of the matrix-free products (built on first use)."""
        if self._main is None:
            self._main = ProductForm([self.scni.G])
        return self._main

    def tangent_operator(self, state: State) -> MatrixFreeTangent:
        """The consistent tangent of :meth:`stiffness` as a matrix-free operator (3N × 3N), N/cm."""
        vol = None if self.volumetric is None else (self.volumetric, state.vol)
        return MatrixFreeTangent(self.product_form, state.A.reshape(-1, 9, 9), self.scni.volume, stab=self.stab,
                                 penalty=self.penalty, volumetric=vol)

    def displacement_moduli(self, state: State, cells: np.ndarray | None = None) -> np.ndarray:
        """V_L A_L per node (n, 9, 9), N·cm, of the displacement block K_d of the mixed form at the
        nodes ``cells`` (n,) int (default: all): the tangent plus, at the nodes of held single-node
        patches, their volumetric term. A new array, made without a whole-model temporary."""
        nodes = slice(None) if cells is None else np.asarray(cells)
        if self.volumetric is None:
            return self.scni.volume[nodes, None, None] * state.A[nodes].reshape(-1, 9, 9)
        C = self.held_volumetric(state, state.A, cells).reshape(-1, 9, 9)
        C *= self.scni.volume[nodes, None, None]
        return C

    def preconditioner_matrix(self, state: State, reach: int = 2, volumetric: str = "nodal") -> sp.bsr_matrix:
        """Filtered positive definite stand-in of the tangent for preconditioning (BSR, 3N × 3N), N/cm.

        Only blocks between nodes at most ``reach`` voxels apart (2 or 3) are made, each node's
        tangent is replaced by :func:`.tangent.spd_surrogate`, and penalty and NSNI terms are
        included. Every product Bᵀ C B (cells, stabilisation, constraint points) is made from
        its factor B cut to the nodes within one voxel of its cell or point
        (:func:`.assembly.local_rows`), not by leaving out the far node pairs of the product: each
        term stays positive semi-definite, so the stand-in is positive definite wherever the
        tangent is. (Left-out pairs gave 41 negative pivots on the 21k leg at 0.078-cm pixels, and
        FGMRES iterations that grew with the model: the git history of docs/performance.md.)
        docs/linsolve-research.md §2(c) explains the filter. With the
        projected volumetric energy the stand-in carries each node's own volumetric stiffness
        K_L a_L⊗a_L instead of the patch terms, whose node pairs reach beyond the filter (on the
        demo leg CG then needs 473 iterations to 10⁻⁶ against 131 with the nodal energy; filtered
        patch terms took 1,554).

        ``volumetric="held"`` keeps that nodal volumetric stiffness only at the nodes of held
        single-node patches: the displacement block of the mixed form (:mod:`.linsolve.mixed`),
        whose other patch pressures are unknowns of their own.
        """
        asm = self.assembler(reach)
        t0 = time.perf_counter()
        data = self.constant_stiffness(asm)
        A = state.A
        if state.vol is not None and volumetric == "held":
            A = self.held_volumetric(state, A)
        elif state.vol is not None:  # the volumetric stiffness node by node, as the nodal energy has it
            a = state.vol.a
            A = A + self.volumetric.bulk[:, None, None, None, None] * np.einsum("nij,nkl->nijkl", a, a)
        self._fill_cells(asm, spd_surrogate(A), data)
        self.timings["assembly_s"] += time.perf_counter() - t0
        self.timings["n_assembly"] += 1
        return nonzero_blocks(asm.matrix(data))

    # -- what the linear solvers use (linsolve.operator.SystemOperator) ---------------------------

    @property
    def n_dofs(self) -> int:
        """Unknowns of the displacement block, 3N (node-major: dof 3I + i)."""
        return 3 * self.n_nodes

    def near_null_space(self, nodes: np.ndarray | None = None) -> np.ndarray:
        """The six rigid-body modes (3 translations, 3 rotations about the centroid) of ``nodes``
        (default: all), (3n, 6), node-major rows: the near-null space of the tangent for multigrid."""
        from .linsolve.base import rigid_body_modes

        X = np.asarray(self.model.X, float)
        return rigid_body_modes(X if nodes is None else X[nodes])

    def displacement_operator(self, state: State, tangent: MatrixFreeTangent | None = None) -> MatrixFreeTangent:
        """The displacement block K_d of the mixed form as a matrix-free operator (3N × 3N), N/cm:
        the tangent without the patch terms of the patches whose pressure is an unknown (those of
        held single-node patches stay). ``tangent``, the :meth:`tangent_operator` of the same
        state, lends its moduli (no second (N, 9, 9) array). Projected volumetric energy only."""
        full = self.tangent_operator(state) if tangent is None else tangent
        vol = self.volumetric
        return full.with_volumetric((vol.restricted(vol.held), state.vol))

    def owned_rows(self, owned: np.ndarray) -> RowAssembler:
        """The rows of the tangent of the nodes ``owned`` (n,) int, for :meth:`.rows.RowAssembler.rows`
        (CSR 3n × 3N at a state, N/cm; ``pressure_free``: the rows of K_d); its ``cells`` are the
        integration cells those rows need (the owned nodes and their halo). Built once per owned set
        (the last one is kept)."""
        owned = np.asarray(owned, np.int64)
        if self._owned_rows is None or not np.array_equal(self._owned_rows.owned, owned):
            self._owned_rows = RowAssembler(self, owned)
        return self._owned_rows

    def pressure_space(self) -> PressureSpace | None:
        """The patch pressures as unknowns of the mixed form (:class:`.pressure.PressureSpace`);
        None without a projected volumetric energy. Made once."""
        vol = self.volumetric
        if vol is None:
            return None
        if self._pressure_space is None:
            shear = vol.Q @ self.shear0
            free = np.flatnonzero(~vol.held)
            box = np.zeros((vol.n_patches, 3), np.int64)
            box[vol.patch_of] = np.asarray(self.model.ijk) // np.asarray(vol.patch)
            self._pressure_space = PressureSpace(
                n_patches=vol.n_patches, free=free, volume=vol.vp, kbar=vol.kbar, shear=shear,
                weight=pressure_scale(shear[free], vol.vp[free], self.model.spacing), box=box, patch_of=vol.patch_of)
        return self._pressure_space

    def patch_divergence(self, state: State, patches: np.ndarray) -> PatchDivergence:
        """G of the patches ``patches`` (n,) int at ``state`` (n × 3N, 1/cm), matrix-free
        (:class:`.pressure.PatchDivergence`). Projected volumetric energy only."""
        main = self.product_form
        return PatchDivergence(main.B, main.BT, state.vol.a, self.volumetric.Q[patches])

    def stiff_regions(self) -> list[np.ndarray]:
        """Node sets (sorted, may overlap) where the displacement block holds stiff rank-one
        couplings a point smoother cannot reduce: per boundary condition the supports of its
        constraint points, and the gradient supports of held single-node patches
        (:func:`.linsolve.subdomains.constraint_regions`)."""
        from .linsolve.subdomains import constraint_regions

        vol = self.volumetric
        return constraint_regions(self, None if vol is None else vol.held[vol.patch_of])

    def region_solves(self, regions: list[np.ndarray], ijk: np.ndarray, single: bool = False,
                      coupling: str = "auto") -> RegionSolves:
        """Solves of K_d on the node ``regions`` (:class:`.linsolve.subdomains.RegionSolves`:
        ``update(state)`` factorises, ``correct(r, z)`` applies the multiplicative correction);
        ``ijk`` (N, 3) int orders the factorisations; ``single``: single-precision PARDISO factors
        refined in double precision at each solve; ``coupling``: ``components`` (each displacement
        component's diagonal block), ``full`` (the whole block) or ``auto`` (the whole block only
        where a held single-node patch couples the components)."""
        from .linsolve.subdomains import RegionSolves

        return RegionSolves(self, regions, ijk, single=single, coupling=coupling)

    def statistics(self) -> dict:
        """Totals for the results' ``info``: seconds and counts of the material evaluations
        (``material_s``, ``n_evaluate``), assemblies (``assembly_s``, ``n_assembly``) and block
        patterns (``pattern_s``), and the stored entries per row of the patterns built: the
        tangent's (``nnz_per_row``) and the filtered preconditioner stand-in's
        (``preconditioner_nnz_per_row``)."""
        out = {"pattern_s": self.timings.get("pattern_s", 0.0), "assembly_s": self.timings["assembly_s"],
               "n_assembly": self.timings["n_assembly"], "material_s": self.timings["material_s"],
               "n_evaluate": self.timings["n_evaluate"]}
        for (reach, _), asm in self._assemblers.items():
            out["nnz_per_row" if reach is None else "preconditioner_nnz_per_row"] = round(asm.nnz / (3 * self.n_nodes), 1)
        return out

    # -- what the load-step driver reads (a distributed system gathers them to rank 0) -----------

    def step_output(self, state: State) -> dict:
        """The results of a converged state: ``d``, ``u`` (nodal displacements) (N, 3) cm, ``cauchy``
        (N, 6) N/cm² (Voigt), and per reaction name ``reaction`` (3,) N, ``prescribed`` (3,) cm and
        ``gaps`` (:meth:`.boundary.Constraints.gaps`)."""
        from .results import cauchy_voigt

        d, t = state.d, state.t
        u = self.nodal_displacement(d)
        c = self.constraints
        return dict(d=np.array(d, float), u=u, reaction=c.reactions(d, t), prescribed=c.prescribed(t),
                    gaps=c.gaps(d, t, u), cauchy=cauchy_voigt(self.cauchy(state)))

    def constrained_components(self) -> dict[str, np.ndarray]:
        """Constrained components per reaction name, (3,) bool."""
        return self.constraints.constrained_components()

    def ellipticity_minimum(self, state: State, directions: np.ndarray) -> np.ndarray:
        """The material law's smallest acoustic-tensor eigenvalue at every node over ``directions``
        (:func:`.ellipticity.acoustic_minimum`), (N,) N/cm²."""
        from .ellipticity import acoustic_minimum

        _, A = self.material_response(state.F, state.alpha)
        return acoustic_minimum(state.F, A, directions)

    def release_moduli(self, state: State) -> None:
        """Let go of ``state``'s moduli A (N, 3, 3, 3, 3) once the solve with its tangent is done: the
        line search evaluates its trial state without them beside it (0.18 GB at 295k nodes). The
        state keeps d, F, P, the residual and the volumetric state."""
        state.A = None

    def gather(self, x: np.ndarray) -> np.ndarray:
        """The whole model's array of per-node values ``x`` (a distributed system's rank 0 gathers them)."""
        return x

    def owned_of(self, x: np.ndarray) -> np.ndarray:
        """The rows of a whole-model array that this system's unknowns are (all of them)."""
        return x

    def memory_for_checkpoint(self, memory):
        """A solver memory as a checkpoint keeps it (a distributed system gathers it)."""
        return memory

    def memory_from_checkpoint(self, memory):
        """A checkpoint's solver memory as this system's solver takes it."""
        return memory

    def strain_energy(self, F: np.ndarray, alpha: float) -> float:
        """Σ_L V_L W(F_L), N·cm."""
        W = np.empty(F.shape[0])
        for code, mat, idx in self.groups:
            W[idx] = mat.energy(F[idx], **self._material_kw(code, idx, alpha))
        return float(np.dot(self.scni.volume, W))

    def energy(self, state: State) -> float:
        """Total potential Π = Σ V W + ½ dᵀ K_stab d + Π_pen, N·cm (volumetric part per patch if projected)."""
        e = self.strain_energy(state.F, state.alpha) + self.constraints.energy(state.d, state.t)
        if state.vol is not None:
            e += self.volumetric.energy_correction(state.vol.J, state.vol.dtheta)
        fs = self.stabilization_force(state.d)
        if fs is not None:
            e += 0.5 * float(np.vdot(state.d, fs))
        return e

    def cauchy(self, state: State) -> np.ndarray:
        """Cauchy stress at the nodes, (N, 3, 3), N/cm²."""
        s = np.empty((self.n_nodes, 3, 3))
        for code, mat, idx in self.groups:
            s[idx] = mat.cauchy(state.F[idx], **self._material_kw(code, idx, state.alpha))
        if state.vol is not None:  # σ̃ = σ + shift I (a_L Fᵀ / J = I)
            s += state.vol.shift[:, None, None] * np.eye(3)
        return s


def check_model(model: Model) -> None:
    """Validate the arrays of a model before solving (InputError naming what is wrong)."""
    n = model.n_nodes
    if n == 0:
        raise InputError("model has no nodes")
    for name, arr, shape in (("X", model.X, (n, 3)), ("ijk", model.ijk, (n, 3)), ("tissue", model.tissue, (n,)),
                             ("fiber", model.fiber, (n, 3))):
        if np.shape(arr) != shape:
            raise InputError(f"model /nodes/{name} has shape {np.shape(arr)}, expected {shape}")
    if not np.all(np.isfinite(model.X)):
        raise InputError("model /nodes/X holds non-finite coordinates")
    h = np.asarray(model.spacing, float)
    if h.shape != (3,) or not np.all(h > 0):
        raise InputError(f"model /grid/spacing must be 3 positive numbers (cm), got {model.spacing}")
    bad = ~np.isin(model.tissue, NODE_TISSUES)
    if bad.any():
        raise InputError(f"model /nodes/tissue: {int(bad.sum())} nodes have codes outside {NODE_TISSUES} "
                         f"({', '.join(TISSUE_NAMES[c] for c in NODE_TISSUES)})")
    expect = np.asarray(model.origin, float) + np.asarray(model.ijk, float) * h
    if not np.allclose(expect, model.X, atol=1e-6 * float(h.min())):
        raise InputError("model /nodes/X is not origin + ijk * spacing: the cells of nodal integration need a "
                         "grid-aligned model (docs/architecture.md, model frame)")
    mus = model.tissue == MUSCLE
    if mus.any():
        norm = np.linalg.norm(model.fiber[mus], axis=1)
        if not np.all(np.abs(norm - 1.0) < 1e-3):
            raise InputError(f"model /nodes/fiber: {int(np.sum(np.abs(norm - 1.0) >= 1e-3))} muscle nodes have no unit "
                             "fibre direction")


def build_system(model: Model, cfg: SolveConfig, *, supports: np.ndarray | None = None, beta: float | None = None,
                 n_total: int | None = None, singular: str = "raise") -> tuple[MechanicalSystem, dict]:
    """Assemble everything that does not change during the solve.

    ``supports`` (N, 3) cm, ``beta`` N/cm³, ``n_total`` and ``singular`` are given by a distributed
    build (:mod:`.distributed`), whose ``model`` is one rank's part: the RK supports and penalty
    number of the whole model, its node count (the residual floor), and ``"empty"`` for the points
    at the part's cut edge whose moment matrices are singular there (:func:`pixmuscle.rk.shape_functions`);
    by default they come from ``model`` and a singular point is an error.

    Returns
    -------
    system : MechanicalSystem
    info : dict
        β, support, pattern size and set-up timings.
    """
    check_model(model)
    info = {}
    t0 = time.perf_counter()
    stab = cfg.stabilization.method != "none" and cfg.stabilization.coefficient > 0
    rk_kw = dict(kernel=cfg.support.kernel, order=cfg.support.order, support_shape=cfg.support.shape, singular=singular)
    bcs = list(cfg.boundary_conditions)
    scni, info["supports_enlarged"] = model_scni(model, cfg, face_gradients=stab, supports=supports, singular=singular)
    sup = scni.support
    info["scni_s"] = time.perf_counter() - t0
    materials = solve_materials(cfg)
    A0 = reference_moduli(model.tissue, model.fiber, materials)
    t3 = time.perf_counter()
    if beta is None:
        beta = cfg.penalty.beta if cfg.penalty.beta is not None else penalty_number(A0, model.spacing, cfg.penalty.factor)
    constraints = build_constraints(model, bcs, scni.faces, sup, beta, at=cfg.penalty.at, **rk_kw)
    info["penalty_s"] = time.perf_counter() - t3
    t2 = time.perf_counter()
    patch = cfg.volumetric.patch if cfg.volumetric.method == "projected" else None
    system = MechanicalSystem(model, scni, materials, constraints, A0, cfg.stabilization if stab else None, patch=patch,
                              held_patches=cfg.volumetric.held)
    info["stabilization_s"] = time.perf_counter() - t2
    # absolute residual floor (N): round-off level of the penalty forces β w (u − g)
    system.atol = 1e-15 * beta * float(np.prod(model.spacing)) * max(1, model.n_nodes if n_total is None else n_total) ** 0.5
    system.rk_kw = rk_kw
    nominal = support_radius(model.spacing, cfg.support.a_over_h)
    info.update(beta=beta, support_cm=nominal.tolist(), n_nodes=model.n_nodes,
                n_constraint_points=int(constraints.points.shape[0]), build_s=time.perf_counter() - t0)
    if not constraints.points.shape[0] and n_total is None:
        _LOG.warning("no boundary condition constrains any node: the stiffness is singular")
    return system, info


def reference_moduli(tissue: np.ndarray, fiber: np.ndarray, materials: dict) -> np.ndarray:
    """A(F = I) at every node, (N, 3, 3, 3, 3) N/cm²: each node's material at rest (α = 0).

    Parameters
    ----------
    tissue : (N,) int
        Tissue code per node.
    fiber : (N, 3) float
        Unit fibre direction per node.
    materials : dict
        Tissue code → material (:func:`solve_materials`).
    """
    tissue = np.asarray(tissue)
    A0 = np.empty((tissue.size, 3, 3, 3, 3))
    for c in NODE_TISSUES:
        idx = np.flatnonzero(tissue == c)
        if idx.size:
            ident = np.broadcast_to(np.eye(3), (idx.size, 3, 3)).copy()
            A0[idx] = materials[c].stress_tangent(ident, **material_kw(materials[c], np.asarray(fiber)[idx], 0.0))[1]
    return A0


def model_scni(model: Model, cfg: SolveConfig, *, face_gradients: bool = False,
               supports: np.ndarray | None = None, singular: str = "raise") -> tuple[SCNI, int]:
    """The SCNI operators of a solve of ``model`` with ``cfg`` (the supports of :func:`node_supports`,
    or ``supports`` (N, 3) cm; end faces held at their vertices by the vertex rule of ``penalty.at``).

    Returns
    -------
    scni : SCNI
        ``scni.deformation_gradient(d)`` is the solve's F at every node.
    n_enlarged : int
        Nodes whose support was enlarged.
    """
    if supports is None:
        sup, n_enlarged = node_supports(model, cfg)
    else:
        sup, n_enlarged = np.asarray(supports, float), 0
    faces = cell_faces(model.X, model.ijk, np.asarray(model.spacing, float))
    vf = vertex_rule_faces(model, list(cfg.boundary_conditions), faces, at=cfg.penalty.at)
    scni = build_scni(model.X, model.ijk, model.spacing, sup, face_gradients=face_gradients, faces=faces,
                      vertex_faces=vf, kernel=cfg.support.kernel, order=cfg.support.order,
                      support_shape=cfg.support.shape, singular=singular)
    return scni, n_enlarged


def solve_materials(cfg: SolveConfig) -> dict:
    """Tissue code → material of a solve (the volumetric part left to the patches when projected)."""
    return make_materials(cfg.materials, projected=cfg.volumetric.method == "projected")


def node_supports(model: Model, cfg: SolveConfig) -> tuple[np.ndarray, int]:
    """Per-node RK support radii (N, 3), cm: a = (a/h)·spacing, enlarged only where needed.

    Thin image features (a one-voxel strand, a diagonal chain left by coarsening) leave some
    face centres or nodes (when end sets are held at their end-face vertices, the default, also cell
    corners) with a singular moment matrix under the nominal support; the supports of the nodes
    around them are enlarged locally (:func:`pixmuscle.rk.covering_supports`) and the count is
    logged. Everywhere else the support is exactly the nominal one.

    Returns
    -------
    support : (N, 3) float
    n_enlarged : int
    """
    return rk_supports(model, cfg.support, corners=end_rule(cfg.penalty.at) == "vertices")


def rk_supports(model: Model, support: SupportConfig, *, corners: bool = False) -> tuple[np.ndarray, int]:
    """:func:`node_supports` for the ``solve.support`` section alone (what the report needs to
    evaluate a solve's RK field again: same inputs, same supports).

    Covered: the SCNI face centres and the nodes; with ``corners`` (``penalty.at`` ``auto`` or
    ``vertices``, whose penalty points and SCNI end-face points are end-face vertices) also every
    cell corner, which enlarges supports beside thin features further (demo: up to 1.56× instead of
    1.25× nominal); ``penalty.at: centres`` or ``nodes`` need only the first two."""
    from ..rk import covering_supports

    nominal = support_radius(model.spacing, support.a_over_h)
    X = np.asarray(model.X, float)
    faces = cell_faces(X, model.ijk, np.asarray(model.spacing, float))
    points = [faces.centre, model.X] + ([cell_corners(X, model.spacing)] if corners else [])
    return covering_supports(model.X, points, nominal, kernel=support.kernel, order=support.order,
                             support_shape=support.shape)

r"""Solves on the stiff regions of the displacement block: a correction after the V-cycle.

The penalty rows of the boundary conditions, β Ψ(x_c)ᵀ w_c Ψ(x_c) with β the stiffness of a
cell's bulk, couple every node in the support of a constraint point x_c; the single-node patches
of nodes held at the node (``volumetric.held: own``) add their K-scaled volumetric stiffness the
same way. A point smoother cannot reduce these rank-one couplings, and the AMG V-cycle on K_d loses
most of its strength to them (docs/performance.md: CG on K_d of the 1.5k leg needs 72 iterations
with the default penalty number, 12 with one a hundred times smaller). They live in thin regions — the node layers
within a support radius of the end faces and of the bone surfaces — where K_d can be factorised
exactly. The preconditioner of K_d is then

    z ← M_A r,    then for each region i:  z ← z + R_i K_i⁻¹ R_iᵀ (r − K_d z)

(one V-cycle, then solves on the regions R_i for the residual it leaves there: a
multiplicative Schwarz step with one subdomain per region). It is not symmetric, so it serves
FGMRES (:mod:`.mixed`).

K_i need not be the whole region block. The penalty rows act on each displacement component on
its own (a condition fixes x, y or z), so K_i = blockdiag(K_xx, K_yy, K_zz), the components'
diagonal blocks of the region's rows, still takes them exactly, and leaves the couplings between
components, which are no stiffer there than anywhere else, to the V-cycle. Its factors are those
of the nodes' graph three times over instead of the graph of all 3n unknowns: about a third of the
entries (``coupling="components"``, :class:`.factorization.ComponentFactors`). Where a held
single-node patch adds its K-scaled volumetric term, which couples the components, the whole
block is factorised (``coupling="auto"``, the default, decides per region).

References
----------
B. Smith, P. Bjørstad, W. Gropp, *Domain Decomposition: Parallel Multilevel Methods for Elliptic
Partial Differential Equations*, Cambridge University Press, 1996, ch. 1 (multiplicative Schwarz).
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
import scipy.sparse as sp

from ..assembly import strong_entries
from ..rows import RowAssembler
from ..tangent import RowProduct, RowSubset
from .factorization import ENGINES, ComponentFactors, engine_name

#: what a region solve factorises: each displacement component's block, or the whole block, or
#: (auto) the whole block where held single-node patches couple the components, else each one's
COUPLINGS = ("auto", "components", "full")

#: a node enters the region of a constraint point where its shape function there is at least this
#: fraction of the point's largest; 0: every node of the point's support
REGION_TOL = 0.0


def constraint_regions(system, held: np.ndarray | None = None, tol: float = REGION_TOL) -> list[np.ndarray]:
    """Node sets of the stiff regions: per boundary condition, the nodes whose shape functions at
    its constraint points reach ``tol`` of the point's largest (|Ψ_J(x_c)| ≥ tol · max_K |Ψ_K(x_c)|),
    plus, for held single-node patches, one region of the nodes in their smoothed-gradient supports.

    A face vertex lies between voxels: its shape functions reach ~30 nodes, the far ones with a few
    thousandths of the point's largest value. Their penalty couplings β Ψ_I Ψ_J are still about as
    stiff as the tissue, so the region takes them all by default. On the 74k leg, first Newton
    system (FGMRES to 10⁻⁶ on the mixed residual): every node (the default), 7,172 in the bone
    region, 49 iterations; 10⁻³, 5,602 nodes, 49; 5·10⁻³, 53; 2·10⁻², 4,514 nodes, 53. On the
    295k model the bone region has 15,259, 11,061 and 9,002 nodes, and its whole sweep took
    29.4 FGMRES iterations per Newton system with every node against 33.4 with 10⁻³ (measured
    with the stand-in whose cut rows kept only their sums; the git history of docs/performance.md).

    Parameters
    ----------
    system : MechanicalSystem
    held : (N,) bool, optional
        Nodes whose single-node patch keeps its volumetric term in K_d.
    tol : float
        Smallest |Ψ| relative to its point's largest that brings a node into the region.

    Returns
    -------
    list of (n_i,) int
        Sorted node indices (regions may overlap).
    """
    cons = system.constraints
    psi = cons.psi.tocsr()
    point = np.repeat(np.arange(psi.shape[0]), np.diff(psi.indptr))
    strong = strong_entries(point, np.abs(psi.data), psi.shape[0], tol)
    sets = []
    for g in range(len(cons.names)):
        on = (cons.group == g) & cons.mask.any(axis=1)
        if on.any():
            sets.append(np.unique(psi.indices[strong & on[point]]))
    if held is not None and np.any(held):
        sets.append(held_reach(system, held))
    return [np.asarray(s, np.int64) for s in sets]


def held_reach(system, held: np.ndarray) -> np.ndarray:
    """The nodes in the smoothed-gradient supports of the ``held`` (N,) bool nodes, sorted (n,) int:
    where the K-scaled volumetric terms of their single-node patches reach."""
    return np.unique(np.concatenate([sp.csr_matrix(Gj)[np.flatnonzero(held)].indices for Gj in system.scni.G]))


class RegionSolves:
    """Factorisations of K_d restricted to node regions (whole blocks or each component's), and the
    correction after a V-cycle.

    Each region keeps the factors of its diagonal block K_RR (assembled on a pattern of that block
    alone, :class:`.rows.RowAssembler` with ``square``) and applies its rows of K_d matrix-free
    (:class:`~..tangent.RowProduct` over the cells around the region, the NSNI rows, the penalty
    rows), so the region rows themselves (78 M non-zeros, 0.94 GB on the 74k leg) are never stored.
    The NSNI, penalty and gradient rows are products with the system's own operators
    (:class:`~..tangent.RowSubset`), and the block's assembler lives only while :meth:`update`
    factorises (the factors keep what they need of its pattern): on the 21k leg the regions held
    0.30 GB before, 0.17 GB so (the factors are most of it).

    Parameters
    ----------
    system : MechanicalSystem
    regions : list of (n_i,) int
        Sorted node sets (they may overlap: the corrections are applied one after the other).
    ijk : (N, 3) int
        Voxel indices (the nested-dissection order of SuperLU).
    engine : str
        ``auto`` (PARDISO when MKL is installed, else SuperLU), ``pardiso`` or ``superlu``.
    single : bool
        With PARDISO: single-precision factors (PARDISO holds 0.32 GB instead of 0.44 on the 21k leg),
        each solve refined in double precision (:class:`~..pardiso.PardisoLDLT`); SuperLU ignores it.
    coupling : {"auto", "components", "full"}
        What is factorised on a region: ``components``, each displacement component's diagonal
        block K_xx, K_yy, K_zz on its own (:class:`.factorization.ComponentFactors`), the
        couplings between components left to the V-cycle; ``full``, the whole block; ``auto``,
        the whole block on a region that reaches the gradient support of a held single-node
        patch (its K-scaled volumetric term couples the components), each component's elsewhere.
        The penalty rows are per component and so are solved exactly by all three.
    """

    def __init__(self, system, regions, ijk, engine: str = "auto", single: bool = False,
                 coupling: str = "auto"):
        if coupling not in COUPLINGS:
            raise ValueError(f"region coupling must be one of {COUPLINGS}, got {coupling!r}")
        self.system = system
        self.parts = []
        name = engine_name(engine)
        extra = {"single": single} if name == "pardiso" else {}
        coupled = _volumetric_reach(system) if coupling == "auto" else None
        for nodes in regions:
            dofs = (3 * nodes[:, None] + np.arange(3)).ravel()
            engine_of = functools.partial(ENGINES[name], ijk=np.asarray(ijk)[nodes], width=(4, 4, 4), **extra)
            whole = coupling == "full" or (coupled is not None and bool(coupled[nodes].any()))
            factor = engine_of() if whole else ComponentFactors(engine_of)
            stab = system.stab.rows(nodes) if system.stab is not None else None
            pen = [RowSubset(P, nodes) for P in system.penalty]
            self.parts.append(_Region(nodes, dofs, None, factor, RowProduct(system.product_form, nodes), stab, pen))

    def update(self, state) -> None:
        """Factorise the regions' diagonal blocks of K_d at ``state`` and keep the moduli of their rows.

        Each block is assembled on a pattern made for it here; the pattern is let go once the block
        is filled, and the block once the engine has taken what it factorises (PARDISO: the upper
        triangle's values), so neither is held through the numerical factorisation."""
        for part in self.parts:
            part.C = self.system.displacement_moduli(state, part.rows.cells)
            part.factor.factorize(lambda p=part: _region_block(self.system, p, state))

    def release(self) -> None:
        """Drop the moduli kept for the rows and the numerical factors until the next :meth:`update`
        (a rebuild of the preconditioner lets the old factors go before it makes the new ones)."""
        for part in self.parts:
            part.C = None
            part.factor.release()

    @property
    def n_nodes(self) -> int:
        return int(sum(p.nodes.size for p in self.parts))

    def correct(self, r: np.ndarray, z: np.ndarray) -> np.ndarray:
        """z ← z + R_i K_i⁻¹ R_iᵀ (r − K_d z) for each region in turn (the region's rows of K_d only)."""
        out = z.copy()
        for part in self.parts:
            out[part.dofs] += part.factor.solve(r[part.dofs] - part.apply(out.reshape(-1, 3)).ravel())
        return out


def _volumetric_reach(system) -> np.ndarray | None:
    """Nodes (N,) bool in the gradient supports of the held single-node patches, whose K-scaled
    volumetric terms stay in K_d and couple the displacement components; None without any."""
    vol = getattr(system, "volumetric", None)
    if vol is None or not np.any(vol.held):
        return None
    out = np.zeros(vol.patch_of.shape[0], bool)
    out[held_reach(system, vol.held[vol.patch_of])] = True
    return out


def _region_block(system, part, state):
    """The diagonal block of K_d on a region (BSR, :meth:`.rows.RowAssembler.block`), assembled on the
    region's kept pattern or on one made for it and dropped on return."""
    asm = part.asm if part.asm is not None else RowAssembler(system, part.nodes, square=True)
    return asm.block(state, pressure_free=True)


@dataclasses.dataclass(eq=False)
class _Region:
    """One region: nodes, dofs, block assembler (None: made at each factorisation), factors, and its
    rows of K_d as products."""

    nodes: np.ndarray
    dofs: np.ndarray
    asm: RowAssembler | None
    factor: object
    rows: RowProduct
    stab: object
    pen: list
    C: np.ndarray | None = None

    def apply(self, Z: np.ndarray) -> np.ndarray:
        """(K_d Z)_R, (n, 3), for nodal values Z (N, 3)."""
        y = self.rows.apply(self.C, Z)
        if self.stab is not None:
            y += self.stab(Z)
        for j, P in enumerate(self.pen):
            y[:, j] += P @ Z[:, j]
        return y


class CorrectedVCycle:
    """M r = V-cycle, then :meth:`RegionSolves.correct`."""

    def __init__(self, M, regions: RegionSolves):
        self.M, self.regions = M, regions

    def __matmul__(self, r):
        return self.regions.correct(r, self.M @ r)

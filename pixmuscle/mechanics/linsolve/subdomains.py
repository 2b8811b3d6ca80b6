r"""Exact solves on the stiff regions of the displacement block: a correction after the V-cycle.

The penalty rows of the boundary conditions, β Ψ(x_c)ᵀ w_c Ψ(x_c) with β the stiffness of a
cell's bulk, couple every node in the support of a constraint point x_c; the single-node patches
of nodes held at the node (``volumetric.held: own``) add their K-scaled volumetric stiffness the
same way. A point smoother cannot reduce these rank-one couplings, and the AMG V-cycle on K_d loses
most of its strength to them (docs/performance.md: CG on K_d of the 1.5k leg needs 72 iterations
with the default penalty number, 12 with one a hundred times smaller). They live in thin regions — the node layers
within a support radius of the end faces and of the bone surfaces — where K_d can be factorised
exactly. The preconditioner of K_d is then

    z ← M_A r,    then for each region i:  z ← z + R_i K_i⁻¹ R_iᵀ (r − K_d z)

(one V-cycle, then exact solves on the regions R_i for the residual it leaves there: a
multiplicative Schwarz step with one subdomain per region). It is not symmetric, so it serves
FGMRES (:mod:`.mixed`).

References
----------
B. Smith, P. Bjørstad, W. Gropp, *Domain Decomposition: Parallel Multilevel Methods for Elliptic
Partial Differential Equations*, Cambridge University Press, 1996, ch. 1 (multiplicative Schwarz).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ..threaded import ThreadedCSR
from .factorization import ENGINES, engine_name
from .rows import RowAssembler


def constraint_regions(system, held: np.ndarray | None = None) -> list[np.ndarray]:
    """Node sets of the stiff regions: the nodes in the supports of each boundary condition's
    constraint points (one region per condition), plus, for held single-node patches, one region
    of the nodes in their smoothed-gradient supports.

    Parameters
    ----------
    system : MechanicalSystem
    held : (N,) bool, optional
        Nodes whose single-node patch keeps its volumetric term in K_d.

    Returns
    -------
    list of (n_i,) int
        Sorted node indices (regions may overlap).
    """
    cons = system.constraints
    psi = cons.psi.tocsr()
    sets = []
    for g in range(len(cons.names)):
        pts = np.flatnonzero((cons.group == g) & cons.mask.any(axis=1))
        if pts.size:
            sets.append(np.unique(psi[pts].indices))
    if held is not None and np.any(held):
        sets.append(np.unique(np.concatenate([sp.csr_matrix(Gj)[np.flatnonzero(held)].indices for Gj in system.scni.G])))
    return [np.asarray(s, np.int64) for s in sets]


class RegionSolves:
    """Exact factorisations of K_d restricted to node regions, and the correction after a V-cycle.

    Parameters
    ----------
    system : MechanicalSystem
    regions : list of (n_i,) int
        Node sets (they may overlap: the corrections are applied one after the other).
    ijk : (N, 3) int
        Voxel indices (the nested-dissection order of SuperLU).
    engine : str
        ``auto`` (PARDISO when MKL is installed, else SuperLU), ``pardiso`` or ``superlu``.
    """

    def __init__(self, system, regions, ijk, engine: str = "auto"):
        self.parts = []
        for nodes in regions:
            dofs = (3 * nodes[:, None] + np.arange(3)).ravel()
            asm = RowAssembler(system, nodes)
            factor = ENGINES[engine_name(engine)](ijk=np.asarray(ijk)[nodes], width=(4, 4, 4))
            self.parts.append([nodes, dofs, asm, factor, None])

    def update(self, state) -> None:
        """Assemble the region rows of K_d at ``state`` and factorise their diagonal blocks."""
        for part in self.parts:
            _, dofs, asm, factor, _ = part
            part[4] = None  # the old rows go before the new ones are assembled
            rows = asm.rows(state, pressure_free=True)
            part[4] = ThreadedCSR(rows)
            factor.factorize(rows[:, dofs])

    def release(self) -> None:
        """Drop the region rows until the next :meth:`update` (a rebuild frees them before the
        multigrid's set-up, whose transient copies of the stand-in then do not add to them)."""
        for part in self.parts:
            part[4] = None

    @property
    def n_nodes(self) -> int:
        return int(sum(p[0].size for p in self.parts))

    def correct(self, r: np.ndarray, z: np.ndarray) -> np.ndarray:
        """z ← z + R_i K_i⁻¹ R_iᵀ (r − K_d z) for each region in turn (region rows of K_d only)."""
        out = z.copy()
        for _, dofs, _, factor, rows in self.parts:
            out[dofs] += factor.solve(r[dofs] - rows @ out)
        return out


class CorrectedVCycle:
    """M r = V-cycle, then :meth:`RegionSolves.correct`."""

    def __init__(self, M, regions: RegionSolves):
        self.M, self.regions = M, regions

    def __matmul__(self, r):
        return self.regions.correct(r, self.M @ r)

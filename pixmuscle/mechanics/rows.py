"""Rows of the consistent tangent for a subset of the nodes (the rows one MPI rank owns).

Every row of K belongs to one node I and collects the cells L whose support holds I
(K = Σ_L V_L B̃_Lᵀ A_L B̃_L + K_stab + K_pen, plus the patch terms of the projected volumetric
energy). The rows of a set of *owned* nodes therefore need only the cells that touch an owned
node (and, with the projected energy, every cell of the patches among them): the owned nodes plus
a halo of about one support radius. :class:`RowAssembler` builds the block pattern of the owned
rows with :class:`~pixmuscle.mechanics.assembly.Assembler` on the restricted cell–node support
(``rows``: the halo rows are never formed, so the memory is that of the owned rows) and fills it
with the same kernels as the whole tangent. The system hands them to the solvers
(:meth:`~pixmuscle.mechanics.system.MechanicalSystem.owned_rows`).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .assembly import Assembler
from .stabilization import gradient_differences, second_moments, stabilization_modulus


class RowAssembler:
    """Tangent rows of the owned nodes of a :class:`~pixmuscle.mechanics.system.MechanicalSystem`.

    Parameters
    ----------
    system : MechanicalSystem
    owned : (n,) int
        Node indices whose rows are assembled.
    square : bool
        Only the diagonal block of the owned nodes (:meth:`block`; ``owned`` sorted), not their
        whole rows: the pattern and the fill leave out every other column.

    Attributes
    ----------
    cells : (n_c,) int
        Integration cells (= nodes) that enter the owned rows.
    """

    def __init__(self, system, owned: np.ndarray, square: bool = False):
        scni = system.scni
        self.owned = np.asarray(owned, np.int64)
        S = system.support
        touch = np.asarray(S[:, self.owned].sum(axis=1)).ravel() > 0
        vol = system.volumetric
        patches = None
        if vol is not None:  # whole patches: the patch vector g_p needs all of its cells
            near = np.unique(vol.patch_of[touch])
            touch |= np.isin(vol.patch_of, near)
        self.cells = np.flatnonzero(touch)
        Sc = S[self.cells].tocsr()
        if vol is not None:
            self.patches, local_patch = np.unique(vol.patch_of[self.cells], return_inverse=True)
            self.local_patch = local_patch.ravel().astype(np.int64)
            patches = sp.csr_matrix((np.ones(self.cells.size), (self.local_patch, np.arange(self.cells.size))),
                                    shape=(self.patches.size, self.cells.size))
        if square and np.any(np.diff(self.owned) <= 0):
            raise ValueError("a square RowAssembler needs sorted, distinct owned nodes")
        self.square = square
        self.asm = Assembler(Sc, patches=patches, rows=self.owned, square=square)  # the owned block rows only
        # the cells' gradients on their rows of the system's support layout are made at each fill
        # (:meth:`gradients`), not kept
        self._stab = None  # NSNI: the rows of the scalar operator, or (its gradient differences, moduli) on this pattern
        if system.stab is not None and system.stab.scalar:
            self._stab = system.stab.L.rows_matrix(self.owned)  # the owned rows only
        elif system.stab is not None:
            st = system.stabilization
            As = stabilization_modulus(system.A0, st.modulus)[self.cells]
            H = gradient_differences(scni)
            M = second_moments(scni.volume, scni.spacing)[self.cells]
            self._stab = [(self.asm.on_support([Hk[self.cells] for Hk in H[k]]), As, st.coefficient * M[:, k])
                          for k in range(3)]
        self.volume = np.asarray(scni.volume, float)[self.cells]
        self.system = system
        self._rows = (3 * self.owned[:, None] + np.arange(3)).ravel()

    def rows(self, state, pressure_free: bool = False) -> sp.csr_matrix:
        """The owned rows of the tangent at ``state``: CSR (3n × 3N), rows in the order of ``owned``, N/cm.

        With ``pressure_free`` (projected volumetric energy): the rows of the displacement block K_d
        of the mixed form instead (:meth:`~pixmuscle.mechanics.system.MechanicalSystem.stiffness`).
        """
        return self.asm.matrix(self._data(state, pressure_free)).tocsr()[self._rows]

    def block(self, state, pressure_free: bool = False) -> sp.bsr_matrix:
        """The diagonal block of the owned nodes (``square``): BSR (3n × 3n, 3 × 3 blocks), dofs
        3m + i of the m-th owned node, N/cm; ``pressure_free`` as :meth:`rows`. BSR as the fill
        makes it (PARDISO's upper triangle is gathered from it; no CSR copy)."""
        if not self.square:
            raise ValueError("RowAssembler.block needs square=True")
        asm = self.asm
        local = np.full(asm.n_nodes, -1, np.int64)
        local[self.owned] = np.arange(self.owned.size)
        counts = np.diff(asm.indptr)[self.owned]  # the other block rows are empty
        indptr = np.concatenate([[0], np.cumsum(counts)])
        n = 3 * self.owned.size
        return sp.bsr_matrix((self._data(state, pressure_free), local[asm.indices], indptr), shape=(n, n))

    def gradients(self) -> np.ndarray:
        """Smoothed gradients of :attr:`cells` on this pattern's support layout, (nnz, 3), cm⁻¹: the
        system's (:meth:`~pixmuscle.mechanics.solve.MechanicalSystem._support_gradients`) at the
        cells' entries."""
        return self.system._support_gradients(self.cells)

    def _constant(self) -> np.ndarray:
        """Block data of the penalty and NSNI rows (made for each assembly, not kept)."""
        data = self.asm.zeros()
        for j, Kj in enumerate(self.system.penalty):  # the owned rows of the penalty stiffness per component
            Kr = sp.csr_matrix(Kj)[self.owned].tocoo()
            Kr = sp.coo_matrix((Kr.data, (self.owned[Kr.row], Kr.col)), shape=Kj.shape)
            self.asm.align_scalar(Kr, j, j, data)
        if isinstance(self._stab, sp.csr_matrix):
            self.asm.add_identity_blocks(self._stab, data)
        elif self._stab is not None:
            for gk, As, w in self._stab:
                self.asm.fill(gk, As, w, out=data)
        return data

    def _data(self, state, pressure_free: bool) -> np.ndarray:
        data = self._constant()
        vol = self.system.volumetric
        pressure_free = pressure_free and vol is not None
        A = self.system.held_volumetric(state, state.A, self.cells) if pressure_free else state.A[self.cells]
        g = self.gradients()
        self.asm.fill(g, A, self.volume, out=data)
        if vol is not None and not pressure_free:
            wv = (vol.volume / vol.vp[vol.patch_of])[self.cells]
            v = self.asm.patch_vectors(g, state.vol.a[self.cells], wv, self.local_patch)
            self.asm.fill_patches(v, (vol.vp * vol.kbar)[self.patches], data)
        return data

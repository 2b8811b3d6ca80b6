"""Where a rank's nodes and pressure patches sit in the global numbering, and how ranks exchange them.

A :class:`Layout` holds, for one rank, the positions of its own nodes among the nodes it holds
(own plus halo, in ascending model order), the global index of every node it holds in the
numbering of the distributed vectors (PETSc order: rank 0's nodes first, each rank's in model
order), and the same for the pressure patches of the mixed form. Its exchanges are PETSc vector
scatters (halo values from their owners) and mpi4py reductions and gathers (norms, forces, the
results for rank 0). On one rank without MPI the layout is the identity (:meth:`Layout.single`).
"""

from __future__ import annotations

import numpy as np

from ...parallel import import_petsc


class Layout:
    """One rank's share of the nodes and patches, and the exchanges between ranks (module docstring).

    Parameters
    ----------
    comm : petsc4py Comm
        The communicator of the solve (PETSc's COMM_WORLD under ``mpiexec``).
    n_global : int
        N, the nodes of the whole model.
    own : (n,) int
        Positions of this rank's own nodes among its held nodes, ascending (their PETSc order).
    petsc : (n_held,) int
        Global PETSc index of every held node.
    model_index : (n_held,) int
        Model index of every held node, ascending.
    X : (n_held, 3) float
        Coordinates of the held nodes, cm (the multigrid's rigid-body modes).
    ijk : (n_held, 3) int
        Their voxel indices (the order of the region factorisations).
    root_order : (N,) int or None
        On rank 0: the model index of every PETSc index (to write results in model order).
    """

    def __init__(self, comm, n_global: int, own: np.ndarray, petsc: np.ndarray, model_index: np.ndarray,
                 X: np.ndarray, ijk: np.ndarray, root_order: np.ndarray | None = None):
        self.PETSc = PETSc = import_petsc()
        self.comm = comm
        self.mpi = comm.tompi4py()
        self.rank, self.size = comm.getRank(), comm.getSize()
        self.n_global = int(n_global)
        self.own = np.asarray(own, np.int64)
        self.petsc = np.asarray(petsc, np.int64)
        self.model_index = np.asarray(model_index, np.int64)
        self.X, self.ijk = np.asarray(X, float), np.asarray(ijk)
        self.n_own, self.n_held = self.own.size, self.petsc.size
        self.root_order = root_order
        self._xg = PETSc.Vec().createMPI((3 * self.n_own, 3 * self.n_global), bsize=3, comm=comm)
        self._xl = PETSc.Vec().createSeq(3 * self.n_held, bsize=3, comm=PETSc.COMM_SELF)
        iset = PETSc.IS().createBlock(3, self.petsc.astype(PETSc.IntType), comm=PETSc.COMM_SELF)
        self._scatter = PETSc.Scatter().create(self._xg, iset, self._xl, None)
        iset.destroy()
        self.patches: PatchLayout | None = None

    @classmethod
    def single(cls, X: np.ndarray, ijk: np.ndarray) -> Layout:
        """The layout of a system that holds and owns all nodes, at ``X`` (N, 3) cm with voxel indices
        ``ijk`` (one rank, no halo)."""
        PETSc = import_petsc()
        idx = np.arange(np.shape(X)[0])
        return cls(PETSc.COMM_WORLD, idx.size, idx, idx, idx, X, ijk, root_order=idx)

    # -- node vectors ---------------------------------------------------------------------------

    def to_held(self, x: np.ndarray) -> np.ndarray:
        """Values at the held nodes (n_held, 3) from the owned values ``x`` of every rank (n, 3) or
        (3n,) (collective: the halo's values come from their owners)."""
        self._xg.setArray(np.asarray(x, float).ravel())
        self._scatter.scatter(self._xg, self._xl, addv=False, mode=self.PETSc.ScatterMode.FORWARD)
        return self._xl.getArray().copy().reshape(-1, 3)

    def gather(self, x: np.ndarray) -> np.ndarray | None:
        """The owned rows ``x`` (n, ...) of every rank as one array in model order (N, ...) on
        rank 0; None on the others (collective)."""
        parts = self.mpi.gather(np.ascontiguousarray(x), root=0)
        if self.rank != 0:
            return None
        whole = np.concatenate(parts, axis=0)
        out = np.empty_like(whole)
        out[self.root_order] = whole
        return out

    def owned_of(self, x: np.ndarray) -> np.ndarray:
        """This rank's rows (n, ...) of a whole-model array ``x`` (N, ...) in model order."""
        return np.asarray(x)[self.model_index[self.own]]

    # -- reductions -----------------------------------------------------------------------------

    def sum(self, value):
        """Σ over the ranks of a number or array (every rank gets it)."""
        from mpi4py import MPI

        return self._reduce(value, MPI.SUM)

    def max(self, value):
        """Largest over the ranks of a number or array (every rank gets it)."""
        from mpi4py import MPI

        return self._reduce(value, MPI.MAX)

    def _reduce(self, value, op):
        if np.isscalar(value):
            return self.mpi.allreduce(value, op=op)
        out = np.empty_like(np.asarray(value, float))
        self.mpi.Allreduce(np.ascontiguousarray(value, float), out, op=op)
        return out


class PatchLayout:
    """One rank's share of the pressure patches: the patches of its held nodes, the ones it owns
    (whose node of lowest model index it owns) and their global (PETSc) indices.

    Parameters
    ----------
    layout : Layout
    patch_of : (n_held,) int
        Patch of every held node (the held system's patch numbering).
    """

    def __init__(self, layout: Layout, patch_of: np.ndarray):
        PETSc = layout.PETSc
        self.layout = layout
        patch_of = np.asarray(patch_of, np.int64)
        n_patches = int(patch_of.max()) + 1 if patch_of.size else 0
        first = np.full(n_patches, np.iinfo(np.int64).max)
        np.minimum.at(first, patch_of, layout.model_index)
        first_node = np.searchsorted(layout.model_index, first)  # held position of each patch's first node
        owned_node = np.zeros(layout.n_held, bool)
        owned_node[layout.own] = True
        self.own = np.flatnonzero(owned_node[first_node])  # owned patches, ascending held numbering
        self.n_own = self.own.size
        self.n_global = int(layout.sum(self.n_own))
        self.start = int(layout.mpi.exscan(self.n_own) or 0)
        self.n_held = n_patches
        # the global index of a patch travels from its owner to the holders of its first node
        mark = np.full(layout.n_held, -1.0)
        mark[first_node[self.own]] = self.start + np.arange(self.n_own)
        got = layout.to_held(np.repeat(mark[layout.own], 3))[:, 0]
        self.petsc = np.rint(got[first_node]).astype(np.int64)  # −1: a patch cut by the halo's edge
        known = np.flatnonzero(self.petsc >= 0)
        self._known = known
        self._pg = PETSc.Vec().createMPI((self.n_own, self.n_global), comm=layout.comm)
        self._pl = PETSc.Vec().createSeq(known.size, comm=PETSc.COMM_SELF)
        iset = PETSc.IS().createGeneral(self.petsc[known].astype(PETSc.IntType), comm=PETSc.COMM_SELF)
        self._scatter = PETSc.Scatter().create(self._pg, iset, self._pl, None)
        iset.destroy()

    def to_held(self, p: np.ndarray) -> np.ndarray:
        """Values at the held patches (n_held,) from the owned values ``p`` of every rank (0 at
        patches cut by the halo's edge, which no owned row reads; collective)."""
        self._pg.setArray(np.asarray(p, float))
        self._scatter.scatter(self._pg, self._pl, addv=False, mode=self.layout.PETSc.ScatterMode.FORWARD)
        out = np.zeros(self.n_held)
        out[self._known] = self._pl.getArray()
        return out

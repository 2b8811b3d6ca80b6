"""One BoomerAMG worker process of :mod:`.linsolve.amg_processes`, and what both sides share.

The run's process spawns its workers with ``python -c "…import serve; serve()"``. Each worker
sets up, cycles and frees hierarchies on rank 0's commands; it needs numpy, mpi4py and petsc4py
and nothing else of the package, so this module imports no more: with the solver package
(numba, SciPy's solvers, the assemblers) a worker held 35 MB more private memory (``smaps_rollup``'s
``Anonymous`` after the imports with mpi4py and petsc4py: 57 MB, against 22 MB with this module).

Shared with rank 0: the transfer of arrays larger than MPI's int counts (:func:`send_array`,
:func:`recv_array`), the block rows as a PETSc matrix (:func:`hypre_matrix`) and BoomerAMG on it
(:func:`hypre_pc`).
"""

from __future__ import annotations

import os
import resource
import sys
import time

import numpy as np

from ..parallel import import_petsc, set_options
from .heap import map_large_allocations, release_free_heap

_CMD, _DATA = 11, 12
_CHUNK = 1 << 26  # elements per message: MPI counts are int


def destroy(objs) -> None:
    """Destroy a hierarchy's PETSc objects (PC, matrix, vectors) in one order on every process."""
    for o in objs:
        o.destroy()


def send_array(comm, a: np.ndarray, rank: int) -> None:
    a = np.ascontiguousarray(a).reshape(-1)
    comm.send((a.dtype.str, a.size), dest=rank, tag=_DATA)
    for lo in range(0, a.size, _CHUNK):
        comm.Send(a[lo:lo + _CHUNK], dest=rank, tag=_DATA)


def recv_array(comm, rank: int = 0) -> np.ndarray:
    dtype, size = comm.recv(source=rank, tag=_DATA)
    a = np.empty(size, dtype=np.dtype(dtype))
    for lo in range(0, size, _CHUNK):
        comm.Recv(a[lo:lo + _CHUNK], source=rank, tag=_DATA)
    return a


def hypre_matrix(comm, indptr, indices, data, n_local: int, n_total: int):
    """This rank's block rows (BSR arrays of 3 × 3 blocks, global block columns) as a PETSc matrix on ``comm``."""
    PETSc = import_petsc()

    idx = PETSc.IntType
    return PETSc.Mat().createBAIJ(size=((3 * n_local, 3 * n_total), (3 * n_local, 3 * n_total)), bsize=3,
                                  comm=comm, csr=(np.asarray(indptr, idx), np.asarray(indices, idx),
                                                  np.asarray(data).reshape(-1)))


def hypre_pc(A, prefix: str, options: dict):
    """BoomerAMG on the processes of ``A`` (converted in place to hypre's matrix type): PC and work vectors.

    The C heap's free pages are released before the set-up and after it (:mod:`.heap`): before,
    those of what the caller has just freed (the stand-in and its assembly's temporaries, or the
    rows a worker received), which hypre's allocations reuse only in part; after, those of the
    set-up's own temporaries (docs/performance.md, "How the solve keeps its memory down").
    """
    PETSc = import_petsc()

    release_free_heap()
    A.convert("hypre")
    A.setBlockSize(3)
    pc = PETSc.PC().create(comm=A.getComm())
    pc.setOptionsPrefix(prefix)
    pc.setOperators(A)
    pc.setType("hypre")
    pc.setHYPREType("boomeramg")
    set_options(prefix, options, None)
    pc.setFromOptions()
    pc.setUp()
    release_free_heap()
    x, y = A.createVecs()
    return A, pc, x, y


def serve() -> None:
    """A worker's loop: set up, apply and free hierarchies on rank 0's commands until ``stop``; any
    error prints its traceback and aborts the MPI job (rank 0 would otherwise wait for ever)."""
    import traceback

    from mpi4py import MPI

    map_large_allocations()  # as the solving process: freed hierarchies go back to the system
    parent = MPI.Comm.Get_parent()
    comm = parent.Merge(high=True)
    comm.send(os.getpid(), dest=0, tag=_DATA)
    try:
        _commands(comm)
    except BaseException:
        traceback.print_exc()
        sys.stderr.flush()
        comm.Abort(1)
    comm.Free()
    parent.Disconnect()


def _commands(comm) -> None:
    PETSc = import_petsc()

    held = {}
    while True:
        nap = 5e-5  # s; doubles up to 1 ms while no command comes: a cycle waits ≤ 1 ms, an idle worker ~1 % of a core
        while not comm.Iprobe(source=0, tag=_CMD):
            time.sleep(nap)
            nap = min(2.0 * nap, 1e-3)
        cmd, *args = comm.recv(source=0, tag=_CMD)
        if cmd == "setup":
            key, n_local, n_total, prefix, options = args
            indptr, indices, data = (recv_array(comm) for _ in range(3))
            A = hypre_matrix(PETSc.Comm(comm), indptr, indices, data, n_local, n_total)
            del indptr, indices, data
            A, pc, x, y = hypre_pc(A, prefix, options)
            held[key] = (pc, A, x, y)
        elif cmd == "apply":
            pc, A, x, y = held[args[0]]
            comm.Recv(x.getArray(), source=0, tag=_DATA)
            pc.apply(x, y)
            comm.Send(y.getArray(), dest=0, tag=_DATA)
        elif cmd == "free":
            destroy(held.pop(args[0]))
            release_free_heap()
        elif cmd == "rss":
            comm.send(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, dest=0, tag=_DATA)
        elif cmd == "stop":
            break
        else:
            raise ValueError(f"unknown command {cmd!r}")
    for objs in held.values():
        destroy(objs)


r"""BoomerAMG on several processes from one serial run: MPI workers spawned on first use.

hypre runs on one core per MPI process (Debian's hypre has no OpenMP), and in ``mixed_amg`` its
V-cycle is most of a Krylov iteration. With ``solve.solver.amg_processes: P`` (P > 1) the process
of the run spawns P − 1 workers (``MPI_Comm_spawn``, from a singleton: no ``mpiexec`` needed) and
joins them in one communicator; each BoomerAMG hierarchy is then set up and cycled on all P
processes, rank 0 (this process) holding the first block of rows. Everything else of the run
stays in this process. A V-cycle sends each worker its slice of the vector and takes its slice of
the result back; between cycles a worker sleeps in a poll of at most 1 ms, so that it leaves its
core to the run's numba threads.
The workers' side, and the pieces both sides share, are :mod:`..amg_worker`, which imports no more
than a worker needs.

Rows are cut into contiguous blocks of whole nodes with about equal non-zeros: the nodes are
numbered slice by slice, so the blocks are slabs. A hierarchy on P processes is not the one on
one process (hypre's hybrid Gauss–Seidel is Jacobi across ranks, and the coarsening sees the cut),
so iteration counts and results at the solver tolerances differ slightly from P = 1; a run
repeats itself for a given P.

The workers end with the run (an ``atexit`` hook sends them ``stop``). A worker that fails prints
its traceback and aborts; a thread of the run checks every second that its workers live, and when
one has died (an error, or killed from outside, e.g. for memory) it ends the run at once with one
``error:`` line and exit status 3, since the run may be waiting for it inside hypre. A run that
fails on its own while the workers are inside a set-up or cycle with it aborts the MPI job at exit
(exit status 1), since they could not receive a ``stop``. Hierarchies are freed on both sides at
the same point of the command sequence: a collected hierarchy is only queued, and freed before the
next command or the next set-up, whichever comes first.
"""

from __future__ import annotations

import atexit
import contextlib
import itertools
import os
import sys
import threading
import time

import numpy as np
import scipy.sparse as sp

from ...errors import SolverError
from ...parallel import import_petsc
from ..amg_worker import _CMD, _DATA, destroy, hypre_matrix, hypre_pc, send_array

_groups: dict[int, WorkerGroup] = {}
_refused: dict[int, str] = {}  # sizes MPI would not spawn, and why
_keys = itertools.count()


def available() -> bool:
    """True when mpi4py imports (the workers need it, and petsc4py with hypre)."""
    try:
        import mpi4py  # noqa: F401
    except ImportError:
        return False
    return True


class WorkerGroup:
    """This process (rank 0) and ``size`` − 1 spawned workers, one communicator.

    Parameters
    ----------
    size : int
        Processes in all, ≥ 2.
    """

    def __init__(self, size: int):
        from mpi4py import MPI

        try:
            self._inter = MPI.COMM_SELF.Spawn(sys.executable, args=["-c", "from pixmuscle.mechanics.amg_worker import serve; serve()"],
                                              maxprocs=size - 1)
        except MPI.Exception as err:
            _refused[size] = str(err)
            raise refusal(size) from None
        self.comm = self._inter.Merge(high=False)
        self.pids = [self.comm.recv(source=rank, tag=_DATA) for rank in range(1, size)]
        self.size = size
        self.open = True
        self.busy = False  # inside a set-up or cycle with the workers
        self._unfreed = []  # (key, PETSc objects) of collected hierarchies, freed before the next command
        atexit.register(self.close)
        threading.Thread(target=self._watch, name="amg-workers-watch", daemon=True).start()

    def _watch(self) -> None:
        """End the run when a worker has died (it may wait for it inside hypre for ever)."""
        while self.open:
            time.sleep(1.0)
            dead = [pid for pid in self.pids if not _alive(pid)]
            if dead and self.open:
                sys.stderr.write(f"error: solve.solver.amg_processes: the BoomerAMG worker process {dead[0]} has "
                                 "died (its error, if it had one, is above; else it was killed, e.g. for memory); "
                                 "the run stops\n")
                sys.stderr.flush()
                os._exit(3)

    def command(self, rank: int, *msg) -> None:
        self.flush()
        self.comm.send(msg, dest=rank, tag=_CMD)

    def flush(self) -> None:
        """Free the queued hierarchies on every process now (never from a finaliser: MPI calls)."""
        while self._unfreed:
            key, objs = self._unfreed.pop(0)
            for r in range(1, self.size):
                self.comm.send(("free", key), dest=r, tag=_CMD)
            destroy(objs)

    @contextlib.contextmanager
    def together(self):
        """Marks work that the workers do together with this process; an exception leaves the mark,
        and :meth:`close` then aborts the job instead of waiting for workers that cannot listen."""
        self.busy = True
        yield
        self.busy = False

    def release(self, key: int, objs: tuple) -> None:
        """Queue hierarchy ``key`` and this process's PETSc objects of it to be freed on all processes."""
        if self.open:
            self._unfreed.append((key, objs))

    def peak_rss_kb(self) -> list[int]:
        """Each worker's peak resident memory so far, kB (Linux ``ru_maxrss``)."""
        out = []
        for rank in range(1, self.size):
            self.command(rank, "rss")
            out.append(int(self.comm.recv(source=rank, tag=_DATA)))
        return out

    def close(self) -> None:
        """Stop the workers and leave the communicator (idempotent)."""
        if not self.open:
            return
        if self.busy:
            self.comm.Abort(1)
        self.open = False
        self._unfreed.clear()
        for rank in range(1, self.size):
            self.command(rank, "stop")
        self.comm.Free()
        self._inter.Disconnect()


def group(size: int) -> WorkerGroup:
    """The worker group of this process with ``size`` processes in all (spawned on first use; a
    size MPI refused once is not tried again, :func:`refusal`)."""
    if size in _refused:
        raise refusal(size)
    if size not in _groups or not _groups[size].open:
        _groups[size] = WorkerGroup(size)
    return _groups[size]


def flush_released() -> None:
    """Free the hierarchies queued for freeing on every open worker group of this process now."""
    for g in _groups.values():
        if g.open:
            g.flush()


def refusal(size: int) -> SolverError:
    """The error of a refused spawn of ``size`` − 1 workers; its ``reason`` is MPI's."""
    exc = SolverError(f"solve.solver.amg_processes: could not start {size - 1} MPI worker(s) for BoomerAMG "
                      f"({_refused[size]}; MPI's own message above says why); amg_processes: 1 needs none")
    exc.reason = _refused[size]
    return exc


def workers_peak_rss_kb() -> list[int]:
    """Peak resident memory of each worker of this process's groups, kB; empty without workers."""
    return [kb for g in _groups.values() if g.open for kb in g.peak_rss_kb()]


def _alive(pid: int) -> bool:
    """Whether process ``pid`` runs (not ended, not a zombie; the workers are not this process's children)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] not in ("Z", "X")
    except FileNotFoundError:
        return False
    except OSError:  # no /proc: ask the kernel
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return False
        return True


def row_blocks(indptr: np.ndarray, parts: int) -> np.ndarray:
    """Boundaries (parts + 1,) of contiguous block-row ranges with about equal non-zeros."""
    n = indptr.size - 1
    cuts = np.searchsorted(indptr, np.arange(1, parts) * (indptr[-1] / parts))
    return np.concatenate([[0], np.clip(cuts, 0, n), [n]]).astype(np.int64)


class SpreadBoomerAMG:
    """One BoomerAMG V-cycle per ``@``, set up and applied on the processes of a :class:`WorkerGroup`.

    Parameters
    ----------
    K : BSR (3N × 3N) with 3 × 3 blocks, or a function of no arguments that returns it
        Stand-in of the tangent, N/cm; given as a function, it is released once the processes hold
        their rows, before hypre's set-up.
    workers : WorkerGroup
    prefix, options
        PETSc options prefix and BoomerAMG options (:data:`.multigrid.BOOMERAMG_OPTIONS`).
    """

    def __init__(self, K, workers: WorkerGroup, prefix: str, options: dict):
        PETSc = import_petsc()

        # a hierarchy dropped just before (a rebuild) is only queued: free it before the stand-in is
        # made, or the rebuild's peak holds both
        workers.flush()
        if callable(K):
            K = K()
        if not (sp.isspmatrix_bsr(K) and K.blocksize == (3, 3)):
            K = sp.bsr_matrix(K, blocksize=(3, 3))
            K.sort_indices()
        self._workers = workers
        self._key = next(_keys)
        self.nnz_per_row = K.nnz / K.shape[0]
        self.levels = None
        self.operator_complexity = None
        comm = workers.comm
        nb = K.shape[0] // 3
        self.bounds = row_blocks(K.indptr, workers.size)
        for rank in range(1, workers.size):
            b0, b1 = self.bounds[rank], self.bounds[rank + 1]
            p0, p1 = K.indptr[b0], K.indptr[b1]
            workers.command(rank, "setup", self._key, int(b1 - b0), nb, prefix, options)
            send_array(comm, K.indptr[b0:b1 + 1] - p0, rank)
            send_array(comm, K.indices[p0:p1], rank)
            send_array(comm, K.data[p0:p1], rank)
        b1 = self.bounds[1]
        p1 = K.indptr[b1]
        with workers.together():
            A = hypre_matrix(PETSc.Comm(comm), K.indptr[:b1 + 1], K.indices[:p1], K.data[:p1], int(b1), nb)
            self.shape = K.shape
            del K
            self._A, self._pc, self._x, self._y = hypre_pc(A, prefix, options)
        self._n0 = 3 * int(b1)

    def __matmul__(self, v: np.ndarray) -> np.ndarray:
        v = np.ascontiguousarray(v, dtype=float)
        comm = self._workers.comm
        out = np.empty_like(v)
        for rank in range(1, self._workers.size):
            lo, hi = 3 * self.bounds[rank], 3 * self.bounds[rank + 1]
            self._workers.command(rank, "apply", self._key)
            comm.Send(v[lo:hi], dest=rank, tag=_DATA)
        with self._workers.together():
            self._x.setArray(v[: self._n0])
            self._pc.apply(self._x, self._y)
            out[: self._n0] = self._y.getArray()
            for rank in range(1, self._workers.size):
                lo, hi = 3 * self.bounds[rank], 3 * self.bounds[rank + 1]
                comm.Recv(out[lo:hi], source=rank, tag=_DATA)
        return out

    def __del__(self):
        # no MPI here: a garbage collection may come in the middle of another hierarchy's set-up
        objs = tuple(getattr(self, o) for o in ("_pc", "_A", "_x", "_y") if getattr(self, o, None) is not None)
        workers = getattr(self, "_workers", None)
        if workers is not None and workers.open:
            workers.release(self._key, objs)
        else:  # the workers are gone (or were never reached): this process's objects only
            destroy(objs)

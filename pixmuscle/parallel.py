"""Where this process stands in an MPI launch (``mpiexec -n P pixmuscle solve …``).

Without a launcher (no MPI environment variables) the process is rank 0 of 1 and nothing is
imported. Under ``mpiexec`` the communicator is PETSc's (petsc4py initialises MPI), so mpi4py is
not needed. Only rank 0 logs, shows progress and writes files; a failure on any rank ends all
ranks (:func:`abort_on_failure`).
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys

#: what to do when petsc4py is missing (``solve.solver.backend: petsc``, hypre, a run under ``mpiexec``)
INSTALL_HINT = ("petsc4py is not installed: on Debian/Ubuntu run `make venv` as root (it installs libpetsc-real-dev "
                "and builds petsc4py against it), or by hand: apt-get install libpetsc-real-dev libopenmpi-dev "
                "openmpi-bin; PETSC_DIR=/usr/lib/petscdir/petsc3.18/x86_64-linux-gnu-real pip install "
                "--no-build-isolation 'cython<3' 'petsc4py==3.18.5' (docs/petsc.md)")

#: environment variables by which MPI launchers (OpenMPI, MPICH/Hydra, PMIx, Slurm) give the process count
_SIZE_VARS = ("OMPI_COMM_WORLD_SIZE", "PMI_SIZE", "PMIX_SIZE", "MPI_LOCALNRANKS")


def launched_size() -> int:
    """Number of processes the launcher started (1 without a launcher)."""
    for var in _SIZE_VARS:
        value = os.environ.get(var)
        if value and value.isdigit():
            return int(value)
    return 1


def share_cores() -> None:
    """Under ``mpiexec``, give each process its share of the cores for numba's parallel kernels:
    ``NUMBA_NUM_THREADS`` = the cores this process may run on // the processes of the launch (at
    least 1), unless it is set already. Called when the package is imported, before numba is: with
    every process starting all cores' threads, three ranks on two cores took 37 s instead of 6 for
    one load step of the test body (their threads spin while they wait for each other)."""
    size = launched_size()
    if size > 1 and "NUMBA_NUM_THREADS" not in os.environ:
        os.environ["NUMBA_NUM_THREADS"] = str(max(1, len(os.sched_getaffinity(0)) // size))


def import_petsc():
    """petsc4py's ``PETSc`` module, PETSc initialised (once per process) without its signal handlers.

    PETSc's default start installs handlers for SIGPIPE, SIGSEGV, SIGFPE and others, and its
    finalisation leaves SIGPIPE at the system default (end the process) instead of Python's ignore.
    A Dask or browser connection closed by its peer then kills the interpreter (``make: … Broken
    pipe``) instead of raising ``BrokenPipeError``. ``-no_signal_handler`` keeps Python's handling.

    Raises
    ------
    ImportError
        When petsc4py is not installed.
    """
    import petsc4py

    if "petsc4py.PETSc" not in sys.modules:
        petsc4py.init(["-no_signal_handler"])
    from petsc4py import PETSc

    return PETSc


def set_options(prefix: str, defaults: dict, options: dict | None) -> dict:
    """Write ``options`` over ``defaults`` (names without the dash) into PETSc's options database
    under ``prefix``, replacing whatever was set under it before (another solver of this process);
    returns the merged mapping. ``true`` (or an empty value) sets a bare flag; whole floats are
    written as integers."""
    PETSc = import_petsc()

    merged = {**defaults, **(options or {})}
    db = PETSc.Options()
    for key in db.getAll():  # forget what an earlier solver of this process set under the prefix
        if key.startswith(prefix):
            db.delValue(key)
    for key, value in merged.items():
        key = str(key).lstrip("-")
        # true is a bare flag: PETSc reads "-ksp_monitor true" as a viewer named "true" and fails
        # and the config reads numbers as floats: "0.0" is no value for an integer option
        if isinstance(value, float) and value.is_integer():
            value = int(value)
        text = "" if value is None or value is True else "false" if value is False else str(value)
        db.setValue(prefix + key, text)
    return merged


def _comm():
    if launched_size() <= 1:
        return None
    try:
        PETSc = import_petsc()
    except ImportError:
        sys.stderr.write(f"error: started by mpiexec with {launched_size()} processes, but {INSTALL_HINT}\n")
        sys.exit(2)
    return PETSc.COMM_WORLD


def rank() -> int:
    """Rank of this process (0 without MPI)."""
    comm = _comm()
    return 0 if comm is None else comm.getRank()


def size() -> int:
    """Number of ranks (1 without MPI)."""
    comm = _comm()
    return 1 if comm is None else comm.getSize()


def quiet_other_ranks() -> None:
    """Silence logging on every rank but 0."""
    if rank() != 0:
        logging.disable(logging.CRITICAL)


@contextlib.contextmanager
def abort_on_failure():
    """Under MPI, end every rank when this one fails: print the error (prefixed by the rank) and abort.

    Without MPI, exceptions pass through unchanged (the CLI prints them as usual).
    """
    comm = _comm()
    if comm is None or comm.getSize() <= 1:
        yield
        return
    try:
        yield
    except BaseException as exc:
        from .errors import PixmuscleError

        code = getattr(exc, "exit_code", None)
        if code == 0:
            raise
        where = "" if comm.getRank() == 0 else f" (rank {comm.getRank()} of {comm.getSize()})"
        msg = str(exc) if isinstance(exc, PixmuscleError | ValueError) else f"{type(exc).__name__}: {exc}"
        sys.stderr.write(f"error{where}: {msg}\n")
        sys.stderr.flush()
        from .errors import SolverError

        if isinstance(exc, SolverError) and comm.getRank() == 0 and getattr(exc, "results_path", None):
            sys.stdout.write(f"{exc.results_path}\n")  # what the failed solve wrote, as without MPI
            sys.stdout.flush()
        _abort(comm, 3 if isinstance(exc, SolverError) else 2 if isinstance(exc, PixmuscleError) else 1)


def _abort(comm, code: int) -> None:
    """End every rank: MPI_Abort through mpi4py where installed, else leave with ``code`` (an MPI
    process that ends without MPI_Finalize makes mpiexec terminate the others)."""
    sys.stdout.flush()
    try:
        comm.tompi4py().Abort(code)
    except Exception:  # mpi4py missing
        pass
    os._exit(code)

"""Dask runner: each case is a chain of stage tasks on a ``dask.distributed`` cluster.

Independent chains run in parallel on the workers; a stage shared by several cases is one task
that their chains depend on. Either a local cluster of ``workers`` processes is started for the
run (one thread each, with numba/OpenMP/MKL/OpenBLAS limited to cores ÷ workers threads so that
the workers do not oversubscribe the machine), or ``scheduler`` names an existing cluster
(``dask scheduler`` + ``dask worker`` processes, dask-jobqueue, ...).

A stage that raises fails its case (the message is kept) and the rest of that chain is dropped;
the other cases go on. A worker process that dies while running a stage (killed, out of memory) is
replaced and the stage is retried once on the local cluster; a second death fails the case with a
message saying so. On an existing cluster the number of retries is the scheduler's
``distributed.scheduler.allowed-failures`` (set it to 1 there for the same behaviour).
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import pickle
import time
import uuid
from collections.abc import Iterator
from dataclasses import field
from pathlib import Path

from ..plan import Stage, execute_stage
from . import RUNNERS, CaseOutcome, Progress, available_cores, error_message

_LOG = logging.getLogger("pixmuscle.runners")

#: event topic of stage starts (worker → client)
TOPIC = "pixmuscle-stage"
#: environment variables that cap the threads of the numerical libraries in a worker process
THREAD_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS",
                    "VECLIB_MAXIMUM_THREADS")


def thread_environment(n_workers: int, cores: int | None = None) -> dict[str, str]:
    """Environment of a worker process so that ``n_workers`` of them share ``cores`` cores."""
    per = max(1, (cores or available_cores()) // max(1, n_workers))
    return {v: str(per) for v in THREAD_VARIABLES}


@contextlib.contextmanager
def local_cluster(n_workers: int) -> Iterator[str]:
    """A ``LocalCluster`` of ``n_workers`` processes (one thread each) for one run; yields its address.

    Killed workers are restarted by their nanny and a task is retried once after a worker death
    (``allowed-failures: 1``). The scheduler's HTTP server (dashboard, if bokeh is installed) takes
    a free port, so that several runs, or another cluster on 8787, do not collide.
    """
    import dask
    from distributed import LocalCluster

    with dask.config.set({"distributed.scheduler.allowed-failures": 1}):
        cluster = LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True,
                               dashboard_address=":0", env=thread_environment(n_workers))
    try:
        yield cluster.scheduler_address
    finally:
        cluster.close()


def _stage_task(plugins: tuple, blob: bytes, force: bool, case: str, upstream: list | None = None) -> list:
    """Worker side: import the config's plugin files, unpickle the stage, announce it, run it (or skip it).

    The stage comes pickled (``blob``) so that it is unpickled only once the plugins it may refer
    to (a material law of a plugin file, say) are imported in this worker process.
    Returns the (label, "ran" | "skipped") pairs of the chain so far, so that the client needs
    only the last task of a case. An exception leaves with the stage label attached
    (``pixmuscle_stage``) so that the client can say which stage failed.
    """
    from ..plugins import import_plugins

    import_plugins(plugins)
    stage = pickle.loads(blob)  # noqa: S301 - the client's own stage
    try:
        from distributed import get_worker

        get_worker().log_event(TOPIC, {"case": case, "stage": stage.label})
    except ValueError:  # not on a worker
        pass
    try:
        state = execute_stage(stage, force)
    except Exception as exc:
        exc.pixmuscle_stage = stage.label
        raise
    return [*(upstream or []), (stage.label, state)]


@RUNNERS.register("dask")
@dataclasses.dataclass(frozen=True)
class Dask:
    """The cases in parallel on a Dask cluster (``execution: {kind: dask, workers: 4}``).

    Parameters
    ----------
    workers : int, optional
        Size of the local cluster started for the run (default: the machine's cores); ignored
        with ``scheduler``.
    scheduler : str, optional
        Address of an existing scheduler, e.g. ``tcp://10.0.0.5:8786``.
    """

    workers: int | None = field(default=None, metadata={
        "range": (1, None), "doc": "worker processes of a local cluster started for the run (default: the cores)"})
    scheduler: str | None = field(default=None, metadata={
        "doc": "address of an existing Dask scheduler, e.g. tcp://host:8786"})

    def run(self, plans: dict[str, list[Stage]], *, force: bool = False, progress: Progress | None = None,
            raise_errors: bool = False) -> dict[str, CaseOutcome]:
        """Run the cases on the cluster; parameters and result as :meth:`pixmuscle.runners.serial.Serial.run`
        (``raise_errors``: the first case's error is re-raised, unless its worker died)."""
        progress = progress or Progress(list(plans))
        if self.scheduler:
            return _run_on(self.scheduler, plans, force, progress, raise_errors)
        with local_cluster(self.workers or available_cores()) as address:
            return _run_on(address, plans, force, progress, raise_errors)


def _run_on(address: str, plans, force, progress, raise_errors) -> dict[str, CaseOutcome]:
    from distributed import Client, as_completed

    from ..errors import InputError

    try:
        client = Client(address, timeout="30s")
    except OSError as exc:
        raise InputError(f"cannot reach the Dask scheduler at {address}: {exc}") from None
    outcomes = {name: CaseOutcome() for name in plans}
    with client:
        client.subscribe_topic(TOPIC, lambda event: progress.stage(event[1]["case"], event[1]["stage"]))
        tag = uuid.uuid4().hex[:8]
        tasks: dict[Path, object] = {}       # stage output → future: a shared stage is one task
        labels: dict[str, str] = {}          # task key → stage label (to name a killed stage)
        ends: dict[str, list[str]] = {}      # key of a chain's last task → its cases
        finals = {}
        for name, stages in plans.items():
            fut = None
            for stage in stages:
                nxt = tasks.get(stage.output)
                if nxt is None:
                    key = f"{name}:{stage.label}:{tag}-{len(tasks)}"
                    nxt = client.submit(_stage_task, stage.plugins, pickle.dumps(stage), force, name, fut, key=key,
                                        pure=False)
                    tasks[stage.output], labels[key] = nxt, stage.label
                fut = nxt
            if fut is None:
                progress.done(name)
                continue
            ends.setdefault(fut.key, []).append(name)
            finals[fut.key] = fut
        tasks.clear()                        # keep only the chain ends: lost intermediates need no recompute
        t0 = time.monotonic()
        for fut in as_completed(list(finals.values())):
            err = None
            if fut.status == "finished":
                states = fut.result()
            else:
                exc = fut.exception()
                if raise_errors and not _is_killed(exc):
                    raise exc
                err = _failure(exc, labels)
            for name in ends[fut.key]:
                out = outcomes[name]
                if err is None:
                    for label, state in states:
                        (out.ran if state == "ran" else out.skipped).append(label)
                        progress.stage_done(name, label, state)
                out.error, out.seconds = err, time.monotonic() - t0
                progress.done(name, err)
        client.unsubscribe_topic(TOPIC)
    return outcomes


def _is_killed(exc: BaseException) -> bool:
    from distributed.scheduler import KilledWorker

    return isinstance(exc, KilledWorker)


def _failure(exc: BaseException, labels: dict[str, str]) -> str:
    """One line naming the failed stage: its error, or that its worker died twice."""
    if _is_killed(exc):
        label = labels.get(exc.task, str(exc.task))
        return (f"{label}: the worker process running it died (killed, or out of memory) and died again "
                "when the stage was retried; not retried further")
    return error_message(getattr(exc, "pixmuscle_stage", "stage"), exc)

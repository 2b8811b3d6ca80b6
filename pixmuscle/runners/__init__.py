"""Runners: execute the stage chains of :func:`pixmuscle.plan.plan_case`, serially or on Dask.

A runner is one module of this package registering itself in :data:`RUNNERS`: a frozen dataclass
of its options (the config section ``execution: {kind: <name>, …options}``) with a method
``run(plans, *, force, progress, raise_errors) -> {case: CaseOutcome}`` where ``plans`` maps a
case name to its list of :class:`~pixmuscle.plan.Stage`. A stage output that several cases share
(a study's segmentation, say) is produced once. A failing case is reported in its outcome and the
other cases go on (``raise_errors=True``: the first error propagates instead).

Runners of pixmuscle: ``serial`` (:class:`~.serial.Serial`, in this process) and ``dask``
(:class:`~.dask.Dask`, a local or an existing ``dask.distributed`` cluster).
"""

from __future__ import annotations

import dataclasses
import logging
import os
import threading
import time
from collections.abc import Mapping, Sequence
from typing import Any

from ..registry import Registry

_LOG = logging.getLogger("pixmuscle.runners")


@dataclasses.dataclass
class CaseOutcome:
    """What happened to one case: stage labels run and skipped, or the error that stopped it."""

    ran: list = dataclasses.field(default_factory=list)
    skipped: list = dataclasses.field(default_factory=list)
    error: str | None = None
    seconds: float = 0.0


def error_message(stage_label: str, exc: BaseException) -> str:
    """One line for a failed stage: pixmuscle's own errors as they are, others with their type."""
    from ..errors import PixmuscleError

    text = str(exc) if isinstance(exc, PixmuscleError) else f"{type(exc).__name__}: {exc}"
    return f"{stage_label}: {text}"


def _hms(seconds: float) -> str:
    seconds = int(round(seconds))
    h, rest = divmod(seconds, 3600)
    m, s = divmod(rest, 60)
    return f"{h}h{m:02d}m{s:02d}s" if h else f"{m}m{s:02d}s" if m else f"{s}s"


class Progress:
    """Case progress as log lines: queued, running, done or failed, and a total with an ETA.

    Thread-safe (the Dask runner reports from the client's event thread). The ETA is the elapsed
    time divided by the finished cases, times the cases left: a rate estimate that includes the
    parallelism of the runner, not a schedule.
    """

    def __init__(self, names: Sequence[str], logger: logging.Logger = _LOG):
        self._names = list(names)
        self._log = logger
        self._lock = threading.Lock()
        self._state = {n: "queued" for n in self._names}
        self._t0 = time.monotonic()
        self._started: dict[str, float] = {}
        self.many = len(self._names) > 1
        if self.many:
            self._log.info("%d cases queued", len(self._names))
            for n in self._names:
                self._log.info("%s: queued", n)

    def stage(self, name: str, label: str) -> None:
        """Stage ``label`` of case ``name`` starts."""
        with self._lock:
            if self._state.get(name) == "queued":
                self._state[name] = "running"
                self._started[name] = time.monotonic()
                if self.many:
                    self._log.info("%s: running", name)
            self._log.debug("[%s] %s ...", name, label)

    def stage_done(self, name: str, label: str, state: str) -> None:
        """Stage ``label`` of case ``name`` ran (``"ran"``) or was up to date (``"skipped"``)."""
        self._log.log(logging.DEBUG if self.many else logging.INFO, "[%s] %s: %s", name, label,
                      "done" if state == "ran" else "up to date, skipped")

    def retry(self, name: str, message: str) -> None:
        self._log.warning("%s: %s", name, message)

    def done(self, name: str, error: str | None = None) -> None:
        """Case ``name`` finished (``error`` None) or failed."""
        with self._lock:
            t = time.monotonic() - self._started.get(name, self._t0)
            self._state[name] = "failed" if error else "done"
            if self.many:
                if error:
                    self._log.error("%s: failed after %s: %s", name, _hms(t), error)
                else:
                    self._log.info("%s: done in %s", name, _hms(t))
                self._log.info("%s", self.total_line())

    def total_line(self) -> str:
        n = len(self._names)
        done = sum(s == "done" for s in self._state.values())
        failed = sum(s == "failed" for s in self._state.values())
        running = sum(s == "running" for s in self._state.values())
        finished = done + failed
        elapsed = time.monotonic() - self._t0
        eta = "" if not finished or finished == n else f", ETA {_hms(elapsed / finished * (n - finished))}"
        return (f"total: {finished}/{n} finished ({done} done, {failed} failed, {running} running), "
                f"elapsed {_hms(elapsed)}{eta}")

    def finish(self) -> None:
        if self.many:
            self._log.info("all cases finished: %s", self.total_line())


def available_cores() -> int:
    """CPU cores this process may use (affinity-aware)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def parse_execution(data: Any, where: str = "execution"):
    """The runner of an ``execution`` section: ``{kind: <name>, …options}`` → that runner's dataclass.

    A mapping without ``kind`` is the short form of the command-line options: ``{workers: 0}`` is
    the serial runner, ``{workers: N}`` and/or ``{scheduler: ADDRESS}`` the Dask runner. ``None``
    (no section) stays ``None``: :func:`choose_runner` then picks by the number of cases.

    Raises
    ------
    InputError
        Naming the key path (``execution.workers: expected a value ≥ 1, got -1``).
    """
    if data is None:
        return None
    if isinstance(data, Mapping) and RUNNERS.key not in data:
        data = {"kind": "serial"} if dict(data) == {"workers": 0} else {"kind": "dask", **data}
    return RUNNERS.parse(data, where)


def choose_runner(execution: Any, n_cases: int, *, workers: int | None = None, scheduler: str | None = None):
    """The runner of a run: the command-line options, else the ``execution`` section, else serial
    for one case and a local Dask cluster sized to the machine for several.

    Parameters
    ----------
    execution : runner dataclass or None
        :func:`parse_execution` of the config's section.
    n_cases : int
    workers, scheduler : optional
        ``pixmuscle run --workers/--scheduler``: the short form of :func:`parse_execution`, which
        replaces the config's section (with both, the scheduler's cluster is used).
    """
    if workers is not None or scheduler is not None:
        opts = {"scheduler": scheduler} if scheduler else {"workers": workers}
        return parse_execution(opts, "command line")
    if execution is not None:
        return execution
    return parse_execution({"workers": 0 if n_cases <= 1 else max(1, min(n_cases, available_cores()))})


#: Registered runners (name → entry); ``execution.kind`` names one.
RUNNERS = Registry("runner", key="kind", package=__name__)
RUNNERS.discover()

__all__ = ["RUNNERS", "CaseOutcome", "Progress", "choose_runner", "parse_execution", "error_message",
           "available_cores"]

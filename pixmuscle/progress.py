"""Logging set-up and progress display, shared by the stages.

Everything here writes to **stderr**; the CLI prints only result paths on stdout, so
``$(pixmuscle run …)`` captures paths. Verbosity (``setup_logging``):

====  ===========================================================================================
-q    warnings and errors only; no progress bars
0     stage summaries (``pixmuscle.pipeline``, ``pixmuscle.stages``, ``pixmuscle.cli``), all
      warnings, progress bars with ETA (a bar shows α and the last Newton residual of a solve)
-v    also the details of every layer (per load step Newton summaries, segmentation, RK supports)
-vv   debug messages, with time and logger name
====  ===========================================================================================

On a terminal, messages go through rich (colours, no line wrapping of paths); elsewhere (a file,
a pipe, CI) they are plain lines ``LEVEL message`` that are never wrapped.
"""

from __future__ import annotations

import contextlib
import logging
import sys
import time
from collections.abc import Iterator

import numpy as np

_LOG = logging.getLogger("pixmuscle")
#: seconds between two progress lines when stderr is not a terminal
PLAIN_EVERY_S = 5.0
#: loggers whose INFO messages are shown at the default verbosity
SUMMARY_LOGGERS = ("pixmuscle.pipeline", "pixmuscle.stages", "pixmuscle.cli", "pixmuscle.runners", "pixmuscle.verify")


class _Verbosity(logging.Filter):
    """At verbosity 0, INFO records pass only from the summary loggers."""

    def __init__(self, verbosity: int):
        super().__init__()
        self.verbosity = verbosity

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno >= logging.WARNING or self.verbosity >= 1:
            return True
        return record.name.startswith(SUMMARY_LOGGERS)


def _is_tty(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False


def setup_logging(verbosity: int = 0, stream=None) -> logging.Handler:
    """Configure the ``pixmuscle`` logger (see the module docstring for the levels).

    Parameters
    ----------
    verbosity : int
        -1 quiet, 0 default, 1 (-v), 2 (-vv).
    stream : file-like, optional
        Default ``sys.stderr``.

    Returns
    -------
    logging.Handler
        The handler installed (replacing earlier ones).
    """
    stream = sys.stderr if stream is None else stream
    level = logging.WARNING if verbosity < 0 else logging.INFO if verbosity < 2 else logging.DEBUG
    logger = logging.getLogger("pixmuscle")
    for h in list(logger.handlers):
        if getattr(h, "_pixmuscle", False):
            logger.removeHandler(h)
    if _is_tty(stream):
        from rich.console import Console
        from rich.logging import RichHandler

        console = Console(file=stream, soft_wrap=True)
        handler: logging.Handler = RichHandler(console=console, show_path=False, show_time=verbosity >= 2,
                                               rich_tracebacks=False, markup=False)
        fmt = "%(name)s: %(message)s" if verbosity >= 2 else "%(message)s"
    else:
        handler = logging.StreamHandler(stream)
        fmt = ("%(asctime)s %(levelname)s %(name)s: %(message)s" if verbosity >= 2
               else "%(levelname)s %(message)s")
    handler.setFormatter(logging.Formatter(fmt))
    handler.setLevel(level)
    handler.addFilter(_Verbosity(verbosity))
    handler._pixmuscle = True  # type: ignore[attr-defined]
    logger.addHandler(handler)
    logger.setLevel(level)
    logger.propagate = False
    return handler


def _fmt_fields(fields: dict) -> str:
    def one(k, v):
        if k == "residual" and isinstance(v, float) and v == 0.0:
            return "residual below round-off"
        return f"{k}={v:.3g}" if isinstance(v, float) else f"{k}={v}"

    return " ".join(one(k, v) for k, v in fields.items())


def _eta(done: float, total: float, elapsed: float) -> str:
    if done <= 0 or total <= done:
        return ""
    s = elapsed / done * (total - done)
    return f", about {s / 60:.0f} min left" if s >= 120 else f", about {s:.0f} s left"


class _Progress:
    """Progress sink handed to the stages: ``advance(n=1, **fields)``, ``log(msg)``."""

    def __init__(self, bar, task, description: str, total: int, plain: bool):
        self._bar, self._task, self._description = bar, task, description
        self._total, self._done, self._t0, self._plain = total, 0, time.perf_counter(), plain
        self._last = -np.inf

    def advance(self, n: int = 1, **fields) -> None:
        self._done += n
        desc = self._description + (" " + _fmt_fields(fields) if fields else "")
        if self._bar is not None:
            self._bar.update(self._task, advance=n, description=desc)
        elif self._plain:  # not a terminal: a line with an ETA at most every PLAIN_EVERY_S, and at the end
            now = time.perf_counter()
            if now - self._last >= PLAIN_EVERY_S or self._done >= self._total:
                self._last = now
                logging.getLogger("pixmuscle.stages.progress").info(
                    "%s: %d of %d%s", desc, self._done, self._total, _eta(self._done, self._total, now - self._t0))

    def update(self, **fields) -> None:
        """Show new values (e.g. the Newton residual of the current iteration) without advancing."""
        desc = self._description + (" " + _fmt_fields(fields) if fields else "")
        if self._bar is not None:
            self._bar.update(self._task, description=desc)
        elif self._plain:
            logging.getLogger("pixmuscle.stages.progress").debug("%s", desc)

    def log(self, msg: str) -> None:
        logging.getLogger("pixmuscle.stages").info(msg)


class _Feed(logging.Handler):
    def __init__(self, bar: _Progress):
        super().__init__(level=logging.DEBUG)
        self.bar = bar

    def emit(self, record: logging.LogRecord) -> None:
        args = record.args if isinstance(record.args, tuple) else ()
        if len(args) == 4:  # step, iteration, residual (N), relative residual
            self.bar.update(step=args[0], iteration=args[1], residual=float(args[3]))


@contextlib.contextmanager
def newton_feed(bar: _Progress, logger: str = "pixmuscle.mechanics.newton") -> Iterator[None]:
    """Show the Newton iteration and relative residual of the running solve on ``bar`` (from the
    solver's per-iteration debug records; nothing is printed unless ``-vv``)."""
    log = logging.getLogger(logger)
    if bar._bar is None:
        yield
        return
    old = log.level
    feed = _Feed(bar)
    log.addHandler(feed)
    log.setLevel(logging.DEBUG)
    try:
        yield
    finally:
        log.removeHandler(feed)
        log.setLevel(old)


@contextlib.contextmanager
def progress(total: int, description: str) -> Iterator[_Progress]:
    """Progress bar (stderr) for ``total`` units of work with elapsed time and ETA.

    Quiet (``-q``): a no-op object. Not a terminal: one log line per unit of work with an ETA.
    """
    if not _LOG.isEnabledFor(logging.INFO):
        yield _Progress(None, None, description, total, plain=False)
        return
    if not _is_tty(sys.stderr):
        yield _Progress(None, None, description, total, plain=True)
        return
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    bar = Progress(
        TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
        TextColumn("ETA"), TimeRemainingColumn(), console=Console(stderr=True), transient=False,
    )
    with bar:
        task = bar.add_task(description, total=total)
        yield _Progress(bar, task, description, total, plain=False)

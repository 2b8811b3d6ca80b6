"""Progress display and logging set-up (rich), shared by the stages.

Stages call :func:`progress` around long loops (slices, load steps). Output goes to stderr; it is
silent when the log level is above INFO (``-q``).
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator

_LOG = logging.getLogger("pixmuscle")


def setup_logging(verbosity: int = 0) -> None:
    """Configure the ``pixmuscle`` logger: -1 quiet (warnings), 0 info, 1+ debug."""
    from rich.logging import RichHandler

    level = logging.WARNING if verbosity < 0 else logging.INFO if verbosity == 0 else logging.DEBUG
    logger = logging.getLogger("pixmuscle")
    logger.handlers.clear()
    handler = RichHandler(show_path=False, rich_tracebacks=False, markup=False)
    handler.setFormatter(logging.Formatter("%(message)s"))
    logger.addHandler(handler)
    logger.setLevel(level)
    logger.propagate = False


class _Progress:
    def __init__(self, bar, task, description: str):
        self._bar, self._task, self._description = bar, task, description

    def advance(self, n: int = 1, **fields) -> None:
        if self._bar is not None:
            desc = self._description
            if fields:
                desc += " " + " ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in fields.items())
            self._bar.update(self._task, advance=n, description=desc)

    def log(self, msg: str) -> None:
        _LOG.info(msg)


@contextlib.contextmanager
def progress(total: int, description: str) -> Iterator[_Progress]:
    """Progress bar for ``total`` units of work; a no-op object when quiet."""
    if not _LOG.isEnabledFor(logging.INFO):
        yield _Progress(None, None, description)
        return
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    bar = Progress(
        TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
        console=Console(stderr=True), transient=False,
    )
    with bar:
        task = bar.add_task(description, total=total)
        yield _Progress(bar, task, description)

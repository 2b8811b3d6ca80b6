"""Serial runner: every case's stages one after the other, in this process."""

from __future__ import annotations

import dataclasses
import logging
import time
from pathlib import Path

from ..errors import Interrupted
from ..plan import Stage, execute_stage
from . import RUNNERS, CaseOutcome, Progress, error_message

_LOG = logging.getLogger("pixmuscle.runners")


@RUNNERS.register("serial")
@dataclasses.dataclass(frozen=True)
class Serial:
    """The cases one after the other in this process (``execution: {kind: serial}``, ``--workers 0``); no options."""

    def run(self, plans: dict[str, list[Stage]], *, force: bool = False, progress: Progress | None = None,
            raise_errors: bool = False) -> dict[str, CaseOutcome]:
        """Run the cases in the order given.

        Parameters
        ----------
        plans : dict
            Case name → its stages in order (:func:`pixmuscle.plan.plan_case`).
        force : bool
            Run stages even when their outputs are up to date.
        progress : Progress, optional
        raise_errors : bool
            Let the first error propagate (single-case runs) instead of recording it.

        Returns
        -------
        dict
            Case name → :class:`CaseOutcome`. A stage output shared by several cases is produced
            once; if it failed, the cases that need it fail with the same message.
        """
        progress = progress or Progress(list(plans))
        done: dict[Path, tuple[str, str | None]] = {}   # output → (state, error)
        outcomes = {}
        for name, stages in plans.items():
            out = outcomes[name] = CaseOutcome()
            t0 = time.monotonic()
            for stage in stages:
                progress.stage(name, stage.label)
                if stage.output in done:
                    state, err = done[stage.output]
                else:
                    try:
                        state, err = execute_stage(stage, force), None
                    except Interrupted as exc:  # Ctrl-C or SIGTERM: the finished stages' files stay
                        exc.kept = [Path(st.output).name for st in stages[:stages.index(stage)] if Path(st.output).exists()]
                        raise
                    except Exception as exc:
                        if raise_errors:
                            raise
                        from ..errors import PixmuscleError

                        if not isinstance(exc, PixmuscleError):
                            _LOG.exception("%s: %s failed with an unexpected error", name, stage.label)
                        state, err = "failed", error_message(stage.label, exc)
                    done[stage.output] = (state, err)
                if err is not None:
                    out.error = err
                    break
                (out.ran if state == "ran" else out.skipped).append(stage.label)
                progress.stage_done(name, stage.label, state)
            out.seconds = time.monotonic() - t0
            progress.done(name, out.error)
        return outcomes

"""Exception types shared by every layer of pixmuscle.

The command-line interface turns a :class:`PixmuscleError` into a one-line message and exit
code 2, 3 for a :class:`SolverError` (no traceback unless ``--debug``); anything else is a bug and
keeps its traceback.
"""


class PixmuscleError(Exception):
    """Base class of every error pixmuscle raises on purpose."""


class InputError(PixmuscleError, ValueError):
    """Bad user input: a file, a config key or a value. The message names it and what was expected."""


class SchemaError(InputError):
    """A stage file of the wrong schema or version."""


class SolverError(PixmuscleError, RuntimeError):
    """A numerical failure: non-convergence after all cutbacks, inverted material points, ..."""


class SolverGaveUp(SolverError):
    """A linear solve abandoned because its system needs far more iterations than the earlier ones
    (an overshooting Newton update): Newton cuts the load increment back instead of iterating on."""


class OutputError(PixmuscleError, OSError):
    """An output that cannot be written (disk full, read-only file system); nothing partial is left."""


class StaleInputError(InputError):
    """A stage would read the output of an upstream stage made under another config (or from
    other input files) than the current one: the message names the first differing key or file
    and the stage to rerun from."""


class Interrupted(KeyboardInterrupt):
    """The run was stopped by a signal: Ctrl-C (SIGINT) or a batch system's SIGTERM.

    A :class:`KeyboardInterrupt`, so everything that cleans up after Ctrl-C cleans up after
    SIGTERM too. The pipeline fills in the stage that was running and the files that are kept.

    Attributes
    ----------
    signal_name : str
        ``"SIGINT"`` or ``"SIGTERM"``.
    stage : str or None
        Label of the stage that was running (``"solve (coarse)"``), None when unknown.
    kept : list of str
        Output files of the stages that finished (or were up to date) before it.
    """

    def __init__(self, signal_name: str = "SIGINT", stage: str | None = None, kept: list | None = None):
        super().__init__(signal_name)
        self.signal_name = signal_name
        self.stage = stage
        self.kept = list(kept or [])

    @property
    def exit_code(self) -> int:
        """128 + the signal number: 130 for SIGINT, 143 for SIGTERM (the shell's convention)."""
        return 143 if self.signal_name == "SIGTERM" else 130

    def message(self) -> str:
        """One line: what was interrupted, that its partial output is gone, what is kept."""
        how = "terminated (SIGTERM)" if self.signal_name == "SIGTERM" else "interrupted (Ctrl-C)"
        where = f" during {self.stage}" if self.stage else ""
        kept = (f"kept: {', '.join(self.kept)}" if self.kept
                else "no stage had finished in this run")
        return (f"{how}{where}: its partial output was removed (an earlier complete one, if any, is unchanged); "
                f"{kept}")

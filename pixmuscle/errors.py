"""Exception types shared by every layer of pixmuscle.

The command-line interface turns a :class:`PixmuscleError` into a one-line message and exit
code 2 (no traceback unless ``--debug``); anything else is a bug and keeps its traceback.
"""


class PixmuscleError(Exception):
    """Base class of every error pixmuscle raises on purpose."""


class InputError(PixmuscleError, ValueError):
    """Bad user input: a file, a config key or a value. The message names it and what was expected."""


class SchemaError(InputError):
    """A stage file of the wrong schema or version."""


class SolverError(PixmuscleError, RuntimeError):
    """A numerical failure: non-convergence after all cutbacks, inverted material points, ..."""


class OutputError(PixmuscleError, OSError):
    """An output that cannot be written (disk full, read-only file system); nothing partial is left."""

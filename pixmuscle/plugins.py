"""User plugins: Python modules imported before a config is validated, so that what they define
(a material law, a runner, a report section) registers itself and the config can name it.

The top-level key ``plugins`` of a pipeline config lists them::

    plugins: [laws/neo_hooke.py, mylab.laws]

An entry ending in ``.py`` (or naming an existing file) is a file, relative to the config file's
folder; any other entry is the name of an importable module. A plugin's file is an input of the
solve stage and of every stage after it, so that a changed law reruns the solve
(:func:`pixmuscle.plan.plan_case`).

A file plugin is imported as a module named :func:`module_name` (its stem and a hash of its
path), so that objects it defines pickle by reference to a module that :func:`import_plugins`
recreates in a worker process (:mod:`pixmuscle.runners.dask`).
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.util
import sys
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from .errors import InputError


def module_name(path: Path) -> str:
    """Module name under which the plugin file ``path`` is imported (stable for one resolved path)."""
    path = Path(path).resolve()
    tag = hashlib.sha256(str(path).encode()).hexdigest()[:10]
    return f"pixmuscle_plugin_{path.stem}_{tag}"


def _import_file(path: Path):
    name = module_name(path)
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
    except BaseException:
        del sys.modules[name]
        raise
    return module


def import_plugins(files: Iterable[Path | str]) -> None:
    """Import plugin files (resolved paths, as :func:`load_plugins` returns them); those already imported are skipped."""
    for p in files:
        _import_file(Path(p))


def load_plugins(data: Any, config: Path | str) -> tuple[Path, ...]:
    """Import the plugins of a config's ``plugins`` list.

    Parameters
    ----------
    data : list of str or None
        The ``plugins`` value: files (relative to the config's folder) or module names.
    config : path
        The config file (its folder resolves relative paths; its name is in the messages).

    Returns
    -------
    tuple of Path
        The plugins' source files (resolved), for the stage lineage.

    Raises
    ------
    InputError
        One line naming ``plugins[i]`` and the file or module: not a list of strings, a missing
        file, or an import that fails (its exception's type and message).
    """
    config = Path(config)
    if data is None:
        return ()
    if not isinstance(data, list) or not all(isinstance(x, str) and x.strip() for x in data):
        raise InputError(f"{config}: plugins: expected a list of Python files or module names, got {data!r}")
    files = []
    for i, entry in enumerate(data):
        where = f"{config}: plugins[{i}]"
        path = (config.parent / entry).resolve()
        try:
            if entry.endswith(".py") or path.is_file():
                if not path.is_file():
                    raise InputError(f"{where}: {path}: plugin file not found")
                _import_file(path)
                files.append(path)
                continue
            module = importlib.import_module(entry)
        except InputError:
            raise
        except Exception as exc:
            what = path if entry.endswith(".py") or path.is_file() else f"module {entry!r}"
            raise InputError(f"{where}: cannot import {what}: {type(exc).__name__}: {' '.join(str(exc).split())}") from None
        origin = getattr(module, "__file__", None)
        if origin and Path(origin).is_file():
            files.append(Path(origin).resolve())
    return tuple(files)


__all__ = ["load_plugins", "import_plugins", "module_name"]

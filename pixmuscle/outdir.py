"""Output folders: checked before any work, locked while a run writes into them, swept of leftovers.

* :func:`prepare_output_dir` — the folder can be created and written (a file in its place, a
  read-only file system or missing permissions are one :class:`~pixmuscle.errors.InputError`
  line, before any stage runs).
* :func:`output_lock` — an exclusive ``fcntl`` lock on ``<folder>/.pixmuscle.lock`` for the length
  of a run. A second run into the same folder refuses at once, naming the process, host, config
  and start time of the holder. The operating system drops the lock when its holder exits, even
  when killed, so a crashed run never blocks the next one; the lock file itself is left behind
  (an unlocked lock file means nothing).
* :func:`remove_leftovers` — hidden ``.*.partial`` files and folders that a killed write left
  behind (see :func:`pixmuscle.store.write_stage` and :func:`pixmuscle.store.atomic_folder`).
  Only called with the lock held, when no other pixmuscle process can be writing there.
* :func:`hold_folders` — both, for every folder of a run.
* :func:`check_free_space` — refuse a long stage whose output would not fit on the disk.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import errno
import fcntl
import json
import logging
import os
import shutil
import socket
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

from .errors import InputError, OutputError

_LOG = logging.getLogger(__name__)

LOCK_NAME = ".pixmuscle.lock"
#: errors of a file system refusing a write (as opposed to a bug or a missing input)
WRITE_ERRNOS = (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM, errno.EIO, errno.EFBIG)
PARTIAL_SUFFIX = ".partial"


def _mb(n: float) -> str:
    return f"{n / 1e6:.1f} MB"


def free_bytes(path: str | os.PathLike) -> int:
    """Free space (bytes) on the file system holding ``path`` or its nearest existing parent."""
    p = Path(path).absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    return shutil.disk_usage(p).free


def prepare_output_dir(path: str | os.PathLike, what: str = "output_dir") -> Path:
    """Create the output folder if needed and check that files can be written in it.

    Parameters
    ----------
    path : path-like
        The folder.
    what : str
        Name of the setting for messages (``output_dir``, ``--output``).

    Returns
    -------
    pathlib.Path
        The folder.

    Raises
    ------
    InputError
        The path (or a parent) is a file, or the folder cannot be created or written.
    """
    path = Path(path)
    for p in (path, *path.parents):
        if p.exists():
            if not p.is_dir():
                kind = "is a file" if p == path else f"cannot be created: {p} is a file"
                raise InputError(f"{what} {path}: {kind}, expected a folder")
            break
    try:
        path.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=f".pixmuscle-write-test.{socket.gethostname()}.{os.getpid()}.",
                                     suffix=PARTIAL_SUFFIX, dir=path)
        os.close(fd)
        with contextlib.suppress(FileNotFoundError):
            os.unlink(probe)
    except OSError as exc:
        raise InputError(f"{what} {path}: not writable ({exc.strerror or exc})") from None
    return path


def _holder(lock_path: Path) -> str:
    try:
        info = json.loads(lock_path.read_text())
        argv = list(info.get("argv") or [])
        cmd = " ".join([Path(argv[0]).name, *argv[1:]]) if argv else "?"
        what = f"config {info['config']}" if info.get("config") else cmd
        return f"pid {info.get('pid')} on {info.get('host')}, {what}, started {info.get('started_utc')}"
    except (OSError, ValueError):
        return "another process"


@contextlib.contextmanager
def output_lock(folder: str | os.PathLike, config: str | os.PathLike | None = None) -> Iterator[Path]:
    """Hold an exclusive lock on an output folder for the duration of a ``with`` block.

    Raises
    ------
    InputError
        Another run holds the lock (the message names it).
    """
    folder = Path(folder)
    lock_path = folder / LOCK_NAME
    fd = os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            if exc.errno not in (errno.EWOULDBLOCK, errno.EACCES, errno.EAGAIN):
                raise
            raise InputError(f"output_dir {folder}: in use by another pixmuscle run ({_holder(lock_path)}); "
                             "wait for it to finish or choose another output_dir") from None
        info = {"pid": os.getpid(), "host": socket.gethostname(), "config": str(config) if config else None,
                "argv": sys.argv, "started_utc": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")}
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(info).encode(), 0)
        yield lock_path
    finally:
        os.close(fd)  # releases the lock


@contextlib.contextmanager
def hold_folders(folders) -> Iterator[list[Path]]:
    """Lock every folder of a run (:func:`output_lock`, in a fixed order) and sweep its leftovers.

    Raises
    ------
    InputError
        One of them is in use by another run (nothing was changed).
    """
    folders = sorted({Path(f) for f in folders})
    with contextlib.ExitStack() as stack:
        for f in folders:
            prepare_output_dir(f)
            stack.enter_context(output_lock(f))
        for f in folders:
            remove_leftovers(f)
        yield folders


def _writer_alive(p: Path) -> bool:
    """``.<name>.<host>.<pid>.<random>.partial`` of a process of this host that still runs."""
    parts = p.name[: -len(PARTIAL_SUFFIX)].rsplit(".", 2)
    if len(parts) != 3 or not parts[1].isdigit() or not parts[0].endswith("." + socket.gethostname()):
        return False
    try:
        os.kill(int(parts[1]), 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_leftovers(folder: str | os.PathLike) -> list[Path]:
    """Remove hidden ``.*.partial`` files and folders in ``folder`` (left by killed writes).

    Call only with :func:`output_lock` held; temporaries of a live process of this host are kept.
    Returns the removed paths (they are logged).
    """
    removed = []
    for p in sorted(Path(folder).glob(f".*{PARTIAL_SUFFIX}")):  # temporaries sit beside their target
        if _writer_alive(p):  # e.g. a single-stage command writing here right now
            continue
        try:
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p)
            else:
                p.unlink()
        except FileNotFoundError:
            continue
        removed.append(p)
    if removed:
        _LOG.info("removed %d unfinished file(s) left by an interrupted run: %s", len(removed),
                  ", ".join(str(p.relative_to(folder)) for p in removed[:5]) + (" ..." if len(removed) > 5 else ""))
    return removed


def check_free_space(path: str | os.PathLike, nbytes: float, what: str) -> None:
    """Refuse to start a stage whose output (about ``nbytes`` bytes) does not fit next to ``path``.

    Raises
    ------
    OutputError
        Less free space than ``nbytes`` on that file system.
    """
    free = free_bytes(Path(path).parent)
    if free < nbytes:
        raise OutputError(f"{path}: not enough free disk space for {what}: needs about {_mb(nbytes)}, "
                          f"{_mb(free)} free")


def describe_os_error(exc: OSError, path: str | os.PathLike | None = None, verb: str | None = "cannot write") -> str:
    """One line for an operating-system error: the path, the reason and (disk full) the free space."""
    p = path if path is not None else (exc.filename or "?")
    text = f"{p}: {verb} ({exc.strerror or exc})" if verb else f"{p}: {exc.strerror or exc}"
    if exc.errno in (errno.ENOSPC, errno.EDQUOT) and p != "?":
        with contextlib.suppress(OSError):
            text += f"; {_mb(free_bytes(p))} free on that disk"
    return text

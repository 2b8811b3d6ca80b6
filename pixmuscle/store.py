"""HDF5 stage files: schema and version, units, config and provenance, atomic writes.

Every pipeline stage writes exactly one HDF5 file through :func:`write_stage`. The file is built
in memory (so an I/O error can never happen inside the HDF5 library, whose failing ``close`` on a
full disk may crash the interpreter), its size is checked against the free space, then written to a
hidden temporary name ``.<name>.<pid>.<random>.partial`` in the destination folder and renamed over
the destination only when complete (``os.replace`` is atomic on POSIX), so a killed run never
leaves a file that looks finished. A write failure (disk full, read-only file system) is an
:class:`~pixmuscle.errors.OutputError` naming the path and the free space, with nothing left
behind; temporary files of a process that no longer runs are removed by the next write of the
same file. :func:`atomic_folder` does the same for a folder of outputs (the report). Root
attributes:

``schema`` (str), ``schema_version`` (int), ``units`` (JSON), ``config`` (YAML of the config
section that produced the file), ``provenance`` (JSON, :func:`provenance`: package version and the
git commit of its source tree, the versions of the numerical libraries used, UTC time, command line,
SHA-256 and path of every input file (also relative to the config file's folder), and a hash of the
config section).
"""

from __future__ import annotations

import contextlib
import contextvars
import datetime as _dt
import functools
import hashlib
import io
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import yaml

from . import __version__
from .errors import InputError, OutputError, SchemaError

DEFAULT_UNITS = {"length": "cm", "force": "N", "stress": "N/cm^2", "volume": "cm^3"}


def sha256_file(path: str | os.PathLike, chunk: int = 1 << 20) -> str:
    """SHA-256 hex digest of a file's bytes; of a folder (a DICOM series), of its files' relative
    names and digests, so that a file added, removed, renamed or changed gives another digest."""
    if os.path.isdir(path):
        root = Path(path)
        h = hashlib.sha256()
        for p in sorted(q for q in root.rglob("*") if q.is_file()):
            h.update(f"{p.relative_to(root).as_posix()}\0{sha256_file(p, chunk)}\n".encode())
        return h.hexdigest()
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while True:
            block = f.read(chunk)
            if not block:
                break
            h.update(block)
    return h.hexdigest()


def config_hash(config: Any) -> str:
    """Stable SHA-256 of a config section (plain data), independent of key order."""
    text = json.dumps(_plain(config), sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()


def _plain(obj: Any) -> Any:
    """Convert dataclasses, paths, tuples and numpy scalars to YAML/JSON-friendly data."""
    import dataclasses

    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        named = getattr(obj, "registry_key", None)  # a registered entry: {key: name, …options}
        head = {named[0]: named[1]} if named else {}
        return head | {f.name: _plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, Mapping):
        return {(k if isinstance(k, (str, int)) else str(k)): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    return obj


#: folder of the config file whose stage is being written (paths in the provenance are also given relative to it)
_CONFIG_DIR: contextvars.ContextVar[Path | None] = contextvars.ContextVar("pixmuscle_config_dir", default=None)


@contextlib.contextmanager
def config_folder(path: str | os.PathLike | None) -> Iterator[None]:
    """Within this block, stage files record their input paths relative to ``path`` too (the folder
    of the config file, against which the config's own paths are resolved)."""
    token = _CONFIG_DIR.set(None if path is None else Path(path).resolve())
    try:
        yield
    finally:
        _CONFIG_DIR.reset(token)


#: plugin files of the stage being written (recorded among its inputs)
_PLUGINS: contextvars.ContextVar[tuple] = contextvars.ContextVar("pixmuscle_plugins", default=())


@contextlib.contextmanager
def plugin_inputs(files: Sequence[str | os.PathLike]) -> Iterator[None]:
    """Within this block, stage files record the SHA-256 of these plugin files among their inputs
    (:mod:`pixmuscle.plugins`), so that a changed plugin makes the stage out of date."""
    token = _PLUGINS.set(tuple(files))
    try:
        yield
    finally:
        _PLUGINS.reset(token)


@functools.lru_cache(maxsize=1)
def source_commit() -> dict | None:
    """Git commit of the pixmuscle source tree, when the package runs from a git checkout.

    Returns
    -------
    dict or None
        ``{"commit": 40-hex SHA-1, "modified": True when tracked files under pixmuscle/ differ from it}``;
        None for an installed (non-checkout) package or without git.
    """
    root = Path(__file__).resolve().parent.parent
    if not (root / ".git").exists():
        return None
    def git(*args):
        return subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True, timeout=10)
    try:
        head = git("rev-parse", "HEAD")
        if head.returncode != 0:
            return None
        status = git("status", "--porcelain", "--untracked-files=no", "--", "pixmuscle")
    except (OSError, subprocess.SubprocessError):
        return None
    return {"commit": head.stdout.strip(), "modified": bool(status.stdout.strip()) if status.returncode == 0 else None}


def _dist_version(name: str) -> str | None:
    from importlib import metadata

    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return None


def _mkl_version() -> str | None:
    """MKL's own version string, once PARDISO was loaded in this process (None: not used)."""
    pardiso = sys.modules.get("pixmuscle.mechanics.pardiso")
    lib = getattr(pardiso, "_LIB", None)
    if lib is None:
        return None
    try:
        import ctypes

        buf = ctypes.create_string_buffer(256)
        lib.MKL_Get_Version_String(buf, len(buf))
        text = buf.value.decode(errors="replace").strip()
    except (AttributeError, OSError):
        text = ""
    return text or f"mkl {_dist_version('mkl') or '?'}"


def library_versions() -> dict[str, str]:
    """Versions of the libraries whose numbers shape the results.

    numpy, scipy, pyamg, h5py and meshio always (dependencies); MKL (PARDISO), VTK and petsc4py
    only when this process used them. Missing packages are left out.
    """
    out = {"python": sys.version.split()[0]}
    for name in ("numpy", "scipy", "pyamg", "h5py", "meshio"):
        v = _dist_version(name)
        if v is not None:
            out[name] = v
    mkl = _mkl_version()
    if mkl is not None:
        out["mkl_pardiso"] = mkl
    if "vtkmodules" in sys.modules:
        out["vtk"] = _dist_version("vtk") or getattr(sys.modules["vtkmodules"], "__version__", "?")
    if "petsc4py" in sys.modules:
        out["petsc4py"] = _dist_version("petsc4py") or "?"
        PETSc = sys.modules.get("petsc4py.PETSc")  # imported means initialised; its version, if so
        if PETSc is not None:
            out["petsc"] = ".".join(map(str, PETSc.Sys.getVersion()))
    return out


def provenance(inputs: Sequence[str | os.PathLike] = (), config: Any = None) -> dict:
    """Provenance record of a stage file.

    Keys: ``package``, ``version``, ``git`` (:func:`source_commit`), ``libraries``
    (:func:`library_versions`), ``created_utc``, ``argv``, ``python``, ``inputs`` (absolute path →
    SHA-256), ``config_dir`` and ``inputs_relative`` (path relative to the config file's folder →
    SHA-256; only inside :func:`config_folder`), ``config_sha256``. The plugin files of
    :func:`plugin_inputs` are inputs too.
    """
    hashes = {str(Path(p)): sha256_file(p) for p in (*inputs, *_PLUGINS.get())}
    rec = {
        "package": "pixmuscle",
        "version": __version__,
        "git": source_commit(),
        "libraries": library_versions(),
        "created_utc": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "argv": list(sys.argv),
        "python": sys.version.split()[0],
        "inputs": hashes,
        "config_sha256": config_hash(config) if config is not None else None,
    }
    base = _CONFIG_DIR.get()
    if base is not None:
        rec["config_dir"] = str(base)
        rec["inputs_relative"] = {os.path.relpath(Path(p).resolve(), base): sha for p, sha in hashes.items()}
    return rec


def write_stage(
    path: str | os.PathLike,
    *,
    schema: str,
    version: int,
    write: Callable[[h5py.File], None],
    config: Any = None,
    inputs: Sequence[str | os.PathLike] = (),
    units: Mapping[str, str] | None = None,
    attrs: Mapping[str, Any] | None = None,
) -> Path:
    """Write one stage file atomically.

    Parameters
    ----------
    path : path-like
        Destination ``.h5`` file; its folder is created if needed.
    schema, version : str, int
        Schema name (e.g. ``"pixmuscle.model"``) and version stored as root attributes.
    write : callable
        ``write(f)`` fills the open :class:`h5py.File`.
    config : dataclass or mapping, optional
        The config section that produced the file (stored as YAML text).
    inputs : sequence of path-like
        Files read by the stage; their SHA-256 go into the provenance.
    units : mapping, optional
        Unit names; defaults to cm, N, N/cm².
    attrs : mapping, optional
        Extra root attributes.

    Returns
    -------
    pathlib.Path
        The final path.
    """
    path = Path(path)
    buf = io.BytesIO()
    with h5py.File(buf, "w") as f:
        f.attrs["schema"] = schema
        f.attrs["schema_version"] = int(version)
        f.attrs["units"] = json.dumps(dict(units or DEFAULT_UNITS))
        f.attrs["config"] = yaml.safe_dump(_plain(config), sort_keys=False) if config is not None else ""
        f.attrs["provenance"] = json.dumps(provenance(inputs, config))
        for k, v in (attrs or {}).items():
            f.attrs[k] = v
        write(f)
    write_bytes_atomic(path, buf.getbuffer())
    return path




def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _temp_prefix(name: str) -> str:
    return f".{name}.{socket.gethostname()}.{os.getpid()}."


def temporary_path(path: str | os.PathLike, tag: str) -> Path:
    """A hidden temporary beside ``path`` for this process, ``.<name>.<host>.<pid>.<tag>.partial``:
    :func:`remove_dead_temporaries` removes it once this process has gone (a killed run)."""
    p = Path(path)
    return p.with_name(f"{_temp_prefix(p.name)}{tag}.partial")


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_dead_temporaries(folder: Path, name: str) -> None:
    """Remove ``.<name>.<host>.<pid>.*.partial`` left in ``folder`` by a process of this host that no
    longer runs (a killed write). Temporaries of live processes and other hosts are kept."""
    import glob

    host = socket.gethostname()
    for p in folder.glob(f".{glob.escape(name)}.*.partial"):
        middle = p.name[len(name) + 2:-len(".partial")]  # <host>.<pid>.<random>
        parts = middle.rsplit(".", 2)
        if len(parts) != 3 or parts[0] != host or not parts[1].isdigit() or _pid_alive(int(parts[1])):
            continue
        with contextlib.suppress(FileNotFoundError):
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p)
            else:
                p.unlink()


def write_bytes_atomic(path: str | os.PathLike, data: bytes | memoryview) -> Path:
    """Write ``data`` to ``path`` through a hidden temporary file and ``os.replace``.

    The free space is checked first; any write error removes the temporary file.

    Raises
    ------
    OutputError
        Not enough free space, or the file system refused the write (the message names the path,
        the reason and the free space).
    """
    from .outdir import WRITE_ERRNOS, describe_os_error, free_bytes, prepare_output_dir

    path = Path(path)
    prepare_output_dir(path.parent, "output folder")
    remove_dead_temporaries(path.parent, path.name)
    size = len(data)
    free = free_bytes(path.parent)
    if size > free:
        raise OutputError(f"{path}: not enough free disk space: the file needs {size / 1e6:.1f} MB, "
                          f"{free / 1e6:.1f} MB free; nothing was written")
    tmp = None
    try:
        fd, tmp = tempfile.mkstemp(prefix=_temp_prefix(path.name), suffix=".partial", dir=path.parent)
        os.fchmod(fd, 0o666 & ~_umask())  # mkstemp makes 0600; a stage file is an ordinary file
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except OSError as exc:
        if tmp is not None:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)
        if exc.errno in WRITE_ERRNOS:
            raise OutputError(describe_os_error(exc, path) + "; nothing was written") from None
        raise
    except BaseException:
        if tmp is not None:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)
        raise
    return path


@contextlib.contextmanager
def atomic_folder(path: str | os.PathLike) -> Iterator[Path]:
    """Build a folder of outputs under a hidden temporary name and put it in place as a unit.

    ``with atomic_folder("out/report") as tmp:`` — write every file into ``tmp``; when the block
    ends without error the old folder (if any) is moved aside and ``tmp`` renamed to ``path``, so a
    reader sees either the old folder or the new one, never a mix. On an error (or a kill) the
    temporary folder is removed (or, after a kill, by the next call or the next ``pixmuscle run``)
    and the old folder is left as it was.

    Raises
    ------
    OutputError
        The file system refused a write (disk full, read-only).
    """
    from .outdir import WRITE_ERRNOS, describe_os_error, prepare_output_dir

    path = Path(path)
    if path.exists() and not path.is_dir():
        raise InputError(f"{path}: is a file, expected a folder (or a path that does not exist)")
    prepare_output_dir(path.parent, "output folder")
    remove_dead_temporaries(path.parent, path.name)
    tmp = Path(tempfile.mkdtemp(prefix=_temp_prefix(path.name), suffix=".partial", dir=path.parent))
    os.chmod(tmp, 0o777 & ~_umask())  # mkdtemp makes 0700
    try:
        try:
            yield tmp
        except OSError as exc:
            if exc.errno in WRITE_ERRNOS:
                raise OutputError(describe_os_error(exc, path) + "; nothing of it was kept, the previous one (if any) "
                                  "is unchanged") from None
            raise
        old = None
        if path.exists():
            old = Path(tempfile.mkdtemp(prefix=_temp_prefix(path.name), suffix=".partial", dir=path.parent))
            os.replace(path, old / path.name)
        os.replace(tmp, path)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


@contextlib.contextmanager
def open_stage(path: str | os.PathLike, *, schema: str, version: int) -> Iterator[h5py.File]:
    """Open a stage file read-only after checking its schema and version.

    Raises
    ------
    InputError
        The file is missing or not HDF5.
    SchemaError
        The file is not a pixmuscle file, or has another schema or version.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: file not found (expected a '{schema}' v{version} HDF5 file)")
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise InputError(f"{path}: not a readable HDF5 file ({exc})") from None
    try:
        got = f.attrs.get("schema")
        got_v = f.attrs.get("schema_version")
        if got is None:
            raise SchemaError(f"{path}: not a pixmuscle stage file (no 'schema' attribute); expected '{schema}' v{version}")
        if isinstance(got, bytes):
            got = got.decode()
        if got != schema or int(got_v) != int(version):
            raise SchemaError(f"{path}: file has schema '{got}' v{got_v}, expected '{schema}' v{version}")
        yield f
    finally:
        f.close()


def read_meta(path: str | os.PathLike) -> dict:
    """Root metadata of a stage file: schema, version, units, config (text) and provenance (dict)."""
    with h5py.File(path, "r") as f:
        a = f.attrs
        return {
            "schema": a.get("schema"),
            "schema_version": int(a.get("schema_version", -1)),
            "units": json.loads(a.get("units", "{}")),
            "config": a.get("config", ""),
            "provenance": json.loads(a.get("provenance", "{}")),
        }


def write_dataset(group: h5py.Group, name: str, array: Any, units: str | None = None, **attrs: Any) -> h5py.Dataset:
    """Create a dataset (gzip-compressed if large) with an optional ``units`` attribute."""
    arr = np.asarray(array)
    if arr.dtype.kind == "U":
        arr = arr.astype(h5py.string_dtype())
    kw = {"compression": "gzip", "compression_opts": 4} if arr.size > 4096 else {}
    ds = group.create_dataset(name, data=arr, **kw)
    if units is not None:
        ds.attrs["units"] = units
    for k, v in attrs.items():
        ds.attrs[k] = v
    return ds


def read_strings(ds: h5py.Dataset) -> list[str]:
    """Read a dataset of strings as a list of Python ``str``."""
    return [s.decode() if isinstance(s, bytes) else str(s) for s in ds[()]]

"""HDF5 stage files: schema and version, units, config and provenance, atomic writes.

Every pipeline stage writes exactly one HDF5 file through :func:`write_stage`. The file is first
written to a temporary name in the destination folder and renamed over the destination only when
complete (``os.replace`` is atomic on POSIX), so a killed run never leaves a file that looks
finished. Root attributes:

``schema`` (str), ``schema_version`` (int), ``units`` (JSON), ``config`` (YAML of the config
section that produced the file), ``provenance`` (JSON: package version, UTC time, command line,
SHA-256 and path of every input file, and a hash of the config section).
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import hashlib
import json
import os
import sys
import tempfile
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import yaml

from . import __version__
from .errors import InputError, SchemaError

DEFAULT_UNITS = {"length": "cm", "force": "N", "stress": "N/cm^2", "volume": "cm^3"}


def sha256_file(path: str | os.PathLike, chunk: int = 1 << 20) -> str:
    """SHA-256 hex digest of a file's bytes."""
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
        return {f.name: _plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
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


def provenance(inputs: Sequence[str | os.PathLike] = (), config: Any = None) -> dict:
    """Provenance record: package version, UTC time, command line, input hashes, config hash."""
    return {
        "package": "pixmuscle",
        "version": __version__,
        "created_utc": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "argv": list(sys.argv),
        "python": sys.version.split()[0],
        "inputs": {str(Path(p)): sha256_file(p) for p in inputs},
        "config_sha256": config_hash(config) if config is not None else None,
    }


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
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".partial", dir=path.parent)
    os.close(fd)
    try:
        with h5py.File(tmp, "w") as f:
            f.attrs["schema"] = schema
            f.attrs["schema_version"] = int(version)
            f.attrs["units"] = json.dumps(dict(units or DEFAULT_UNITS))
            f.attrs["config"] = yaml.safe_dump(_plain(config), sort_keys=False) if config is not None else ""
            f.attrs["provenance"] = json.dumps(provenance(inputs, config))
            for k, v in (attrs or {}).items():
                f.attrs[k] = v
            write(f)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    return path


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

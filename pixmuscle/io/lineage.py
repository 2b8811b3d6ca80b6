"""Stage records carried by every stage file: the stage's warnings, the upstream stages, ``synthetic``.

Each stage file gets four root attributes besides those of :func:`pixmuscle.store.write_stage`:

``stage``      the stage that wrote it (segment, build-model, coarsen, solve);
``warnings``   JSON list of the warnings logged while the stage ran (``pixmuscle`` logger);
``stages``     JSON list of records of the upstream stage files, oldest first: ``stage``, ``schema``,
               ``file``, ``config`` (YAML text), ``provenance``, ``warnings``, ``synthetic``;
``synthetic``  bool: the inputs are synthetic phantoms (said by the config, by an upstream stage
               file, or by a phantom's ``<prefix>_truth.json`` beside an input image).

So ``results.h5`` alone tells the report the configuration, provenance and warnings of every stage
that led to it.
"""

from __future__ import annotations

import contextlib
import json
import logging
from collections.abc import Iterator, Sequence
from pathlib import Path

import h5py

_ROOT = "pixmuscle"


class _Collect(logging.Handler):
    def __init__(self, sink: list):
        super().__init__(level=logging.WARNING)
        self.sink = sink

    def emit(self, record: logging.LogRecord) -> None:
        try:
            msg = record.getMessage()
        except Exception:  # a bad format string must not break the stage
            msg = str(record.msg)
        if msg not in self.sink:
            self.sink.append(msg)


@contextlib.contextmanager
def capture_warnings() -> Iterator[list[str]]:
    """Collect the messages of WARNING (and higher) records of the ``pixmuscle`` loggers.

    Yields
    ------
    list of str
        Filled while the block runs (duplicates dropped); the records still reach the other
        handlers (the terminal).
    """
    sink: list[str] = []
    handler = _Collect(sink)
    logger = logging.getLogger(_ROOT)
    logger.addHandler(handler)
    try:
        yield sink
    finally:
        logger.removeHandler(handler)


def _text(v) -> str:
    return v.decode() if isinstance(v, bytes) else str(v)


def _json(v, default):
    if v is None:
        return default
    try:
        return json.loads(_text(v))
    except json.JSONDecodeError:
        return default


def stage_record(path: str | Path) -> list[dict] | None:
    """Records of a stage file and of its own upstream stages (oldest first); None when ``path``
    is not a pixmuscle stage file."""
    path = Path(path)
    try:
        with h5py.File(path, "r") as f:
            a = f.attrs
            if "schema" not in a:
                return None
            own = {
                "stage": _text(a.get("stage", a["schema"])), "schema": _text(a["schema"]), "file": str(path), "config": _text(a.get("config", "")),
                "provenance": _json(a.get("provenance"), {}), "warnings": _json(a.get("warnings"), []),
                "synthetic": _text(a.get("synthetic", "")).lower() in ("true", "1", "yes"),
            }
            upstream = _json(a.get("stages"), [])
    except OSError:
        return None
    return [r for r in upstream if isinstance(r, dict)] + [own]


def phantom_truth(path: str | Path) -> Path | None:
    """The ``<prefix>_truth.json`` of a pixmuscle phantom that ``path`` belongs to, if it says
    ``"synthetic": true`` (files written by :mod:`pixmuscle.synth.write`)."""
    path = Path(path)
    with contextlib.suppress(OSError):
        for truth in path.parent.glob("*_truth.json"):
            prefix = truth.name[: -len("_truth.json")]
            if path.name.startswith(prefix + "_"):
                with contextlib.suppress(OSError, json.JSONDecodeError):
                    if json.loads(truth.read_text()).get("synthetic") is True:
                        return truth
    return None


def stage_attrs(stage: str, inputs: Sequence[str | Path], warnings: Sequence[str] = (), *,
                synthetic: bool = False) -> dict:
    """Root attributes ``stage``, ``warnings``, ``stages`` and ``synthetic`` of a stage file made from
    ``inputs``.

    Parameters
    ----------
    stage : str
        Name of the stage writing the file.
    inputs : sequence of path-like
        Files the stage read: upstream stage files contribute their records, images their
        phantom flag.
    warnings : sequence of str
        The stage's own warnings (:func:`capture_warnings`).
    synthetic : bool
        The config says the inputs are synthetic.
    """
    records: list[dict] = []
    seen = set()
    for p in inputs:
        recs = stage_record(p) if Path(p).suffix in (".h5", ".hdf5") else None
        if recs is None:
            synthetic = synthetic or phantom_truth(p) is not None
            continue
        for r in recs:
            key = (r["file"], r["provenance"].get("created_utc"))
            if key not in seen:
                seen.add(key)
                records.append(r)
            synthetic = synthetic or bool(r.get("synthetic"))
    return {"stage": stage, "warnings": json.dumps(list(warnings)), "stages": json.dumps(records, default=str),
            "synthetic": bool(synthetic)}

"""Command-line overrides of a pipeline YAML: ``--set solve.steps=5``.

The value is read as YAML (``5`` → int, ``0.5`` → float, ``[x, y]`` → list, ``true`` → bool,
anything else → text) and set into the raw config mapping before validation, so it is typed and
checked exactly like the same key written in the file (unknown keys, types, ranges, with the key
path in the message).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import yaml

from .errors import InputError
from .study import set_key


def parse_override(text: str) -> tuple[str, Any]:
    """``"a.b.c=value"`` → (``"a.b.c"``, value read as YAML).

    Raises
    ------
    InputError
        No ``=``, an empty key or key part, or a value that is not valid YAML.
    """
    key, sep, value = text.partition("=")
    key = key.strip()
    if not sep or not key or any(not p for p in key.split(".")):
        raise InputError(f"--set {text!r}: expected KEY.PATH=VALUE, e.g. --set solve.steps=5")
    try:
        parsed = yaml.safe_load(value) if value.strip() else None
    except yaml.YAMLError as exc:
        raise InputError(f"--set {key}: the value {value!r} is not valid YAML ({str(exc).splitlines()[0]})") from None
    return key, parsed


def apply_overrides(raw: dict, overrides: Sequence[str | tuple[str, Any]]) -> dict:
    """A copy of ``raw`` with every override set (later ones win)."""
    out = raw
    for o in overrides:
        key, value = parse_override(o) if isinstance(o, str) else o
        out = set_key(out, key, value, "--set")
    return out

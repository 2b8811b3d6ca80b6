"""YAML configuration → validated, typed, frozen dataclasses.

Each stage owns its section dataclass (``segment``, ``build_model``, ``coarsen``, ``solve``,
``report``); :func:`parse_section` validates plain data against such a dataclass from its type
hints and field metadata, and :func:`load_config` assembles the whole file.

Field metadata understood by the validator:

``range``  (lo, hi) inclusive bounds, either may be None;
``gt``     strict lower bound;
``must_exist``  for ``Path`` fields: the file must exist;
``doc``    one-line description with units (used in error messages and ``pixmuscle config --help``);
``registry``  a :class:`pixmuscle.registry.Registry`: the value is ``{key: name, …options}``,
           validated by the chosen entry's own dataclass (``default``: the entry and values used
           when the mapping names none).

Every error is an :class:`~pixmuscle.errors.InputError` naming the key path
(``solve.activation.to``), what was expected and what was found.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import types
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal, Union

import yaml

from .errors import InputError

_MISSING = dataclasses.MISSING


def _typename(tp: Any) -> str:
    origin = typing.get_origin(tp)
    if tp is float:
        return "a number"
    if tp is int:
        return "an integer"
    if tp is bool:
        return "true or false"
    if tp is str:
        return "a string"
    if tp is Path:
        return "a file path"
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in typing.get_args(tp))
    if origin in (list, tuple):
        args = typing.get_args(tp)
        return f"a list of {_typename(args[0])}" if args else "a list"
    if origin in (dict, Mapping):
        return "a mapping"
    if origin in (Union, types.UnionType):
        return " or ".join(_typename(a) for a in typing.get_args(tp) if a is not type(None))
    if dataclasses.is_dataclass(tp):
        return "a mapping"
    return getattr(tp, "__name__", str(tp))


def _got(value: Any) -> str:
    text = repr(value)
    return text if len(text) < 60 else text[:57] + "..."


def _coerce(value: Any, tp: Any, where: str, base_dir: Path, meta: Mapping) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if meta.get("registry") is not None:  # an extension point: {key: name, …options} of the chosen entry
        return meta["registry"].parse(value, where, base_dir, default=meta.get("default"))
    if tp is Any:
        return value
    if origin in (Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        real = [a for a in args if a is not type(None)]
        if len(real) == 1:  # Optional[X]: X's own, more specific message
            return _coerce(value, real[0], where, base_dir, meta)
        errors = {}
        for a in args:
            if a is type(None):
                continue
            try:
                return _coerce(value, a, where, base_dir, meta)
            except InputError as exc:
                errors[a] = exc
        number = isinstance(value, (int, float)) and not isinstance(value, bool)
        for a in (float, int):  # a number that fails as a number: that message is the specific one
            if number and a in errors:
                raise errors[a]
        raise InputError(f"{where}: expected {_typename(tp)}, got {_got(value)}")
    if origin is Literal:
        if isinstance(value, str) and value not in args:  # choices are case-insensitive
            value = next((a for a in args if isinstance(a, str) and a.lower() == value.lower()), value)
        if value not in args:
            close = difflib.get_close_matches(str(value), [str(a) for a in args], n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise InputError(f"{where}: expected {_typename(tp)}, got {_got(value)}{hint}")
        return value
    if dataclasses.is_dataclass(tp):
        return parse_section(tp, value, where, base_dir)
    if tp is bool:
        if not isinstance(value, bool):
            raise InputError(f"{where}: expected true or false, got {_got(value)}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise InputError(f"{where}: expected an integer, got {_got(value)}")
        _check_range(value, where, meta)
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise InputError(f"{where}: expected a number, got {_got(value)}")
        value = float(value)
        if not math.isfinite(value):
            raise InputError(f"{where}: expected a finite number, got {value}")
        _check_range(value, where, meta)
        return value
    if tp is str:
        if not isinstance(value, str):
            raise InputError(f"{where}: expected a string, got {_got(value)}")
        return value
    if tp is Path:
        if not isinstance(value, (str, Path)):
            raise InputError(f"{where}: expected a file path, got {_got(value)}")
        p = Path(value).expanduser()
        if not p.is_absolute():
            p = (base_dir / p).resolve()
        if meta.get("must_exist") and not p.exists():
            raise InputError(f"{where}: file not found: {p}")
        return p
    if origin in (list, tuple):
        item0 = args[0] if args else Any
        open_ended = origin is list or (origin is tuple and (not args or args[-1] is Ellipsis))
        if open_ended and item0 in (float, int) and isinstance(value, (int, float)) and not isinstance(value, bool):
            value = [value]  # one number where a list of numbers is expected ("1 value or K")
        elif (open_ended and typing.get_origin(item0) in (list, tuple) and isinstance(value, (list, tuple)) and value
              and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)):
            value = [value]  # one point where a list of points is expected
        if isinstance(value, (str, bytes)) or not isinstance(value, (list, tuple)):
            raise InputError(f"{where}: expected {_typename(tp)}, got {_got(value)}")
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(value) != len(args):
                raise InputError(f"{where}: expected a list of {len(args)} items, got {len(value)}")
            return tuple(_coerce(v, a, f"{where}[{i}]", base_dir, meta) for i, (v, a) in enumerate(zip(value, args, strict=True)))
        item = args[0] if args else Any
        out = [_coerce(v, item, f"{where}[{i}]", base_dir, meta) for i, v in enumerate(value)]
        return tuple(out) if origin is tuple else out
    if origin in (dict, Mapping):
        if not isinstance(value, Mapping):
            raise InputError(f"{where}: expected a mapping, got {_got(value)}")
        kt, vt = args if args else (Any, Any)
        return {
            _coerce(k, kt, f"{where} key {k!r}", base_dir, {}): _coerce(v, vt, f"{where}.{k}", base_dir, meta)
            for k, v in value.items()
        }
    raise TypeError(f"config field {where}: unsupported type {tp!r}")  # programming error


def _check_range(value: float, where: str, meta: Mapping) -> None:
    lo, hi = meta.get("range", (None, None))
    gt = meta.get("gt")
    if gt is not None and not value > gt:
        raise InputError(f"{where}: expected a value > {gt}, got {value}")
    if lo is not None and value < lo:
        raise InputError(f"{where}: expected a value ≥ {lo}, got {value}")
    if hi is not None and value > hi:
        raise InputError(f"{where}: expected a value ≤ {hi}, got {value}")


def parse_section(cls: type, data: Mapping | None, where: str, base_dir: Path | str = ".") -> Any:
    """Validate plain data against a dataclass and build it.

    Parameters
    ----------
    cls : dataclass type
        The section schema.
    data : mapping or None
        Parsed YAML; ``None`` means all defaults.
    where : str
        Key path of this section, used in messages (``"solve"``).
    base_dir : path
        Folder that relative paths are resolved against (the config file's folder).

    Raises
    ------
    InputError
        Unknown key (with the closest valid key), missing required key, wrong type or out of range.
    """
    base_dir = Path(base_dir)
    if data is None:
        data = {}
    if not isinstance(data, Mapping):
        raise InputError(f"{where}: expected a mapping of keys, got {_got(data)}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = [k for k in data if k not in fields]
    if unknown:
        k = unknown[0]
        close = difflib.get_close_matches(str(k), list(fields), n=1)
        hint = f"; did you mean '{close[0]}'?" if close else f"; valid keys: {', '.join(fields)}"
        raise InputError(f"{where}.{k}: unknown key{hint}")
    kwargs = {}
    for name, f in fields.items():
        key = f"{where}.{name}" if where else name
        if name in data:
            kwargs[name] = _coerce(data[name], hints[name], key, base_dir, f.metadata)
        elif f.default is _MISSING and f.default_factory is _MISSING:
            doc = f.metadata.get("doc")
            raise InputError(f"{key}: required key is missing" + (f" ({doc})" if doc else ""))
    try:
        return cls(**kwargs)
    except InputError:
        raise
    except (TypeError, ValueError) as exc:
        raise InputError(f"{where}: {exc}") from None


def check_key(cls: type, dotted: str, value: Any, where: str, base_dir: Path | str = ".") -> Any:
    """Check that ``dotted`` names a key of the section dataclass ``cls`` and that ``value`` has its
    type and range, without the rest of the section (a study's ``vary`` keys, before any case).

    Parameters
    ----------
    cls : dataclass type
        The section schema (``SolveConfig``).
    dotted : str
        Key path inside the section (``"materials.muscle.sigma_max"``); it may continue into a
        mapping-typed field (``"activation.to"``).
    value : object
        The value the key would get.
    where : str
        Prefix of the key path in messages (``"study.vary.solve"``).

    Returns
    -------
    object
        The value as the section would hold it.

    Raises
    ------
    InputError
        An unknown key (with the closest valid one), or a value of the wrong type or range.
    """
    tp: Any = cls
    meta: Mapping = {}
    parts = dotted.split(".")
    for i, name in enumerate(parts):
        key = ".".join([where, *parts[:i + 1]]) if where else ".".join(parts[:i + 1])
        origin = typing.get_origin(tp)
        if origin in (Union, types.UnionType):  # Optional[X] on the way down: X
            real = [a for a in typing.get_args(tp) if a is not type(None)]
            tp = next((a for a in real if dataclasses.is_dataclass(a) or typing.get_origin(a) in (dict, Mapping)), real[0])
            origin = typing.get_origin(tp)
        if dataclasses.is_dataclass(tp):
            fields = {f.name: f for f in dataclasses.fields(tp) if f.init}
            if name not in fields:
                close = difflib.get_close_matches(name, list(fields), n=1)
                hint = f"; did you mean '{close[0]}'?" if close else f"; valid keys: {', '.join(fields)}"
                raise InputError(f"{key}: unknown key{hint}")
            tp, meta = typing.get_type_hints(tp)[name], fields[name].metadata
            reg = meta.get("registry")
            if reg is not None and i + 1 < len(parts):  # into an extension point: its name, or the default entry's options
                if parts[i + 1] == reg.key and i + 2 == len(parts):
                    reg.get(value, ".".join([where, *parts]) if where else dotted)
                    return value
                tp, meta = reg.entry_of(meta["default"]).options, {}
        elif origin in (dict, Mapping):
            args = typing.get_args(tp)
            tp = args[1] if args else Any
        elif tp is Any:
            return value
        else:
            raise InputError(f"{key}: '{'.'.join(parts[:i])}' is {_typename(tp)}, not a mapping, so it has no key '{name}'")
    where_value = ".".join([where, *parts]) if where else dotted
    return _coerce(value, tp, where_value, Path(base_dir), meta)


class _UniqueKeyLoader(yaml.SafeLoader):
    """Safe YAML loader that refuses a mapping key given twice (plain YAML keeps the last one)."""

    def construct_mapping(self, node, deep=False):
        if isinstance(node, yaml.MappingNode):
            seen: dict = {}  # explicit keys only: a key may override one merged in with `<<:`
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":
                    continue
                key = self.construct_object(key_node, deep=True)
                try:
                    first = seen.setdefault(key, key_node.start_mark)
                except TypeError:  # unhashable key: let the base class report it
                    continue
                if first is not key_node.start_mark:
                    m = key_node.start_mark
                    raise yaml.constructor.ConstructorError(
                        None, None, f"key {key!r} is given twice (first on line {first.line + 1}); keep one", m)
        return super().construct_mapping(node, deep=deep)


def _yaml_error_line(path: Path, exc: yaml.YAMLError) -> str:
    """One line ``file:line:column: problem`` for a YAML error (PyYAML's own text spans several lines)."""
    mark = getattr(exc, "problem_mark", None) or getattr(exc, "context_mark", None)
    problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
    context = getattr(exc, "context", None)
    where = f"{path}:{mark.line + 1}:{mark.column + 1}" if mark is not None else str(path)
    what = f"{problem} ({context})" if context and "given twice" not in problem else problem
    return f"{where}: not valid YAML: {' '.join(what.split())}"


def read_yaml(path: str | Path) -> dict:
    """Read a YAML mapping; every problem is one :class:`InputError` line naming the file.

    Refused: a missing or unreadable file, a syntax error (reported as ``file:line:column``), a key
    given twice in one mapping, an empty file and a top level that is not a mapping.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: config file not found")
    if path.is_dir():
        raise InputError(f"{path}: is a folder, expected a YAML config file")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read the config file ({exc})") from None
    try:
        data = yaml.load(text, Loader=_UniqueKeyLoader)  # noqa: S506 - a SafeLoader subclass
    except yaml.YAMLError as exc:
        raise InputError(_yaml_error_line(path, exc)) from None
    if data is None:
        raise InputError(f"{path}: the config file is empty (expected sections such as build_model, solve, report)")
    if not isinstance(data, dict):
        raise InputError(f"{path}: expected a mapping of sections at the top level, got {type(data).__name__}")
    return data

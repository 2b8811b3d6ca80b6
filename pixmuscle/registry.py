"""Named entries of an extension point, each with its own options dataclass.

An extension point (material laws today) keeps one :class:`Registry`; an entry registers itself in
the module that defines it::

    LAWS = Registry("material law", key="law", package="pixmuscle.mechanics.materials")

    @LAWS.register("yeoh", needs=())
    @dataclasses.dataclass(frozen=True)
    class Yeoh:
        C10: float = field(default=3.0, metadata={"gt": 0, "doc": "N/cm²"})
        ...

The options dataclass is the entry itself when ``options`` is not given (a material law is a frozen
dataclass of its constants). A config mapping ``{<key>: name, …options}`` is validated by
:meth:`Registry.parse` against the chosen entry's dataclass, with the key-path errors of
:func:`pixmuscle.config.parse_section`. Entries of the registry's own package are found when the
package loads (:meth:`Registry.discover` imports its modules); an entry defined elsewhere is found
once its module is imported.
"""

from __future__ import annotations

import dataclasses
import difflib
import importlib
import pkgutil
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from .errors import InputError


@dataclasses.dataclass(frozen=True)
class Entry:
    """One registered entry: its name, the object, its options dataclass and declared attributes."""

    name: str
    obj: Any
    options: type
    attrs: Mapping[str, Any]


class Registry:
    """Name → :class:`Entry` of one extension point.

    Parameters
    ----------
    what : str
        What an entry is, for messages (``"material law"``).
    key : str
        Config key that names the entry (``"law"``).
    package : str, optional
        Package whose modules :meth:`discover` imports.
    """

    def __init__(self, what: str, *, key: str = "kind", package: str | None = None):
        self.what = what
        self.key = key
        self.package = package
        self._entries: dict[str, Entry] = {}

    def register(self, name: str, *, options: type | None = None, **attrs) -> Callable:
        """Decorator registering ``obj`` under ``name``; ``attrs`` are declared properties (e.g. ``needs``).

        The decorated object and its options dataclass get ``registry_key = (key, name)``, so
        :meth:`entry_of` finds the entry of an options instance and :func:`pixmuscle.store._plain`
        writes the name back into plain config data. An options dataclass belongs to one entry.
        """

        def deco(obj):
            opts = obj if options is None else options
            if not dataclasses.is_dataclass(opts):
                raise TypeError(f"{self.what} {name!r}: options must be a dataclass, got {opts!r}")
            old = self._entries.get(name)
            if old is not None and old.obj.__qualname__ != obj.__qualname__:
                raise ValueError(f"{self.what} {name!r} is registered twice ({old.obj!r} and {obj!r})")
            mine = vars(opts).get("registry_key")
            if mine is not None and mine != (self.key, name):
                raise ValueError(f"{self.what} {name!r}: options {opts.__qualname__} already belong to {mine[1]!r}")
            self._entries[name] = Entry(name, obj, opts, dict(attrs))
            obj.registry_key = opts.registry_key = (self.key, name)
            return obj

        return deco

    def discover(self) -> None:
        """Import every module of ``package`` so that their entries register themselves."""
        if self.package is None:
            return
        pkg = importlib.import_module(self.package)
        for mod in pkgutil.iter_modules(pkg.__path__):
            importlib.import_module(f"{self.package}.{mod.name}")

    def names(self) -> list[str]:
        """Registered names, sorted."""
        return sorted(self._entries)

    def get(self, name: str, where: str = "") -> Entry:
        """The entry called ``name``; an unknown name raises InputError naming ``where`` and the choices."""
        if name not in self._entries:
            close = difflib.get_close_matches(str(name), self.names(), n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            at = f"{where}: " if where else ""
            raise InputError(f"{at}unknown {self.what} {name!r}; expected one of {', '.join(self.names())}{hint}")
        return self._entries[name]

    def entry_of(self, obj: Any) -> Entry:
        """The entry whose object or options dataclass is ``obj`` or ``obj``'s class."""
        key = getattr(obj, "registry_key", None)
        if key is None or key[0] != self.key or key[1] not in self._entries:
            raise InputError(f"{obj!r} is not a registered {self.what}")
        return self._entries[key[1]]

    def parse(self, data: Mapping | None, where: str, base_dir: Path | str = ".", default: Any = None) -> Any:
        """Validate ``{key: name, …options}`` and build the chosen entry's options dataclass.

        Parameters
        ----------
        data : mapping or None
            Plain config data; ``None`` means ``default``.
        where : str
            Key path, for messages.
        base_dir : path
            Folder that relative paths are resolved against.
        default : dataclass instance, optional
            Used when ``data`` names no entry (its entry is taken) and, when the named entry is the
            default's, as the source of the values ``data`` does not give.
        """
        from .config import parse_section

        data = {} if data is None else data
        if not isinstance(data, Mapping):
            raise InputError(f"{where}: expected a mapping {{{self.key}: name, ...}}, got {data!r}")
        data = dict(data)
        name = data.pop(self.key, None)
        if name is None:
            if default is None:
                raise InputError(f"{where}.{self.key}: required key is missing (one of {', '.join(self.names())})")
            name = self.entry_of(default).name
        if not isinstance(name, str):
            raise InputError(f"{where}.{self.key}: expected a name, got {name!r}")
        entry = self.get(name, f"{where}.{self.key}")
        if default is not None and getattr(default, "registry_key", None) == (self.key, name):
            fields = {f.name for f in dataclasses.fields(entry.options) if f.init}
            data = {**{k: getattr(default, k) for k in fields}, **data}
        try:
            return parse_section(entry.options, data, where, base_dir)
        except InputError as exc:  # a check across constants in the entry's own __post_init__: add the key path
            if str(exc).startswith(where):
                raise
            raise InputError(f"{where}: {exc}") from None

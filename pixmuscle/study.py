"""Parameter studies: the ``study:`` section of a pipeline YAML expanded into cases.

Example::

    study:
      mode: grid                                   # grid (every combination, default) or list
      vary:
        solve.materials.muscle.sigma_max: [20, 25, 30]
        solve.materials.connective_tissue.C10: [15, 30, 60]

Each varied key is a dotted path into the config (its first part a section name); ``grid`` makes
every combination of the listed values (3 × 3 = 9 cases above), ``list`` takes the i-th value of
every key together (all lists of the same length). A case's folder name is made of the shortest
unique tail of each key and its value, e.g. ``sigma_max=20,connective_tissue.C10=15``. Pure data in,
data out: nothing here reads files.
"""

from __future__ import annotations

import copy
import dataclasses
import itertools
import re
from typing import Any

from .errors import InputError

_SAFE = re.compile(r"[^A-Za-z0-9._+-]")

#: most cases one run may have (subjects × combinations); each case is a whole solve
MAX_CASES = 1000


@dataclasses.dataclass(frozen=True)
class Study:
    """An expanded study: the varied keys and one tuple of values per case.

    Attributes
    ----------
    keys : tuple of str
        Dotted config paths, in the order of the YAML.
    cases : tuple of tuple
        One tuple of values (in the order of ``keys``) per case.
    names : tuple of str
        Folder name of each case (unique).
    mode : str
        ``"grid"`` or ``"list"``.
    """

    keys: tuple
    cases: tuple
    names: tuple
    mode: str

    @property
    def sections(self) -> frozenset:
        """Config sections that the study varies (the first part of each key)."""
        return frozenset(k.split(".")[0] for k in self.keys)


def format_value(v: Any) -> str:
    """Folder-safe text of one varied value (floats to 12 significant digits)."""
    if isinstance(v, bool):
        text = str(v).lower()
    elif isinstance(v, float):
        text = format(v, ".12g")
    else:
        text = str(v)
    return _SAFE.sub("_", text) or "_"


def short_names(keys: list[str]) -> list[str]:
    """The shortest dotted tail of each key that no other key ends with."""
    parts = [k.split(".") for k in keys]
    out = []
    for i, p in enumerate(parts):
        for n in range(1, len(p) + 1):
            tail = p[-n:]
            if all(q[-n:] != tail for j, q in enumerate(parts) if j != i):
                break
        out.append(".".join(tail))
    return out


def parse_study(raw: Any, sections: set[str], where: str = "study") -> Study | None:
    """Validate a ``study`` section and expand it into cases (None when ``raw`` is None).

    Parameters
    ----------
    raw : mapping or None
        ``{vary: {dotted.key: [values...]}, mode: grid|list}``.
    sections : set of str
        Config sections a key may start with.
    where : str
        Key path prefix for messages.
    """
    if raw is None:
        return None
    if not isinstance(raw, dict):
        raise InputError(f"{where}: expected a mapping with 'vary' (and optionally 'mode'), got {type(raw).__name__}")
    bad = sorted(set(raw) - {"vary", "mode"})
    if bad:
        raise InputError(f"{where}.{bad[0]}: unknown key; expected 'vary' and optionally 'mode'")
    mode = raw.get("mode", "grid")
    if mode not in ("grid", "list"):
        raise InputError(f"{where}.mode: expected 'grid' or 'list', got {mode!r}")
    vary = raw.get("vary")
    if not isinstance(vary, dict) or not vary:
        raise InputError(f"{where}.vary: expected a non-empty mapping of dotted config keys to lists of values")
    keys = list(vary)
    for k in keys:
        head = str(k).split(".")[0]
        if not isinstance(k, str) or "." not in k or head not in sections:
            raise InputError(f"{where}.vary.{k}: expected a dotted key inside a config section "
                             f"({', '.join(sorted(sections))}), e.g. solve.materials.muscle.sigma_max")
        vals = vary[k]
        if not isinstance(vals, list) or not vals:
            raise InputError(f"{where}.vary.{k}: expected a non-empty list of values, got {vals!r}")
        seen: dict[str, Any] = {}
        for v in vals:
            if isinstance(v, (dict, list)):
                raise InputError(f"{where}.vary.{k}: values must be numbers, strings or booleans, got {v!r}")
            text = format_value(v)
            if text in seen:
                raise InputError(f"{where}.vary.{k}: values {seen[text]!r} and {v!r} give the same case folder "
                                 f"('{text}'): duplicate case")
            seen[text] = v
    n_grid = 1
    for k in keys:
        n_grid *= len(vary[k])
    if mode == "grid" and n_grid > MAX_CASES:  # before the grid is expanded in memory
        sizes = " × ".join(f"{len(vary[k])} ({k})" for k in keys)
        raise InputError(f"{where}.vary: the grid makes {n_grid} cases ({sizes}), more than the bound of "
                         f"{MAX_CASES} cases of one run; vary fewer values, or split the study into several configs")
    if mode == "list":
        lengths = {k: len(vary[k]) for k in keys}
        if len(set(lengths.values())) > 1:
            raise InputError(f"{where}.vary: mode 'list' needs lists of one length, got "
                             + ", ".join(f"{k}: {n}" for k, n in lengths.items()))
        cases = list(zip(*(vary[k] for k in keys), strict=True))
    else:
        cases = list(itertools.product(*(vary[k] for k in keys)))
    tails = short_names(keys)
    names = [",".join(f"{t}={format_value(v)}" for t, v in zip(tails, c, strict=True)) for c in cases]
    if len(set(names)) != len(names):
        dup = next(n for n in names if names.count(n) > 1)
        raise InputError(f"{where}: case folder '{dup}' appears twice: duplicate case")
    return Study(tuple(keys), tuple(tuple(c) for c in cases), tuple(names), mode)


def set_key(raw: dict, dotted: str, value: Any, where: str = "study.vary") -> dict:
    """A deep copy of ``raw`` with ``dotted`` (``a.b.c``) set to ``value`` (missing levels created)."""
    out = copy.deepcopy(raw)
    node = out
    parts = dotted.split(".")
    for i, p in enumerate(parts[:-1]):
        nxt = node.get(p)
        if nxt is None:
            nxt = node[p] = {}
        if not isinstance(nxt, dict):
            raise InputError(f"{where}.{dotted}: '{'.'.join(parts[:i + 1])}' is not a mapping in the config "
                             f"(got {type(nxt).__name__}), so it cannot hold '{parts[i + 1]}'")
        node = nxt
    node[parts[-1]] = copy.deepcopy(value)
    return out

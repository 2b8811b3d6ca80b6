"""Named label maps → tissue map: which tissue or muscle each named label (a Slicer segment, an ITK-SNAP
label) stands for.

A name maps itself when it is a tissue class (``muscle``, ``connective_tissue``, ``fat``, ``bone``,
``background``) or one of the case's muscles (the segment seeds' names, ``build_model.muscle_fibers``);
any other name through the config's explicit ``label_names`` mapping. Names are compared without case,
with spaces and hyphens read as underscores ("Medial gastrocnemius" is ``medial_gastrocnemius``).
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Mapping
from typing import Any

from pixmuscle.errors import InputError
from pixmuscle.model.tissues import TISSUE_CODES

__all__ = ["normalise_name", "tissue_map_from_names"]


def normalise_name(name: str) -> str:
    """Lower case, runs of spaces and hyphens as one underscore, no outer blanks."""
    return re.sub(r"[\s\-]+", "_", str(name).strip().lower())


def tissue_map_from_names(names: Mapping[int, str], label_names: Mapping[str, Any] | None,
                          muscles: Iterable[str], source: str) -> dict[int, Any]:
    """A tissue map (label value → tissue or ``{muscle: name}``) for a label map's named values.

    Parameters
    ----------
    names : mapping of int → str
        Label value → name, as read from the file (0 is background whatever its name).
    label_names : mapping of str → tissue or {muscle: name}, optional
        The config's explicit mapping (``build_model.label_names``); it takes precedence.
    muscles : iterable of str
        The case's muscle names.
    source : str
        The file, for error messages.

    Returns
    -------
    dict of int → str or dict
        For :func:`pixmuscle.model.build.parse_tissue_map`.

    Raises
    ------
    InputError
        A name that maps to nothing (listing the names that would), or a ``label_names`` key that names no
        label of the file.
    """
    user = {normalise_name(k): v for k, v in (label_names or {}).items()}
    known = {normalise_name(m): m for m in muscles}
    tissues = {normalise_name(t): t for t in TISSUE_CODES}
    out: dict[int, Any] = {0: "background"}
    unmatched, used = [], set()
    for value, name in sorted(names.items()):
        if value == 0:
            continue
        key = normalise_name(name)
        if key in user:
            out[value], _ = user[key], used.add(key)
        elif key in known:
            out[value] = {"muscle": known[key]}
        elif key in tissues:
            out[value] = tissues[key]
        else:
            unmatched.append(name)
    if unmatched:
        listed = ", ".join(repr(n) for n in unmatched)
        muscles_txt = ", ".join(sorted(known.values())) or "none named in the config"
        raise InputError(f"{source}: label(s) {listed} match no muscle or tissue of the config; map each in "
                         "build_model.label_names as <label name>: <tissue> or {muscle: <name>} "
                         f"(tissues: {', '.join(TISSUE_CODES)}; muscles: {muscles_txt})")
    stray = sorted(set(user) - used - {normalise_name(n) for n in names.values()})
    if stray:
        raise InputError(f"build_model.label_names: {', '.join(map(repr, stray))} name(s) no label of {source} "
                         f"(its labels: {', '.join(repr(n) for n in names.values())})")
    return out

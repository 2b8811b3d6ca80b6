"""Report section: the force–length curves of the ``force_length`` experiment."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from ...errors import InputError
from . import SECTIONS


@SECTIONS.register("force_length", inputs=("force_length", "summary", "outdir", "dpi"), order=30)
@dataclasses.dataclass(frozen=True)
class ForceLength:
    """Passive, active and total end force against the end displacement; no options."""

    def html(self, force_length: Path | None, summary: dict, outdir: Path, dpi: int) -> list[str]:
        """Figure and table of ``force_length_<model>.h5`` (PNG and CSV into ``outdir``); empty without one.
        A file that cannot be read is a warning in ``summary["warnings"]``."""
        if force_length is None:
            return []
        from ...io.force_length import load_force_length
        from ..experiments import force_length_section

        try:
            fl = load_force_length(force_length)
        except (InputError, OSError) as exc:
            summary["warnings"].append(f"force–length curves not shown: {exc}")
            return []
        parts, info = force_length_section(fl, outdir, dpi=dpi, warnings=summary["warnings"])
        summary["outputs"].update(info["outputs"])
        return parts

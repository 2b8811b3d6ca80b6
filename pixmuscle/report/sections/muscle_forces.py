"""Report section: the end force split by muscle (the ``muscle_forces`` experiment)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from ...errors import InputError
from . import SECTIONS


def _fmax_step(summary: dict) -> int | None:
    """Index of the converged state of largest end force (None: none)."""
    c = summary.get("curve") or {}
    f = np.asarray(c.get("end_force_N") or [], float)
    ok = np.asarray(c.get("converged") or [], bool)
    if f.size == 0 or ok.shape != f.shape:
        return None
    ok &= np.isfinite(f)
    return int(np.flatnonzero(ok)[np.argmax(f[ok])]) if ok.any() else None


@SECTIONS.register("muscle_forces", inputs=("muscle_forces", "summary", "tissue", "outdir", "dpi", "activation"),
                   order=20)
@dataclasses.dataclass(frozen=True)
class MuscleForces:
    """Each muscle's contribution to the end force, and its F_max in the tissue table; no options."""

    def html(self, muscle_forces: Path | None, summary: dict, tissue: dict, outdir: Path, dpi: int,
             activation: dict | None) -> list[str]:
        """Figure and table of ``muscle_forces_<model>.h5``; empty without one.

        Side effects: PNG/CSV files into ``outdir``; the tissue table's per-muscle F_max
        (``tissue["rows"]``, ``summary["tissue_table"]``, the footnote); ``summary["muscle_forces"]``,
        ``summary["outputs"]`` entries and warnings in ``summary["warnings"]``.
        """
        if muscle_forces is None:
            return []
        from ...io.muscle_forces import load_muscle_forces
        from ..experiments import muscle_forces_section

        warnings = summary["warnings"]
        try:
            mf = load_muscle_forces(muscle_forces)
        except (InputError, OSError) as exc:
            warnings.append(f"per-muscle forces not shown: {exc}")
            return []
        k = _fmax_step(summary)
        if k is not None and k >= len(mf["total"]):
            warnings.append("per-muscle forces: the decomposition has fewer steps than the results; not tabulated")
            k = None
        parts, info = muscle_forces_section(mf, outdir, rows=tissue["rows"], k=k, dpi=dpi, warnings=warnings,
                                            activation=activation)
        summary["outputs"].update(info.pop("outputs"))
        if info:
            summary["muscle_forces"] = info
            fmax = summary.get("F_max_N")
            if fmax and abs(info["total_N"] - fmax) > 1e-6 * abs(fmax):
                warnings.append(f"per-muscle forces: their all-muscle run gives {info['total_N']:.6g} N at the step "
                                f"of F_max, the results {fmax:.6g} N (stale muscle_forces file?)")
            summary["tissue_table"] = [dict(r) for r in tissue["rows"]]
            if info["contribution_N"]:  # the per-muscle rows now show forces, not volumes only
                from ..tables import footnote

                tissue["footnote"] = summary["tissue_footnote"] = footnote(
                    tissue["rule"], tissue["attach_distance"], tissue["aponeurosis_mask"], per_muscle_force=True)
        return parts

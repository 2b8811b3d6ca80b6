"""Report sections of the per-muscle forces, force–length curves and DWI fit, called by :func:`pixmuscle.stages.report.make_report`.

Reads the files the pipeline names in the report's ``extra`` mapping —
``muscle_forces`` (``muscle_forces_<model>.h5``), ``force_length`` (``force_length_<model>.h5``),
``dwi_qc`` (the segmentation QC folder of a DWI fit) — and returns the HTML sections; fills the
tissue table's per-muscle F_max from the muscle-force decomposition.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..errors import InputError

_LOG = logging.getLogger(__name__)

__all__ = ["experiment_sections"]


def _fmax_step(summary: dict) -> int | None:
    c = summary.get("curve") or {}
    f = np.asarray(c.get("end_force_N") or [], float)
    ok = np.asarray(c.get("converged") or [], bool)
    if f.size == 0 or ok.shape != f.shape:
        return None
    ok &= np.isfinite(f)
    return int(np.flatnonzero(ok)[np.argmax(f[ok])]) if ok.any() else None


def experiment_sections(extra: dict, outdir, summary: dict, tissue: dict, *, dpi: int = 120,
                        activation: dict | None = None) -> list[str]:
    """HTML sections: activation per muscle, and the per-muscle forces, force–length curves and DWI
    fit named in ``extra``.

    ``activation`` is the results' ``solver_info["activation"]`` (muscle → [from, to] mean α).

    Side effects: writes the PNG/CSV files into ``outdir``; fills ``tissue["rows"]`` and
    ``summary["tissue_table"]`` per-muscle F_max; adds ``summary["muscle_forces"]`` /
    ``summary["outputs"]`` entries and warnings to ``summary["warnings"]``.
    """
    from ..report.dwi import dwi_section
    from ..report.experiments import force_length_section, muscle_forces_section
    from ..report.html import table

    outdir = Path(outdir)
    warnings = summary["warnings"]
    parts: list[str] = []
    if activation and len({tuple(v) for v in activation.values()}) > 1:
        parts += ["<h2>Activation per muscle</h2>",
                  table(["muscle", "α at the start (mean)", "α at the end (mean)"],
                        [[m, a, b] for m, (a, b) in activation.items()]),
                  '<p class="foot">solve.activation: per-muscle values and/or an activation image (α: the mean over '
                  "each muscle's nodes). Each muscle's α ramps linearly with the load factor s, α = start + s (end − "
                  "start), so the force curves are drawn against s, with every muscle's α named on the axis.</p>"]
    if extra.get("muscle_forces"):
        from ..io.muscle_forces import load_muscle_forces

        try:
            mf = load_muscle_forces(extra["muscle_forces"])
        except (InputError, OSError) as exc:
            warnings.append(f"per-muscle forces not shown: {exc}")
        else:
            k = _fmax_step(summary)
            if k is not None and k >= len(mf["total"]):
                warnings.append("per-muscle forces: the decomposition has fewer steps than the results; not tabulated")
                k = None
            p, info = muscle_forces_section(mf, outdir, rows=tissue["rows"], k=k, dpi=dpi, warnings=warnings,
                                            activation=activation)
            parts += p
            summary["outputs"].update(info.pop("outputs"))
            if info:
                summary["muscle_forces"] = info
                fmax = summary.get("F_max_N")
                if fmax and abs(info["total_N"] - fmax) > 1e-6 * abs(fmax):
                    warnings.append(f"per-muscle forces: their all-muscle run gives {info['total_N']:.6g} N at the step "
                                    f"of F_max, the results {fmax:.6g} N (stale muscle_forces file?)")
                summary["tissue_table"] = [dict(r) for r in tissue["rows"]]
                if info["contribution_N"]:  # the per-muscle rows now show forces, not volumes only
                    from ..report.tables import footnote

                    tissue["footnote"] = summary["tissue_footnote"] = footnote(
                        tissue["rule"], tissue["attach_distance"], tissue["aponeurosis_mask"], per_muscle_force=True)
    if extra.get("force_length"):
        from ..io.force_length import load_force_length

        try:
            fl = load_force_length(extra["force_length"])
        except (InputError, OSError) as exc:
            warnings.append(f"force–length curves not shown: {exc}")
        else:
            p, info = force_length_section(fl, outdir, dpi=dpi, warnings=warnings)
            parts += p
            summary["outputs"].update(info["outputs"])
    if extra.get("dwi_qc"):
        parts += dwi_section(extra["dwi_qc"])
    return parts

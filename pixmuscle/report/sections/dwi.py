"""Report section of a scanner DWI fit: the QC maps and numbers of :mod:`pixmuscle.stages.dwi_qc`."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

from ..html import esc, img_tag, kv_table
from . import SECTIONS

__all__ = ["DwiFit", "dwi_section"]


@SECTIONS.register("dwi", inputs=("dwi_qc",), order=40)
@dataclasses.dataclass(frozen=True)
class DwiFit:
    """The scanner DWI tensor fit of the segmentation: its numbers and FA/MD/V1 maps; no options."""

    def html(self, dwi_qc: Path | None) -> list[str]:
        """:func:`dwi_section` of the QC folder; empty without one."""
        return [] if dwi_qc is None else dwi_section(dwi_qc)


def dwi_section(qc_dir) -> list[str]:
    """HTML fragments from ``<qc_dir>/dwi_summary.json`` and ``dwi_maps.png`` (empty list when absent)."""
    qc_dir = Path(qc_dir)
    summary_path = qc_dir / "dwi_summary.json"
    if not summary_path.is_file():
        return []
    s = json.loads(summary_path.read_text())
    fa, md = s.get("fa_percentiles_5_50_95") or [], s.get("md_percentiles_5_50_95_mm2_per_s") or []
    facts = {
        "series": s.get("image", "—"), "b-values / b-vectors": f"{s.get('bvals', '—')} / {s.get('bvecs', '—')}",
        "b-vector convention": s.get("bvecs_convention", "—"), "fit": s.get("method", "—"),
        "fitted voxels": s.get("fitted_voxels"), "DWI grid": " × ".join(map(str, s.get("grid_shape", []))),
        "FA 5 / 50 / 95 %": " / ".join(f"{v:.3g}" for v in fa) or "—",
        "MD 5 / 50 / 95 % [10⁻³ mm²/s]": " / ".join(f"{1e3 * v:.3g}" for v in md) or "—",
    }
    parts = ["<h2>Diffusion data (DWI tensor fit)</h2>", kv_table(facts)]
    png = qc_dir / "dwi_maps.png"
    if png.is_file():
        parts.append(img_tag(png, "FA, MD and V1 colour maps"))
    parts.append(f'<p class="foot">Maps on the DWI grid: <code>{esc(qc_dir.name)}/dwi_fa.nii.gz</code>, '
                 "<code>dwi_md.nii.gz</code>, <code>dwi_v1.nii.gz</code> (world axes).</p>")
    return parts

"""Report section of the MRI's bias-field correction: the field N4 removed before the level sets
(:mod:`pixmuscle.imaging.bias`), its range and a slice."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from ..html import esc, img_tag, kv_table
from . import SECTIONS

__all__ = ["BiasField"]


@SECTIONS.register("bias_field", inputs=("bias_field",), order=45)
@dataclasses.dataclass(frozen=True)
class BiasField:
    """The N4 bias field of the segmentation's MRI: its range over the limb and its middle slice; no options."""

    def html(self, bias_field: Path | None) -> list[str]:
        """HTML fragments; empty without a bias field."""
        if bias_field is None or not Path(bias_field).is_file():
            return []
        from ...imaging.nifti import load_volume

        field = load_volume(bias_field, kind="image").data
        inside = np.abs(field - 1.0) > 1e-9                  # outside the limb's mask the field is ~1 as well
        vals = field[inside] if inside.any() else field.ravel()
        lo, mid, hi = np.percentile(vals, [1, 50, 99])
        facts = {"correction": "N4 (SimpleITK), on the MRI before the level sets",
                 "field 1 / 50 / 99 % (multiplicative)": f"{lo:.3f} / {mid:.3f} / {hi:.3f}",
                 "field file": Path(bias_field).name}
        parts = ["<h2>MRI bias field</h2>", kv_table(facts)]
        png = Path(bias_field).with_name("segmentation_qc") / "bias_field.png"
        if png.is_file():
            parts.append(img_tag(png, "N4 bias field, middle slice"))
        parts.append(f'<p class="foot">The segmentation ran on the MRI divided by this field; '
                     f'<code>{esc(Path(bias_field).name)}</code> holds it on the MRI grid.</p>')
        return parts

"""Report section: the activation of each muscle, when the muscles were not all ramped alike."""

from __future__ import annotations

import dataclasses

from ..html import table
from . import SECTIONS


@SECTIONS.register("activation", inputs=("activation",), order=10)
@dataclasses.dataclass(frozen=True)
class ActivationPerMuscle:
    """α at the start and the end of each muscle's ramp (the mean over its nodes); no options."""

    def html(self, activation: dict | None) -> list[str]:
        """A table of muscle → (α from, α to); empty when every muscle had the same ramp."""
        if not activation or len({tuple(v) for v in activation.values()}) <= 1:
            return []
        return ["<h2>Activation per muscle</h2>",
                table(["muscle", "α at the start (mean)", "α at the end (mean)"],
                      [[m, a, b] for m, (a, b) in activation.items()]),
                '<p class="foot">solve.activation: per-muscle values and/or an activation image (α: the mean over '
                "each muscle's nodes). Each muscle's α ramps linearly with the load factor s, α = start + s (end − "
                "start), so the force curves are drawn against s, with every muscle's α named on the axis.</p>"]

"""SYNTHETIC phantoms standing in for the paper's (non-public) MRI and DTI data.

``make_leg_phantom`` imitates an axial lower-leg scan with 7 muscles (paper Example 2);
``make_mg_phantom`` a medial gastrocnemius of a young or old subject (Example 3, Table 3).
``write_phantom`` writes one as NIfTI files plus a JSON truth file; ``generate_samples``
regenerates the small committed samples under ``data/synthetic/``. See docs/phantoms.md.
"""

from pixmuscle.synth.leg import MUSCLE_NAMES as LEG_MUSCLE_NAMES
from pixmuscle.synth.leg import make_leg_phantom
from pixmuscle.synth.mg import make_mg_phantom, tissue_volumes
from pixmuscle.synth.phantom import Phantom

__all__ = [
    "LEG_MUSCLE_NAMES", "Phantom", "generate_samples", "make_leg_phantom", "make_mg_phantom",
    "tissue_volumes", "write_phantom",
]


def __getattr__(name):
    # the writer is imported lazily so that ``python -m pixmuscle.synth.write`` runs cleanly
    if name in ("generate_samples", "write_phantom"):
        from pixmuscle.synth import write

        return getattr(write, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

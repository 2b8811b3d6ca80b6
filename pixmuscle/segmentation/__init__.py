"""Level-set segmentation of limb MRI + DTI (paper §4.1–4.2).

* :func:`chan_vese` — two-phase multichannel Chan–Vese (2-D or 3-D);
* :func:`multiphase_chan_vese` — multiphase multichannel Vese–Chan (eq. 21);
* :func:`regions_to_muscles` — regions -> named muscles by seed points;
* :func:`assemble_labels` — tissue labels (§4.2);
* :func:`segment_volume` — the whole chain on a volume; :class:`SegmentConfig` its settings.
"""

from pixmuscle.segmentation.assemble import assemble_labels, fiber_data
from pixmuscle.segmentation.chan_vese import ChanVeseResult, chan_vese
from pixmuscle.segmentation.config import (
    BoneConfig,
    MultiphaseConfig,
    SegmentConfig,
    TwoPhaseConfig,
)
from pixmuscle.segmentation.features import fiber_channels, normalize_intensity
from pixmuscle.segmentation.multiphase import (
    MultiphaseResult,
    multiphase_chan_vese,
    regions_to_muscles,
    seed_features,
    seed_regions,
)
from pixmuscle.segmentation.volume import SegmentationResult, segment_volume

__all__ = [
    "ChanVeseResult", "chan_vese",
    "MultiphaseResult", "multiphase_chan_vese", "regions_to_muscles", "seed_features",
    "seed_regions",
    "fiber_channels", "normalize_intensity",
    "assemble_labels", "fiber_data",
    "TwoPhaseConfig", "BoneConfig", "MultiphaseConfig", "SegmentConfig",
    "SegmentationResult", "segment_volume",
]

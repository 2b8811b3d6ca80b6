"""Configuration of the build-model and coarsen stages (YAML sections ``build_model``, ``coarsen``)."""

from __future__ import annotations

import dataclasses
from dataclasses import field
from pathlib import Path
from typing import Any, Literal

from ..errors import InputError


@dataclasses.dataclass(frozen=True)
class BuildModelConfig:
    """Label volume → pixel-point model (paper §4.2).

    The input is either a NIfTI label image (``labels``, values mapped by ``tissue_map``) or the
    ``segmentation.h5`` of the segment stage (``segmentation``), not both. When the pipeline runs
    the segment stage it fills in ``segmentation`` itself, so neither needs to be given then.
    """

    labels: Path | None = field(default=None, metadata={"must_exist": True, "doc": "NIfTI label image (any orientation; header units mm or cm); its values are mapped by tissue_map"})
    segmentation: Path | None = field(default=None, metadata={"must_exist": True, "doc": "segmentation.h5 of the segment stage (tissue codes, muscle ids and names, fibres)"})
    fibers: Path | None = field(default=None, metadata={"must_exist": True, "doc": "4-D NIfTI fibre image (I, J, K, 3) on the label grid, scanner-frame vectors of any length and sign; overrides /fiber of segmentation.h5"})
    fiber_components: Literal["world", "voxel", "fsl"] = field(default="world", metadata={"doc": "axes of the fibre image's vector components: world (scanner axes of the affine), voxel (stored voxel axes) or fsl (FSL dtifit V1 convention)"})
    tissue_map: dict[int, Any] | None = field(default=None, metadata={"doc": "label value → muscle | connective_tissue | fat | bone | background | {muscle: <name>, fiber: [x, y, z]} (default: 0 background, 1 muscle, 2 connective_tissue, 3 fat, 4 bone)"})
    muscle_fibers: dict[str, list[float]] | None = field(default=None, metadata={"doc": "muscle name → fibre direction [x, y, z] in scanner coordinates (unitless, normalised); overrides the fibre image for that muscle"})
    fiber_fallback: Literal["error", "muscle_mean"] = field(default="error", metadata={"doc": "muscle nodes without a usable fibre: error, or the muscle's sign-invariant mean direction (with a warning)"})
    masks: dict[str, Path] = field(default_factory=dict, metadata={"must_exist": True, "doc": "extra node sets: set name → NIfTI mask on the label grid (non-zero = in the set)"})

    def __post_init__(self):
        if self.labels is not None and self.segmentation is not None:
            raise InputError("build_model: give either 'labels' (a NIfTI label image) or 'segmentation' "
                             "(segmentation.h5), not both")
        from .build import _check_direction, parse_tissue_map
        from .nodesets import _check_set_name

        if self.tissue_map is not None:
            parse_tissue_map(self.tissue_map, "build_model.tissue_map")
        for name, d in (self.muscle_fibers or {}).items():
            _check_direction(d, f"build_model.muscle_fibers.{name}")
        for name in self.masks:
            try:
                _check_set_name(name)
            except InputError as exc:
                raise InputError(f"build_model.masks: {exc}") from None

    def require_input(self) -> Path:
        """The input file (labels or segmentation); InputError when neither is given."""
        if self.labels is None and self.segmentation is None:
            raise InputError("build_model: no input; give 'labels' (a NIfTI label image) or 'segmentation' "
                             "(segmentation.h5), or add a 'segment' section")
        return self.labels if self.labels is not None else self.segmentation


@dataclasses.dataclass(frozen=True)
class CoarsenConfig:
    """Coarse model: every ``factor``-th pixel in-plane, all slices (paper §4.2, Fig. 9b)."""

    factor: int = field(default=2, metadata={"range": (1, None), "doc": "in-plane coarsening factor (coarse spacing = factor × pixel size; slices unchanged)"})
    enabled: bool = field(default=True, metadata={"doc": "make the coarse model"})

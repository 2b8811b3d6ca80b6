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

    The input is a label map (``labels``: NIfTI, a 3D Slicer ``.seg.nrrd`` or NRRD), the
    ``segmentation.h5`` of the segment stage (``segmentation``), or both: then the label map (a
    segmentation corrected by hand) replaces the segmentation's labels, placed on its grid through the
    affines, and the fibres and muscle names come from the segmentation. When the pipeline runs the
    segment stage it fills in ``segmentation`` itself.

    A label map's values are tissues by ``tissue_map``, or, when the file names them (Slicer segments,
    an ITK-SNAP ``label_descriptions`` file), by their names (:mod:`pixmuscle.model.label_names`).
    """

    labels: Path | None = field(default=None, metadata={"must_exist": True, "doc": "label map: NIfTI (any orientation; header units mm or cm), 3D Slicer .seg.nrrd or NRRD; values mapped by tissue_map, or by their names (Slicer segments, label_descriptions)"})
    label_descriptions: Path | None = field(default=None, metadata={"must_exist": True, "doc": "ITK-SNAP label description file naming the values of the labels file"})
    label_names: dict[str, Any] | None = field(default=None, metadata={"doc": "label (segment) name → muscle | connective_tissue | fat | bone | background | {muscle: <name>}, for names that are not a tissue or a muscle of the case"})
    segmentation: Path | None = field(default=None, metadata={"must_exist": True, "doc": "segmentation.h5 of the segment stage (tissue codes, muscle ids and names, fibres)"})
    fibers: Path | None = field(default=None, metadata={"must_exist": True, "doc": "4-D NIfTI fibre image (I, J, K, 3) on the label grid, scanner-frame vectors of any length and sign; overrides /fiber of segmentation.h5"})
    fiber_components: Literal["world", "voxel", "fsl"] = field(default="world", metadata={"doc": "axes of the fibre image's vector components: world (scanner axes of the affine), voxel (stored voxel axes) or fsl (FSL dtifit V1 convention)"})
    tissue_map: dict[int, Any] | None = field(default=None, metadata={"doc": "label value → muscle | connective_tissue | fat | bone | background | {muscle: <name>, fiber: [x, y, z]} (default: 0 background, 1 muscle, 2 connective_tissue, 3 fat, 4 bone)"})
    muscle_fibers: dict[str, list[float]] | None = field(default=None, metadata={"doc": "muscle name → fibre direction [x, y, z] in scanner coordinates (unitless, normalised); overrides the fibre image for that muscle"})
    fiber_fallback: Literal["error", "muscle_mean"] = field(default="error", metadata={"doc": "muscle nodes without a usable fibre: error, or the muscle's sign-invariant mean direction (with a warning)"})
    masks: dict[str, Path] = field(default_factory=dict, metadata={"must_exist": True, "doc": "extra node sets: set name → NIfTI mask on the label grid (non-zero = in the set)"})

    def __post_init__(self):
        if self.label_descriptions is not None and self.labels is None:
            raise InputError("build_model.label_descriptions: names the values of 'labels', which is not given")
        if self.tissue_map is not None and (self.label_names is not None or self.label_descriptions is not None):
            raise InputError("build_model.tissue_map: give either tissue_map (label values) or label names "
                             "(label_names / label_descriptions), not both")
        from .build import _check_direction, parse_tissue_map
        from .nodesets import _check_set_name

        if self.tissue_map is not None:
            parse_tissue_map(self.tissue_map, "build_model.tissue_map")
        for name, spec in (self.label_names or {}).items():
            parse_tissue_map({1: spec}, f"build_model.label_names.{name}")
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

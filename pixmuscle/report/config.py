"""Configuration of the report stage (YAML section ``report``)."""

from __future__ import annotations

import dataclasses
from dataclasses import field
from pathlib import Path
from typing import Literal

from ..errors import InputError

#: quantities ``report.reference_values`` may give (units: cm^3, N, N/cm^3), keys of the report summary's
#: ``compared`` dict (:func:`pixmuscle.report.summary.compared_quantities`)
REFERENCE_QUANTITIES = ("muscle", "imat", "imct", "aponeurosis", "table3_total", "F_max",
                        "force_per_table3_volume", "force_per_muscle_volume")


@dataclasses.dataclass(frozen=True)
class ReportConfig:
    """Which report outputs to write and how.

    The force–activation CSV/PNG (a displacement-driven run: ``force_displacement.csv/png``, see
    :mod:`pixmuscle.report.displacement`), the tissue table (activation runs) and ``summary.json``
    are always written; the flags below switch the heavier outputs.
    """

    vtu: bool = field(default=True, metadata={"doc": "write the ParaView VTU time series (fields/*.vtu + fields.pvd): the model's voxel cells with cell and point data"})
    xdmf: bool = field(default=True, metadata={"doc": "also write the series as XDMF + HDF5 (fields.xdmf, fields.h5) for large models"})
    segmentation_qc: bool = field(default=True, metadata={"doc": "segmentation QC section: MRI with the labels filled in and per-slice areas (needs the segment stage's file)"})
    view3d: bool = field(default=True, metadata={"doc": "interactive 3-D view on the page (plotly.js written beside index.html, no network needed): rotate the model, pick a field (|u|, largest principal stress, tissue, muscle, fibre angle) and a load step; needs the `plotly` package (extra `view`)"})
    view3d_max_points: int = field(default=20000, metadata={"range": (100, None), "doc": "the 3-D view shows at most this many nodes (larger models: every k-th voxel in-plane, all slices)"})
    slices: bool = field(default=True, metadata={"doc": "write the slice figures of |u| and max principal stress"})
    html: bool = field(default=True, metadata={"doc": "write the self-contained index.html"})
    every_nth_step: int = field(default=1, metadata={"range": (1, None), "doc": "write every n-th converged step to VTU (the last converged step is always written)"})
    force_sets: list[str] | None = field(default=None, metadata={"doc": "end node sets whose axial reaction is the muscle force (default: z_min and z_max when constrained)"})
    dpi: int = field(default=120, metadata={"range": (30, 600), "doc": "figure resolution, dots per inch"})
    vtu_frame: Literal["model", "rotated"] = field(default="model", metadata={"doc": "VTU coordinates: model frame (cm), or with grid/rotation applied about the origin"})
    vtu_compression: Literal["zlib", "none"] = field(default="zlib", metadata={"doc": "compression of the VTU arrays: zlib (smaller, slower) or none"})
    slice_position: tuple[float, ...] | None = field(default=None, metadata={"doc": "(x, y, z) point in cm the three slice planes pass through (default: centre of the node cloud)"})
    slice_step: int | None = field(default=None, metadata={"range": (0, None), "doc": "step shown on the slice figures (default: last converged step)"})
    arrows: bool = field(default=True, metadata={"doc": "draw in-plane displacement arrows on the displacement slices"})
    imat_rule: Literal["enclosed", "near_muscle"] = field(default="enclosed", metadata={"doc": "IMAT = fat inside the muscle envelope or not connected in its slice to the outside or the skin (enclosed), or fat within attach_distance of muscle (near_muscle)"})
    reference_curve: Path | None = field(default=None, metadata={"must_exist": True, "doc": "displacement-driven runs: CSV (columns displacement_cm, force_N) of a reference force against the prescribed displacement, drawn beside the end force (e.g. data/synthetic/tendon_fe_reference.csv, the finite-element tendon of `pixmuscle verify tendon`)"})
    reference_label: str = field(default="reference", metadata={"doc": "legend and table label of reference_curve"})
    reference_values: dict[str, float] = field(default_factory=dict, metadata={"doc": "published values to show beside the model's (cohort page and report): quantity -> value, quantities " + ", ".join(REFERENCE_QUANTITIES)})
    reference_values_label: str = field(default="paper", metadata={"doc": "where reference_values come from (column heading)"})
    attach_distance: float = field(default=2.0, metadata={"gt": 0, "doc": "IMAT/IMCT are attributed to the muscle of the nearest muscle node within this many cells (Chebyshev distance in grid cells)"})

    def __post_init__(self):
        if self.slice_position is not None and len(self.slice_position) != 3:
            raise InputError(f"report.slice_position: expected 3 numbers (x, y, z) in cm, got {len(self.slice_position)}")
        for k in self.reference_values:
            if k not in REFERENCE_QUANTITIES:
                raise InputError(f"report.reference_values.{k}: unknown quantity; expected one of {', '.join(REFERENCE_QUANTITIES)}")
        if self.force_sets is not None and len(self.force_sets) == 0:
            raise InputError("report.force_sets: expected at least one set name, or leave it out for the default (z_min, z_max)")

"""Report sections: one module per section of the HTML page, each registering itself in :data:`SECTIONS`.

A section is a frozen dataclass of its options (none so far) registered with
``@SECTIONS.register(name, inputs=(...), order=n)``, with a method ``html(**inputs) -> list[str]``
that returns the page's HTML fragments (empty: the section is left out). ``inputs`` names the
fields of :class:`ReportInputs` the section takes; the report stage builds those once
(:func:`pixmuscle.stages.report.make_report`) and :func:`render` passes each section what it
declared. Sections are drawn in increasing ``order``, after the per-model comparison and before
the solver statistics.

Sections of pixmuscle: ``activation`` (α per muscle), ``muscle_forces`` (force by muscle),
``force_length`` (force–length curves), ``ellipticity`` (nodes where the material law is not
strongly elliptic), ``dwi`` (the DWI tensor fit) and ``bias_field`` (the MRI's N4 bias field).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from ...registry import Registry


@dataclasses.dataclass(frozen=True)
class ReportInputs:
    """What the report sections may take, built once per report.

    Attributes
    ----------
    results : Results
        The headline model's results (:class:`pixmuscle.mechanics.results.Results`).
    summary : dict
        The report summary (:func:`pixmuscle.report.summary.compute_summary`); a section may add
        to its ``outputs`` and ``warnings``.
    tissue : dict
        The tissue table (:func:`pixmuscle.report.tables.tissue_table`); a section may fill its rows.
    outdir : Path
        Folder the report is written into (a section's PNG and CSV files go here).
    dpi : int
        Resolution of the figures (``report.dpi``).
    activation : dict or None
        Muscle → (α at the start, α at the end), the mean over its nodes (the solve's record).
    muscle_forces : Path or None
        ``muscle_forces_<model>.h5`` of the headline model (:mod:`pixmuscle.io.muscle_forces`).
    force_length : Path or None
        ``force_length_<model>.h5`` of the headline model (:mod:`pixmuscle.io.force_length`).
    dwi_qc : Path or None
        Folder of the segmentation's DWI-fit QC maps (:mod:`pixmuscle.stages.dwi_qc`).
    bias_field : Path or None
        The MRI's bias field as N4 estimated it (``segmentation_bias_field.nii.gz``).
    """

    results: Any
    summary: dict
    tissue: dict
    outdir: Path
    dpi: int = 120
    activation: dict | None = None
    muscle_forces: Path | None = None
    force_length: Path | None = None
    dwi_qc: Path | None = None
    bias_field: Path | None = None

    @classmethod
    def build(cls, results, run: Mapping, summary: dict, tissue: dict, outdir: Path, dpi: int) -> ReportInputs:
        """The inputs of one report: ``run`` is the caller's run information (the pipeline names
        the experiment files there: ``muscle_forces``, ``force_length``, ``dwi_qc``, ``bias_field``)."""
        def path(key):
            return Path(run[key]) if run.get(key) else None

        return cls(results=results, summary=summary, tissue=tissue, outdir=Path(outdir), dpi=dpi,
                   activation=(results.info or {}).get("activation"), muscle_forces=path("muscle_forces"),
                   force_length=path("force_length"), dwi_qc=path("dwi_qc"),
                   bias_field=path("bias_field"))


#: Registered report sections (name → entry; entry.attrs: ``inputs``, ``order``).
SECTIONS = Registry("report section", key="section", package=__name__)


def render(inputs: ReportInputs) -> list[str]:
    """HTML fragments of every registered section, in order, each given the inputs it declares."""
    fields = {f.name for f in dataclasses.fields(ReportInputs)}
    parts: list[str] = []
    entries = sorted((SECTIONS.get(n) for n in SECTIONS.names()), key=lambda e: (e.attrs.get("order", 100), e.name))
    for entry in entries:
        wanted = tuple(entry.attrs.get("inputs", ()))
        unknown = [n for n in wanted if n not in fields]
        if unknown:
            raise TypeError(f"report section {entry.name!r} asks for unknown inputs {unknown}; "
                            f"ReportInputs has {sorted(fields)}")
        parts += entry.obj().html(**{n: getattr(inputs, n) for n in wanted})
    return parts


SECTIONS.discover()

__all__ = ["SECTIONS", "ReportInputs", "render"]

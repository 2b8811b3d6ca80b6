"""Report layer: force–activation curves, tissue tables, ParaView fields, slice figures, HTML pages.

Reading ``results.h5`` happens only in :func:`pixmuscle.report.inputs.load_results`; the rest works
on arrays and writes files. The stage entry point is :func:`pixmuscle.stages.report.run_report`.
"""

from .config import ReportConfig
from .curves import axial_forces, end_normal, plot_force_activation, select_force_sets
from .inputs import ReportInput, StepFields, load_results
from .tables import subcutaneous_fat, tissue_classes, tissue_table


def cohort_summary(*args, **kwargs):
    """See :func:`pixmuscle.report.cohort.cohort_summary`."""
    from .cohort import cohort_summary as _cs

    return _cs(*args, **kwargs)


__all__ = [
    "ReportConfig", "ReportInput", "StepFields", "load_results", "axial_forces", "end_normal",
    "plot_force_activation", "select_force_sets", "subcutaneous_fat", "tissue_classes", "tissue_table",
    "cohort_summary",
]

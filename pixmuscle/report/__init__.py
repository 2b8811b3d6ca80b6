"""Report layer: force–activation curves, tissue tables, ParaView fields, slice figures, HTML pages.

``results.h5`` is read by :func:`pixmuscle.io.results.load_results` (the one reader, at the edge)
into a :class:`~pixmuscle.mechanics.results.Results`; the summary is
:func:`pixmuscle.report.summary.compute_summary`, the figures are registered in
:mod:`pixmuscle.report.figures`. The stage entry point is :func:`pixmuscle.stages.report.run_report`.
"""

from .config import ReportConfig
from .curves import axial_forces, end_normal, plot_force_activation, select_force_sets
from .tables import subcutaneous_fat, tissue_classes, tissue_table


def cohort_summary(*args, **kwargs):
    """See :func:`pixmuscle.report.cohort.cohort_summary`."""
    from .cohort import cohort_summary as _cs

    return _cs(*args, **kwargs)


__all__ = [
    "ReportConfig", "axial_forces", "end_normal",
    "plot_force_activation", "select_force_sets", "subcutaneous_fat", "tissue_classes", "tissue_table",
    "cohort_summary",
]

"""The force's uncertainty from the scan: the ``uncertainty`` config section and the interval of F_max.

Realisations of DTI noise (:mod:`pixmuscle.imaging.dti_noise`) and of the segmentation's boundaries
(:mod:`pixmuscle.segmentation.perturb`) are made by the ``perturb`` stage
(:mod:`pixmuscle.stages.perturb`); each is a case of the run (:func:`pixmuscle.pipeline.load_run`),
summarised by :mod:`pixmuscle.report.uncertainty_page` with :func:`prediction_interval`.
"""

from .config import UncertaintyConfig
from .interval import prediction_interval

__all__ = ["UncertaintyConfig", "prediction_interval"]

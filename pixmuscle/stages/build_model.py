"""Stage ``build-model``: labels (NIfTI, Slicer .seg.nrrd / NRRD, or segmentation.h5) → ``model.h5``.

Reads the inputs named by :class:`~pixmuscle.model.config.BuildModelConfig` (label maps through
:mod:`pixmuscle.io.labelmap`; a label map given with a segmentation replaces its labels), calls
:func:`pixmuscle.model.build.model_from_labels` and writes the model (schema ``pixmuscle.model``
v1) through :func:`pixmuscle.io.model.save_model`.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..io.labelmap import read_label_map
from ..io.lineage import capture_warnings, stage_attrs
from ..io.model import save_model
from ..io.segmentation import read_segmentation
from ..model.build import model_from_labels
from ..model.config import BuildModelConfig
from ..model.label_names import tissue_map_from_names

_LOG = logging.getLogger(__name__)

#: largest difference (cm) between two affines that still counts as the same grid
AFFINE_ATOL = 1e-4


def _on_grid(shape, affine, ref_shape, ref_affine) -> bool:
    """Whether a volume of ``shape`` / ``affine`` lies on the grid ``ref_shape`` / ``ref_affine``."""
    return tuple(shape[:3]) == tuple(ref_shape[:3]) and np.allclose(affine, ref_affine, atol=AFFINE_ATOL)


def _same_grid(name: str, path: Path, shape, affine, ref_path: Path, ref_shape, ref_affine) -> None:
    if not _on_grid(shape, affine, ref_shape, ref_affine):
        raise InputError(
            f"{name} {path} is not on the label grid of {ref_path}: shape {tuple(shape)} vs {tuple(ref_shape)}, "
            f"voxel → cm affine {np.round(affine, 4).tolist()} vs {np.round(ref_affine, 4).tolist()}; "
            "resample it onto the label grid first")


def _labels_on_grid(lm, grid):
    """A label map's labels and affine, placed on ``grid`` = (shape, affine, file) when given.

    The same grid: as they are; another grid with an affine (a Slicer segmentation cropped to its extent,
    another resolution): nearest-neighbour resampling through both affines; no affine: only a map of the
    grid's own shape, which is then taken to lie on it.
    """
    if grid is None:
        if lm.affine is None:
            raise InputError(f"{lm.path}: the label map has no geometry (no 'space directions' / 'space origin'), "
                             "so its voxel size and position are unknown; save it with its geometry")
        return lm.labels, lm.affine
    shape, affine, ref = grid
    if lm.affine is None:
        if tuple(lm.labels.shape) != tuple(shape):
            raise InputError(f"{lm.path}: the label map has no geometry and its grid {tuple(lm.labels.shape)} differs "
                             f"from the MRI grid {tuple(shape)} of {ref}: nothing maps one onto the other; save it "
                             "with its geometry (space directions and origin)")
        _LOG.warning("%s has no geometry; taken to lie on the MRI grid of %s (same shape)", lm.path, ref)
        return lm.labels, affine
    if _on_grid(lm.labels.shape, lm.affine, shape, affine):
        return lm.labels, affine
    from ..imaging.resample import resample_labels

    _LOG.info("%s: placing the label map %s on the MRI grid %s (nearest neighbour)", lm.path, lm.labels.shape, shape)
    return resample_labels(lm.labels, lm.affine, shape, affine, name=f"build_model.labels {lm.path}"), affine


def run_build_model(cfg: BuildModelConfig, out_path: str | Path, progress: Any = None, *,
                    synthetic: bool = False) -> Path:
    """Build ``model.h5`` from the inputs of ``cfg``.

    Parameters
    ----------
    cfg : BuildModelConfig
        Exactly one of ``labels`` / ``segmentation`` must be set.
    out_path : path
        Destination ``model.h5``.
    progress : object with ``.log(msg)``, optional
        Progress reporter (:func:`pixmuscle.progress.progress`); messages also go to logging.
    synthetic : bool
        The inputs are synthetic phantoms (also detected from the inputs, see
        :func:`pixmuscle.io.lineage.stage_attrs`).

    Returns
    -------
    pathlib.Path
        ``out_path``.
    """
    with capture_warnings() as warnings:
        model, inputs = _build(cfg, progress)
    _say(progress, f"writing {out_path} ({model.n_nodes} nodes)")
    return save_model(out_path, model, config=cfg, inputs=inputs,
                      attrs=stage_attrs("build-model", inputs, warnings, synthetic=synthetic))


def _say(progress: Any, msg: str) -> None:
    if progress is not None and hasattr(progress, "log"):
        progress.log(msg)
    else:
        _LOG.info(msg)


def _build(cfg: BuildModelConfig, progress: Any):
    """The model and the list of input files read."""
    def say(msg: str) -> None:
        _say(progress, msg)

    if cfg.fibers is not None or cfg.masks:
        from ..imaging.nifti import load_volume

    src = Path(cfg.require_input())
    inputs = [src]
    muscle_ids, names, fibers = None, None, None
    tissue_map = cfg.tissue_map
    seg_masks: dict = {}
    if cfg.segmentation is not None:
        say(f"reading {cfg.segmentation}")
        seg = read_segmentation(cfg.segmentation)
        labels, affine = seg["labels"], seg["affine"]
        muscle_ids, names, fibers = seg["muscle_id"], seg["muscle_names"], seg["fiber"]
        seg_masks = seg["masks"]
        if muscle_ids is not None and muscle_ids.shape != labels.shape:
            raise InputError(f"{cfg.segmentation}: /muscle_id has shape {muscle_ids.shape}, /labels {labels.shape}")
        if fibers is not None and fibers.shape != (*labels.shape, 3):
            raise InputError(f"{cfg.segmentation}: /fiber has shape {fibers.shape}, expected {(*labels.shape, 3)}")
    if cfg.labels is not None:
        say(f"reading {cfg.labels}")
        lm = read_label_map(cfg.labels, descriptions=cfg.label_descriptions)
        for note in lm.notes:
            _LOG.warning(note)
        if cfg.label_descriptions is not None:
            inputs.append(Path(cfg.label_descriptions))
        if cfg.segmentation is not None:               # a corrected segmentation: on its grid, its muscles
            inputs.append(Path(cfg.segmentation))
            grid = (labels.shape, affine, Path(cfg.segmentation))
            muscles = list(names or [])
            muscle_ids, names = None, None
        else:
            grid, muscles = None, []
        labels, affine = _labels_on_grid(lm, grid)
        if lm.names:
            tissue_map = tissue_map_from_names(lm.names, cfg.label_names, [*muscles, *(cfg.muscle_fibers or {})],
                                               str(cfg.labels))
        elif cfg.label_names is not None:
            raise InputError(f"build_model.label_names: {cfg.labels} names none of its labels (a plain label map: "
                             "map its values with tissue_map, or give label_descriptions)")
    if cfg.fibers is not None:
        fv = load_volume(cfg.fibers, kind="vectors", components=cfg.fiber_components)
        if fv.data.ndim != 4 or fv.data.shape[3] != 3:
            raise InputError(f"fibers {cfg.fibers}: expected a 4-D image with 3 components (I, J, K, 3), "
                             f"got shape {fv.data.shape}")
        _same_grid("fibre image", Path(cfg.fibers), fv.data.shape, np.asarray(fv.affine, float), src, labels.shape, affine)
        fibers = fv.data
        inputs.append(Path(cfg.fibers))
    masks = dict(seg_masks)  # e.g. the aponeurosis: node set of that name
    for name, p in cfg.masks.items():
        mv = load_volume(p, kind="labels", allow_empty=True)
        _same_grid(f"mask '{name}'", Path(p), mv.data.shape, np.asarray(mv.affine, float), src, labels.shape, affine)
        masks[name] = np.asarray(mv.data) != 0
        if not masks[name].any():
            _LOG.warning("mask '%s' (%s) is empty: node set '%s' will be empty", name, p, name)
        inputs.append(Path(p))
    model = model_from_labels(
        labels, affine, tissue_map=tissue_map, fibers=fibers, muscle_fibers=cfg.muscle_fibers,
        fiber_fallback=cfg.fiber_fallback, masks=masks, muscle_ids=muscle_ids, muscle_names=names,
    )
    return model, inputs

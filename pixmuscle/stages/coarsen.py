"""Stage ``coarsen``: ``model.h5`` → coarse ``model_coarse.h5`` (paper §4.2, Fig. 9b)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from ..io.lineage import capture_warnings, stage_attrs
from ..io.model import load_model, save_model
from ..model.coarsen import coarsen_model


def run_coarsen(model_path: str | Path, factor: int, out_path: str | Path, config: Any = None, *,
                synthetic: bool = False) -> Path:
    """Coarsen a model file by ``factor`` in-plane and write the coarse model.

    Parameters
    ----------
    model_path : path
        Fine ``model.h5`` (schema ``pixmuscle.model`` v1).
    factor : int
        In-plane coarsening factor (≥ 1).
    out_path : path
        Destination file.
    config : CoarsenConfig or mapping, optional
        Stored in the file's ``config`` attribute (default ``{"factor": factor}``).
    synthetic : bool
        The inputs are synthetic phantoms (also taken from the input file's ``synthetic``).

    Returns
    -------
    pathlib.Path
        ``out_path``.
    """
    with capture_warnings() as warnings:
        model = load_model(model_path)
        coarse = coarsen_model(model, factor)
    return save_model(out_path, coarse, config=config if config is not None else {"factor": int(factor)},
                      inputs=[Path(model_path)], attrs=stage_attrs("coarsen", [model_path], warnings, synthetic=synthetic))

"""Checks of a subject's configuration that need no stage to run, done before any work starts.

Config loading (:mod:`pixmuscle.config`) validates each key on its own; what is checked here
needs several sections together or the file system:

* the output folder can be created and written (not a file, not read-only);
* every node-set boundary condition of ``solve`` names a set the model will have: the geometric
  sets of :data:`pixmuscle.model.nodesets.GEOMETRIC_SETS` plus the ``build_model.masks``
  names when the model is built in this run, else the sets of the existing model file.

Each failure is one :class:`~pixmuscle.errors.InputError` line naming the key.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from .errors import InputError
from .outdir import prepare_output_dir


def stage_folders(stages) -> set[Path]:
    """The folders a case's stages write into (a report stage: the folder holding ``report/``)."""
    return {Path(st.output).parent.parent if st.kind == "report" else Path(st.output).parent for st in stages}


def expected_node_sets(cfg: Any, stages) -> set[str] | None:
    """Names of the node sets the solved model(s) will have, or None when that cannot be known yet.

    Parameters
    ----------
    cfg : pixmuscle.pipeline.PipelineConfig
    stages : list of pixmuscle.plan.Stage
        The case's plan.
    """
    from .model.nodesets import GEOMETRIC_SETS

    if any(st.kind == "build-model" for st in stages):
        masks = getattr(cfg.build_model, "masks", None) or {}
        return set(GEOMETRIC_SETS) | set(masks)
    names = None
    for st in stages:  # from --from coarsen/solve: the sets of the model files the solves read
        if st.kind != "solve":
            continue
        sets = _sets_in(Path(st.kwargs["model_path"]))
        if sets is None:
            return None
        names = sets if names is None else names & sets
    return names


def _sets_in(path: Path) -> set[str] | None:
    import h5py

    try:
        with h5py.File(path, "r") as f:
            return set(f["sets"]) if "sets" in f else None
    except (OSError, KeyError):
        return None


def check_case(cfg: Any, stages) -> None:
    """Everything about one case that can be checked before its first stage runs.

    Parameters
    ----------
    cfg : pixmuscle.pipeline.PipelineConfig
    stages : list of pixmuscle.plan.Stage
        Its plan (:func:`pixmuscle.plan.plan_case`).

    Raises
    ------
    InputError
        See the module docstring.
    """
    for folder in sorted(stage_folders(stages) | {Path(cfg.output_dir)}):
        prepare_output_dir(folder)
    if cfg.solve is not None and any(st.kind == "solve" for st in stages):
        known = expected_node_sets(cfg, stages)
        if known is not None:
            for i, bc in enumerate(cfg.solve.boundary_conditions):
                if bc.nodes is not None and bc.nodes not in known:
                    raise InputError(f"solve.boundary_conditions[{i}].nodes: node set {bc.nodes!r} does not exist "
                                     f"(the model will have: {', '.join(sorted(known))}; add other sets with "
                                     "build_model.masks)")

"""Checks of a subject's configuration that need no stage to run, done before any work starts.

Config loading (:mod:`pixmuscle.config`) validates each key on its own; what is checked here
needs several sections together or the file system:

* the output folder can be created and written (not a file, not read-only);
* every node-set boundary condition of ``solve`` names a set the model will have: the geometric
  sets of :data:`pixmuscle.model.nodesets.GEOMETRIC_SETS` plus the ``build_model.masks``
  names when the model is built in this run, else the sets of the existing model file;
* when the model to solve exists already, the solve's time and results size
  (:func:`estimate_solve`, logged) and whether the results fit on the disk.

Each failure is one :class:`~pixmuscle.errors.InputError` line naming the key.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from .errors import InputError
from .outdir import prepare_output_dir

#: bytes per node and stored state of a results file: u, d (3 each), Cauchy stress (6), max principal (1), float64
RESULT_BYTES_PER_NODE_STEP = 13 * 8
#: the rough cost of one load step, s: ``a n^p + b n²`` with n = n_nodes / :data:`NODES_REF` and
#: ``STEP_SECONDS = (a, p, b)``, a least-squares fit in log to the whole sweeps at today's defaults on 2 cores
#: (benchmarks/results/bench_solve.json, ``"defaults": true`` and not superseded: their time less the
#: system build, per load step; refit and checked with ``benchmarks/fit_time_estimate.py``). The n² term
#: is the growth of the Krylov iterations with the model's size on top of the work per iteration,
#: which grows about like n.
STEP_SECONDS = (4.182, 0.633, 0.017)
#: the one-off cost of a solve, s: ``c n^q`` with ``SETUP_SECONDS = (c, q)``, the same sweeps' system build
#: (RK shape functions, SCNI and stabilisation operators: ``build_s``), fitted likewise; a solve of few
#: load steps is mostly this
SETUP_SECONDS = (3.112, 0.866)
NODES_REF = 5460


def estimate_solve(n_nodes: int, steps: int) -> tuple[float, float]:
    """Rough wall time and results size of one solve, before it starts.

    Parameters
    ----------
    n_nodes : int
        Nodes of the model.
    steps : int
        Load steps (``solve.steps``); the results hold ``steps + 1`` states.

    Returns
    -------
    seconds : float
        Order of magnitude only (one machine of docs/performance.md, default solver settings).
    nbytes : float
        Uncompressed size of the per-node fields of every stored state (gzip rarely halves it).
    """
    n = max(n_nodes, 1) / NODES_REF
    a, p, b = STEP_SECONDS
    c, q = SETUP_SECONDS
    seconds = c * n**q + steps * (a * n**p + b * n**2)
    return seconds, float(steps + 1) * n_nodes * RESULT_BYTES_PER_NODE_STEP


def check_solve_size(out_path: Path, n_nodes: int, steps: int, key: str = "solve.steps") -> tuple[float, float]:
    """Refuse a solve when not even half of its results fit on the disk (gzip rarely halves them).

    Returns
    -------
    (seconds, nbytes) of :func:`estimate_solve` (:func:`describe_estimate` words them).

    Raises
    ------
    OutputError
        Naming the output, ``key`` and the free space.
    """
    from .errors import OutputError
    from .outdir import _mb, free_bytes

    seconds, nbytes = estimate_solve(n_nodes, steps)
    free = free_bytes(Path(out_path).parent)
    if free < 0.5 * nbytes:
        raise OutputError(f"{out_path}: not enough free disk space for the results of this solve: {key} = {steps} "
                          f"load steps of a {n_nodes}-node model need about {_mb(nbytes)}, {_mb(free)} free; "
                          f"lower {key} (or use a coarser model) or free disk space")
    return seconds, nbytes


def describe_estimate(n_nodes: int, steps: int, seconds: float, nbytes: float) -> str:
    """``"73753 nodes × 10 load steps: about 5 min and 84.4 MB of results (rough estimate)"``."""
    from .outdir import _mb

    return (f"{n_nodes} nodes × {steps} load steps: about {_duration(seconds)} and {_mb(nbytes)} of results "
            "(rough estimate)")


def _duration(seconds: float) -> str:
    if seconds < 90:
        return f"{max(seconds, 1):.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


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


def _nodes_in(path: Path) -> int | None:
    import h5py

    try:
        with h5py.File(path, "r") as f:
            return int(f["nodes/X"].shape[0]) if "nodes/X" in f else None
    except (OSError, KeyError):
        return None


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
        for st in stages:  # the model exists (--from solve): its size and the steps, before any stage runs
            n = _nodes_in(Path(st.kwargs["model_path"])) if st.kind == "solve" else None
            if n is not None:
                prepare_output_dir(Path(st.output).parent)
                check_solve_size(Path(st.output), n, cfg.solve.steps)
        known = expected_node_sets(cfg, stages)
        if known is not None:
            for i, bc in enumerate(cfg.solve.boundary_conditions):
                if bc.nodes is not None and bc.nodes not in known:
                    raise InputError(f"solve.boundary_conditions[{i}].nodes: node set {bc.nodes!r} does not exist "
                                     f"(the model will have: {', '.join(sorted(known))}; add other sets with "
                                     "build_model.masks)")

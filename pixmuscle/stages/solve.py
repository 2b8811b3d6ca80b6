"""Stage ``solve``: ``model.h5`` → ``results.h5`` (schema ``pixmuscle.results`` v1, paper §3 and §5)."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from .. import parallel
from ..config import parse_section
from ..errors import InputError, OutputError, PixmuscleError, SolverError
from ..imaging.nifti import load_volume
from ..io.checkpoint import checkpoint_key, checkpoint_path, load_checkpoint, save_checkpoint
from ..io.lineage import capture_warnings, stage_attrs
from ..io.model import load_model
from ..io.results import StepStore, save_results
from ..mechanics.activation import ActivationRamp, activation_ramp, per_muscle_summary
from ..mechanics.boundary import check_boundary_conditions
from ..mechanics.config import SolveConfig
from ..mechanics.solve import solve
from ..model.tissues import MUSCLE
from ..outdir import prepare_output_dir
from ..preflight import check_solve_size, describe_estimate
from ..progress import newton_feed
from ..progress import progress as _progress

_LOG = logging.getLogger(__name__)


def model_activation(model, cfg: SolveConfig) -> ActivationRamp | None:
    """Per-node activation of ``cfg.activation`` for this model (reads the activation image); None if uniform.

    Raises InputError for muscle names the model does not have and for a bad image.
    """
    if cfg.uniform_activation:
        return None
    image = None
    path = cfg.activation.get("image")
    if path is not None:
        vol = load_volume(path, kind="image", allow_empty=True)
        image = (vol.data, vol.affine)
    return activation_ramp(model, cfg.activation, image)


def _per_muscle(cfg: SolveConfig, ramp: ActivationRamp | None, model) -> dict:
    """Mean α per muscle at the start and end of the ramp (stored in the results' solver_info)."""
    if ramp is None:
        ramp = ActivationRamp.uniform(cfg.alpha_from, cfg.alpha_to, model.tissue == MUSCLE)
    return per_muscle_summary(ramp, model)


def _describe(cfg: SolveConfig, ramp: ActivationRamp | None, model) -> str:
    if ramp is None:
        return f"{cfg.alpha_from:.3g} → {cfg.alpha_to:.3g}"
    per = per_muscle_summary(ramp, model)
    return ", ".join(f"{k} {a:.3g} → {b:.3g}" for k, (a, b) in per.items()) or "none (no muscle nodes)"


def _resume(path: Path, key: str, n_steps: int) -> list | None:
    """The converged steps of an interrupted solve from its checkpoint, or None (none, unreadable, or
    made by another model or configuration: logged and not used)."""
    if not path.exists():
        return None
    try:
        ckpt = load_checkpoint(path)
    except (PixmuscleError, OSError) as exc:
        _LOG.warning("ignoring the checkpoint %s: it cannot be read (%s); solving from the start", path, exc)
        return None
    if ckpt.key != key or ckpt.n_steps != n_steps:
        _LOG.warning("ignoring the checkpoint %s: it was made with another model file or solve configuration; "
                     "solving from the start", path)
        return None
    if not ckpt.records:
        return None
    k = ckpt.records[-1].step
    _LOG.info("resuming from load step %d of %d, checkpoint %s", k, n_steps, path)
    return ckpt.records


class _Checkpointer:
    """Writes the converged steps after each step; a refused write is logged once and checkpoints stop."""

    def __init__(self, path: Path, key: str, n_steps: int):
        self.path, self.key, self.n_steps, self.on = path, key, n_steps, True

    def __call__(self, records) -> None:
        if not self.on:
            return
        try:
            save_checkpoint(self.path, records, key=self.key, n_steps=self.n_steps)
        except OutputError as exc:
            self.on = False
            _LOG.warning("cannot write the checkpoint (%s); the solve goes on without one", exc)

    def remove(self) -> None:
        self.path.unlink(missing_ok=True)


def run_solve(model_path: str | Path, cfg: SolveConfig | Mapping | None, out_path: str | Path, progress: Any = None, *,
              synthetic: bool = False) -> Path:
    """Solve a model file and write the results file.

    Parameters
    ----------
    model_path : path
        ``model.h5`` (schema ``pixmuscle.model`` v1).
    cfg : SolveConfig or mapping
        The ``solve`` section (a mapping is validated with :func:`pixmuscle.config.parse_section`).
    out_path : path
        Destination ``results.h5``.
    progress : object with ``advance(n=1, **fields)``, None or False
        Progress sink; None (default): a progress bar "load step k/m" showing α and the Newton
        residual; False: no progress display.
    synthetic : bool
        The inputs are synthetic phantoms (also taken from the model file's ``synthetic``).

    Returns
    -------
    pathlib.Path
        ``out_path``.

    Raises
    ------
    InputError
        Bad model file or configuration.
    SolverError
        A load step failed after all cutbacks. The results file is still written, with the
        converged steps and ``status = "failed: ..."``, before the error is raised.

    Notes
    -----
    Each converged load step is written to the checkpoint ``<out_path>.checkpoint``
    (:mod:`pixmuscle.io.checkpoint`). When the solve is killed, the same call resumes after the
    last converged step, if the checkpoint was made from the same model file(s), ``solve``
    section and package version (else it is ignored, with a warning). The checkpoint is removed
    once the results file is written, or when a load step fails (the same call would fail again).
    """
    if cfg is None:
        raise InputError("solve: the configuration has no `solve` section")
    if not isinstance(cfg, SolveConfig):
        cfg = parse_section(SolveConfig, cfg, "solve")
    with capture_warnings() as warnings:
        model = load_model(model_path)
        check_boundary_conditions(model, list(cfg.boundary_conditions))  # before the (long) set-up
        # log the time and size estimate; refuse to start when not even half of the results fit
        prepare_output_dir(Path(out_path).parent, "output folder")
        estimate = check_solve_size(Path(out_path), model.n_nodes, cfg.steps)
        _LOG.info("solve: %s", describe_estimate(model.n_nodes, cfg.steps, *estimate))
        ramp = model_activation(model, cfg)
        falling = {k: ab for k, ab in _per_muscle(cfg, ramp, model).items() if ab[1] < ab[0]}
        if falling:
            _LOG.warning("solve.activation: decreasing ramp (relaxation) for %s; allowed: the curve runs from high to "
                         "low activation and F_max is usually at step 0",
                         ", ".join(f"{k} {a:.3g} → {b:.3g}" for k, (a, b) in falling.items()))
        _LOG.info("solve: %d nodes, %d load steps, activation %s", model.n_nodes, cfg.steps, _describe(cfg, ramp, model))
        inputs = [Path(model_path)] + ([cfg.activation["image"]] if cfg.activation.get("image") is not None else [])
        root = parallel.rank() == 0  # under mpiexec only rank 0 shows progress and writes the results
        if not root:
            progress = False
        # converged steps are checkpointed beside the results so that a killed solve resumes where it
        # was; under mpiexec rank 0 writes it (the whole model's d) and every rank reads it to resume
        keep = _Checkpointer(checkpoint_path(out_path), checkpoint_key(cfg, inputs), cfg.steps)
        # each converged step's nodal fields wait in a file beside the results, not in memory
        store = StepStore(out_path) if root else None
        kw = dict(activation=ramp, resume=keep and _resume(keep.path, keep.key, cfg.steps), on_checkpoint=keep,
                  store=store)
        try:
            if progress is None:
                with _progress(cfg.steps + 1, "load step") as bar, newton_feed(bar):
                    results = solve(model, cfg, progress=bar, **kw)
            else:
                results = solve(model, cfg, progress=progress or None, **kw)
        except SolverError as exc:
            partial = getattr(exc, "results", None)
            if partial is not None and root:
                partial.info["activation"] = _per_muscle(cfg, ramp, model)
                save_results(out_path, partial, config=cfg, inputs=inputs,
                             attrs=stage_attrs("solve", inputs, warnings, synthetic=synthetic))
                _LOG.error("solve failed; converged steps written to %s (status: %s)", out_path, partial.status)
                exc.results_path = str(out_path)  # the CLI prints it
            if root:  # the same command would fail the same way: nothing to resume
                keep.remove()
            raise
        finally:
            if store is not None:  # read back into the results by now, or not wanted any more
                store.remove()
    if not root:
        return Path(out_path)
    results.info["activation"] = _per_muscle(cfg, ramp, model)
    try:
        save_results(out_path, results, config=cfg, inputs=inputs,
                     attrs=stage_attrs("solve", inputs, warnings, synthetic=synthetic))
    except OSError:  # e.g. a full disk: the solve is not lost
        if keep.path.exists():
            _LOG.warning("the converged load steps are kept in %s: run the same command again to resume from "
                         "them", keep.path)
        raise
    keep.remove()
    info = results.info
    _LOG.info("solve: done in %.1f s (build %.1f s, %d assemblies %.1f s, linear solves %.1f s)", info.get("total_s", 0.0),
              info.get("build_s", 0.0), info.get("n_assembly", 0), info.get("assembly_s", 0.0),
              info.get("linear_setup_s", 0.0) + info.get("linear_solve_s", 0.0))
    return Path(out_path)

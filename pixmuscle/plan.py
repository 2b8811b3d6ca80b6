"""The pipeline as data: each case is a chain of :class:`Stage` descriptions that a runner executes.

A stage names the function that does the work (``module:function``, imported only when the stage
runs), its keyword arguments, the file it writes with that file's schema and version, the config
section that produced it and the files it reads. :func:`plan_case` turns one validated case
configuration into that chain; :func:`execute_stage` runs one stage, or skips it when its output is
up to date. The runners (:mod:`pixmuscle.runners.serial`, :mod:`pixmuscle.runners.dask`) only decide
where and in which order stages execute; nothing here knows about them.

A stage is skipped when its output exists, has the right schema and version, and its provenance
records the same config-section hash and the same SHA-256 for every input file. A solve whose
checkpoint (:mod:`pixmuscle.io.checkpoint`) lies beside its output was interrupted and always runs.
"""

from __future__ import annotations

import dataclasses
import importlib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from .config import parse_section
from .errors import InputError, Interrupted, SolverError
from .io import force_length as _force_length
from .io import model as _model
from .io import muscle_forces as _muscle_forces
from .io import results as _results
from .io import segmentation as _segmentation
from .store import config_hash, sha256_file

#: the CLI stages in pipeline order
STAGES = ("segment", "build-model", "coarsen", "solve", "report")

#: stage kind → (schema, version) of the file it writes (None: not an HDF5 stage file, always runs)
SCHEMAS = {
    "segment": (_segmentation.SCHEMA, _segmentation.VERSION),
    "perturb": (_segmentation.SCHEMA, _segmentation.VERSION),
    "build-model": (_model.SCHEMA, _model.VERSION),
    "coarsen": (_model.SCHEMA, _model.VERSION),
    "solve": (_results.SCHEMA, _results.VERSION),
    "muscle-forces": (_muscle_forces.SCHEMA, _muscle_forces.VERSION),
    "force-length": (_force_length.SCHEMA, _force_length.VERSION),
    "report": None,
}

#: stage kind → config section it depends on
SECTION_OF = {"segment": "segment", "perturb": "uncertainty", "build-model": "build_model", "coarsen": "coarsen", "solve": "solve",
              "muscle-forces": "muscle_forces", "force-length": "force_length", "report": "report"}


@dataclasses.dataclass(frozen=True)
class Stage:
    """One step of a case: what runs, what it reads and what it writes.

    Attributes
    ----------
    kind : str
        One of :data:`STAGES`.
    label : str
        Name shown in progress and summaries (``"solve (coarse)"`` when several models are solved).
    action : str
        ``"module:function"`` called as ``function(**kwargs)``.
    kwargs : dict
        Keyword arguments of ``action`` (plain, picklable data: config dataclasses and paths).
    output : Path
        The file the stage writes.
    config : object
        The config section recorded in (and compared with) the output's provenance.
    inputs : tuple of Path
        Files the stage reads (config inputs and upstream outputs); those that exist when the
        stage runs must be recorded in the output's provenance for it to be skipped.
    on_failure : Stage, optional
        Run when this stage fails with a :class:`~pixmuscle.errors.SolverError` (a solve's report
        stage: the report of the converged steps must replace the report of an older run).
    config_dir : Path, optional
        Folder of the config file: the output's provenance gives input paths relative to it too.
    plugins : tuple of Path
        Plugin files (:mod:`pixmuscle.plugins`) the stage depends on: imported before it runs and
        recorded among its inputs.
    """

    kind: str
    label: str
    action: str
    kwargs: dict
    output: Path
    config: Any = None
    inputs: tuple = ()
    on_failure: Any = None
    config_dir: Path | None = None
    plugins: tuple = ()

    @property
    def schema(self) -> tuple[str, int] | None:
        return SCHEMAS[self.kind]


def up_to_date(output: Path, schema: str, version: int, config: Any, inputs: list[Path]) -> bool:
    """True when ``output`` was made from this config section and these exact input files."""
    from .store import read_meta

    if not output.exists():
        return False
    try:
        meta = read_meta(output)
    except OSError:
        return False
    if meta["schema"] != schema or meta["schema_version"] != version:
        return False
    prov = meta["provenance"]
    if prov.get("config_sha256") != config_hash(config):
        return False
    recorded = prov.get("inputs", {})
    for p in inputs:
        if str(p) not in recorded:
            return False
    for p, sha in recorded.items():
        if not Path(p).exists() or sha256_file(p) != sha:
            return False
    return True


def is_up_to_date(stage: Stage) -> bool:
    """True when ``stage`` would be skipped (its output matches its config and inputs)."""
    if stage.schema is None:
        return False
    if stage.kind == "solve":
        from .io.checkpoint import checkpoint_path

        if checkpoint_path(stage.output).exists():  # a solve was interrupted here: run it (it resumes)
            return False
    schema, version = stage.schema
    return up_to_date(stage.output, schema, version, stage.config, [p for p in stage.inputs if p.exists()])


def execute_stage(stage: Stage, force: bool = False) -> str:
    """Run one stage unless its output is up to date.

    Returns
    -------
    str
        ``"ran"`` or ``"skipped"``.
    """
    if not force and is_up_to_date(stage):
        return "skipped"
    from .plugins import import_plugins
    from .store import config_folder, plugin_inputs

    import_plugins(stage.plugins)
    module, func = stage.action.split(":")
    # the report folder itself is put in place as a unit by the stage (never created empty here)
    (stage.output.parent.parent if stage.kind == "report" else stage.output.parent).mkdir(parents=True, exist_ok=True)
    try:
        with config_folder(stage.config_dir), plugin_inputs(stage.plugins):
            getattr(importlib.import_module(module), func)(**stage.kwargs)
    except SolverError as exc:
        if stage.on_failure is not None:
            exc.report = _after_failure(stage.on_failure)  # the CLI prints it
        raise
    except KeyboardInterrupt as exc:  # Ctrl-C or SIGTERM: say which stage was running
        if not isinstance(exc, Interrupted):
            exc = Interrupted("SIGINT")
        if exc.stage is None:
            exc.stage = stage.label
        raise exc from None
    return "ran"


def _after_failure(report: Stage) -> str | None:
    """Report of a failed solve's partial results, returning its path; if even that fails, no report
    (never a stale one) and None."""
    import logging
    import shutil

    from .errors import PixmuscleError

    log = logging.getLogger("pixmuscle.plan")
    folder = Path(report.kwargs["outdir"])
    try:
        module, func = report.action.split(":")
        index = getattr(importlib.import_module(module), func)(**report.kwargs)
        log.error("the solve failed; the report shows its converged steps: %s", index)
        return str(index)
    except (PixmuscleError, OSError) as exc:
        shutil.rmtree(folder, ignore_errors=True)
        log.error("the solve failed and its report could not be written (%s); the older report was removed", exc)
        return None


#: the ``--from`` stage that redoes the output of each stage kind
RERUN_FROM = {"segment": "segment", "perturb": "build-model", "build-model": "build-model", "coarsen": "coarsen", "solve": "solve",
              "muscle-forces": "solve", "force-length": "solve"}

_UNSET = "(not set)"


@dataclasses.dataclass(frozen=True)
class Mismatch:
    """An upstream stage file that no longer matches the current config (or its own inputs).

    Attributes
    ----------
    stage : str
        Kind of the upstream stage (``"solve"``).
    file : Path
        Its output file, which the run would read as it is.
    rerun_from : str
        The ``--from`` stage that remakes it.
    key : str or None
        First config key (dotted path) whose value differs; None when an input file changed.
    recorded, current : object
        The key's value in the file's recorded config and in the current config.
    changed_input : str or None
        An input file of that stage whose content changed since the file was made.
    """

    stage: str
    file: Path
    rerun_from: str
    key: str | None = None
    recorded: Any = None
    current: Any = None
    changed_input: str | None = None

    def describe(self) -> str:
        """What differs, in one clause (no advice)."""
        if self.key is not None:
            return (f"{self.key} is {self.current!r} in the config but {self.file.name} was made with "
                    f"{self.recorded!r}")
        return f"{self.file.name} was made from another version of {self.changed_input} (changed since)"


def _tree(obj: Any) -> Any:
    """A config section as plain nested dicts and lists, keeping :class:`~pathlib.Path` values."""
    import numpy as np

    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: _tree(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, Mapping):
        return {(k if isinstance(k, (str, int)) else str(k)): _tree(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_tree(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def _first_difference(recorded: Any, current: Any, prefix: str, same_file) -> tuple[str, Any, Any] | None:
    """First (key path, recorded value, current value) where a recorded config tree and the current
    one differ; a path is the same when ``same_file(recorded, current)`` says so."""
    if isinstance(recorded, dict) and isinstance(current, dict):
        for k in [*current, *(k for k in recorded if k not in current)]:
            key = f"{prefix}.{k}" if prefix else str(k)
            if k not in recorded or k not in current:
                return key, recorded.get(k, _UNSET), current.get(k, _UNSET)
            found = _first_difference(recorded[k], current[k], key, same_file)
            if found:
                return found
        return None
    if isinstance(recorded, list) and isinstance(current, list) and len(recorded) == len(current):
        for i, (a, b) in enumerate(zip(recorded, current, strict=True)):
            found = _first_difference(a, b, f"{prefix}[{i}]", same_file)
            if found:
                return found
        return None
    if isinstance(current, Path):
        return None if same_file(recorded, current) else (prefix, recorded, str(current))
    return None if recorded == current else (prefix, recorded, current)


def stage_mismatch(stage: Stage) -> Mismatch | None:
    """How an existing stage file differs from what ``stage`` would make now (None: it matches, or
    it is missing or not a stage file, which the stage reading it reports itself).

    Config values are compared as recorded in the file; a file path is the same when it names a file
    with the content the stage read (so a copied or moved output folder is not stale). An input file
    whose content is not among those the stage read is a mismatch too.
    """
    import yaml

    from .store import read_meta

    if stage.schema is None or not stage.output.is_file():
        return None
    try:
        meta = read_meta(stage.output)
    except (OSError, ValueError):
        return None
    prov = meta["provenance"]
    rerun = RERUN_FROM[stage.kind]
    read = set(prov.get("inputs", {}).values())
    digests: dict[Path, str] = {}

    def digest(p: Path) -> str | None:
        if p not in digests and p.exists():
            digests[p] = sha256_file(p)
        return digests.get(p)

    def same_file(rec: Any, cur: Path) -> bool:
        return str(rec) == str(cur) or (digest(cur) is not None and digest(cur) in read)

    if prov.get("config_sha256") != config_hash(stage.config):
        text = meta["config"]
        recorded = yaml.safe_load(text.decode() if isinstance(text, bytes) else text or "{}")
        prefix = SECTION_OF[stage.kind] if stage.kind in STAGES else ""
        found = _first_difference(recorded, _tree(stage.config), prefix, same_file)
        if found:
            key, old, new = found
            return Mismatch(stage.kind, stage.output, rerun, key=key, recorded=old, current=new)
    for p in stage.inputs:
        d = digest(Path(p))
        if d is not None and d not in read:
            return Mismatch(stage.kind, stage.output, rerun, changed_input=Path(p).name)
    return None


def stale_upstream(cfg: Any, start: str | None) -> list[Mismatch]:
    """The stage files before ``--from start`` that a run would read although they were made under
    another config (or from input files that changed since), in pipeline order.

    Parameters
    ----------
    cfg : pixmuscle.pipeline.PipelineConfig
        One case.
    start : str or None
        ``--from``: the stages before it are not run, their files are used as they are.
    """
    a, _ = stage_range(start, None)
    if a == 0:
        return []
    try:
        upstream = plan_case(cfg, None, STAGES[a - 1])
    except InputError:  # e.g. no solve section for --from report: nothing to compare
        return []
    return [m for m in map(stage_mismatch, upstream) if m is not None]


def stale_message(mismatches: list[Mismatch], config: str | Path, case: str = "") -> str:
    """One line refusing a run on stale inputs: the first difference and the stage to rerun from."""
    m = mismatches[0]
    who = f"{case}: " if case else ""
    return (f"{who}{m.describe()}: rerun from {m.rerun_from} (pixmuscle run {config} --from {m.rerun_from}), "
            "or pass --allow-stale to go on with the older results")


def with_stale_note(stages: list[Stage], mismatches: list[Mismatch]) -> list[Stage]:
    """The stages with the mismatches handed to the report stage (shown on its first screen)."""
    if not mismatches:
        return stages
    lines = [f"{m.describe()} (rerun from {m.rerun_from} to update it)" for m in mismatches]

    def noted(report: Stage) -> Stage:
        extra = {**report.kwargs.get("extra", {}), "stale_inputs": lines}
        return dataclasses.replace(report, kwargs={**report.kwargs, "extra": extra})

    out = []
    for st in stages:
        if st.kind == "report":
            st = noted(st)
        elif st.on_failure is not None:
            st = dataclasses.replace(st, on_failure=noted(st.on_failure))
        out.append(st)
    return out


def stage_range(start: str | None, until: str | None) -> tuple[int, int]:
    """Indices into :data:`STAGES` of ``--from`` / ``--until`` (inclusive)."""
    def idx(name, default):
        if name is None:
            return default
        name = name.replace("_", "-")
        if name not in STAGES:
            raise InputError(f"unknown stage '{name}': expected one of {', '.join(STAGES)}")
        return STAGES.index(name)

    a, b = idx(start, 0), idx(until, len(STAGES) - 1)
    if a > b:
        raise InputError(f"--from {start} comes after --until {until}")
    return a, b


def config_paths(section: Any) -> tuple[Path, ...]:
    """Every path named anywhere in a config section (its input files, existing or not)."""
    found: list[Path] = []

    def walk(v):
        if dataclasses.is_dataclass(v):
            for f in dataclasses.fields(v):
                walk(getattr(v, f.name))
        elif isinstance(v, Mapping):
            for x in v.values():
                walk(x)
        elif isinstance(v, (list, tuple)):
            for x in v:
                walk(x)
        elif isinstance(v, Path):
            found.append(v)

    walk(section)
    return tuple(found)


def _with_segmentation(bm: Any, seg_path: Path, base_dir: Path) -> Any:
    """The build_model section pointed at this subject's segmentation.h5 (a label map it names, a
    segmentation corrected by hand, then replaces the segmentation's labels)."""
    from .model.config import BuildModelConfig

    if bm is None:
        bm = parse_section(BuildModelConfig, {"segmentation": str(seg_path)}, "build_model", base_dir)
    return dataclasses.replace(bm, segmentation=seg_path)


def plan_case(cfg: Any, start: str | None = None, until: str | None = None) -> list[Stage]:
    """The chain of stages of one case, in execution order.

    Parameters
    ----------
    cfg : pixmuscle.pipeline.PipelineConfig
        One validated case (a subject, or a subject × study combination). Stages whose config
        sections the study does not vary write into ``cfg.shared_dir`` (shared by the cases of
        that subject), the others into ``cfg.output_dir``.
    start, until : str, optional
        First and last stage kind (``--from`` / ``--until``).

    Returns
    -------
    list of Stage
    """
    a, b = stage_range(start, until)
    active = set(STAGES[a:b + 1])

    seg_path = stage_dir(cfg, "segment") / "segmentation.h5"
    model_path = stage_dir(cfg, "build-model") / "model.h5"
    coarse_path = stage_dir(cfg, "coarsen") / "model_coarse.h5"
    stages: list[Stage] = []

    if cfg.segment is not None and "segment" in active:
        stages.append(Stage("segment", "segment", "pixmuscle.stages.segment:run_segment",
                            {"cfg": cfg.segment, "out_path": seg_path, "synthetic": cfg.synthetic}, seg_path, cfg.segment,
                            config_paths(cfg.segment)))
    bm = cfg.build_model
    if bm is None and cfg.segment is None:
        raise InputError(f"{cfg.name}: neither a `segment` nor a `build_model` section: nothing to build a model from")
    if cfg.segment is not None and getattr(cfg, "realisation", 0):
        # an uncertainty realisation: its own segmentation, the noise-free one perturbed (pixmuscle.stages.perturb)
        noisy = stage_dir(cfg, "perturb") / "segmentation.h5"
        if "build-model" in active:
            unc = {"segment": cfg.segment, "uncertainty": cfg.uncertainty, "realisation": cfg.realisation}
            stages.append(Stage("perturb", "perturb", "pixmuscle.stages.perturb:run_perturb",
                                {"segment_cfg": cfg.segment, "uncertainty_cfg": cfg.uncertainty,
                                 "realisation": cfg.realisation, "segmentation_path": seg_path, "out_path": noisy,
                                 "synthetic": cfg.synthetic}, noisy, unc, (seg_path, *cfg.segment.dti_files())))
    if cfg.segment is not None:
        bm = _with_segmentation(bm, noisy if getattr(cfg, "realisation", 0) else seg_path, cfg.base_dir)
    if "build-model" in active:
        stages.append(Stage("build-model", "build-model", "pixmuscle.stages.build_model:run_build_model",
                            {"cfg": bm, "out_path": model_path, "synthetic": cfg.synthetic}, model_path, bm, config_paths(bm)))
    if cfg.coarsen is not None and cfg.coarsen.enabled and "coarsen" in active:
        stages.append(Stage("coarsen", "coarsen", "pixmuscle.stages.coarsen:run_coarsen",
                            {"model_path": model_path, "factor": cfg.coarsen.factor, "out_path": coarse_path,
                             "config": cfg.coarsen, "synthetic": cfg.synthetic}, coarse_path, cfg.coarsen, (model_path,)))
    results, experiments = results_paths(cfg), {}
    for which in cfg.models:
        mpath = coarse_path if which == "coarse" else model_path
        rpath = results[which]
        if "solve" in active:
            if cfg.solve is None:
                raise InputError(f"{cfg.name}: no `solve` section")
            stages.append(Stage("solve", f"solve ({which})", "pixmuscle.stages.solve:run_solve",
                                {"model_path": mpath, "cfg": cfg.solve, "out_path": rpath, "synthetic": cfg.synthetic}, rpath, cfg.solve,
                                (mpath,)))
        experiments.update(_experiment_stages(cfg, which, mpath, rpath, stages if "solve" in active else None))
    if "report" in active:
        # the headline is the finest model (the answer); a coarser one gives its discretisation estimate
        headline = "fine" if "fine" in cfg.models else cfg.models[0]
        main = results[headline]
        extra = {"title": cfg.title, "synthetic": cfg.synthetic, "subject": cfg.subject or cfg.name,
                 "compare": {k: str(v) for k, v in results.items()}}
        # per-muscle forces and force-length curves of the headline model, the DWI fit's QC maps
        extra.update({k[:-len(f"_{headline}")]: str(v) for k, v in experiments.items() if k.endswith(f"_{headline}")})
        if cfg.segment is not None and getattr(cfg.segment, "dwi", None) is not None:
            extra["dwi_qc"] = str(seg_path.with_name("segmentation_qc"))
        if cfg.segment is not None and getattr(cfg.segment, "bias_correction", "none") != "none":
            extra["bias_field"] = str(seg_path.with_name("segmentation_bias_field.nii.gz"))
        if cfg.params:
            extra["study"] = {k: v for k, v in cfg.params}
        out = cfg.output_dir / "report"
        report = Stage("report", "report", "pixmuscle.stages.report:run_report",
                       {"results_path": main, "outdir": out, "cfg": cfg.report, "extra": extra},
                       out / "index.html", cfg.report, tuple(results.values()))
        # a failed solve still gets its report (converged steps, reason), never an older run's
        stages = [dataclasses.replace(st, on_failure=report) if st.kind == "solve" else st for st in stages]
        stages.append(report)
    return [_with_plugins(dataclasses.replace(st, config_dir=getattr(cfg, "base_dir", None)), getattr(cfg, "plugins", ()))
            for st in stages]


#: stages that depend on the config's plugins (a material law: the solve and everything computed from it)
PLUGIN_STAGES = ("solve", "muscle-forces", "force-length", "report")


def _with_plugins(stage: Stage, plugins: tuple) -> Stage:
    """``stage`` with the plugin files among its inputs when its kind is one of :data:`PLUGIN_STAGES`."""
    if not plugins or stage.kind not in PLUGIN_STAGES:
        return stage
    failure = stage.on_failure and _with_plugins(stage.on_failure, plugins)
    return dataclasses.replace(stage, inputs=(*stage.inputs, *plugins), plugins=tuple(plugins), on_failure=failure)


def _experiment_stages(cfg: Any, which: str, mpath: Path, rpath: Path, stages: list | None) -> dict[str, Path]:
    """The multi-solve experiments of one model, after its solve: ``muscle_forces`` and
    ``force_length`` sections → stages appended to ``stages`` (None: only their output paths).

    Returns ``{"muscle_forces_<model>": path, "force_length_<model>": path}`` for the sections present.
    """
    out = {}
    mf, fl = getattr(cfg, "muscle_forces", None), getattr(cfg, "force_length", None)
    if mf is not None:
        p = cfg.output_dir / f"muscle_forces_{which}.h5"
        out[f"muscle_forces_{which}"] = p
        if stages is not None:
            stages.append(Stage("muscle-forces", f"muscle forces ({which})", "pixmuscle.stages.muscle_forces:run_muscle_forces",
                                {"model_path": mpath, "solve_cfg": cfg.solve, "cfg": mf, "out_path": p,
                                 "results_path": rpath, "synthetic": cfg.synthetic},
                                p, {"solve": cfg.solve, "muscle_forces": mf}, (mpath, rpath)))
    if fl is not None:
        p = cfg.output_dir / f"force_length_{which}.h5"
        out[f"force_length_{which}"] = p
        if stages is not None:
            image = cfg.solve.activation.get("image")
            stages.append(Stage("force-length", f"force-length ({which})", "pixmuscle.stages.force_length:run_force_length",
                                {"model_path": mpath, "solve_cfg": cfg.solve, "cfg": fl, "out_path": p,
                                 "synthetic": cfg.synthetic},
                                p, {"solve": cfg.solve, "force_length": fl}, (mpath, *([image] if image else []))))
    return out


def stage_dir(cfg: Any, kind: str) -> Path:
    """Folder of a stage's output: the case folder, or in a study the subject folder shared by its
    cases when the study varies neither this stage's config section nor any section before it."""
    if cfg.shared_dir is None or SECTION_OF[kind] in cfg.varied_sections():
        return cfg.output_dir
    return cfg.shared_dir


def results_paths(cfg: Any) -> dict[str, Path]:
    """model name → results file of a case (whether or not it exists yet)."""
    return {which: stage_dir(cfg, "solve") / f"results_{which}.h5" for which in cfg.models}

"""The whole pipeline: root config, stage chaining, skip/resume, cohorts.

Root YAML keys (all optional except what the chosen stages need)::

    title: text shown in reports
    synthetic: true          # inputs are synthetic phantoms (said plainly in the report)
    output_dir: out/demo     # relative to the config file; default out/<config stem>
    models: [coarse]         # which models to solve: fine, coarse or both (convergence check)
    segment: {...}           # pixmuscle.segmentation.config.SegmentConfig (omit to start from labels)
    build_model: {...}       # pixmuscle.model.config.BuildModelConfig
    coarsen: {...}           # pixmuscle.model.config.CoarsenConfig
    solve: {...}             # pixmuscle.mechanics.config.SolveConfig
    report: {...}            # pixmuscle.report.config.ReportConfig
    subjects:                # optional cohort: each entry = name + section overrides (deep-merged)
      - {name: young, build_model: {labels: young_labels.nii.gz}}

A stage is skipped when its output exists, has the right schema, and its provenance records the
same config-section hash and the same SHA-256 for every input file (``--force`` redoes it).
"""

from __future__ import annotations

import copy
import dataclasses
import importlib
import json
import logging
from pathlib import Path
from typing import Any

from .config import parse_section, read_yaml
from .errors import InputError, PixmuscleError
from .store import config_hash, sha256_file

_LOG = logging.getLogger("pixmuscle.pipeline")

STAGES = ("segment", "build-model", "coarsen", "solve", "report")

#: config section → (module, dataclass name)
SECTIONS = {
    "segment": ("pixmuscle.segmentation.config", "SegmentConfig"),
    "build_model": ("pixmuscle.model.config", "BuildModelConfig"),
    "coarsen": ("pixmuscle.model.config", "CoarsenConfig"),
    "solve": ("pixmuscle.mechanics.config", "SolveConfig"),
    "report": ("pixmuscle.report.config", "ReportConfig"),
}
_ROOT_KEYS = {"title", "synthetic", "output_dir", "models", "subjects", *SECTIONS}


@dataclasses.dataclass(frozen=True)
class PipelineConfig:
    """One subject's validated configuration (sections are None when absent)."""

    name: str
    title: str
    synthetic: bool
    output_dir: Path
    models: tuple
    base_dir: Path
    segment: Any = None
    build_model: Any = None
    coarsen: Any = None
    solve: Any = None
    report: Any = None


def _section_class(name: str):
    module, cls = SECTIONS[name]
    try:
        return getattr(importlib.import_module(module), cls)
    except ModuleNotFoundError:
        raise InputError(f"config section '{name}': this part of pixmuscle is not available yet ({module})") from None


def _deep_merge(base: dict, over: dict) -> dict:
    out = copy.deepcopy(base)
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _deep_merge(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out


def _parse_subject(raw: dict, name: str, where: str, base_dir: Path, default_out: Path) -> PipelineConfig:
    models = raw.get("models", None)
    if models is None:
        coarsen_on = raw.get("coarsen") is not None and (raw.get("coarsen") or {}).get("enabled", True)
        models = ["coarse"] if coarsen_on else ["fine"]
    if isinstance(models, str):
        models = [models]
    if not isinstance(models, list) or not models or any(m not in ("fine", "coarse") for m in models):
        raise InputError(f"{where}models: expected a list of 'fine' and/or 'coarse', got {models!r}")
    if "coarse" in models and raw.get("coarsen") is None:
        raise InputError(f"{where}models: 'coarse' asks for a coarsen section (e.g. coarsen: {{factor: 2}})")
    sections = {}
    for sec in SECTIONS:
        if sec in raw:
            sections[sec] = parse_section(_section_class(sec), raw[sec], f"{where}{sec}", base_dir)
    out = raw.get("output_dir")
    out_dir = (base_dir / out).resolve() if out else default_out
    return PipelineConfig(
        name=name, title=str(raw.get("title", name)), synthetic=bool(raw.get("synthetic", False)),
        output_dir=out_dir, models=tuple(models), base_dir=base_dir, **sections,
    )


def load_subjects(path: str | Path, *, strict: bool = True) -> list:
    """Read and validate a pipeline YAML; one entry per subject (one for a single-subject config).

    With ``strict=False`` a subject whose own section is invalid (a missing file, a bad key) is
    returned as a :class:`SubjectError` instead of raising, so a cohort can run the others.
    """
    path = Path(path)
    raw = read_yaml(path)
    unknown = sorted(set(raw) - _ROOT_KEYS)
    if unknown:
        import difflib

        close = difflib.get_close_matches(unknown[0], sorted(_ROOT_KEYS), n=1)
        hint = f"; did you mean '{close[0]}'?" if close else f"; valid keys: {', '.join(sorted(_ROOT_KEYS))}"
        raise InputError(f"{path}: {unknown[0]}: unknown top-level key{hint}")
    base_dir = path.parent.resolve()
    default_out = (base_dir / raw["output_dir"]).resolve() if raw.get("output_dir") else (Path.cwd() / "out" / path.stem).resolve()
    subjects = raw.get("subjects")
    common = {k: v for k, v in raw.items() if k not in ("subjects", "output_dir")}
    if subjects is None:
        return [_parse_subject(raw, path.stem, "", base_dir, default_out)]
    if not isinstance(subjects, list) or not subjects:
        raise InputError(f"{path}: subjects: expected a non-empty list of {{name: ..., <section overrides>}}")
    out = []
    for i, s in enumerate(subjects):
        if not isinstance(s, dict) or not isinstance(s.get("name"), str):
            raise InputError(f"{path}: subjects[{i}]: expected a mapping with a 'name' string")
        try:
            bad = sorted(set(s) - (_ROOT_KEYS - {"subjects", "output_dir"}) - {"name"})
            if bad:
                raise InputError(f"{path}: subjects[{i}].{bad[0]}: unknown key")
            merged = _deep_merge(common, {k: v for k, v in s.items() if k != "name"})
            out.append(_parse_subject(merged, s["name"], f"subjects[{i}].", base_dir, default_out / s["name"]))
        except InputError as exc:
            if strict:
                raise
            out.append(SubjectError(s["name"], str(exc), default_out / s["name"]))
    return out


@dataclasses.dataclass(frozen=True)
class SubjectError:
    """A cohort subject whose configuration could not be validated."""

    name: str
    error: str
    output_dir: Path


def load_config(path: str | Path) -> PipelineConfig:
    """Validated config of a single-subject YAML (the first subject of a cohort)."""
    return load_subjects(path)[0]


# --------------------------------------------------------------------------- skip logic
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


def _stage_range(start: str | None, until: str | None) -> tuple[int, int]:
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


def run_subject(cfg: PipelineConfig, *, force: bool = False, start: str | None = None,
                until: str | None = None) -> dict:
    """Run the stages for one subject; returns a summary dict (paths, report data)."""
    a, b = _stage_range(start, until)
    active = set(STAGES[a:b + 1])
    out = cfg.output_dir
    out.mkdir(parents=True, exist_ok=True)
    seg_path, model_path = out / "segmentation.h5", out / "model.h5"
    coarse_path = out / "model_coarse.h5"
    summary: dict = {"name": cfg.name, "output_dir": str(out), "skipped": [], "ran": []}

    def note(stage, ran):
        (summary["ran"] if ran else summary["skipped"]).append(stage)
        _LOG.info("[%s] %s: %s", cfg.name, stage, "done" if ran else "up to date, skipped")

    # segment ---------------------------------------------------------------------------
    if cfg.segment is not None and "segment" in active:
        from .stages.segment import run_segment

        inputs = _existing_paths(cfg.segment)
        if force or not up_to_date(seg_path, "pixmuscle.segmentation", 1, cfg.segment, inputs):
            run_segment(cfg.segment, seg_path)
            note("segment", True)
        else:
            note("segment", False)

    # build-model -------------------------------------------------------------------------
    bm = cfg.build_model
    if bm is None and cfg.segment is None:
        raise InputError(f"{cfg.name}: neither a `segment` nor a `build_model` section: nothing to build a model from")
    if cfg.segment is not None:
        bm = _with_segmentation(bm, seg_path, cfg)
    if "build-model" in active:
        from .stages.build_model import run_build_model

        inputs = _existing_paths(bm)
        if force or not up_to_date(model_path, "pixmuscle.model", 1, bm, inputs):
            run_build_model(bm, model_path)
            note("build-model", True)
        else:
            note("build-model", False)

    # coarsen -----------------------------------------------------------------------------
    if cfg.coarsen is not None and cfg.coarsen.enabled and "coarsen" in active:
        from .stages.coarsen import run_coarsen

        if force or not up_to_date(coarse_path, "pixmuscle.model", 1, cfg.coarsen, [model_path]):
            run_coarsen(model_path, cfg.coarsen.factor, coarse_path, config=cfg.coarsen)
            note("coarsen", True)
        else:
            note("coarsen", False)

    # solve -------------------------------------------------------------------------------
    results = {}
    for which in cfg.models:
        mpath = coarse_path if which == "coarse" else model_path
        rpath = out / f"results_{which}.h5"
        results[which] = rpath
        if "solve" in active:
            if cfg.solve is None:
                raise InputError(f"{cfg.name}: no `solve` section")
            from .stages.solve import run_solve

            if force or not up_to_date(rpath, "pixmuscle.results", 1, cfg.solve, [mpath]):
                run_solve(mpath, cfg.solve, rpath)
                note(f"solve ({which})", True)
            else:
                note(f"solve ({which})", False)
    summary["results"] = {k: str(v) for k, v in results.items()}

    # report ------------------------------------------------------------------------------
    if "report" in active:
        from .stages.report import run_report

        main = results[cfg.models[0]]
        extra = {"title": cfg.title, "synthetic": cfg.synthetic, "subject": cfg.name,
                 "compare": {k: str(v) for k, v in results.items()}}
        index = run_report(main, out / "report", cfg.report, extra=extra)
        summary["report"] = str(index)
        note("report", True)
        _LOG.info("[%s] report: %s", cfg.name, index)
    return summary


def _existing_paths(section: Any) -> list[Path]:
    """All existing file paths named anywhere in a config section (its inputs)."""
    found: list[Path] = []

    def walk(v):
        if dataclasses.is_dataclass(v):
            for f in dataclasses.fields(v):
                walk(getattr(v, f.name))
        elif isinstance(v, dict):
            for x in v.values():
                walk(x)
        elif isinstance(v, (list, tuple)):
            for x in v:
                walk(x)
        elif isinstance(v, Path) and v.is_file():
            found.append(v)

    walk(section)
    return found


def _with_segmentation(bm: Any, seg_path: Path, cfg: PipelineConfig) -> Any:
    """The build_model section pointed at this subject's segmentation.h5."""
    from .model.config import BuildModelConfig

    if bm is None:
        bm = parse_section(BuildModelConfig, {"segmentation": str(seg_path)}, "build_model", cfg.base_dir)
    fields = {f.name for f in dataclasses.fields(bm)}
    changes = {"segmentation": seg_path}
    if "labels" in fields:
        changes["labels"] = None
    return dataclasses.replace(bm, **changes)


def run_pipeline(path: str | Path, *, force: bool = False, start: str | None = None,
                 until: str | None = None) -> bool:
    """Run every subject of a config; a failing subject is reported and the others go on.

    Returns True when every subject succeeded.
    """
    subjects = load_subjects(path, strict=False)
    summaries, failures = [], []
    for i, cfg in enumerate(subjects, 1):
        if len(subjects) > 1:
            _LOG.info("subject %d of %d: %s", i, len(subjects), cfg.name)
        if isinstance(cfg, SubjectError):
            _LOG.error("subject %s: invalid configuration: %s", cfg.name, cfg.error)
            failures.append({"name": cfg.name, "error": cfg.error})
            continue
        try:
            summaries.append(run_subject(cfg, force=force, start=start, until=until))
        except PixmuscleError as exc:
            if len(subjects) == 1:
                raise
            _LOG.error("subject %s failed: %s", cfg.name, exc)
            failures.append({"name": cfg.name, "error": str(exc)})
        except Exception as exc:  # a bug in one subject must not lose the others
            if len(subjects) == 1:
                raise
            _LOG.exception("subject %s failed with an unexpected error", cfg.name)
            failures.append({"name": cfg.name, "error": f"{type(exc).__name__}: {exc}"})
    if len(subjects) > 1:
        cohort_dir = subjects[0].output_dir.parent
        _write_cohort(cohort_dir, summaries, failures)
    return not failures


def _write_cohort(cohort_dir: Path, summaries: list[dict], failures: list[dict]) -> None:
    cohort_dir.mkdir(parents=True, exist_ok=True)
    (cohort_dir / "cohort_status.json").write_text(json.dumps({"ok": summaries, "failed": failures}, indent=2))
    try:
        from .report.cohort import cohort_summary
    except ModuleNotFoundError:
        return
    cohort_summary([s for s in summaries if "results" in s], cohort_dir, failures=failures)

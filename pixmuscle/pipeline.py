"""The whole pipeline: root config → cases → a runner → per-case reports, cohort and study pages.

Root YAML keys (all optional except what the chosen stages need)::

    title: text shown in reports
    plugins: [my_law.py]     # Python files (relative to this file) or module names imported first, so
                             # that the laws, runners or report sections they register can be named
    synthetic: true          # inputs are synthetic phantoms (said plainly in the report)
    output_dir: out/demo     # relative to the config file; default out/<config stem>
    models: [coarse]         # which models to solve: fine, coarse or both (convergence check: the
                             # report's headline is then the fine model, the coarse one its
                             # discretisation estimate)
    segment: {...}           # pixmuscle.segmentation.config.SegmentConfig (omit to start from labels)
    build_model: {...}       # pixmuscle.model.config.BuildModelConfig
    coarsen: {...}           # pixmuscle.model.config.CoarsenConfig
    solve: {...}             # pixmuscle.mechanics.config.SolveConfig
    muscle_forces: {...}     # pixmuscle.mechanics.experiments.MuscleForcesConfig (end force split by muscle)
    force_length: {...}      # pixmuscle.mechanics.experiments.ForceLengthConfig (end-displacement sweep)
    report: {...}            # pixmuscle.report.config.ReportConfig
    subjects:                # optional cohort: each entry = name + section overrides (deep-merged)
      - {name: young, build_model: {labels: young_labels.nii.gz}}
    study:                   # optional parameter study (pixmuscle.study): every combination × subject
      vary: {solve.materials.muscle.sigma_max: [20, 25, 30]}
    execution:               # optional: where the cases run (pixmuscle.runners; --workers/--scheduler replace it)
      kind: dask                   # a registered runner: serial (this process) or dask
      workers: 4                   # its options: a local cluster of 4 worker processes,
      scheduler: tcp://host:8786   # or an existing Dask cluster

A *case* is one subject with one combination of the study's values. Its stages are described by
:func:`pixmuscle.plan.plan_case` and executed by :mod:`pixmuscle.runners.serial` (in this process)
or :mod:`pixmuscle.runners.dask` (worker processes of a Dask cluster). Folders::

    <output_dir>/                    single subject, no study: every file here
    <output_dir>/<subject>/          cohort: one folder per subject, cohort.html beside them
    <output_dir>/[<subject>/]<case>/ study: results and report of each case; the stages the study
                                     does not vary (e.g. segmentation, model) stay one level up and
                                     are shared by the subject's cases; study.html at the top

Re-running skips every stage whose output is up to date (see :mod:`pixmuscle.plan`).
"""

from __future__ import annotations

import copy
import dataclasses
import difflib
import importlib
import json
import logging
from pathlib import Path
from typing import Any

from .config import parse_section, read_yaml
from .errors import InputError, PixmuscleError, StaleInputError
from .overrides import apply_overrides, parse_override
from .plan import STAGES, plan_case, results_paths, stage_range, up_to_date  # noqa: F401  (re-exported)
from .study import Study, parse_study, set_key

_LOG = logging.getLogger("pixmuscle.pipeline")

#: config section → (module, dataclass name)
SECTIONS = {
    "segment": ("pixmuscle.segmentation.config", "SegmentConfig"),
    "uncertainty": ("pixmuscle.uncertainty.config", "UncertaintyConfig"),
    "build_model": ("pixmuscle.model.config", "BuildModelConfig"),
    "coarsen": ("pixmuscle.model.config", "CoarsenConfig"),
    "solve": ("pixmuscle.mechanics.config", "SolveConfig"),
    "muscle_forces": ("pixmuscle.mechanics.experiments", "MuscleForcesConfig"),
    "force_length": ("pixmuscle.mechanics.experiments", "ForceLengthConfig"),
    "report": ("pixmuscle.report.config", "ReportConfig"),
}
_ROOT_KEYS = {"title", "synthetic", "output_dir", "models", "subjects", "study", "execution", "plugins", *SECTIONS}
#: keys a subject entry may override (besides its name)
_SUBJECT_KEYS = _ROOT_KEYS - {"subjects", "output_dir", "study", "execution", "plugins"}
#: folder of the per-combination cohort pages of a study (not allowed as a subject name)
STUDY_COHORTS = "study_cohorts"


@dataclasses.dataclass(frozen=True)
class PipelineConfig:
    """One case's validated configuration (sections are None when absent).

    ``name`` is unique within a run: the subject name, followed by ``/<case>`` in a study.
    ``shared_dir`` (studies only) holds the stages the study does not vary; ``params`` the
    (key, value) pairs of the study combination; ``plugins`` the source files of the config's
    plugins (:func:`pixmuscle.plugins.load_plugins`); ``realisation`` the uncertainty realisation
    of the case (1, 2, ...; 0: the noise-free case), see :mod:`pixmuscle.uncertainty`.
    """

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
    muscle_forces: Any = None
    force_length: Any = None
    report: Any = None
    subject: str = ""
    case: str = ""
    params: tuple = ()
    shared_dir: Path | None = None
    study_sections: frozenset = frozenset()
    plugins: tuple = ()
    uncertainty: Any = None
    realisation: int = 0

    def varied_sections(self) -> frozenset:
        """Config sections a study varies, plus every section downstream of the first of them."""
        if not self.study_sections:
            return frozenset()
        order = list(SECTIONS)
        first = min(order.index(s) for s in self.study_sections)
        return frozenset(order[first:])


@dataclasses.dataclass(frozen=True)
class SubjectError:
    """A case whose configuration could not be validated."""

    name: str
    error: str
    output_dir: Path
    subject: str = ""
    case: str = ""
    params: tuple = ()


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """Everything one ``pixmuscle run`` does: the cases, the study, where to run them.

    Attributes
    ----------
    path : Path
        The YAML file.
    root_dir : Path
        Top output folder (cohort and study pages go here).
    cases : list of PipelineConfig or SubjectError
    subjects : tuple of str
        Subject names in config order (one entry, the config stem, for a single subject).
    cohort : bool
        True when the config has a ``subjects`` list.
    study : Study or None
    execution : runner dataclass or None
        The ``execution`` section (:func:`pixmuscle.runners.parse_execution`), e.g.
        :class:`pixmuscle.runners.dask.Dask`; None when the config has none.
    uncertainty : UncertaintyConfig or None
        The top-level ``uncertainty`` section: each subject is run noise-free and in its realisations.
    """

    path: Path
    root_dir: Path
    cases: list
    subjects: tuple
    cohort: bool
    study: Study | None = None
    execution: Any = None
    uncertainty: Any = None


def _section_class(name: str):
    module, cls = SECTIONS[name]
    return getattr(importlib.import_module(module), cls)


def _deep_merge(base: dict, over: dict) -> dict:
    out = copy.deepcopy(base)
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _deep_merge(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out


def _parse_case(raw: dict, name: str, where: str, base_dir: Path, out_dir: Path, **extra) -> PipelineConfig:
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
    _check_muscle_names(sections, where)
    if "uncertainty" in sections:
        _check_uncertainty(sections, where)
    return PipelineConfig(
        name=name, title=str(raw.get("title", extra.get("subject") or name)), synthetic=bool(raw.get("synthetic", False)),
        output_dir=out_dir, models=tuple(models), base_dir=base_dir, **sections, **extra,
    )


def _check_uncertainty(sections: dict, where: str) -> None:
    """An ``uncertainty`` section perturbs what the segment stage made: it needs that stage, a DTI with
    tensors for DTI noise, and no hand-made label map replacing the perturbed labels."""
    unc, seg, bm = sections["uncertainty"], sections.get("segment"), sections.get("build_model")
    if seg is None:
        raise InputError(f"{where}uncertainty: needs a segment section: the realisations perturb the DTI and the "
                         "segmentation it makes (a model built from a label map alone has neither)")
    if unc.dti_snr is not None and seg.dwi is None and seg.dti_tensor is None:
        raise InputError(f"{where}uncertainty.dti_snr: segment.dti_v1 gives fibre directions without their tensors, "
                         "so there is no signal to add noise to; give segment.dti_tensor or segment.dwi, or set "
                         "uncertainty.dti_snr: null")
    if unc.boundary_voxels > 0 and bm is not None and getattr(bm, "labels", None) is not None:
        raise InputError(f"{where}uncertainty.boundary_voxels: build_model.labels replaces the segmentation's labels, "
                         "so a moved boundary would not reach the model; set boundary_voxels: 0 or drop "
                         "build_model.labels")


def _check_muscle_names(sections: dict, where: str) -> None:
    """Muscle names in activation mappings and muscle_forces.muscles must be muscles of the case: checked
    here against the segment seeds (the muscles a segmentation will have) before any stage runs; the
    solve stage checks again against the model."""
    seg = sections.get("segment")
    if seg is None or not seg.seeds:
        return
    from .mechanics.activation import check_muscle_names, muscle_values

    names = list(seg.seeds)
    if sections.get("solve") is not None:
        check_muscle_names(sections["solve"].activation, names, f"{where}solve.activation")
    fl = sections.get("force_length")
    if fl is not None and isinstance(fl.activation, dict):
        muscle_values(fl.activation, names, f"{where}force_length.activation")
    mf = sections.get("muscle_forces")
    for m in (mf.muscles or []) if mf is not None else []:
        if m not in names:
            raise InputError(f"{where}muscle_forces.muscles: unknown muscle {m!r}; the segment seeds name: "
                             f"{', '.join(names)}")


def _check_subject_name(path: Path, i: int, name: Any, seen: dict) -> str:
    if not isinstance(name, str) or not name.strip():
        raise InputError(f"{path}: subjects[{i}]: expected a mapping with a non-empty 'name' string")
    if "/" in name or "\\" in name or name in (".", "..") or name == STUDY_COHORTS:
        raise InputError(f"{path}: subjects[{i}].name: {name!r} cannot be a folder name "
                         f"(no '/', '\\', '.', '..' or '{STUDY_COHORTS}')")
    if name in seen:
        raise InputError(f"{path}: subjects[{i}].name: '{name}' is already the name of subjects[{seen[name]}]; "
                         "subject names must be unique (each names its output folder)")
    seen[name] = i
    return name


def load_run(path: str | Path, *, strict: bool = True, overrides=(), output_dir: str | Path | None = None,
             subject: str | None = None) -> RunConfig:
    """Read and validate a pipeline YAML into its cases.

    With ``strict=False`` a case whose own section is invalid (a missing file, a bad key) is
    returned as a :class:`SubjectError` instead of raising, so the other cases can run. Errors
    of the file as a whole (unknown top-level key, duplicate subject names, a malformed study)
    always raise.

    Parameters
    ----------
    overrides : sequence of "key.path=value"
        ``pixmuscle run --set``: set into the file's mapping before validation (and again into
        every subject's merged mapping, so they win over the subject entries).
    output_dir : path-like, optional
        ``pixmuscle run -o``: the top output folder (relative to the current folder), instead of
        the file's ``output_dir``.
    subject : str, optional
        ``pixmuscle run --subject``: only this subject of a cohort (all its study cases).
    """
    path = Path(path)
    sets = [parse_override(o) if isinstance(o, str) else o for o in overrides]
    raw = apply_overrides(read_yaml(path), sets)
    unknown = sorted(set(raw) - _ROOT_KEYS)
    if unknown:
        close = difflib.get_close_matches(unknown[0], sorted(_ROOT_KEYS), n=1)
        hint = f"; did you mean '{close[0]}'?" if close else f"; valid keys: {', '.join(sorted(_ROOT_KEYS))}"
        raise InputError(f"{path}: {unknown[0]}: unknown top-level key{hint}")
    from .plugins import load_plugins

    plugins = load_plugins(raw.get("plugins"), path)  # before any section names what they register
    base_dir = path.parent.resolve()
    if output_dir is not None:
        root = Path(output_dir).resolve()
    elif raw.get("output_dir"):
        root = (base_dir / raw["output_dir"]).resolve()
    else:
        root = (Path.cwd() / "out" / path.stem).resolve()
    study = parse_study(raw.get("study"), set(SECTIONS) - {"uncertainty"}, f"{path}: study")
    uncertainty = _top_uncertainty(raw, study, path, base_dir)
    from .runners import parse_execution

    execution = parse_execution(raw.get("execution"), f"{path}: execution")
    common = {k: v for k, v in raw.items() if k in _SUBJECT_KEYS}
    subjects = raw.get("subjects")
    if subjects is None:
        entries = [(path.stem, {}, "", root)]
    else:
        if not isinstance(subjects, list) or not subjects:
            raise InputError(f"{path}: subjects: expected a non-empty list of {{name: ..., <section overrides>}}")
        seen: dict = {}
        entries = []
        for i, s in enumerate(subjects):
            if not isinstance(s, dict):
                raise InputError(f"{path}: subjects[{i}]: expected a mapping with a 'name' string")
            name = _check_subject_name(path, i, s.get("name"), seen)
            entries.append((name, s, f"subjects[{i}].", root / name))
    if subject is not None:
        names = [e[0] for e in entries]
        if subjects is None and subject != path.stem:
            raise InputError(f"--subject {subject}: {path} has no `subjects` list (its one subject is '{path.stem}')")
        if subject not in names:
            close = difflib.get_close_matches(subject, names, n=1)
            hint = f"; did you mean '{close[0]}'?" if close else f"; subjects: {', '.join(names)}"
            raise InputError(f"--subject {subject}: no such subject in {path}{hint}")
        entries = [e for e in entries if e[0] == subject]
    combos = [((), "")] if study is None else [
        (tuple(zip(study.keys, vals, strict=True)), cname) for vals, cname in zip(study.cases, study.names, strict=True)]
    if study is not None:
        _check_study(study, len(entries), path, base_dir)
    if uncertainty is not None:  # the noise-free case, then the realisations (pixmuscle.uncertainty)
        width = max(2, len(str(uncertainty.realisations)))
        combos = [((), "", 0)] + [((), f"r{r:0{width}d}", r) for r in range(1, uncertainty.realisations + 1)]
    else:
        combos = [(params, cname, 0) for params, cname in combos]
    cases = []
    folders: dict[Path, str] = {}
    for name, s, where, subj_dir in entries:
        bad = sorted(set(s) - _SUBJECT_KEYS - {"name"})
        base_ok = study is not None and _parses(common, s, sets, bad, name, where, base_dir, subj_dir)
        if uncertainty is None and "uncertainty" in s:
            raise InputError(f"{path}: {where}uncertainty: a subject may change the keys of a top-level uncertainty "
                             "section, but there is none; put the section at the top level")
        for params, cname, realisation in combos:
            case_name = f"{name}/{cname}" if cname else name
            out_dir = (subj_dir / "uncertainty" / cname if realisation else subj_dir / cname) if cname else subj_dir
            if out_dir in folders:
                raise InputError(f"{path}: cases '{folders[out_dir]}' and '{case_name}' write to the same folder "
                                 f"{out_dir}: duplicate case folder")
            folders[out_dir] = case_name
            info = {"subject": name, "case": cname, "params": params}
            try:
                if bad:
                    raise InputError(f"{path}: {where}{bad[0]}: unknown key")
                merged = _deep_merge(common, {k: v for k, v in s.items() if k != "name"})
                if s:
                    merged = apply_overrides(merged, [(k, v) for k, v in sets if k.split(".")[0] in _SUBJECT_KEYS])
                for key, value in params:
                    merged = set_key(merged, key, value, f"{path}: study.vary")
                extra = dict(info, shared_dir=subj_dir if study else None,
                             study_sections=study.sections if study else frozenset(), plugins=plugins)
                if realisation:
                    merged = _realisation_raw(merged, realisation, uncertainty.realisations, name)
                    extra.update(shared_dir=subj_dir, study_sections=frozenset({"uncertainty"}), realisation=realisation)
                case = _parse_case(merged, case_name, where, base_dir, out_dir, **extra)
                if uncertainty is not None and case.uncertainty.realisations != uncertainty.realisations:
                    raise InputError(f"{path}: {where}uncertainty.realisations: the number of realisations is one for "
                                     f"the whole run ({uncertainty.realisations}, the top-level section's); a subject "
                                     "may change the other keys")
                cases.append(case)
            except InputError as exc:
                if base_ok:  # the subject is valid without the study's values: the study is at fault
                    raise InputError(f"{path}: study.vary: {exc} (study case {cname}); nothing was run") from None
                if strict or (subjects is None and study is None):   # a single case: its error is the run's
                    raise
                msg = f"{exc} (study case {cname})" if cname else str(exc)
                cases.append(SubjectError(case_name, msg, out_dir, **info))
    return RunConfig(path, root, cases, tuple(e[0] for e in entries), subjects is not None and subject is None, study,
                     execution, uncertainty)


#: report keys of a realisation: curves, tables and summary.json only (its F_max is what the run needs)
REALISATION_REPORT = {"vtu": False, "xdmf": False, "view3d": False, "slices": False, "segmentation_qc": False}


def _realisation_raw(raw: dict, realisation: int, n: int, subject: str) -> dict:
    """A case's config as its uncertainty realisation ``realisation`` of ``n`` runs it: a light report
    (:data:`REALISATION_REPORT`) titled as the realisation, and none of the extra solves of
    ``muscle_forces`` / ``force_length``."""
    out = {k: v for k, v in raw.items() if k not in ("muscle_forces", "force_length")}
    out["report"] = {**(raw.get("report") or {}), **REALISATION_REPORT}
    out["title"] = f"{raw.get('title', subject)} — noisy realisation {realisation} of {n} (uncertainty)"
    return out


def _top_uncertainty(raw: dict, study: Study | None, path: Path, base_dir: Path):
    """The top-level ``uncertainty`` section (None when absent); a study and an uncertainty run are two runs."""
    if raw.get("uncertainty") is None:
        return None
    if study is not None:
        raise InputError(f"{path}: uncertainty: a config has either a study or an uncertainty section, not both "
                         "(run the uncertainty of one combination with its values set in the sections)")
    return parse_section(_section_class("uncertainty"), raw["uncertainty"], f"{path}: uncertainty", base_dir)


def _check_study(study: Study, n_subjects: int, path: Path, base_dir: Path) -> None:
    """Every ``vary`` key and value against the typed config, and the case count against its bound,
    before any case is set up (a bad study is the run's error, never one error per case)."""
    from .config import check_key
    from .study import MAX_CASES, format_value

    n = n_subjects * len(study.cases)
    if n > MAX_CASES:
        sizes = " × ".join(f"{len({format_value(c[i]) for c in study.cases})} ({k})" for i, k in enumerate(study.keys))
        per = f" × {n_subjects} subjects" if n_subjects > 1 else ""
        raise InputError(f"{path}: study.vary: {n} cases ({sizes}{per}) is more than the bound of {MAX_CASES} "
                         "cases of one run; vary fewer values, or split the study into several configs")
    for i, key in enumerate(study.keys):
        section, rest = key.split(".", 1)
        cls = _section_class(section)
        for value in {format_value(c[i]): c[i] for c in study.cases}.values():
            check_key(cls, rest, value, f"{path}: study.vary.{section}", base_dir)


def _parses(common: dict, s: dict, sets: list, bad: list, name: str, where: str, base_dir: Path, out: Path) -> bool:
    """True when a subject's config (without the study's values) is valid on its own."""
    if bad:
        return False
    merged = _deep_merge(common, {k: v for k, v in s.items() if k != "name"})
    if s:
        merged = apply_overrides(merged, [(k, v) for k, v in sets if k.split(".")[0] in _SUBJECT_KEYS])
    try:
        _parse_case(merged, name, where, base_dir, out)
    except InputError:
        return False
    return True


def load_subjects(path: str | Path, *, strict: bool = True) -> list:
    """Validated cases of a pipeline YAML (one per subject and study combination); see :func:`load_run`."""
    return load_run(path, strict=strict).cases


def load_config(path: str | Path) -> PipelineConfig:
    """Validated config of a single-subject YAML (the first case of a cohort or study)."""
    return load_subjects(path)[0]


# --------------------------------------------------------------------------- running
def run_subject(cfg: PipelineConfig, *, force: bool = False, start: str | None = None,
                until: str | None = None, allow_stale: bool = False) -> dict:
    """Run the stages of one case in this process; returns its summary (paths, stages run/skipped).

    Errors propagate (:class:`~pixmuscle.errors.PixmuscleError` for bad input or a failed solve).
    Before any stage: :func:`pixmuscle.preflight.check_case`; the case's folders are locked for
    the run and swept of leftovers (:func:`pixmuscle.outdir.hold_folders`).
    """
    from .outdir import hold_folders
    from .preflight import check_case, stage_folders
    from .runners.serial import Serial

    stages = _check_upstream(cfg, plan_case(cfg, start, until), start, allow_stale, "CONFIG")
    check_case(cfg, stages)
    with hold_folders(stage_folders(stages) | {cfg.output_dir}):
        outcome = Serial().run({cfg.name: stages}, force=force, raise_errors=True)[cfg.name]
    return _case_summary(cfg, outcome)


def run_pipeline(path: str | Path, *, force: bool = False, start: str | None = None, until: str | None = None,
                 workers: int | None = None, scheduler: str | None = None, overrides=(),
                 output_dir: str | Path | None = None, subject: str | None = None, allow_stale: bool = False) -> bool:
    """Run every case of a config; a failing case is reported and the others go on.

    Parameters
    ----------
    path : path-like
        Pipeline YAML.
    force, start, until
        As ``pixmuscle run --force --from --until``.
    workers : int, optional
        Run on a local Dask cluster of this many worker processes (0: serially in this process),
        instead of the config's ``execution`` section. Default: that section, else serial for one
        case and a local cluster sized to the machine for several.
    scheduler : str, optional
        Address of an existing Dask scheduler (``tcp://host:port``), instead of ``execution``.
    overrides, output_dir, subject
        As ``pixmuscle run --set``, ``-o`` and ``--subject`` (see :func:`load_run`).
    allow_stale : bool
        As ``pixmuscle run --allow-stale``: go on when a stage file before ``--from`` was made under
        another config (else :class:`~pixmuscle.errors.StaleInputError`); the report shows the mismatch.

    Returns
    -------
    bool
        True when every case succeeded. A single-case run raises its error instead.
    """
    return not run_cases(path, force=force, start=start, until=until, workers=workers, scheduler=scheduler,
                         overrides=overrides, output_dir=output_dir, subject=subject,
                         allow_stale=allow_stale)["failures"]


def run_cases(path: str | Path, *, force: bool = False, start: str | None = None, until: str | None = None,
              workers: int | None = None, scheduler: str | None = None, overrides=(),
              output_dir: str | Path | None = None, subject: str | None = None, allow_stale: bool = False) -> dict:
    """:func:`run_pipeline`, returning ``summaries`` (one per finished case: paths, stages run),
    ``failures`` (case name → error) and ``pages`` (cohort/study pages written)."""
    from .outdir import hold_folders
    from .preflight import check_case, stage_folders
    from .runners import Progress, choose_runner

    run = load_run(path, strict=False, overrides=overrides, output_dir=output_dir, subject=subject)
    cases = run.cases
    plans, failures = {}, {}
    for c in cases:
        if isinstance(c, SubjectError):
            failures[c.name] = c.error
            continue
        try:
            plans[c.name] = _check_upstream(c, plan_case(c, start, until), start, allow_stale, run.path,
                                            c.name if len(cases) > 1 else "")
            check_case(c, plans[c.name])  # before any stage of any case runs
        except InputError as exc:
            plans.pop(c.name, None)
            if len(cases) == 1 or isinstance(exc, StaleInputError):  # stale inputs stop the whole run
                raise
            failures[c.name] = str(exc)
    for name, err in failures.items():
        _LOG.error("%s: invalid configuration: %s", name, err)
    folders = {f for c in cases if c.name in plans for f in stage_folders(plans[c.name]) | {c.output_dir}}
    if run.cohort or run.study is not None or run.uncertainty is not None:
        folders.add(run.root_dir)
    with hold_folders(folders):  # one run at a time in these folders
        progress = Progress([c.name for c in cases if c.name in plans])
        runner = choose_runner(run.execution, len(plans), workers=workers, scheduler=scheduler)
        outcomes = runner.run(plans, force=force, progress=progress, raise_errors=len(cases) == 1)
        summaries = []
        for c in cases:
            if c.name in failures:
                continue
            o = outcomes[c.name]
            if o.error is not None:
                failures[c.name] = o.error
            else:
                summaries.append(_case_summary(c, o))
        progress.finish()
        pages = [] if subject else _write_summaries(run, summaries, failures)  # one subject: leave the pages alone
    return {"summaries": summaries, "failures": failures, "pages": pages}


def _check_upstream(cfg: PipelineConfig, stages: list, start: str | None, allow_stale: bool, config: Any,
                    case: str = "") -> list:
    """The plan of a case after comparing the stage files before ``--from`` with the current config.

    Raises
    ------
    StaleInputError
        One of them was made under another config (or from changed inputs) and ``allow_stale``
        is False. With ``allow_stale`` the mismatches are logged and shown on the report's first
        screen instead.
    """
    from .plan import stale_message, stale_upstream, with_stale_note

    stale = stale_upstream(cfg, start)
    if not stale:
        return stages
    if not allow_stale:
        raise StaleInputError(stale_message(stale, config, case))
    for m in stale:
        _LOG.warning("%s%s: going on with it (--allow-stale); rerun from %s to update it",
                     f"{case}: " if case else "", m.describe(), m.rerun_from)
    return with_stale_note(stages, stale)


def _case_summary(cfg: PipelineConfig, outcome) -> dict:
    results = results_paths(cfg)
    summary = {"name": cfg.name, "subject": cfg.subject or cfg.name, "case": cfg.case,
               "params": {k: v for k, v in cfg.params}, "realisation": cfg.realisation,
               "output_dir": str(cfg.output_dir),
               "ran": list(outcome.ran), "skipped": list(outcome.skipped),
               "results": {k: str(v) for k, v in results.items()}}
    report_dir = cfg.output_dir / "report"
    for name in ("index.html", "summary.json"):
        if "report" in outcome.ran and (report_dir / name).exists():
            summary["report"] = str(report_dir / name)
            break
    return summary


def _write_uncertainty(run: RunConfig, resolved: list, failures: dict[str, str]) -> list[str]:
    """Each subject's ``uncertainty.csv`` / ``.json`` / ``_curves.png`` and the run's ``uncertainty.html``."""
    from .report.uncertainty_page import uncertainty_summary

    by_name = {s["name"]: r for s, r in resolved}
    rows = [{"subject": c.subject, "realisation": getattr(c, "realisation", 0), "case": c.case,
             "summary": by_name.get(c.name), "error": failures.get(c.name), "output_dir": str(c.output_dir)}
            for c in run.cases]
    if not any(r["summary"] for r in rows) and not any(r["error"] for r in rows):
        return []  # e.g. --until segment: nothing to summarise
    subject_dirs = {c.subject: c.output_dir for c in run.cases if not getattr(c, "realisation", 0)}
    title = next((c.title for c in run.cases if isinstance(c, PipelineConfig)), "")
    page = uncertainty_summary(rows, run.uncertainty, run.root_dir, subject_dirs=subject_dirs,
                               subjects=list(run.subjects),
                               title=f"Force uncertainty from the scan — {title}" if title else "")
    return [str(page)]


def _report_summary(s: dict) -> dict | None:
    """The report summary of a finished case: its summary.json, else computed from its results."""
    if s.get("report"):
        js = Path(s["report"]).with_name("summary.json")
        if js.exists():
            out = json.loads(js.read_text())
            out["label"] = s["subject"]
            return out
    results = s.get("results", {})
    res = results.get("fine") or next(iter(results.values()), None)  # the finest model is the answer
    if res and Path(res).exists():
        from .stages.report import summarize_results

        return summarize_results(res, extra={"subject": s["subject"]})
    return None


def _write_summaries(run: RunConfig, summaries: list[dict], failures: dict[str, str]) -> list[str]:
    """cohort_status.json, the cohort page(s) and the study page of a run; returns the pages written."""
    if not run.cohort and run.study is None and run.uncertainty is None:
        return []
    root = run.root_dir
    root.mkdir(parents=True, exist_ok=True)
    fail_list = [{"name": n, "error": e} for n, e in failures.items()]
    (root / "cohort_status.json").write_text(json.dumps({"ok": summaries, "failed": fail_list}, indent=2, default=str))
    resolved = [(s, _report_summary(s)) for s in summaries]
    from .report.cohort import cohort_summary

    if run.study is None:
        pages = [] if run.uncertainty is None else _write_uncertainty(run, resolved, failures)
        if not run.cohort:
            return pages
        noise_free = {c.name for c in run.cases if not getattr(c, "realisation", 0)}
        sums = [r for s, r in resolved if r is not None and s["name"] in noise_free]
        fails = [f for f in fail_list if f["name"] in noise_free]
        if not sums and not fails:  # e.g. --until segment: no subject has a report yet
            return pages
        return [str(cohort_summary(sums, root, failures=fails)), *pages]
    from .report.study_page import study_summary

    rows = []
    for c in run.cases:
        found = next(((s, r) for s, r in resolved if s["name"] == c.name), None)
        rows.append({"subject": c.subject, "case": c.case, "params": dict(c.params),
                     "summary": found[1] if found else None, "error": failures.get(c.name),
                     "output_dir": str(c.output_dir)})
    cohort_pages = {}
    if run.cohort:
        for cname in run.study.names:
            sums = [r["summary"] for r in rows if r["case"] == cname and r["summary"] is not None]
            fails = [{"name": r["subject"], "error": r["error"]} for r in rows if r["case"] == cname and r["error"]]
            if sums or fails:
                cohort_pages[cname] = str(cohort_summary(sums, root / STUDY_COHORTS / cname, failures=fails,
                                                         title=f"Cohort comparison — {cname}"))
    title = next((c.title for c in run.cases if isinstance(c, PipelineConfig)), "")
    page = study_summary(rows, list(run.study.keys), root, subjects=list(run.subjects), cohort_pages=cohort_pages,
                         title=f"Parameter study — {title}" if title else "Parameter study")
    return [str(page), *cohort_pages.values()]


__all__ = ["PipelineConfig", "SubjectError", "RunConfig", "load_run", "load_subjects", "load_config",
           "run_subject", "run_pipeline", "PixmuscleError"]

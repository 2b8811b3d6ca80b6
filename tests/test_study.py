"""Study expansion, case folders and config errors of cohorts/studies (no solves: fast)."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from pixmuscle.errors import InputError
from pixmuscle.pipeline import load_run, load_subjects
from pixmuscle.plan import plan_case
from pixmuscle.study import parse_study, set_key, short_names

SECTIONS = {"segment", "build_model", "coarsen", "solve", "report"}


def test_grid_and_list_expansion():
    s = parse_study({"vary": {"solve.materials.muscle.sigma_max": [20, 25, 30],
                              "solve.materials.connective_tissue.C10": [15, 30]}}, SECTIONS)
    assert len(s.cases) == 6 and s.cases[0] == (20, 15) and s.cases[-1] == (30, 30)
    assert s.names[1] == "sigma_max=20,C10=30"
    assert s.sections == {"solve"}
    s = parse_study({"mode": "list", "vary": {"solve.steps": [2, 3], "coarsen.factor": [2, 4]}}, SECTIONS)
    assert s.cases == ((2, 2), (3, 4)) and s.names == ("steps=2,factor=2", "steps=3,factor=4")


def test_short_names_disambiguate_same_tail():
    assert short_names(["solve.materials.muscle.C10", "solve.materials.fat.C10", "solve.steps"]) == [
        "muscle.C10", "fat.C10", "steps"]


@pytest.mark.parametrize("raw, match", [
    ({"vary": {}}, "non-empty mapping"),
    ({"vary": {"sigma_max": [1]}}, "dotted key"),
    ({"vary": {"nonsense.a": [1]}}, "dotted key"),
    ({"vary": {"solve.steps": 3}}, "non-empty list"),
    ({"vary": {"solve.steps": [2, 2]}}, "duplicate case"),
    ({"vary": {"solve.materials.muscle.sigma_max": [20, 20.0]}}, "duplicate case"),
    ({"mode": "list", "vary": {"solve.steps": [2, 3], "coarsen.factor": [2]}}, "one length"),
    ({"mode": "random", "vary": {"solve.steps": [2]}}, "grid"),
    ({"vary": {"solve.steps": [2]}, "vray": 1}, "unknown key"),
])
def test_bad_study(raw, match):
    with pytest.raises(InputError, match=match):
        parse_study(raw, SECTIONS)


def test_set_key_creates_levels_and_rejects_non_mappings():
    raw = {"solve": {"steps": 2}}
    out = set_key(raw, "solve.materials.muscle.sigma_max", 25)
    assert out["solve"]["materials"]["muscle"]["sigma_max"] == 25 and "materials" not in raw["solve"]
    with pytest.raises(InputError, match="not a mapping"):
        set_key(raw, "solve.steps.x", 1)


def _labels_config(tmp_path: Path, **extra) -> Path:
    import nibabel as nib
    import numpy as np

    lab = np.zeros((6, 6, 3), np.int16)
    lab[1:5, 1:5, :] = 1
    nib.save(nib.Nifti1Image(lab, np.diag([1.0, 1.0, 1.0, 1.0])), tmp_path / "labels.nii.gz")
    cfg = {"output_dir": "out", "build_model": {"labels": "labels.nii.gz"}, "coarsen": {"factor": 2},
           "models": ["coarse"], "solve": {"steps": 1}, **extra}
    p = tmp_path / "c.yaml"
    p.write_text(yaml.safe_dump(cfg))
    return p


def test_duplicate_subject_names_are_a_config_error(tmp_path):
    p = _labels_config(tmp_path, subjects=[{"name": "young"}, {"name": "old"}, {"name": "young"}])
    for strict in (True, False):
        with pytest.raises(InputError, match=r"subjects\[2\].name: 'young' is already the name of subjects\[0\]"):
            load_subjects(p, strict=strict)
    p = _labels_config(tmp_path, subjects=[{"name": "a/b"}])
    with pytest.raises(InputError, match="folder name"):
        load_subjects(p)


def test_study_cases_folders_and_shared_stages(tmp_path):
    p = _labels_config(tmp_path, subjects=[{"name": "young"}, {"name": "old"}],
                       study={"vary": {"solve.materials.muscle.sigma_max": [20, 30]}})
    run = load_run(p)
    assert [c.name for c in run.cases] == ["young/sigma_max=20", "young/sigma_max=30", "old/sigma_max=20",
                                           "old/sigma_max=30"]
    c = run.cases[1]
    assert c.solve.materials.muscle.sigma_max == 30 and c.params == (("solve.materials.muscle.sigma_max", 30),)
    stages = {s.kind: s for s in plan_case(c)}
    root = (tmp_path / "out").resolve()
    # the model is shared by the subject's cases, the solve and report are the case's own
    assert stages["build-model"].output == root / "young" / "model.h5"
    assert stages["coarsen"].output == root / "young" / "model_coarse.h5"
    assert stages["solve"].output == root / "young" / "sigma_max=30" / "results_coarse.h5"
    assert stages["report"].output.parent == root / "young" / "sigma_max=30" / "report"
    # varying an upstream section moves that stage and everything after it into the case folder
    p = _labels_config(tmp_path, study={"vary": {"coarsen.factor": [1, 2]}})
    c = load_run(p).cases[0]
    stages = {s.kind: s for s in plan_case(c)}
    assert stages["build-model"].output == root / "model.h5"
    assert stages["coarsen"].output == root / "factor=1" / "model_coarse.h5"
    # a report-only study solves once and writes one report per case
    p = _labels_config(tmp_path, study={"vary": {"report.dpi": [40, 80]}})
    stages = {s.kind: s for s in plan_case(load_run(p).cases[1])}
    assert stages["solve"].output == root / "results_coarse.h5"
    assert stages["report"].output.parent == root / "dpi=80" / "report"
    assert stages["report"].kwargs["results_path"] == root / "results_coarse.h5"


def test_study_values_are_checked_before_any_case(tmp_path):
    """A bad vary key or value is the run's error (every mode); a subject's own bad section stays its case's."""
    p = _labels_config(tmp_path, study={"vary": {"solve.materials.muscle.sigma_max": [20, -5]}})
    for strict in (True, False):
        with pytest.raises(InputError, match=r"study.vary.solve.materials.muscle.sigma_max: expected a value ≥ 0.0"):
            load_run(p, strict=strict)
    p = _labels_config(tmp_path, subjects=[{"name": "a"}, {"name": "b", "coarsen": {"factor": 0}}],
                       study={"vary": {"solve.materials.muscle.sigma_max": [20, 30]}})
    cases = load_run(p, strict=False).cases
    assert [type(c).__name__ for c in cases] == ["PipelineConfig"] * 2 + ["SubjectError"] * 2
    assert "coarsen.factor" in cases[2].error


def test_execution_section(tmp_path):
    """`execution: {kind, …options}` is validated by the runner's own dataclass; the short form of the
    command-line options ({workers}, {scheduler}) still works."""
    from pixmuscle.runners import choose_runner
    from pixmuscle.runners.dask import Dask
    from pixmuscle.runners.serial import Serial

    p = _labels_config(tmp_path, execution={"scheduler": "tcp://127.0.0.1:8786", "workers": 2})
    assert load_run(p).execution == Dask(workers=2, scheduler="tcp://127.0.0.1:8786")
    p = _labels_config(tmp_path, execution={"kind": "dask", "workers": 3})
    assert load_run(p).execution == Dask(workers=3)
    for short in ({"workers": 0}, {"kind": "serial"}):
        assert load_run(_labels_config(tmp_path, execution=short)).execution == Serial()
    assert load_run(_labels_config(tmp_path)).execution is None
    # the command line replaces the section; without either, one case runs serially, several on a local cluster
    assert choose_runner(Serial(), 4, workers=2) == Dask(workers=2)
    assert choose_runner(Dask(workers=3), 4, workers=0) == Serial()
    assert choose_runner(Serial(), 4, scheduler="tcp://h:1") == Dask(scheduler="tcp://h:1")
    assert choose_runner(None, 1) == Serial() and isinstance(choose_runner(None, 3), Dask)
    for bad, message in [({"workers": -1}, r"execution.workers: expected a value ≥ 1, got -1"),
                         ({"kind": "serial", "workers": 2}, r"execution.workers: unknown key"),
                         ({"kind": "slurm"}, r"execution.kind: unknown runner 'slurm'; expected one of dask, serial"),
                         ({"kind": "dask", "schedular": "x"}, r"execution.schedular: unknown key.*did you mean 'scheduler'")]:
        with pytest.raises(InputError, match=message):
            load_run(_labels_config(tmp_path, execution=bad))


def test_report_layer_does_not_import_the_stages_layer():
    import ast

    import pixmuscle.report

    for f in Path(pixmuscle.report.__file__).parent.glob("*.py"):
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.ImportFrom):
                mod = ("." * node.level) + (node.module or "")
                assert "stages" not in mod.split("."), f"{f.name} imports {mod}"
            elif isinstance(node, ast.Import):
                assert not any("pixmuscle.stages" in a.name for a in node.names), f.name

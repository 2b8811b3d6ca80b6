"""Cohorts and studies on a real Dask cluster (scheduler + two worker processes on localhost).

The same tiny SYNTHETIC young/old medial-gastrocnemius phantoms as test_pipeline, one load step:
the Dask run must give the serial run's numbers, a 2 × 2 study the numbers of its four cases run
one by one, and a worker killed in the middle of a case must be retried (or the case reported)
while the other cases complete.
"""

from __future__ import annotations

import csv
import json
import logging
import os
import signal
from pathlib import Path

import numpy as np
import pytest
import yaml

distributed = pytest.importorskip("distributed")

from pixmuscle.pipeline import load_subjects, run_pipeline, run_subject  # noqa: E402
from pixmuscle.runners.dask import local_cluster  # noqa: E402
from pixmuscle.synth import make_mg_phantom, write_phantom  # noqa: E402


@pytest.fixture(scope="module")
def phantoms(tmp_path_factory):
    """Ground-truth labels and fibres of tiny young/old phantoms (the segment stage is tested elsewhere)."""
    out = tmp_path_factory.mktemp("phantoms")
    inputs = {}
    for who, seed in (("young", 3), ("old", 4)):
        write_phantom(make_mg_phantom(who, shape=(28, 20, 3), pixel_cm=0.25, seed=seed), out, who)
        inputs[who] = {"labels": str(out / f"{who}_labels.nii.gz"), "fibers": str(out / f"{who}_fibers.nii.gz")}
    return inputs


def _config(path: Path, out: Path, inputs: dict, **extra) -> Path:
    cfg = {
        "title": "tiny dask test", "synthetic": True, "output_dir": str(out), "models": ["coarse"],
        "build_model": {}, "coarsen": {"factor": 2},
        "solve": {"steps": 1, "activation": {"from": 0.0, "to": 0.5},
                  "boundary_conditions": [{"nodes": "z_min", "fix": ["x", "y", "z"]},
                                          {"nodes": "z_max", "fix": ["x", "y", "z"]}]},
        "report": {"vtu": False, "slices": False, "dpi": 40},
        **extra,
    }
    if len(inputs) == 1:
        cfg["build_model"] = dict(next(iter(inputs.values())))
    else:
        cfg["subjects"] = [{"name": k, "build_model": v} for k, v in inputs.items()]
    path.write_text(yaml.safe_dump(cfg))
    return path


def _rows(path: Path) -> list[dict]:
    with open(path) as fh:
        return list(csv.DictReader(fh))


@pytest.fixture(scope="module")
def cluster():
    """A real LocalCluster (processes=True, two workers) started the way `--workers 2` starts it."""
    with local_cluster(2) as address:
        yield address


def test_workers_limit_their_threads(cluster):
    with distributed.Client(cluster) as client:
        env = client.run(lambda: {v: os.environ.get(v) for v in ("OMP_NUM_THREADS", "MKL_NUM_THREADS",
                                                                "NUMBA_NUM_THREADS")})
    from pixmuscle.runners import available_cores

    want = str(max(1, available_cores() // 2))
    assert len(env) == 2 and all(set(e.values()) == {want} for e in env.values())


def test_cohort_on_dask_equals_serial(phantoms, tmp_path, cluster):
    serial = _config(tmp_path / "serial.yaml", tmp_path / "serial", phantoms)
    dask_cfg = _config(tmp_path / "dask.yaml", tmp_path / "dask", phantoms)
    assert run_pipeline(serial, workers=0)
    assert run_pipeline(dask_cfg, scheduler=cluster)
    a, b = _rows(tmp_path / "serial" / "cohort.csv"), _rows(tmp_path / "dask" / "cohort.csv")
    assert [r["subject"] for r in a] == [r["subject"] for r in b] == ["young", "old"]
    for col in a[0]:
        if col in ("subject", "status"):
            assert [r[col] for r in a] == [r[col] for r in b]
        else:
            # '' = no value (e.g. a ratio to a zero volume): compared as missing
            vb, va = ([float(r[col]) if r[col] != "" else np.nan for r in rows] for rows in (b, a))
            np.testing.assert_allclose(vb, va, rtol=1e-10, atol=0)
    assert float(a[0]["F_max [N]"]) > 0
    # resume: nothing but the reports runs again on the cluster
    assert run_pipeline(dask_cfg, scheduler=cluster)
    status = json.loads((tmp_path / "dask" / "cohort_status.json").read_text())
    assert all(s["ran"] == ["report"] for s in status["ok"])


def test_study_2x2_equals_one_by_one(phantoms, tmp_path, cluster):
    young = {"young": phantoms["young"]}
    vary = {"solve.materials.muscle.sigma_max": [20.0, 30.0], "solve.materials.connective_tissue.C10": [15.0, 60.0]}
    cfg = _config(tmp_path / "study.yaml", tmp_path / "study", young, study={"vary": vary})
    assert run_pipeline(cfg, scheduler=cluster)
    rows = _rows(tmp_path / "study" / "study.csv")
    assert len(rows) == 4 and (tmp_path / "study" / "study.html").exists()
    reports = sorted((tmp_path / "study").glob("*/report/index.html"))
    assert len(reports) == 4
    # the shared stages ran once, in the subject folder
    assert (tmp_path / "study" / "model_coarse.h5").exists()
    for r in rows:
        sigma, c10 = float(r["solve.materials.muscle.sigma_max"]), float(r["solve.materials.connective_tissue.C10"])
        one = _config(tmp_path / "one.yaml", tmp_path / f"one_{sigma}_{c10}", young)
        raw = yaml.safe_load(one.read_text())
        raw["solve"]["materials"] = {"muscle": {"sigma_max": sigma}, "connective_tissue": {"C10": c10}}
        one.write_text(yaml.safe_dump(raw))
        s = run_subject(load_subjects(one)[0])
        summary = json.loads(Path(s["report"]).with_name("summary.json").read_text())
        np.testing.assert_allclose(float(r["F_max [N]"]), summary["F_max_N"], rtol=1e-10)
        np.testing.assert_allclose(float(r["F_max / total volume [N/cm^3]"]),
                                   summary["force_per_volume_N_per_cm3"], rtol=1e-10)
    f = {(float(r["solve.materials.muscle.sigma_max"]), float(r["solve.materials.connective_tissue.C10"])):
         float(r["F_max [N]"]) for r in rows}
    assert f[30.0, 15.0] > f[20.0, 15.0]      # more fibre stress, more force


class KillOnStage(distributed.WorkerPlugin):
    """Kills the worker process (SIGKILL) when a task whose key contains ``match`` starts executing,
    at most ``times`` times over all workers (counted with marker files)."""

    name = "pixmuscle-test-killer"

    def __init__(self, marker_dir: str, match: str, times: int):
        self.marker_dir, self.match, self.times = marker_dir, match, times

    def transition(self, key, start, finish, **kwargs):
        if finish == "executing" and self.match in str(key):
            d = Path(self.marker_dir)
            if len(list(d.glob("kill-*"))) < self.times:
                (d / f"kill-{len(list(d.glob('kill-*')))}").touch()
                os.kill(os.getpid(), signal.SIGKILL)


def test_killed_worker_is_retried_once_then_reported(phantoms, tmp_path):
    with local_cluster(2) as own, distributed.Client(own) as client:   # its own cluster: workers get killed
        for times in (1, 2):
            cfg = _config(tmp_path / f"kill{times}.yaml", tmp_path / f"kill{times}", phantoms)
            marks = tmp_path / f"marks{times}"
            marks.mkdir()
            client.register_plugin(KillOnStage(str(marks), "old:solve", times))
            ok = run_pipeline(cfg, scheduler=own)
            status = json.loads((tmp_path / f"kill{times}" / "cohort_status.json").read_text())
            assert len(list(marks.glob("kill-*"))) == times
            assert "young" in [s["name"] for s in status["ok"]]
            if times == 1:   # one death: the solve ran again on a fresh worker and the case is complete
                assert ok and [s["name"] for s in status["ok"]] == ["young", "old"]
                client.wait_for_workers(2, timeout=120)
            else:            # died again on the retry: reported, nothing half-written
                assert not ok
                [fail] = status["failed"]
                assert fail["name"] == "old" and "died" in fail["error"] and "solve" in fail["error"]
                assert not (tmp_path / "kill2" / "old" / "results_coarse.h5").exists()
                assert "old" in (tmp_path / "kill2" / "cohort.html").read_text()


def test_failing_case_is_reported_and_the_others_finish(phantoms, tmp_path, cluster):
    broken = tmp_path / "broken_labels.nii.gz"
    broken.write_bytes(b"not a NIfTI file")
    inputs = {"young": phantoms["young"], "broken": {"labels": str(broken), "fibers": phantoms["young"]["fibers"]}}
    cfg = _config(tmp_path / "fail.yaml", tmp_path / "fail", inputs)
    records = []
    handler = logging.Handler()
    handler.emit = records.append
    log = logging.getLogger("pixmuscle.runners")
    log.addHandler(handler)
    old_level = log.level
    log.setLevel(logging.INFO)
    try:
        assert run_pipeline(cfg, scheduler=cluster) is False
    finally:
        log.removeHandler(handler)
        log.setLevel(old_level)
    status = json.loads((tmp_path / "fail" / "cohort_status.json").read_text())
    assert [s["name"] for s in status["ok"]] == ["young"]
    [fail] = status["failed"]
    assert fail["name"] == "broken" and fail["error"].startswith("build-model: ") and "broken_labels.nii.gz" in fail["error"]
    assert (tmp_path / "fail" / "young" / "report" / "index.html").exists()
    # progress: one line per case and state, a total after each finished case
    lines = [r.getMessage() for r in records]
    for who in ("young", "broken"):
        assert f"{who}: queued" in lines and f"{who}: running" in lines
    assert any(x.startswith("young: done in ") for x in lines)
    assert any(x.startswith("broken: failed after ") and "broken_labels.nii.gz" in x for x in lines)
    assert any(x.startswith("total: 1/2 finished") and "ETA" in x for x in lines)


def test_cli_workers_option(phantoms, tmp_path):
    from typer.testing import CliRunner

    from pixmuscle.cli import app

    cfg = _config(tmp_path / "cli.yaml", tmp_path / "cli", phantoms)
    res = CliRunner().invoke(app, ["-q", "run", str(cfg), "--workers", "2"])
    assert res.exit_code == 0, res.output
    assert len(_rows(tmp_path / "cli" / "cohort.csv")) == 2


def test_plugin_law_on_the_workers(tmp_path, cluster):
    """A material law of a plugin file (config `plugins`) is imported by each worker before it unpickles a
    stage: both cases of a cohort on the cluster give the law's closed-form force."""
    from test_material_law_plugin import LAM, MU, _check_closed_form
    from test_material_law_plugin import _config as block_config

    law = tmp_path / "fat_on_dask.py"
    law.write_text(Path(__file__).with_name("neo_hooke_law.py").read_text().replace('"neo_hooke"', '"fat_on_dask"'))
    cfg = {**block_config(tmp_path, {"fat": {"law": "fat_on_dask", "mu": MU, "lam": LAM}}),
           "plugins": [law.name], "subjects": [{"name": "a"}, {"name": "b"}]}
    path = tmp_path / "c.yaml"
    path.write_text(yaml.safe_dump(cfg))
    assert run_pipeline(path, scheduler=cluster, until="solve")
    for name in ("a", "b"):
        _check_closed_form(tmp_path / "out" / name / "results_fine.h5")

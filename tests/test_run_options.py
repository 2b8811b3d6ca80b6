"""`pixmuscle run -o DIR --set key=value --subject NAME`: overrides typed and checked like the file."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import h5py
import pytest
import yaml

from pixmuscle.errors import InputError
from pixmuscle.overrides import parse_override
from pixmuscle.pipeline import load_run

ROOT = Path(__file__).resolve().parents[1]
LABELS = ROOT / "data" / "synthetic" / "leg_demo_labels.nii.gz"
FIBERS = ROOT / "data" / "synthetic" / "leg_demo_fibers.nii.gz"
SOLVE = {"steps": 4, "activation": {"from": 0.0, "to": 0.5},
         "boundary_conditions": [{"nodes": "z_min", "fix": ["x", "y", "z"]}]}


def _cohort(tmp_path) -> Path:
    cfg = {"build_model": {"labels": str(LABELS)}, "solve": SOLVE,
           "subjects": [{"name": "young"}, {"name": "old", "solve": {"steps": 7}}]}
    p = tmp_path / "cohort.yaml"
    p.write_text(yaml.safe_dump(cfg))
    return p


def test_parse_override_types():
    assert parse_override("solve.steps=5") == ("solve.steps", 5)
    assert parse_override("solve.activation.to=0.5") == ("solve.activation.to", 0.5)
    assert parse_override("report.vtu=false") == ("report.vtu", False)
    assert parse_override("models=[fine, coarse]") == ("models", ["fine", "coarse"])
    for bad in ("solve.steps", "=3", "solve..steps=3"):
        with pytest.raises(InputError, match="KEY.PATH=VALUE"):
            parse_override(bad)


def test_set_wins_over_file_and_subjects_and_is_validated(tmp_path):
    path = _cohort(tmp_path)
    run = load_run(path, overrides=["solve.steps=3"])
    assert [c.solve.steps for c in run.cases] == [3, 3]
    with pytest.raises(InputError, match=r"solve\.steps"):
        load_run(path, overrides=["solve.steps=three"])
    with pytest.raises(InputError, match="stpes"):
        load_run(path, overrides=["solve.stpes=3"])
    with pytest.raises(InputError, match="unknown top-level key"):
        load_run(path, overrides=["solv.steps=3"])


def test_output_dir_and_subject(tmp_path):
    path = _cohort(tmp_path)
    run = load_run(path, output_dir=tmp_path / "elsewhere", subject="old")
    assert [c.name for c in run.cases] == ["old"] and run.cases[0].solve.steps == 7
    assert run.cases[0].output_dir == (tmp_path / "elsewhere" / "old").resolve()
    with pytest.raises(InputError, match="did you mean 'old'"):
        load_run(path, subject="olf")


def test_cli_run_prints_the_case_folder_and_uses_the_override(tmp_path):
    cfg = tmp_path / "one.yaml"
    cfg.write_text(yaml.safe_dump({"build_model": {"labels": str(LABELS)}, "solve": SOLVE}))
    out = tmp_path / "out dir"
    p = subprocess.run([sys.executable, "-m", "pixmuscle.cli", "run", str(cfg), "-o", str(out), "--until", "build-model",
                        "--set", f"build_model.fibers={FIBERS}"], capture_output=True, text=True, cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert p.stdout == f"{out.resolve()}\n"
    with h5py.File(out / "model.h5") as f:
        assert f"fibers: {FIBERS}" in f.attrs["config"]

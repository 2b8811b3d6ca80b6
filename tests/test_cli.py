"""CLI behaviour: one-line errors with exit code 2, --debug tracebacks, help for every command."""

from __future__ import annotations

import subprocess
import sys

import pytest
from typer.testing import CliRunner

from pixmuscle import __version__
from pixmuscle.cli import app

runner = CliRunner()


def test_version_and_help():
    r = runner.invoke(app, ["--version"])
    assert r.exit_code == 0 and __version__ in r.output
    for cmd in ["segment", "build-model", "coarsen", "solve", "report", "run", "synth", "verify"]:
        r = runner.invoke(app, [cmd, "--help"])
        assert r.exit_code == 0, (cmd, r.output)


def test_missing_config_is_one_line_exit_2(tmp_path):
    r = runner.invoke(app, ["run", str(tmp_path / "nope.yaml")])
    assert r.exit_code == 2
    assert "config file not found" in r.output
    assert "Traceback" not in r.output


def test_unknown_top_level_key(tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("solv:\n  steps: 3\n")
    r = runner.invoke(app, ["run", str(cfg)])
    assert r.exit_code == 2
    assert "solv: unknown top-level key; did you mean 'solve'?" in r.output


def test_bad_stage_name(tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("title: x\n")
    r = runner.invoke(app, ["run", str(cfg), "--from", "sovle"])
    assert r.exit_code == 2 and "unknown stage 'sovle'" in r.output


def test_debug_shows_traceback(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "pixmuscle.cli", "--debug", "run", str(tmp_path / "nope.yaml")],
        capture_output=True, text=True,
    )
    assert proc.returncode != 0
    assert "Traceback" in proc.stderr and "InputError" in proc.stderr


@pytest.mark.parametrize("quiet", [["-q"], []])
def test_quiet_flag_accepted(tmp_path, quiet):
    r = runner.invoke(app, [*quiet, "run", str(tmp_path / "nope.yaml")])
    assert r.exit_code == 2

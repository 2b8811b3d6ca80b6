"""What the CLI prints, run as a real process: result paths on stdout, logs on stderr, verbosity,
no wrapping of long paths, `report` without -o, no folder left after a failed report."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from fixtures_results import write_results_fixture

from pixmuscle import __version__
from pixmuscle.io.model import save_model
from pixmuscle.verify.mechanics import mask_model


def _cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "pixmuscle.cli", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd)


def test_version():
    p = _cli("--version")
    assert p.returncode == 0 and p.stdout.strip() == f"pixmuscle {__version__}"


def test_report_without_output_writes_next_to_the_results_and_prints_only_the_path(tmp_path):
    deep = tmp_path / ("a_folder_name_long_enough_that_a_terminal_of_eighty_columns_would_split_it_" * 2) / "run"
    truth = write_results_fixture(deep / "results.h5", n_steps=1)
    p = _cli("report", truth.path, cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    index = deep / "results_report" / "index.html"
    assert p.stdout == f"{index}\n"  # the whole path on one line, nothing else on stdout
    assert index.exists()
    assert not (tmp_path / "report").exists()  # nothing in the current folder


def test_failed_report_leaves_no_folder(tmp_path):
    p = _cli("report", tmp_path / "missing.h5", cwd=tmp_path)
    assert p.returncode == 2 and p.stdout == ""
    assert p.stderr.startswith("error: ") and p.stderr.count("\n") == 1
    assert list(tmp_path.iterdir()) == []


@pytest.fixture(scope="module")
def tiny_model(tmp_path_factory):
    d = tmp_path_factory.mktemp("cli")
    model = mask_model(np.ones((3, 3, 4), bool), (0.2, 0.2, 0.3), tissue=1)
    save_model(d / "model.h5", model)
    (d / "c.yaml").write_text("solve:\n  steps: 1\n  activation: {from: 0.0, to: 0.3}\n  boundary_conditions:\n"
                              "    - {nodes: z_min, fix: [x, y, z]}\n    - {nodes: z_max, fix: [x, y, z]}\n")
    return d


def test_verbosity_changes_what_is_logged(tiny_model):
    d = tiny_model
    runs = {flags: _cli(*flags, "solve", d / "model.h5", "-c", d / "c.yaml", "-o", d / f"r{len(flags)}.h5")
            for flags in ((), ("-v",), ("-vv",), ("-q",))}
    for flags, p in runs.items():
        assert p.returncode == 0, (flags, p.stderr)
        assert p.stdout.strip().endswith(".h5") and p.stdout.count("\n") == 1  # only the result path
    default, v, vv, q = (runs[f].stderr for f in ((), ("-v",), ("-vv",), ("-q",)))
    assert "solve: 36 nodes" in default and "load step 1 of 1" not in default
    assert "load step 1 of 1" in v and "Newton iteration 0" not in v
    assert "Newton iteration 0" in vv and "DEBUG" in vv
    assert q == ""


def test_global_options_work_after_the_command(tiny_model):
    """-v / -vv / -q / --debug where users type them: after the command name, as before it."""
    d = tiny_model
    after = {flags: _cli("solve", d / "model.h5", "-c", d / "c.yaml", "-o", d / f"a{len(flags)}.h5", *flags)
             for flags in (("-vv",), ("-q",))}
    for flags, p in after.items():
        assert p.returncode == 0, (flags, p.stderr)
        assert p.stdout == f"{d / f'a{len(flags)}.h5'}\n"
    assert "Newton iteration 0" in after[("-vv",)].stderr and "DEBUG" in after[("-vv",)].stderr
    assert after[("-q",)].stderr == ""
    p = _cli("run", d / "missing.yaml", "--debug")
    assert p.returncode != 0 and "Traceback" in p.stderr and "No such option" not in p.stderr
    p = _cli("run", d / "missing.yaml", "-v")
    assert p.returncode == 2 and "config file not found" in p.stderr and "No such option" not in p.stderr


@pytest.mark.parametrize("args", [(), ("run",), ("solve",), ("report",), ("verify", "rk")])
def test_help_shows_flags_without_a_value(args):
    """Flags (-q, --force, --debug, --help) take no value, so the help shows none."""
    p = _cli(*args, "--help")
    assert p.returncode == 0, p.stderr
    assert "<bool>" not in p.stdout and "BOOLEAN" not in p.stdout
    assert "-q, --quiet" in p.stdout and "--debug" in p.stdout


def test_help_lists_the_exit_codes():
    p = _cli("--help")
    assert "3 a failed solve" in " ".join(p.stdout.split())

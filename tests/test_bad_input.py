"""Failures, faults and hostile input: each case gives one line naming the file or key,
the exit code, and leaves nothing that looks complete.

One small phantom is segmented, modelled and solved once (module fixture, a few seconds); the
cases copy its output folder and break one thing each. Real processes where it matters (the
output lock, stderr, disk full on a small tmpfs mounted in a private mount namespace).
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import h5py
import nibabel as nib
import numpy as np
import pytest
import yaml
from fixtures_results import write_mg_phantom
from typer.testing import CliRunner

from pixmuscle.cli import app
from pixmuscle.errors import InputError, SolverError
from pixmuscle.pipeline import load_subjects, run_subject

runner = CliRunner()


# --------------------------------------------------------------------------- fixtures and helpers
@pytest.fixture(scope="module")
def phantom(tmp_path_factory):
    """A tiny SYNTHETIC medial-gastrocnemius phantom (48 × 32 × 3 voxels) and a seed inside the muscle."""
    return write_mg_phantom(tmp_path_factory.mktemp("phantom"))


def base_config(phantom, out_dir) -> dict:
    d, seed = phantom
    return {
        "title": "bad-input phantom", "synthetic": True, "output_dir": str(out_dir), "models": ["coarse"],
        "segment": {"mri": str(d / "mg_mri.nii.gz"), "dti_tensor": str(d / "mg_dti_tensor.nii.gz"),
                    "imct_mask": str(d / "mg_imct.nii.gz"), "imat_mask": str(d / "mg_imat.nii.gz"),
                    "seeds": {"medial_gastrocnemius": [seed]}},
        "build_model": {},
        "coarsen": {"factor": 2},
        "solve": {"steps": 2, "activation": {"from": 0.0, "to": 0.5},
                  "boundary_conditions": [{"nodes": "z_min", "fix": ["x", "y", "z"]},
                                          {"nodes": "z_max", "fix": ["x", "y", "z"]}]},
        "report": {"vtu": True, "slices": False, "html": True},
    }


@pytest.fixture(scope="module")
def solved(phantom, tmp_path_factory):
    """Output folder of one complete run (never modified: cases work on copies)."""
    tmp = tmp_path_factory.mktemp("solved")
    cfg = base_config(phantom, tmp / "out")
    path = write_config(tmp / "config.yaml", cfg)
    run_subject(load_subjects(path)[0])
    return tmp / "out", cfg


def write_config(path: Path, cfg: dict | str) -> Path:
    path.write_text(cfg if isinstance(cfg, str) else yaml.safe_dump(cfg, sort_keys=False))
    return path


def copy_run(solved, tmp_path, **changes) -> tuple[Path, Path]:
    """A copy of the solved output folder and a config pointing at it (``changes``: section overrides)."""
    src, cfg = solved
    out = tmp_path / "out"
    shutil.copytree(src, out)
    cfg = {**cfg, "output_dir": str(out), **changes}
    return write_config(tmp_path / "config.yaml", cfg), out


def cli(*args):
    return runner.invoke(app, [str(a) for a in args])


def proc(*args, **kw):
    return subprocess.run([sys.executable, "-m", "pixmuscle.cli", *map(str, args)], capture_output=True, text=True, **kw)


def error_line(stderr: str) -> str:
    """The one error line of a failed command (no traceback, nothing multi-line)."""
    assert "Traceback" not in stderr, stderr
    lines = [ln for ln in stderr.splitlines() if ln.startswith("error:")]
    assert len(lines) == 1, stderr
    return lines[0]


def leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in Path(folder).rglob("*") if p.name.endswith(".partial"))


def dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def _can_mount() -> bool:
    if sys.platform != "linux" or shutil.which("unshare") is None:
        return False
    probe = subprocess.run(["unshare", "-rm", "sh", "-c", "d=$(mktemp -d) && mount -t tmpfs -o size=64k tmpfs $d"],
                           capture_output=True)
    return probe.returncode == 0


needs_mount = pytest.mark.skipif(not _can_mount(), reason="cannot mount a tmpfs in a private mount namespace here")


def in_tmpfs(mount: Path, options: str, *args) -> subprocess.CompletedProcess:
    """Run pixmuscle with a fresh tmpfs on ``mount`` (private mount namespace: gone afterwards);
    prints the mount's contents after the command as a line ``LEFT: ...``."""
    mount.mkdir(parents=True, exist_ok=True)
    cmd = " ".join(["exec_pm() {", sys.executable, "-m", "pixmuscle.cli", '"$@"; }'])
    script = (f'mount -t tmpfs -o {options} tmpfs "$0" || exit 99; {cmd}; exec_pm "$@"; rc=$?; '
              'echo "LEFT: $(ls -A "$0" | tr "\\n" " ")"; exit $rc')
    return subprocess.run(["unshare", "-rm", "sh", "-c", script, str(mount), *map(str, args)],
                          capture_output=True, text=True)


# --------------------------------------------------------------------------- failed solves
def test_failed_solve_rewrites_the_report_as_failed(solved, tmp_path):
    """After a complete run, a failing solve leaves a report that says failed."""
    cfg_path, out = copy_run(solved, tmp_path)
    assert json.loads((out / "report/summary.json").read_text())["status"] == "complete"
    raw = yaml.safe_load(cfg_path.read_text())
    raw["solve"]["newton"] = {"max_iterations": 2, "max_cutbacks": 0}   # step 1 cannot converge in 2 iterations
    write_config(cfg_path, raw)
    r = proc("run", cfg_path)                                          # the real command, as a script sees it
    assert r.returncode == 3                                           # a failed solve, not a bad input (2)
    assert "load step 1 of 2" in error_line(r.stderr)
    assert r.stdout.splitlines() == [str(out / "report" / "index.html")]   # the report that says why
    with h5py.File(out / "results_coarse.h5") as f:
        assert str(f.attrs["status"]).startswith("failed")
    summary = json.loads((out / "report/summary.json").read_text())
    assert summary["failed"] and summary["status"].startswith("failed: load step 1 of 2")
    assert summary["curve"]["converged"] == [True]                       # the converged steps are shown
    html = (out / "report/index.html").read_text()
    assert "did not complete" in html and "load step 1 of 2" in html
    assert leftovers(out) == []


def test_failed_solve_stage_prints_its_results_and_exits_3(solved, tmp_path):
    """The `solve` command alone: a failed solve prints the results file of its converged steps, exit 3."""
    cfg_path, out = copy_run(solved, tmp_path)
    raw = yaml.safe_load(cfg_path.read_text())
    raw["solve"]["newton"] = {"max_iterations": 2, "max_cutbacks": 0}
    write_config(cfg_path, raw)
    res = tmp_path / "failed.h5"
    r = proc("solve", out / "model_coarse.h5", "-c", cfg_path, "-o", res, "-q")   # -q after the command
    assert r.returncode == 3, r.stderr
    assert r.stdout.splitlines() == [str(res)] and "load step 1 of 2" in error_line(r.stderr)
    assert "INFO" not in r.stderr and "solve:" not in r.stderr.replace(error_line(r.stderr), "")
    with h5py.File(res) as f:
        assert str(f.attrs["status"]).startswith("failed")


def test_max_iterations_one_is_a_config_error(solved, tmp_path):
    """A setting that can never converge is refused before any work."""
    cfg_path, out = copy_run(solved, tmp_path)
    raw = yaml.safe_load(cfg_path.read_text())
    raw["solve"]["newton"] = {"max_iterations": 1}
    write_config(cfg_path, raw)
    r = cli("run", cfg_path)
    assert r.exit_code == 2 and "solve.newton: max_iterations: 1 can never converge" in error_line(r.stderr)


class _Saturating:
    """One node, residual r = t·g − tanh(d) per component: no equilibrium once t·g > 1.

    Newton can never get the residual below t·g − 1, so once the increment is past the limit every
    attempt stagnates, whatever its size."""

    n_nodes, atol = 1, 1e-12

    def __init__(self, g):
        self.g = g

    def evaluate(self, d, t, alpha):
        from types import SimpleNamespace

        return SimpleNamespace(d=d, t=t, alpha=alpha, r=t * self.g - np.tanh(d), force_scale=max(t * self.g, 1e-30))

    def energy(self, s):
        return float(np.sum(np.log(np.cosh(s.d)) - s.t * self.g * s.d))


class _Diagonal:
    def prepare(self, system, state):
        self.k = np.maximum(1.0 / np.cosh(np.minimum(np.abs(state.d), 300.0)) ** 2, 1e-300).ravel()

    def solve(self, r, rtol=None):
        return r / self.k


def test_cutbacks_stop_when_they_cannot_help():
    """Two stagnating attempts in a row end the step instead of cutting back 6 times."""
    from pixmuscle.mechanics.config import NewtonConfig
    from pixmuscle.mechanics.newton import load_steps

    cfg = NewtonConfig(max_iterations=6, max_cutbacks=6)
    with pytest.raises(SolverError) as exc:
        load_steps(_Saturating(g=10.0), 1, 0.0, 1.0, cfg, _Diagonal())
    msg = str(exc.value)
    assert "after 1 cutbacks" in msg and "stopped early: two successive cutbacks stagnated" in msg
    # a load the model can carry is still reached through cutbacks (t·g ≤ 0.9 < 1 at every step)
    records = load_steps(_Saturating(g=0.9), 1, 0.0, 1.0, NewtonConfig(max_iterations=25), _Diagonal())
    assert np.allclose(np.tanh(records[-1].state.d), 0.9)


# --------------------------------------------------------------------------- the report as a unit, leftovers
def test_report_failing_midway_leaves_the_old_report_untouched(solved, tmp_path):
    """The report folder is replaced as a unit; a failure half-way changes nothing."""
    _, out = copy_run(solved, tmp_path)
    before = {p.relative_to(out): p.read_bytes() for p in (out / "report").rglob("*") if p.is_file()}
    bad = write_config(tmp_path / "report.yaml", {"report": {"slices": True, "slice_step": 99}})
    r = cli("report", out / "results_coarse.h5", "-o", out / "report", "-c", bad)   # fails after the CSVs
    assert r.exit_code == 2 and "report.slice_step" in error_line(r.stderr)
    after = {p.relative_to(out): p.read_bytes() for p in (out / "report").rglob("*") if p.is_file()}
    assert after == before
    assert leftovers(out) == []


def test_leftover_partials_are_removed(solved, tmp_path):
    """Temporaries of killed writes (stage file, report folder) are swept."""
    cfg_path, out = copy_run(solved, tmp_path)
    host, pid = socket.gethostname(), dead_pid()
    (out / f".results_coarse.h5.{host}.{pid}.x1y2.partial").write_bytes(b"half an HDF5 file")
    (out / ".results_coarse.h5.old_style.partial").write_bytes(b"from an older version")
    live = out / f".model.h5.{host}.{os.getpid()}.k5l6.partial"       # a writer that still runs: kept
    live.write_bytes(b"being written")
    killed_report = out / f".report.{host}.{pid}.z3w4.partial"
    killed_report.mkdir()
    (killed_report / "force_activation.csv").write_text("alpha\n0\n")
    r = cli("run", cfg_path, "--from", "report")
    assert r.exit_code == 0, r.stderr
    assert leftovers(out) == [live.name]
    assert (out / "report/index.html").exists()
    assert ".partial" not in (out / "report/summary.json").read_text()     # paths name the final folder


def test_write_stage_removes_temporaries_of_dead_writers_only(tmp_path):
    """Single-stage commands: the next write of a file removes its dead writer's temporary."""
    from pixmuscle.store import write_stage

    host = socket.gethostname()
    dead = tmp_path / f".m.h5.{host}.{dead_pid()}.abcd.partial"
    alive = tmp_path / f".m.h5.{host}.{os.getpid()}.efgh.partial"
    other_host = tmp_path / f".m.h5.elsewhere.{dead_pid()}.ijkl.partial"
    for p in (dead, alive, other_host):
        p.write_bytes(b"x")
    write_stage(tmp_path / "m.h5", schema="pixmuscle.test", version=1, write=lambda f: None)
    assert not dead.exists() and alive.exists() and other_host.exists()
    assert oct((tmp_path / "m.h5").stat().st_mode & 0o777) == oct(0o666 & ~_umask())


def _umask() -> int:
    m = os.umask(0)
    os.umask(m)
    return m


# --------------------------------------------------------------------------- unique subjects, one run per output folder
def test_duplicate_subject_names(phantom, tmp_path):
    """Two subjects of one name are refused by pipeline.load_run before anything is written."""
    cfg = base_config(phantom, tmp_path / "cohort")
    cfg["subjects"] = [{"name": "young"}, {"name": "young", "solve": {"steps": 1}}]
    c = write_config(tmp_path / "c.yaml", cfg)
    r = cli("run", c)
    assert r.exit_code == 2
    assert f"{c}: subjects[1].name: 'young' is already the name of subjects[0]" in error_line(r.stderr)
    assert not (tmp_path / "cohort").exists()


def test_second_run_into_a_locked_folder_refuses(solved, tmp_path):
    """A run holding the folder makes another run refuse, naming the holder."""
    cfg_path, out = copy_run(solved, tmp_path)
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys; from pixmuscle.outdir import output_lock\n"
         f"with output_lock({str(out)!r}):\n    print('locked', flush=True); sys.stdin.read()"],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        r = proc("run", cfg_path)
        line = error_line(r.stderr)
        assert r.returncode == 2 and "in use by another pixmuscle run" in line and f"pid {holder.pid}" in line
    finally:
        holder.stdin.close()
        holder.wait()
    r = cli("run", cfg_path, "--from", "report")  # the lock went with its holder
    assert r.exit_code == 0, r.stderr


# --------------------------------------------------------------------------- DTI without signal
def test_dti_hole_in_a_muscle_is_reported(phantom, tmp_path):
    """Zero tensors over part of the muscle: warning with voxel counts, in the log and the report."""
    d, seed = phantom
    img = nib.load(d / "mg_dti_tensor.nii.gz")
    assert img.header.get_xyzt_units()[0] == "mm"
    data = np.asarray(img.dataobj).copy()
    world = nib.affines.apply_affine(img.affine, np.indices(data.shape[:3]).reshape(3, -1).T).reshape(*data.shape[:3], 3)
    dx, dy = world[..., 0] - 10 * seed[0], world[..., 1] - 10 * seed[1]   # mm from the seed
    data[(dx > -12) & (dx < -3) & (np.abs(dy) < 6)] = 0                    # a hole beside (not on) the seed
    hole = tmp_path / "dti_hole.nii.gz"
    nib.save(nib.Nifti1Image(data, img.affine, img.header), hole)
    cfg = base_config(phantom, tmp_path / "out")
    cfg["segment"]["dti_tensor"] = str(hole)
    cfg["solve"]["steps"] = 1
    cfg["report"] = {"vtu": False, "slices": False, "html": True}
    r = cli("run", write_config(tmp_path / "c.yaml", cfg))
    assert r.exit_code == 0, r.stderr
    assert "DTI has no signal" in r.stderr and "medial_gastrocnemius" in r.stderr and "DTI" not in r.stdout
    with h5py.File(tmp_path / "out/segmentation.h5") as f:
        counts = f["qc/no_signal_voxels"][()]
    assert counts[0] > 0
    warnings = json.loads((tmp_path / "out/report/summary.json").read_text())["warnings"]
    assert any("DTI has no signal" in w and f"medial_gastrocnemius {counts[0]}" in w for w in warnings)


# --------------------------------------------------------------------------- boundary conditions
def test_point_bc_far_outside_the_body(solved, tmp_path):
    """A point farther than one cell from every node is an error naming the BC."""
    out, cfg = solved
    c = write_config(tmp_path / "c.yaml", {"solve": {**cfg["solve"], "boundary_conditions": [
        {"nodes": "z_min", "fix": ["x", "y", "z"]}, {"point": [0.0, 0.0, 162.0], "fix": ["x"]}]}})
    r = cli("solve", out / "model_coarse.h5", "-c", c, "-o", tmp_path / "r.h5")
    assert r.exit_code == 2
    assert "solve.boundary_conditions[1].point: [0.0, 0.0, 162.0] cm is" in error_line(r.stderr)
    assert not (tmp_path / "r.h5").exists() and leftovers(tmp_path) == []


def test_missing_node_set_is_caught_before_any_stage(phantom, tmp_path):
    """A BC naming a set the model will not have stops the run before segmenting."""
    cfg = base_config(phantom, tmp_path / "out")
    cfg["solve"]["boundary_conditions"][1]["nodes"] = "z_top"
    r = cli("run", write_config(tmp_path / "c.yaml", cfg))
    assert r.exit_code == 2
    assert "solve.boundary_conditions[1].nodes: node set 'z_top' does not exist" in error_line(r.stderr)
    assert not (tmp_path / "out/segmentation.h5").exists()


# --------------------------------------------------------------------------- config files
@pytest.mark.parametrize("text, expected", [
    ("solve:\n  steps: 10\n  activation: {from: 0, to: 1}\n  steps: 2\n",
     ":4:3: not valid YAML: key 'steps' is given twice (first on line 2)"),
    ("solve:\n  steps: 10\n  activation: {from: 0, to: 1\n", ":4:1: not valid YAML:"),
    ("solve:\n  steps: 10\n   boundary_conditions: []\n", ":3:23: not valid YAML: mapping values are not allowed here"),
    ("", ": the config file is empty"),
    ("# nothing but a comment\n", ": the config file is empty"),
])
def test_config_file_errors_name_file_line_column(tmp_path, monkeypatch, text, expected):
    monkeypatch.chdir(tmp_path)
    c = write_config(tmp_path / "demo.yaml", text)
    r = cli("run", c)
    assert r.exit_code == 2
    assert error_line(r.stderr).startswith(f"error: {c}{expected}")
    assert not (tmp_path / "out").exists()                                  # nothing created


@pytest.mark.parametrize("solve, key", [
    ({"boundary_conditions": [{"nodes": "z_min", "fix": ["x", "y", "z"]}, {"nodes": "z_max", "displace": {"z": float("nan")}}]},
     "solve.boundary_conditions[1].displace.z: expected a finite number, got nan"),
    ({"materials": {"muscle": {"sigma_max": float("nan")}}}, "solve.materials.muscle.sigma_max: expected a finite number, got nan"),
    ({"activation": {"from": 0.0, "to": float("inf")}}, "solve.activation.to: expected a finite number, got inf"),
    ({"penalty": {"factor": float("-inf")}}, "solve.penalty.factor: expected a finite number, got -inf"),
])
def test_nan_and_inf_in_config_name_the_key(phantom, tmp_path, solve, key):
    """NaN/inf are config errors naming the key (not a Newton failure later)."""
    cfg = base_config(phantom, tmp_path / "out")
    cfg["solve"].update(solve)
    with pytest.raises(InputError, match=None) as exc:
        load_subjects(write_config(tmp_path / "c.yaml", cfg))
    assert key in str(exc.value)


def test_nan_in_yaml_text_exit_2(phantom, tmp_path):
    cfg = yaml.safe_dump(base_config(phantom, tmp_path / "out")).replace("to: 0.5", "to: .nan")
    r = cli("run", write_config(tmp_path / "c.yaml", cfg))
    assert r.exit_code == 2 and "solve.activation.to: expected a finite number, got nan" in error_line(r.stderr)
    assert not (tmp_path / "out").exists()


# --------------------------------------------------------------------------- output folder and disk
def test_output_dir_that_is_a_file(phantom, tmp_path):
    """An output_dir that is a file is refused, naming the path."""
    (tmp_path / "out").write_text("not a folder")
    r = cli("run", write_config(tmp_path / "c.yaml", base_config(phantom, tmp_path / "out")))
    assert r.exit_code == 2 and f"output_dir {tmp_path / 'out'}: is a file, expected a folder" in error_line(r.stderr)


@needs_mount
def test_read_only_output_folder_is_refused_before_work(phantom, tmp_path):
    """Checked before segmentation (a read-only file system stops even root)."""
    cfg = write_config(tmp_path / "c.yaml", base_config(phantom, tmp_path / "ro" / "out"))
    r = in_tmpfs(tmp_path / "ro", "ro", "run", cfg)
    assert r.returncode == 2
    assert f"output_dir {tmp_path / 'ro' / 'out'}: not writable (Read-only file system)" in error_line(r.stderr)
    assert "outer boundary" not in r.stderr                              # no stage started


@needs_mount
def test_read_only_output_of_a_stage_command_is_refused_before_work(solved, tmp_path):
    """For a single stage: `pixmuscle solve -o <read-only>/r.h5` stops before solving."""
    out, cfg = solved
    c = write_config(tmp_path / "c.yaml", {"solve": cfg["solve"]})
    r = in_tmpfs(tmp_path / "ro", "ro", "solve", out / "model_coarse.h5", "-c", c, "-o", tmp_path / "ro" / "r.h5")
    assert r.returncode == 2
    assert f"output folder {tmp_path / 'ro'}: not writable (Read-only file system)" in error_line(r.stderr)
    assert "load step" not in r.stdout + r.stderr


@needs_mount
@pytest.mark.parametrize("size, expected", [
    ("64k", "not enough free disk space for the results of this solve"),   # refused before solving
    ("128k", "not enough free disk space: the file needs"),               # the file's exact size, after it
])
def test_disk_full_stage_file(solved, tmp_path, size, expected):
    """A stage file that does not fit: one line with the path and the free space, nothing left."""
    out, cfg = solved
    c = write_config(tmp_path / "c.yaml", {"solve": cfg["solve"]})
    target = tmp_path / "small" / "results.h5"
    r = in_tmpfs(target.parent, f"size={size}", "solve", out / "model_coarse.h5", "-c", c, "-o", target)
    assert r.returncode == 2, r.stderr
    line = error_line(r.stderr)
    assert str(target) in line and expected in line and "MB free" in line
    left = r.stdout.split("LEFT:", 1)[1].split()
    # no half-written results; the converged steps of a finished solve are kept for the rerun
    assert left in ([], ["results.h5.checkpoint"]), left
    assert not left or "run the same command again" in r.stderr


@needs_mount
def test_disk_full_while_writing_vtu(solved, tmp_path):
    """The report (VTU series) runs out of space: one line, no partial VTU or report left."""
    out, _ = solved
    size = sum(p.stat().st_size for p in (out / "report").rglob("*") if p.is_file())
    target = tmp_path / "small"
    r = in_tmpfs(target, f"size={max(size // 3, 16384)}", "report", out / "results_coarse.h5", "-o", target / "report")
    assert r.returncode == 2, r.stderr + r.stdout
    line = error_line(r.stderr)
    assert "free" in line and str(target) in line
    assert r.stdout.strip() == "LEFT:"


@needs_mount
def test_disk_full_during_the_segment_side_outputs(phantom, tmp_path):
    """The NIfTI/PNG side outputs of segment do not fit: one line, and no segmentation.h5
    (the stage file is written last, so the stage is not taken as done)."""
    cfg = write_config(tmp_path / "c.yaml", base_config(phantom, tmp_path / "unused"))
    target = tmp_path / "small"
    r = in_tmpfs(target, "size=24k", "segment", "-c", cfg, "-o", target / "segmentation.h5")
    assert r.returncode == 2, r.stderr + r.stdout
    line = error_line(r.stderr)
    assert "No space left on device" in line and "free" in line and str(target) in line
    left = r.stdout.split("LEFT:", 1)[1].split()
    assert "segmentation.h5" not in left and not [n for n in left if n.startswith(".")]


# --------------------------------------------------------------------------- model file missing a dataset
def test_model_missing_a_dataset(solved, tmp_path):
    out, cfg = solved
    model = tmp_path / "model.h5"
    shutil.copy(out / "model_coarse.h5", model)
    with h5py.File(model, "a") as f:
        del f["nodes/fiber"]
    r = cli("solve", model, "-c", write_config(tmp_path / "c.yaml", {"solve": cfg["solve"]}), "-o", tmp_path / "r.h5")
    assert r.exit_code == 2 and f"{model}: dataset '/nodes/fiber' is missing" in error_line(r.stderr)
    assert not (tmp_path / "r.h5").exists()


# --------------------------------------------------------------------------- two muscles, one seed
def test_two_muscles_with_the_same_seed(phantom, tmp_path):
    cfg = base_config(phantom, tmp_path / "out")
    seed = cfg["segment"]["seeds"]["medial_gastrocnemius"]
    cfg["segment"]["seeds"] = {"medial_gastrocnemius": seed, "lateral_gastrocnemius": seed}
    r = cli("run", write_config(tmp_path / "c.yaml", cfg))
    assert r.exit_code == 2
    assert "segment.seeds: 'medial_gastrocnemius' and 'lateral_gastrocnemius' have a seed in the same voxel" \
        in error_line(r.stderr)
    assert not (tmp_path / "out/segmentation.h5").exists()


# --------------------------------------------------------------------------- log on stderr, decreasing activation
def test_decreasing_ramp_is_allowed_and_logged_on_stderr(solved, tmp_path):
    """A relaxation ramp (from > to) runs, and the log says so, on stderr."""
    out, cfg = solved
    solve = {**cfg["solve"], "activation": {"from": 0.5, "to": 0.1}}
    r = cli("solve", out / "model_coarse.h5", "-c", write_config(tmp_path / "c.yaml", {"solve": solve}),
            "-o", tmp_path / "r.h5")
    assert r.exit_code == 0, r.stderr
    assert "decreasing ramp" in r.stderr and "relaxation" in r.stderr
    assert "relaxation" not in r.stdout and "load step" not in r.stdout       # the log is on stderr
    with h5py.File(tmp_path / "r.h5") as f:
        assert f.attrs["status"] == "complete"
        np.testing.assert_allclose(f["steps/alpha"][()], [0.5, 0.3, 0.1])


# --------------------------------------------------------------------------- results that match their config
def _report_html(out: Path) -> str:
    return (out / "report" / "index.html").read_text()


def test_report_on_results_of_another_config_is_refused_or_marked(solved, tmp_path):
    """`--from report` after editing a solve key: refused naming the key and `--from solve`; with
    --allow-stale the report says so on its first screen and shows the config the results were solved with."""
    cfg_path, out = copy_run(solved, tmp_path)
    before = _report_html(out)
    raw = yaml.safe_load(cfg_path.read_text())
    raw["solve"]["materials"] = {"muscle": {"sigma_max": 20}}        # the results were solved with 30 (default)
    write_config(cfg_path, raw)
    r = proc("run", cfg_path, "--from", "report")
    assert r.returncode == 2, r.stderr
    line = error_line(r.stderr)
    assert "solve.materials.muscle.sigma_max is 20.0 in the config but results_coarse.h5 was made with 30.0" in line
    assert "--from solve" in line and "--allow-stale" in line
    assert _report_html(out) == before and not leftovers(out)     # nothing was run
    r = cli("run", cfg_path, "--from", "report", "--allow-stale")
    assert r.exit_code == 0, r.stderr
    html = _report_html(out)
    first_screen = html[:html.index("<h2>")]                       # above the first section heading
    assert "Inputs made under another configuration" in first_screen and "sigma_max is 20.0" in first_screen
    solved_with = html[html.index("<h2>Configuration</h2>"):html.index("<h2>Provenance</h2>")]
    assert "sigma_max: 30.0" in solved_with and "sigma_max: 20" not in solved_with
    # an edit of an earlier stage names that stage
    raw["solve"].pop("materials")
    raw["coarsen"] = {"factor": 3}
    write_config(cfg_path, raw)
    line = error_line(proc("run", cfg_path, "--from", "solve").stderr)
    assert "coarsen.factor is 3 in the config but model_coarse.h5 was made with 2" in line and "--from coarsen" in line


# --------------------------------------------------------------------------- SIGTERM (batch schedulers)
def _terminate(cmd: list, ready) -> tuple[int, str]:
    """Start ``pixmuscle`` with ``cmd``, send SIGTERM once ``ready(stderr_line)`` says so, return (rc, stderr)."""
    import signal

    p = subprocess.Popen([sys.executable, "-m", "pixmuscle.cli", *map(str, cmd)], stderr=subprocess.PIPE,
                         stdout=subprocess.DEVNULL, text=True)
    seen = []
    try:
        for line in p.stderr:
            seen.append(line)
            if ready(line):
                break
        p.send_signal(signal.SIGTERM)
        rest = p.stderr.read()
        return p.wait(timeout=60), "".join(seen) + rest
    finally:
        if p.poll() is None:
            p.kill()


def test_sigterm_during_the_report(solved, tmp_path):
    cfg_path, out = copy_run(solved, tmp_path)
    before = _report_html(out)
    rc, err = _terminate(["run", cfg_path], lambda line: "writing fields" in line)
    assert rc == 143, err
    last = err.strip().splitlines()[-1]
    assert last.startswith("terminated (SIGTERM) during report: its partial output was removed"), err
    assert "kept: segmentation.h5, model.h5, model_coarse.h5, results_coarse.h5" in last
    assert not leftovers(out) and _report_html(out) == before     # the earlier report as it was


def test_sigterm_during_the_solve(solved, tmp_path):
    cfg_path, out = copy_run(solved, tmp_path)
    rc, err = _terminate(["run", cfg_path, "--set", "solve.steps=300"], lambda line: "300 load steps" in line)
    assert rc == 143, err
    last = err.strip().splitlines()[-1]
    assert last.startswith("terminated (SIGTERM) during solve (coarse)") and "kept: segmentation.h5" in last, err
    assert not leftovers(out) and "Traceback" not in err


# --------------------------------------------------------------------------- bounded work
def test_too_many_load_steps_are_refused_before_any_work(phantom, tmp_path):
    c = write_config(tmp_path / "c.yaml", base_config(phantom, tmp_path / "out"))
    r = proc("run", c, "--set", "solve.steps=100000", timeout=60)  # (it used to start: hours, ~4 GB)
    assert r.returncode == 2
    assert "solve.steps: expected a value ≤ 1000, got 100000" in error_line(r.stderr)
    assert not (tmp_path / "out").exists()


def test_study_grid_beyond_the_bound_is_refused(phantom, tmp_path):
    cfg = base_config(phantom, tmp_path / "out")
    cfg["study"] = {"vary": {"solve.materials.muscle.sigma_max": list(range(1, 41)), "solve.steps": list(range(1, 31))}}
    r = proc("run", write_config(tmp_path / "c.yaml", cfg), timeout=60)
    assert r.returncode == 2
    line = error_line(r.stderr)
    assert "study.vary: the grid makes 1200 cases (40 (solve.materials.muscle.sigma_max) × 30 (solve.steps))" in line
    assert "bound of 1000" in line and not (tmp_path / "out").exists()


@needs_mount
def test_results_beyond_the_free_disk_are_refused_naming_solve_steps(solved, tmp_path):
    """The estimate of the results (nodes × states) against the free space, before the solve starts."""
    out, cfg = solved
    c = write_config(tmp_path / "c.yaml", {"solve": {**cfg["solve"], "steps": 1000}})
    target = tmp_path / "small" / "results.h5"
    r = in_tmpfs(target.parent, "size=1m", "solve", out / "model_coarse.h5", "-c", c, "-o", target)
    assert r.returncode == 2, r.stderr
    line = error_line(r.stderr)
    assert "not enough free disk space for the results of this solve: solve.steps = 1000 load steps" in line
    assert "lower solve.steps" in line and "load step 1" not in r.stderr
    assert r.stdout.strip() == "LEFT:"


def test_the_time_estimate_is_within_a_factor_1_5_of_the_recorded_sweeps():
    """The rough time a solve logs before it starts against every whole sweep recorded at today's
    defaults (benchmarks/results/bench_solve.json, not superseded; 5k to 295k nodes, 10 load steps)."""
    import json
    import pathlib

    from pixmuscle.preflight import estimate_solve

    path = pathlib.Path(__file__).parents[1] / "benchmarks" / "results" / "bench_solve.json"
    records = [c for c in json.loads(path.read_text())["cases"]
               if c.get("defaults") and c["status"] == "complete" and not c.get("superseded")]
    assert min(c["nodes"] for c in records) < 6_000 and max(c["nodes"] for c in records) > 250_000
    for c in records:
        seconds, _ = estimate_solve(c["nodes"], c["steps"])
        assert 1 / 1.5 < seconds / c["sweep_s"] < 1.5, (c["nodes"], seconds, c["sweep_s"])


def test_the_time_estimate_is_within_a_factor_2_for_every_backend():
    """The estimate against the recorded wall time of each backend on one model of few load steps
    (benchmarks/results/bench_backends.json: mixed_amg, direct, petsc_mixed under mpiexec -n 1 and 2),
    where the one-off set-up weighs most."""
    import json
    import pathlib

    from pixmuscle.preflight import estimate_solve

    path = pathlib.Path(__file__).parents[1] / "benchmarks" / "results" / "bench_backends.json"
    rows = [c for c in json.loads(path.read_text())["cases"] if not c.get("exit")]
    assert {c["backend"] for c in rows} >= {"mixed_amg", "direct", "petsc_mixed"}
    for c in rows:
        seconds, _ = estimate_solve(c["nodes"], c["steps"])
        assert 1 / 2 < seconds / c["wall_s"] < 2, (c["case"], seconds, c["wall_s"])


def test_solve_logs_its_estimate(solved, tmp_path):
    out, cfg = solved
    c = write_config(tmp_path / "c.yaml", {"solve": {**cfg["solve"], "steps": 1}})
    r = cli("solve", out / "model_coarse.h5", "-c", c, "-o", tmp_path / "r.h5")
    assert r.exit_code == 0, r.stderr
    with h5py.File(out / "model_coarse.h5") as f:
        n = f["nodes/X"].shape[0]
    assert f"solve: {n} nodes × 1 load steps: about " in r.stderr and "MB of results (rough estimate)" in r.stderr


# --------------------------------------------------------------------------- studies checked before any case
@pytest.mark.parametrize("vary, expected", [
    ({"solve.materials.muscle.sigma_mx": [20, 30]},
     "study.vary.solve.materials.muscle.sigma_mx: unknown key; did you mean 'sigma_max'?"),
    ({"solve.materials.muscle.sigma_max": [20, -5]},
     "study.vary.solve.materials.muscle.sigma_max: expected a value ≥ 0.0, got -5.0"),
    ({"solve.steps": [2, "many"]}, "study.vary.solve.steps: expected an integer, got 'many'"),
    ({"solve.steps.first": [1]}, "study.vary.solve.steps.first: 'steps' is an integer, not a mapping"),
])
def test_study_with_a_bad_vary_key_or_value(phantom, tmp_path, vary, expected):
    cfg = base_config(phantom, tmp_path / "out")
    cfg["study"] = {"vary": vary}
    c = write_config(tmp_path / "c.yaml", cfg)
    r = cli("run", c)
    assert r.exit_code == 2, r.stderr
    assert f"{c}: {expected}" in error_line(r.stderr)
    assert not (tmp_path / "out").exists()

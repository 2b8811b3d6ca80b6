"""Provenance of the stage files: the git commit of the source tree, the versions of the numerical
libraries used, and input paths relative to the config file, checked against git, the libraries
themselves and a real `pixmuscle solve` process."""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
import scipy

import pixmuscle
from pixmuscle.io.model import save_model
from pixmuscle.mechanics import pardiso
from pixmuscle.store import config_folder, read_meta, write_stage
from pixmuscle.verify.mechanics import mask_model

ROOT = Path(pixmuscle.__file__).resolve().parent.parent


def _git_head() -> str | None:
    if not (ROOT / ".git").exists():
        return None
    p = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"], capture_output=True, text=True)
    return p.stdout.strip() if p.returncode == 0 else None


def test_stage_file_records_commit_libraries_and_relative_inputs(tmp_path):
    (tmp_path / "data").mkdir()
    src = tmp_path / "data" / "mri.bin"
    src.write_bytes(b"voxels" * 10)
    cfg_dir = tmp_path / "configs"
    cfg_dir.mkdir()
    with config_folder(cfg_dir):
        write_stage(tmp_path / "out" / "s.h5", schema="pixmuscle.test", version=1, write=lambda f: None, inputs=[src])
    prov = read_meta(tmp_path / "out" / "s.h5")["provenance"]
    sha = hashlib.sha256(src.read_bytes()).hexdigest()
    assert prov["inputs"] == {str(src): sha}                                  # absolute, as before
    assert prov["inputs_relative"] == {os.path.join("..", "data", "mri.bin"): sha}
    assert prov["config_dir"] == str(cfg_dir.resolve())
    head = _git_head()
    if head is None:
        assert prov["git"] is None
    else:
        assert prov["git"]["commit"] == head and isinstance(prov["git"]["modified"], bool)
    libs = prov["libraries"]
    assert libs["numpy"] == np.__version__ and libs["scipy"] == scipy.__version__ and libs["h5py"] == h5py.__version__
    assert {"pyamg", "meshio"} <= set(libs)
    # outside a config folder: no relative paths (a stage command without --config)
    write_stage(tmp_path / "t.h5", schema="pixmuscle.test", version=1, write=lambda f: None, inputs=[src])
    assert "inputs_relative" not in read_meta(tmp_path / "t.h5")["provenance"]


def test_solve_command_records_the_solver_libraries_it_used(tmp_path):
    """A real `pixmuscle solve`: PARDISO's MKL version when the direct solver used it, no petsc4py
    (not used), the model path relative to the config's folder."""
    model_dir, cfg_dir = tmp_path / "models", tmp_path / "study" / "configs"
    model_dir.mkdir()
    cfg_dir.mkdir(parents=True)
    save_model(model_dir / "model.h5", mask_model(np.ones((3, 3, 4), bool), (0.2, 0.2, 0.3), tissue=1))
    cfg = cfg_dir / "c.yaml"
    cfg.write_text("solve:\n  steps: 1\n  activation: {from: 0.0, to: 0.3}\n  boundary_conditions:\n"
                   "    - {nodes: z_min, fix: [x, y, z]}\n    - {nodes: z_max, fix: [x, y, z]}\n")
    out = tmp_path / "results.h5"
    p = subprocess.run([sys.executable, "-m", "pixmuscle.cli", "solve", str(model_dir / "model.h5"), "-c", str(cfg),
                        "-o", str(out), "-q"], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    with h5py.File(out) as f:
        prov = json.loads(f.attrs["provenance"])
        backend = json.loads(f.attrs["solver_info"]).get("backend", "") if "solver_info" in f.attrs else ""
    assert list(prov["inputs_relative"]) == [os.path.join("..", "..", "models", "model.h5")]
    libs = prov["libraries"]
    assert "petsc4py" not in libs
    if pardiso.available():
        assert "Math Kernel Library" in libs["mkl_pardiso"] or libs["mkl_pardiso"].startswith("mkl "), (libs, backend)
    else:
        assert "mkl_pardiso" not in libs
    if _git_head() is not None:
        assert prov["git"]["commit"] == _git_head()


@pytest.mark.skipif(not pardiso.available(), reason="MKL PARDISO not installed")
def test_mkl_version_is_mkls_own():
    """The MKL version string comes from the loaded library (MKL_Get_Version_String)."""
    from pixmuscle.store import library_versions

    pardiso._load()
    v = library_versions()["mkl_pardiso"]
    assert "Math Kernel Library" in v and "Version" in v

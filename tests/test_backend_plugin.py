"""A linear-solver backend added in one file (tests/dense_backend.py) runs through the pipeline unchanged.

A block of fat and muscle, stretched along the fibres while the muscle is activated, is solved
once with the dense backend (LAPACK on the dense tangent) and once with the shipped ``direct``
backend: the reaction forces and displacements agree to round-off, and the results' ``info``
carries the new backend's own statistics.
"""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest
import yaml
from dense_backend import DenseOptions

from pixmuscle.config import parse_section
from pixmuscle.errors import InputError
from pixmuscle.imaging.nifti import save_volume
from pixmuscle.mechanics.config import SolveConfig
from pixmuscle.mechanics.linsolve import BACKENDS, make_solver
from pixmuscle.pipeline import load_subjects, run_subject

SHAPE, H = (3, 3, 5), (0.2, 0.2, 0.3)  # voxels, cm


def test_backend_registers_itself_with_its_own_options():
    assert "dense" in BACKENDS.names()
    cfg = parse_section(SolveConfig, {"solver": {"backend": "dense", "max_dofs": 600}}, "solve")
    assert cfg.solver == DenseOptions(max_dofs=600)
    with pytest.raises(InputError, match=r"^solve\.solver\.rtol: unknown key; valid keys: max_dofs$"):
        parse_section(SolveConfig, {"solver": {"backend": "dense", "rtol": 1e-8}}, "solve")
    with pytest.raises(InputError, match=r"^solve\.solver\.backend: unknown linear-solver backend 'dens'; expected one "
                                         r"of .*dense.*direct.*\(did you mean 'dense'\?\)$"):
        parse_section(SolveConfig, {"solver": {"backend": "dens"}}, "solve")
    assert make_solver("dense", np.zeros((4, 3))).name == "dense"


def _run(tmp_path, solver: dict) -> tuple[np.ndarray, np.ndarray, dict]:
    labels = np.full(SHAPE, 3, np.int16)  # 3: fat, 1: muscle in the default tissue map
    labels[1, 1, :] = 1
    save_volume(tmp_path / "labels.nii.gz", labels, np.diag([*H, 1.0]), kind="labels")
    top = 0.05 * SHAPE[2] * H[2]
    cfg = {
        "synthetic": True,
        "output_dir": str(tmp_path / "out"),
        "models": ["fine"],
        "build_model": {"labels": "labels.nii.gz", "muscle_fibers": {"muscle": [0.0, 0.0, 1.0]}},
        "solve": {
            "steps": 2,
            "activation": {"from": 0.0, "to": 0.5},
            "solver": solver,
            "boundary_conditions": [{"nodes": "z_min", "fix": ["x", "y", "z"]},
                                    {"nodes": "z_max", "fix": ["x", "y"], "displace": {"z": top}}],
        },
    }
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(cfg))
    run_subject(load_subjects(tmp_path / "config.yaml")[0], until="solve")
    with h5py.File(tmp_path / "out" / "results_fine.h5") as f:
        return f["steps/reaction/z_max"][()], f["steps/u"][()], json.loads(f.attrs["solver_info"])


def test_new_backend_through_the_pipeline_matches_direct(tmp_path):
    (tmp_path / "dense").mkdir()
    (tmp_path / "direct").mkdir()
    f_dense, u_dense, info = _run(tmp_path / "dense", {"backend": "dense"})
    f_direct, u_direct, ref = _run(tmp_path / "direct", {"backend": "direct", "reuse_factorization": False})
    assert abs(f_direct[-1, 2]) > 0.1
    np.testing.assert_allclose(f_dense, f_direct, rtol=1e-9, atol=1e-12 * np.abs(f_direct).max())
    np.testing.assert_allclose(u_dense, u_direct, rtol=0, atol=1e-10 * np.abs(u_direct).max())
    assert info["linear_solver"] == "dense" and info["dense_solves"] == sum(info["linear_iterations"]) > 0
    assert ref["linear_solver"] == "direct" and "dense_solves" not in ref

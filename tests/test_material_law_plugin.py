"""A material law added in one file (tests/neo_hooke_law.py) runs through the pipeline unchanged.

A block of fat under uniaxial strain (rollers on every face, the top face displaced): the
deformation is homogeneous, F = diag(1, 1, λ), so the end force is the closed form of the
compressible neo-Hookean law, R = A0 [μ (λ − 1/λ) + λ_L ln λ / λ], and the law's tangent is
checked against finite differences of its stress. The same law, written beside a config that
names it in ``plugins`` (with a report section in one more file), runs through the ``pixmuscle``
executable; its file is part of the solve's lineage.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml
from neo_hooke_law import NeoHooke

from pixmuscle.errors import InputError
from pixmuscle.imaging.nifti import save_volume
from pixmuscle.mechanics.materials import LAWS, material_from_config
from pixmuscle.pipeline import load_subjects, run_subject

MU, LAM = 4.0, 30.0
SHAPE, H = (3, 3, 5), (0.2, 0.2, 0.3)  # voxels, cm
STRETCH = 1.08


def test_law_registers_itself_with_its_own_constants():
    assert "neo_hooke" in LAWS.names()
    m = material_from_config("fat", {"law": "neo_hooke", "mu": MU})
    assert m == NeoHooke(mu=MU)  # the law's own defaults, not the fat's Yeoh constants
    F = np.eye(3)[None] + 0.05 * np.random.default_rng(0).standard_normal((4, 3, 3))
    P, A = m.stress_tangent(F)
    eps = 1e-6
    for k, L in [(0, 0), (1, 2), (2, 1)]:
        dF = np.zeros((3, 3))
        dF[k, L] = eps
        fd = (m.stress(F + dF) - m.stress(F - dF)) / (2 * eps)
        np.testing.assert_allclose(A[:, :, :, k, L], fd, rtol=0, atol=1e-7 * np.abs(A).max())


def _config(tmp_path, materials: dict, volumetric: str = "nodal") -> dict:
    labels = np.full(SHAPE, 3, np.int16)  # 3: fat in the default tissue map
    affine = np.diag([*H, 1.0])
    save_volume(tmp_path / "labels.nii.gz", labels, affine, kind="labels")
    top = (STRETCH - 1.0) * SHAPE[2] * H[2]
    return {
        "synthetic": True,
        "output_dir": str(tmp_path / "out"),
        "models": ["fine"],
        "build_model": {"labels": "labels.nii.gz"},
        "solve": {
            "steps": 2,
            "activation": {"from": 0.0, "to": 0.0},
            "volumetric": {"method": volumetric},
            "penalty": {"factor": 1.0e4},  # stiff supports: the closed form holds the faces exactly
            "materials": materials,
            "boundary_conditions": [
                {"nodes": "x_min", "fix": ["x"]}, {"nodes": "x_max", "fix": ["x"]},
                {"nodes": "y_min", "fix": ["y"]}, {"nodes": "y_max", "fix": ["y"]},
                {"nodes": "z_min", "fix": ["z"]}, {"nodes": "z_max", "displace": {"z": top}},
            ],
        },
    }


def _run(tmp_path, cfg) -> dict:
    path = tmp_path / "config.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return run_subject(load_subjects(path)[0], until="solve")


def _check_closed_form(results: Path) -> None:
    with h5py.File(results) as f:
        r_top = f["steps/reaction/z_max"][()][:, 2]
        r_bottom = f["steps/reaction/z_min"][()][:, 2]
        u = f["steps/u"][-1]
        X = f["nodes/X"][()]
    area = SHAPE[0] * H[0] * SHAPE[1] * H[1]
    lam_z = 1.0 + np.array([0.5, 1.0]) * (STRETCH - 1.0)
    closed = area * (MU * (lam_z - 1.0 / lam_z) + LAM * np.log(lam_z) / lam_z)
    np.testing.assert_allclose(r_top[1:], closed, rtol=2e-3)
    np.testing.assert_allclose(-r_bottom[1:], closed, rtol=2e-3)
    # the displacement is the homogeneous field u = (0, 0, (λ − 1)(Z − z0)), z0 the bottom face
    z0 = X[:, 2].min() - H[2] / 2  # the ends are held on their cell faces
    np.testing.assert_allclose(u[:, 2], (STRETCH - 1.0) * (X[:, 2] - z0), atol=2e-3 * (STRETCH - 1.0) * np.ptp(X[:, 2]))


def test_new_law_through_the_pipeline_matches_closed_form(tmp_path):
    cfg = _config(tmp_path, {"fat": {"law": "neo_hooke", "mu": MU, "lam": LAM}})
    summary = _run(tmp_path, cfg)
    assert "solve (fine)" in summary["ran"]
    _check_closed_form(tmp_path / "out" / "results_fine.h5")


def _pixmuscle(*args) -> subprocess.CompletedProcess:
    """The installed ``pixmuscle`` executable (this checkout first on the path)."""
    import pixmuscle

    exe = Path(sys.executable).with_name("pixmuscle")
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "pixmuscle.cli"]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(Path(pixmuscle.__file__).parents[1]),
                                                        os.environ.get("PYTHONPATH", "")])}
    return subprocess.run([*cmd, *map(str, args)], capture_output=True, text=True, env=env, timeout=300)


#: a report section in one file: the top face's force of the last step, on the page
SECTION = """
import dataclasses

from pixmuscle.report.sections import SECTIONS


@SECTIONS.register("top_force", inputs=("results",), order=50)
@dataclasses.dataclass(frozen=True)
class TopForce:
    def html(self, results):
        return ["<h2>Top face</h2>", f'<p id="top-force">{results.reaction["z_max"][-1, 2]:.9e}</p>']
"""


def test_plugin_law_and_section_through_the_cli(tmp_path):
    """A law file and a report-section file named in `plugins`, run by the `pixmuscle` executable: the
    solve matches the law's closed form and the page shows the section; an edited law file reruns the
    solve (its SHA-256 is in the results' provenance). The plugins are imported only in the
    subprocesses, so this process's registries stay as they were."""
    from pixmuscle.store import read_meta, sha256_file

    law = tmp_path / "laws" / "my_fat.py"
    law.parent.mkdir()
    law.write_text(Path(__file__).with_name("neo_hooke_law.py").read_text().replace('"neo_hooke"', '"my_fat"'))
    (tmp_path / "top_force.py").write_text(SECTION)
    cfg = {"plugins": ["laws/my_fat.py", "top_force.py"],
           **_config(tmp_path, {"fat": {"law": "my_fat", "mu": MU, "lam": LAM}}),
           "report": {"vtu": False, "slices": False, "view3d": False, "dpi": 40}}
    path = tmp_path / "config.yaml"
    path.write_text(yaml.safe_dump(cfg))
    done = _pixmuscle("-q", "run", path)
    assert done.returncode == 0, done.stderr
    results = tmp_path / "out" / "results_fine.h5"
    _check_closed_form(results)
    page = (tmp_path / "out" / "report" / "index.html").read_text()
    shown = float(page.split('<p id="top-force">')[1].split("<")[0])
    area = SHAPE[0] * H[0] * SHAPE[1] * H[1]
    assert shown == pytest.approx(area * (MU * (STRETCH - 1 / STRETCH) + LAM * np.log(STRETCH) / STRETCH), rel=2e-3)
    # lineage: the law file is an input of the solve; unchanged it is skipped, edited it reruns
    inputs = read_meta(results)["provenance"]["inputs"]
    assert inputs[str(law.resolve())] == sha256_file(law)
    made = results.stat().st_mtime_ns
    assert _pixmuscle("-q", "run", path, "--until", "solve").returncode == 0
    assert results.stat().st_mtime_ns == made
    law.write_text(law.read_text() + "\n# edited\n")
    assert _pixmuscle("-q", "run", path, "--until", "solve").returncode == 0
    assert results.stat().st_mtime_ns != made
    assert read_meta(results)["provenance"]["inputs"][str(law.resolve())] == sha256_file(law)


@pytest.mark.parametrize("plugins,text,message", [
    (["missing.py"], None, r"plugins\[0\]: .*missing.py: plugin file not found"),
    (["bad.py"], "raise RuntimeError('no such constant')",
     r"plugins\[0\]: cannot import .*bad.py: RuntimeError: no such constant"),
    (["no_such_module_xyz"], None, r"plugins\[0\]: cannot import module 'no_such_module_xyz': ModuleNotFoundError"),
    ("bad.py", None, r"plugins: expected a list of Python files or module names"),
])
def test_bad_plugin_is_one_line_naming_key_and_file(tmp_path, plugins, text, message):
    if text is not None:
        (tmp_path / "bad.py").write_text(text)
    path = tmp_path / "config.yaml"
    path.write_text(yaml.safe_dump({"plugins": plugins, **_config(tmp_path, {})}))
    with pytest.raises(InputError, match=message) as exc:
        load_subjects(path)
    assert "\n" not in str(exc.value) and str(path) in str(exc.value)


def test_law_without_volumetric_split_refuses_the_projection(tmp_path):
    cfg = _config(tmp_path, {"fat": {"law": "neo_hooke"}}, volumetric="projected")
    with pytest.raises(InputError, match=r"solve.materials.fat: law 'neo_hooke' .*volumetric.method: nodal"):
        _run(tmp_path, cfg)


@pytest.mark.parametrize("fat,message", [
    ({"law": "neo_hook"}, r"solve.materials.fat.law: unknown material law 'neo_hook'.*did you mean 'neo_hooke'"),
    ({"law": "neo_hooke", "C10": 3.0}, r"solve.materials.fat.C10: unknown key"),
    ({"law": "neo_hooke", "mu": -1.0}, r"solve.materials.fat.mu: expected a value > 0"),
])
def test_bad_law_config_names_the_key(tmp_path, fat, message):
    path = tmp_path / "config.yaml"
    path.write_text(yaml.safe_dump(_config(tmp_path, {"fat": fat})))
    with pytest.raises(InputError, match=message):
        load_subjects(path)

"""The material law's strong ellipticity at the nodes: the field a solve records at its last converged
step (``/ellipticity/acoustic_minimum``), its recomputation from a results file, the ParaView files
and the report section.

Independent checks: a homogeneous deformation, where the SCNI gradient is exact and the acoustic
tensor is computed here from finite differences of the law's stress, and the known loss of
ellipticity of the paper's muscle matrix in isochoric uniaxial tension between stretches 1.36 and
1.37 (tests/test_ellipticity.py, from the independent tensortrax law)."""

import dataclasses

import numpy as np
import pytest

from pixmuscle.config import parse_section
from pixmuscle.mechanics.config import SolveConfig
from pixmuscle.mechanics.ellipticity import directions
from pixmuscle.mechanics.node_ellipticity import results_ellipticity, state_acoustic_minimum
from pixmuscle.mechanics.solve import solve
from pixmuscle.mechanics.system import model_scni, solve_materials
from pixmuscle.verify.mechanics import mask_model

FIBER = np.array([np.sin(np.deg2rad(25.0)), 0.0, np.cos(np.deg2rad(25.0))])
CLAMPED = [{"nodes": "z_min", "fix": ["x", "y", "z"]}, {"nodes": "z_max", "fix": ["x", "y", "z"]}]


def _cfg(**kw):
    return parse_section(SolveConfig, {"activation": {"from": 0.0, "to": 0.95}, "boundary_conditions": CLAMPED, **kw},
                         "solve")


def _acoustic_by_differences(mat, F, alpha, m, eps=1e-6):
    """min over the directions m of the smaller eigenvalue of the acoustic tensor on the plane ⊥ F⁻ᵀm,
    with A from central differences of the law's first Piola–Kirchhoff stress (one point F)."""
    kw = {"fiber": FIBER[None], "activation": alpha}
    A = np.empty((3, 3, 3, 3))
    for k in range(3):  # ∂P/∂F_kL column by column
        for L in range(3):
            dF = np.zeros((3, 3))
            dF[k, L] = eps
            A[:, :, k, L] = (mat.stress((F + dF)[None], **kw)[0] - mat.stress((F - dF)[None], **kw)[0]) / (2 * eps)
    Finv_t = np.linalg.inv(F).T
    best = np.inf
    for mm in m:  # a few hundred directions
        Q = np.einsum("iJkL,J,L->ik", A, mm, mm)
        v = Finv_t @ mm
        v /= np.linalg.norm(v)
        basis = np.linalg.svd(v[None])[2][1:]          # two unit vectors ⊥ v
        best = min(best, float(np.linalg.eigvalsh(basis @ (0.5 * (Q + Q.T)) @ basis.T)[0]))
    return best


@pytest.mark.parametrize("stretch, elliptic", [(1.30, True), (1.45, False)])
def test_homogeneous_uniaxial_tension_gives_the_known_loss_of_ellipticity_at_every_node(stretch, elliptic):
    """A block of muscle (3 × 3 × 5 voxels of 0.4 cm, fibres at 25° to z) under the isochoric uniaxial
    stretch diag(s^-½, s^-½, s): d = (F − I) X is reproduced exactly by the linear RK basis, so the
    solve's SCNI F is F at every node, and the field is the same everywhere: positive at s = 1.30, negative
    at 1.45 (the matrix loses ellipticity between 1.36 and 1.37), and equal to the acoustic minimum of
    finite-difference moduli."""
    model = mask_model(np.ones((3, 3, 5), bool), (0.4, 0.4, 0.4), tissue=1, fiber=FIBER)
    cfg = _cfg()
    F0 = np.diag([stretch**-0.5, stretch**-0.5, stretch])
    d = np.asarray(model.X, float) @ (F0 - np.eye(3)).T
    F = model_scni(model, cfg)[0].deformation_gradient(d)
    assert np.allclose(F, F0, atol=1e-10)
    q = state_acoustic_minimum(model, cfg, d, 0.95, n_directions=300)
    assert q.shape == (model.n_nodes,)
    assert np.ptp(q) <= 1e-8 * abs(q[0])
    assert (q > 0).all() if elliptic else (q < 0).all()
    ref = _acoustic_by_differences(solve_materials(cfg)[1], F0, 0.95, directions(300))
    assert q[0] == pytest.approx(ref, rel=1e-5, abs=1e-6)


@pytest.fixture(scope="module")
def solved(tmp_path_factory):
    """The clamped active block of tests/test_active_block.py (h = 0.5 cm, 144 nodes, α 0 → 0.95 in 10
    steps), not strongly elliptic near the clamps at the end; saved and read back."""
    from pixmuscle.io.results import load_results, save_results

    model = mask_model(np.ones((4, 3, 12), bool), (0.5, 0.5, 0.5), tissue=1, fiber=FIBER)
    cfg = _cfg(steps=10)
    res = solve(model, cfg)
    path = save_results(tmp_path_factory.mktemp("ell") / "results.h5", res, config=cfg)
    return res, load_results(path), path


def test_the_solve_records_the_field_at_its_last_converged_step(solved):
    res, back, _ = solved
    ell = res.ellipticity
    assert ell is not None and ell.step == res.n_states - 1 and ell.minimum.shape == (res.model.n_nodes,)
    assert 0 < ell.count < res.model.n_nodes
    assert ell.count == res.info["non_elliptic_nodes"]
    assert back.ellipticity.step == ell.step and back.ellipticity.n_directions == 300
    assert np.array_equal(back.ellipticity.minimum, ell.minimum)
    assert back.step(ell.step).acoustic_minimum is not None and back.step(ell.step - 1).acoustic_minimum is None
    # recomputed from the file's RK coefficients and configuration alone: the same field
    again = results_ellipticity(back)
    assert again.step == ell.step
    assert np.allclose(again.minimum, ell.minimum, rtol=1e-9, atol=1e-9 * np.abs(ell.minimum).max())


def test_a_results_file_without_the_field_still_reads_and_reports(solved, tmp_path):
    from pixmuscle.io.results import load_results, save_results
    from pixmuscle.report.sections.ellipticity import Ellipticity

    res, _, _ = solved
    old = load_results(save_results(tmp_path / "old.h5", dataclasses.replace(res, ellipticity=None)))
    assert old.ellipticity is None and old.step(old.n_states - 1).acoustic_minimum is None
    assert Ellipticity().html(results=old, summary={"outputs": {}, "warnings": []}, outdir=tmp_path, dpi=50) == []


def _vtu_cell_data(path):
    """Cell arrays of a VTU, read by VTK's own reader (ParaView's; meshio cannot read the files' string field data)."""
    from vtkmodules.util.numpy_support import vtk_to_numpy
    from vtkmodules.vtkIOXML import vtkXMLUnstructuredGridReader

    r = vtkXMLUnstructuredGridReader()
    r.SetFileName(str(path))
    r.Update()
    cd = r.GetOutput().GetCellData()
    return {cd.GetArrayName(i): vtk_to_numpy(cd.GetArray(i)) for i in range(cd.GetNumberOfArrays())}


def test_the_paraview_files_carry_the_field_at_the_last_step(solved, tmp_path):
    import meshio

    from pixmuscle.report.fields import ACOUSTIC_MINIMUM, NON_ELLIPTIC, write_vtu_series

    _, res, _ = solved
    m = res.model
    last = res.ellipticity.step
    flag = (res.ellipticity.minimum < 0).astype(int)
    out = write_vtu_series(tmp_path, [last - 1, last], [0.9, 0.95], res.step, ijk=m.ijk, origin=m.origin,
                           spacing=m.spacing, fiber=m.fiber, tissue=m.tissue, muscle_id=m.muscle_id, xdmf=True)
    cd = _vtu_cell_data(out["vtu"][1])
    assert np.allclose(cd[ACOUSTIC_MINIMUM], res.ellipticity.minimum)
    assert np.array_equal(cd[NON_ELLIPTIC], flag)
    assert NON_ELLIPTIC not in _vtu_cell_data(out["vtu"][0])
    with meshio.xdmf.TimeSeriesReader(out["xdmf"]) as reader:  # the XDMF series, read by meshio
        reader.read_points_cells()
        _, _, cell_data = reader.read_data(1)
    assert np.array_equal(np.asarray(cell_data[NON_ELLIPTIC][0]).ravel(), flag)
    assert np.allclose(np.asarray(cell_data[ACOUSTIC_MINIMUM][0]).ravel(), res.ellipticity.minimum)


def test_the_report_section_counts_the_nodes_and_draws_them(solved, tmp_path):
    from pixmuscle.report.sections.ellipticity import Ellipticity

    _, res, _ = solved
    summary = {"outputs": {}, "warnings": []}
    parts = Ellipticity().html(results=res, summary=summary, outdir=tmp_path, dpi=50)
    text = "".join(parts)
    assert "Strong ellipticity of the material law" in text
    assert f"{res.ellipticity.count:,} of {res.model.n_nodes:,}" in text
    assert summary["ellipticity"]["non_elliptic_nodes"] == res.ellipticity.count
    assert sum(summary["ellipticity"]["by_region"].values()) == res.ellipticity.count
    assert (tmp_path / "ellipticity.png").is_file() and "data:image/png;base64" in text

"""ParaView files read back with VTK's own reader, and the stage records the report shows
(warnings, configuration and provenance of every stage, synthetic flag, constraint gap)."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest
from fixtures_results import write_results_fixture

from pixmuscle.io.lineage import capture_warnings, stage_attrs, stage_record
from pixmuscle.report import ReportConfig
from pixmuscle.stages.report import make_report
from pixmuscle.store import write_stage

vtk_xml = pytest.importorskip("vtkmodules.vtkIOXML")


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    d = tmp_path_factory.mktemp("files")
    truth = write_results_fixture(d / "results.h5", n_steps=2)
    summary = make_report(truth.path, d / "out", ReportConfig(dpi=40, slices=False, view3d=False))
    return truth, summary, d / "out"


def _read(path):
    r = vtk_xml.vtkXMLUnstructuredGridReader()
    r.SetFileName(str(path))
    r.Update()
    return r.GetOutput()


def test_slice_at_an_off_node_plane_returns_the_cells_of_that_layer(report):
    """ParaView's Slice (vtkCutter) at a plane between node layers cuts exactly the cells of one layer."""
    from vtkmodules.util.numpy_support import vtk_to_numpy
    from vtkmodules.vtkCommonDataModel import vtkPlane
    from vtkmodules.vtkFiltersCore import vtkCutter

    truth, summary, out = report
    grid = _read(out / "fields" / "step_0002.vtu")
    with h5py.File(truth.path, "r") as f:
        X, h = f["nodes/X"][()], f["grid/spacing"][()]
        u = f["steps/u"][2]
    zs = np.unique(X[:, 2])
    z_plane = zs[2] + 0.3 * h[2]  # inside the cells of layer 2, off every node
    plane = vtkPlane()
    plane.SetOrigin(0.0, 0.0, z_plane)
    plane.SetNormal(0.0, 0.0, 1.0)
    cut = vtkCutter()
    cut.SetCutFunction(plane)
    cut.SetInputData(grid)
    cut.GenerateTrianglesOff()  # one polygon per cut cell
    cut.Update()
    poly = cut.GetOutput()
    layer = np.isclose(X[:, 2], zs[2])
    assert poly.GetNumberOfCells() == layer.sum() > 0
    got = vtk_to_numpy(poly.GetCellData().GetArray("displacement [cm]"))
    np.testing.assert_allclose(np.sort(got, axis=0), np.sort(u[layer], axis=0))


def test_threshold_on_tissue_gives_the_muscle_cells(report):
    from vtkmodules.vtkCommonDataModel import vtkDataObject
    from vtkmodules.vtkFiltersCore import vtkThreshold

    truth, _, out = report
    grid = _read(out / "fields" / "step_0001.vtu")
    th = vtkThreshold()
    th.SetInputData(grid)
    th.SetInputArrayToProcess(0, 0, 0, vtkDataObject.FIELD_ASSOCIATION_CELLS, "tissue")
    th.SetLowerThreshold(0.5)
    th.SetUpperThreshold(1.5)
    th.Update()
    assert th.GetOutput().GetNumberOfCells() == sum(truth.n_muscle.values())


def test_units_and_names_in_field_data(report):
    _, _, out = report
    grid = _read(out / "fields" / "step_0000.vtu")
    fd = grid.GetFieldData()

    def strings(name):
        a = fd.GetAbstractArray(name)
        return [a.GetValue(i) for i in range(a.GetNumberOfValues())]

    assert strings("muscle_names") == ["(not muscle)", "medial", "lateral"]
    assert strings("tissue_names") == ["background", "muscle", "connective_tissue", "fat"]
    units = strings("units")
    assert "displacement [cm]: cm" in units and any(u.startswith("cauchy [N/cm^2]: N/cm^2") for u in units)
    cauchy = grid.GetCellData().GetArray("cauchy [N/cm^2]")
    assert [cauchy.GetComponentName(i) for i in range(6)] == ["XX", "YY", "ZZ", "XY", "YZ", "XZ"]


def test_every_stage_is_recorded_and_shown(tmp_path):
    """Warnings, config and provenance of the upstream stages reach the report through results.h5
    alone; the synthetic flag of an upstream file gives the banner without any run information."""
    import logging

    image = tmp_path / "leg_mri.nii.gz"
    image.write_bytes(b"not really an image")
    (tmp_path / "leg_truth.json").write_text(json.dumps({"synthetic": True}))
    with capture_warnings() as seg_w:
        logging.getLogger("pixmuscle.segmentation").warning("seed of muscle 'soleus' moved by 0.4 cm")
    seg = write_stage(tmp_path / "segmentation.h5", schema="pixmuscle.segmentation", version=1, write=lambda f: None,
                      config={"seeds": {"soleus": [1, 2, 3]}}, inputs=[image],
                      attrs=stage_attrs("segment", [image], seg_w))
    assert stage_record(seg)[-1]["synthetic"] is True
    model = write_stage(tmp_path / "model.h5", schema="pixmuscle.model", version=1, write=lambda f: None,
                        config={"fiber_fallback": "muscle_mean"}, inputs=[seg],
                        attrs=stage_attrs("build-model", [seg], ["muscle 'soleus': 12 of 300 nodes use the mean fibre"]))
    gap = {"z_min": {"max_cm": 1e-4, "relative": 1e-3}, "z_max": {"max_cm": 0.03, "relative": 0.025}}
    attrs = stage_attrs("solve", [model], ["RK supports enlarged at 387 of 1000 nodes (up to 1.3x nominal)"])
    truth = write_results_fixture(tmp_path / "results.h5", n_steps=2,
                                  attrs={**attrs, "constraint_gap": json.dumps(gap)})
    summary = make_report(truth.path, tmp_path / "out", ReportConfig(dpi=40, vtu=False, slices=False, view3d=False))
    w = summary["warnings"]
    assert "segment: seed of muscle 'soleus' moved by 0.4 cm" in w
    assert "build-model: muscle 'soleus': 12 of 300 nodes use the mean fibre" in w
    assert any(x.startswith("solve: RK supports enlarged at 387") for x in w)
    assert any("z_max" in x and "constraint gap" in x for x in w) and not any("'z_min'" in x for x in w)
    assert summary["synthetic"] is True
    assert [r["stage"] for r in summary["stages"]] == ["segment", "build-model", "solve"]
    text = (tmp_path / "out" / "index.html").read_text()
    assert "Synthetic inputs" in text and "moved by 0.4 cm" in text and "fiber_fallback: muscle_mean" in text
    assert str(image) in text  # provenance of the segment stage's input
    assert "Constraint gap" in text and "2.5" in text


def test_solver_info_table_and_round_off(tmp_path):
    info = {"supports_enlarged": 0, "total_s": 1.25, "linear_iterations": list(range(20)), "linear_solver": "direct"}
    truth = write_results_fixture(tmp_path / "results.h5", n_steps=2, attrs={"solver_info": json.dumps(info)})
    with h5py.File(truth.path, "a") as f:  # an exactly converged final residual
        f["newton/residual_norm"][-1] = 0.0
        f["newton/energy_norm"][...] = 0.0
    summary = make_report(truth.path, tmp_path / "out", ReportConfig(dpi=40, vtu=False, slices=False, view3d=False))
    text = (tmp_path / "out" / "index.html").read_text()
    assert "below round-off" in text
    assert "final energy norm" not in text  # a column that is always 0 is left out
    assert "20 values, total 190" in text and "<td>total s</td>" in text
    assert summary["solver_info"]["linear_solver"] == "direct"


# ------------------------------------------------------------------------------------------ stress tensors
def _tensors(voigt):
    """(N, 6) xx yy zz xy yz xz (results.h5) → (N, 3, 3)."""
    xx, yy, zz, xy, yz, xz = np.moveaxis(voigt, -1, 0)
    return np.stack([np.stack([xx, xy, xz], -1), np.stack([xy, yy, yz], -1), np.stack([xz, yz, zz], -1)], -2)


def test_stress_tensor_reads_back_through_vtk_xdmf_and_vtu_readers(report):
    """fields.xdmf read by VTK's XDMF reader and the VTUs read by VTK's XML reader give every stress component
    of results.h5, and the principal stresses VTK computes (ParaView's Tensor Principal Invariants on the VTU,
    eigenvalues of the XDMF tensor) are the solver's."""
    from vtkmodules.util.numpy_support import vtk_to_numpy
    from vtkmodules.vtkFiltersTensor import vtkTensorPrincipalInvariants
    from vtkmodules.vtkIOXdmf2 import vtkXdmfReader

    truth, summary, out = report
    name = "cauchy [N/cm^2]"
    with h5py.File(truth.path, "r") as f:
        cauchy, top, alpha = f["steps/cauchy"][()], f["steps/max_principal"][()], f["steps/alpha"][()]
    xdmf = vtkXdmfReader()
    xdmf.SetFileName(str(out / "fields.xdmf"))
    steps = summary["outputs"]["vtu_steps"]
    assert len(steps) == 3
    for s in steps:
        full = _tensors(cauchy[s])
        if s > 0:  # the components differ, so any mix-up of the order shows
            assert np.abs(full[:, 0, 1]).max() > 0 and np.abs(full[:, 1, 1] - full[:, 0, 1]).max() > 0.1
        xdmf.UpdateTimeStep(float(alpha[s]))
        got = vtk_to_numpy(xdmf.GetOutputDataObject(0).GetCellData().GetArray(name))
        np.testing.assert_array_equal(got.reshape(-1, 3, 3), full)  # VTK expands Tensor6 to the full tensor
        np.testing.assert_allclose(np.linalg.eigvalsh(got.reshape(-1, 3, 3))[:, -1], top[s], rtol=1e-12, atol=1e-12)

        vtu = vtk_xml.vtkXMLUnstructuredGridReader()
        vtu.SetFileName(str(out / "fields" / f"step_{s:04d}.vtu"))
        inv = vtkTensorPrincipalInvariants()
        inv.SetInputConnection(vtu.GetOutputPort())
        inv.GetCellDataArraySelection().EnableArray(name)
        inv.Update()
        cd = inv.GetOutput().GetCellData()
        np.testing.assert_array_equal(vtk_to_numpy(cd.GetArray(name)), cauchy[s])  # VTK's order XX YY ZZ XY YZ XZ
        eig = np.linalg.eigvalsh(full)
        for k, col in ((1, 2), (2, 1), (3, 0)):  # VTK's Sigma 1 ≥ Sigma 2 ≥ Sigma 3
            np.testing.assert_allclose(vtk_to_numpy(cd.GetArray(f"{name} - Sigma {k}")), eig[:, col], rtol=1e-10,
                                       atol=1e-9)
        np.testing.assert_allclose(vtk_to_numpy(cd.GetArray(f"{name} - Sigma 1")), top[s], rtol=1e-10, atol=1e-9)
        np.testing.assert_allclose(vtk_to_numpy(cd.GetArray("max_principal_cauchy [N/cm^2]")), top[s])
        # the point displacement of the two series is the same field
        u_x = vtk_to_numpy(xdmf.GetOutputDataObject(0).GetPointData().GetArray("displacement [cm]"))
        np.testing.assert_array_equal(u_x, vtk_to_numpy(vtu.GetOutput().GetPointData().GetArray("displacement [cm]")))


def test_xdmf_tensor6_order_unit():
    """The XDMF writer stores a VTK-ordered symmetric tensor in the Tensor6 order VTK's XDMF reader expands."""
    from pixmuscle.io.xdmf import TO_XDMF_TENSOR6

    v = np.array([[1.0, 2.0, 3.0, 4.0, 5.0, 6.0]])  # XX YY ZZ XY YZ XZ
    np.testing.assert_array_equal(v[:, TO_XDMF_TENSOR6], [[1.0, 4.0, 6.0, 2.0, 5.0, 3.0]])  # XX XY XZ YY YZ ZZ


# ------------------------------------------------------------------------------------------ point data
@pytest.fixture(scope="module")
def clamped(tmp_path_factory):
    """A small muscle block, both ends clamped (by default at their end-face vertices), activated: results.h5
    of a real solve and its report."""
    from pixmuscle.io.results import save_results
    from pixmuscle.mechanics.solve import solve
    from pixmuscle.model.tissues import MUSCLE
    from pixmuscle.verify.mechanics import _cfg, mask_model

    d = tmp_path_factory.mktemp("clamped")
    model = mask_model(np.ones((4, 4, 8), bool), (0.25, 0.25, 0.5), tissue=MUSCLE, fiber=(0.3, 0.0, 1.0))
    cfg = _cfg(steps=2, activation={"from": 0.0, "to": 0.6},
               boundary_conditions=[{"nodes": "z_min", "fix": ["x", "y", "z"]}, {"nodes": "z_max", "fix": ["x", "y", "z"]}])
    path = save_results(d / "results.h5", solve(model, cfg), config=cfg)
    summary = make_report(path, d / "out", ReportConfig(dpi=30, slices=False, view3d=False, html=False))
    return path, summary, d / "out", cfg


def test_point_data_is_the_rk_field_and_holds_the_clamped_ends(clamped):
    """The VTU's point displacement is the model's own field Σ_J Ψ_J(x) d_J at the cell corners: every point
    of the clamped z faces, their outer edges and corners included, moves ≤ 1 % of the largest point
    displacement with the default penalty at the end-face vertices (0.83 % here; a mean of nodal values: 33 %;
    ``penalty.at: centres`` leaves the outer edge at 7.8 %), and at sample corners it equals Ψ computed here
    from the RK shape functions with the solve's support."""
    from vtkmodules.util.numpy_support import vtk_to_numpy

    from pixmuscle.rk import shape_functions

    path, summary, out, cfg = clamped
    s = summary["outputs"]["vtu_steps"][-1]
    grid = _read(out / "fields" / f"step_{s:04d}.vtu")
    pts = vtk_to_numpy(grid.GetPoints().GetData())
    u = vtk_to_numpy(grid.GetPointData().GetArray("displacement [cm]"))
    with h5py.File(path, "r") as f:
        X, h, d = f["nodes/X"][()], f["grid/spacing"][()], f["steps/d"][s]
    umax = np.linalg.norm(u, axis=1).max()
    assert umax > 1e-3
    ends = np.isclose(pts[:, 2], X[:, 2].min() - h[2] / 2) | np.isclose(pts[:, 2], X[:, 2].max() + h[2] / 2)
    lo, hi = X.min(axis=0) - h / 2, X.max(axis=0) + h / 2
    edge = np.isclose(pts[:, :2], lo[:2]).any(axis=1) | np.isclose(pts[:, :2], hi[:2]).any(axis=1)
    assert ends.sum() == 2 * 5 * 5 and (ends & ~edge).sum() == 2 * 3 * 3
    assert np.linalg.norm(u[ends], axis=1).max() <= 0.01 * umax
    sample = np.random.default_rng(3).choice(pts.shape[0], 12, replace=False)
    a = np.asarray(cfg.support.a_over_h) * h  # the solve's support (a box: no enlarged supports)
    psi = shape_functions(X, pts[sample], a, kernel=cfg.support.kernel, order=cfg.support.order,
                          support_shape=cfg.support.shape)
    np.testing.assert_allclose(u[sample], psi @ d, rtol=1e-10, atol=1e-12 * umax)
    fd = grid.GetFieldData().GetAbstractArray("notes")
    notes = [fd.GetValue(i) for i in range(fd.GetNumberOfValues())]
    assert any("Psi_J(x) d_J" in n for n in notes) and any("cell data only" in n for n in notes)
    assert grid.GetPointData().GetArray("cauchy [N/cm^2]") is None  # stresses: cell data only

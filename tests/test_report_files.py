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


def test_view3d_is_drawn(tmp_path):
    truth = write_results_fixture(tmp_path / "results.h5", n_steps=1)
    summary = make_report(truth.path, tmp_path / "out", ReportConfig(dpi=30, vtu=False, slices=False))
    assert (tmp_path / "out" / "view3d.png").read_bytes()[:4] == b"\x89PNG"
    assert summary["view3d"].startswith(("VTK", "matplotlib"))
    assert "Model in 3-D" in (tmp_path / "out" / "index.html").read_text()

"""Tests of the report stage against independent reads of results.h5 and known fixture answers."""

from __future__ import annotations

import csv
import html
import json
import re
import xml.etree.ElementTree as ET
from types import SimpleNamespace

import h5py
import meshio
import numpy as np
import pytest
from fixtures_results import write_results_fixture

from pixmuscle.config import parse_section
from pixmuscle.errors import InputError
from pixmuscle.io.results import load_results
from pixmuscle.report import ReportConfig, plot_force_activation, tissue_table
from pixmuscle.report.cohort import cohort_summary
from pixmuscle.report.fields import rotate_voigt
from pixmuscle.report.slices import plane_image
from pixmuscle.stages.report import make_report, run_report, summarize_results


def _csv(path):
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    return rows[0], rows[1:]


def _col(header, rows, name):
    j = header.index(name)
    return np.array([float(r[j]) if r[j] != "" else np.nan for r in rows])


@pytest.fixture(scope="module")
def done(tmp_path_factory):
    d = tmp_path_factory.mktemp("report")
    truth = write_results_fixture(d / "results.h5", n_steps=4, attrs={"info": '{"linear_solver": "direct-lu"}'})
    summary = make_report(truth.path, d / "out", ReportConfig(dpi=50), extra={"title": "Phantom leg", "synthetic": True})
    return truth, summary, d / "out"


@pytest.fixture(scope="module")
def failed(tmp_path_factory):
    d = tmp_path_factory.mktemp("failed")
    truth = write_results_fixture(d / "results.h5", n_steps=3, failed=True, newton_layout="compound")
    index = run_report(truth.path, d / "out", ReportConfig(dpi=40, arrows=False))
    return truth, index, d / "out"


# ------------------------------------------------------------------------------------------ curves
def test_force_csv_equals_h5(done):
    truth, summary, out = done
    header, rows = _csv(out / "force_activation.csv")
    with h5py.File(truth.path, "r") as f:
        alpha = f["steps/alpha"][()]
        lf = f["steps/load_factor"][()]
        conv = f["steps/converged"][()]
        R = {k: v[()] for k, v in f["steps/reaction"].items()}
    np.testing.assert_array_equal(_col(header, rows, "step"), np.arange(alpha.size))
    np.testing.assert_array_equal(_col(header, rows, "alpha"), alpha)
    np.testing.assert_array_equal(_col(header, rows, "load_factor"), lf)
    for s, r in R.items():
        for c, name in enumerate("xyz"):
            np.testing.assert_array_equal(_col(header, rows, f"{s}.R{name} [N]"), r[:, c])
    # axial force = R . n_out: +z at z_max, -z at z_min (docs/architecture.md)
    np.testing.assert_array_equal(_col(header, rows, "z_max.F [N]"), R["z_max"][:, 2])
    np.testing.assert_array_equal(_col(header, rows, "z_min.F [N]"), -R["z_min"][:, 2])
    assert "bone_surface.F [N]" not in header  # not an end set
    np.testing.assert_allclose(_col(header, rows, "end_force [N]"), 0.5 * (R["z_max"][:, 2] - R["z_min"][:, 2]), rtol=1e-15)
    np.testing.assert_array_equal(_col(header, rows, "converged").astype(bool), conv)
    assert header[-1] == "converged"
    assert summary["force_sets"] == ["z_min", "z_max"]
    assert summary["F_max_N"] == pytest.approx(truth.f_max, rel=1e-12)


def test_force_plot_overlays_curves(tmp_path):
    import matplotlib.image as mpimg

    a = np.linspace(0, 0.95, 5)
    p = plot_force_activation({"coarse": (a, 60 * a), "fine": (a, 62 * a, np.array([1, 1, 1, 1, 0], bool))},
                              tmp_path / "f.png", dpi=40)
    img = mpimg.imread(p)
    assert img.ndim == 3 and img.shape[0] > 50
    with pytest.raises(InputError, match="alpha has shape"):
        plot_force_activation({"bad": (a, a[:3])}, tmp_path / "g.png")


# ------------------------------------------------------------------------------------------ fields
def read_vtu(path):
    """Points, hexahedra, cell data, point data and field data of a VTU, read by VTK's own reader."""
    from vtkmodules.util.numpy_support import vtk_to_numpy
    from vtkmodules.vtkIOXML import vtkXMLUnstructuredGridReader

    r = vtkXMLUnstructuredGridReader()
    r.SetFileName(str(path))
    r.Update()
    g = r.GetOutput()
    conn = vtk_to_numpy(g.GetCells().GetConnectivityArray()).reshape(-1, 8)

    def arrays(data):
        return {data.GetArrayName(i): vtk_to_numpy(data.GetArray(i)) for i in range(data.GetNumberOfArrays())}

    fd = g.GetFieldData()
    field = {}
    for i in range(fd.GetNumberOfArrays()):
        a = fd.GetAbstractArray(i)
        field[a.GetName()] = [a.GetValue(j) for j in range(a.GetNumberOfValues())]
    return SimpleNamespace(grid=g, points=vtk_to_numpy(g.GetPoints().GetData()), hexa=conn,
                           cell_data=arrays(g.GetCellData()), point_data=arrays(g.GetPointData()), field=field)


def test_vtu_series_matches_h5(done):
    """The VTU holds one hexahedron per node (its integration cell) with the node's values as cell data
    (read back with VTK's own reader)."""
    pytest.importorskip("vtkmodules")
    from pixmuscle.report.fields import CAUCHY, DISPLACEMENT, FIBER, MAX_PRINCIPAL

    truth, summary, out = done
    pvd = ET.parse(out / "fields.pvd").getroot()
    sets = pvd.findall("./Collection/DataSet")
    with h5py.File(truth.path, "r") as f:
        alpha = f["steps/alpha"][()]
        X = f["nodes/X"][()]
        h = f["grid/spacing"][()]
        assert [d.get("file") for d in sets] == [f"fields/step_{s:04d}.vtu" for s in range(alpha.size)]
        np.testing.assert_array_equal([float(d.get("timestep")) for d in sets], alpha)
        for s in (0, alpha.size - 1):
            m = read_vtu(out / f"fields/step_{s:04d}.vtu")
            n = X.shape[0]
            assert m.grid.GetNumberOfCells() == n and m.grid.GetCellType(0) == 12  # VTK_HEXAHEDRON
            corners = m.points[m.hexa]                      # (N, 8, 3)
            np.testing.assert_allclose(corners.mean(axis=1), X, atol=1e-12)   # cell centre = node
            np.testing.assert_allclose(np.ptp(corners, axis=1), np.broadcast_to(h, (n, 3)), atol=1e-12)
            cd = m.cell_data
            np.testing.assert_array_equal(cd[DISPLACEMENT], f["steps/u"][s])
            np.testing.assert_array_equal(cd[CAUCHY], f["steps/cauchy"][s])
            np.testing.assert_array_equal(cd[MAX_PRINCIPAL], f["steps/max_principal"][s])
            np.testing.assert_array_equal(cd[FIBER], f["nodes/fiber"][()])
            np.testing.assert_array_equal(cd["tissue"], f["nodes/tissue"][()])
            np.testing.assert_array_equal(cd["muscle_id"], f["nodes/muscle_id"][()])
            np.testing.assert_array_equal(cd["imat"].astype(bool), truth.imat_nodes)
            assert m.point_data[DISPLACEMENT].shape == (m.points.shape[0], 3)
        with meshio.xdmf.TimeSeriesReader(out / "fields.xdmf") as xr:  # the XDMF + HDF5 copy of the series
            points, cells = xr.read_points_cells()
            assert xr.num_steps == alpha.size and cells[0].type == "hexahedron"
            t, pd, cd = xr.read_data(alpha.size - 1)
            assert t == pytest.approx(alpha[-1])
            np.testing.assert_array_equal(cd[DISPLACEMENT][0], f["steps/u"][alpha.size - 1])


def test_rotate_voigt_against_scipy_rotation():
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(0)
    R = Rotation.from_euler("zyx", [30, -20, 10], degrees=True).as_matrix()
    A = rng.normal(size=(7, 3, 3))
    T = A + A.transpose(0, 2, 1)
    v = np.stack([T[:, 0, 0], T[:, 1, 1], T[:, 2, 2], T[:, 0, 1], T[:, 1, 2], T[:, 0, 2]], -1)
    w = rotate_voigt(v, R)
    full = R @ T @ R.T
    np.testing.assert_allclose(w, np.stack([full[:, 0, 0], full[:, 1, 1], full[:, 2, 2], full[:, 0, 1], full[:, 1, 2], full[:, 0, 2]], -1), atol=1e-12)
    np.testing.assert_allclose(np.linalg.eigvalsh(full), np.linalg.eigvalsh(T), atol=1e-12)  # invariants


def test_rotated_frame_mesh():
    from scipy.spatial.transform import Rotation

    from pixmuscle.mechanics.results import StepFields
    from pixmuscle.report.fields import DISPLACEMENT, FIBER, MAX_PRINCIPAL, step_mesh, voxel_hexahedra

    rng = np.random.default_rng(1)
    R = Rotation.from_rotvec([0.1, -0.2, 0.3]).as_matrix()
    ijk = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 0, 1], [2, 1, 1]])
    origin, spacing = np.array([1.0, 2.0, 3.0]), np.array([0.2, 0.3, 0.5])
    u, fib = rng.normal(size=(5, 3)), rng.normal(size=(5, 3))
    c = rng.normal(size=(5, 6))
    fl = StepFields(u=u, cauchy=c, max_principal=rng.normal(size=5))
    m = step_mesh(ijk, origin, spacing, fl, fiber=fib, tissue=np.ones(5), muscle_id=np.ones(5), rotation=R)
    pts, _ = voxel_hexahedra(ijk, origin, spacing)
    np.testing.assert_allclose(m.points, (R @ pts.T).T, atol=1e-14)
    np.testing.assert_allclose(m.cell_data[DISPLACEMENT][0], (R @ u.T).T, atol=1e-14)
    np.testing.assert_allclose(m.cell_data[FIBER][0], (R @ fib.T).T, atol=1e-14)
    np.testing.assert_array_equal(m.cell_data[MAX_PRINCIPAL][0], fl.max_principal)  # invariant


def test_max_principal_recomputed_when_missing(tmp_path):
    truth = write_results_fixture(tmp_path / "r.h5", n_steps=2, with_max_principal=False)
    fl = load_results(truth.path).step(2)
    with h5py.File(truth.path, "r") as f:
        c = f["steps/cauchy"][2]
    T = np.empty((c.shape[0], 3, 3))
    for (a, b), k in zip([(0, 0), (1, 1), (2, 2), (0, 1), (1, 2), (0, 2)], range(6), strict=True):
        T[:, a, b] = T[:, b, a] = c[:, k]
    np.testing.assert_allclose(fl.max_principal, np.linalg.eigvalsh(T)[:, -1], rtol=1e-12, atol=1e-12)


def test_plane_image_places_nodes_on_their_voxels(done):
    truth, _, _ = done
    with h5py.File(truth.path, "r") as f:
        ijk = f["nodes/ijk"][()].astype(np.int64)
    vals = np.arange(ijk.shape[0], dtype=float)
    k = 2
    img, lo = plane_image(ijk, vals, axis=2, index=k, haxis=0, vaxis=1)
    on = np.flatnonzero(ijk[:, 2] == k)
    assert img.shape == (ijk[:, 1].max() - ijk[:, 1].min() + 1, ijk[:, 0].max() - ijk[:, 0].min() + 1)
    for n in on[:: max(1, on.size // 25)]:  # a sample of nodes, checked one by one
        assert img[ijk[n, 1] - lo[1], ijk[n, 0] - lo[0]] == vals[n]
    assert np.isfinite(img).sum() == on.size  # NaN everywhere else


def test_slice_figures_exist(done):
    _, summary, out = done
    for name in ("slices_displacement.png", "slices_stress.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert summary["slices"]["step"] == 4
    # the planes pass through the centre of the node cloud
    assert summary["slices"]["plane_index_xyz"] == [10, 10, 3]


# ------------------------------------------------------------------------------------------ tissues
def test_tissue_table_volumes(done):
    truth, summary, out = done
    header, rows = _csv(out / "tissue_table.csv")
    by = {r[0]: dict(zip(header, r, strict=True)) for r in rows}
    with h5py.File(truth.path, "r") as f:
        cell = float(np.prod(f["grid/spacing"][()]))
        n = f["nodes/tissue"].shape[0]
    assert cell == pytest.approx(0.25 * 0.25 * 1.0)
    for mid, name in ((1, "medial"), (2, "lateral")):
        r = by[name]
        assert float(r["muscle [cm^3]"]) == pytest.approx(truth.n_muscle[mid] * cell, rel=1e-12)
        assert float(r["IMAT [cm^3]"]) == pytest.approx(truth.n_imat[mid] * cell, rel=1e-12)
        assert int(r["IMAT nodes"]) == truth.n_imat[mid]
        assert float(r["IMCT [cm^3]"]) == pytest.approx(truth.n_imct.get(mid, 0) * cell, rel=1e-12)
        assert r["F_max [N]"] == ""  # per-muscle force is not separable
    na = by["not attributed"]
    # the CT patch far from muscle lies at the body's surface (0.7 cells from it): skin, not IMCT
    assert int(na["IMCT nodes"]) == 0 and int(na["skin nodes"]) == truth.n_imct[0]
    assert int(na["subcutaneous fat nodes"]) == truth.n_subcutaneous
    tot = by["total"]
    assert float(tot["whole model [cm^3]"]) == pytest.approx(n * cell, rel=1e-12)
    assert int(tot["IMAT nodes"]) == sum(truth.n_imat.values())
    total = "total volume: muscle + IMAT + IMCT + aponeurosis [cm^3]"
    for h in ("muscle [cm^3]", "IMAT [cm^3]", "IMCT [cm^3]", "subcutaneous fat [cm^3]", "skin [cm^3]", total,
              "whole model [cm^3]"):
        assert sum(float(by[k][h]) for k in ("medial", "lateral", "not attributed")) == pytest.approx(float(tot[h]), rel=1e-12)
    fmax = float(tot["F_max [N]"])
    assert fmax == pytest.approx(truth.f_max, rel=1e-12)
    # the paper's total volume: muscle + IMAT + IMCT (+ aponeurosis, none here), without subcutaneous fat and skin
    v3 = (sum(truth.n_muscle.values()) + sum(truth.n_imat.values()) + truth.n_imct[1]) * cell
    assert float(tot[total]) == pytest.approx(v3, rel=1e-12) and v3 < 0.8 * n * cell
    assert float(tot["F_max / total volume [N/cm^3]"]) == pytest.approx(fmax / v3, rel=1e-12)
    assert summary["force_per_volume_N_per_cm3"] == pytest.approx(fmax / v3, rel=1e-12)
    assert summary["force_per_whole_model_volume_N_per_cm3"] == pytest.approx(fmax / (n * cell), rel=1e-12)


def test_table3_section_uses_the_papers_total_volume(done):
    """The page's table headed "(paper Table 3)" and its first screen divide F_max by muscle + IMAT + IMCT +
    aponeurosis (the paper's total volume), not by the whole model with its subcutaneous fat."""
    truth, summary, out = done
    page = (out / "index.html").read_text()
    section = page.split("(paper Table 3)</h2>", 1)[1].split("<h2>", 1)[0]
    head = [html.unescape(h) for h in section.split("<thead>", 1)[1].split("</thead>", 1)[0]
            .replace("<tr>", "").replace("</tr>", "").replace("</th>", "").split("<th>")[1:]]
    last = section.split("<tbody>", 1)[1].split("<tr>")[-1]
    cells = [html.unescape(c.split("</td>")[0]) for c in last.split("<td>")[1:]]
    row = dict(zip(head, cells, strict=True))
    v3 = (sum(truth.n_muscle.values()) + sum(truth.n_imat.values()) + truth.n_imct[1]) * truth.cell_volume
    assert row["region"] == "total"
    assert float(row["F_max / total volume [N/cm³]"]) == pytest.approx(truth.f_max / v3, rel=1e-3)
    assert float(row["total volume: muscle + IMAT + IMCT + aponeurosis [cm³]"]) == pytest.approx(v3, rel=1e-3)
    assert float(row["whole model [cm³]"]) == pytest.approx(truth.n_nodes * truth.cell_volume, rel=1e-3)
    first = html.unescape(page.split("<h2>", 1)[0])
    assert f"F_max / total volume (muscle + IMAT + IMCT + aponeurosis) [N/cm³]</td><td>{truth.f_max / v3:.4g}<" in first


def test_near_muscle_rule_against_brute_force(done):
    truth, _, _ = done
    m = load_results(truth.path).model
    t = tissue_table(m.ijk, m.tissue, m.muscle_id, m.shape, m.spacing, m.muscle_names, rule="near_muscle", attach_distance=2.0)
    fat = np.flatnonzero(m.tissue == 3)
    mus = np.flatnonzero(m.tissue == 1)
    d = np.abs(m.ijk[fat][:, None, :].astype(int) - m.ijk[mus][None, :, :].astype(int)).max(axis=2).min(axis=1)
    expect = int((d <= 2).sum())
    total = t["rows"][-1]
    assert total["IMAT nodes"] == expect
    assert total["subcutaneous fat nodes"] == fat.size - expect
    assert expect > sum(truth.n_imat.values())  # the simple rule also counts fat lying against muscle


# ------------------------------------------------------------------------------------------ html
def test_html_page(done):
    _, summary, out = done
    text = (out / "index.html").read_text()
    assert "data:image/png;base64," in text
    assert text.count("<img") >= 4
    assert "Phantom leg" in text and "Synthetic inputs" in text
    assert "complete" in text
    # the only scripts: the 3-D view's files beside the page (no inline code, nothing from the network)
    assert re.findall(r"<script[^>]*>", text) == [f'<script src="{f}">' for f in ("plotly.min.js", "view3d_data.js", "view3d.js")]
    assert all((out / f).is_file() for f in ("plotly.min.js", "view3d_data.js", "view3d.js"))
    assert "direct-lu" in text  # other solver attributes are shown
    assert "activation" in text and "tissue_table.csv" in text
    saved = json.loads((out / "summary.json").read_text())
    assert saved["F_max_N"] == summary["F_max_N"]
    assert saved["newton"]["iterations"] == [0, 4, 4, 4, 4]
    np.testing.assert_allclose(saved["newton"]["final_residual"][1:], 10.0 ** (1 - 2 ** 4))


def test_failed_solve_report(failed):
    truth, index, out = failed
    text = index.read_text()
    assert index.name == "index.html"
    assert html.escape(truth.status) in text and 'class="fail"' in text
    header, rows = _csv(out / "force_activation.csv")
    conv = _col(header, rows, "converged")
    np.testing.assert_array_equal(conv, [1, 1, 1, 0])
    # F_max only over converged steps (fixture: the failed step has the largest force)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["failed"] is True
    assert summary["F_max_N"] == pytest.approx(truth.f_max, rel=1e-12)
    assert summary["F_max_N"] < _col(header, rows, "end_force [N]")[-1]
    assert summary["outputs"]["vtu_steps"] == [0, 1, 2]
    assert any("did not converge" in w for w in summary["warnings"])
    assert summary["newton"]["iterations"][-1] == 25


# ------------------------------------------------------------------------------------------ cohort
def test_cohort_summary(tmp_path):
    young = write_results_fixture(tmp_path / "young.h5", n_steps=2, force_scale=68.76)
    old = write_results_fixture(tmp_path / "old.h5", n_steps=2, force_scale=37.74, shape=(18, 18, 5))
    cfg = ReportConfig(vtu=False, slices=False, dpi=40)
    s_young = make_report(young.path, tmp_path / "ry", cfg, extra={"subject": "young"})
    idx_old = run_report(old.path, tmp_path / "ro", cfg)
    entries = [s_young, {"name": "old", "report": str(idx_old)}, summarize_results(old.path, extra={"subject": "old-again"})]
    page = cohort_summary(entries, tmp_path / "cohort", failures=[{"name": "broken", "error": "segmentation failed"}])
    header, rows = _csv(tmp_path / "cohort" / "cohort.csv")
    assert [r[0] for r in rows] == ["young", "old", "old-again"]
    f = _col(header, rows, "F_max [N]")
    np.testing.assert_allclose(f, [young.f_max, old.f_max, old.f_max], rtol=1e-12)
    np.testing.assert_allclose(_col(header, rows, "F_max (ratio to first)"), f / f[0], rtol=1e-12)
    vol = _col(header, rows, "model total volume [cm^3]")
    np.testing.assert_allclose(vol, [young.n_nodes * young.cell_volume, old.n_nodes * old.cell_volume, old.n_nodes * old.cell_volume])
    np.testing.assert_allclose(_col(header, rows, "F_max / model total volume [N/cm^3]"), f / vol, rtol=1e-12)
    muscle = _col(header, rows, "muscle [cm^3]")
    np.testing.assert_allclose(_col(header, rows, "F_max / muscle volume [N/cm^3]"), f / muscle, rtol=1e-12)
    text = page.read_text()
    assert "broken" in text and "data:image/png;base64," in text and "%" in text


def test_cohort_shows_the_reference_values_beside_the_model(tmp_path):
    young = write_results_fixture(tmp_path / "young.h5", n_steps=2, force_scale=68.76)
    old = write_results_fixture(tmp_path / "old.h5", n_steps=2, force_scale=37.74, shape=(18, 18, 5))
    ref = {"young": {"F_max": 68.76, "force_per_muscle_volume": 0.695}, "old": {"F_max": 37.74, "force_per_muscle_volume": 0.6098}}
    sums = [make_report(r.path, tmp_path / f"r{k}", ReportConfig(vtu=False, slices=False, html=False, dpi=40,
                                                                   reference_values=ref[k], reference_values_label="paper"),
                        extra={"subject": k}) for k, r in (("young", young), ("old", old))]
    page = cohort_summary(sums, tmp_path / "cohort")
    header, rows = _csv(tmp_path / "cohort" / "cohort.csv")
    np.testing.assert_allclose(_col(header, rows, "F_max [N] (paper)"), [68.76, 37.74])
    np.testing.assert_allclose(_col(header, rows, "F_max / muscle volume (ratio to first, reference)"), [1.0, 0.6098 / 0.695])
    assert "old / young (paper)" in page.read_text()
    with pytest.raises(InputError, match="report.reference_values.F_mx"):
        ReportConfig(reference_values={"F_mx": 1.0})


# ------------------------------------------------------------------------------------------ errors
def test_bad_inputs(tmp_path, done):
    truth, _, _ = done
    with pytest.raises(InputError, match="force_sets"):
        make_report(truth.path, tmp_path / "a", ReportConfig(force_sets=["z_top"], vtu=False, slices=False, html=False))
    with pytest.raises(InputError, match="slice_position"):
        make_report(truth.path, tmp_path / "b", ReportConfig(vtu=False, slice_position=(1e3, 0.0, 0.0), html=False))
    with pytest.raises(InputError, match="not found"):
        run_report(tmp_path / "missing.h5", tmp_path / "c")
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as f:
        f.attrs["schema"] = "pixmuscle.model"
        f.attrs["schema_version"] = 1
    with pytest.raises(InputError, match="pixmuscle.results"):
        run_report(other, tmp_path / "d")
    with pytest.raises(InputError, match="every_nth_step"):
        parse_section(ReportConfig, {"every_nth_stpe": 2}, "report")
    with pytest.raises(InputError, match="slice_position"):
        parse_section(ReportConfig, {"slice_position": [1.0, 2.0]}, "report")
    cfg = parse_section(ReportConfig, {"vtu": False, "force_sets": ["z_max"], "slice_position": [1, 2, 3]}, "report")
    assert cfg.force_sets == ["z_max"] and cfg.slice_position == (1.0, 2.0, 3.0)


# ------------------------------------------------------------------------------------------ solver files
def test_reads_files_written_by_the_solver_module(tmp_path):
    """A file written by pixmuscle.mechanics.results.save_results reports with the solver's own R·n_out."""
    R = pytest.importorskip("pixmuscle.mechanics.results")
    from fixtures_results import phantom_model

    from pixmuscle.io.results import save_results

    model, _ = phantom_model()
    n, s1 = model.n_nodes, 3
    rng = np.random.default_rng(3)
    A = rng.normal(size=(s1, n, 3, 3))
    cauchy = np.stack([R.cauchy_voigt(a + np.swapaxes(a, -1, -2)) for a in A])
    u = 0.01 * rng.normal(size=(s1, n, 3))
    reaction = {k: rng.normal(size=(s1, 3)) for k in ("z_min", "z_max", "bone_surface")}
    constrained = {"z_min": np.ones(3, bool), "z_max": np.ones(3, bool), "bone_surface": np.array([1, 1, 0], bool)}
    rows = 5
    newton = {c: (np.repeat([1, 2, 3], [2, 2, 1]) if c == "step" else np.array([0, 1, 0, 1, 0]) if c == "iteration"
                  else rng.uniform(size=rows)) for c in R.NEWTON_COLUMNS}
    res = R.Results(model=model, alpha=np.array([0.0, 0.3, 0.6]), load_factor=np.array([0.0, 1 / 3, 2 / 3]),
                    converged=np.ones(s1, bool), iterations=np.array([0, 2, 2]), cutbacks=np.array([0, 1, 0]),
                    u=u, d=u, reaction=reaction, prescribed={k: np.zeros((s1, 3)) for k in reaction},
                    constrained=constrained, cauchy=cauchy, max_principal=R.max_principal(cauchy), newton=newton,
                    status="failed: load step 3 of 3 did not converge after 4 cutbacks", n_steps_planned=3,
                    info={"linear_solver": "direct"}, sign_convention="R . n_out")
    path = save_results(tmp_path / "results.h5", res, config={"steps": 3})
    summary = make_report(path, tmp_path / "out", ReportConfig(dpi=40, slices=False))
    expect = 0.5 * (res.force("z_min") + res.force("z_max"))
    np.testing.assert_allclose(summary["curve"]["end_force_N"], expect, rtol=1e-14)
    assert summary["F_max_N"] == pytest.approx(expect.max())
    assert summary["newton"]["cutbacks"] == [0, 1, 0] and summary["newton"]["n_steps_planned"] == 3
    assert summary["failed"] and "failed: load step 3" in (tmp_path / "out" / "index.html").read_text()
    with meshio.xdmf.TimeSeriesReader(tmp_path / "out" / "fields.xdmf") as xr:
        xr.read_points_cells()
        _, _, cd = xr.read_data(2)
    np.testing.assert_array_equal(cd["displacement [cm]"][0], u[2])
    np.testing.assert_allclose(cd["max_principal_cauchy [N/cm^2]"][0], res.max_principal[2])


def test_force_sets_follow_constrained_components():
    from pixmuscle.report.curves import select_force_sets

    r = {k: np.zeros((2, 3)) for k in ("z_min", "z_max", "bone_surface")}
    assert select_force_sets(r) == ["z_min", "z_max"]
    assert select_force_sets(r, constrained={"z_min": "xyz", "z_max": "xy"}) == ["z_min"]
    with pytest.raises(InputError, match="not constrained along z"):
        select_force_sets(r, ["z_max"], constrained={"z_max": "xy"})
    with pytest.raises(InputError, match="not an end set"):
        select_force_sets(r, ["bone_surface"])


# ------------------------------------------------------------------------------------------ page layout
def _page_width(path, width):
    """(document scroll width, window width) of an HTML file in headless Chromium at ``width`` px."""
    import re
    import shutil
    import subprocess

    exe = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")
    if exe is None:
        pytest.skip("no Chromium on this machine")
    probe = path.with_name(path.stem + "_probe.html")
    script = ('<script>document.body.setAttribute("data-width", document.documentElement.scrollWidth + " " + '
              "window.innerWidth)</script>")
    probe.write_text(path.read_text(encoding="utf-8").replace("</body>", script + "</body>"), encoding="utf-8")
    out = subprocess.run([exe, "--headless", "--no-sandbox", "--disable-gpu", f"--window-size={width},900",
                          "--dump-dom", probe.as_uri()], capture_output=True, text=True, timeout=60).stdout
    scroll, inner = map(int, re.search(r'data-width="(\d+) (\d+)"', out).groups())
    return scroll, inner


def test_wide_tables_scroll_within_the_page(done, tmp_path):
    """A per-slice area table of many muscles (and the report page itself) never widens the page: a table
    wider than the page scrolls inside its own box (checked in a real browser)."""
    from pixmuscle.report.html import page, table

    names = [f"gastrocnemius_{k} [cm^2]" for k in range(12)] + [f"soleus_{k} [cm^2]" for k in range(12)]
    wide = page("areas", ["<h3>Area per slice [cm²]</h3>",
                          table(["slice", "z [cm]", *names], [[k, 0.5 * k, *np.linspace(1, 2, len(names))] for k in range(4)])])
    (tmp_path / "areas.html").write_text(wide, encoding="utf-8")
    scroll, inner = _page_width(tmp_path / "areas.html", 1400)
    assert scroll <= inner == 1400
    _, _, out = done
    scroll, inner = _page_width(out / "index.html", 900)
    assert scroll <= inner


# ------------------------------------------------------------------ figures of docs/examples.md (Example 2)
def test_region_edges_outline_a_block_and_a_hole():
    """A 3 × 2 block inside a 5 × 6 image: 2 (3 + 2) = 10 unit edges around it, at the pixel borders; a
    region touching the image border is closed by the border."""
    from pixmuscle.report.slices import region_edges

    lab = np.zeros((5, 6), int)
    lab[1:3, 2:5] = 7                      # rows 1-2, columns 2-4
    seg = region_edges(lab, x0=10.0, y0=-1.0, dh=0.5, dv=2.0)
    assert seg.shape == (10, 2, 2)
    xs, ys = seg[..., 0], seg[..., 1]
    assert set(np.round(xs.ravel(), 9)) == {11.0, 11.5, 12.0, 12.5}   # x0 + 2 dh .. x0 + 5 dh
    assert set(np.round(ys.ravel(), 9)) == {1.0, 3.0, 5.0}            # y0 + 1 dv .. y0 + 3 dv
    assert np.allclose(np.linalg.norm(seg[:, 1] - seg[:, 0], axis=1)[(xs[:, 0] == xs[:, 1])], 2.0)
    full = region_edges(np.ones((2, 3), int), 0.0, 0.0, 1.0, 1.0)
    assert full.shape == (2 * (2 + 3), 2, 2)   # the border of a full image


def test_plane_points_lie_in_node_cells_on_the_plane(tmp_path):
    from fixtures_results import phantom_model

    from pixmuscle.report.slices import plane_points

    m, _ = phantom_model()
    ijk = np.asarray(m.ijk, np.int64)
    pts = plane_points(ijk, m.origin, m.spacing, 1, 10, 0, 2, step_cm=1.0)   # coronal plane j = 10
    assert pts.shape[0] > 10
    assert np.allclose(pts[:, 1], m.origin[1] + 10 * m.spacing[1])
    cell = np.rint((pts - m.origin) / m.spacing).astype(np.int64)
    assert {tuple(c) for c in cell} <= {tuple(c) for c in ijk}
    gaps = np.diff(np.unique(np.round(pts[:, 0], 9)))
    assert np.allclose(gaps % 1.0, 0.0) or np.allclose(gaps, 1.0)   # a 1-cm grid along x


@pytest.fixture(scope="module")
def example2(tmp_path_factory):
    """fig_examples.py run on an Example 2-like folder: a coarse and a fine fixture model, the coarse
    model's RK coefficients replaced by a linear field d_J = A X_J + b (reproduced exactly by the RK
    approximation with a linear basis, whatever the supports)."""
    import importlib.util
    from pathlib import Path

    d = tmp_path_factory.mktemp("example2")
    coarse = write_results_fixture(d / "results_coarse.h5", n_steps=3)
    write_results_fixture(d / "results_fine.h5", n_steps=3, force_scale=66.0)
    A = np.array([[0.01, -0.02, 0.0], [0.03, 0.01, 0.005], [0.0, 0.02, -0.04]])
    b = np.array([0.1, -0.05, 0.02])
    with h5py.File(coarse.path, "r+") as f:
        X = f["nodes/X"][()]
        f["steps/d"][3] = X @ A.T + b
    spec = importlib.util.spec_from_file_location("fig_examples", Path(__file__).parents[1] / "benchmarks" / "fig_examples.py")
    fe = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(fe)
    assert fe.main(["lower_leg_small", "--run-dir", str(d), "--out-dir", str(d / "figs")]) == 0
    return fe, d, A, b


def test_example2_figures_are_written(example2):
    fe, d, _, _ = example2
    for name in ("force_activation", "displacement", "stress"):
        assert (d / "figs" / f"example2_small_{name}.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    curves = fe.model_curves(d)
    assert [c["name"] for c in curves] == ["coarse", "fine"]
    assert np.nanmax(curves[0]["force_N"]) == pytest.approx(68.76) and np.nanmax(curves[1]["force_N"]) == pytest.approx(66.0)


def test_example2_arrows_are_the_rk_field(example2, tmp_path):
    """The arrows are u(x) = Σ Ψ_J(x) d_J at points between the nodes: equal to the linear field A x + b."""
    fe, d, A, b = example2
    res = load_results(d / "results_coarse.h5")
    out = fe.plot_displacement_planes(res, 3, tmp_path / "u.png", title="t", step_cm=0.6)
    for name in ("transverse", "coronal", "sagittal"):
        p, u = out[name]["points"], out[name]["u"]
        assert p.shape[0] > 5 and out[name]["n_fallback"] == 0
        nodes = {tuple(x) for x in np.round(res.model.X, 6)}
        assert any(tuple(q) not in nodes for q in np.round(p, 6))  # points between the nodes, too
        np.testing.assert_allclose(u, p @ A.T + b, atol=1e-9)


def test_example2_stress_planes_hold_the_nodal_stress(example2, tmp_path):
    fe, d, _, _ = example2
    res = load_results(d / "results_coarse.h5")
    out = fe.plot_stress_planes(res, 3, tmp_path / "s.png", title="t")
    mp = np.asarray(res.max_principal[3])
    k = fe.planes(res.model)[0][4]
    on = mp[np.asarray(res.model.ijk)[:, 2] == k]
    img = out["transverse"]
    assert np.isfinite(img).sum() == on.size and np.allclose(np.sort(img[np.isfinite(img)]), np.sort(on))
    ijk = np.asarray(res.model.ijk)
    every = np.concatenate([mp[ijk[:, n] == i] for _, n, _, _, i in fe.planes(res.model)])
    assert out["min"] == every.min() and out["max"] == every.max()
    assert (out["vmin"], out["vmax"]) == tuple(np.percentile(every, [0.5, 99.5]))   # the shared colour range


def test_example_record_from_a_finished_run_folder(example2):
    """benchmarks/bench_examples.py --from-run: the per-model record read back from the results files
    (fixture answers: 3 converged steps of 4 Newton iterations, F_max 68.76 / 66 N) and the wall time
    from the folder's lock file to its newest file."""
    import importlib.util
    import os
    from pathlib import Path

    _, d, _, _ = example2
    (d / ".pixmuscle.lock").write_text(json.dumps({"argv": ["/x/bin/pixmuscle", "run", "configs/lower_leg_small.yaml"],
                                                   "started_utc": "2026-01-01T00:00:00+00:00"}))
    for p in d.rglob("*"):
        if p.is_file():
            os.utime(p, (1767225600 + 100, 1767225600 + 100))   # 2026-01-01 00:01:40 UTC
    spec = importlib.util.spec_from_file_location("bench_examples", Path(__file__).parents[1] / "benchmarks" / "bench_examples.py")
    be = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(be)
    key, rec = be.from_run("lower_leg_small", d, None, 1.5, [2.0, 2.1])
    assert key == "lower_leg_small" and rec["status"] == "complete"
    assert rec["command"] == "pixmuscle run configs/lower_leg_small.yaml"
    assert rec["wall_s"] == 100.0 and rec["peak_rss_GB"] == 1.5 and rec["load_avg"] == [2.0, 2.1]
    m = rec["models"]
    assert list(m) == ["coarse", "fine"]
    assert m["coarse"]["newton_iterations"] == 12 and m["coarse"]["steps_converged"] == 3
    assert m["coarse"]["F_max_N"] == pytest.approx(68.76) and m["fine"]["F_max_N"] == pytest.approx(66.0)
    assert m["coarse"]["nodes"] == load_results(d / "results_coarse.h5").model.n_nodes
    only = d / "coarse_only"            # one of the config's two models, no lock file
    only.mkdir()
    (only / "results_coarse.h5").write_bytes((d / "results_coarse.h5").read_bytes())
    key, rec = be.from_run("lower_leg_small", only, None, None, None)
    assert key == "lower_leg_small [coarse]" and rec["wall_s"] is None and rec["peak_rss_GB"] is None

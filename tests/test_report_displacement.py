"""The report of a displacement-driven run (paper Example 1's protocol) is a force–displacement report.

A connective-tissue bar between roller ends is stretched by 10 % (a homogeneous state: the analytic
uniaxial force of :func:`pixmuscle.mechanics.homogeneous.uniaxial_bar` is the reference curve). The
report finds the protocol from the results file alone, draws the end force against the prescribed
displacement beside the reference, and has no activation content (force vs activation, α at F_max,
force per unit volume, the Table 3 tissue table)."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from pixmuscle.config import parse_section
from pixmuscle.io.results import save_results
from pixmuscle.mechanics import homogeneous
from pixmuscle.mechanics.config import SolveConfig
from pixmuscle.mechanics.solve import make_materials, solve
from pixmuscle.model.tissues import CONNECTIVE_TISSUE
from pixmuscle.report.config import ReportConfig
from pixmuscle.report.displacement import run_protocol
from pixmuscle.stages.report import make_report
from pixmuscle.verify.mechanics import mask_model, roller_bcs

SPACING = (0.2, 0.2, 0.3)
SHAPE = (3, 3, 6)
STRETCH = 1.10


@pytest.fixture(scope="module")
def bar_report(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("bar")
    model = mask_model(np.ones(SHAPE, bool), SPACING)
    length, area = SHAPE[2] * SPACING[2], SHAPE[0] * SPACING[0] * SHAPE[1] * SPACING[1]
    cfg = parse_section(SolveConfig, {"steps": 2, "activation": {"from": 0.0, "to": 0.0},
                                      "boundary_conditions": roller_bcs(model, (STRETCH - 1) * length)}, "solve")
    res = solve(model, cfg)
    results = save_results(tmp / "results.h5", res, config=cfg)
    # the analytic reference, at the run's displacements and between them
    mat = make_materials(cfg.materials)[CONNECTIVE_TISSUE]
    disp = np.linspace(0.0, (STRETCH - 1) * length, 9)
    ref = tmp / "analytic.csv"
    with open(ref, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["step", "displacement_cm", "force_N"])
        for k, d in enumerate(disp):
            w.writerow([k, d, homogeneous.uniaxial_bar(mat, 1 + d / length, area)["force"] if d > 0 else 0.0])
    out = tmp / "report"
    summary = make_report(results, out, ReportConfig(vtu=False, view3d=False, slices=False, reference_curve=ref,
                                                     reference_label="homogeneous bar (analytic)"))
    return res, summary, out, length


def test_protocol_is_found_from_the_results():
    assert run_protocol([0.0, 0.5, 0.95], {"z_min": np.zeros((3, 3))})["kind"] == "activation"
    p = run_protocol([0.2, 0.2, 0.2], {"z_min": np.zeros((3, 3)), "z_max": [[0, 0, 0], [0, 0, -0.5], [0, 0, -1.0]]})
    assert (p["kind"], p["set"], p["component"], p["alpha"]) == ("displacement", "z_max", "z", 0.2)
    np.testing.assert_allclose(p["displacement_cm"], [0, -0.5, -1.0])
    assert run_protocol([0.0, 0.0], {"z_min": np.zeros((2, 3))})["kind"] == "activation"  # nothing moves


def test_displacement_report_has_the_force_displacement_curve(bar_report):
    res, summary, out, length = bar_report
    assert summary["protocol"] == {"kind": "displacement", "set": "z_max", "component": "z", "alpha": 0.0}
    np.testing.assert_allclose(summary["curve"]["displacement_cm"], [0.0, 0.05 * length, 0.1 * length])
    # the curve against the analytic bar: the homogeneous state, so they agree closely
    ref = summary["reference"]
    assert ref["max_abs_relative"] < 5e-3
    np.testing.assert_allclose(ref["force_N"][1:], summary["curve"]["end_force_N"][1:], rtol=5e-3)
    rows = list(csv.reader(open(out / "force_displacement.csv")))
    assert rows[0][:3] == ["step", "z_max.uz [cm]", "load_factor"]
    col = rows[0].index("z_max.uz [cm]")
    np.testing.assert_allclose([float(r[col]) for r in rows[1:]], summary["curve"]["displacement_cm"])
    assert "relative_difference" in rows[0] and "alpha" not in rows[0]
    assert (out / "force_displacement.png").is_file()
    page = (out / "index.html").read_text()
    assert "<h2>Force–displacement</h2>" in page and "homogeneous bar (analytic)" in page


def test_displacement_report_has_no_activation_content(bar_report):
    _, summary, out, _ = bar_report
    assert not (out / "force_activation.csv").exists() and not (out / "force_activation.png").exists()
    assert not (out / "tissue_table.csv").exists()
    page = (out / "index.html").read_text()
    for text in ("Force–activation", "vs activation", "α at F_max", "per unit total volume", "per unit volume",
                 "Table 3", "α [-]", "force_activation"):
        assert text not in page, text
    assert summary["alpha_at_F_max"] is None and summary["force_per_volume_N_per_cm3"] is None
    assert "force_activation_csv" not in summary["outputs"]
    assert json.loads((out / "summary.json").read_text())["protocol"]["kind"] == "displacement"

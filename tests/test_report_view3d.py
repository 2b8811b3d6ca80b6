"""The report's interactive 3-D view, opened from disk in a real headless Chromium (Debian's
``chromium``, driven by Playwright; .ci/install-browser installs it): the WebGL plot draws, the
field list and the step slider change what is drawn (checked against the results file), the tissue
legend counts match the model, no console errors, no request leaves the report folder. Plus the
decimation of large models and the report without plotly."""

from __future__ import annotations

import io
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
from fixtures_results import write_results_fixture

from pixmuscle.io.results import load_results
from pixmuscle.report.config import ReportConfig
from pixmuscle.report.view3d import FILES, decimate
from pixmuscle.stages.report import make_report

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
#: the flags of docs: no sandbox as root, software WebGL (SwiftShader), no background connections
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader", "--use-angle=swiftshader",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 "--no-first-run"]


def test_decimate_keeps_a_regular_in_plane_subset():
    ijk = np.stack(np.meshgrid(np.arange(60), np.arange(50), np.arange(4), indexing="ij"), -1).reshape(-1, 3)
    assert np.array_equal(decimate(ijk, 20000), np.arange(len(ijk)))         # small: every node
    keep = decimate(ijk, 2000)
    assert 0 < keep.size <= 2000
    k = np.unique(np.diff(np.unique(ijk[keep, 0])))
    assert k.size == 1 and k[0] >= 2                                          # every k-th voxel in x ...
    assert np.array_equal(np.unique(ijk[keep, 2]), np.arange(4))              # ... all slices kept
    assert keep.size == len(np.unique(ijk[keep, 0])) * len(np.unique(ijk[keep, 1])) * 4


def test_report_says_so_without_plotly(tmp_path, monkeypatch):
    truth = write_results_fixture(tmp_path / "results.h5", n_steps=1)
    monkeypatch.setitem(sys.modules, "plotly", None)                         # import plotly → ImportError
    summary = make_report(truth.path, tmp_path / "out", ReportConfig(dpi=30, vtu=False, slices=False))
    assert "plotly is not installed" in summary["view3d"]["error"]
    assert "Interactive 3-D view not written: plotly is not installed" in (tmp_path / "out" / "index.html").read_text()
    assert not any((tmp_path / "out" / f).exists() for f in FILES)


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    pytest.importorskip("plotly")
    d = tmp_path_factory.mktemp("view3d")
    truth = write_results_fixture(d / "results.h5", n_steps=2)
    summary = make_report(truth.path, d / "out", ReportConfig(dpi=30, vtu=False, slices=False))
    return truth, d / "out", summary


@pytest.fixture(scope="module")
def browser():
    sync_api = pytest.importorskip("playwright.sync_api", reason="playwright not installed (pip install playwright)")
    if CHROMIUM is None:
        pytest.skip("no chromium on this machine (.ci/install-browser installs Debian's)")
    with sync_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        yield b
        b.close()


def _open(browser, index: Path):
    page = browser.new_page(viewport={"width": 1400, "height": 1000})
    seen = {"errors": [], "requests": []}
    page.on("console", lambda m: m.type == "error" and seen["errors"].append(m.text))
    page.on("pageerror", lambda e: seen["errors"].append(str(e)))
    page.on("request", lambda r: seen["requests"].append(r.url))
    page.goto(index.as_uri())
    return page, seen


def _drawn(page, field: str, step: int) -> None:
    page.wait_for_selector(f'#view3d-plot[data-drawn="1"][data-field="{field}"][data-step="{step}"]', timeout=30000)


def _picture(page) -> np.ndarray:
    from PIL import Image

    png = page.locator("#view3d-plot .gl-container canvas").first.screenshot()
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))


def test_view_draws_and_follows_field_and_step(report, browser):
    truth, out, summary = report
    res = load_results(truth.path)
    page, seen = _open(browser, out / "index.html")
    _drawn(page, "umag", 2)                                                   # default: |u| at the last step
    img = _picture(page)
    painted = (img < 245).any(axis=2).mean()
    colours = len(np.unique(img.reshape(-1, 3), axis=0))
    assert painted > 0.05 and colours > 50, (painted, colours)               # the WebGL canvas is not empty
    assert "displacement magnitude |u| [cm]" in page.locator("#view3d-plot .cbtitle").text_content()

    # the points are the nodes on the deformed body of the chosen step (vs the results file)
    def xyz():
        return np.array(page.evaluate("() => { const t = document.getElementById('view3d-plot').data[0];"
                                      " return [t.x, t.y, t.z]; }")).T

    X, u2 = res.model.X, res.step(2).u
    np.testing.assert_allclose(np.sort(xyz(), axis=0), np.sort(X + u2, axis=0), atol=1e-3)
    page.locator("#view3d-step").fill("0")                                    # slider to step 0: the reference body
    _drawn(page, "umag", 0)
    np.testing.assert_allclose(np.sort(xyz(), axis=0), np.sort(X + res.step(0).u, axis=0), atol=1e-3)
    assert "step 0" in page.locator("#view3d-step-label").inner_text()

    page.select_option("#view3d-field", "tissue")                            # categorical: legend with counts
    _drawn(page, "tissue", 0)
    legend = page.locator("#view3d-plot .legendtext").all_text_contents()
    n_fat = int((res.model.tissue == 3).sum())
    n_imat = int(truth.imat_nodes.sum())
    assert f"muscle ({sum(truth.n_muscle.values())})" in legend
    assert f"intermuscular fat (IMAT) ({n_imat})" in legend
    assert f"other fat (subcutaneous) ({n_fat - n_imat})" in legend
    assert not np.array_equal(_picture(page), img)

    for field in ("s1", "muscle", "fibre"):
        page.select_option("#view3d-field", field)
        _drawn(page, field, 0)
    assert "fibre angle" in page.locator("#view3d-plot .cbtitle").text_content()
    assert len(page.locator("#view3d-plot .legendtext").all_text_contents()) >= 1     # 'no fibre (not muscle)'
    assert page.locator(".view3d-missing").is_hidden()
    assert seen["errors"] == []
    assert [u for u in seen["requests"] if not u.startswith(("file:", "data:", "blob:"))] == []  # no network
    page.close()


def test_page_says_what_is_missing_without_the_scripts(report, browser, tmp_path):
    _, out, _ = report
    copy = tmp_path / "copied"
    shutil.copytree(out, copy)
    (copy / "plotly.min.js").unlink()                                         # index.html copied alone, say
    page, _ = _open(browser, copy / "index.html")
    page.wait_for_load_state("load")
    assert page.locator(".view3d-missing").is_visible()
    assert "plotly.min.js" in page.locator(".view3d-missing").inner_text()
    page.close()

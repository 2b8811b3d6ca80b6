"""The force's uncertainty from the scan: the perturbations against independent expectations, the config,
and a small uncertainty run of the demo through the real pipeline (noise-free + 2 realisations)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from pixmuscle.errors import InputError
from pixmuscle.imaging.dti import principal_eigenvector
from pixmuscle.imaging.dti_noise import acquisition, design_matrix, fibre_angle_deg, noisy_tensors
from pixmuscle.segmentation.perturb import boundary_displacement, warp_labels
from pixmuscle.uncertainty import prediction_interval

ROOT = Path(__file__).resolve().parents[1]


def _rotation(rng) -> np.ndarray:
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def _expected_rms_angle_deg(evals, evecs, snr, bvals, g) -> float:
    """First-order eigenvector perturbation (Anderson, MRM 46:1174, 2001): E θ² = Σ_j Var(e_jᵀ δD e1) / (λ1 − λj)²,
    with the covariance of the weighted log-linear fit σ² (Bᵀ diag(S²) B)⁻¹, S the noise-free signals."""
    D = evecs @ np.diag(evals) @ evecs.T
    B = design_matrix(bvals, g)
    p = np.array([D[0, 0], D[1, 1], D[2, 2], D[0, 1], D[0, 2], D[1, 2], 0.0])
    s = np.exp(B @ p)
    cov = np.linalg.inv(B.T @ (s[:, None] ** 2 * B)) / snr**2
    e1 = evecs[:, 0]
    total = 0.0
    for j in (1, 2):
        ej = evecs[:, j]
        a = np.array([ej[0] * e1[0], ej[1] * e1[1], ej[2] * e1[2], ej[0] * e1[1] + ej[1] * e1[0],
                      ej[0] * e1[2] + ej[2] * e1[0], ej[1] * e1[2] + ej[2] * e1[1], 0.0])
        total += a @ cov @ a / (evals[0] - evals[j]) ** 2
    return float(np.degrees(np.sqrt(total)))


@pytest.mark.parametrize("snr", [50.0, 100.0])
def test_fibre_angular_error_matches_first_order_theory(snr):
    """The re-estimated fibres of many voxels of one muscle-like tensor (FA ≈ 0.3) scatter as the analytic
    first-order theory of the fit predicts, at the stated SNR."""
    rng = np.random.default_rng(1)
    evals = np.array([2.1e-3, 1.4e-3, 1.2e-3])          # mm²/s, skeletal muscle
    evecs = _rotation(rng)
    D = evecs @ np.diag(evals) @ evecs.T
    bvals, g = acquisition(500.0, 12, 1)
    field = np.broadcast_to(D, (20000, 3, 3))
    noisy = noisy_tensors(field, snr, np.random.default_rng(2), bvals=bvals, gradients=g)
    v, _, _ = principal_eigenvector(noisy)
    measured = float(np.sqrt(np.mean(fibre_angle_deg(v, evecs[:, 0]) ** 2)))
    expected = _expected_rms_angle_deg(evals, evecs, snr, bvals, g)
    assert measured == pytest.approx(expected, rel=0.05), (measured, expected)
    # the mean tensor is unbiased to within the Monte-Carlo error and Rician bias (a few % at these SNRs)
    assert np.allclose(noisy.mean(axis=0), D, atol=0.05 * evals[0])


def test_noise_free_limit_and_zero_tensors():
    D = np.zeros((2, 2, 1, 3, 3))
    D[0, 0, 0] = np.diag([2e-3, 1e-3, 1e-3])
    bvals, g = acquisition(500.0, 12, 1)
    out = noisy_tensors(D, 1e7, np.random.default_rng(0), bvals=bvals, gradients=g)
    assert np.allclose(out[0, 0, 0], D[0, 0, 0], atol=1e-8)
    assert not np.any(out[1:]) and not np.any(out[0, 1])     # no data stays no data


def _blocks(shape=(40, 40, 3)) -> np.ndarray:
    """A label volume with several regions and straight and curved boundaries."""
    i, j, _ = np.meshgrid(*(np.arange(n) for n in shape), indexing="ij")
    lab = np.zeros(shape, np.int16)
    lab[(i - 20) ** 2 + (j - 20) ** 2 < 16**2] = 3
    lab[(i - 17) ** 2 + (j - 20) ** 2 < 9**2] = 1
    lab[(i >= 22) & (i < 30) & (j >= 14) & (j < 26)] = 2
    lab[(i - 20) ** 2 + (j - 20) ** 2 < 3**2] = 4
    return lab


@pytest.mark.parametrize("bound", [0.8, 1.5, 2.5])
def test_boundary_moves_within_the_stated_voxels(bound):
    """Every relabelled voxel has, in its own slice, a cell of its new label within ``bound`` voxels of its
    centre (distance to the cell, not to the cell's centre): the boundary moved past it by at most ``bound``."""
    lab = _blocks()
    affine = np.diag([0.156, 0.156, 0.5, 1.0])
    u = boundary_displacement(lab.shape, affine, bound, 0.6, np.random.default_rng(3))
    assert np.linalg.norm(u, axis=-1).max() <= bound + 1e-12
    assert np.linalg.norm(u, axis=-1).max() > 0.8 * bound      # the bound is reached somewhere
    (new,) = warp_labels([lab], u)
    changed = np.argwhere(new != lab)
    assert len(changed) > 20
    r = int(np.ceil(bound)) + 1
    best = np.full(len(changed), np.inf)
    for di in range(-r, r + 1):
        for dj in range(-r, r + 1):
            ii, jj = changed[:, 0] + di, changed[:, 1] + dj
            ok = (ii >= 0) & (ii < lab.shape[0]) & (jj >= 0) & (jj < lab.shape[1])
            same = np.zeros(len(changed), bool)
            same[ok] = lab[ii[ok], jj[ok], changed[ok, 2]] == new[tuple(changed[ok].T)]
            d = np.hypot(max(0.0, abs(di) - 0.5), max(0.0, abs(dj) - 0.5))
            best = np.where(same, np.minimum(best, d), best)
    assert best.max() <= bound + 1e-9
    # and a boundary moved by at most half a voxel moves no voxel centre
    (same,) = warp_labels([lab], boundary_displacement(lab.shape, affine, 0.5, 0.6, np.random.default_rng(3)) * 0.999)
    assert np.array_equal(same, lab)


def test_boundary_field_is_drawn_in_cm():
    """The random field is evaluated at the voxel centres in cm: the same draw on a grid twice as fine gives,
    at the points both grids share, the same displacement in voxels (the bound is in voxels); and it is
    smooth: neighbouring voxels differ by far less than the bound."""
    uc = boundary_displacement((10, 10, 2), np.diag([0.2, 0.2, 0.5, 1.0]), 1.0, 1.0, np.random.default_rng(5))
    uf = boundary_displacement((20, 20, 2), np.diag([0.1, 0.1, 0.5, 1.0]), 1.0, 1.0, np.random.default_rng(5))
    assert np.allclose(uc, uf[::2, ::2], atol=1e-5)
    assert np.abs(np.diff(uf, axis=0)).max() < 0.25


def test_prediction_interval_is_the_spread_not_the_standard_error():
    """The interval of 6 draws holds one more draw of the same normal distribution 95 % of the time
    (binomial error over 4000 trials ≈ 0.35 %); a standard-error interval would hold it far less often."""
    rng = np.random.default_rng(0)
    draws = rng.normal(100.0, 5.0, size=(4000, 6))
    nxt = rng.normal(100.0, 5.0, size=len(draws))
    pis = [prediction_interval(row) for row in draws]
    cover = np.mean([p["low"] <= x <= p["high"] for p, x in zip(pis, nxt, strict=True)])
    assert cover == pytest.approx(0.95, abs=0.015)
    pi = prediction_interval([1.0, 2.0, 3.0])
    assert pi["high"] - pi["mean"] == pytest.approx(4.302653 * 1.0 * np.sqrt(1 + 1 / 3), rel=1e-5)
    assert prediction_interval([1.0])["low"] is None


def _summary(f: float, volume: float = 10.0) -> dict:
    a = np.linspace(0, 0.95, 4)
    return {"F_max_N": f, "force_per_muscle_volume_N_per_cm3": f / volume, "volumes_cm3": {"muscle": volume},
            "status": "complete", "failed": False, "curve": {"alpha": list(a), "end_force_N": list(f * a / 0.95),
                                                            "converged": [True] * 4}}


def test_uncertainty_page_of_a_cohort(tmp_path):
    """Two subjects: each subject's files from its rows alone, and the comparison says whether the force per
    muscle volume differs by more than the intervals."""
    from pixmuscle.report.uncertainty_page import uncertainty_summary
    from pixmuscle.uncertainty import UncertaintyConfig

    young = [100.0, 98.0, 103.0, 101.0]
    old = [60.0, 62.0, 59.0, 61.0, None]                       # the last realisation failed
    rows = [{"subject": "young", "realisation": i, "case": f"r{i:02d}" if i else "", "summary": _summary(f),
             "error": None, "output_dir": str(tmp_path / "young")} for i, f in enumerate(young)]
    rows += [{"subject": "old", "realisation": i, "case": f"r{i:02d}" if i else "",
              "summary": None if f is None else _summary(f), "error": "solve: failed" if f is None else None,
              "output_dir": str(tmp_path / "old")} for i, f in enumerate(old)]
    dirs = {"young": tmp_path / "young", "old": tmp_path / "old"}
    page = uncertainty_summary(rows, UncertaintyConfig(realisations=4), tmp_path, subject_dirs=dirs,
                               subjects=["young", "old"])
    y = json.loads((tmp_path / "young" / "uncertainty.json").read_text())
    o = json.loads((tmp_path / "old" / "uncertainty.json").read_text())
    assert y["realisations"] == 3 and y["noise_free_F_max_N"] == 100.0
    assert y["F_max_mean_N"] == pytest.approx(np.mean(young[1:]))
    assert o["realisations"] == 3 and o["failed"] == [4] and o["realisations_planned"] == 4
    assert (tmp_path / "old" / "uncertainty.csv").read_text().count("\n") == 5   # header + 4 realisations
    text = page.read_text()
    assert "yes: the intervals do not overlap" in text and "solve: failed" in text


# --------------------------------------------------------------------------- config
def _config(tmp_path: Path, **changes) -> Path:
    raw = yaml.safe_load((ROOT / "configs" / "uncertainty.yaml").read_text())
    for section in ("segment",):
        for key in ("mri", "dti_tensor", "imct_mask", "imat_mask"):
            raw[section][key] = str((ROOT / "configs" / raw[section][key]).resolve())
    raw["output_dir"] = str(tmp_path / "out")
    for k, v in changes.items():
        if v is None:
            raw.pop(k, None)
        elif isinstance(v, dict) and isinstance(raw.get(k), dict):
            raw[k] = {**raw[k], **v}
        else:
            raw[k] = v
    p = tmp_path / "unc.yaml"
    p.write_text(yaml.safe_dump(raw, sort_keys=False))
    return p


@pytest.mark.parametrize("change, match", [
    ({"uncertainty": {"dti_snr": -1}}, r"uncertainty.dti_snr: expected a value > 0"),
    ({"uncertainty": {"realisations": 1}}, r"uncertainty.realisations: expected a value ≥ 2"),
    ({"uncertainty": {"boundary_voxels": 0.5}}, r"uncertainty.boundary_voxels: 0.5 moves no voxel"),
    ({"uncertainty": {"dti_snr": None, "boundary_voxels": 0}}, r"nothing is perturbed"),
    ({"uncertainty": {"dti_snrr": 20}}, r"uncertainty.dti_snrr: unknown key; did you mean 'dti_snr'"),
    ({"study": {"vary": {"solve.steps": [2, 3]}}}, r"either a study or an uncertainty section"),
])
def test_bad_uncertainty_config_names_the_key(tmp_path, change, match):
    from pixmuscle.pipeline import load_run

    raw = dict(change)
    if "uncertainty" in raw and None in raw["uncertainty"].values():
        full = yaml.safe_load((ROOT / "configs" / "uncertainty.yaml").read_text())["uncertainty"]
        raw["uncertainty"] = {**full, **raw["uncertainty"]}
    with pytest.raises(InputError, match=match):
        load_run(_config(tmp_path, **raw))


def test_realisation_cases_and_folders(tmp_path):
    from pixmuscle.pipeline import load_run
    from pixmuscle.plan import plan_case

    run = load_run(_config(tmp_path))
    out = tmp_path / "out"
    assert [c.realisation for c in run.cases] == [0, 1, 2, 3, 4]
    assert [c.output_dir for c in run.cases] == [out] + [out / "uncertainty" / f"r{r:02d}" for r in range(1, 5)]
    plan = {st.kind: st.output for st in plan_case(run.cases[2])}
    assert plan["segment"] == out / "segmentation.h5"                     # shared with the noise-free case
    assert plan["perturb"] == out / "uncertainty" / "r02" / "segmentation.h5"
    assert plan["solve"] == out / "uncertainty" / "r02" / "results_coarse.h5"
    assert "perturb" not in {st.kind for st in plan_case(run.cases[0])}  # the noise-free case is the plain demo


# --------------------------------------------------------------------------- end to end
def test_small_uncertainty_run_end_to_end(tmp_path):
    """The demo, noise-free and in 2 realisations (3 load steps, light reports) on a local Dask cluster:
    the files, the interval containing the noise-free F_max, the realisations reproducible from the seed,
    and a serial re-run that skips every stage up to the solve."""
    from pixmuscle.io.segmentation import read_segmentation
    from pixmuscle.pipeline import load_run, run_cases
    from pixmuscle.stages.perturb import run_perturb

    light = {"vtu": False, "xdmf": False, "view3d": False, "slices": False, "segmentation_qc": False}
    cfg = _config(tmp_path, uncertainty={"realisations": 2}, report=light,
                  solve={**yaml.safe_load((ROOT / "configs" / "uncertainty.yaml").read_text())["solve"], "steps": 3})
    raw = yaml.safe_load(cfg.read_text())
    raw["segment"]["qc_png"] = False
    cfg.write_text(yaml.safe_dump(raw, sort_keys=False))
    done = run_cases(cfg, workers=2)                                      # the Dask runner: a local cluster
    assert not done["failures"], done["failures"]
    out = tmp_path / "out"
    assert (out / "uncertainty.html").is_file() and (out / "uncertainty_curves.png").is_file()
    rec = json.loads((out / "uncertainty.json").read_text())
    for key in ("realisations", "F_max_mean_N", "ci95_low_N", "ci95_high_N", "noise_free_F_max_N"):
        assert rec[key] is not None, key
    assert rec["realisations"] == 2
    assert rec["ci95_low_N"] <= rec["noise_free_F_max_N"] <= rec["ci95_high_N"]
    rows = (out / "uncertainty.csv").read_text().splitlines()
    assert rows[0].split(",")[:2] == ["realisation", "F_max_N"] and len(rows) == 3
    per = rec["per_realisation"]
    assert all(p["voxels_relabelled"] > 0 and 1.0 < p["fibre_angle_median_deg"] < 30.0 for p in per)
    assert len({p["F_max_N"] for p in per}) == 2                           # two different realisations
    # the same seed and realisation give the same segmentation, another realisation another one
    again = run_perturb(**{k: v for k, v in _perturb_kwargs(load_run(cfg).cases[1]).items()},
                        out_path=tmp_path / "again.h5")
    a, b = read_segmentation(again), read_segmentation(out / "uncertainty" / "r01" / "segmentation.h5")
    c = read_segmentation(out / "uncertainty" / "r02" / "segmentation.h5")
    assert np.array_equal(a["labels"], b["labels"]) and np.array_equal(a["fiber"], b["fiber"])
    assert not np.array_equal(a["labels"], c["labels"]) and not np.array_equal(a["fiber"], c["fiber"])
    # checkpoint/skip: nothing up to the solve runs again
    again = run_cases(cfg, workers=0, until="solve")
    assert all(not s["ran"] for s in again["summaries"]), [s["ran"] for s in again["summaries"]]


def _perturb_kwargs(case) -> dict:
    from pixmuscle.plan import plan_case

    st = next(s for s in plan_case(case) if s.kind == "perturb")
    return {k: v for k, v in st.kwargs.items() if k != "out_path"}

"""Example 3's old/young force per unit muscle volume, one candidate cause at a time.

The paper's old medial gastrocnemius produces 87.7 % of the young one's force per unit muscle volume
((37.74 / 61.89) / (68.76 / 98.93), its Table 3). This runs the SYNTHETIC MG phantoms at the
paper's resolution and length (96 × 64 × 25 voxels of 0.078 × 0.078 × 0.5 cm, 12.5 cm; solved on the
paper's coarse model, every second pixel: 0.156 × 0.156 × 0.5 cm) and changes one thing at a time
against a **baseline** in which the old phantom has the young architecture (25° pennation, 5.68-cm
fascicles) and the shipped phantoms' volumes: muscle, IMCT, IMAT and the outer layer (aponeurosis and
skin) of every phantom within 1 % of the shipped phantom's (the sizes and tissue ratios are re-calibrated after each change, :func:`phantom`).
Models are built from the phantoms' truth labels and fibres (``build_model.labels``), so the
segmentation plays no part; both ends fixed, α 0 → 0.95 in 10 steps, the shipped defaults otherwise.

Candidates (``CASES``):

* ``shipped``: the shipped phantoms: the old MG with the smaller pennation (21.75°) and shorter
  fascicles (5.11 cm) of Narici et al. 2003 (J Appl Physiol 95:2229), everything else as baseline;
* ``baseline``: the old MG with the young architecture;
* ``a_dti_noise``: fibres re-estimated from noisy DTI (Rician noise on the phantom's noise-free
  tensors, 12 directions, b = 500 s/mm², weighted linear fit, :mod:`pixmuscle.imaging.dti_noise`):
  young at SNR 25 (Damon 2008, MRM 60:934: the SNR that keeps muscle DTI's fibre bias small), old at
  the SNR its fat fraction leaves, 25 · (1 − FF_old) / (1 − FF_young), FF = (IMAT + sub-voxel fat) /
  (muscle + IMAT) with the sub-voxel fat of ``b``;
* ``b_subvoxel_fat``: fat infiltrated below the voxel size: muscle voxels keep their label but a
  contractile fraction 1 − f (an activation image, ``solve.activation.image``), f = 6.7 % young and
  11.9 % old, the mid-points of the intramuscular fat contents Yoshiko et al. 2017 (BMC Med Imaging
  17:12) measured in young (4.8–8.6 %) and old (9.5–14.3 %) thigh muscle groups;
* ``b_subvoxel_fat_needed``: the old subject's f that would give 87.7 % on its own (from the
  baseline's ratio), young f as in ``b``;
* ``c_imct_series``: the IMCT sheets of both subjects normal to the fibres (every fibre crosses them,
  in series) instead of containing them (in parallel), volumes held;
* ``c_imct_series_compliant``: as ``c_imct_series`` with connective tissue as compliant as fat
  (Table 1's fat constants C10, C20, C30 for ``connective_tissue``, both subjects);
* ``c_imct_parallel_compliant``: the baseline's layout (sheets containing the fibres) with that
  compliant connective tissue: the stiffness of the IMCT alone;
* ``combined``: ``a_dti_noise``, ``b_subvoxel_fat`` and ``c_imct_series_compliant`` together;
* ``d_outer_layer``: the aponeurosis thickened until the outer connective tissue (aponeurosis and
  skin) is the 37.3 / 31.2 cm³ that the paper's force per total volume implies.

Recorded per case: per subject F_max, the model's muscle / IMCT / IMAT volumes, nodes, the phantom's
truth volumes and what was changed; the ratio old/young of F_max per muscle volume in %
(``ratio_force_per_muscle_volume``); the fields of :mod:`_record`.

Run:  .venv/bin/python benchmarks/bench_example3.py [--cases NAME ...]     (all: ~30 min on 2 cores)
      .venv/bin/python benchmarks/bench_example3.py --figure                 (the figure from the record)
Results: benchmarks/results/bench_example3.json (``cases``: one row per candidate, merged by name);
figure docs/figures/example3_candidates.png.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _record import Run  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results" / "bench_example3.json"
WORK = ROOT / "out" / "bench_example3"
FIGURE = ROOT / "docs" / "figures" / "example3_candidates.png"
PAPER_RATIO = 100.0 * (37.74 / 61.89) / (68.76 / 98.93)
SHAPE = (96, 64, 25)
SEEDS = {"young": 1, "old": 2}
#: volumes held within this relative tolerance of the shipped phantom's (muscle, IMCT, IMAT)
VOLUME_TOL = 0.01
#: paper's Table 3 total volume implied by F_max / (force per total volume), minus Table 3's rows, cm³
OUTER_LAYER_CM3 = {"young": 68.76 / 0.430 - (98.93 + 2.83 + 20.86), "old": 37.74 / 0.294 - (61.89 + 6.15 + 29.15)}
#: sub-voxel fat fraction of the muscle voxels (Yoshiko et al. 2017, mid-points of the ranges)
SUBVOXEL_FAT = {"young": 0.067, "old": 0.119}
DTI_SNR_YOUNG = 25.0
DTI = {"bvalue": 500.0, "directions": 12, "b0": 1}
#: Table 1's fat constants (N/cm²) given to connective tissue for the compliant variant
COMPLIANT_CT = {"C10": 3.0, "C20": 8.0, "C30": 80.0}

CASES = ["shipped", "baseline", "a_dti_noise", "b_subvoxel_fat", "b_subvoxel_fat_needed", "c_imct_series",
         "c_imct_series_compliant", "c_imct_parallel_compliant", "combined", "d_outer_layer"]


def _young_architecture() -> dict:
    from pixmuscle.synth.mg import FASCICLE_CM, PENNATION_DEG

    return {"pennation_deg": PENNATION_DEG["young"], "fascicle_cm": FASCICLE_CM["young"]}


def phantom(subject: str, target: dict | None = None, **kw):
    """An MG phantom whose truth volumes are within :data:`VOLUME_TOL` of ``target``.

    Parameters
    ----------
    subject : {"young", "old"}
    target : dict, optional
        Volumes (cm³) to hold: ``muscle``, ``imct``, ``imat`` and optionally ``outer_ct``; none: the
        phantom as made from ``kw``.
    **kw
        Further :func:`pixmuscle.synth.mg.make_mg_phantom` arguments (architecture, IMCT layout).

    Returns
    -------
    (Phantom, dict)
        The phantom and its truth volumes (:func:`pixmuscle.synth.mg.tissue_volumes`), cm³.

    The cross-section scale, the IMCT / IMAT ratios and (for ``outer_ct``) the aponeurosis thickness
    are corrected by fixed-point iteration: volume ∝ scale², ratios ∝ the volume ratios, outer layer
    ∝ thickness.
    """
    from pixmuscle.synth.mg import _size_scale, make_mg_phantom, table3_ratios, tissue_volumes

    scale, ratios, apo = _size_scale(subject), dict(table3_ratios(subject)), 0.12
    for _ in range(15):
        ph = make_mg_phantom(subject, shape=SHAPE, seed=SEEDS[subject], dti_noise=0.0, size_scale=scale,
                             tissue_ratios=ratios, aponeurosis_cm=apo, **kw)
        v = tissue_volumes(ph)
        if target is None:
            return ph, v
        err = {k: v[k] / target[k] - 1.0 for k in target}
        if max(abs(e) for e in err.values()) <= VOLUME_TOL / 2:
            return ph, v
        for k in ("imct", "imat"):
            ratios[f"{k}_per_muscle"] *= (target[k] / target["muscle"]) / (v[k] / v["muscle"])
        scale *= np.sqrt(target["muscle"] / v["muscle"])
        if "outer_ct" in target:
            apo *= target["outer_ct"] / v["outer_ct"]
    raise RuntimeError(f"{subject}: volumes not within {VOLUME_TOL:.0%} of {target} after 15 iterations: {v}")


def _noisy_fibres(ph, snr: float, seed: int) -> tuple[np.ndarray, float]:
    """Fibres (I, J, K, 3) on the MRI grid from the phantom's noise-free DTI with Rician noise at ``snr``,
    and the mean angle (deg) to the true fibres over the muscle voxels."""
    from pixmuscle.imaging.dti import resample_tensor_to_grid, tensor_from_components
    from pixmuscle.imaging.dti_noise import acquisition, fibre_angle_deg, noisy_tensors
    from pixmuscle.segmentation.assemble import fiber_data
    from pixmuscle.stages.perturb import nearest_fill

    bvals, g = acquisition(DTI["bvalue"], DTI["directions"], DTI["b0"])
    d = noisy_tensors(tensor_from_components(ph.dti_tensor, "fsl"), snr, np.random.default_rng(seed),
                      bvals=bvals, gradients=g)
    d_grid, covered = resample_tensor_to_grid(d, ph.dti_affine, ph.labels.shape, ph.affine)
    valid, v, _ = fiber_data(d_grid, covered)
    muscle = ph.labels == 1
    v = nearest_fill(v, valid, muscle, ph.spacing)  # muscle voxels without fibre data: the nearest voxel's (cm)
    v = np.where(muscle[..., None], v, ph.fiber_true)
    return v, float(np.nanmean(fibre_angle_deg(v[muscle], ph.fiber_true[muscle])))


def _subjects(case: str, baseline_ratio: float | None) -> dict:
    """``{subject: (phantom, truth volumes cm³, what was changed (JSON-able), extra model inputs)}``."""
    series = case.startswith("c_imct_series") or case == "combined"
    fat = case.startswith("b_subvoxel_fat") or case == "combined"
    dti = case in ("a_dti_noise", "combined")
    shipped = {s: phantom(s)[1] for s in ("young", "old")}
    held = {s: {k: shipped[s][k] for k in ("muscle", "imct", "imat", "outer_ct")} for s in shipped}
    arch = {"young": {}, "old": _young_architecture()}
    out = {}
    for s in ("young", "old"):
        change, extra = {}, {}
        if case == "shipped":
            ph, v = phantom(s)
        elif series:
            ph, v = phantom(s, held[s], imct_layout="series", **arch[s])
            change["imct_layout"] = "series"
        elif case == "d_outer_layer":
            ph, v = phantom(s, dict(held[s], outer_ct=OUTER_LAYER_CM3[s]), **arch[s])
            change["outer_ct_cm3"] = round(OUTER_LAYER_CM3[s], 2)
            change["aponeurosis_cm"] = round(ph.params["aponeurosis_cm"], 4)
        else:
            ph, v = phantom(s, held[s] if s == "old" else None, **arch[s])
        if s == "old" and case != "shipped":
            change["architecture"] = "young (25 deg, 5.68 cm fascicles)"
        if case.endswith("_compliant") or case == "combined":
            change["connective_tissue"] = dict(COMPLIANT_CT)
        if fat:
            f = SUBVOXEL_FAT[s]
            if case == "b_subvoxel_fat_needed" and s == "old":
                f = 1.0 - (1.0 - SUBVOXEL_FAT["young"]) * PAPER_RATIO / baseline_ratio
            extra["contractile_fraction"] = 1.0 - f
            change["subvoxel_fat_fraction"] = round(f, 4)
        if dti:
            ff = {t: (shipped[t]["imat"] + SUBVOXEL_FAT[t] * shipped[t]["muscle"])
                  / (shipped[t]["muscle"] + shipped[t]["imat"]) for t in shipped}
            snr = DTI_SNR_YOUNG * (1 - ff[s]) / (1 - ff["young"])
            fib, angle = _noisy_fibres(ph, snr, seed=SEEDS[s])
            extra["fibres"] = fib
            change.update(dti_snr=round(snr, 2), fat_fraction=round(ff[s], 4), mean_fibre_angle_error_deg=round(angle, 2),
                          dti=dict(DTI))
        out[s] = (ph, v, change, extra)
    return out


def _case_config(case: str, subjects: dict) -> Path:
    """Write the subjects' inputs and the cohort config of one case; returns the config path."""
    import yaml

    from pixmuscle.imaging.nifti import save_volume
    from pixmuscle.synth import write_phantom

    folder = WORK / case
    entries = []
    for s, (ph, _, _, extra) in subjects.items():
        files = write_phantom(ph, folder / "data", s)
        fibres = files["fibers"]
        if "fibres" in extra:
            fibres = save_volume(folder / "data" / f"{s}_dti_fibres.nii.gz", extra["fibres"], ph.affine, kind="vectors")
        entry = {"name": s, "build_model": {"labels": str(files["labels"]), "fibers": str(fibres),
                                            "masks": {"aponeurosis": str(files["aponeurosis"])}}}
        if "contractile_fraction" in extra:
            img = np.where(ph.labels == 1, extra["contractile_fraction"], 1.0)
            path = save_volume(folder / "data" / f"{s}_contractile.nii.gz", img, ph.affine, kind="image")
            entry["solve"] = {"activation": {"image": str(path)}}
        entries.append(entry)
    solve = {"steps": 10, "activation": {"from": 0.0, "to": 0.95},
             "boundary_conditions": [{"nodes": "z_min", "fix": ["x", "y", "z"]},
                                     {"nodes": "z_max", "fix": ["x", "y", "z"]}],
             "newton": {"residual_tol": 1.0e-2, "energy_tol": 1.0e-2}}
    if case.endswith("_compliant") or case == "combined":
        solve["materials"] = {"connective_tissue": dict(COMPLIANT_CT)}
    cfg = {"title": f"Example 3 experiment: {case}", "synthetic": True, "output_dir": str(folder / "out"),
           "models": ["coarse"], "build_model": {}, "coarsen": {"factor": 2}, "solve": solve,
           "report": {"vtu": False, "slices": False, "view3d": False, "segmentation_qc": False},
           "subjects": entries}
    path = folder / "config.yaml"
    path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    return path


def run_case(case: str, baseline_ratio: float | None) -> dict:
    """Build, solve and report one case; its record row."""
    from pixmuscle.pipeline import run_pipeline

    record = Run(defaults=False, command=f".venv/bin/python benchmarks/bench_example3.py --cases {case}")
    t0 = time.perf_counter()
    subjects = _subjects(case, baseline_ratio)
    config = _case_config(case, subjects)
    ok = run_pipeline(config, force=True, workers=0)
    row = {"candidate": case, "ok": bool(ok), "wall_s": round(time.perf_counter() - t0, 1), "nodes": {},
           "subjects": {}}
    for s, (_, v, change, _) in subjects.items():
        summary = json.loads((WORK / case / "out" / s / "report" / "summary.json").read_text())
        q = summary["compared"]
        row["nodes"][s] = int(summary["n_nodes"])
        row["subjects"][s] = {"F_max_N": q["F_max"], "model_volumes_cm3": {k: q[k] for k in ("muscle", "imct", "imat")},
                              "force_per_muscle_volume_N_per_cm3": q["force_per_muscle_volume"],
                              "phantom_volumes_cm3": {k: round(x, 3) for k, x in v.items()}, "changed": change}
    y, o = (row["subjects"][s]["force_per_muscle_volume_N_per_cm3"] for s in ("young", "old"))
    row["ratio_force_per_muscle_volume"] = round(100.0 * o / y, 2)
    row.update(record.fields())
    return row


def _load() -> dict:
    if RESULTS.exists():
        return json.loads(RESULTS.read_text())
    return {"paper_ratio_force_per_muscle_volume": round(PAPER_RATIO, 2), "cases": []}


def figure(data: dict) -> Path:
    """Bar chart of the old/young ratio per candidate against the paper's → :data:`FIGURE`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for r in data["cases"] if r.get("ok")]
    names = [r["candidate"].replace("_", " ") for r in rows]
    vals = [r["ratio_force_per_muscle_volume"] for r in rows]
    fig, ax = plt.subplots(figsize=(7.5, 0.42 * len(rows) + 1.2), dpi=110)
    ax.barh(range(len(rows)), vals, color=["tab:gray" if r["candidate"] in ("shipped", "baseline") else "tab:blue"
                                          for r in rows])
    ax.axvline(100.0, color="k", lw=0.8)
    ax.axvspan(PAPER_RATIO - 3, PAPER_RATIO + 3, color="tab:red", alpha=0.12)
    ax.axvline(PAPER_RATIO, color="tab:red", ls="--", lw=1.2, label=f"paper {PAPER_RATIO:.1f} % (± 3 points shaded)")
    for i, v in enumerate(vals):
        ax.text(v + 0.4, i, f"{v:.1f} %", va="center", fontsize=8)
    ax.set_yticks(range(len(rows)), names, fontsize=8)
    ax.invert_yaxis()
    ax.set_xlim(min(80.0, min(vals) - 3), max(110.0, max(vals) + 5))
    ax.set_xlabel("old / young: F_max per unit muscle volume [%]")
    ax.set_title("Example 3 (SYNTHETIC MG phantoms, paper resolution): one candidate at a time", fontsize=9)
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    FIGURE.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(FIGURE)
    plt.close(fig)
    return FIGURE


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", default=CASES, choices=CASES)
    ap.add_argument("--figure", action="store_true", help="only draw the figure from the record")
    a = ap.parse_args(argv)
    data = _load()
    if a.figure:
        print(figure(data))
        return 0
    for case in a.cases:
        base = next((r for r in data["cases"] if r["candidate"] == "baseline"), None)
        if case == "b_subvoxel_fat_needed" and base is None:
            raise SystemExit("b_subvoxel_fat_needed needs the baseline's ratio: run --cases baseline first")
        row = run_case(case, base["ratio_force_per_muscle_volume"] if base else None)
        data["cases"] = [r for r in data["cases"] if r["candidate"] != case] + [row]
        data["cases"].sort(key=lambda r: CASES.index(r["candidate"]))
        RESULTS.parent.mkdir(parents=True, exist_ok=True)
        tmp = RESULTS.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(data, indent=2) + "\n")
        tmp.replace(RESULTS)
        print(f"{case}: old/young {row['ratio_force_per_muscle_volume']} % ({row['wall_s']} s)", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

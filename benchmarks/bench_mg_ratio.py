"""Why the old/young force per unit muscle volume of Example 3 comes out where it does.

One experiment per candidate cause, each changing one thing against the shipped MG phantoms
(``mg_young_small`` / ``mg_old_small`` settings: 96 × 64 × 8 voxels of 0.078 × 0.078 × 0.5 cm,
coarse model every 4th pixel). The models are built from the phantoms' truth labels and fibres
(``build_model.labels``), so segmentation errors play no part; the solve and report are the
shipped ones (both ends fixed, α 0 → 0.95).

* ``shipped``: IMCT sheets contain the fibres (in parallel with them), λ̂0 = 1;
* ``same_architecture``: the old MG with the young pennation (25°) and fascicle length;
* ``imct_series``: IMCT sheets normal to the fibres, which every fibre crosses (in series);
* ``lambda_opt_1.4``: λ̂0 = 1.4 (Blemker 2005): the image length lies on the ascending limb;
* ``imct_series_lambda_opt_1.4``: both.

Recorded per variant and subject: F_max, muscle volume, F_max / muscle volume, and the old/young
ratio of the latter (paper: (37.74 / 61.89) / (68.76 / 98.93) = 0.877). Figure:
``docs/figures/mg_old_young_ratio.png``.

Run:  .venv/bin/python benchmarks/bench_mg_ratio.py [--variants NAME ...] [--steps 10]
Results: benchmarks/results/bench_mg_ratio.json / .md (each run merged in).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _record import Run  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"
WORK = ROOT / "out" / "bench_mg_ratio"
FIGURE = ROOT / "docs" / "figures" / "mg_old_young_ratio.png"
PAPER_RATIO = (37.74 / 61.89) / (68.76 / 98.93)
SEEDS = {"young": 1, "old": 2}


def _variants():
    from pixmuscle.synth.mg import FASCICLE_CM, PENNATION_DEG

    young_arch = {"pennation_deg": PENNATION_DEG["young"], "fascicle_cm": FASCICLE_CM["young"]}
    series = {"imct_layout": "series"}
    l14 = {"materials": {"muscle": {"lambda_opt": 1.4}}}
    return {
        "shipped": ({}, {}, {}),
        "same_architecture": ({}, young_arch, {}),
        "imct_series": (series, series, {}),
        "lambda_opt_1.4": ({}, {}, l14),
        "imct_series_lambda_opt_1.4": (series, series, l14),
    }


def _case(name: str, young_kw: dict, old_kw: dict, solve_extra: dict, steps: int) -> Path:
    """Write the two phantoms and the cohort config of one variant; returns the config path."""
    import yaml

    from pixmuscle.synth import make_mg_phantom, write_phantom

    folder = WORK / name
    subjects = []
    for subject, kw in (("young", young_kw), ("old", old_kw)):
        ph = make_mg_phantom(subject, shape=(96, 64, 8), seed=SEEDS[subject], **kw)
        files = write_phantom(ph, folder / "data", subject)
        subjects.append({"name": subject, "build_model": {
            "labels": str(files["labels"]), "fibers": str(files["fibers"]),
            "masks": {"aponeurosis": str(files["aponeurosis"])}}})
    solve = {"steps": steps, "activation": {"from": 0.0, "to": 0.95},
             "boundary_conditions": [{"nodes": "z_min", "fix": ["x", "y", "z"]},
                                     {"nodes": "z_max", "fix": ["x", "y", "z"]}], **solve_extra}
    cfg = {"title": f"MG old/young experiment: {name}", "synthetic": True, "output_dir": str(folder / "out"),
           "models": ["coarse"], "build_model": {}, "coarsen": {"factor": 4}, "solve": solve,
           "report": {"vtu": False, "slices": False, "view3d": False, "segmentation_qc": False},
           "subjects": subjects}
    path = folder / "config.yaml"
    path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    return path


def run_variant(name: str, steps: int) -> dict:
    from pixmuscle.pipeline import run_pipeline

    young_kw, old_kw, solve_extra = _variants()[name]
    config = _case(name, young_kw, old_kw, solve_extra, steps)
    record = Run(defaults=name == "shipped" and steps == 10,
                 command=f".venv/bin/python benchmarks/bench_mg_ratio.py --variants {name} --steps {steps}")
    t0 = time.perf_counter()
    ok = run_pipeline(config, force=True, workers=0)
    wall = time.perf_counter() - t0
    fields = record.fields()
    rec = {"variant": name, "ok": bool(ok), "wall_s": round(wall, 1),
           "load_avg": [fields["load_average"]["before"][0], fields["load_average"]["after"][0]],
           "phantom": {"young": young_kw, "old": old_kw}, "solve": solve_extra, "steps": steps,
           "date_utc": fields["utc"][:16].replace("T", " "), **fields}
    for subject in ("young", "old"):
        s = json.loads((WORK / name / "out" / subject / "report" / "summary.json").read_text())
        q = s["compared"]
        rec[subject] = {"F_max_N": q["F_max"], "muscle_cm3": q["muscle"], "imct_cm3": q["imct"], "imat_cm3": q["imat"],
                        "force_per_muscle_volume": q["force_per_muscle_volume"],
                        "force_per_table3_volume": q["force_per_table3_volume"], "n_nodes": s["n_nodes"]}
    y, o = rec["young"]["force_per_muscle_volume"], rec["old"]["force_per_muscle_volume"]
    rec["old_over_young_force_per_muscle_volume"] = o / y if y else None
    return rec


def write(records: dict) -> None:
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "bench_mg_ratio.json").write_text(json.dumps(records, indent=2) + "\n")
    lines = ["## bench_mg_ratio: old/young force per unit muscle volume, one cause at a time", "",
             f"Paper: {PAPER_RATIO:.3f}. Models from the phantoms' truth labels, coarse (every 4th pixel), both ends fixed, "
             "α 0 → 0.95. Machine shared with other jobs (load average before/after).", "",
             "| variant | young F_max [N] | old F_max [N] | young F/V_muscle [N/cm³] | old F/V_muscle [N/cm³] | old/young | "
             "wall (s) | load | command |", "|---|---|---|---|---|---|---|---|---|"]
    for name, r in records.items():
        lines.append(f"| {name} | {r['young']['F_max_N']:.4g} | {r['old']['F_max_N']:.4g} | "
                     f"{r['young']['force_per_muscle_volume']:.4g} | {r['old']['force_per_muscle_volume']:.4g} | "
                     f"**{r['old_over_young_force_per_muscle_volume']:.3f}** | {r['wall_s']} | {r['load_avg'][0]}/{r['load_avg'][1]} | "
                     f"`python benchmarks/bench_mg_ratio.py --variants {name} --steps {r['steps']}` |")
    (RESULTS / "bench_mg_ratio.md").write_text("\n".join(lines) + "\n")
    _figure(records)


def _figure(records: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(records)
    vals = [records[n]["old_over_young_force_per_muscle_volume"] for n in names]
    fig, ax = plt.subplots(figsize=(7.5, 3.6), dpi=110)
    ax.barh(range(len(names)), vals, color="tab:blue")
    ax.axvline(1.0, color="k", lw=0.8)
    ax.axvline(PAPER_RATIO, color="tab:red", ls="--", lw=1.2, label=f"paper {PAPER_RATIO:.3f}")
    for i, v in enumerate(vals):
        ax.text(v + 0.005, i, f"{v:.3f}", va="center", fontsize=8)
    ax.set_yticks(range(len(names)), [n.replace("_", " ") for n in names], fontsize=8)
    ax.invert_yaxis()
    ax.set_xlim(min(0.7, min(vals) - 0.05), max(1.2, max(vals) + 0.08))
    ax.set_xlabel("old / young: F_max per unit muscle volume [-]")
    ax.set_title("Example 3 (SYNTHETIC MG phantoms): one cause changed at a time", fontsize=9)
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    FIGURE.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(FIGURE)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--variants", nargs="+", default=list(_variants()), choices=list(_variants()))
    ap.add_argument("--steps", type=int, default=10)
    a = ap.parse_args(argv)
    path = RESULTS / "bench_mg_ratio.json"
    records = json.loads(path.read_text()) if path.exists() else {}
    for name in a.variants:
        records[name] = run_variant(name, a.steps)
        write(records)
        print(name, records[name]["old_over_young_force_per_muscle_volume"], records[name]["wall_s"], "s", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Figures of docs/examples.md, drawn from the results of a finished example run (no solve).

Reads each subject's ``results_coarse.h5`` of an example config (the run of
``benchmarks/bench_examples.py EXAMPLE``) with pixmuscle's results reader, computes the end force
per step as the report does (mean axial reaction of the force sets, converged steps only) and plots
force against activation with the reference F_max of each subject (``report.reference_values`` of
the config: the paper's Table 3) marked at the last activation.

Run:  .venv/bin/python benchmarks/fig_examples.py mg_young_old
Writes: docs/figures/example3_force_activation.png (a few seconds: reads two files, no solve).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
FIGURES = ROOT / "docs" / "figures"
EXAMPLES = {"mg_young_old": ("configs/mg_young_old.yaml", "example3_force_activation.png")}


def subject_curves(config: Path) -> list[dict]:
    """Force–activation curve of every subject of a cohort config, read from its coarse results.

    Returns
    -------
    list of dict
        ``name``, ``alpha`` (S+1,), ``force_N`` (S+1,; NaN at unconverged steps), ``n_nodes``,
        ``reference_F_max_N`` (float or None).
    """
    import yaml

    from pixmuscle.io.results import load_results
    from pixmuscle.report.curves import axial_forces, end_force, select_force_sets

    raw = yaml.safe_load(config.read_text())
    out = (config.parent / raw["output_dir"]).resolve()
    curves = []
    for sub in raw["subjects"]:
        path = out / sub["name"] / "results_coarse.h5"
        if not path.exists():
            raise SystemExit(f"{path}: not found — run `python benchmarks/bench_examples.py` for {config.name} first")
        res = load_results(path)
        sets = select_force_sets(res.reaction, None, res.constrained_text())
        force = end_force(axial_forces(res.reaction, sets), res.n_states)
        force = np.where(np.asarray(res.converged, bool), force, np.nan)
        ref = ((sub.get("report") or {}).get("reference_values") or {}).get("F_max")
        curves.append({"name": sub["name"], "alpha": np.asarray(res.alpha, float), "force_N": force,
                       "n_nodes": res.model.n_nodes, "reference_F_max_N": ref})
    return curves


def plot(curves: list[dict], title: str, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2), dpi=110)
    for k, c in enumerate(curves):
        color = f"C{k}"
        f_max = np.nanmax(c["force_N"])
        ax.plot(c["alpha"], c["force_N"], "o-", color=color, ms=4,
                label=f"{c['name']}, pixmuscle ({c['n_nodes']:,} nodes): F_max {f_max:.4g} N")
        if c["reference_F_max_N"] is not None:
            a_end = float(c["alpha"][-1])
            ax.plot([a_end], [c["reference_F_max_N"]], "*", color=color, ms=13, mec="k", mew=0.6,
                    label=f"{c['name']}, paper Table 3: F_max {c['reference_F_max_N']:.4g} N")
            ax.axhline(c["reference_F_max_N"], color=color, ls=":", lw=0.9)
    ax.set_xlabel("activation α [-]")
    ax.set_ylabel("end force [N] (mean of both fixed ends)")
    ax.set_xlim(left=0.0)
    ax.set_ylim(bottom=0.0)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7.5, loc="upper left")
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("example", choices=sorted(EXAMPLES))
    a = ap.parse_args(argv)
    config, name = EXAMPLES[a.example]
    curves = subject_curves(ROOT / config)
    title = ("Example 3 at the paper's resolution: SYNTHETIC phantoms, coarse models (0.156 cm)\n"
             "stars and dotted lines: the paper's F_max at the highest activation (Table 3)")
    print(plot(curves, title, FIGURES / name))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""The tables of measured figures in README.md and docs/*.md, made from ``benchmarks/results/*.json``.

A page holds a generated table between two markers::

    <!-- records:NAME -->
    ...                      (written by this script; edits inside are overwritten)
    <!-- /records:NAME -->

where NAME is a key of :data:`TABLES`. Each table says which record file and which command made
its rows; rows made before the shipped defaults last changed (``"superseded"``) are left out of the
tables of today's defaults and listed under them with the command that remakes them.

Usage::

    make docs-tables                                   # rewrite every marked block
    .venv/bin/python benchmarks/docs_tables.py --check # exit 1 when a page differs from its records

``tests/test_docs_tables.py`` runs the check.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
BLOCK = re.compile(r"(<!-- records:(?P<name>[\w-]+) -->\n)(?P<body>.*?)(<!-- /records:(?P=name) -->)", re.S)
SOLVE = "benchmarks/results/bench_solve.json"
EXAMPLES = "benchmarks/results/bench_examples.json"


def _load(rel: str):
    return json.loads((ROOT / rel).read_text())


def _minutes(s: float) -> str:
    return f"{s:,.0f} s" if s < 120 else f"{s:,.0f} s ({s / 60:.1f} min)"


def _load_text(r: dict) -> str:
    la = r.get("load_average")
    if isinstance(la, dict):
        before, after = la.get("before", la.get("start")), la.get("after", la.get("end"))
        return f"{before[0]:.1f} → {after[0]:.1f}"
    return "—"


def _made(r: dict) -> str:
    """The commit a row was made at, or — for older rows — nothing known."""
    return r["commit"][:10] if r.get("commit") else "—"


def _pixels(r: dict) -> str:
    return f"{r['spacing_cm'][0]:g} cm"


def _stale(rows: list[dict], what: str, command) -> list[str]:
    """Lines listing rows left out because the defaults changed after them, each with its re-run."""
    if not rows:
        return []
    lines = ["", f"Not shown, {what} made before the last change of the defaults (to be remade):"]
    lines += [f"- {command(r)}: {r['superseded']}." for r in rows]
    return lines


def sweeps(default: bool = True) -> str:
    """Whole activation sweeps of the synthetic leg (bench_solve.json) at today's defaults, or (``default``
    False) at other settings measured since the defaults last changed."""
    cases = [c for c in _load(SOLVE)["cases"] if "error" not in c and c.get("status") == "complete"]
    rows = [c for c in cases if bool(c.get("defaults")) == default and not c.get("superseded")]
    rows.sort(key=lambda c: (c["nodes"], c.get("case", "")))
    head = ("| nodes | pixel | case | Newton its per step | Krylov its (per Newton system) | multigrid builds | whole sweep "
            "| peak memory | F_z(z_max) at α = 0.95 | load avg before → after |")
    lines = [head, "|---" * (head.count("|") - 1) + "|"]
    for c in rows:
        its = c["newton_iterations_per_step"][1:]
        kry = (f"{c['krylov_iterations_total']:,} ({c['krylov_iterations_total'] / max(c['newton_iterations_total'], 1):.1f})"
               if c.get("krylov_iterations_total") else "—")
        builds = c.get("preconditioner_builds")
        build_s = c.get("preconditioner_build_s")
        build_txt = "—" if not builds else (f"{builds} ({', '.join(f'{x:.0f}' for x in build_s)} s)"
                                            if isinstance(build_s, list) else str(builds))
        lines.append(f"| {c['nodes']:,} | {_pixels(c)} | `{c.get('case', c['size'] + ':' + c['backend'])}` | "
                     f"{', '.join(map(str, its))} | {kry} | {build_txt} | **{_minutes(c['sweep_s'])}** | "
                     f"**{c['peak_rss_GB']:.2f} GB** | {c['force_z_max_N'][-1]:.3f} N | {_load_text(c)} |")
    if not rows:
        lines.append("| (none recorded at these settings since the defaults last changed) | | | | | | | | | |")
    lines += ["", f"Record: `{SOLVE}`, rows with `\"defaults\": {str(default).lower()}` and no `superseded`; each row's "
              "command is in it, e.g. `.venv/bin/python benchmarks/bench_solve.py --append --cases "
              + ("75k:auto" if default else "5k:mixed_amg") + "`. α 0 → 0.95 in 10 load steps, 2 cores."]
    if default:
        lines += _stale([c for c in cases if c.get("defaults") and c.get("superseded")], "the default sweep",
                        lambda c: f"{c['nodes']:,} nodes (`.venv/bin/python benchmarks/bench_solve.py --append --cases "
                                  f"{c.get('case', c['size'] + ':auto')}`, {c['sweep_s']:g} s then)")
    return "\n".join(lines)


def sweeps_other() -> str:
    return sweeps(default=False)


def first_system() -> str:
    """The first Newton system's Krylov iterations at each size at the default solver (conditioning records)."""
    order = ["5k", "20k", "20k-fine", "75k", "75k-fine", "295k"]
    lines = ["| model | nodes | pixel | FGMRES its (Newton's mixed update) | its, condensed stop | set-up | solve | made |",
             "|---|---|---|---|---|---|---|---|"]
    files = []
    for size in order:
        rel = f"benchmarks/results/bench_solve_conditioning_{size}.json"
        if not (ROOT / rel).exists():
            continue
        rec = _load(rel)
        rows = [r for r in rec["rows"] if r.get("default") and r.get("bulk_scale") == 1.0]
        if not rows:
            continue
        r = rows[-1]
        files.append(rel.rsplit("/", 1)[1])
        pixel = "0.078 cm" if size.endswith("fine") or size == "295k" else "0.156 cm"
        made = "since the last change of the defaults" if not r.get("superseded") else r["superseded"].split(" changed")[0]
        lines.append(f"| `{size}` | {rec['nodes']:,} | {pixel} | **{r.get('krylov_iterations_mixed', '—')}** | "
                     f"{r['krylov_iterations']} | {r['setup_s']} s | {r.get('mixed_solve_s', r['solve_s'])} s | {made} |")
    lines += ["", "Records: `benchmarks/results/` " + ", ".join(f"`{f}`" for f in files) + " (the last row with "
              "`\"default\": true` at the tissues' own bulk moduli); command per row in the record, e.g. "
              "`.venv/bin/python benchmarks/bench_solve.py --conditioning 75k --append --variants "
              "projected:2,2,3:mixed_amg:own --scales 1`. The first load step (α = 0.095), FGMRES to 10⁻⁶."]
    return "\n".join(lines)


def _example(key: str) -> dict | None:
    return _load(EXAMPLES).get(key)


def _example_head(r: dict, key: str) -> list[str]:
    peak = f", peak memory {r['peak_rss_GB']} GB" if r.get("peak_rss_GB") is not None else ", peak memory not recorded"
    wall = r.get("wall_s") or sum(s["wall_s"] for s in r.get("stages", []))
    lines = [f"Record: `{EXAMPLES}` entry `{key}`, made {r['date_utc']} UTC by `{r['command']}`: the whole run "
             f"{_minutes(wall)}{peak}."]
    if r.get("superseded"):
        lines.append(f"**This record was {r['superseded']}**; `.venv/bin/python benchmarks/bench_examples.py {key}` "
                     "remakes it at today's defaults and `make docs-tables` this table.")
    return lines


def example2(key: str = "lower_leg") -> str:
    """Example 2 (configs/lower_leg.yaml, or its small variant): coarse and fine model, from bench_examples.json."""
    r = _example(key)
    if r is None:
        return f"No record yet: `.venv/bin/python benchmarks/bench_examples.py {key}`."
    ell = any(m.get("non_elliptic_nodes") is not None for m in r["models"].values())
    lines = ["| model | nodes | Newton iterations | FGMRES iterations | F_max | solve (solver's clock) |"
             + (" nodes past strong ellipticity at the last step |" if ell else ""),
             "|---|---|---|---|---|---|" + ("---|" if ell else "")]
    for name, m in r["models"].items():
        lines.append(f"| {name} | {m['nodes']:,} | {m['newton_iterations']} | {m['krylov_iterations']:,} | "
                     f"{m['F_max_N']:.1f} N | {_minutes(m['solve_s'])} |"
                     + (f" {m.get('non_elliptic_nodes', '—'):,} |" if ell else ""))
    conv = next((e["convergence"] for e in r["reports"].values() if e.get("convergence")), None)
    lines.append("")
    if conv:
        d = conv["F_max_relative_difference"]["coarse"]
        lines.append(f"F_max of the coarse model differs from the fine one's by {100 * d:.2f} % (largest over the "
                     f"ramp {100 * conv['max_relative_difference']['coarse']:.2f} %).")
    return "\n".join(lines + _example_head(r, key))


#: Example 3 as printed in the paper (Table 3 and its forces; bracketed values are implied, not printed)
PAPER_EXAMPLE3 = {"muscle": (98.93, 61.89), "imat": (2.83, 6.15), "imct": (20.86, 29.15), "aponeurosis": (None, None),
                  "table3_total": (159.9, 128.4), "F_max": (68.76, 37.74), "force_per_table3_volume": (0.430, 0.294),
                  "force_per_muscle_volume": (0.695, 0.610)}
#: the paper's old/young ratios as it states them (from its unrounded figures), where they differ from the rounded ones'
PAPER_RATIO = {"muscle": "62.5 %", "table3_total": "(80.3 %)", "force_per_muscle_volume": "87.7 %"}


def example3(key: str = "mg_young_old") -> str:
    """Example 3 (configs/mg_young_old.yaml, or its small variant): both subjects against the paper, from
    bench_examples.json."""
    r = _example(key)
    if r is None:
        return f"No record yet: `.venv/bin/python benchmarks/bench_examples.py {key}`."
    q = {path.split("/")[-2]: e["compared"] for path, e in r["reports"].items()}
    y, o = q["young"], q["old"]
    rows = [("muscle [cm³]", "muscle", ".2f"), ("IMAT [cm³]", "imat", ".3f"),
            ("IMCT, without the aponeurosis [cm³]", "imct", ".2f"), ("aponeurosis [cm³]", "aponeurosis", ".2f"),
            ("Table 3 total: muscle + IMAT + IMCT + aponeurosis [cm³]", "table3_total", ".1f"),
            ("F_max [N]", "F_max", ".2f"), ("F_max / Table 3 total volume [N/cm³]", "force_per_table3_volume", ".3f"),
            ("F_max / muscle volume [N/cm³]", "force_per_muscle_volume", ".3f")]

    def paper(v):
        return "—" if v is None else (f"({v:g})" if isinstance(v, float) and v > 100 else f"{v:g}")

    lines = ["| | young | paper | old | paper | old / young | paper |", "|---|---|---|---|---|---|---|"]
    for label, q_key, fmt in rows:
        py, po = PAPER_EXAMPLE3[q_key]
        ratio = f"{100 * o[q_key] / y[q_key]:.1f} %"
        pratio = PAPER_RATIO.get(q_key) or ("—" if py is None else f"{100 * po / py:.1f} %")
        if q_key in ("F_max", "force_per_muscle_volume"):
            ratio, pratio = f"**{ratio}**", f"**{pratio}**"
        lines.append(f"| {label} | {y[q_key]:{fmt}} | {paper(py)} | {o[q_key]:{fmt}} | {paper(po)} | {ratio} | {pratio} |")
    nodes = {path.split("/")[-2]: e["n_nodes"] for path, e in r["reports"].items()}
    lines += ["", f"Bracketed: implied by the paper's F_max and force per total volume, not printed. Solved on the "
                  f"coarse models, {nodes['young']:,} (young) and {nodes['old']:,} (old) nodes."]
    return "\n".join(lines + [""] + _example_head(r, key))


#: what each Example 3 candidate changes (bench_example3.py's CASES), for the table
EXAMPLE3_CANDIDATES = {
    "shipped": "the old MG with the architecture of Narici et al. 2003 (pennation 21.75° against 25°, fascicles −10 %)",
    "baseline": "the old MG with the young architecture; every other row changes one thing against this one",
    "a_dti_noise": "(a) fibres from noisy DTI: young at SNR 25, old at the SNR its fat fraction leaves",
    "b_subvoxel_fat": "(b) fat below the voxel size: contractile fraction 1 − f, f = 6.7 % young, 11.9 % old",
    "b_subvoxel_fat_needed": "(b) as above, with the old f that would give 87.7 % alone",
    "c_imct_series": "(c) IMCT sheets normal to the fibres (in series) in both subjects",
    "c_imct_series_compliant": "(c) as above, connective tissue as compliant as fat",
    "c_imct_parallel_compliant": "the baseline's sheets (in parallel), connective tissue as compliant as fat",
    "combined": "(a), (b) and (c, compliant) together",
    "d_outer_layer": "(d) outer layer (aponeurosis and skin) at the paper's implied 37.3 / 31.2 cm³",
}


def example3_candidates() -> str:
    """Example 3's old/young force per muscle volume, one candidate at a time (bench_example3.json)."""
    path = "benchmarks/results/bench_example3.json"
    if not (ROOT / path).exists():
        return "No record yet: `.venv/bin/python benchmarks/bench_example3.py`."
    r = _load(path)
    lines = ["| candidate | what it changes | nodes young / old | F_max young / old [N] | old / young, F_max per "
             "muscle volume |", "|---|---|---|---|---|"]
    for c in r["cases"]:
        y, o = c["subjects"]["young"], c["subjects"]["old"]
        what = EXAMPLE3_CANDIDATES.get(c["candidate"], "")
        f = o["changed"].get("subvoxel_fat_fraction")
        if c["candidate"] == "b_subvoxel_fat_needed" and f is not None:
            what = what.replace("the old f", f"the old f = {100 * f:.1f} %")
        if c["candidate"] == "a_dti_noise":
            what += (f" (SNR {y['changed']['dti_snr']:g} / {o['changed']['dti_snr']:g}, mean fibre error "
                     f"{y['changed']['mean_fibre_angle_error_deg']:.1f}° / {o['changed']['mean_fibre_angle_error_deg']:.1f}°)")
        lines.append(f"| `{c['candidate']}` | {what} | {c['nodes']['young']:,} / {c['nodes']['old']:,} | "
                     f"{y['F_max_N']:.1f} / {o['F_max_N']:.1f} | **{c['ratio_force_per_muscle_volume']:.1f} %** |")
    loads = [c["load_average"]["before"][0] for c in r["cases"]]
    lines += ["", f"Paper: **{r['paper_ratio_force_per_muscle_volume']:.1f} %**. Record `{path}`, rows made by "
                  f"`.venv/bin/python benchmarks/bench_example3.py --cases NAME` at {_made(r['cases'][-1])} "
                  f"({r['cases'][0]['utc'][:10]}, load average {min(loads):.1f}–{max(loads):.1f} at their starts)."]
    return "\n".join(lines)


def example3_uncertainty(key: str = "mg_young_old_uncertainty") -> str:
    """Example 3's force per muscle volume with its 95 % prediction interval per subject (bench_examples.json)."""
    r = _example(key)
    if r is None:
        return f"No record yet: `.venv/bin/python benchmarks/bench_examples.py {key}`."
    lines = ["| subject | realisations | F_max noise-free | F_max mean [95 % interval] | F_max / muscle volume "
             "noise-free | mean [95 % interval] |", "|---|---|---|---|---|---|"]
    u = {k.split(" ", 1)[1]: v for k, v in r.items() if k.startswith("uncertainty ")}
    for s in ("young", "old"):
        if s not in u:
            continue
        q = u[s]
        lines.append(f"| {s} | {q['realisations']} | {q['noise_free_F_max_N']:.1f} N | {q['F_max_mean_N']:.1f} "
                     f"[{q['ci95_low_N']:.1f}, {q['ci95_high_N']:.1f}] N | "
                     f"{q['noise_free_force_per_muscle_volume_N_per_cm3']:.3f} N/cm³ | "
                     f"{q['force_per_muscle_volume_mean_N_per_cm3']:.3f} "
                     f"[{q['force_per_muscle_volume_ci95_low_N_per_cm3']:.3f}, "
                     f"{q['force_per_muscle_volume_ci95_high_N_per_cm3']:.3f}] N/cm³ |")
    if {"young", "old"} <= set(u):
        y, o = u["young"], u["old"]
        lines += ["", f"Old / young, force per muscle volume: noise-free "
                      f"{100 * o['noise_free_force_per_muscle_volume_N_per_cm3'] / y['noise_free_force_per_muscle_volume_N_per_cm3']:.1f} %, "
                      f"of the realisations' means "
                      f"{100 * o['force_per_muscle_volume_mean_N_per_cm3'] / y['force_per_muscle_volume_mean_N_per_cm3']:.1f} %."]
    return "\n".join(lines + _example_head(r, key))


def bias_field() -> str:
    """Segmentation Dice under a bias field, with and without N4 (bench_bias_field.json)."""
    r = _load("benchmarks/results/bench_bias_field.json")
    lines = ["| phantom | bias field | correction | outline | bone | fat | connective tissue | muscles (mean / lowest) |",
             "|---|---|---|---|---|---|---|---|"]
    for c in r["cases"]:
        d = c["dice"]
        lines.append(f"| {c['phantom']} {' × '.join(map(str, c['shape']))} | ±{c['bias_amplitude'] * 100:.0f} % | "
                     f"{c['bias_correction']} | {d['outline']:.3f} | {d['bone']:.3f} | {d['fat']:.3f} | "
                     f"{d['connective_tissue']:.3f} | {d['muscle_mean']:.3f} / {d['muscle_min']:.3f} |")
    lines += ["", f"Dice against the phantoms' truth. Record `benchmarks/results/bench_bias_field.json`, made by "
                  f"`{r['command']}` at {_made(r)} ({r['utc'][:10]}, load average {_load_text(r)})."]
    return "\n".join(lines)


def memory() -> str:
    """Where a solve's memory goes: phases and owners of the first Newton system (bench_memory.json)."""
    r = _load("benchmarks/results/bench_memory.json")
    lines = ["| model | nodes | phase | wall | resident after | peak during |", "|---|---|---|---|---|---|"]
    for c in r["cases"]:
        for p in c["phases"]:
            lines.append(f"| `{c['size']}` | {c['nodes']:,} | {p['phase']} | {p['wall_s']} s | {p['rss_after_GB']:.2f} GB | "
                         f"{p['peak_GB']:.2f} GB |")
    lines += ["", "| model | owner (numpy arrays and sparse matrices, each counted once) | GB |", "|---|---|---|"]
    for c in r["cases"]:
        top = sorted(((k, v) for k, v in c["owners_detail_GB"].items() if k.count(".") == 1 and "[" not in k),
                     key=lambda kv: -kv[1])[:8]
        for k, v in top:
            lines.append(f"| `{c['size']}` | `{k}` | {v:.3f} |")
        lines.append(f"| `{c['size']}` | not held by numpy (factors of the region solves, libraries, Python, free pages) "
                     f"| {c['not_numpy_GB']:.3f} |")
        lines.append(f"| `{c['size']}` | BoomerAMG worker process(es), peak | {sum(c['amg_workers_peak_GB']):.3f} |")
    last = r["cases"][-1]
    lines += ["", "Per displacement unknown: " + "; ".join(
        f"`{c['size']}` {c['kB_per_dof']['with_workers']:.1f} kB at the peak (workers included), "
        f"{c['kB_per_dof']['numpy_owned']:.1f} kB held in numpy arrays" for c in r["cases"]) + ".",
        f"Record `benchmarks/results/bench_memory.json`, made by `{last['command']}` at {_made(last)} "
        f"({last['utc'][:10]}, load average {_load_text(last)})."]
    return "\n".join(lines)


def memory_change() -> str:
    """The memory of the first Newton system now and at each earlier record of it (bench_memory.json ``before``, oldest first)."""
    r = _load("benchmarks/results/bench_memory.json")
    if not r.get("before"):
        return "No earlier record in `benchmarks/results/bench_memory.json` (key `before`)."

    def peak(c):
        return max(p["peak_GB"] for p in c["phases"]) + sum(c["amg_workers_peak_GB"])

    lines = ["| model | nodes | | peak, workers included | per unknown | held in numpy arrays | not held by numpy | made at |",
             "|---|---|---|---|---|---|---|---|"]
    for c in r["cases"]:
        rows = [("before", b) for b in r["before"] if b["size"] == c["size"]] + [("now", c)]
        for label, x in rows:
            lines.append(f"| `{c['size']}` | {c['nodes']:,} | {label} | {peak(x):.2f} GB | "
                         f"{x['kB_per_dof']['with_workers']:.1f} kB | {x['kB_per_dof']['numpy_owned']:.1f} kB | "
                         f"{x['not_numpy_GB']:.2f} GB | {_made(x)} |")
    lines += ["", "Record `benchmarks/results/bench_memory.json`: every row of a model made by `.venv/bin/python benchmarks/bench_memory.py SIZE` (`--keep-before` adds "
                  "the row it replaces to the record's `before` list, oldest first); the peak is the largest phase peak of the main "
                  "process plus the BoomerAMG workers' peaks; per unknown: per displacement degree of freedom."]
    return "\n".join(lines)


def backends() -> str:
    """Serial mixed_amg / direct against petsc_mixed under mpiexec on one model (bench_backends.json)."""
    path = "benchmarks/results/bench_backends.json"
    if not (ROOT / path).exists():
        return "No record yet: `.venv/bin/python benchmarks/bench_backends.py`."
    r = _load(path)
    sys.path.insert(0, str(ROOT))
    from pixmuscle.preflight import estimate_solve

    lines = ["| backend | ranks | wall | peak per rank (largest) | all ranks | Newton its | Krylov its | builds | F_max | "
             "today's estimate (`preflight.estimate_solve`) | made at |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for c in sorted(r["cases"], key=lambda c: (c["backend"] != "mixed_amg", c["backend"], c["ranks"])):
        if c.get("exit"):
            lines.append(f"| `{c['backend']}` | {c['ranks']} | failed (exit {c['exit']}) | | | | | | | | |")
            continue
        lines.append(f"| `{c['backend']}` | {c['ranks']} | {c['wall_s']:.0f} s | {c['peak_rss_GB_per_rank_max']:.2f} GB | "
                     f"{c['peak_rss_GB']:.2f} GB | {c['newton_iterations']} | {c['krylov_iterations'] or '—'} | "
                     f"{c['preconditioner_builds'] or '—'} | {c['force_z_max_N']:.4f} N | "
                     f"{estimate_solve(c['nodes'], c['steps'])[0]:.0f} s | {_made(c)} |")
    c0 = r["cases"][0]
    loads = [c["load_average"]["before"][0] for c in r["cases"] if "load_average" in c]
    lines += ["", f"Model `{r['model']}` ({c0.get('nodes', 0):,} nodes, the fine model of `configs/lower_leg_small.yaml`), "
                  f"{c0['steps']} load steps to α = 0.95. Record `{path}`, made by `.venv/bin/python "
                  f"benchmarks/bench_backends.py --cases BACKEND:RANKS` (load average "
                  f"{min(loads):.1f}–{max(loads):.1f} at the cases' starts)."]
    return "\n".join(lines)


def _rel_diff(a: list, b: list) -> float:
    """Largest relative difference of two force histories (relative to the largest force of ``b``)."""
    import numpy as np

    a, b = np.asarray(a, float), np.asarray(b, float)
    return float(np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-300))


def scaling() -> str:
    """The distributed solve under mpiexec: weak scaling and the refined leg on two ranks (bench_weak_scaling.json)."""
    path = "benchmarks/results/bench_weak_scaling.json"
    if not (ROOT / path).exists():
        return "No record yet: `.venv/bin/python benchmarks/bench_scaling.py`."
    r = _load(path)
    lines = ["| model | ranks | nodes | per rank | held by rank 0 | peak per rank (largest) | all ranks | Krylov its per "
             "Newton system (mean, max) | Newton its | sweep | F_z(z_max) at α = 0.95 | load avg before → after | made at |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    order = {"37k": 0, "75k": 1, "150k": 2, "295k": 3}
    serial = {c["size"]: c for c in r["cases"] if c.get("backend") == "auto" and not c.get("exit")}
    for c in sorted(r["cases"], key=lambda c: (order.get(c["size"], 9), c.get("backend") == "petsc_mixed", c["ranks"])):
        ranks = "1, serial `auto`" if c.get("backend") == "auto" else str(c["ranks"])
        if c.get("exit"):
            lines.append(f"| `{c['size']}` | {ranks} | failed (exit {c['exit']}) | | | | | | | | | | |")
            continue
        its = c["krylov_iterations_per_system"]
        wall = _minutes(c["wall_s"]) + (" (oversubscribed)" if c["ranks"] > c["machine"]["cpus"] else "")
        resumed = f", resumed after step {c['resumed_after_step']}" if c.get("resumed_after_step") is not None else ""
        lines.append(f"| `{c['size']}` | {ranks} | {c['nodes']:,} | {c['nodes'] // c['ranks']:,} | "
                     f"{c['held_nodes_rank0'] or c['nodes']:,} | **{c['peak_rss_GB_per_rank_max']:.2f} GB** | "
                     f"{c['peak_rss_GB']:.2f} GB | {sum(its) / max(len(its), 1):.1f}, {max(its, default=0)} | "
                     f"{sum(c['newton_iterations_per_step'])} | {wall}{resumed} | {c['force_z_max_N'][-1]:.3f} N | "
                     f"{_load_text(c)} | {_made(c)} |")
    lines += ["", f"Record `{path}`; each row's command is in it, e.g. `.venv/bin/python benchmarks/bench_scaling.py "
                  "--cases 75k:2`. `petsc_mixed` through `mpiexec -n P pixmuscle solve`, every other setting at its "
                  "default; α 0 → 0.95 in 10 load steps; peak per rank: each rank's own high-water mark at its exit (`VmHWM`; older rows: `RUSAGE_SELF`). "
                  "Serial `auto` rows: `pixmuscle solve` of the same model at the shipped defaults in one process, "
                  "its peak the largest sampled memory of its process tree (the BoomerAMG worker included)."]
    ratios = [f"`{c['size']}` on {c['ranks']} ranks {c['peak_rss_GB_per_rank_max'] / serial[c['size']]['peak_rss_GB']:.2f} ×, "
              f"wall time {c['wall_s'] / serial[c['size']]['wall_s']:.2f} ×, F_z to "
              f"{_rel_diff(c['force_z_max_N'], serial[c['size']]['force_z_max_N']):.0e}"
              for c in r["cases"] if c.get("backend") == "petsc_mixed" and not c.get("exit") and c["size"] in serial]
    if ratios:
        lines += ["", "Largest rank's peak against the serial run's of the same model: " + "; ".join(ratios) + "."]
    model = r.get("memory_model")
    if model:
        lines += ["", f"Memory model (least squares over the rows above): peak per rank ≈ {model['base_GB']:.2f} GB + "
                      f"{model['kB_per_held_node']:.1f} kB × the nodes the rank holds. "
                      + " ".join(f"A {p['nodes']:,}-node leg ({p['what']}) on {p['ranks']} ranks: each rank holds up "
                                 f"to {p['held_max']:,} nodes, so ≈ {p['GB_per_rank']:.1f} GB per rank."
                                 for p in model.get("predictions", []))]
    return "\n".join(lines)


#: NAME → function making the block's text (without the markers)
TABLES = {"sweeps": sweeps, "sweeps-other": sweeps_other, "first-system": first_system,
          "example2": example2, "example3": example3, "bias-field": bias_field,
          "memory": memory, "example2-small": lambda: example2("lower_leg_small"),
          "example2-elliptic": lambda: example2("lower_leg_elliptic"),
          "example3-small": lambda: example3("mg_young_old_small"),
          "example3-candidates": example3_candidates, "example3-uncertainty": example3_uncertainty,
          "memory-change": memory_change, "backends": backends, "scaling": scaling}


def render(text: str) -> str:
    """``text`` with every marked block rewritten from the records (an unknown NAME is an error)."""
    def block(m):
        name = m.group("name")
        if name not in TABLES:
            raise KeyError(f"<!-- records:{name} -->: no such table (known: {', '.join(TABLES)})")
        return f"{m.group(1)}{TABLES[name]()}\n{m.group(4)}"

    return BLOCK.sub(block, text)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="write nothing; exit 1 when a page differs from its records")
    args = ap.parse_args(argv)
    stale = []
    for page in PAGES:
        text = page.read_text()
        new = render(text)
        if new != text:
            stale.append(page.relative_to(ROOT))
            if not args.check:
                page.write_text(new)
    verb = "differ from their records" if args.check else "rewritten"
    print(f"{len(stale)} page(s) {verb}" + (": " + ", ".join(map(str, stale)) if stale else ""))
    return 1 if args.check and stale else 0


if __name__ == "__main__":
    sys.exit(main())

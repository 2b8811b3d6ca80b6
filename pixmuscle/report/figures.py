"""The report's figures, in one registry: each entry says where on the page it goes and how it is made.

A figure is a function ``make(ctx) -> Path | None`` registered with :func:`figure`; the report
stage calls every registered figure in order and the HTML page shows each in its section. Adding
a figure is one decorated function here.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..mechanics.results import Results
from .config import ReportConfig
from .curves import (
    axial_forces,
    end_force,
    load_factor_label,
    plot_force_activation,
    plot_newton,
    select_force_sets,
    write_csv,
)

#: sections of the page, in order (key → heading)
SECTIONS = {
    "force": "Force–activation",
    "segmentation": "Segmentation QC",
    "model": "Model in 3-D",
    "slices": "Fields on slices",
    "solver": "Solver and Newton statistics",
}


@dataclasses.dataclass
class Context:
    """What a figure may use: the results, the summary, the config, the output folder, and a list
    to append warnings to. ``extra`` is the caller's run information (comparison curves)."""

    res: Results
    summary: dict
    cfg: ReportConfig
    outdir: Path
    warnings: list
    extra: dict


@dataclasses.dataclass(frozen=True)
class FigureSpec:
    key: str
    section: str
    caption: str
    make: Callable[[Context], Path | None]


FIGURES: list[FigureSpec] = []


def figure(key: str, section: str, caption: str):
    """Register ``make(ctx) -> Path | None`` as figure ``key`` (file ``<key>.png``) of ``section``."""
    if section not in SECTIONS:
        raise ValueError(f"unknown report section {section!r}")

    def deco(fn):
        FIGURES.append(FigureSpec(key, section, caption, fn))
        return fn

    return deco


def make_figures(ctx: Context, sections=None) -> dict[str, tuple[FigureSpec, Path]]:
    """Make every registered figure (only those of ``sections`` when given); returns key → (spec,
    PNG path) of those made."""
    out = {}
    for spec in FIGURES:
        if sections is not None and spec.section not in sections:
            continue
        p = spec.make(ctx)
        if p is not None:
            out[spec.key] = (spec, Path(p))
    return out


# ------------------------------------------------------------------------------------------ figures
def _by_displacement(ctx: Context) -> bool:
    return (ctx.summary.get("protocol") or {}).get("kind") == "displacement"


def _state(ctx: Context, step: int) -> str:
    """How far the load had gone at ``step``: its α, or the driving set's displacement."""
    if _by_displacement(ctx):
        p = ctx.summary["protocol"]
        d = ctx.summary["curve"]["displacement_cm"][step]
        return f"{p['set']} displaced {d:.3g} cm along {p['component']}"
    return f"α = {float(ctx.res.alpha[step]):.3g}"


@figure("force_activation", "force", "End force vs activation (mean of the force sets; other models overlaid)")
def _force_activation(ctx: Context) -> Path | None:
    if _by_displacement(ctx):
        return None
    res, summary, extra = ctx.res, ctx.summary, ctx.extra
    path = Path(summary["results"]) if summary["results"] else None
    compare = dict(extra.get("compare") or {})
    main_label = next((lab for lab, p in compare.items()
                       if path is not None and Path(p).resolve() == path.resolve() and len(compare) > 1), None)
    prefix = f"{main_label}: " if main_label else ""
    # muscles ramped differently: against the load factor, each muscle's α named on the axis
    by_load = load_factor_label((res.info or {}).get("activation"))
    x = res.load_factor if by_load else res.alpha
    curves = {f"{prefix}{s} end": (x, np.array(summary["curve"]["axial_force_N"][s], float), res.converged)
              for s in summary["force_sets"]}
    curves.update(_compare_curves(compare, path, ctx, by_load=bool(by_load)))
    for lab, c in dict(extra.get("curves") or {}).items():
        curves[str(lab)] = tuple(c)
    return plot_force_activation(curves, ctx.outdir / "force_activation.png", dpi=ctx.cfg.dpi,
                                   title=f"Isometric force vs {'load factor' if by_load else 'activation'} — "
                                         f"{summary['label']}", xlabel=by_load or "activation α [-]")


@figure("force_displacement", "force", "End force vs the prescribed displacement (mean of the force sets), beside "
                                      "the reference curve of report.reference_curve; lower panel: relative difference")
def _force_displacement(ctx: Context) -> Path | None:
    if not _by_displacement(ctx):
        return None
    s = ctx.summary
    p, c = s["protocol"], s["curve"]
    d = np.array(c["displacement_cm"], float)
    curves = {"end force (mean of " + ", ".join(s["force_sets"]) + ")": (d, np.array(c["end_force_N"], float),
                                                                      np.array(c["converged"], bool))}
    ref = s.get("reference")
    from .displacement import plot_force_displacement

    return plot_force_displacement(
        curves, ctx.outdir / "force_displacement.png", dpi=ctx.cfg.dpi,
        reference=None if not ref else (ref["label"], ref["curve"]["displacement_cm"], ref["curve"]["force_N"]),
        relative=None if not ref else [np.nan if r is None else r for r in ref["relative"]],
        xlabel=f"prescribed displacement of {p['set']} along {p['component']} [cm]",
        title=f"Force vs prescribed displacement — {s['label']}")


def _compare_curves(compare: dict, main: Path | None, ctx: Context, by_load: bool = False) -> dict:
    """End-force curves of the other results files in ``compare`` (label → path), against α or
    (``by_load``) the load factor."""
    from ..io.results import load_results

    curves = {}
    for lab, p in compare.items():
        p = Path(p)
        try:
            if main is not None and p.resolve() == main.resolve():
                continue
            other = load_results(p)
            sets = select_force_sets(other.reaction, ctx.cfg.force_sets, other.constrained_text())
            f = end_force(axial_forces(other.reaction, sets), other.n_states)
            if sets:
                curves[f"{lab} (mean of {', '.join(sets)})"] = (other.load_factor if by_load else other.alpha, f,
                                                               other.converged)
        except (InputError, OSError) as exc:
            ctx.warnings.append(f"comparison curve '{lab}' not drawn: {exc}")
    return curves


@figure("segmentation_qc", "segmentation", "MRI with the segmentation filled in (muscles by name, connective "
                                              "tissue, fat, bone); axes in cm")
def _segmentation(ctx: Context) -> Path | None:
    if not ctx.cfg.segmentation_qc:
        return None
    from ..imaging.nifti import load_volume
    from ..io.segmentation import read_segmentation
    from .segmentation_qc import find_segmentation, plot_overlays, slice_areas

    seg_path, mri_path, note = find_segmentation(ctx.summary.get("stages", []))
    if seg_path is None:
        ctx.summary["segmentation_qc"] = {"note": note}
        return None
    try:
        seg = read_segmentation(seg_path)
    except (KeyError, OSError, InputError) as exc:
        ctx.summary["segmentation_qc"] = {"note": f"segmentation file {seg_path} not readable ({exc})"}
        return None
    mri = None
    if mri_path is not None:
        try:
            mri = load_volume(mri_path, kind="image").data
        except InputError as exc:
            note = f"MRI not shown: {exc}"
    header, rows = slice_areas(seg["labels"], seg["muscle_id"], seg["muscle_names"], seg["affine"])
    ctx.summary["segmentation_qc"] = {"file": str(seg_path), "mri": str(mri_path) if mri_path else None, "note": note,
                                      "areas_header": header, "areas": rows}
    write_csv(ctx.outdir / "segmentation_areas.csv", header, rows)
    return plot_overlays(mri, seg, ctx.outdir / "segmentation_qc.png", dpi=ctx.cfg.dpi)


def _slice_step(ctx: Context) -> int | None:
    return ctx.summary.get("field_step")


@figure("slices_displacement", "slices", "Displacement magnitude on three planes through the model (reference "
                                          "configuration); arrows: in-plane displacement")
def _slices_u(ctx: Context) -> Path | None:
    step = _slice_step(ctx)
    if step is None or not ctx.cfg.slices:
        return None
    from .slices import plane_indices, plot_slices

    m = ctx.res.model
    fields = ctx.res.step(step)
    umag = np.linalg.norm(fields.u, axis=1)
    if not np.isfinite(umag).all():
        ctx.warnings.append(f"displacement at step {step} has {int((~np.isfinite(umag)).sum())} non-finite "
                            "values (blank on the slices)")
    if not np.isfinite(umag).any():
        return None
    at = plane_indices(m.ijk, m.origin, m.spacing, ctx.cfg.slice_position)
    return plot_slices(m.ijk, m.origin, m.spacing, umag, ctx.outdir / "slices_displacement.png", label="|u| [cm]",
                       title=f"Displacement magnitude, step {step} ({_state(ctx, step)}), on the reference configuration",
                       planes_at=at, vectors=fields.u if ctx.cfg.arrows else None, cmap="viridis", dpi=ctx.cfg.dpi)


@figure("slices_stress", "slices", "Largest principal Cauchy stress on the same planes")
def _slices_s(ctx: Context) -> Path | None:
    step = _slice_step(ctx)
    if step is None or not ctx.cfg.slices:
        return None
    from .slices import plane_indices, plot_slices

    m = ctx.res.model
    mp = ctx.res.step(step).max_principal
    if mp is None:
        ctx.warnings.append("no stress in the results file: no stress slices")
        return None
    if not np.isfinite(mp).any():
        return None
    if not np.isfinite(mp).all():
        ctx.warnings.append(f"max principal stress at step {step} has non-finite values (blank on the slices)")
    at = plane_indices(m.ijk, m.origin, m.spacing, ctx.cfg.slice_position)
    return plot_slices(m.ijk, m.origin, m.spacing, mp, ctx.outdir / "slices_stress.png",
                       label="max principal Cauchy stress [N/cm²]",
                       title=f"Maximum principal Cauchy stress, step {step} ({_state(ctx, step)}), on the reference configuration",
                       planes_at=at, cmap="magma", dpi=ctx.cfg.dpi)


@figure("newton", "solver", "Newton residual per iteration of every load step")
def _newton(ctx: Context) -> Path | None:
    return plot_newton(ctx.res.newton, ctx.outdir / "newton.png", dpi=ctx.cfg.dpi)


def field_step(res: Results, cfg: ReportConfig, warnings: list) -> int | None:
    """The state shown on the slices and in 3-D: ``cfg.slice_step`` or the last converged one."""
    if cfg.slice_step is not None:
        if cfg.slice_step >= res.n_states:
            raise InputError(f"report.slice_step: {cfg.slice_step} but the results file has steps 0..{res.n_states - 1}")
        if not res.converged[cfg.slice_step]:
            warnings.append(f"report.slice_step {cfg.slice_step} did not converge: the figures show a "
                            "non-converged state")
        return int(cfg.slice_step)
    conv = np.flatnonzero(res.converged)
    return int(conv[-1]) if conv.size else None


__all__ = ["FIGURES", "SECTIONS", "Context", "FigureSpec", "figure", "make_figures", "field_step"]

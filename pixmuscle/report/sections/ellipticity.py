"""Report section: where the material law is not strongly elliptic at the last converged step.

Reads the results' acoustic-tensor minimum at the nodes (:class:`~pixmuscle.mechanics.results.
NodeEllipticity`, N/cm²): the number of nodes where it is negative per muscle and tissue, the
smallest value, and the three planes of the slice figures with those nodes marked. Left out for
results files that do not record it (written before it was recorded): their solver statistics
still give the count, ``non_elliptic_nodes``.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from ...model.tissues import TISSUE_NAMES
from ..html import esc, img_tag, kv_table, table
from . import SECTIONS

__all__ = ["Ellipticity", "ellipticity_rows"]


def ellipticity_rows(model, minimum: np.ndarray) -> list[list]:
    """Per muscle and per other tissue: [name, nodes, non-elliptic nodes, %, smallest minimum (N/cm²)].

    Parameters
    ----------
    model : Model
    minimum : (N,) float
        Acoustic-tensor minimum per node, N/cm².
    """
    q = np.asarray(minimum, float)
    tissue, mid = np.asarray(model.tissue), np.asarray(model.muscle_id)
    groups = [(str(name), (tissue == 1) & (mid == k + 1)) for k, name in enumerate(model.muscle_names)]
    groups += [(TISSUE_NAMES.get(c, str(c)), tissue == c) for c in (2, 3)]
    rows = []
    for name, sel in groups:  # the muscles, connective tissue, fat
        n = int(sel.sum())
        if n == 0:
            continue
        bad = int(np.count_nonzero(q[sel] < 0.0))
        rows.append([name, n, bad, 100.0 * bad / n, float(q[sel].min())])
    return rows


@SECTIONS.register("ellipticity", inputs=("results", "summary", "outdir", "dpi"), order=35)
@dataclasses.dataclass(frozen=True)
class Ellipticity:
    """Nodes where the material law is not strongly elliptic at the last converged step; no options."""

    def html(self, results, summary: dict, outdir: Path, dpi: int) -> list[str]:
        """Table per muscle and tissue, and (when there are such nodes) a slice figure; empty when
        the results do not record the field.

        Side effects: ``summary["ellipticity"]`` (step, α, counts) and, with a figure,
        ``summary["outputs"]["ellipticity_png"]``.
        """
        ell = getattr(results, "ellipticity", None)
        if ell is None:
            return []
        m = results.model
        q = np.asarray(ell.minimum, float)
        bad = q < 0.0
        step = int(ell.step)
        alpha = float(results.alpha[step])
        rows = ellipticity_rows(m, q)
        summary["ellipticity"] = {"step": step, "alpha": alpha, "non_elliptic_nodes": int(bad.sum()),
                                  "n_nodes": int(q.size), "smallest_N_per_cm2": float(q.min()),
                                  "by_region": {r[0]: r[2] for r in rows}}
        facts = {"state": f"step {step}, α = {alpha:.3g} (last converged)",
                 "nodes not strongly elliptic": f"{int(bad.sum()):,} of {q.size:,} ({100.0 * bad.mean():.2g} %)",
                 "smallest acoustic-tensor eigenvalue": f"{q.min():.3g} N/cm²",
                 "directions checked": ell.n_directions}
        parts = ["<h2>Strong ellipticity of the material law</h2>", kv_table(facts),
                 table(["region", "nodes", "not elliptic", "%", "smallest eigenvalue [N/cm²]"], rows)]
        if bad.any():
            from ..slices import plot_slices

            png = Path(outdir) / "ellipticity.png"
            plot_slices(m.ijk, m.origin, m.spacing, bad.astype(float), png, cmap="Reds", dpi=dpi,
                        label="1: not strongly elliptic", title=f"nodes where the law is not strongly elliptic, α = {alpha:.3g}")
            summary["outputs"]["ellipticity_png"] = str(png)
            parts.append(img_tag(png, "nodes where the material law is not strongly elliptic"))
        parts.append('<p class="foot">At these nodes the acoustic tensor of the law at the node\'s deformation '
                     "gradient has a negative eigenvalue for some direction: the continuum admits strain jumps "
                     "across a plane there, deformation can localise in bands, and forces and fields depend on the "
                     "resolution. ParaView: the cell arrays <code>non_elliptic</code> and "
                     f"<code>{esc('acoustic_minimum [N/cm^2]')}</code> of the last step's file.</p>")
        return parts

"""Verification of the RK approximation against the paper's 1-D examples (§2, Figs. 3 and 4).

Fig. 3: u = sin x on [0, 10], uniform nodes of spacing h, coefficients d_I = u(x_I) (nodal values,
as in the paper), L2 error of eq. 8 by a composite Gauss rule. The RK approximation reproduces
polynomials of degree <= n (eq. 5), so the error is O(h^(n+1)): rate 2 for n = 1, 3 for n = 2.
Normalised supports: a/h = 2.0 for n = 1 and a/h = 2.5 for n = 2 (an order-2 basis needs three
nodes strictly inside the support of every point, including x = 0 and x = 10, hence a/h > 2).

Fig. 4: Young's modulus E = 30 for x < 5 and 5 for x >= 5 given at the nodes, represented by RK
(cubic B-spline kernel, linear basis) for several supports, against the piecewise-constant
finite-element representation that jumps at x = 5.
"""

from __future__ import annotations

import pathlib

import numpy as np

from pixmuscle.rk import KERNELS, shape_functions

DOMAIN = (0.0, 10.0)
N_ELEMENTS = (20, 40, 80, 160, 320)
SUPPORT_RATIO = {1: 2.0, 2: 2.5}
TRANSITION_SUPPORT_RATIOS = (1.65, 2.5, 4.0)
TRANSITION_SPACING = 0.25
E_LEFT, E_RIGHT, X_INTERFACE = 30.0, 5.0, 5.0


def gauss_rule(n_cells, n_gauss=6, domain=DOMAIN):
    """Composite Gauss–Legendre rule: points (n_cells * n_gauss,) and weights on ``domain``."""
    xg, wg = np.polynomial.legendre.leggauss(n_gauss)
    edges = np.linspace(domain[0], domain[1], n_cells + 1)
    half = 0.5 * np.diff(edges)
    mid = 0.5 * (edges[:-1] + edges[1:])
    return (mid[:, None] + half[:, None] * xg).ravel(), (half[:, None] * wg).ravel()


def sine_l2_error(n_elements, kernel="cubic", order=1, a_over_h=None):
    """L2 error (eq. 8) of the RK approximation of sin x on [0, 10] with nodal coefficients.

    Parameters
    ----------
    n_elements : int
        Number of node intervals; h = 10 / n_elements, n_elements + 1 nodes.
    kernel, order : see :func:`pixmuscle.rk.shape_functions`
    a_over_h : float, optional
        Normalised support; default ``SUPPORT_RATIO[order]``.

    Returns
    -------
    h : float
    error : float
    """
    a_over_h = SUPPORT_RATIO.get(order, 2.5) if a_over_h is None else a_over_h
    x = np.linspace(*DOMAIN, n_elements + 1)
    h = x[1] - x[0]
    q, w = gauss_rule(8 * n_elements)
    psi = shape_functions(x[:, None], q[:, None], a_over_h * h, kernel=kernel, order=order)
    uh = psi @ np.sin(x)
    return float(h), float(np.sqrt(np.sum(w * (uh - np.sin(q)) ** 2)))


def observed_rate(h, error):
    """Least-squares slope of log(error) against log(h)."""
    return float(np.polyfit(np.log(h), np.log(error), 1)[0])


def convergence_table(kernels=KERNELS, orders=(1, 2), n_elements=N_ELEMENTS):
    """Convergence study of paper Fig. 3.

    Returns
    -------
    list of dict
        One row per (order, kernel, refinement): ``order``, ``kernel``, ``a_over_h``, ``h``,
        ``error``, ``rate`` (against the previous refinement, None for the first) and
        ``fitted_rate`` (least-squares slope over all refinements of that order and kernel).
    """
    rows = []
    for order in orders:
        for kernel in kernels:
            hs, errs = zip(*(sine_l2_error(n, kernel, order) for n in n_elements), strict=True)
            fitted = observed_rate(hs, errs)
            for i, (h, err) in enumerate(zip(hs, errs, strict=True)):
                rate = None if i == 0 else float(np.log(errs[i - 1] / err) / np.log(hs[i - 1] / h))
                rows.append(
                    {
                        "order": order,
                        "kernel": kernel,
                        "a_over_h": SUPPORT_RATIO[order],
                        "h": h,
                        "error": err,
                        "rate": rate,
                        "fitted_rate": fitted,
                    }
                )
    return rows


def material_transition(a_over_h=TRANSITION_SUPPORT_RATIOS, h=TRANSITION_SPACING, n_samples=8001):
    """RK representation of a two-material Young's modulus (paper Fig. 4).

    Returns
    -------
    dict
        ``x`` (n_samples,) cm; ``E_fe`` piecewise constant; ``E_rk`` {a/h: values}; per a/h the
        ``width`` of the transition (x-range where 5.25 < E < 29.75), ``max_jump`` between
        samples and ``max_slope`` (max |dE/dx| from the exact RK gradient).
    """
    nodes = np.arange(DOMAIN[0], DOMAIN[1] + 0.5 * h, h)
    e_nodes = np.where(nodes < X_INTERFACE, E_LEFT, E_RIGHT)
    xs = np.linspace(*DOMAIN, n_samples)
    step = xs[1] - xs[0]
    out = {"x": xs, "E_fe": np.where(xs < X_INTERFACE, E_LEFT, E_RIGHT), "h": h}
    out["E_rk"], out["width"], out["max_jump"], out["max_slope"] = {}, {}, {}, {}
    lo = E_RIGHT + 0.01 * (E_LEFT - E_RIGHT)
    hi = E_LEFT - 0.01 * (E_LEFT - E_RIGHT)
    for ratio in a_over_h:
        psi, (dpsi,) = shape_functions(nodes[:, None], xs[:, None], ratio * h, kernel="cubic", order=1, gradient=True)
        e = psi @ e_nodes
        out["E_rk"][ratio] = e
        out["width"][ratio] = float(step * np.count_nonzero((e > lo) & (e < hi)))
        out["max_jump"][ratio] = float(np.abs(np.diff(e)).max())
        out["max_slope"][ratio] = float(np.abs(dpsi @ e_nodes).max())
    return out


def _print_table(rows, console):
    header = ("order", "kernel", "a/h", "h", "L2 error", "rate", "fitted")
    lines = [
        (
            str(r["order"]),
            r["kernel"],
            f"{r['a_over_h']:.2f}",
            f"{r['h']:.5f}",
            f"{r['error']:.3e}",
            "" if r["rate"] is None else f"{r['rate']:.2f}",
            f"{r['fitted_rate']:.2f}",
        )
        for r in rows
    ]
    if console is not None:
        from rich.table import Table

        table = Table(title="RK convergence, u = sin x on [0, 10] (paper Fig. 3)")
        for name in header:
            table.add_column(name, justify="right")
        for line in lines:
            table.add_row(*line)
        console.print(table)
        return
    widths = [max(len(h), *(len(line[i]) for line in lines)) for i, h in enumerate(header)]
    print("RK convergence, u = sin x on [0, 10] (paper Fig. 3)")
    print("  ".join(h.rjust(w) for h, w in zip(header, widths, strict=True)))
    for line in lines:
        print("  ".join(c.rjust(w) for c, w in zip(line, widths, strict=True)))


def _plot_convergence(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    orders = sorted({r["order"] for r in rows})
    fig, axes = plt.subplots(1, len(orders), figsize=(5.5 * len(orders), 4.5), squeeze=False)
    for ax, order in zip(axes[0], orders, strict=True):
        for kernel in dict.fromkeys(r["kernel"] for r in rows if r["order"] == order):
            sel = [r for r in rows if r["order"] == order and r["kernel"] == kernel]
            ax.loglog(
                [r["h"] for r in sel],
                [r["error"] for r in sel],
                "o-",
                label=f"{kernel}: rate {sel[0]['fitted_rate']:.2f}",
            )
        hs = [r["h"] for r in rows if r["order"] == order and r["kernel"] == sel[0]["kernel"]]
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.set_xticks(hs, [f"{h:g}" for h in hs])
        ax.set_xlabel("nodal spacing h")
        ax.set_ylabel("L2 error (eq. 8)")
        ax.set_title(f"n = {order}, a/h = {SUPPORT_RATIO[order]:g}")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    fig.suptitle("RK approximation of sin x on [0, 10] (paper Fig. 3)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _plot_transition(tr, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    ax.plot(tr["x"], tr["E_fe"], "k-", lw=1.5, label="FE (piecewise constant)")
    for ratio, e in tr["E_rk"].items():
        ax.plot(tr["x"], e, lw=1.5, label=f"RK a/h = {ratio:g} (width {tr['width'][ratio]:.2f})")
    ax.set_xlim(3.0, 7.0)
    ax.set_xlabel("x")
    ax.set_ylabel("Young's modulus E")
    ax.set_title(f"RK vs FE material transition, cubic kernel, n = 1, h = {tr['h']:g}")
    ax.legend()
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def verify_rk(outdir: pathlib.Path, console=None) -> dict:
    """Run the paper-§2 RK checks, print the convergence table and write two figures.

    Parameters
    ----------
    outdir : pathlib.Path
        Created if missing; receives ``rk_convergence.png`` (Fig. 3 equivalent) and
        ``rk_material_transition.png`` (Fig. 4 equivalent).
    console : rich.console.Console, optional
        Print a rich table there; plain text on stdout otherwise.

    Returns
    -------
    dict
        ``convergence`` (rows of :func:`convergence_table`), ``rates``
        {"n=<order>/<kernel>": fitted rate}, ``transition`` {a/h: {"width", "max_jump",
        "max_slope"}} and ``figures`` (paths written).
    """
    outdir = pathlib.Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    rows = convergence_table()
    _print_table(rows, console)
    tr = material_transition()
    conv_png = outdir / "rk_convergence.png"
    trans_png = outdir / "rk_material_transition.png"
    _plot_convergence(rows, conv_png)
    _plot_transition(tr, trans_png)
    rates = {f"n={r['order']}/{r['kernel']}": r["fitted_rate"] for r in rows}
    transition = {
        float(k): {
            "width": tr["width"][k],
            "max_jump": tr["max_jump"][k],
            "max_slope": tr["max_slope"][k],
        }
        for k in tr["E_rk"]
    }
    msg = "RK material transition (Fig. 4): " + ", ".join(
        f"a/h={k:g}: width {v['width']:.3f}" for k, v in transition.items()
    )
    if console is not None:
        console.print(msg)
    else:
        print(msg)
    return {
        "convergence": rows,
        "rates": rates,
        "transition": transition,
        "figures": [str(conv_png), str(trans_png)],
    }

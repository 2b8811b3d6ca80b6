"""Active muscle on the clamped oblique-fibre block: pixmuscle against mixed finite elements.

Case: a 2 × 1.5 × 6 cm block of muscle (paper eqs. 22–26 with the ERRATA: Table 2 matrix constants,
K = 5000, σ_max = 30 N/cm², λ̂0 = 1), fibres in the x–z plane at 25° to the long axis z, both end
faces z = 0 and z = 6 clamped (u = 0), activation α ramped 0 → 0.95 in 10 equal steps. Measured:
the reaction at z = 6, F_z (axial, positive = the block pulls on the support) and F_x (shear), N.

Methods (``--cases``):

``q1:NXxNYxNZ`` / ``q2:NXxNYxNZ``
    FElupe finite elements, the muscle law written here independently of pixmuscle (``muscle_law``:
    the isochoric part as a tensortrax function, differentiated automatically; the fibre force of
    eq. 24 integrated in closed form), in FElupe's nearly-incompressible three-field u/p/J̄ form
    (``NearlyIncompressible``, U = K/2 (J̄ − 1)²). ``q1``: trilinear hexahedra with constant
    p, J̄ per element (Q1/P0). ``q2``: triquadratic hexahedra (27 nodes) with discontinuous trilinear
    p, J̄ (Q2/dQ1, inf-sup stable). NX × NY × NZ elements for the whole block; only y ≥ 0 is meshed
    (the fibres lie in the x–z plane, so the block, its fibres and its clamps are mirror-symmetric
    about y = 0: u_y = 0 there, forces ×2; x is not a symmetry plane, the fibres are not mirrored).
    Newton to a relative residual of 1e-8 with PARDISO (``pypardiso``); a step that does not
    converge in 30 iterations is halved (the record counts the halvings).
``pixmuscle:H``
    pixmuscle's SCNI–RKPM solver, one node per voxel of H cm (the block as a voxel mask, every
    setting at its default), reaction at the ``z_max`` node set. ``pixmuscle:H:KEY=VALUE,...``
    passes ``solve`` options (``volumetric.method=nodal``) for experiments.

``--check-law`` compares ``muscle_law`` with ``pixmuscle.mechanics.materials.MUSCLE`` (stress and
tangent at random deformation gradients and α) before anything else.

``--ellipticity`` records, for the muscle law, where it stops being strongly elliptic (the smallest
eigenvalue of the acoustic tensor, over wave directions, turning negative) along uniaxial,
planar and shear paths, and the FE cases record the share of the block past that limit
(``non_elliptic_volume``) and the largest principal stretch at the last converged step.

Writes ``benchmarks/results/bench_active_block.json`` and ``.md`` (``--append`` merges cases into
an existing record); ``--fields CASE`` also writes the FE fields of one case at α = 0.95 to
``benchmarks/results/bench_active_block_fields_CASE.npz`` for ``docs/figures``.

FElupe is in the optional extra ``bench`` (``.venv/bin/pip install felupe tensortrax pypardiso``).

Usage::

    .venv/bin/python benchmarks/bench_active_block.py --check-law --ellipticity
    .venv/bin/python benchmarks/bench_active_block.py --append --cases q2:4x4x12 q1:8x8x24 pixmuscle:0.5
    .venv/bin/python benchmarks/bench_active_block.py --tables
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import sys
import time

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from _record import Run  # noqa: E402

OUT = pathlib.Path(__file__).parent / "results"
STEM = "bench_active_block"
SIZE = (2.0, 1.5, 6.0)          # cm
ANGLE = np.deg2rad(25.0)        # fibre angle to z in the x-z plane
FIBER = np.array([np.sin(ANGLE), 0.0, np.cos(ANGLE)])
STEPS, ALPHA_END = 10, 0.95
NEWTON_TOL, NEWTON_MAXITER = 1e-8, 30

# paper Table 2 (ERRATA), N/cm²; σ_max, λ̂0 and the passive constants of eqs. 24-25
MATRIX = {"C10": 6.43, "C01": -3.8, "C20": 0.94, "C02": 0.0005, "C11": -0.0043}
BULK, SIGMA_MAX, LAMBDA_OPT, GAMMA1, GAMMA2 = 5000.0, 30.0, 1.0, 0.05, 6.6


# ----------------------------------------------------------------------------------------------
# the muscle law, written from the paper (eqs. 22-26, ERRATA) without pixmuscle's code
# ----------------------------------------------------------------------------------------------

def fiber_force(s, alpha):
    """Normalised fibre force α f_active(s) + f_passive(s) and its s-derivative (eqs. 25-26, ERRATA).

    s = λ̂/λ̂0 (any shape); f_active = 9(s−0.4)² on [0.4, 0.6], 1 − 4(1−s)² on (0.6, 1.4],
    9(s−1.6)² on (1.4, 1.6], 0 outside [0.4, 1.6]; f_passive = 0 for s ≤ 1, γ1(e^(γ2(s−1)) − 1) on
    (1, 1.4], continued linearly (C¹) beyond 1.4.
    """
    s = np.asarray(s, float)
    fa = np.piecewise(s, [s < 0.4, (s >= 0.4) & (s <= 0.6), (s > 0.6) & (s <= 1.4), (s > 1.4) & (s <= 1.6)],
                      [0.0, lambda t: 9 * (t - 0.4) ** 2, lambda t: 1 - 4 * (1 - t) ** 2, lambda t: 9 * (t - 1.6) ** 2, 0.0])
    dfa = np.piecewise(s, [s < 0.4, (s >= 0.4) & (s <= 0.6), (s > 0.6) & (s <= 1.4), (s > 1.4) & (s <= 1.6)],
                       [0.0, lambda t: 18 * (t - 0.4), lambda t: 8 * (1 - t), lambda t: 18 * (t - 1.6), 0.0])
    e14 = np.exp(0.4 * GAMMA2)
    fp = np.piecewise(s, [s <= 1.0, (s > 1.0) & (s <= 1.4)],
                      [0.0, lambda t: GAMMA1 * (np.exp(GAMMA2 * (t - 1)) - 1), lambda t: GAMMA1 * GAMMA2 * e14 * (t - 1.4) + GAMMA1 * (e14 - 1)])
    dfp = np.piecewise(s, [s <= 1.0, (s > 1.0) & (s <= 1.4)],
                       [0.0, lambda t: GAMMA1 * GAMMA2 * np.exp(GAMMA2 * (t - 1)), GAMMA1 * GAMMA2 * e14])
    return alpha * fa + fp, alpha * dfa + dfp


def fiber_energy(lam, alpha):
    """W_fiber(λ̂) with W_fiber(λ̂0) = 0, by 16-point Gauss–Legendre quadrature of eq. 24 on each
    smooth piece of the force (exact: the pieces are polynomials and one exponential, which 16
    points integrate to round-off)."""
    lam = np.asarray(lam, float)
    s = lam / LAMBDA_OPT
    x, w = np.polynomial.legendre.leggauss(16)
    knots = np.array([0.4, 0.6, 1.0, 1.4, 1.6])
    out = np.zeros_like(s)
    lo, hi = np.minimum(s, 1.0), np.maximum(s, 1.0)
    sign = np.where(s < 1.0, -1.0, 1.0)
    edges = np.sort(np.concatenate([knots, [0.0, 10.0]]))
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        a_, b_ = np.clip(lo, a, b), np.clip(hi, a, b)
        mid, half = 0.5 * (a_ + b_), 0.5 * (b_ - a_)
        t = mid[..., None] + half[..., None] * x
        out += half * (fiber_force(t, alpha)[0] * w).sum(-1)
    return SIGMA_MAX * sign * out


def muscle_law(C, alpha=0.0, fiber=FIBER, **matrix):
    """Isochoric strain energy of the muscle (eqs. 22-24) as a function of C = FᵀF (tensortrax).

    W = Σ C_ij (Ī1 − 3)^i (Ī2 − 3)^j + W_fiber(λ̂),  C̄ = J^(−2/3) C,  Ī1 = tr C̄,
    Ī2 = ½(Ī1² − tr C̄²), λ̂ = √(N·C̄N); the volumetric K/2 (J − 1)² is added by the mixed form.
    """
    import tensortrax.math as tm

    c = {**MATRIX, **matrix}
    Cu = tm.linalg.det(C) ** (-1 / 3) * C
    I1 = tm.trace(Cu)
    I2 = (I1**2 - tm.trace(Cu @ Cu)) / 2
    I4 = sum(fiber[i] * fiber[j] * Cu[i, j] for i in range(3) for j in range(3) if fiber[i] * fiber[j] != 0)
    x, y = I1 - 3, I2 - 3
    W = c["C10"] * x + c["C01"] * y + c["C20"] * x**2 + c["C02"] * y**2 + c["C11"] * x * y

    def g(lam):  # dW/dλ̂ (eq. 24)
        return SIGMA_MAX / LAMBDA_OPT * fiber_force(lam / LAMBDA_OPT, alpha)[0]

    def dg(lam):
        return SIGMA_MAX / LAMBDA_OPT**2 * fiber_force(lam / LAMBDA_OPT, alpha)[1]

    lam = tm.sqrt(I4)
    return W + tm.external(lam, lambda v: fiber_energy(v, alpha), g, dg, indices="")


def law_stress_tangent(F, alpha, fiber=FIBER, **matrix):
    """P (n,3,3) and A (n,3,3,3,3) of muscle_law + K/2 (J−1)² at F (n,3,3), by tensortrax."""
    import tensortrax as tr
    import tensortrax.math as tm

    def W(F):
        C = F.T @ F
        J = tm.linalg.det(F)
        return muscle_law(C, alpha, fiber, **matrix) + BULK / 2 * (J - 1) ** 2

    Ft = np.ascontiguousarray(np.moveaxis(F, 0, -1))           # (3, 3, n): tensortrax trailing axes
    P = tr.gradient(W, ntrax=1)(Ft)
    A = tr.hessian(W, ntrax=1)(Ft)
    return np.moveaxis(P, -1, 0), np.moveaxis(A, -1, 0)


def check_law(n=200, seed=0) -> dict:
    """Largest relative differences of P and A between ``law_stress_tangent`` and pixmuscle's MUSCLE."""
    from pixmuscle.mechanics.materials import MUSCLE

    rng = np.random.default_rng(seed)
    F = np.eye(3) + 0.25 * rng.standard_normal((n, 3, 3))
    F = F[np.linalg.det(F) > 0.3]
    rows = []
    for alpha in (0.0, 0.5, 0.95):
        P1, A1 = law_stress_tangent(F, alpha)
        P2, A2 = MUSCLE.stress_tangent(F, fiber=FIBER, activation=alpha)
        rows.append({"alpha": alpha, "points": len(F),
                     "P_rel_diff": float(np.abs(P1 - P2).max() / np.abs(P2).max()),
                     "A_rel_diff": float(np.abs(A1 - A2).max() / np.abs(A2).max())})
    return {"rows": rows, "stretch_range": [float(np.linalg.svd(F, compute_uv=False).min()),
                                            float(np.linalg.svd(F, compute_uv=False).max())]}


def acoustic_minimum(F, A, n_dirs=2000):
    """Smallest eigenvalue of the isochoric acoustic tensor over wave directions (n,) [N/cm²].

    Q_ik(m) = A_iJkL m_J m_L on the two polarisations a ⊥ F⁻ᵀm (the third, volumetric one, is
    stiffened by K); the law is strongly elliptic at F where this is > 0 for every m. m runs over
    ``n_dirs`` quasi-uniform unit vectors (a Fibonacci sphere); each point's 2 × 2 blocks by numpy's
    eigvalsh.
    """
    k = np.arange(n_dirs) + 0.5
    phi, z = np.pi * (1 + 5**0.5) * k, 1 - 2 * k / n_dirs
    r = np.sqrt(1 - z * z)
    m = np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)
    out = np.empty(len(F))
    for e in range(len(F)):
        Q = np.einsum("iJkL,mJ,mL->mik", A[e], m, m)
        v = m @ np.linalg.inv(F[e])                            # (F⁻ᵀ m)ᵀ
        v /= np.linalg.norm(v, axis=1)[:, None]
        t1 = np.cross(v, [0.3, 0.5, 0.7])
        t1 /= np.linalg.norm(t1, axis=1)[:, None]
        T = np.stack([t1, np.cross(v, t1)], 2)
        out[e] = np.linalg.eigvalsh(T.transpose(0, 2, 1) @ Q @ T)[:, 0].min()
    return out


def ellipticity_limits() -> list[dict]:
    """Where the muscle law stops being strongly elliptic on three isochoric paths (α = 0 and 0.95)."""
    paths = {"uniaxial tension along z (stretch)": lambda s: np.diag([s**-0.5, s**-0.5, s]),
             "planar tension along z (stretch)": lambda s: np.diag([1 / s, 1.0, s]),
             "simple shear in x-z (amount of shear)": lambda g: np.array([[1, 0, g], [0, 1, 0], [0, 0, 1.0]])}
    rows = []
    for name, path in paths.items():
        for alpha in (0.0, 0.95):
            grid = np.arange(0.0, 1.5, 0.005) if "shear" in name else np.arange(1.0, 2.0, 0.005)
            F = np.stack([path(v) for v in grid])
            q = acoustic_minimum(F, law_stress_tangent(F, alpha)[1])
            lost = np.flatnonzero(q < 0)
            rows.append({"path": name, "alpha": alpha, "limit": float(grid[lost[0]]) if lost.size else None,
                         "q_at_start_N_cm2": float(q[0])})
    return rows


# ----------------------------------------------------------------------------------------------
# finite elements (FElupe)
# ----------------------------------------------------------------------------------------------

def run_fe(family: str, n: tuple[int, int, int], fields_out: pathlib.Path | None = None, matrix=None) -> dict:
    """Half-model FElupe solve; F_z, F_x at z = 6 per step (N), iterations, halvings."""
    os.environ.setdefault("FELUPE_VERBOSE", "false")
    import felupe as fem
    from pypardiso import spsolve

    nx, ny, nz = n
    if ny % 2:
        raise SystemExit(f"{family}:{nx}x{ny}x{nz}: NY must be even (half model about y = 0)")
    t0 = time.perf_counter()
    mesh = fem.Cube(a=(0.0, 0.0, 0.0), b=(SIZE[0], SIZE[1] / 2, SIZE[2]), n=(nx + 1, ny // 2 + 1, nz + 1))
    if family == "q2":
        mesh = fem.mesh.convert(mesh, order=2, calc_midfaces=True, calc_midvolumes=True)
        region = fem.RegionTriQuadraticHexahedron(mesh)
    else:
        region = fem.RegionHexahedron(mesh)
    field = fem.FieldsMixed(region, n=3)
    umat = fem.Hyperelastic(muscle_law, alpha=0.0, fiber=FIBER, **(matrix or {}))
    solid = fem.SolidBody(fem.NearlyIncompressible(umat, bulk=BULK), field)
    p = mesh.points
    bounds = {"bottom": fem.Boundary(field[0], mask=np.isclose(p[:, 2], 0.0)),
              "top": fem.Boundary(field[0], mask=np.isclose(p[:, 2], SIZE[2])),
              "sym": fem.Boundary(field[0], mask=np.isclose(p[:, 1], 0.0), skip=(1, 0, 1))}
    dof0, dof1 = fem.dof.partition(field, bounds)
    ext0 = fem.dof.apply(field, bounds, dof0)
    alphas = ALPHA_END * np.arange(1, STEPS + 1) / STEPS
    out = {"case": f"{family}:{nx}x{ny}x{nz}", "matrix": {**MATRIX, **(matrix or {})},
           "method": f"FElupe {'Q2/dQ1' if family == 'q2' else 'Q1/P0'} u/p/J, half model",
           "elements_half": int(mesh.ncells), "dofs": int(sum(f.values.size for f in field.fields)), "alpha": [0.0], "Fz_N": [0.0], "Fx_N": [0.0],
           "iterations": [], "halvings": 0, "status": "complete"}
    a_done = 0.0
    for a_target in alphas:
        da = a_target - a_done
        its = 0
        while a_done < a_target - 1e-12:
            a_try = min(a_done + da, a_target)
            saved = [f.values.copy() for f in field.fields]
            umat.kwargs["alpha"] = a_try
            try:
                res = fem.newtonraphson(items=[solid], x0=field, dof1=dof1, dof0=dof0, ext0=ext0, solver=spsolve,
                                        tol=NEWTON_TOL, maxiter=NEWTON_MAXITER, verbose=0)
                ok = bool(res.success)
            except Exception:                                   # no convergence or an inverted element
                ok = False
            if not ok:
                for f, v in zip(field.fields, saved, strict=True):
                    f.values[:] = v
                da /= 2
                out["halvings"] += 1
                if da < 1e-4:
                    out["status"] = f"failed at alpha {a_try:.4f}"
                    break
                continue
            its += int(res.iterations)
            a_done = a_try
        if out["status"] != "complete":
            break
        force = 2.0 * fem.tools.force(field, res.fun, bounds["top"])      # half model: ×2 (F_y = 0)
        sgn = 1.0                                                         # residual at the support = its pull
        out["alpha"].append(float(a_done))
        out["Fz_N"].append(float(sgn * force[2]))
        out["Fx_N"].append(float(sgn * force[0]))
        out["iterations"].append(its)
        if fields_out is not None and mesh.ncells * region.h.shape[1] <= 20000:   # where the law is past its ellipticity limit
            diag = fe_diagnostics(field, umat, a_done, None, matrix)
            out.setdefault("non_elliptic_fraction_per_step", []).append(diag["non_elliptic_fraction"])
            out.setdefault("stretch_max_per_step", []).append(diag["stretch_max"])
        print(f"  {out['case']} alpha {a_done:.3f} Fz {out['Fz_N'][-1]:.4f} Fx {out['Fx_N'][-1]:.4f} it {its}", flush=True)
    out.update(fe_diagnostics(field, umat, out["alpha"][-1], fields_out, matrix))
    out["wall_s"] = round(time.perf_counter() - t0, 1)
    return out


def fe_diagnostics(field, umat, alpha, path, matrix) -> dict:
    """Largest principal stretch, smallest fibre stretch, and the share of the volume where the law
    is not strongly elliptic, at the quadrature points of the last converged state."""
    F = field[0].extract(grad=True, add_identity=True)          # (3, 3, q, e)
    Fp = np.moveaxis(F.reshape(3, 3, -1), -1, 0)
    dV = field.region.dV.reshape(-1)
    lam_f = np.sqrt(np.einsum("i,nki,nkj,j->n", FIBER, Fp, Fp, FIBER)) * np.linalg.det(Fp) ** (-1 / 3)
    sv = np.linalg.svd(Fp, compute_uv=False)
    qmin = np.empty(len(Fp))
    for s in range(0, len(Fp), 4096):
        qmin[s:s + 4096] = acoustic_minimum(Fp[s:s + 4096], law_stress_tangent(Fp[s:s + 4096], alpha, **(matrix or {}))[1], 400)
    bad = qmin < 0
    if path is not None:
        pts = field.region.mesh.points
        cells = field.region.mesh.cells
        h = field.region.h                                       # (nodes/elem, q)
        h = h[..., 0] if h.ndim == 3 and h.shape[2] == 1 else h
        xq = np.einsum("aq,eai->qei" if h.ndim == 2 else "aqe,eai->qei", h, pts[cells]).reshape(-1, 3)
        np.savez_compressed(path, xq=xq, F=Fp, qmin=qmin, lam_fiber=lam_f, stretch_max=sv[:, 0], dV=dV, alpha=alpha)
    return {"stretch_max": float(sv[:, 0].max()), "fiber_stretch_min": float(lam_f.min()),
            "fiber_stretch_max": float(lam_f.max()),
            "non_elliptic_volume_cm3": float(2.0 * dV[bad].sum()),
            "non_elliptic_fraction": float(dV[bad].sum() / dV.sum())}


# ----------------------------------------------------------------------------------------------
# pixmuscle
# ----------------------------------------------------------------------------------------------

def run_pixmuscle(h: float, options: dict | None = None) -> dict:
    """pixmuscle on the block as a voxel mask of h cm; F_z, F_x at z_max per step."""
    from pixmuscle.config import parse_section
    from pixmuscle.errors import SolverError
    from pixmuscle.mechanics.config import SolveConfig
    from pixmuscle.mechanics.solve import solve
    from pixmuscle.verify.mechanics import mask_model

    n = [round(s / h) for s in SIZE]
    model = mask_model(np.ones(n, bool), (h, h, h), tissue=1, fiber=FIBER)
    raw = {"steps": STEPS, "activation": {"from": 0.0, "to": ALPHA_END},
           "boundary_conditions": [{"nodes": "z_min", "fix": ["x", "y", "z"]}, {"nodes": "z_max", "fix": ["x", "y", "z"]}]}
    for key, value in (options or {}).items():
        d = raw
        *head, last = key.split(".")
        for k in head:
            d = d.setdefault(k, {})
        d[last] = value
    cfg = parse_section(SolveConfig, raw, "solve")
    t0 = time.perf_counter()
    try:
        res, status = solve(model, cfg), "complete"
    except SolverError as exc:
        res, status = exc.results, f"failed: {exc}"
    R = np.asarray(res.reaction["z_max"])                       # body pulls on the support, N
    opt = ",".join(f"{k}={v}" for k, v in (options or {}).items())
    return {"case": f"pixmuscle:{h:.4g}" + (f":{opt}" if opt else ""),
            "method": "pixmuscle SCNI-RKPM" + (f" ({opt})" if opt else ""),
            "h_cm": h, "voxels": n, "nodes": int(model.n_nodes), "alpha": res.alpha.tolist(),
            "Fz_N": R[:, 2].tolist(), "Fx_N": R[:, 0].tolist(), "iterations": np.asarray(res.iterations).tolist(),
            "status": status, "wall_s": round(time.perf_counter() - t0, 1)}


# ----------------------------------------------------------------------------------------------
# records
# ----------------------------------------------------------------------------------------------

def parse_case(spec: str):
    kind, _, rest = spec.partition(":")
    if kind in ("q1", "q2"):
        size, _, opts = rest.partition(":")
        n = tuple(int(v) for v in size.split("x"))
        if len(n) != 3:
            raise SystemExit(f"case {spec!r}: expected {kind}:NXxNYxNZ[:C10=..,C01=..]")
        matrix = {k: float(v) for k, _, v in (kv.partition("=") for kv in filter(None, opts.split(",")))}
        return kind, n, matrix
    if kind == "pixmuscle":
        h, _, opts = rest.partition(":")
        options = {}
        for kv in filter(None, opts.split(",")):
            k, _, v = kv.partition("=")
            try:
                v = json.loads(v)
            except json.JSONDecodeError:
                pass
            options[k] = v
        return kind, eval_h(h), options
    raise SystemExit(f"case {spec!r}: expected q1:NXxNYxNZ, q2:NXxNYxNZ or pixmuscle:H[:KEY=VALUE,...]")


def eval_h(text: str) -> float:
    num, _, den = text.partition("/")
    return float(num) / (float(den) if den else 1.0)


def write(record: dict) -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / f"{STEM}.json").write_text(json.dumps(record, indent=1))
    cases = record.get("cases", [])
    lines = ["# Active clamped oblique-fibre block: pixmuscle against mixed finite elements", "",
             "2 × 1.5 × 6 cm muscle block (paper eqs. 22–26, ERRATA), fibres in x–z at 25° to z, both ends clamped, "
             "α 0 → 0.95 in 10 steps. F_z, F_x: reaction at z = 6 (N, positive F_z = the block pulls on the support). "
             "The record is of forces; wall times were measured on a shared machine under the load averages below "
             "and are upper bounds, not timings.", ""]
    for run in record.get("runs", []):
        lines.append(f"- `{run['command']}` — {run.get('utc', run.get('date'))}, load average {run['load_average']}")
    lines.append("")
    if "law_check" in record:
        lines += ["## Muscle law: independent tensortrax law vs pixmuscle's MUSCLE", "",
                  "| α | points | max rel. diff P | max rel. diff A |", "|---|---|---|---|"]
        lines += [f"| {r['alpha']} | {r['points']} | {r['P_rel_diff']:.1e} | {r['A_rel_diff']:.1e} |" for r in record["law_check"]["rows"]]
        lines.append("")
    if "ellipticity" in record:
        lines += ["## Where the muscle law stops being strongly elliptic", "",
                  "| path | α | limit |", "|---|---|---|"]
        lines += [f"| {r['path']} | {r['alpha']} | {r['limit']} |" for r in record["ellipticity"]]
        lines.append("")
    if cases:
        alphas = cases[0]["alpha"]
        for comp in ("Fz_N", "Fx_N"):
            lines += [f"## {comp[:2]} (N)", "", "| α | " + " | ".join(c["case"] for c in cases) + " |",
                      "|---" * (len(cases) + 1) + "|"]
            for i, a in enumerate(alphas[1:], 1):
                vals = [f"{c[comp][i]:.3f}" if i < len(c[comp]) else "—" for c in cases]
                lines.append(f"| {a:.3f} | " + " | ".join(vals) + " |")
            lines.append("")
        lines += ["## Cases", "", "| case | method | size | iterations per step | halvings | wall [s] | status | max stretch | "
                  "non-elliptic share |", "|---|---|---|---|---|---|---|---|---|"]
        for c in cases:
            size = c.get("nodes") and f"{c['nodes']} nodes" or f"{c.get('elements_half')} el. (half), {c.get('dofs')} dofs"
            lines.append(f"| {c['case']} | {c['method']} | {size} | {c['iterations']} | {c.get('halvings', '')} | {c['wall_s']} | "
                         f"{c['status'][:50]} | {c.get('stretch_max', float('nan')):.3f} | {c.get('non_elliptic_fraction', float('nan')):.2e} |")
    (OUT / f"{STEM}.md").write_text("\n".join(lines) + "\n")


def figure(record: dict, fields: list[pathlib.Path], path: pathlib.Path) -> None:
    """F_z(α) of every case (paper law and elliptic variant) and, per fields file, the largest
    principal stretch on the mid-plane y = 0 with the points where the law is not strongly elliptic."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2 + len(fields), figsize=(4.0 * (2 + len(fields)), 4.6), squeeze=False,
                             gridspec_kw={"width_ratios": [1.4, 1.0] + [0.8] * len(fields)})
    ax = axes[0, 0]
    for c in record.get("cases", []):
        style = "--" if "C01=0" in c["case"] else "-"
        marker = "o" if c["case"].startswith("pixmuscle") else ("s" if c["case"].startswith("q2") else "^")
        ax.plot(c["alpha"], c["Fz_N"], style, marker=marker, ms=3, lw=1, label=c["case"].replace("materials.muscle.", ""))
    ax.set_xlabel("activation α")
    ax.set_ylabel("F_z at z = 6 (N)")
    ax.set_title("reaction; dashed: C10 = 2.63, C01 = 0")
    ax.legend(fontsize=5.5)
    ax = axes[0, 1]
    for c in record.get("cases", []):
        if "non_elliptic_fraction_per_step" in c:
            ax.plot(c["alpha"][1:], 100 * np.asarray(c["non_elliptic_fraction_per_step"]), "--" if "C01=0" in c["case"] else "-",
                    marker=".", label=c["case"])
    ax.set_xlabel("activation α")
    ax.set_ylabel("volume where the law is not strongly elliptic (%)")
    ax.legend(fontsize=6)
    for ax, f in zip(axes[0, 2:], fields, strict=True):
        d = np.load(f)
        xq = d["xq"]
        near = xq[:, 1] <= np.quantile(xq[:, 1], 0.12)            # the quadrature layer next to y = 0
        size = 900.0 / max(1, near.sum()) ** 0.5
        sc = ax.scatter(xq[near, 0], xq[near, 2], c=d["stretch_max"][near], s=size, marker="s", cmap="viridis", vmin=1.0, vmax=2.0)
        bad = near & (d["qmin"] < 0)
        ax.scatter(xq[bad, 0], xq[bad, 2], s=0.25 * size, c="r", marker=".", linewidths=0)
        t = np.linspace(0, 6, 7)
        for x0 in (-2.0, 0.0, 2.0):                                # a few fibre lines (undeformed)
            ax.plot(x0 + t * np.tan(ANGLE), t, color="w", lw=0.5, alpha=0.7)
        ax.set_xlim(0, SIZE[0])
        ax.set_ylim(0, SIZE[2])
        ax.set_aspect("equal")
        ax.set_xlabel("x (cm)")
        ax.set_ylabel("z (cm)")
        ax.set_title(f"{f.stem.split('fields_')[-1]}, α = {float(d['alpha']):.2f}\nlargest principal stretch; red: not elliptic", fontsize=8)
        fig.colorbar(sc, ax=ax, shrink=0.8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=150)


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", nargs="*", default=[])
    ap.add_argument("--append", action="store_true", help="merge into the existing record")
    ap.add_argument("--check-law", action="store_true")
    ap.add_argument("--ellipticity", action="store_true")
    ap.add_argument("--fields", nargs="*", default=[], help="FE cases whose fields at the end are saved (.npz)")
    ap.add_argument("--tables", action="store_true", help="only rewrite the .md from the .json")
    ap.add_argument("--figure", nargs="*", default=None,
                    help="write docs/figures/active_block.png from the record and these fields files (.npz)")
    args = ap.parse_args(argv)
    path = OUT / f"{STEM}.json"
    record = json.loads(path.read_text()) if (args.append or args.tables or args.figure is not None) and path.exists() else {}
    if not args.tables and args.figure is None:
        if args.check_law:
            record["law_check"] = check_law()
            print(json.dumps(record["law_check"]), flush=True)
        if args.ellipticity:
            record["ellipticity"] = ellipticity_limits()
            print(json.dumps(record["ellipticity"]), flush=True)
        cases = {c["case"]: c for c in record.get("cases", [])}
        command = " ".join([".venv/bin/python benchmarks/bench_active_block.py", *argv])
        whole = Run(defaults=False, command=command)
        for spec in args.cases:
            case_run = Run(defaults=False, command=command)
            kind, arg, opts = parse_case(spec)
            if kind == "pixmuscle":
                row = run_pixmuscle(arg, opts)
            else:
                fpath = OUT / f"{STEM}_fields_{''.join(ch if ch.isalnum() else '_' for ch in spec)}.npz" if spec in args.fields else None
                row = run_fe(kind, arg, fpath, opts)
                row["case"] = spec
            row.update(case_run.fields())
            cases[row["case"]] = row
            print(json.dumps({k: v for k, v in row.items() if k not in ("alpha",)}), flush=True)
        record["cases"] = sorted(cases.values(), key=lambda c: (c["case"].split(":")[0], c.get("dofs", c.get("nodes", 0))))
        record.setdefault("runs", []).append(whole.fields())
    write(record)
    if args.figure is not None:
        figure(record, [pathlib.Path(f) for f in args.figure], pathlib.Path(__file__).parents[1] / "docs" / "figures" / "active_block.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

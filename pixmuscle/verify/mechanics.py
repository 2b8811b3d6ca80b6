"""Verification of the meshfree solver against independent truths.

Each check compares the SCNI–RKPM solver (:mod:`pixmuscle.mechanics.solve`) with something it
does not share code with:

``patch_test``
    linear patch test on an irregular voxel domain (an L-shaped block with a hole): the SCNI
    gradients of u = A X + c reproduce A, and the linear-elastic solve with that field prescribed
    reproduces it in the interior (analytic truth);
``stabilization_check``
    eigenvalues of the small-strain stiffness of a free block (six rigid-body zero modes) and of a
    block clamped on its outer layers (lowest modes oscillatory or smooth), with and without NSNI;
``uniaxial_check`` / ``isometric_check`` / ``oblique_check``
    homogeneous-deformation reference solutions of :mod:`pixmuscle.mechanics.homogeneous`
    (1-D root finding / 5-unknown energy minimisation on the material law alone);
``tendon_comparison``
    the paper's Example 1 against a scikit-fem finite-element solution on the same voxel domain
    (:mod:`pixmuscle.verify.tendon_fem`).

:func:`verify_mechanics` runs the fast checks, prints a table and writes CSV + PNG;
:func:`verify_tendon` runs Example 1 at a finer resolution and writes the comparison plot.
"""

from __future__ import annotations

import csv
import logging
import pathlib
import time

import numpy as np
import scipy.sparse.linalg as spla

from ..config import parse_section
from ..mechanics.assembly import Assembler, support_pattern
from ..mechanics.config import SolveConfig
from ..mechanics.scni import build_scni, face_incidence, support_radius
from ..mechanics.stabilization import gradient_differences, stabilization_stiffness
from ..model.model import Model
from ..model.tissues import CONNECTIVE_TISSUE, MUSCLE

# ----------------------------------------------------------------------------------------------
# models


def mask_model(mask, spacing, *, tissue: int = CONNECTIVE_TISSUE, fiber=(0.0, 0.0, 1.0), origin=(0.0, 0.0, 0.0)) -> Model:
    """Pixel-point model of a boolean voxel mask: one tissue, uniform fibre, the builder's node sets.

    Parameters
    ----------
    mask : (I, J, K) bool
    spacing : (3,) float, cm
    tissue : int
        Tissue code of every node.
    fiber : (3,) float
        Fibre direction of muscle nodes (normalised).
    """
    from ..model.nodesets import compute_node_sets

    mask = np.asarray(mask, bool)
    if mask.ndim != 3 or not mask.any():
        raise ValueError("mask must be a non-empty 3-D boolean volume")
    h = np.asarray(spacing, float)
    ijk = np.argwhere(mask).astype(np.int32)
    n = ijk.shape[0]
    X = np.asarray(origin, float) + ijk * h
    fib = np.zeros((n, 3))
    names = []
    if tissue == MUSCLE:
        fib[:] = np.asarray(fiber, float) / np.linalg.norm(fiber)
        names = ["muscle"]
    sets = compute_node_sets(ijk, mask.shape)
    return Model(X=X, ijk=ijk, tissue=np.full(n, tissue, np.int8), muscle_id=np.full(n, int(tissue == MUSCLE), np.int16),
                 fiber=fib, muscle_names=names, spacing=h, origin=np.asarray(origin, float),
                 shape=np.asarray(mask.shape, np.int64), sets=sets)


def irregular_mask(n: int = 10, nz: int = 6) -> np.ndarray:
    """L-shaped block (n × n × nz minus a corner quadrant) with a through-hole: an irregular voxel domain."""
    m = np.ones((n, n, nz), bool)
    h = n // 2
    m[h:, h:, :] = False  # L-shape
    m[1:3, h + 1:h + 3, 1:nz - 1] = False  # closed cavity in the upper arm
    return m


def linear_elastic_tangent(n: int, lam: float, mu: float) -> np.ndarray:
    """Small-strain isotropic elasticity tensor A_iJkL = λ δ_iJ δ_kL + μ (δ_ik δ_JL + δ_iL δ_Jk), (n, 3, 3, 3, 3)."""
    d = np.eye(3)
    A = lam * np.einsum("ij,kl->ijkl", d, d) + mu * (np.einsum("ik,jl->ijkl", d, d) + np.einsum("il,jk->ijkl", d, d))
    return np.ascontiguousarray(np.broadcast_to(A, (n, 3, 3, 3, 3)))


def linear_stiffness(model: Model, *, lam: float = 100.0, mu: float = 10.0, stabilization: str = "nsni",
                     coefficient: float = 1.0, modulus: str = "shear", a_over_h=(1.65, 1.65, 1.65)):
    """Small-strain stiffness K = Σ_L V_L B̃ᵀ C B̃ (+ NSNI) of a model (CSR, 3N × 3N) and its SCNI data."""
    sup = support_radius(model.spacing, a_over_h)
    scni = build_scni(model.X, model.ijk, model.spacing, sup, face_gradients=True)
    asm = Assembler(support_pattern(face_incidence(scni.faces, scni.volume), scni.psi_faces))
    C = linear_elastic_tangent(model.n_nodes, lam, mu)
    data = asm.fill(asm.on_support(scni.G), C, scni.volume)
    if stabilization == "nsni":
        stabilization_stiffness(scni, asm, C, coefficient=coefficient, modulus=modulus, out=data)
    return asm.matrix(data).tocsr(), scni


# ----------------------------------------------------------------------------------------------
# linear patch test


def patch_test(mask=None, spacing=(0.1, 0.12, 0.25), *, stabilization: str = "nsni", seed: int = 0) -> dict:
    """Linear patch test on an irregular voxel domain.

    With u = A X + c (random A, c) and small-strain isotropic elasticity (λ = 100, μ = 10 N/cm²):

    * ``gradient_error``: max |G_k u − A[:, k]| over all cells (smoothed gradients reproduce A);
    * ``integration_error``: max |Σ_L V_L G_k[L, I] − Σ_boundary faces A_f n_k Ψ_I(x_f)| (discrete
      divergence theorem of SCNI);
    * ``dirichlet_error``: the coefficients of every node whose shape function is non-zero on a
      boundary face are prescribed (d = A X + c, exact for a linear basis), the others solved for
      with no load; max |d − (A X + c)| over the solved nodes, relative to max |A X + c|;
    * ``traction_error``: only the outer layer (nodes with a boundary face) prescribed and the
      exact traction σ n applied on every boundary face (one-point face quadrature); same error.

    Returns
    -------
    dict
        The four errors and the node counts.
    """
    mask = irregular_mask(12, 8) if mask is None else np.asarray(mask, bool)
    model = mask_model(mask, spacing)
    rng = np.random.default_rng(seed)
    A = rng.uniform(-0.01, 0.01, (3, 3))
    c = rng.uniform(-0.01, 0.01, 3)
    lam, mu = 100.0, 10.0
    K, scni = linear_stiffness(model, lam=lam, mu=mu, stabilization=stabilization)
    X = model.X
    exact = X @ A.T + c
    grad_err = max(float(np.abs(scni.G[k] @ exact - A[:, k]).max()) for k in range(3))
    faces = scni.faces
    bnd = faces.boundary
    sgn = faces.normal_sign
    integ = 0.0
    for k in range(3):
        lhs = scni.G[k].T @ scni.volume
        on = bnd & (faces.axis == k)
        rhs = scni.psi_faces[on].T @ (faces.area[on] * sgn[on])
        integ = max(integ, float(np.abs(lhs - rhs).max()))
    scale = float(np.abs(exact).max())
    # (1) Dirichlet on every node whose Ψ reaches the boundary
    touches = np.asarray(abs(scni.psi_faces[bnd]).sum(axis=0)).ravel() > 0
    dir_err = _solve_patch(K, exact, touches, np.zeros_like(exact)) / scale
    # (2) outer layer prescribed + exact traction on the boundary faces
    outer = np.zeros(model.n_nodes, bool)
    outer[faces.low[bnd & (faces.low >= 0)]] = True
    outer[faces.high[bnd & (faces.high >= 0)]] = True
    eps = 0.5 * (A + A.T)
    sigma = lam * np.trace(eps) * np.eye(3) + 2 * mu * eps
    normals = np.zeros((int(bnd.sum()), 3))
    normals[np.arange(normals.shape[0]), faces.axis[bnd]] = sgn[bnd]
    traction = (normals @ sigma.T) * faces.area[bnd][:, None]  # σ n A_f (σ symmetric)
    f_ext = scni.psi_faces[bnd].T @ traction
    tr_err = _solve_patch(K, exact, outer, f_ext) / scale
    return dict(gradient_error=grad_err, integration_error=integ, dirichlet_error=dir_err, traction_error=tr_err,
                n_nodes=model.n_nodes, n_prescribed_dirichlet=int(touches.sum()), n_free_dirichlet=int((~touches).sum()),
                n_prescribed_traction=int(outer.sum()))


def _solve_patch(K, exact, prescribed, f_ext) -> float:
    fixed = np.repeat(prescribed, 3)
    free = ~fixed
    if not free.any():
        raise ValueError("patch test domain has no free nodes; use a larger mask")
    u = exact.reshape(-1).copy()
    rhs = f_ext.reshape(-1)[free] - K[free][:, fixed] @ u[fixed]
    x = spla.spsolve(K[free][:, free].tocsc(), rhs)
    return float(np.abs(x - u[free]).max())


# ----------------------------------------------------------------------------------------------
# stabilisation


def stabilization_check(free_shape=(5, 5, 5), clamped_n: int = 10, spacing=(0.1, 0.1, 0.1), n_modes: int = 6) -> dict:
    """Effect of the NSNI stabilisation on the small-strain stiffness (λ = 100, μ = 10 N/cm²).

    * ``free_zero_modes``: number of eigenvalues of the free block's stiffness below 1e-10·λ_max,
      per method (``none``, ``nsni``); 6 = rigid-body modes only.
    * ``checker_interior_gradient``: max over interior cells of |G_k d| for the oscillating
      field d_I = (−1)^(i+j+k): SCNI's smoothed gradient misses it entirely (a zero-energy mode of
      every interior cell), NSNI's gradient differences do not (``checker_interior_nsni``).
    * ``clamped_*``: lowest ``n_modes`` eigenvalues (N/cm) of a block with its two outer node layers
      fixed and an oscillation index per mode, ‖Δd‖ / ‖Δ(d·(−1)^(i+j+k))‖ along x (> 1: the mode
      alternates in sign from node to node, i.e. it is spurious; < 1: smooth).
    """
    out = {}
    model = mask_model(np.ones(free_shape, bool), spacing)
    for method in ("none", "nsni"):
        K, _ = linear_stiffness(model, stabilization=method)
        ev = np.linalg.eigvalsh(K.toarray())
        out[f"free_zero_modes_{method}"] = int(np.sum(ev < 1e-10 * ev.max()))
        out[f"free_first_nonzero_{method}"] = float(np.sort(ev)[6] / ev.max())
    n = clamped_n
    model = mask_model(np.ones((n, n, n), bool), spacing)
    ijk = model.ijk - model.ijk.min(axis=0)
    chk = (-1.0) ** ijk.sum(axis=1)
    deep = np.all((ijk >= 3) & (ijk <= n - 4), axis=1)
    inner = np.all((ijk >= 2) & (ijk <= n - 3), axis=1)
    free = np.repeat(inner, 3)
    for method in ("none", "nsni"):
        K, scni = linear_stiffness(model, stabilization=method)
        if method == "none":
            out["checker_interior_gradient"] = max(float(np.abs((G @ chk)[deep]).max()) for G in scni.G)
        else:
            H = gradient_differences(scni)
            out["checker_interior_nsni"] = max(float(np.abs((H[k][J] @ chk)[deep]).max()) for k in range(3) for J in range(3))
        Kf = K[free][:, free].toarray()
        ev, V = np.linalg.eigh(Kf)
        osc = []
        for j in range(n_modes):
            d = np.zeros((model.n_nodes, 3))
            d[inner] = V[:, j].reshape(-1, 3)
            grid = np.zeros((n, n, n, 3))
            grid[tuple(ijk.T)] = d
            gridc = np.zeros((n, n, n, 3))
            gridc[tuple(ijk.T)] = d * chk[:, None]
            osc.append(float(np.linalg.norm(np.diff(grid, axis=0)) / np.linalg.norm(np.diff(gridc, axis=0))))
        out[f"clamped_eigenvalues_{method}"] = ev[:n_modes].tolist()
        out[f"clamped_oscillation_{method}"] = osc
    return out


# ----------------------------------------------------------------------------------------------
# homogeneous references


def _cfg(**kw) -> SolveConfig:
    return parse_section(SolveConfig, kw, "solve")


def roller_bcs(model: Model, top: float) -> list[dict]:
    """Roller ends along z: z_min fixed in z, z_max displaced by ``top`` (cm) in z; rigid motions removed
    by fixing x, y of the bottom node nearest the axis and y of a bottom node on the +x side."""
    X = model.X
    bottom = X[model.sets["z_min"]]
    centre = bottom.mean(axis=0)
    p0 = bottom[np.argmin(np.sum((bottom - centre) ** 2, axis=1))]
    p1 = bottom[np.argmax(bottom[:, 0] - 1e-3 * np.abs(bottom[:, 1] - p0[1]))]
    return [
        {"nodes": "z_min", "fix": ["z"]},
        {"nodes": "z_max", "displace": {"z": float(top)}} if top else {"nodes": "z_max", "fix": ["z"]},
        {"point": p0.tolist(), "fix": ["x", "y"], "name": "pin"},
        {"point": p1.tolist(), "fix": ["y"], "name": "pin_rotation"},
    ]


def _block_dims(model: Model):
    h = np.asarray(model.spacing, float)
    ext = model.ijk.max(axis=0) - model.ijk.min(axis=0) + 1
    return float(ext[2] * h[2]), float(ext[0] * h[0] * ext[1] * h[1])


def uniaxial_check(stretches=(1.02, 1.05, 1.10), shape=(4, 4, 8), spacing=(0.2, 0.2, 0.3), steps_per_case: int = 2,
                   **solve_kw) -> list[dict]:
    """Connective-tissue bar with roller ends stretched to each λ; end force vs :func:`homogeneous.uniaxial_bar`.

    One solve to the largest stretch with load steps at every requested stretch; the force of step
    k (λ_k = 1 + t_k (λ_max − 1)) is compared with the homogeneous bar of the same length.
    """
    from ..mechanics import homogeneous
    from ..mechanics.solve import make_materials, solve

    model = mask_model(np.ones(shape, bool), spacing)
    L, area = _block_dims(model)
    lam_max = max(stretches)
    # load factors of the requested stretches (equal sub-steps between them)
    targets = sorted((s - 1) / (lam_max - 1) for s in stretches)
    n_steps = _common_steps(targets, steps_per_case)
    cfg = _cfg(steps=n_steps, activation={"from": 0.0, "to": 0.0}, boundary_conditions=roller_bcs(model, (lam_max - 1) * L),
               **solve_kw)
    res = solve(model, cfg)
    mat = make_materials(cfg.materials)[CONNECTIVE_TISSUE]
    rows = []
    for s in stretches:
        k = int(round((s - 1) / (lam_max - 1) * n_steps))
        ref = homogeneous.uniaxial_bar(mat, s, area)["force"]
        f = float(res.force("z_max")[k])
        rows.append(dict(check="uniaxial bar (connective tissue)", parameter=f"stretch {s:.2f}", force=f, reference=ref,
                         rel_error=(f - ref) / ref, balance=float(res.force("z_min")[k] / f - 1), nodes=model.n_nodes,
                         iterations=int(res.iterations[k])))
    return rows


def _common_steps(targets, per) -> int:
    for n in range(1, 200):
        if all(abs(t * n - round(t * n)) < 1e-9 for t in targets):
            return n * per
    raise ValueError(f"no common step count for load factors {targets}")


def isometric_check(alphas=(0.25, 0.5, 0.95), shape=(4, 4, 8), spacing=(0.2, 0.2, 0.3), fiber_angle_deg: float = 0.0,
                    steps: int = 20, **solve_kw) -> list[dict]:
    """Muscle block between roller ends at fixed length, activation ramped 0 → 1 in ``steps`` steps.

    Fibres in the xz plane at ``fiber_angle_deg`` from the axis z. The end force at each α is
    compared with :func:`homogeneous.isometric_block` (fibres along z) or
    :func:`homogeneous.homogeneous_min_energy` with the third row of F fixed to (0, 0, 1)
    (oblique fibres; then the block really shears and the homogeneous state is only an
    approximation, see that function's caveat).
    """
    from ..mechanics import homogeneous
    from ..mechanics.solve import make_materials, solve

    th = np.deg2rad(fiber_angle_deg)
    fiber = (np.sin(th), 0.0, np.cos(th))
    model = mask_model(np.ones(shape, bool), spacing, tissue=MUSCLE, fiber=fiber)
    L, area = _block_dims(model)
    cfg = _cfg(steps=steps, activation={"from": 0.0, "to": 1.0}, boundary_conditions=roller_bcs(model, 0.0), **solve_kw)
    res = solve(model, cfg)
    mat = make_materials(cfg.materials)[MUSCLE]
    rows = []
    for a in alphas:
        k = int(np.argmin(np.abs(res.alpha - a)))
        if abs(res.alpha[k] - a) > 1e-9:
            raise ValueError(f"activation {a} is not a load step of {steps} steps from 0 to 1")
        if fiber_angle_deg == 0.0:
            ref = homogeneous.isometric_block(mat, a, area, fiber=fiber)["force"]
            name = "isometric block, fibres along z"
        else:
            ref = homogeneous.homogeneous_min_energy(mat, 1.0, area, fiber=fiber, activation=a)["force"]
            name = f"isometric block, fibres at {fiber_angle_deg:g} deg"
        f = float(res.force("z_max")[k])
        rows.append(dict(check=name, parameter=f"alpha {a:.2f}", force=f, reference=ref, rel_error=(f - ref) / ref,
                         balance=float(res.force("z_min")[k] / f - 1), nodes=model.n_nodes,
                         iterations=int(res.iterations[k])))
    return rows


def oblique_check(alphas=(0.25, 0.5, 0.95), shape=(4, 4, 8), spacing=(0.2, 0.2, 0.3), fiber_angle_deg: float = 30.0,
                  steps: int = 20, variants=("roller", "uz"), **solve_kw) -> list[dict]:
    """Muscle block with oblique fibres against :func:`homogeneous.homogeneous_min_energy`.

    Two variants, at each α:

    * ``roller ends``: the block of :func:`isometric_check` (ends fixed in z only, lateral faces
      free). With oblique fibres its solution is *not* homogeneous (the homogeneous state would
      need axial shear tractions P_zx on the lateral faces, see ``homogeneous_min_energy``), so
      the end force is only compared for information.
    * ``u_z = 0 everywhere``: every node held in z (penalty at the nodes, factor 10³), x and y free except the
      rigid-motion pins. Then F's third row is (0, 0, 1) at every cell, which is exactly the
      homogeneous problem; the nodal Cauchy stress σ_zz (and the force σ_zz-based P_zz · area) must
      match the homogeneous minimum-energy state.
    """
    from ..mechanics import homogeneous
    from ..mechanics.solve import make_materials, solve

    th = np.deg2rad(fiber_angle_deg)
    fiber = (np.sin(th), 0.0, np.cos(th))
    rows = []
    if "roller" in variants:
        rows = isometric_check(alphas, shape, spacing, fiber_angle_deg=fiber_angle_deg, steps=steps, **solve_kw)
        for r in rows:
            r["check"] = f"oblique fibres {fiber_angle_deg:g} deg, roller ends (inhomogeneous)"
    if "uz" not in variants:
        return rows
    model = mask_model(np.ones(shape, bool), spacing, tissue=MUSCLE, fiber=fiber)
    model.sets["all"] = np.arange(model.n_nodes, dtype=np.int64)
    _, area = _block_dims(model)
    bcs = [{"nodes": "all", "fix": ["z"]}] + roller_bcs(model, 0.0)[2:]
    # the constraint stands in for an exact u_z = 0 at every node: a stiff penalty (factor 10³)
    # keeps the gap at round-off level relative to the strains compared here
    kw = {"penalty": {"factor": 1.0e3}, **solve_kw}
    cfg = _cfg(steps=steps, activation={"from": 0.0, "to": 1.0}, boundary_conditions=bcs, **kw)
    res = solve(model, cfg)
    mat = make_materials(cfg.materials)[MUSCLE]
    for a in alphas:
        k = int(np.argmin(np.abs(res.alpha - a)))
        ref = homogeneous.homogeneous_min_energy(mat, 1.0, area, fiber=fiber, activation=a)
        F, P = ref["F"], ref["P"]
        sig = P @ F.T / np.linalg.det(F)
        s_zz = res.cauchy[k][:, 2]
        # P_zz = σ_zz J / F_zz... with the third row of F = (0, 0, 1): P_zz = J (σ F⁻ᵀ)_zz
        Pzz = float(np.mean(s_zz)) * (P[2, 2] / sig[2, 2])
        f, fref = Pzz * area, float(ref["force"])
        rows.append(dict(check=f"oblique fibres {fiber_angle_deg:g} deg, u_z = 0 everywhere (homogeneous)",
                         parameter=f"alpha {a:.2f}", force=f, reference=fref, rel_error=(f - fref) / fref,
                         stress_spread=float((s_zz.max() - s_zz.min()) / abs(sig[2, 2])), nodes=model.n_nodes,
                         iterations=int(res.iterations[k]), balance=0.0))
    return rows


# ----------------------------------------------------------------------------------------------
# Example 1: tendon vs finite elements


def tendon_model(h=(0.2, 0.2, 1.0)):
    """Meshfree model, voxel mask and affine of the Example-1 tendon at voxel size ``h`` (cm)."""
    from .tendon_geometry import tendon_voxels

    mask, affine = tendon_voxels(h=h)
    model = mask_model(mask, np.diag(affine)[:3], origin=affine[:3, 3])
    return model, mask, affine


def tendon_comparison(h=(0.2, 0.2, 1.0), stretch: float = 2.0, steps: int = 5, refine=1, element: str = "mixed",
                      fem: dict | None = None, **solve_kw) -> dict:
    """Example 1: reaction at the fixed end per step, meshfree vs scikit-fem on the same voxel domain.

    Bottom (z_min) fixed in x, y, z; top (z_max) fixed in x, y and displaced by ``stretch`` cm in z
    over ``steps`` equal steps; connective tissue (Table 1).

    Returns
    -------
    dict
        ``fem`` and ``meshfree`` (each with ``displacement`` and ``force`` per step, the force =
        reaction at the fixed end · (−z), tension positive), ``rel_error`` per step, node counts
        and timings.
    """
    from ..mechanics.solve import solve
    from ..progress import newton_feed, progress
    from .tendon_fem import tendon_fem_reaction

    log = logging.getLogger("pixmuscle.verify.tendon")
    model, mask, affine = tendon_model(h)
    t0 = time.perf_counter()
    if fem is None:
        log.info("tendon: finite-element reference (scikit-fem, %s elements, %d steps) ...", element, steps)
        fem = tendon_fem_reaction(mask, affine, stretch=stretch, steps=steps, refine=refine, element=element, bc="clamped")
    t_fem = time.perf_counter() - t0
    cfg = _cfg(steps=steps, activation={"from": 0.0, "to": 0.0}, boundary_conditions=[
        {"nodes": "z_min", "fix": ["x", "y", "z"]},
        {"nodes": "z_max", "fix": ["x", "y"], "displace": {"z": float(stretch)}},
    ], **solve_kw)
    log.info("tendon: FE reference done in %.1f s; meshfree solve (%d nodes, %d load steps) ...",
             time.perf_counter() - t0, model.n_nodes, steps)
    t1 = time.perf_counter()
    with progress(steps + 1, "tendon load step") as bar, newton_feed(bar):
        res = solve(model, cfg, progress=bar)
    t_mf = time.perf_counter() - t1
    log.info("tendon: meshfree solve done in %.1f s", t_mf)
    mf = dict(displacement=res.load_factor * stretch, force=res.force("z_min"), force_top=res.force("z_max"))
    f_fe = np.asarray(fem["force"], float)
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.where(f_fe != 0, (mf["force"] - f_fe) / f_fe, 0.0)
    return dict(fem=fem, meshfree=mf, rel_error=rel, n_nodes=model.n_nodes, fem_dofs=int(fem.get("dofs", 0)),
                fem_s=t_fem, meshfree_s=t_mf, h=tuple(float(x) for x in h), iterations=res.iterations.tolist())


# ----------------------------------------------------------------------------------------------
# reports


def _print_rows(rows, console, title):
    try:
        from rich.console import Console
        from rich.table import Table
    except ImportError:  # pragma: no cover
        for r in rows:
            print(r)
        return
    console = console or Console(width=160)
    t = Table(title=title)
    for col in ("check", "parameter", "value", "reference", "error", "tolerance", "ok"):
        t.add_column(col)
    for r in rows:
        t.add_row(r["check"], r["parameter"], r["value"], r["reference"], r["error"], r["tolerance"],
                  "✔" if r["ok"] else "✘")
    console.print(t)


def verify_mechanics(outdir, console=None) -> dict:
    """Run the fast mechanics checks, print a table, write ``mechanics_checks.csv`` and ``mechanics_checks.png``.

    Returns
    -------
    dict
        ``rows`` (one per check with value, reference, error, tolerance, ok), ``patch``,
        ``stabilization``, ``all_ok``, and the paths written.
    """
    outdir = pathlib.Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    rows = []
    patch = patch_test()
    for key, tol in (("gradient_error", 1e-10), ("integration_error", 1e-10), ("dirichlet_error", 1e-8), ("traction_error", 1e-8)):
        rows.append(dict(check="linear patch test (L-shape with cavity)", parameter=key.replace("_", " "),
                         value=f"{patch[key]:.2e}", reference="0", error=f"{patch[key]:.2e}", tolerance=f"{tol:g}",
                         ok=patch[key] <= tol))
    stab = stabilization_check(clamped_n=12)
    rows.append(dict(check="free block zero eigenvalues", parameter="NSNI", value=str(stab["free_zero_modes_nsni"]),
                     reference="6", error="", tolerance="exact", ok=stab["free_zero_modes_nsni"] == 6))
    rows.append(dict(check="free block zero eigenvalues", parameter="no stabilisation", value=str(stab["free_zero_modes_none"]),
                     reference="6", error="", tolerance="(info)", ok=True))
    osc_none = max(stab["clamped_oscillation_none"])
    osc_nsni = max(stab["clamped_oscillation_nsni"])
    rows.append(dict(check="clamped block lowest modes", parameter="oscillation index, SCNI / NSNI",
                     value=f"{osc_none:.2f} / {osc_nsni:.2f}", reference="< 1 smooth", error="",
                     tolerance="NSNI < 1", ok=osc_nsni < 1.0))
    mech = []
    mech += uniaxial_check()
    mech += isometric_check()
    oblique = oblique_check(fiber_angle_deg=30.0)
    for r in mech + oblique:
        info_only = "roller" in r["check"]
        tol = 0.005 if "oblique" not in r["check"] else 0.01
        rows.append(dict(check=r["check"], parameter=r["parameter"], value=f"{r['force']:.5g} N", reference=f"{r['reference']:.5g} N",
                         error=f"{100 * r['rel_error']:+.4f} %", tolerance="(info)" if info_only else f"{100 * tol:g} %",
                         ok=True if info_only else abs(r["rel_error"]) <= tol))
    _print_rows(rows, console, "mechanics verification (SCNI–RKPM vs independent truths)")
    csv_path = outdir / "mechanics_checks.csv"
    with open(csv_path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    png = outdir / "mechanics_checks.png"
    _plot_checks(mech + oblique, stab, png)
    return dict(rows=rows, patch=patch, stabilization=stab, homogeneous=mech + oblique,
                all_ok=all(r["ok"] for r in rows), csv=csv_path, png=png)


def _plot_checks(rows, stab, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, bx) = plt.subplots(1, 2, figsize=(10, 4))
    rows = [r for r in rows if "roller" not in r["check"]]
    labels = [f"{r['check'].split(',')[0].replace('isometric block', 'iso')}\n{r['parameter']}" for r in rows]
    err = [max(abs(r["rel_error"]), 1e-12) for r in rows]
    ax.bar(range(len(rows)), err, color=["C0" if e <= 0.005 else "C3" for e in err])
    ax.set_yscale("log")
    ax.axhline(0.005, color="k", ls="--", lw=0.8, label="tolerance 0.5 %")
    ax.legend(fontsize=7)
    ax.set_xticks(range(len(rows)))
    ax.set_xticklabels(labels, rotation=90, fontsize=6)
    ax.set_ylabel("|relative force error|")
    ax.set_title("vs homogeneous references", fontsize=9)
    for method, c in (("none", "C3"), ("nsni", "C0")):
        ev = np.asarray(stab[f"clamped_eigenvalues_{method}"])
        bx.plot(range(1, len(ev) + 1), ev, "o-", color=c, label=f"{'SCNI only' if method == 'none' else 'SCNI + NSNI'}")
    bx.set_xlabel("mode")
    bx.set_ylabel("eigenvalue (N/cm)")
    bx.set_title("lowest modes of a clamped block", fontsize=9)
    bx.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def verify_tendon(outdir, console=None, h=(0.2, 0.2, 0.125), steps: int = 10, refine=1, **solve_kw) -> dict:
    """Paper Example 1 at voxel size ``h``: meshfree vs scikit-fem reaction per step; writes
    ``tendon_comparison.png`` (via :func:`pixmuscle.verify.tendon_fem.plot_comparison`) and
    ``tendon_comparison.csv``."""
    from .tendon_fem import plot_comparison

    outdir = pathlib.Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    cmp = tendon_comparison(h=h, steps=steps, refine=refine, **solve_kw)
    png = outdir / "tendon_comparison.png"
    plot_comparison(cmp["fem"], cmp["meshfree"], png)
    csv_path = outdir / "tendon_comparison.csv"
    with open(csv_path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["step", "top_displacement_cm", "force_fem_N", "force_meshfree_N", "rel_error"])
        for k, (d, a, b, e) in enumerate(zip(cmp["fem"]["displacement"], cmp["fem"]["force"], cmp["meshfree"]["force"], cmp["rel_error"], strict=True)):
            w.writerow([k, f"{d:.6g}", f"{a:.8g}", f"{b:.8g}", f"{e:.3e}"])
    worst = float(np.max(np.abs(cmp["rel_error"][1:])))
    try:
        from rich.console import Console

        (console or Console()).print(
            f"Example 1 tendon (h = {h} cm, {cmp['n_nodes']} nodes, FE {cmp['fem_dofs']} dofs): largest force difference "
            f"{100 * worst:.2f} % (tolerance 3 %); meshfree {cmp['meshfree_s']:.1f} s, FE {cmp['fem_s']:.1f} s")
    except ImportError:  # pragma: no cover
        pass
    cmp.update(png=png, csv=csv_path, max_rel_error=worst, ok=worst <= 0.03)
    return cmp


__all__ = ["patch_test", "stabilization_check", "uniaxial_check", "isometric_check", "oblique_check", "tendon_comparison",
           "verify_mechanics", "verify_tendon", "mask_model", "irregular_mask", "linear_stiffness", "roller_bcs"]


"""Benchmark of the meshfree solver against hexahedral finite elements on the same voxels (paper Examples 1 and 2).

Tendon cases: the Example 1 tendon of :func:`pixmuscle.verify.mechanics.tendon_model` at voxel size
h = (0.2, 0.2, 0.5) cm (800 voxels); connective tissue, paper eq. (27),
W = C10 (Ī1 − 3) + C20 (Ī1 − 3)² + C30 (Ī1 − 3)³ + K/2 (J − 1)², Ī1 = J^(−2/3) I1, with C10 = 30,
C20 = 80, C30 = 800, K = 50 000 N/cm². Bottom end z_min fixed in x, y, z; top end z_max held in
x, y and displaced +2 cm in z over ``--steps`` equal load steps. Measured: the reaction force at
the fixed end at 2 cm (N, tension positive), its error against a converged reference, wall time
and peak RSS of each case.

Methods (``--cases``):

``pixmuscle:nodal`` / ``pixmuscle:projected``
    pixmuscle's SCNI–RKPM solver, one node per voxel, with ``solve.volumetric.method`` ``nodal``
    (K/2 (J − 1)² at every node, as in the paper) or ``projected`` (mean dilatation per patch of
    voxels, the default: 2 × 2 × 3 voxels; the record's +0.36 % was measured with 1 × 1 × 3); every
    other setting at its default.
``felupe:RXxRYxRZ`` (e.g. ``felupe:1x1x1``, ``felupe:2x2x2``)
    FElupe's trilinear hexahedra (hex8) in the mixed Q1/P0/P0 (u, p, J̄) form of
    ``SolidBodyNearlyIncompressible`` (mean dilatation per element, pressure and dilatation
    condensed out), with FElupe's isochoric Yeoh law on Ī1 (tensortrax differentiates it) and
    bulk modulus K. The mesh is the voxel domain itself: each voxel of the mask split into
    RX × RY × RZ boxes, nodes at the box corners (from the affine), so the ends are the outer faces
    of the end slices. Newton by ``felupe.newtonraphson`` to a relative residual of 1e-4 (pixmuscle's default) with
    PARDISO (``pypardiso``, FElupe's recommended solver; SciPy's SuperLU when it is missing).

Leg cases (paper Example 2 set-up): the SYNTHETIC leg of ``bench_solve.py`` (``bench_solve.leg_case``,
imported from this folder; voxel size 0.156 × 0.156 × 0.5 cm; muscles with per-voxel fibres,
connective tissue and skin, fat; bone voxels and background are not part of the body), activation
α 0 → 0.95 in 10 equal load steps (whatever ``--steps`` says), both ends z_min and z_max fixed in
x, y, z, bone surfaces fixed in x, y. Measured: the reaction force F_z at z_max (N, tension
positive) at every step, its difference from pixmuscle's, Newton iterations, wall time, peak RSS.

``legSIZE:pixmuscle`` (SIZE a key of ``bench_solve.SIZES``: ``1.5k``, ``5k``, ...)
    pixmuscle's ``solve()`` with every default, as ``bench_solve.run_case(SIZE, "auto", 10, 0.95, None)``.
``legSIZE:pixmuscle:RXxRYxRZ`` (e.g. ``leg5k:pixmuscle:2x2x2``)
    the same on the same voxel domain with every voxel split into RX × RY × RZ voxels of its tissue and
    fibre (``bench_solve.leg_case(..., refine=...)``), one node each: pixmuscle's own refinement.
``legSIZE:felupe:RXxRYxRZ`` (e.g. ``leg5k:felupe:1x1x2``)
    FElupe hex8 Q1/P0/P0 on the body voxels (:func:`voxel_hex8_mesh`, each voxel split into
    RX × RY × RZ boxes), one ``SolidBodyNearlyIncompressible`` per tissue (the bulk modulus
    differs between tissues and is one number per body) whose isochoric material is pixmuscle's
    own law for that tissue (:func:`felupe_material`: the law's stress and tangent with its
    K/2 (J − 1)² removed, checked by :func:`check_felupe_material` before every such case), the
    law's bulk modulus in the body, the voxel's fibre per cell and α set per load step. Held:
    every node on the z_min and z_max faces (x, y, z) and on faces shared with bone voxels (x, y).
    Newton as in the tendon cases, each step from the last.

The reference is the scikit-fem mixed Q2–P1disc solution on the same voxel domain,
:func:`pixmuscle.verify.tendon_fem.tendon_fem_reaction` with ``refine=(1, 1, 4)``, 2 load steps
(15.467 N; 15.483 N at refine (1, 1, 2) and 15.485 N at (2, 2, 2), so converged to about 0.1 %). It is
computed in the run and kept in the results file; ``--reuse-reference`` takes it from there instead.

Every case runs in its own process (so its peak RSS is its own, imports included) with
``--threads`` threads for MKL/OpenMP/numba (default 1: on a machine shared with other jobs
oversubscribed MKL threads make the direct solves several times slower, and one thread gives
both methods the same footing).

Writes ``benchmarks/results/bench_vs_fe.json`` and ``bench_vs_fe.md`` (a tendon and a leg section). Without
``--append`` a run replaces the cases of the section(s) it measures and keeps the other's; the leg
cases never compute the tendon reference.

Usage (FElupe is in the optional extra ``bench``: ``.venv/bin/pip install -e '.[bench]'``)::

    .venv/bin/python benchmarks/bench_vs_fe.py                      # the DEFAULT_CASES and the reference
    .venv/bin/python benchmarks/bench_vs_fe.py --reuse-reference --append --cases felupe:3x3x3
    .venv/bin/python benchmarks/bench_vs_fe.py --append --cases leg5k:pixmuscle leg5k:felupe:1x1x1 leg5k:felupe:1x1x2
    .venv/bin/python benchmarks/bench_vs_fe.py --tables             # only rewrite the .md from the .json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import pathlib
import platform
import subprocess
import sys
import time

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from _record import Run, peak_rss_GB  # noqa: E402

OUT = pathlib.Path(__file__).parent / "results"
STEM = "bench_vs_fe"
H = (0.2, 0.2, 0.5)          # voxel size, cm
STRETCH = 2.0                # top displacement, cm
REFERENCE = {"refine": (1, 1, 4), "steps": 2, "element": "mixed", "bc": "clamped"}
DEFAULT_CASES = ["pixmuscle:nodal", "pixmuscle:projected", "felupe:1x1x1", "felupe:1x1x2", "felupe:1x1x4", "felupe:2x2x2"]
NEWTON_TOL = 1e-4            # FElupe: ‖f(free)‖ / ‖f(prescribed)‖, as pixmuscle's default residual tolerance
SHARED_NOTE = ("measured on a machine shared with other jobs (load average in meta): wall times are "
               "upper bounds and comparable only within one run")
THREAD_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS")
LEG_STEPS = 10               # leg cases: load steps of paper Example 2 (--steps is the tendon's)
LEG_ALPHA = 0.95             # leg cases: activation at the last load step
ISO_K = 1e-300               # N/cm²: bulk modulus left in a law for its isochoric part (the laws require K > 0)


def _bench_solve():
    """The sibling script ``benchmarks/bench_solve.py`` as a module (its SYNTHETIC leg: ``leg_case``, ``SIZES``)."""
    here = str(pathlib.Path(__file__).resolve().parent)
    if here not in sys.path:
        sys.path.insert(0, here)
    import bench_solve

    return bench_solve


def _refine(text: str) -> tuple[int, int, int] | None:
    """``RXxRYxRZ`` → (rx, ry, rz), whole numbers >= 1; None if it is not that."""
    parts = text.split("x")
    if len(parts) == 3 and all(p.isdigit() and int(p) >= 1 for p in parts):
        return tuple(int(p) for p in parts)
    return None


def is_leg(spec: str) -> bool:
    """Whether a case name is one of the leg cases (``legSIZE:...``)."""
    return spec.startswith("leg")


def parse_case(spec: str) -> tuple[str, object]:
    """Case name → (method, argument).

    ``pixmuscle:nodal|projected`` → ("pixmuscle", method); ``felupe:RXxRYxRZ`` → ("felupe", (rx, ry, rz));
    ``reference`` → ("reference", None); ``legSIZE:pixmuscle[:RXxRYxRZ]`` → ("leg:pixmuscle", (SIZE,
    (rx, ry, rz))) ((1, 1, 1) without the split) and ``legSIZE:felupe:RXxRYxRZ`` → ("leg:felupe", (SIZE,
    (rx, ry, rz))), SIZE a leg size of
    ``bench_solve.SIZES`` (``1.5k``, ``5k``, ...).
    """
    if spec == "reference":
        return "reference", None
    method, _, arg = spec.partition(":")
    if method == "pixmuscle" and arg in ("nodal", "projected"):
        return method, arg
    if method == "felupe" and _refine(arg):
        return method, _refine(arg)
    if is_leg(method) and method[3:] in _bench_solve().SIZES:
        kind, _, rest = arg.partition(":")
        if arg == "pixmuscle":
            return "leg:pixmuscle", (method[3:], (1, 1, 1))
        if kind == "pixmuscle" and _refine(rest):
            return "leg:pixmuscle", (method[3:], _refine(rest))
        if kind == "felupe" and _refine(rest):
            return "leg:felupe", (method[3:], _refine(rest))
    raise ValueError(f"case {spec!r}: expected pixmuscle:nodal, pixmuscle:projected, felupe:RXxRYxRZ (whole numbers "
                     f">= 1, e.g. felupe:2x2x2), legSIZE:pixmuscle[:RXxRYxRZ] or legSIZE:felupe:RXxRYxRZ (SIZE in "
                     f"{', '.join(_bench_solve().SIZES)}, e.g. leg5k:felupe:1x1x2)")


def voxel_hex8_mesh(mask: np.ndarray, affine: np.ndarray, refine=(1, 1, 1), with_voxels: bool = False):
    """Hexahedral mesh of the union of the voxel boxes of ``mask``, each split into ``refine`` boxes.

    Parameters
    ----------
    mask : ndarray of bool, shape (I, J, K)
        Voxels of the body.
    affine : ndarray, shape (4, 4)
        Grid-aligned voxel index → cm of the voxel centres (diagonal spacing).
    refine : sequence of 3 int
        Boxes per voxel edge along x, y, z.
    with_voxels : bool
        Also return the voxel of each box.

    Returns
    -------
    points : ndarray, shape (n, 3)
        Box corners, cm.
    cells : ndarray of int, shape (m, 8)
        Corner indices per box in VTK hexahedron order (bottom face counter-clockwise, then top).
    voxels : ndarray of int, shape (m, 3)
        Only with ``with_voxels``: the voxel index (i, j, k) of ``mask`` that each box lies in.
    """
    r = np.asarray(refine, int)
    h = np.diag(affine)[:3]
    fine = mask
    for a in range(3):
        fine = np.repeat(fine, r[a], axis=a)
    corner = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]])
    lattice = np.array(fine.shape) + 1
    boxes = np.argwhere(fine)
    flat = np.ravel_multi_index((boxes[:, None, :] + corner).reshape(-1, 3).T, lattice)
    used, cells = np.unique(flat, return_inverse=True)
    points = (affine[:3, 3] - 0.5 * h) + (h / r) * np.column_stack(np.unravel_index(used, lattice))
    if with_voxels:
        return points, cells.reshape(-1, 8), boxes // r
    return points, cells.reshape(-1, 8)


def peak_rss_gb() -> float:
    """Peak resident memory of this case's process tree, GB (:func:`_record.peak_rss_GB`)."""
    return peak_rss_GB()


def run_pixmuscle(method: str, steps: int) -> dict:
    """pixmuscle's solve of the tendon with ``solve.volumetric.method = method``."""
    from pixmuscle.mechanics.solve import solve
    from pixmuscle.verify.mechanics import _cfg, tendon_model

    model, _, _ = tendon_model(H)
    cfg = _cfg(steps=steps, activation={"from": 0.0, "to": 0.0}, volumetric={"method": method}, boundary_conditions=[
        {"nodes": "z_min", "fix": ["x", "y", "z"]},
        {"nodes": "z_max", "fix": ["x", "y"], "displace": {"z": STRETCH}},
    ])
    t0 = time.perf_counter()
    res = solve(model, cfg)
    wall = time.perf_counter() - t0
    return {"method": f"pixmuscle SCNI-RKPM, volumetric {method}", "nodes": model.n_nodes, "dofs": 3 * model.n_nodes,
            "elements_per_voxel": None, "status": res.status, "force_N": float(res.force("z_min")[-1]),
            "force_top_N": float(res.force("z_max")[-1]), "force_curve_N": [float(f) for f in res.force("z_min")],
            "newton_iterations_per_step": res.iterations.tolist()[1:], "linear_engine": res.info.get("linear_engine"),
            "wall_s": round(wall, 2), "peak_rss_GB": peak_rss_gb()}


def import_felupe(tensortrax: bool = True):
    """The ``felupe`` module (with tensortrax, which its ``Hyperelastic`` needs, if ``tensortrax``);
    exits with the install command when it is missing."""
    os.environ.setdefault("FELUPE_VERBOSE", "false")
    try:
        import felupe as fem
        if tensortrax:
            fem.Hyperelastic  # noqa: B018  (present only with tensortrax)
    except (ImportError, AttributeError):
        raise SystemExit("bench_vs_fe: felupe with tensortrax is needed for the felupe cases: "
                         ".venv/bin/pip install -e '.[bench]'") from None
    return fem


def direct_solver():
    """(spsolve, name): PARDISO (``pypardiso``, FElupe's recommended solver), else SciPy's SuperLU."""
    try:
        from pypardiso import spsolve
        return spsolve, "pardiso (pypardiso)"
    except ImportError:
        from scipy.sparse.linalg import spsolve
        return spsolve, "superlu (scipy)"


def run_felupe(refine: tuple[int, int, int], steps: int) -> dict:
    """FElupe hex8 Q1/P0/P0 solve of the tendon on its voxel domain, each voxel split into ``refine`` boxes."""
    fem = import_felupe()
    from pixmuscle.verify.mechanics import tendon_model
    from pixmuscle.verify.tendon_fem import CONNECTIVE_TISSUE

    solver, engine = direct_solver()
    C10, C20, C30, K = CONNECTIVE_TISSUE
    _, mask, affine = tendon_model(H)
    t0 = time.perf_counter()
    points, cells = voxel_hex8_mesh(mask, affine, refine)
    field = fem.FieldContainer([fem.Field(fem.RegionHexahedron(fem.Mesh(points, cells, "hexahedron")), dim=3)])
    umat = fem.Hyperelastic(fem.yeoh, C10=C10, C20=C20, C30=C30)     # isochoric: Ī1 = J^(-2/3) tr C
    solid = fem.SolidBodyNearlyIncompressible(umat, field, bulk=K)
    z = points[:, 2]
    bottom = fem.Boundary(field[0], mask=np.isclose(z, z.min()))                   # x, y, z fixed
    top_xy = fem.Boundary(field[0], mask=np.isclose(z, z.max()), skip=(0, 0, 1))   # x, y held
    top_z = fem.Boundary(field[0], mask=np.isclose(z, z.max()), skip=(1, 1, 0))    # z displaced
    bounds = {"bottom": bottom, "top_xy": top_xy, "top_z": top_z}
    dof0, dof1 = fem.dof.partition(field, bounds)
    curve, top, iterations = [0.0], 0.0, []
    for n in range(1, steps + 1):
        top_z.update(STRETCH * n / steps)
        res = fem.newtonraphson(items=[solid], x0=field, dof1=dof1, dof0=dof0, ext0=fem.dof.apply(field, bounds, dof0),
                                solver=solver, tol=NEWTON_TOL, verbose=0)
        # the residual at prescribed dofs is the force the support exerts on the body; at the bottom
        # (outward normal -z) tension is -f_z
        curve.append(float(-fem.tools.force(field, res.fun, bottom)[2]))
        top = float(fem.tools.force(field, res.fun, top_z)[2])
        iterations.append(int(res.iterations))
    wall = time.perf_counter() - t0
    return {"method": f"FElupe hex8 Q1/P0/P0, {'x'.join(map(str, refine))} per voxel", "nodes": len(points),
            "dofs": 3 * len(points), "elements": len(cells), "elements_per_voxel": list(refine), "status": "complete",
            "force_N": curve[-1], "force_top_N": top, "force_curve_N": curve, "newton_iterations_per_step": iterations,
            "linear_engine": engine, "felupe_version": fem.__version__, "wall_s": round(wall, 2),
            "peak_rss_GB": peak_rss_gb()}


def run_reference() -> dict:
    """The scikit-fem Q2–P1disc reference (:data:`REFERENCE` settings) on the voxel domain."""
    from pixmuscle.verify.mechanics import tendon_model
    from pixmuscle.verify.tendon_fem import tendon_fem_reaction

    _, mask, affine = tendon_model(H)
    t0 = time.perf_counter()
    res = tendon_fem_reaction(mask, affine, stretch=STRETCH, **REFERENCE)
    return {"method": "scikit-fem Q2-P1disc (reference)", "refine": list(REFERENCE["refine"]),
            "steps": REFERENCE["steps"], "dofs": res["dofs"], "symmetry_factor": res["symmetry_factor"],
            "force_N": float(res["force"][-1]), "force_top_N": float(res["force_top"][-1]),
            "wall_s": round(time.perf_counter() - t0, 2), "peak_rss_GB": peak_rss_gb()}


# ---------------------------------------------------------------------------------------------
# the SYNTHETIC leg (paper Example 2 set-up)


def isochoric(law):
    """The isochoric part of a pixmuscle material law: the same law with K = :data:`ISO_K`.

    The laws of :mod:`pixmuscle.mechanics.materials` add K/2 (J − 1)² to an isochoric energy of
    Ī1, Ī2, Ī4 and require K > 0; with K = 1e-300 N/cm² what is left of the volumetric stress and
    tangent (≤ 1e-300 · J² N/cm²) lies far below the rounding of any other term.
    :func:`check_felupe_material` verifies the split.

    Raises
    ------
    ValueError
        The law has no volumetric term K/2 (J − 1)² (no field ``K`` or ``bulk_modulus`` None).
    """
    if getattr(law, "bulk_modulus", None) is None or "K" not in {f.name for f in dataclasses.fields(law)}:
        raise ValueError(f"{type(law).__name__}: no volumetric term K/2 (J - 1)^2 to remove")
    return dataclasses.replace(law, K=ISO_K)


def felupe_material(law, fiber: np.ndarray | None = None):
    """FElupe material of the isochoric part of a pixmuscle law, for one solid body of hexahedra.

    Parameters
    ----------
    law : material law of :mod:`pixmuscle.mechanics.materials`
        ``stress(F, **kw)`` → P (n, 3, 3) and ``stress_tangent(F, **kw)`` → (P, A), A (n, 3, 3, 3, 3)
        = ∂P/∂F, with a volumetric term K/2 (J − 1)² (``bulk_modulus``).
    fiber : ndarray, shape (c, 3), optional
        Reference fibre direction per cell of the body, the same at each of its quadrature
        points; only for laws that need one (the muscle law).

    Returns
    -------
    felupe.Material
        ``stress([F, ζ], activation)`` → [P, ζ] and ``elasticity([F, ζ], activation)`` → [A] of
        ``isochoric(law)`` in FElupe's layout, F and P (3, 3, q, c), A (3, 3, 3, 3, q, c). The
        activation α is the material keyword ``activation`` (0 at first): set
        ``umat.kwargs["activation"]`` before each load step. The volumetric part belongs to the
        body, ``felupe.SolidBodyNearlyIncompressible(umat, field, bulk=law.bulk_modulus)``.
    """
    fem = import_felupe(tensortrax=False)
    from pixmuscle.mechanics.solve import material_kw

    iso = isochoric(law)
    fiber = None if fiber is None else np.asarray(fiber, float)

    def at_points(F, activation):
        """F (3, 3, q, c) → (c·q, 3, 3), cell by cell, and the law's keywords at those points."""
        q, c = F.shape[2:]
        Fn = np.ascontiguousarray(F.transpose(3, 2, 0, 1)).reshape(c * q, 3, 3)
        fib = None if fiber is None else np.repeat(fiber, q, axis=0)
        return Fn, material_kw(iso, fib, activation), (c, q)

    def stress(x, activation=0.0):
        Fn, kw, (c, q) = at_points(x[0], activation)
        P = iso.stress(Fn, **kw).reshape(c, q, 3, 3)
        return [np.ascontiguousarray(P.transpose(2, 3, 1, 0)), x[-1]]

    def elasticity(x, activation=0.0):
        Fn, kw, (c, q) = at_points(x[0], activation)
        A = iso.stress_tangent(Fn, **kw)[1].reshape(c, q, 3, 3, 3, 3)
        return [np.ascontiguousarray(A.transpose(2, 3, 4, 5, 1, 0))]

    return fem.Material(stress, elasticity, activation=0.0)


def check_felupe_material(law, activation: float = 0.6, cells: int = 3, seed: int = 0, rtol: float = 1e-6) -> dict:
    """Check :func:`felupe_material` for ``law`` and return the largest relative differences found.

    At random deformation gradients F = I + 0.15·N(0, 1) (``cells`` × 8 points, det F > 0), random
    unit fibres and α = ``activation``, with P, A the law's full stress and tangent, K its bulk
    modulus and H = F⁻ᵀ:

    ``layout``    the material's stress and elasticity in FElupe's (3, 3, q, c) layout are the
                  isochoric law's P_iso, A_iso at the same points and fibres;
    ``split``     P − P_iso = K (J − 1) J H and
                  A − A_iso = K J (2J − 1) H⊗H − K (J − 1) J H_iL H_kJ;
    ``isochoric`` P_iso Fᵀ is deviatoric (its trace, relative to |P_iso| |F|) and P_iso(sF) = P_iso(F)/s (s = 1.3);
    ``tangent``   A_iso against central differences of P_iso (step 1e-6);
    ``body``      one cube in ``SolidBodyNearlyIncompressible(umat, bulk=K)`` under the homogeneous
                  F of the first point carries the law's full P at its 8 quadrature points
                  (P_iso + p ∂J/∂F, p = K (J̄ − 1), J̄ = J).

    Raises
    ------
    AssertionError
        A difference above ``rtol`` (``tangent``: 1e-5).
    """
    fem = import_felupe(tensortrax=False)
    from pixmuscle.mechanics.materials import needs
    from pixmuscle.mechanics.solve import material_kw

    rng = np.random.default_rng(seed)
    n = 8 * cells
    F = np.eye(3) + 0.15 * rng.standard_normal((n, 3, 3))
    F[np.linalg.det(F) < 0, :, 0] *= -1.0
    fib = rng.standard_normal((cells, 3))
    fib /= np.linalg.norm(fib, axis=1)[:, None]
    has_fiber = "fiber" in needs(law)
    umat = felupe_material(law, fiber=fib if has_fiber else None)
    umat.kwargs["activation"] = activation
    kw = material_kw(law, np.repeat(fib, 8, axis=0), activation)
    iso = isochoric(law)
    P, A = law.stress_tangent(F, **kw)
    Pi, Ai = iso.stress_tangent(F, **kw)
    K = law.bulk_modulus
    J = np.linalg.det(F)
    H = np.linalg.inv(F).transpose(0, 2, 1)

    def rel(a, b):
        return float(np.max(np.abs(a - b)) / np.max(np.abs(b)))

    out = {}
    Ff = F.reshape(cells, 8, 3, 3).transpose(2, 3, 1, 0)            # FElupe layout (3, 3, q, c)
    Pf = umat.gradient([Ff, np.zeros(0)])[0]
    Af = umat.hessian([Ff, np.zeros(0)])[0]
    out["layout"] = max(rel(Pf.transpose(3, 2, 0, 1).reshape(n, 3, 3), Pi),
                        rel(Af.transpose(5, 4, 0, 1, 2, 3).reshape(n, 3, 3, 3, 3), Ai))
    Pv = (K * (J - 1.0) * J)[:, None, None] * H
    Av = ((K * J * (2.0 * J - 1.0))[:, None, None, None, None] * np.einsum("nij,nkl->nijkl", H, H)
          - (K * (J - 1.0) * J)[:, None, None, None, None] * np.einsum("nil,nkj->nijkl", H, H))
    out["split"] = max(rel(Pi + Pv, P), rel(Ai + Av, A))
    trace = np.abs(np.einsum("nij,nij->n", Pi, F)) / (np.linalg.norm(Pi, axis=(1, 2)) * np.linalg.norm(F, axis=(1, 2)))
    out["isochoric"] = max(float(np.max(trace)), rel(1.3 * iso.stress(1.3 * F, **kw), Pi))
    eps, fd = 1e-6, np.empty_like(Ai)
    for k in range(3):
        for L in range(3):
            dF = np.zeros((3, 3))
            dF[k, L] = eps
            fd[:, :, :, k, L] = (iso.stress(F + dF, **kw) - iso.stress(F - dF, **kw)) / (2.0 * eps)
    out["tangent"] = rel(fd, Ai)
    cube = fem.Cube(n=2)
    field = fem.FieldContainer([fem.Field(fem.RegionHexahedron(cube), dim=3)])
    field[0].values[:] = cube.points @ (F[0] - np.eye(3)).T
    body = fem.SolidBodyNearlyIncompressible(felupe_material(law, fiber=fib[:1] if has_fiber else None), field, bulk=K)
    body.umat.kwargs["activation"] = activation
    for _ in range(2):  # J̄ is updated from the last state: the second evaluation has J̄ = v/V = det F
        Pb = body.evaluate.gradient(field)[0]
    full = law.stress(np.repeat(F[:1], Pb.shape[2], axis=0), **material_kw(law, np.repeat(fib[:1], Pb.shape[2], axis=0),
                                                                             activation))
    out["body"] = rel(Pb[:, :, :, 0].transpose(2, 0, 1), full)
    bad = {k: v for k, v in out.items() if v > (1e-5 if k == "tangent" else rtol)}
    assert not bad, f"felupe_material({type(law).__name__}): relative differences {bad} too large"
    return out


def model_grid(model) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(body, bone, affine): the node voxels and the bone voxels of a pixmuscle model as masks on its
    grid, and the grid's voxel index → cm affine (voxel centres, model frame)."""
    shape = tuple(int(x) for x in model.shape)
    body = np.zeros(shape, bool)
    body[tuple(np.asarray(model.ijk).T)] = True
    bone = np.zeros(shape, bool)
    if model.bone_ijk is not None and len(model.bone_ijk):
        bone[tuple(np.asarray(model.bone_ijk).T)] = True
    affine = np.eye(4)
    affine[:3, :3] = np.diag(model.spacing)
    affine[:3, 3] = model.origin
    return body, bone, affine


def shared_face_points(points: np.ndarray, affine: np.ndarray, refine, body: np.ndarray, other: np.ndarray) -> np.ndarray:
    """Which points of ``voxel_hex8_mesh(body, affine, refine)`` lie on a voxel face that a voxel of
    ``body`` shares with a voxel of ``other`` (face neighbours only, as pixmuscle's ``bone_surface``).

    Returns
    -------
    ndarray of bool, shape (n,)
    """
    r = np.asarray(refine, int)
    h = np.diag(affine)[:3]
    lattice = np.array(body.shape) * r + 1
    on_face = np.zeros(lattice, bool)
    for a in range(3):
        b, c = [x for x in range(3) if x != a]
        for side in (0, 1):  # the voxel's lower / upper face along a
            neighbour = np.zeros_like(other)
            src, dst = [slice(None)] * 3, [slice(None)] * 3
            src[a], dst[a] = (slice(0, -1), slice(1, None)) if side == 0 else (slice(1, None), slice(0, -1))
            neighbour[tuple(dst)] = other[tuple(src)]
            corner = np.argwhere(body & neighbour) * r
            corner[:, a] += side * r[a]
            for p in range(r[b] + 1):
                for q in range(r[c] + 1):
                    at = corner.copy()
                    at[:, b] += p
                    at[:, c] += q
                    on_face[tuple(at.T)] = True
    ijk = np.rint((points - (affine[:3, 3] - 0.5 * h)) / (h / r)).astype(int)
    return on_face[tuple(ijk.T)]


def leg_solve_keys(bench_solve) -> dict:
    """``solve`` keys of the leg cases: those of ``bench_solve.run_case(size, "auto", 10, 0.95, None)``,
    α 0 → 0.95 in 10 load steps and every other setting at its default."""
    return {"steps": LEG_STEPS, "activation": {"from": 0.0, "to": LEG_ALPHA}, "solver": bench_solve.BACKENDS["auto"],
            **bench_solve.newton_tolerances(None)}


def run_leg_pixmuscle(size: str, refine: tuple[int, int, int] = (1, 1, 1)) -> dict:
    """pixmuscle's solve of the SYNTHETIC leg at ``size`` (``bench_solve.leg_case``), every default,
    each voxel split into ``refine`` voxels of its tissue and fibre (one node each)."""
    from pixmuscle.mechanics.solve import solve

    bench_solve = _bench_solve()
    model, cfg = bench_solve.leg_case(size, None, refine=refine, **leg_solve_keys(bench_solve))
    t0 = time.perf_counter()
    res = solve(model, cfg)
    wall = time.perf_counter() - t0
    force = [float(f) for f in res.force("z_max")]
    bottom = float(res.force("z_min")[-1])
    tissue = np.bincount(model.tissue, minlength=4)
    split = "" if tuple(refine) == (1, 1, 1) else f", {'x'.join(map(str, refine))} nodes per voxel"
    return {"method": f"pixmuscle SCNI-RKPM, every solve default{split}", "size": size, "nodes": model.n_nodes,
            "dofs": 3 * model.n_nodes, "elements": None, "elements_per_voxel": list(refine),
            "tissue_voxels": {"muscle": int(tissue[1]), "connective_tissue": int(tissue[2]), "fat": int(tissue[3])},
            "status": res.status, "alpha": [float(a) for a in res.alpha], "force_N": force[-1], "force_z_min_N": bottom,
            "force_curve_N": force,
            "newton_iterations_per_step": res.iterations.tolist()[1:], "cutbacks": int(np.sum(res.cutbacks)),
            "newton_residual_tol": cfg.newton.residual_tol, "linear_engine": res.info.get("linear_engine"),
            "wall_s": round(wall, 2), "peak_rss_GB": peak_rss_gb()}


def run_leg_felupe(size: str, refine: tuple[int, int, int]) -> dict:
    """FElupe hex8 Q1/P0/P0 solve of the SYNTHETIC leg at ``size`` on its body voxels, each split
    into ``refine`` boxes: one ``SolidBodyNearlyIncompressible`` per tissue with the isochoric part
    of pixmuscle's own law (:func:`felupe_material`, checked first by :func:`check_felupe_material`)
    and the law's bulk modulus; the load steps and boundary conditions of the pixmuscle case."""
    fem = import_felupe(tensortrax=False)
    from pixmuscle.mechanics.materials import needs
    from pixmuscle.mechanics.solve import make_materials
    from pixmuscle.model.tissues import TISSUE_NAMES

    solver, engine = direct_solver()
    bench_solve = _bench_solve()
    model, cfg = bench_solve.leg_case(size, None, **leg_solve_keys(bench_solve))
    laws = make_materials(cfg.materials)                       # tissue code → law, as pixmuscle's solve
    checks = {TISSUE_NAMES[code]: check_felupe_material(law) for code, law in laws.items()}
    alphas = np.linspace(cfg.alpha_from, cfg.alpha_to, cfg.steps + 1)
    t0 = time.perf_counter()
    body, bone, affine = model_grid(model)
    points, cells, voxels = voxel_hex8_mesh(body, affine, refine, with_voxels=True)
    index = np.full(body.shape, -1)
    index[tuple(np.asarray(model.ijk).T)] = np.arange(model.n_nodes)
    node = index[tuple(voxels.T)]                              # the pixmuscle node of each cell's voxel
    tissue = np.asarray(model.tissue)[node]
    field = fem.FieldContainer([fem.Field(fem.RegionHexahedron(fem.Mesh(points, cells, "hexahedron"), grad=False),
                                          dim=3)])
    solids, cells_per_tissue = [], {}
    for code, law in laws.items():
        sel = tissue == code
        if not sel.any():
            continue
        cells_per_tissue[TISSUE_NAMES[code]] = int(sel.sum())
        region = fem.RegionHexahedron(fem.Mesh(points, cells[sel], "hexahedron"))
        umat = felupe_material(law, fiber=np.asarray(model.fiber)[node[sel]] if "fiber" in needs(law) else None)
        solids.append(fem.SolidBodyNearlyIncompressible(umat, fem.FieldContainer([fem.Field(region, dim=3)]),
                                                        bulk=law.bulk_modulus))
    z = points[:, 2]
    top = np.isclose(z, z.max())
    ends = np.isclose(z, z.min()) | top
    on_bone = shared_face_points(points, affine, refine, body, bone)
    bounds = {"ends": fem.Boundary(field[0], mask=ends),                                   # x, y, z fixed
              "bone_surface": fem.Boundary(field[0], mask=on_bone & ~ends, skip=(0, 0, 1))}  # x, y fixed
    dof0, dof1 = fem.dof.partition(field, bounds)
    ext0 = fem.dof.apply(field, bounds, dof0)
    curve, bottom, iterations, status = [0.0], 0.0, [], "complete"
    for n, alpha in enumerate(alphas[1:], 1):
        for solid in solids:
            solid.umat.kwargs["activation"] = float(alpha)
        try:
            res = fem.newtonraphson(items=solids, x0=field, dof1=dof1, dof0=dof0, ext0=ext0, solver=solver,
                                    tol=NEWTON_TOL, verbose=0)
        except fem.NewtonConvergenceError as exc:
            status = f"failed at load step {n}: {str(exc).strip()}"
            break
        field.link(res.x)                                      # the next step starts from this one
        # res.fun at a held dof is the force the support exerts on the body: at z_max (outward
        # normal +z) its z component, tension positive, as pixmuscle's force("z_max")
        f = res.fun.reshape(-1, 3)
        curve.append(float(f[top, 2].sum()))
        bottom = float(-f[ends & ~top, 2].sum())                # z_min: outward normal -z
        iterations.append(int(res.iterations))
    wall = time.perf_counter() - t0
    return {"method": f"FElupe hex8 Q1/P0/P0, {'x'.join(map(str, refine))} per voxel, pixmuscle's laws",
            "size": size, "nodes": len(points), "dofs": 3 * len(points), "elements": len(cells),
            "elements_per_voxel": list(refine), "cells_per_tissue": cells_per_tissue,
            "held_nodes": {"ends": int(ends.sum()), "bone_surface_xy": int((on_bone & ~ends).sum())}, "status": status,
            "alpha": [float(a) for a in alphas[:len(curve)]], "force_N": curve[-1], "force_z_min_N": bottom,
            "force_curve_N": curve,
            "newton_iterations_per_step": iterations, "newton_residual_tol": NEWTON_TOL, "linear_engine": engine,
            "felupe_version": fem.__version__, "material_check": checks, "wall_s": round(wall, 2),
            "peak_rss_GB": peak_rss_gb()}


def run_one(spec: str, steps: int) -> dict:
    method, arg = parse_case(spec)
    if method == "reference":
        return run_reference()
    if method == "leg:pixmuscle":
        return run_leg_pixmuscle(*arg)
    if method == "leg:felupe":
        return run_leg_felupe(*arg)
    return run_pixmuscle(arg, steps) if method == "pixmuscle" else run_felupe(arg, steps)


def in_subprocess(spec: str, steps: int, threads: int) -> dict:
    """Run one case in a fresh process with ``threads`` threads; its result, or its last error line."""
    env = dict(os.environ, FELUPE_VERBOSE="false", **{v: str(threads) for v in THREAD_VARS})
    proc = subprocess.run([sys.executable, __file__, "--one", spec, "--steps", str(steps)],
                          capture_output=True, text=True, env=env)
    got = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
    if got:
        return json.loads(got[-1][7:])
    return {"error": (proc.stderr.strip().splitlines() or [f"exit status {proc.returncode}"])[-1]}


def with_errors(cases: list[dict], ref: dict | None) -> list[dict]:
    """Add to each tendon case the relative error of its final force against the reference
    (``rel_error``), to each leg case the relative difference of its final force from the
    pixmuscle case on the same leg (``diff_vs_pixmuscle``; None when that case is missing)."""
    pix = {c.get("size"): c for c in cases if is_base_leg_case(c.get("case", "")) and "force_N" in c}
    for c in cases:
        if "force_N" not in c:
            continue
        if is_leg(c.get("case", "")):
            p = None if is_base_leg_case(c["case"]) else pix.get(c.get("size"))
            c["diff_vs_pixmuscle"] = None if p is None else (c["force_N"] - p["force_N"]) / p["force_N"]
        elif ref:
            c["rel_error"] = (c["force_N"] - ref["force_N"]) / ref["force_N"]
    return cases


def is_base_leg_case(spec: str) -> bool:
    """Whether a case is pixmuscle on the leg at one node per voxel (what the leg rows are compared with)."""
    return is_leg(spec) and spec.split(":")[1:] in (["pixmuscle"], ["pixmuscle", "1x1x1"])


def extrapolate(h, force) -> tuple[float, float]:
    """Richardson extrapolation of three forces at element sizes ``h`` (any unit, decreasing):
    (F*, p) of F(h) = F* + C h^p through all three points; p by bisection on
    (F1 − F2)/(F2 − F3) = (h1^p − h2^p)/(h2^p − h3^p), in 0.05 ≤ p ≤ 8. NaNs where the forces do not
    approach a limit monotonically (no p in that range fits)."""
    h, f = np.asarray(h, float), np.asarray(force, float)
    ratio = (f[0] - f[1]) / (f[1] - f[2]) if f[1] != f[2] else np.inf

    def gap(p):
        return (h[0] ** p - h[1] ** p) / (h[1] ** p - h[2] ** p) - ratio

    lo, hi = 0.05, 8.0
    if not np.isfinite(ratio) or ratio <= 0 or gap(lo) * gap(hi) > 0:
        return float("nan"), float("nan")
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if gap(lo) * gap(mid) > 0 else (lo, mid)
    p = 0.5 * (lo + hi)
    c = (f[0] - f[1]) / (h[0] ** p - h[1] ** p)
    return float(f[0] - c * h[0] ** p), float(p)


def extrapolation_lines(cases: list[dict]) -> list[str]:
    """Per leg size and method, the Richardson extrapolation over the cases split 1, 2 and 3 times
    along every edge of a voxel, and each case's force against it."""
    lines = []
    for size in dict.fromkeys(c.get("size") for c in cases):
        for name in ("pixmuscle", "felupe"):
            by_r = {c["elements_per_voxel"][0]: c for c in cases
                    if c.get("size") == size and c.get("case", "").split(":")[1:2] == [name] and "force_N" in c
                    and c.get("elements_per_voxel") and len(set(c["elements_per_voxel"])) == 1}
            if not {1, 2, 3} <= set(by_r):
                continue
            fstar, p = extrapolate([1, 1 / 2, 1 / 3], [by_r[r]["force_N"] for r in (1, 2, 3)])
            errs = ", ".join(f"{r} × {r} × {r}: {pct((by_r[r]['force_N'] - fstar) / fstar)}" for r in (1, 2, 3))
            lines.append(f"- leg {size}, {name}: F* = {fstar:.2f} N, p = {p:.2f} (F = F* + C h^p through the "
                         f"forces at 1, 2 and 3 nodes or elements per voxel edge, h in voxels); against F*: {errs}.")
    return (["", "Extrapolated forces:", "", *lines]) if lines else []


def pct(x: float | None) -> str:
    return "—" if x is None else f"{100 * x:+.2f} %"


def tendon_lines(cases: list[dict], ref: dict | None, meta: dict) -> list[str]:
    """The tendon section of the .md."""
    lines = ["## Example 1 tendon", "",
             f"{meta['date_utc']}, {meta['platform']}, Python {meta['python']}, {meta['cpus']} CPUs, "
             f"{meta['threads']} thread(s) per case, load average {meta['load_average']} at start; {SHARED_NOTE}.", "",
             f"Command: `{meta['command']}`", "",
             f"Tendon at voxel size {tuple(H)} cm, top displaced {STRETCH:g} cm in {meta['steps']} load steps. "
             "Error: final reaction force against the reference below.", ""]
    if ref:
        lines += [f"Reference: {ref['method']}, refine {tuple(ref['refine'])}, {ref['steps']} steps, {ref['dofs']} dofs "
                  f"(quarter model, ×{ref['symmetry_factor']}): **{ref['force_N']:.4f} N** "
                  f"({ref['wall_s']} s, {ref['peak_rss_GB']} GB).", ""]
    lines += ["| case | method | voxel (cm) | nodes | dofs | F_z at 2 cm (N) | error vs ref. | within 1 % | "
              "Newton its / step | wall (s) | peak RSS (GB) |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for c in cases:
        if "error" in c:
            lines.append(f"| {c['case']} | failed: {c['error'][:80]} | | | | | | | | | |")
            continue
        err = c.get("rel_error")
        lines.append(f"| {c['case']} | {c['method']} | {' × '.join(f'{x:g}' for x in c['voxel_size_cm'])} | "
                     f"{c['nodes']} | {c['dofs']} | {c['force_N']:.4f} | {pct(err)} | "
                     + ("—" if err is None else ("yes" if abs(err) <= 0.01 else "no")) + f" | "
                     f"{c['newton_iterations_per_step']} | {c['wall_s']} | {c['peak_rss_GB']} |")
    lines += ["", "Wall time: pixmuscle's `solve()` (RK/SCNI build included, the model from the mask not); FElupe "
              "from the voxel mask to the last step (mesh, region and field included). Peak RSS: of the case's own "
              "process, imports included. FElupe dofs: displacements only (the element pressure and dilatation are "
              "condensed). Commands per case in bench_vs_fe.json.", ""]
    return lines


def leg_lines(cases: list[dict], meta: dict) -> list[str]:
    """The leg section of the .md: one row per case, then the force curves of each leg size."""
    lines = ["## SYNTHETIC leg (paper Example 2 set-up)", "",
             f"{meta['date_utc']}, {meta['platform']}, Python {meta['python']}, {meta['cpus']} CPUs, "
             f"{meta['threads']} thread(s) per case, load average {meta['load_average']} at start; {SHARED_NOTE}.", "",
             f"Command: `{meta['command']}`", "",
             "The SYNTHETIC leg of bench_solve.py (`leg_case`: muscles with per-voxel fibres, connective tissue and "
             "skin, fat; bone voxels and background are not part of the body) at voxel size "
             f"{' × '.join(f'{x:g}' for x in meta['voxel_size_cm'])} cm. Activation α 0 → {meta['alpha_to']:g} in "
             f"{meta['steps']} equal load steps; z_min and z_max fixed in x, y, z, bone surfaces fixed in x, y. "
             "Force: reaction F_z at z_max, tension positive. FElupe carries the isochoric part of pixmuscle's own "
             "law per tissue (muscle: transversely isotropic law with the voxel's fibre and α; connective tissue "
             "and fat: Yeoh) and the law's bulk modulus in the Q1/P0/P0 body, so only the discretisation and the way "
             "the supports are imposed differ. vs pixmuscle: final force against pixmuscle at one node per voxel on the same leg.",
             "",
             "| case | method | nodes | dofs | hexahedra | F_z(z_max) at α = 0.95 (N) | vs pixmuscle | "
             "Newton its / step | wall (s) | peak RSS (GB) | load average 1 min, start → end | status |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for c in cases:
        if "error" in c:
            lines.append(f"| {c['case']} | failed: {c['error'][:80]} | | | | | | | | | | |")
            continue
        load = c.get("load_average", {})
        load = (f"{load.get('start', load.get('before'))[0]:.1f} → {load.get('end', load.get('after'))[0]:.1f}"
                if load else "—")
        lines.append(f"| {c['case']} | {c['method']} | {c['nodes']} | {c['dofs']} | {c.get('elements') or '—'} | "
                     f"{c['force_N']:.4f} | {pct(c.get('diff_vs_pixmuscle'))} | "
                     f"{c['newton_iterations_per_step']} | {c['wall_s']} | {c['peak_rss_GB']} | {load} | "
                     f"{c['status'][:40]} |")
    lines += extrapolation_lines(cases)
    for size in dict.fromkeys(c.get("size") for c in cases if "force_curve_N" in c):
        cs = [c for c in cases if c.get("size") == size and "force_curve_N" in c]
        alpha = max((c["alpha"] for c in cs), key=len)
        lines += ["", f"Force F_z(z_max) (N) per load step, leg {size}:", "",
                  "| α | " + " | ".join(c["case"] for c in cs) + " |", "|---|" + "---|" * len(cs)]
        for k, a in enumerate(alpha):
            lines.append(f"| {a:.3f} | " + " | ".join(f"{c['force_curve_N'][k]:.4f}" if k < len(c["force_curve_N"])
                                                       else "—" for c in cs) + " |")
    lines += ["", "Wall time: pixmuscle's `solve()` (RK/SCNI build included, the model from the labels not); FElupe "
              "from the model's voxel grid to the last step (mesh, regions and fields included; the model from the "
              "labels and the material check not). Peak RSS: of the case's own process, imports included. Supports: "
              "pixmuscle holds the end faces at their vertices and the bone-surface nodes (voxel centres) by its "
              "penalty; FElupe holds the mesh nodes on the end faces and on the faces shared with bone exactly. "
              "Newton: pixmuscle to its default tolerances (residual 1e-4), FElupe to ‖f(free)‖ / ‖f(held)‖ < "
              f"{NEWTON_TOL:g}. Material check (`check_felupe_material`, per tissue, before each FElupe case) and "
              "commands per case in bench_vs_fe.json."]
    return lines


def write_results(cases: list[dict], ref: dict | None, meta: dict | None, meta_leg: dict | None = None) -> None:
    """Write ``bench_vs_fe.json`` and ``bench_vs_fe.md`` (a tendon and a leg section, each with the
    metadata of the run that last measured it)."""
    (OUT / f"{STEM}.json").write_text(json.dumps({"meta": meta, "meta_leg": meta_leg, "reference": ref, "cases": cases},
                                                 indent=1))
    lines = [f"# {STEM}: meshfree vs hexahedral finite elements on the same voxels", ""]
    tendon = [c for c in cases if not is_leg(c.get("case", ""))]
    leg = [c for c in cases if is_leg(c.get("case", ""))]
    if meta and tendon:
        lines += tendon_lines(tendon, ref, meta)
    if meta_leg and leg:
        lines += leg_lines(leg, meta_leg)
    (OUT / f"{STEM}.md").write_text("\n".join(lines) + "\n")


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--cases", nargs="+", default=DEFAULT_CASES,
                   help="pixmuscle:nodal, pixmuscle:projected, felupe:RXxRYxRZ, legSIZE:pixmuscle[:RXxRYxRZ], "
                        "legSIZE:felupe:RXxRYxRZ (default: %(default)s)")
    p.add_argument("--steps", type=int, default=4, help="tendon: load steps to the 2-cm stretch (default: %(default)s)")
    p.add_argument("--threads", type=int, default=1, help="MKL/OpenMP/numba threads per case (default: %(default)s)")
    p.add_argument("--reuse-reference", action="store_true",
                   help="take the reference force from the existing results file instead of computing it")
    p.add_argument("--append", action="store_true",
                   help="merge into the existing results file (cases measured again are replaced)")
    p.add_argument("--tables", action="store_true", help=f"only rewrite {STEM}.md from {STEM}.json")
    p.add_argument("--one", default=None, help=argparse.SUPPRESS)  # internal: run one case, print JSON
    args = p.parse_args(argv)
    if args.one:
        print("RESULT " + json.dumps(run_one(args.one, args.steps)), flush=True)
        return 0
    path = OUT / f"{STEM}.json"
    old = json.loads(path.read_text()) if path.exists() else None
    if args.tables:
        if old is None:
            p.error(f"--tables: {path} does not exist")
        write_results(old["cases"], old["reference"], old.get("meta"), old.get("meta_leg"))
        return 0
    for spec in args.cases:
        try:
            parse_case(spec)
        except ValueError as exc:
            p.error(str(exc))
    if args.steps < 1 or args.threads < 1:
        p.error("--steps and --threads must be >= 1")
    OUT.mkdir(parents=True, exist_ok=True)
    tendon = [s for s in args.cases if not is_leg(s)]
    legs = [s for s in args.cases if is_leg(s)]
    command = " ".join([".venv/bin/python benchmarks/bench_vs_fe.py", *argv])
    run = {"python": platform.python_version(), "machine": platform.machine(), "platform": platform.platform(),
           "cpus": os.cpu_count(), "load_average": [round(x, 1) for x in os.getloadavg()],
           "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "command": command,
           "threads": args.threads, "note": SHARED_NOTE}
    old = old or {}
    meta = {**run, "steps": args.steps, "voxel_size_cm": list(H), "stretch_cm": STRETCH} if tendon else old.get("meta")
    meta_leg = old.get("meta_leg")
    if legs:
        meta_leg = {**run, "steps": LEG_STEPS, "alpha_to": LEG_ALPHA, "voxel_size_cm": list(_bench_solve().SPACING)}
    ref = old.get("reference")
    if tendon and not args.reuse_reference:
        print("== reference", flush=True)
        ref = in_subprocess("reference", args.steps, args.threads)
        ref.update(command=command, date_utc=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                   platform=run["platform"], cpus=run["cpus"], threads=args.threads)
        print(json.dumps(ref), flush=True)
        if "error" in ref:
            ref = None
    # without --append a run replaces the cases of the benchmark(s) it measures (tendon, leg); the other's stay
    measured = {is_leg(s) for s in args.cases}
    cases = [c for c in old.get("cases", []) if c.get("case") not in set(args.cases)
             and (args.append or is_leg(c.get("case", "")) not in measured)]
    for spec in args.cases:
        print(f"== {spec}", flush=True)
        case_run = Run(defaults=False)
        res = in_subprocess(spec, args.steps, args.threads)
        common = dict(case=spec, threads=args.threads, date_utc=case_run.utc, platform=run["platform"], cpus=run["cpus"],
                      note=SHARED_NOTE)
        if is_leg(spec):
            method, arg = parse_case(spec)
            res.update(common, size=arg[0], steps=LEG_STEPS, alpha_to=LEG_ALPHA,
                       voxel_size_cm=list(_bench_solve().SPACING),
                       command=f".venv/bin/python benchmarks/bench_vs_fe.py --cases {spec} --threads {args.threads} "
                               "--append")
        else:
            res.update(common, voxel_size_cm=list(H), steps=args.steps,
                       command=f".venv/bin/python benchmarks/bench_vs_fe.py --cases {spec} --steps {args.steps} "
                               f"--threads {args.threads} --reuse-reference --append")
        res.update(case_run.fields(command=res["command"], peak_rss_GB=res.get("peak_rss_GB")))
        cases.append(res)
        print(json.dumps(res)[:600], flush=True)
        write_results(with_errors(cases, ref), ref, meta, meta_leg)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

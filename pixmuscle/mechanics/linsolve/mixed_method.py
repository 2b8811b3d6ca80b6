r"""The mixed displacement–pressure method, written once for both backends that run it.

``mixed_amg`` (:mod:`.mixed`: SciPy/PARDISO, BoomerAMG in this process or its workers) and
``petsc_mixed`` (:mod:`.petsc_mixed`: PETSc objects on one or several MPI ranks) solve the Newton
systems of the projected volumetric energy in the scaled mixed form

    [ K_d      w Gᵀ       ] [Δd]   [r]
    [ w G   −w² D⁻¹       ] [ q̃] = [0],        D = diag(V_p K̄_p),  w = mean_p(μ_p V_p) / s,

with the upper block-triangular preconditioner P = [M_A, w Gᵀ; 0, −Ŝ] (:mod:`.mixed` explains the
form, its scaling and why it is robust in K/μ). What the two share is here:

* :class:`MixedBlocks`: the diagonal blocks of a set of patches (D, w² D⁻¹) and the diagonal Schur
  approximation Ŝ (probed or the scaled pressure mass);
* :func:`probe_colours`, :func:`probe_diagonal` and :func:`probed_schur_diagonal`: the probed
  diagonal of G M_A Gᵀ (same colours and signs on one rank and several);
* :class:`MixedOperator` and :class:`BlockTriangular`: the mixed operator and P⁻¹ as Python
  operators (the serial backend; PETSc builds the same blocks as a MatNest and a Schur field split);
* :func:`refine`: the refinement loop of a condensed solve — mixed solves for the condensed
  residual left, each to a target tightened by the lag (condensed residual per mixed residual)
  the previous one showed.

The pressure side of the right-hand side and of the update is
:meth:`~pixmuscle.mechanics.pressure.PressureSpace.scaled_rhs` and
:meth:`~pixmuscle.mechanics.pressure.PressureSpace.update`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np

#: condensed solves stop after this many mixed passes
MAX_PASSES = 8


class MixedBlocks:
    """The scalar blocks of the scaled mixed form on a set of patches.

    Parameters
    ----------
    space : PressureSpace
    patches : (n,) int
        The patches (pressure unknowns) of these blocks: the free ones, or one rank's share.

    Attributes
    ----------
    w : float
        Scale of the pressure rows, N.
    D : (n,) float
        V_p K̄_p, N·cm.
    c22 : (n,) float
        w² D⁻¹, N/cm: the pressure–pressure block is −c22.
    mass : (n,) float
        μ_p V_p, N·cm (the scaled pressure mass is its inverse).
    """

    def __init__(self, space, patches: np.ndarray):
        self.w = space.weight
        vp, kbar = space.volume[patches], space.kbar[patches]
        self.D = vp * kbar
        self.c22 = self.w * self.w / self.D
        self.mass = space.shear[patches] * vp

    def schur(self, schur: str, scale: float, probe: np.ndarray | None = None) -> np.ndarray:
        """Ŝ = w² D⁻¹ + w² diag(G M_A Gᵀ) with ``schur="probed"`` (``probe``: that diagonal,
        w² included), else w² (D⁻¹ + c/(μ_p V_p)) with c = ``scale`` (``schur="mass"``), (n,)."""
        if schur == "probed":
            return self.c22 + probe
        return self.w * self.w * (1.0 / self.D + scale / self.mass)


def box_signs(box: np.ndarray) -> np.ndarray:
    """A fixed ±1 per patch from its box indices alone (a hash of them): the probe signs of a
    distributed solve, the same whichever ranks own the patches."""
    h = (np.asarray(box, np.int64) * np.array([73856093, 19349663, 83492791])).sum(axis=1)
    h ^= h >> 13
    h = (h * 0x5BD1E995) & 0xFFFFFFFF
    return np.where((h >> 15) & 1, -1.0, 1.0)


def probe_colours(box: np.ndarray, spacing: int) -> tuple[np.ndarray, np.ndarray]:
    """Colour (0 … spacing³ − 1) and fixed random sign (±1, seed 0) of each patch for
    :func:`probed_schur_diagonal`, from the patches' box indices ``box`` (N_p, 3) on the patch grid."""
    colour = ((box % spacing) * np.array([spacing * spacing, spacing, 1])).sum(axis=1)
    sign = np.where(np.random.default_rng(0).random(box.shape[0]) < 0.5, -1.0, 1.0)
    return colour, sign


def probe_diagonal(product: Callable[[np.ndarray], np.ndarray], colour: np.ndarray, sign: np.ndarray,
                   colours, largest: Callable[[np.ndarray], float] | None = None) -> np.ndarray:
    """Diagonal of a patch operator A by signed colour probing: for each colour c,
    s_p (A (s ∘ 1_c))_p estimates A_pp of every patch p of that colour.

    Parameters
    ----------
    product : callable
        q (n,) ↦ A q (n,) on these patches (collective on several ranks).
    colour, sign : (n,) int, (n,) float
        Of each patch (:func:`probe_colours`).
    colours : iterable of int
        The colours to probe (every rank must probe every colour: the products are collective).
    largest : callable, optional
        The largest |entry| of the estimates over all ranks (default: of these patches).

    Returns
    -------
    (n,) float, positive: |estimate|, at least 10⁻¹² of the largest.
    """
    out = np.zeros(colour.size)
    for c in colours:
        sel = colour == c
        out[sel] = sign[sel] * product(np.where(sel, sign, 0.0))[sel]
    top = (float(np.max(np.abs(out))) if out.size else 0.0) if largest is None else largest(out)
    return np.maximum(np.abs(out), 1e-12 * top)


def probed_schur_diagonal(G, M, box: np.ndarray, spacing: int = 2) -> np.ndarray:
    """Diagonal of G M Gᵀ (M ≈ K_d⁻¹) by probing: the patches are coloured by their box index on the
    patch grid modulo ``spacing`` (spacing³ colours: 8 for 2, 27 for 3), and for each colour c,
    s_p (G M Gᵀ (s ∘ 1_c))_p estimates the diagonal entry of every patch p of that colour (the
    patches within ``spacing`` − 1 boxes, which couple most, have other colours); s is a fixed
    random ±1 per patch. spacing³ applications of M.

    The signs matter on large models. Without them each estimate adds the couplings of patch p to
    every other patch of its colour, and the coupling decays too slowly with distance for that sum
    to stay bounded as the model grows: on the 73,753-node leg 22 % of the patches came out 5–48
    times their pressure-mass estimate (none at 21,169 nodes) and FGMRES needed 467 iterations,
    more than with the mass (195). With random signs those couplings add up as noise of zero mean
    (the probing estimator of Bekas, Kokiopoulou & Saad 2007).

    On the 5k leg (2 × 2 × 3 patches) the preconditioned Schur complement then spans a ratio of
    40 between its extreme eigenvalues (measured before the signs), against 347 for the scaled
    pressure mass c/(μ_p V_p) and 25 for the exact diagonal: the mass misses how much softer or
    stiffer a patch's surroundings are than the patch itself (connective-tissue patches next to
    muscle, partial patches at the surface).

    Parameters
    ----------
    G : object with ``@`` and ``T``
        Rows of the patches (N_p × 3N), e.g. :class:`~pixmuscle.mechanics.pressure.PatchDivergence`.
    M : object with ``@``
        Preconditioner of the displacement block.
    box : (N_p, 3) int
        Box index of each patch on the patch grid.
    spacing : int
        Same-colour patches are ``spacing`` boxes apart along each axis (≥ 2).

    Returns
    -------
    (N_p,) float, positive

    References
    ----------
    C. Bekas, E. Kokiopoulou, Y. Saad, "An estimator for the diagonal of a matrix", Appl. Numer.
    Math. 57(11–12), 1214–1229, 2007.
    """
    colour, sign = probe_colours(box, spacing)
    return probe_diagonal(lambda q: G @ (M @ G.T(q)), colour, sign, np.unique(colour))


class MixedOperator:
    """The scaled mixed operator [K_d, w Gᵀ; w G, −w² D⁻¹] on z = [Δd; q̃].

    One gradient and one transposed-gradient product serve K_d x, w Gᵀ q̃ and w G x.

    Parameters
    ----------
    Kd : displacement block with ``apply(x, extra=)`` (:meth:`.operator.SystemOperator.displacement_operator`)
    G : PatchDivergence of the pressure patches
    c22 : (n,) float
        w² D⁻¹.
    w : float
    """

    def __init__(self, Kd, G, c22: np.ndarray, w: float):
        self.Kd, self.G, self.w, self.c22 = Kd, G, w, c22
        self.n = Kd.shape[0]

    def __matmul__(self, z):
        x, q = z[: self.n], z[self.n:]
        G = self.G
        wq = self.w * q
        seen = []

        def pressure_stress(grad):  # grad[L, i, J]; one gradient product serves K_d x and G x
            seen.append(grad)
            return G.stress(wq)

        y = self.Kd.apply(x, extra=pressure_stress)
        return np.concatenate([y, self.w * G.of_gradient(seen[0]) - self.c22 * q])


class BlockTriangular:
    """P⁻¹ for P = [M_A, w Gᵀ; 0, −Ŝ]: q̃ = −u₂/Ŝ, Δd = M_A⁻¹ (u₁ − w Gᵀ q̃).

    Parameters
    ----------
    MA : object with ``@``
        Preconditioner of the displacement block (3N,).
    G : PatchDivergence
    shat : (n,) float
        Ŝ (:meth:`MixedBlocks.schur`).
    w : float
    n : int
        3N.
    """

    def __init__(self, MA, G, shat: np.ndarray, w: float, n: int):
        self.MA, self.G, self.shat, self.w, self.n = MA, G, shat, w, n

    def __matmul__(self, u):
        q = -u[self.n:] / self.shat
        x = self.MA @ (u[: self.n] - self.w * self.G.T(q))
        return np.concatenate([x, q])


def refinement_target(rtol: float, bn: float, rn: float, lag: float, floor: float) -> float:
    """Relative target of a refinement pass: the condensed target ``rtol`` · ``bn`` asked of the
    condensed residual ``rn`` left so far, divided by the ``lag`` (condensed residual per mixed
    residual) the last pass showed, halved for margin; within [``floor``, 0.5]."""
    return min(0.5, max(0.5 * rtol * bn / (rn * lag), floor))


@dataclasses.dataclass
class Pass:
    """One mixed solve of a condensed solve (what a backend's pass returns to :func:`refine`).

    Attributes
    ----------
    dx : (3N,) float
        The displacement part of its solution, cm (added to the update).
    iterations : int
    status : str
        ``"converged"`` (the mixed solve met its target), ``"maxiter"``, ``"breakdown"`` or a
        backend's divergence message.
    lag : float or None
        None: the update so far meets the condensed target. Else the condensed residual per mixed
        residual this pass showed: a refinement follows.
    residual : (3N,) float or None
        The condensed residual b − K x of the update so far when the pass has it, else None.
    """

    dx: np.ndarray
    iterations: int
    status: str
    lag: float | None = None
    residual: np.ndarray | None = None


def refine(mixed_pass: Callable[..., Pass], condensed_residual: Callable[[np.ndarray], np.ndarray], b: np.ndarray,
           rtol: float, maxiter: int, floor: float,
           norm: Callable[[np.ndarray], float] = np.linalg.norm) -> tuple[np.ndarray, int, str, int]:
    """Solve K x = b (the condensed system, 3N) to ‖b − K x‖ ≤ ``rtol`` ‖b‖ by mixed solves.

    The condensed residual of a mixed iterate, r₁ + Gᵀ (D/w) r₂, can exceed the mixed one by up to
    K/μ. The first pass asks the mixed solve for ``rtol``; while the condensed residual is too
    large, a further pass solves the mixed system for the condensed residual left, to the target
    :func:`refinement_target` sets from the lag the last pass showed (at least ``floor``); at most
    :data:`MAX_PASSES` passes and ``maxiter`` iterations together.

    Parameters
    ----------
    mixed_pass : callable
        ``mixed_pass(res, x, target, lag, budget, attempt) -> Pass``: a mixed solve with the
        right-hand side [res; 0] (res (3N,) N) to the relative ``target``, in at most ``budget``
        iterations; ``x`` is the update so far, ``lag`` the last pass's, ``attempt`` 0, 1, ….
    condensed_residual : callable
        x ↦ b − K x (3N,).
    b : (3N,) float
    rtol : float
    maxiter : int
    floor : float
        Round-off floor of the mixed residual, relative.
    norm : callable
        Euclidean norm of a residual (a distributed solve's sums over the ranks' rows).

    Returns
    -------
    x : (3N,) float
    iterations : int
    status : str
        ``"converged"``, or the failing pass's status (``"maxiter"`` also when the passes or
        iterations ran out).
    passes : int
    """
    b = np.asarray(b, float)
    x = np.zeros(b.size)
    bn = float(norm(b))
    if bn == 0.0:
        return x, 0, "converged", 0
    total, lag, res, status = 0, 1.0, b, "maxiter"
    for attempt in range(MAX_PASSES):
        rn = float(norm(res))
        target = rtol if not attempt else refinement_target(rtol, bn, rn, lag, floor)
        p = mixed_pass(res, x, target, lag, maxiter - total, attempt)
        total += p.iterations
        x = x + p.dx
        status = p.status
        if status != "converged" or p.lag is None:
            return x, total, status, attempt + 1
        lag = p.lag
        if total >= maxiter:
            return x, total, "maxiter", attempt + 1
        res = condensed_residual(x) if p.residual is None else p.residual
    status = "converged" if float(norm(res)) <= rtol * bn else "maxiter"
    return x, total, status, MAX_PASSES

"""Newton–Raphson with line search, and incremental loading with step cutback (paper eqs. 11, 18).

The solver works on any *system* object with

``evaluate(d, t, alpha) -> State``
    residual r = f_ext − f_int (N, shape (N, 3)) and force scale at coefficients ``d`` (cm), load
    factor ``t`` (0..1, ramp of the prescribed displacements) and activation ``alpha``; raises
    :class:`~pixmuscle.errors.SolverError` for inverted material points (det F ≤ 0);
``stiffness(state) -> sparse matrix``
    consistent tangent K = −∂r/∂d (3N × 3N);
``energy(state) -> float``
    total potential Π (N·cm), used by the line search.

Convergence of a load step needs both (tolerances in ``solve.newton``)

    ‖r‖ ≤ residual_tol · max(‖f_int‖, ‖f_pen‖) + atol          (relative residual)
    |Δd·r| ≤ energy_tol · max_iterations-of-the-step |Δd·r|      (energy norm of the last update)

The force scale in the first test is the size of the internal (= penalty, at equilibrium) forces,
not the first residual of the step, which is dominated by the penalty forces of the new prescribed
displacements and would make the test far too loose.

Start of a load increment: the state is the last converged d with the new load factor and α, or
the linear extrapolation of the last converged increment where that has the smaller residual.
Every update, the first of the increment included, is computed with the tangent of the current
state; one that is no descent direction of Π (Δd·r ≤ 0), whose linear solve fails, or whose
line search fails, is computed again with the tangent of the last converged state, which is
positive definite at a stable equilibrium. The tangent at the start state need not be: the new
active fibre stress can make it indefinite along the soft lateral mode of a clamped muscle
(geometric stiffness of the deviatoric active stress). With the halving line search its update
then overshot that mode and Newton wandered for ~10 iterations, which is why the converged
tangent used to start every increment; with the energy line search and this fallback the
current tangent takes fewer iterations on the clamped block, and on the 21k leg the iterative
solvers' preconditioner is then built for the activated state (the git history of docs/performance.md).

Pressure between iterations (projected volumetric energy, ``pressure_update``). The condensed
tangent's geometric term holds the patch pressure. ``exact`` takes K̄(θ − 1) of the new state;
``linearised`` takes K̄(θ − 1 + g·s Δd) from the last state, the pressure that Newton on the
mixed (displacement, pressure) form carries. Eliminating that form's pressure increment gives
back the condensed update equation K Δd = r(d), so only the tangent differs. The exact pressure
of a large update holds K̄ times the second-order part of the dilatation, which the linearised
one leaves out.

``mixed`` (the default) is ``linearised``, and with a linear solver that solves the mixed form
itself (``solve_mixed``: ``mixed_amg``, ``petsc_mixed``) Newton runs on the mixed form: the carried pressure p is an unknown of its own, the solve takes the
force residual at p and the pressure residual θ − 1 − p/K̄
(:meth:`~.system.MechanicalSystem.mixed_residual`), stops on the mixed residual, and returns
(Δd, Δp); the line search moves d and p together. An inexact solve then leaves its pressure-row
error in the next iteration's pressure residual, where the condensed form multiplies it by the
bulk modulus: the condensed solve has to reach a mixed residual ~K/μ smaller, which cost about
half of its Krylov iterations on the leg. Eisenstat–Walker's η follows the mixed residual
‖[r_u; w r_p]‖ (w: :attr:`~.system.MechanicalSystem.pressure_weight`); its safeguard, and the
convergence tests below, stay on the condensed residual r(d), so a converged state is the same
equilibrium whichever form Newton ran on.

Line search (:func:`line_search`): an energy line search — the step factor s is the root of
Π′(s) = −Δd·r(d + sΔd), bracketed and interpolated by regula falsi, unless the full step already
lowers ‖r‖. A step that still fails, a non-finite residual, a linear solve that gives
up (:class:`~pixmuscle.errors.SolverGaveUp`: the system needs far more iterations than the earlier
ones, the mark of an update that overshot; the converged tangent is not tried then, since on the
74k leg it led to a Newton that gained a few per cent per iteration), or no convergence in
``max_iterations`` makes the load step fail; :func:`load_steps` then halves the load increment
(cutback), keeps it halved for the rest of the ramp (``hold_cutback``), and retries, down to
``max_cutbacks`` halvings of the nominal increment, and finally raises
:class:`~pixmuscle.errors.SolverError` naming the step, α and the last residual. It gives up before the last cutback when a smaller increment cannot help
(see :func:`_cutback_cannot_help`: a failed linear solve or a non-finite residual at the start of
an increment, or two successive attempts that stagnated).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from typing import Any

import numpy as np

from ..errors import SolverError, SolverGaveUp
from .config import NewtonConfig

_LOG = logging.getLogger(__name__)


@dataclasses.dataclass
class NewtonRow:
    """One Newton iteration: residual before the update, energy norm and line-search factor of the update."""

    step: int
    load_factor: float
    iteration: int
    residual_norm: float
    relative_residual: float
    energy_norm: float
    line_search: float


@dataclasses.dataclass
class NewtonResult:
    state: Any
    converged: bool
    iterations: int
    rows: list
    relative_residual: float
    reason: str = ""


def _inner(system, a, b) -> float:
    """a·b over all unknowns: ``system.inner`` (a distributed system sums over its ranks), else numpy's."""
    inner = getattr(system, "inner", None)
    return float(np.vdot(a, b)) if inner is None else inner(a, b)


def _norm(system, r) -> float:
    return float(np.sqrt(max(_inner(system, r, r), 0.0)))


ETA_MAX = 1e-2


def forcing_term(rn: float, rn_prev: float | None, target: float, eta_max: float = ETA_MAX) -> float:
    """Relative accuracy η of the linear solve of one Newton iteration (inexact Newton).

    Eisenstat & Walker (1996), choice 2 with γ = 0.9, exponent 2, capped at η_max (default 1e-2): while
    Newton converges quadratically the next residual is ~‖r‖², so solving K Δd = r much more
    accurately than ‖r_k‖²/‖r_{k−1}‖² is wasted; the safeguard 0.1·target/‖r‖ stops
    over-solving in the last iteration (its linear residual only has to be 10× below the
    convergence target). The first iteration of a load step gets η_max. Direct solves are exact
    whatever η is; iterative ones (CG) save most of their iterations in the first Newton
    iteration of each step.

    Parameters
    ----------
    rn, rn_prev : float
        Residual norms of this and the previous Newton iteration (N); ``rn_prev`` None at the first.
    target : float
        Residual norm that ends the iteration (N).
    eta_max : float
        Cap of η (``solve.newton.forcing_max``).
    """
    if rn_prev is None or rn_prev <= 0.0:
        return eta_max
    return float(min(eta_max, max(0.9 * (rn / rn_prev) ** 2, 0.1 * target / rn)))


def line_search(system, state, dd: np.ndarray, cfg: NewtonConfig, pressure: tuple | None = None):
    """Step length s along the Newton update ``dd``: an energy line search (regula falsi on Π′).

    Along d(s) = d + s Δd the slope of the total potential is Π′(s) = −Δd·r(s) (r = −∂Π/∂d), so
    g(s) = Δd·r(s) (N·cm) is positive while Π decreases and its root is the minimum of Π on the
    line (Matthies & Strang 1979; Crisfield 1991, §9.3). The full step is accepted when it lowers
    ‖r‖ or leaves |g(1)| ≤ ½ g(0) (near the minimum of Π) or g(1) > 0 (Π still decreasing at the
    full step); otherwise the minimum is bracketed in [s_lo, s_hi] with g(s_lo) > 0 > g(s_hi) and
    the next s interpolates g linearly (Illinois regula falsi, kept 10 % inside the bracket) —
    not halving, which on a soft tangent (the active fibre at λ* ≈ 1 has zero stiffness, f_active′(1)
    = 0) needs many evaluations to come back from a step that overshoots 3–10× and then keeps
    far too short a step. A trial that inverts a material point or gives a non-finite residual
    is an upper bound s_hi of unknown slope (bisection). When Δd is not a descent direction of
    Π (g(0) ≤ 0: the tangent is indefinite along Δd) the search halves s until ‖r‖ decreases.

    Parameters
    ----------
    system, state
        See :func:`newton`.
    dd : (N, 3) float
        Newton update, cm.
    cfg : NewtonConfig
        ``line_search`` (off: the full step), ``max_line_search`` (evaluations after the first).
    pressure : (p, Δp), optional
        Newton on the mixed form: the carried patch pressure (N_p,) N/cm² and its update. The trial
        at s carries p + sΔp, and r is the force residual with the carried pressure
        (:meth:`~.system.MechanicalSystem.mixed_residual`): g(s) is then the slope along Δd of the
        potential at the pressure p + sΔp.

    Returns
    -------
    trial : State or None
        The accepted state (``None``: no acceptable step).
    s : float
        Its step factor.
    why : str
        Reason of the last rejection ("" when accepted at once).
    """
    t, alpha = state.t, state.alpha
    if pressure is None:
        def residual(st):
            return st.r

        def trial_state(s):
            return system.evaluate(state.d + s * dd, t, alpha)
    else:
        def residual(st):
            return system.mixed_residual(st)[0]

        def trial_state(s):
            return system.evaluate(state.d + s * dd, t, alpha, pressure=pressure[0] + s * pressure[1])
    r0 = residual(state)
    rn = _norm(system, r0)
    g0 = _inner(system, dd, r0)
    descent = g0 > 0.0
    lo, g_lo, hi, g_hi = 0.0, g0, None, None  # bracket of the root of g; g_hi None: slope unknown
    side = 0  # Illinois: which end was kept last (halve its g when kept twice)
    s, why = 1.0, ""
    best = None
    for _ in range(cfg.max_line_search + 1 if cfg.line_search else 1):
        try:
            cand = trial_state(s)
            rc_vec = residual(cand)
            rc = _norm(system, rc_vec)
            if not np.isfinite(rc):
                raise SolverError("non-finite residual")
        except SolverError as exc:
            why = str(exc)
            hi, g_hi = s, None
            s = lo + 0.5 * (hi - lo)
            continue
        if not cfg.line_search:
            return cand, s, ""
        g = _inner(system, dd, rc_vec)
        if rc <= rn or (descent and (abs(g) <= 0.5 * g0 or (g > 0.0 and hi is None))):
            return cand, s, ""
        why = f"no decrease of residual or energy (residual {rc:.3g} > {rn:.3g})"
        if not descent:
            s *= 0.5
            continue
        if g > 0.0:
            lo, g_lo, best = s, g, cand
            if side == -1 and g_hi is not None:
                g_hi *= 0.5
            side = -1
        else:
            hi, g_hi = s, g
            if side == 1:
                g_lo *= 0.5
            side = 1
        w = hi - lo
        s = lo + w * (g_lo / (g_lo - g_hi) if g_hi is not None else 0.5)
        s = min(max(s, lo + 0.1 * w), hi - 0.1 * w)
    if best is not None:  # Π decreased monotonically up to s_lo
        return best, lo, ""
    return None, s, why


def newton(system, state, cfg: NewtonConfig, linsolver, *, step: int = 0, fallback_tangent=None) -> NewtonResult:
    """Newton iterations from ``state`` at fixed load factor and activation.

    Parameters
    ----------
    system
        See the module docstring.
    state
        Evaluated start state (``system.evaluate(d0, t, alpha)``).
    cfg : NewtonConfig
    linsolver : LinearSolver
    step : int
        Load-step number, for the log.
    fallback_tangent : State or callable, optional
        Last converged state, or a function of no arguments that evaluates it: its tangent
        recomputes an update that is no descent direction of Π, or whose solve or line search
        fails (see the module docstring). ``None``: no fallback.

    Returns
    -------
    NewtonResult
        ``converged`` false (with ``reason``) instead of raising when the iteration fails.
    """
    rows = []
    E_ref = 0.0
    en_last = np.inf
    rn_prev = rm_prev = None
    rel = np.inf
    t = state.t
    mixed = (cfg.pressure_update == "mixed" and getattr(state, "vol", None) is not None
             and hasattr(linsolver, "solve_mixed"))
    for it in range(cfg.max_iterations + 1):
        rn = _norm(system, state.r)
        scale = state.force_scale
        if rn <= system.atol:  # round-off level: nothing left to do
            rel = 0.0
        else:
            rel = rn / scale if scale > 0 else np.inf
        if not np.isfinite(rn):
            return NewtonResult(state, False, it, rows, rel, "non-finite residual")
        _LOG.debug("load step %d, Newton iteration %d: residual %.3e N, relative %.3e", step, it, rn, rel)
        res_ok = rn <= cfg.residual_tol * scale + system.atol
        if res_ok and (it == 0 or en_last <= cfg.energy_tol * E_ref):
            rows.append(NewtonRow(step, t, it, rn, rel, 0.0, 0.0))
            return NewtonResult(state, True, it, rows, rel)
        if it == cfg.max_iterations:
            rows.append(NewtonRow(step, t, it, rn, rel, 0.0, 0.0))
            break
        target = cfg.residual_tol * scale + system.atol
        eta = forcing_term(rn, rn_prev, target, cfg.forcing_max)
        rn_prev = rn
        r, rp, p_step = state.r, None, None
        if mixed:  # Newton on the mixed form (module docstring)
            r, rp = system.mixed_residual(state)
            rm = float(np.hypot(_norm(system, r), system.pressure_weight * _norm(system, rp)))
            # Eisenstat–Walker on the mixed residual; the safeguard on the condensed one, which the
            # pressure rows' residual reaches multiplied by the bulk modulus
            eta = min(cfg.forcing_max, max(forcing_term(rm, rm_prev, 0.0, cfg.forcing_max), 0.1 * target / rn))
            rm_prev = rm
        # an update that is no descent direction of Π, or whose solve or line search fails, is computed
        # again with the (positive definite) tangent of the last converged state
        tangents = [state] if fallback_tangent is None else [state, fallback_tangent]
        trial = None
        for k, tangent_state in enumerate(tangents):
            try:
                if callable(tangent_state):  # a converged state kept as the function that evaluates it
                    tangent_state = tangent_state()
                linsolver.prepare(system, tangent_state)
                if rp is None:
                    dd = linsolver.solve(r.reshape(-1), rtol=eta).reshape(state.d.shape)
                else:
                    dd, dp = linsolver.solve_mixed(r.reshape(-1), rp, rtol=eta)
                    dd = dd.reshape(state.d.shape)
                    p0 = state.vol.pressure if state.pressure is None else state.pressure
                    p_step = None if dp is None else (p0, dp)
            except SolverGaveUp as exc:  # far harder than the systems before: the increment overshot
                rows.append(NewtonRow(step, t, it, rn, rel, 0.0, 0.0))
                return NewtonResult(state, False, it, rows, rel, f"linear solver gave up: {exc}")
            except SolverError as exc:
                if k + 1 < len(tangents):  # the converged state's tangent is the fallback
                    _LOG.debug("load step %d, Newton iteration %d: %s; using the converged tangent", step, it, exc)
                    continue
                rows.append(NewtonRow(step, t, it, rn, rel, 0.0, 0.0))
                return NewtonResult(state, False, it, rows, rel, f"linear solver: {exc}")
            if k + 1 < len(tangents) and _inner(system, dd, r) <= 0.0:
                continue
            trial, s, why = line_search(system, state, dd, cfg, pressure=p_step)
            if trial is not None:
                break
        en = abs(_inner(system, dd, r))
        E_ref = max(E_ref, en)
        if trial is None:
            rows.append(NewtonRow(step, t, it, rn, rel, en, 0.0))
            return NewtonResult(state, False, it, rows, rel, f"line search failed: {why}")
        rows.append(NewtonRow(step, t, it, rn, rel, en, s))
        en_last = s * en
        if cfg.pressure_update != "exact" and getattr(state, "vol", None) is not None and p_step is None:
            trial = system.evaluate(trial.d, trial.t, trial.alpha, pressure=system.linearised_pressure(state, s * dd))
        state = trial
    return NewtonResult(state, False, cfg.max_iterations, rows, rel,
                        f"no convergence in {cfg.max_iterations} iterations")


def _start(system, d, last, dt, t, alpha):
    """Start state of a load increment with a changing activation: the converged ``d`` at the new
    load factor and α, or the extrapolation of :func:`_predict` where its residual is smaller."""
    state = system.evaluate(d, t, alpha)
    if last is None:
        return state
    pred = _predict(system, d, last, dt, t, alpha)
    return pred if _norm(system, pred.r) < _norm(system, state.r) else state


def _fallback(system, state):
    """The converged ``state`` as the fallback tangent of the next increments: a function that
    evaluates it again from its d, t, α and carried pressure (the same state: ``evaluate`` is
    deterministic), so that its F, P and moduli are not held while they are not needed."""
    d, t, alpha, pressure = state.d, state.t, state.alpha, getattr(state, "pressure", None)
    return lambda: system.evaluate(d, t, alpha, pressure=pressure)


def _predict(system, d, last, dt, t, alpha):
    """Start state of a load increment: linear extrapolation of the last converged increment
    (scaled to ``dt``), or ``d`` itself when there is none or the extrapolation inverts a point."""
    if last is not None and dt > 0:
        try:
            return system.evaluate(d + (dt / last[1]) * last[0], t, alpha)
        except SolverError:
            pass
    return system.evaluate(d, t, alpha)


def held_halvings(dt: float, n_steps: int) -> int:
    """Halvings of the nominal increment 1/``n_steps`` that give the converged increment ``dt`` (the
    increment a resumed ramp holds after a cutback, as the uninterrupted one did)."""
    return max(0, int(round(np.log2(1.0 / (n_steps * dt))))) if dt > 0 else 0


def _stagnated(res: NewtonResult, cfg: NewtonConfig) -> bool:
    """A failed attempt that spent a third of ``max_iterations`` or more without halving its residual."""
    rel = [r.relative_residual for r in res.rows if np.isfinite(r.relative_residual)]
    return res.iterations >= max(2, cfg.max_iterations // 3) and bool(rel) and min(rel) > 0.5 * rel[0]


def _cutback_cannot_help(res: NewtonResult, stalled: int) -> str:
    """Why a smaller load increment cannot rescue a failed attempt ("" when it may).

    * the linear solver failed (other than by giving up on a hard system), or the residual was
      not finite, at the start state of the attempt (a singular tangent or a bad state does not
      depend on the increment);
    * two successive attempts, each with a halved increment, stagnated: Newton spent a third of its
      iterations or more without halving the residual, so the increment size is not what stops it
      (e.g. a prescribed stretch far beyond what the tissue model can follow).
    Quick failures (an inverted material point in the line search) always get their cutbacks.
    """
    if res.iterations == 0 and (res.reason.startswith("linear solver:") or res.reason == "non-finite residual"):
        return f"{res.reason.split(':')[0]} at the start of the increment, which a smaller increment does not change"
    if stalled >= 2:
        return "two successive cutbacks stagnated (a third of the Newton iterations or more without halving the residual)"
    return ""


@dataclasses.dataclass
class StepRecord:
    """Converged state of one load step and its Newton log."""

    step: int
    t: float
    alpha: float
    state: Any
    iterations: int
    cutbacks: int
    rows: list
    #: (Δd (N, 3) cm, Δt) of the last converged increment up to this step (None: none yet); the
    #: predictor of the next increment extrapolates it, so a resumed solve needs it
    increment: tuple | None = None
    #: the linear solver's :class:`~.linsolve.base.SolverMemory` after this step (None: nothing kept);
    #: a resumed solve rebuilds the solver from it, so that it decides as the uninterrupted one
    solver: Any = None


@dataclasses.dataclass
class SavedState:
    """What a checkpoint keeps of a converged state: coefficients d (N, 3) cm, load factor t and α
    exactly as the state was evaluated (``system.evaluate(d, t, alpha)`` rebuilds the rest)."""

    d: np.ndarray
    t: float
    alpha: float


def load_steps(system, n_steps: int, alpha_from: float, alpha_to: float, cfg: NewtonConfig, linsolver, *,
               on_step: Callable[[StepRecord], None] | None = None, d0: np.ndarray | None = None,
               resume: list[StepRecord] | None = None) -> list[StepRecord]:
    """Incremental loading over ``n_steps`` steps with cutback.

    Step k (k = 0..n_steps) reaches load factor t_k = k / n_steps and activation
    α_k = α_from + t_k (α_to − α_from). Step 0 solves the initial state (trivial unless α_from > 0).
    A step whose Newton iteration fails is retried with the increment halved (sub-steps), down to
    ``cfg.max_cutbacks`` halvings of the nominal increment 1/``n_steps``. With ``cfg.hold_cutback``
    (the default) the halved increment is kept for the later steps too, so a ramp whose full
    increment overshoots pays for one failed attempt, not one per step; the converged states are
    still reported at t_k.

    Parameters
    ----------
    system
        See the module docstring (needs ``n_nodes``).
    on_step : callable, optional
        Called with each converged :class:`StepRecord` (progress display, storage).
    resume : list of StepRecord, optional
        Converged steps 0..k of an interrupted run of the same system (a checkpoint): loading
        continues with step k + 1 from the last one's state (its ``state`` needs ``d``, ``t`` and
        ``alpha``; a full evaluated state is used as it is) and ``increment``, exactly as the
        uninterrupted run would have. ``on_step`` is not called for them.

    Returns
    -------
    list of StepRecord
        One per step, 0..n_steps (the resumed ones first). Only the last holds the evaluated
        state; the others hold its :class:`SavedState` (d, t, α): an evaluated state keeps
        F, P and the tangent moduli of every node (~0.9 kB per node, 0.27 GB at 295k nodes), which
        the ramp kept for every step until the end.

    Raises
    ------
    SolverError
        A step failed after all cutbacks; ``exc.records`` holds the converged steps before it.
    """
    def alpha_of(t):
        return alpha_from + t * (alpha_to - alpha_from)

    d = np.zeros((system.n_nodes, 3)) if d0 is None else np.asarray(d0, float).copy()
    records: list[StepRecord] = []
    t_done = 0.0
    conv = None  # last converged state (evaluated when needed): its tangent is the fallback of every increment
    final = None  # the evaluated state of the last step, which its record keeps
    # With a constant activation (displacement-driven loading) the tangent does not change with the load
    # factor, so the start of an increment is the linear extrapolation of the last converged increment
    # (the fastest start there). With a changing activation an increment starts at the converged d, or at
    # that extrapolation where its residual is smaller (on the 1.5k leg at every step, 0.4–0.9 times the
    # residual; on the 74k leg not in steps 2 and 3); the extrapolation can land where the new active stress
    # makes the tangent indefinite (the clamped block), which the fallback tangent then catches.
    passive_ramp = alpha_from == alpha_to
    last = None  # (increment of d, increment of t) of the last converged increment
    level = 0  # halvings of the nominal increment in force (held after a cutback with cfg.hold_cutback)
    if resume:
        records = list(resume)
        prev = records[-1]
        d, t_done, last = np.asarray(prev.state.d, float).copy(), float(prev.state.t), prev.increment
        if not passive_ramp:
            conv = _fallback(system, prev.state)
        if cfg.hold_cutback and last is not None:
            level = held_halvings(last[1], n_steps)
    for k in range(len(records), n_steps + 1):
        t_target = k / n_steps
        if not cfg.hold_cutback:
            level = 0
        dt = (t_target - t_done) / 2.0**level
        cut = subs = 0
        stalled = 0  # successive failed attempts in which Newton stagnated (see _stagnated)
        rows: list = []
        iters = 0
        first = True
        while first or t_done < t_target - 1e-12:
            first = False
            t_try = min(t_done + dt, t_target) if dt > 0 else t_target
            # no evaluated state is held here while Newton runs (the start, the predictor it lost to,
            # the last converged one): each keeps F, P and the moduli of every node (0.26 GB at 295k nodes)
            res = None
            try:
                if passive_ramp:
                    res = newton(system, _predict(system, d, last, t_try - t_done, t_try, alpha_of(t_try)), cfg,
                                 linsolver, step=k)
                else:
                    res = newton(system, _start(system, d, last, t_try - t_done, t_try, alpha_of(t_try)), cfg,
                                 linsolver, step=k, fallback_tangent=conv)
            except SolverError as exc:  # inverted already at the start of the increment
                res = NewtonResult(None, False, 0, [], np.inf, str(exc))
            rows.extend(res.rows)
            iters += res.iterations
            if res.converged:
                if t_try > t_done:
                    last = (res.state.d - d, t_try - t_done)
                    subs += 1
                d = res.state.d
                conv = _fallback(system, res.state)
                t_done = t_try
                state, res = res.state, None
                continue
            cut += 1
            stalled = stalled + 1 if _stagnated(res, cfg) else 0
            hopeless = _cutback_cannot_help(res, stalled)
            if not hopeless:
                _LOG.info("load step %d: Newton failed at load factor %.4g (%s); cutting back", k, t_try, res.reason)
            if level + 1 > cfg.max_cutbacks or dt <= 0 or hopeless:
                exc = SolverError(
                    f"load step {k} of {n_steps} (α = {alpha_of(t_try):.4g}, load factor {t_try:.4g}, increment {dt:.3g}) did "
                    f"not converge after {cut - 1} cutbacks in this step: {res.reason}; last relative residual {res.relative_residual:.3g}"
                    + (f"; stopped early: {hopeless}" if hopeless else "")
                )
                exc.records = records
                exc.rows = rows
                raise exc
            dt /= 2.0
            level += 1
        if subs > 1:
            _LOG.info("load step %d: %d increments of load factor (the last %.4g)", k, subs, last[1])
        rec = StepRecord(step=k, t=t_target, alpha=alpha_of(t_target), state=state, iterations=iters, cutbacks=cut, rows=rows,
                         increment=last)
        if records and not isinstance(records[-1].state, SavedState):  # a resumed last step's F, P and A go
            st = records[-1].state
            records[-1] = dataclasses.replace(records[-1], state=SavedState(st.d, st.t, st.alpha))
        records.append(rec)
        if on_step is not None:
            on_step(rec)
        # the next step does not hold this one's F, P and A (the fallback evaluates them again if needed)
        records[-1] = dataclasses.replace(rec, state=SavedState(state.d, state.t, state.alpha))
        final, state, rec = (state if k == n_steps else None), None, None
    if records and final is not None:  # the last step keeps its evaluated state
        records[-1] = dataclasses.replace(records[-1], state=final)
    return records

"""Total-Lagrangian finite-strain meshfree solve of a pixel-point model (paper §3 and §5): the load-step driver.

Pipeline of :func:`solve`:

1. the discrete system (:func:`.system.build_system`): RK shape functions and SCNI operators,
   materials per node, the constant stiffness (NSNI stabilisation and penalty) — everything that
   does not change during the solve (:class:`.system.MechanicalSystem`);
2. incremental loading: α ramped from ``activation.from`` to ``activation.to`` and prescribed
   displacements ramped from 0, Newton–Raphson per step (:mod:`.newton`), linear solves by the
   configured backend (:mod:`.linsolve`), which sees the system through
   :class:`~.linsolve.operator.SystemOperator`;
3. per converged step: RK-interpolated nodal displacements u(X_I) = Σ_J Ψ_J(X_I) d_J,
   reactions per constrained set, Cauchy stress at the nodes and its largest principal value.

The system's names (:class:`~.system.MechanicalSystem`, :class:`~.system.State`,
:func:`~.system.build_system`, …) stay importable from this module.
"""

from __future__ import annotations

import dataclasses
import logging
import time

import numpy as np

from ..errors import SolverError
from ..model.model import Model
from . import newton as _newton
from .boundary import SIGN_CONVENTION
from .config import SolveConfig
from .ellipticity import directions
from .heap import map_large_allocations, release_free_heap
from .linsolve import make_solver
from .results import NodeEllipticity, Results, max_principal
from .system import (
    LOCAL_RADIUS,
    LOCAL_TOL,
    MechanicalSystem,
    State,
    build_system,
    check_model,
    make_materials,
    material_kw,
    node_supports,
    rk_supports,
)

_LOG = logging.getLogger(__name__)

# the system of equations lives in .system; its names stay importable from here
__all__ = ["solve", "constraint_gap", "ellipticity_warning", "GAP_WARN", "LOCAL_RADIUS", "LOCAL_TOL", "MechanicalSystem",
           "State", "build_system", "check_model", "make_materials", "material_kw", "node_supports", "rk_supports",
           "node_ellipticity", "ELLIPTICITY_DIRECTIONS"]


#: the per-step nodal fields a solve's ``store`` takes (the displacement coefficients d stay: the
#: checkpoint records hold them)
STORED_FIELDS = ("u", "cauchy", "max_principal")

#: a constraint gap is worth a warning above this fraction of the largest displacement and of the voxel
GAP_WARN = 0.01


def constraint_gap(steps: list[dict], h_min: float) -> dict[str, dict]:
    """Largest constraint gap of every boundary condition over the converged steps.

    Per reaction name: ``max_cm`` — the largest error of the constrained components where the
    condition is imposed (the constraint points: end faces or nodes, :meth:`.boundary.Constraints.gaps`),
    cm — and ``relative``, the same divided by the largest nodal displacement of the solve (0 when
    nothing moves); ``node_cm`` and ``relative_node``: the same at the constrained nodes themselves
    (for end sets constrained on their end faces, the node layer half a voxel inside the face moves
    with the tissue between them); ``max_displacement_cm`` (the largest of the steps' ``u_max_cm``);
    ``significant``: the gap exceeds :data:`GAP_WARN` of both the largest displacement and the
    smallest voxel edge ``h_min`` (cm) — in a nearly isometric solve a gap of a few µm can be
    percents of the tiny largest displacement).
    """
    if not steps:
        return {}
    umax = max(s["u_max_cm"] for s in steps)
    out = {}
    for name in steps[0]["gaps"]:
        pt = max(s["gaps"][name]["point_cm"] for s in steps)
        nd = max(s["gaps"][name]["node_cm"] for s in steps)
        rel = pt / umax if umax > 0 else 0.0
        out[name] = {"max_cm": pt, "relative": rel, "node_cm": nd, "relative_node": nd / umax if umax > 0 else 0.0,
                     "max_displacement_cm": umax, "significant": bool(rel > GAP_WARN and pt > GAP_WARN * h_min)}
    return out


#: reference directions of the ellipticity check at the nodes
ELLIPTICITY_DIRECTIONS = 300


def node_ellipticity(system: MechanicalSystem, state: State, step: int) -> NodeEllipticity | None:
    """The material law's smallest acoustic-tensor eigenvalue at every node at ``state`` (stored state
    ``step``), :func:`.ellipticity.acoustic_minimum` over :data:`ELLIPTICITY_DIRECTIONS` directions,
    N/cm²; the law is not strongly elliptic where it is < 0. None on the ranks but 0 of a distributed system."""
    q = system.ellipticity_minimum(state, directions(ELLIPTICITY_DIRECTIONS))
    return None if q is None else NodeEllipticity(step=int(step), minimum=q, n_directions=ELLIPTICITY_DIRECTIONS)


def ellipticity_warning(minimum: np.ndarray) -> tuple[int, str]:
    """Nodes where the material law is not strongly elliptic at the last converged step, and a one-line warning.

    Parameters
    ----------
    minimum : (N,) float
        Smallest acoustic-tensor eigenvalue per node, N/cm² (:func:`node_ellipticity`).

    Returns
    -------
    (count, message)
        The message names the count, the smallest eigenvalue and what it means for the results.
    """
    q = np.asarray(minimum, float)
    bad = int(np.count_nonzero(q < 0.0))
    return bad, (f"the material law is not strongly elliptic at {bad} of {q.size} nodes at the last converged step "
                 f"(smallest acoustic-tensor eigenvalue {q.min():.3g} N/cm²): deformation can localise there and "
                 f"forces and fields depend on the resolution (pixmuscle.mechanics.ellipticity)")


def _build(model: Model, cfg: SolveConfig):
    """The system of this process: under ``mpiexec`` with a PETSc backend this rank's part of a
    distributed system (:mod:`.distributed`), else the whole one."""
    from .. import parallel
    from .linsolve import BACKENDS

    if parallel.size() > 1 and BACKENDS.entry_of(cfg.solver).name in ("petsc", "petsc_mixed"):
        from .distributed import build_distributed_system

        return build_distributed_system(model, cfg)
    return build_system(model, cfg)


def solve(model: Model, cfg: SolveConfig | None = None, progress=None, activation=None, *,
          resume: list | None = None, on_checkpoint=None, store=None) -> Results:
    """Solve the finite-strain equilibrium of a pixel-point model over the load steps.

    Parameters
    ----------
    model : Model
    cfg : SolveConfig, optional
        Defaults: paper settings (see :mod:`pixmuscle.mechanics.config`).
    progress : object with ``advance(n=1, **fields)``, optional
        Advanced once per converged load step with α and the final Newton residual.
    activation : ActivationRamp, optional
        Per-node α at the start and end of the ramp (:mod:`.activation`); default: built from
        ``cfg.activation`` (numbers or per-muscle mappings; an image needs the stage layer).
        ``/steps/alpha`` then holds the mean α of the muscle nodes.
    resume : list of :class:`~.newton.StepRecord`, optional
        Converged steps 0..k of an interrupted solve of this model and configuration (a
        checkpoint, states as :class:`~.newton.SavedState`): their records are rebuilt from d and
        loading continues at step k + 1 exactly as the uninterrupted solve would have.
    on_checkpoint : callable, optional
        Called after each converged step with the list of all converged
        :class:`~.newton.StepRecord` so far (the stage writes them to a checkpoint file).
    store : object with ``append(fields)`` and ``read(name)``, optional
        Where each converged step's nodal fields ``u``, ``cauchy`` and ``max_principal`` go as soon as
        the step has converged (:class:`pixmuscle.io.results.StepStore`, a file), read back when the
        results are made; default: they are held in memory until then.

    Returns
    -------
    Results
        Every step 0..S (status ``"complete"``).

    Raises
    ------
    InputError
        Bad model or configuration (e.g. an unknown node set).
    SolverError
        A load step failed after all cutbacks. ``exc.results`` holds a :class:`Results` with the
        converged steps and ``status = "failed: ..."``.
    """
    cfg = cfg or SolveConfig()
    t_start = time.perf_counter()
    map_large_allocations()  # freed per-node arrays go back to the system at once, not into the heap's holes
    if activation is None and not cfg.uniform_activation:
        from .activation import activation_ramp

        activation = activation_ramp(model, cfg.activation)
    system, info = _build(model, cfg)
    release_free_heap()  # the build's temporaries: their heap pages would stay resident through the solve
    system.activation = activation
    root = getattr(system, "layout", None) is None or system.layout.rank == 0
    linsolver = make_solver(cfg.solver, model.X, ijk=model.ijk,
                            width=2 * np.floor(np.asarray(cfg.support.a_over_h) + 0.5).astype(int))
    steps: list = []
    last_state: list = []
    lin_time = {"setup_s": 0.0, "solve_s": 0.0, "iterations": []}

    class _Timed:
        name = linsolver.name

        prepared = None  # the state whose tangent the linear solver is prepared for

        def prepare(self, system, state):
            t0 = time.perf_counter()
            linsolver.prepare(system, state)
            self.prepared = state
            # every Newton iteration: the last iteration's trial states and temporaries, which glibc serves
            # from the heap's trimmed free space whatever their size and keeps resident once freed (0.7 GB
            # at 295k nodes from the first line search on, docs/performance.md)
            release_free_heap()
            lin_time["setup_s"] += time.perf_counter() - t0

        def _timed(self, method, *args, **kw):
            t0 = time.perf_counter()
            out = method(*args, **kw)
            lin_time["solve_s"] += time.perf_counter() - t0
            lin_time["iterations"].append(linsolver.info["iterations"])
            # one solve per prepared tangent (newton.py): its operator and the prepared state's moduli
            # are let go before the line search evaluates its trial state
            linsolver.finish()
            system.release_moduli(self.prepared)
            self.prepared = None
            return out

        def solve(self, r, rtol=None):
            return self._timed(linsolver.solve, r, rtol=rtol)

        if hasattr(linsolver, "solve_mixed"):  # Newton then runs on the mixed form (newton.py)
            def solve_mixed(self, r, rp, rtol=None):
                return self._timed(linsolver.solve_mixed, r, rp, rtol=rtol)

    done: list = []

    def on_step(rec, replay=False):
        st = rec.state
        last_state[:] = [(st.d, st.t, st.alpha)]  # evaluated again at the end: its F, P and A are not held meanwhile
        out = system.step_output(st)  # under MPI: the nodal fields on rank 0 only (None elsewhere)
        steps.append(dict(alpha=rec.alpha if activation is None else activation.mean(rec.alpha), t=rec.t,
                          iterations=rec.iterations, cutbacks=rec.cutbacks, rows=rec.rows, **out))
        steps[-1]["max_principal"] = None if out["cauchy"] is None else max_principal(out["cauchy"])
        steps[-1]["u_max_cm"] = None if out["u"] is None else float(np.linalg.norm(out["u"], axis=1).max())
        if store is not None and out["cauchy"] is not None:  # not held until the end (under MPI: rank 0's)
            store.append({name: steps[-1].pop(name) for name in STORED_FIELDS})
        last_rel = rec.rows[-1].relative_residual if rec.rows else 0.0
        # the checkpoint's records hold the whole model's d (rank 0 writes them)
        inc = rec.increment
        if inc is not None:
            inc = (system.gather(inc[0]), inc[1])
        mem = rec.solver if replay else system.memory_for_checkpoint(linsolver.memory())
        if done:  # a checkpoint keeps the last record's increment and solver memory only (io.checkpoint)
            done[-1] = dataclasses.replace(done[-1], increment=None, solver=None)
        done.append(dataclasses.replace(rec, state=_newton.SavedState(out["d"], st.t, st.alpha),  # no F, P, A kept
                                        increment=inc, solver=mem))
        if on_checkpoint is not None and not replay and root:
            on_checkpoint(done)
        release_free_heap()  # the step's freed temporaries: pages held in the heap's holes would add up over the steps
        _LOG.log(logging.DEBUG if replay else logging.INFO, "load step %d of %d: α = %.4g, load factor %.4g, %d Newton iterations, %d cutbacks, relative residual %.2e",
                  rec.step, cfg.steps, steps[-1]["alpha"], rec.t, rec.iterations, rec.cutbacks, last_rel)
        if progress is not None:
            last = rec.rows[-1].relative_residual if rec.rows else 0.0
            if activation is None and cfg.alpha_from == cfg.alpha_to:  # displacement-driven: show the load factor
                progress.advance(1, load=float(rec.t), residual=float(last))
            else:
                progress.advance(1, alpha=float(steps[-1]["alpha"]), residual=float(last))

    status = "complete"
    error = None
    try:
        ramp = (cfg.alpha_from, cfg.alpha_to) if activation is None else (0.0, 1.0)
        owned = []  # the resumed records as this system's rows (a rank's own nodes under MPI)
        for rec in resume or ():  # the converged steps of the interrupted run, rebuilt from their d
            st = rec.state
            inc = None if rec.increment is None else (system.owned_of(rec.increment[0]), rec.increment[1])
            mine = dataclasses.replace(rec, state=system.evaluate(system.owned_of(np.asarray(st.d, float)), st.t, st.alpha),
                                       increment=inc)
            on_step(mine, replay=True)
            # only the last keeps its evaluated state (F, P and the moduli of every node)
            owned[-1:] = [dataclasses.replace(r, state=_newton.SavedState(r.state.d, r.state.t, r.state.alpha))
                          for r in owned[-1:]]
            owned.append(mine)
        if done:
            info["resumed_after_step"] = len(done) - 1
            mem = done[-1].solver  # the preconditioner or factors the interrupted solve held
            if mem is not None and mem.backend == linsolver.memory_tag:
                t0 = time.perf_counter()
                linsolver.recall(system, system.memory_from_checkpoint(mem))
                lin_time["setup_s"] += time.perf_counter() - t0
            elif mem is not None:
                _LOG.warning("the checkpoint's linear-solver memory is of backend %s, this solve uses %s: it starts "
                             "afresh, and its forces agree with an uninterrupted run to the Newton tolerance only",
                             mem.backend, linsolver.memory_tag)
        _newton.load_steps(system, cfg.steps, *ramp, cfg.newton, _Timed(), on_step=on_step, resume=owned or None)
    except SolverError as exc:
        status = f"failed: {exc}"
        error = exc
        failed_rows = getattr(exc, "rows", [])
    else:
        failed_rows = []
    linsolver.release()  # the preconditioner does not share the peak with the last evaluation and the results
    done.clear()  # each step's d is then held by its results row only, which Results.from_steps moves
    info.update(total_s=time.perf_counter() - t_start, linear_setup_s=lin_time["setup_s"],
                linear_solve_s=lin_time["solve_s"], linear_iterations=lin_time["iterations"])
    info.update(linsolver.statistics())
    info.update(system.statistics())
    gaps = constraint_gap(steps, float(np.min(model.spacing))) if root else {}
    for name, g in gaps.items():
        _LOG.log(logging.WARNING if g["significant"] else logging.INFO,
                 "boundary condition %s: constraint gap %.3g cm (%.2g %% of the largest displacement, %.3g cm); "
                 "its nodes move %.3g cm in the constrained components", name, g["max_cm"], 100 * g["relative"],
                 g["max_displacement_cm"], g["node_cm"])
    warnings = list(getattr(linsolver, "warnings", []))
    ellipticity = None
    if last_state:  # computed once, at the last converged state: the warning and the stored field
        ellipticity = node_ellipticity(system, system.evaluate(*last_state[0]), len(steps) - 1)
    if ellipticity is not None:
        bad, msg = ellipticity_warning(ellipticity.minimum)
        info["non_elliptic_nodes"] = bad
        if bad:
            _LOG.warning(msg)
            warnings.append(msg)
    constrained = system.constrained_components()
    if not root:  # a distributed solve's results are rank 0's
        if error is not None:
            error.results = None
            raise error
        return None
    stacked = {name: store.read(name) for name in STORED_FIELDS} if store is not None and steps else None
    results = Results.from_steps(model, steps, stacked=stacked, failed_rows=failed_rows, status=status, n_steps=cfg.steps,
                                 constrained=constrained, info=info,
                                 sign_convention=SIGN_CONVENTION, constraint_gap=gaps, warnings=warnings,
                                 ellipticity=ellipticity)
    if error is not None:
        error.results = results
        raise error
    return results

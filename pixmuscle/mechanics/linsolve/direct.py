"""Sparse direct backend ``direct``: a factorisation engine (PARDISO or SuperLU) and a reuse policy."""

from __future__ import annotations

import dataclasses
import time
from dataclasses import field
from typing import Literal

import numpy as np
import scipy.sparse.linalg as spla

from ...errors import SolverError
from .base import BACKENDS, LinearSolver, SolverMemory, Tolerance, built_from, memory_state, pcg
from .factorization import ENGINES, PARDISO_MISSING, engine_name


@dataclasses.dataclass(frozen=True)
class DirectOptions(Tolerance):
    """Options of ``solve.solver: {backend: direct, …}``."""

    engine: Literal["auto", "pardiso", "superlu"] = field(default="auto", metadata={"doc": "MKL PARDISO (optional package mkl, pip install 'pixmuscle[fast]') or SciPy's SuperLU; auto takes PARDISO when installed"})
    reuse_factorization: bool = field(default=True, metadata={"doc": "keep the factors of an earlier tangent and use them to precondition CG on the exact (matrix-free) tangent; refactorise when that gets slow (a solve needs more than 20 CG iterations; counted in iterations, not seconds, so that a run repeats itself exactly)"})

    def __post_init__(self):
        if self.engine == "pardiso" and engine_name("auto") != "pardiso":
            raise ValueError(PARDISO_MISSING)


_FACTORS = ("none", "current", "reused", "stale")  # the states of ReusePolicy.factors


class ReusePolicy:
    """When the direct backend factorises: the state of the kept factors.

    ``factors`` is ``"none"`` (nothing factorised yet), ``"current"`` (the factors are of the
    tangent being solved: direct solves), ``"reused"`` (of an earlier tangent: they precondition a
    Krylov solve on the current one) or ``"stale"`` (too slow as a preconditioner: factorise the
    next tangent). Without ``reuse`` every tangent is factorised.

    Parameters
    ----------
    reuse : bool
    krylov_maxiter : int
        Krylov iterations per solve with kept factors; a solve that needs more than half of them
        makes the factors stale.
    """

    def __init__(self, reuse: bool, krylov_maxiter: int):
        self.reuse = reuse
        self.krylov_maxiter = krylov_maxiter
        self.factors = "none"

    def keep(self) -> bool:
        """At a new Newton state: keep the factors (and solve matrix-free) instead of assembling?"""
        return self.reuse and self.factors in ("current", "reused")

    def must_factorize(self) -> bool:
        """Given an assembled tangent: factorise it?"""
        return self.factors in ("none", "stale") or not self.reuse

    def factorized(self) -> None:
        """The current tangent was factorised."""
        self.factors = "current"

    def kept(self) -> None:
        """The kept factors serve the current tangent as a preconditioner."""
        self.factors = "reused"

    @property
    def exact(self) -> bool:
        """True when the factors are of the current tangent."""
        return self.factors == "current"

    def solved(self, iterations: int) -> None:
        """A Krylov solve with the kept factors converged: are they still worth keeping?

        By the iteration count alone (a rule in seconds would make two runs of one config take
        different decisions). At 5k–20k nodes a refactorisation costs about as much as 20–25
        iterations with kept factors, so the two rules nearly agree."""
        if iterations > self.krylov_maxiter // 2:
            self.factors = "stale"  # refactorise at the next Newton iteration


@BACKENDS.register("direct", options=DirectOptions)
class DirectSolver(LinearSolver):
    """Sparse direct factorisation of the assembled tangent, with optional factorisation reuse.

    The factorisation is an engine's (:mod:`.factorization`): ``pardiso``
    (:class:`~.factorization.PardisoFactor`, MKL PARDISO LDLᵀ), ``superlu``
    (:class:`~.factorization.SuperLUFactor`, SciPy's SuperLU in a nested-dissection order of the
    voxel grid ``ijk``) or ``auto`` (PARDISO when MKL is installed, otherwise SuperLU). Every
    solve gets up to three steps of iterative refinement against the assembled matrix; if it is
    still inaccurate, the engine escalates its pivoting and refactorises, or, when it cannot,
    GMRES preconditioned by the factors finishes the solve.

    Reuse (``reuse=True``, :class:`ReusePolicy`): the factors of an earlier tangent K₀ are kept and
    later systems K x = r are solved by conjugate gradients on the matrix-free exact tangent
    (:meth:`~pixmuscle.mechanics.system.MechanicalSystem.tangent_operator`, no assembly)
    preconditioned with K₀⁻¹ (GMRES if K₀ was indefinite), to the tolerance the caller asks
    (inexact Newton). The tangent is refactorised at the next Newton iteration when a solve
    needed more than ``krylov_maxiter``/2 iterations, and at once when it fails to converge in
    ``krylov_maxiter``.
    """

    name = "direct"

    def __init__(self, reuse: bool = True, rtol: float = 1e-10, krylov_maxiter: int = 40, ijk=None, width=(4, 4, 4),
                 engine: str = "auto"):
        super().__init__()
        name = engine_name(engine)
        if name not in ENGINES:
            raise ValueError(f"unknown direct engine {engine!r}: expected auto, {', '.join(ENGINES)}")
        self.engine = ENGINES[name](ijk=ijk, width=width)
        self.policy = ReusePolicy(reuse, krylov_maxiter)
        self.rtol = rtol
        self.krylov_maxiter = krylov_maxiter
        self._K = None
        self._op = None
        self._system = self._state = None
        self._K_at = None  # (d, t, α, carried pressure) of the state whose tangent self._K is (None: not known)
        self._factored_at = None  # the same for the kept factors
        self.info.update(factorizations=0, krylov_iterations=0, engine=name, analysis_s=0.0)

    @classmethod
    def from_options(cls, opts: DirectOptions, X, *, ijk=None, width=(4, 4, 4)) -> DirectSolver:
        return cls(reuse=opts.reuse_factorization, rtol=opts.rtol, ijk=ijk, width=width, engine=opts.engine)

    # -- factorisation -------------------------------------------------------------------
    def _refactor(self):
        t0 = time.perf_counter()
        self.engine.factorize(self._K)
        self._factored_at = self._K_at
        self.info.update(self.engine.info)
        self.policy.factorized()
        self.info["factorizations"] += 1
        self.info["setup_s"] += time.perf_counter() - t0

    def _accurate_solve(self, r):
        """Factor solve with up to 3 steps of iterative refinement; escalate (engine pivoting, or GMRES) if inaccurate."""
        rn = np.linalg.norm(r)
        while True:
            x = self.engine.solve(r)
            self.info["iterations"] = 1
            for _ in range(3):
                if not np.all(np.isfinite(x)):
                    break
                res = r - self._K @ x
                if np.linalg.norm(res) <= 1e-10 * rn:
                    break
                x = x + self.engine.solve(res)
                self.info["iterations"] += 1
            ok = np.all(np.isfinite(x)) and np.linalg.norm(r - self._K @ x) <= 1e-8 * rn
            if ok:
                return x
            if not self.engine.escalate():  # perturbed pivots of a nearly singular tangent: Krylov on top
                return self._krylov(self._K, r, 1e-10, x0=x if np.all(np.isfinite(x)) else None, gmres=True)[0]
            self._refactor()

    def _krylov(self, A, r, rtol, x0=None, gmres=False):
        """Solve A x = r preconditioned by the kept factors; returns (x, iterations, converged)."""
        M = spla.LinearOperator(A.shape, matvec=lambda v: self.engine.solve(np.asarray(v, float).ravel()))
        if not gmres:
            x, its, status = pcg(A, r, M, rtol, self.krylov_maxiter, x0=x0)
            return x, its, status == "converged"
        count = [0]

        def cb(_):
            count[0] += 1

        x, flag = spla.gmres(A, r, x0=x0, rtol=rtol, atol=0.0, restart=self.krylov_maxiter, maxiter=1, M=M,
                             callback=cb, callback_type="pr_norm")
        return x, count[0], flag == 0 and bool(np.all(np.isfinite(x)))

    # -- interface -----------------------------------------------------------------------
    def prepare(self, system, state):
        """Factorise the tangent of ``state``, or (reuse) keep the factors and take the matrix-free tangent."""
        self.info["setup_s"] = 0.0
        if self.policy.keep():
            self._system, self._state = system, state
            self._K = None
            self._op = system.tangent_operator(state)
            self.policy.kept()
            return
        self._system = self._state = None
        self._take(system.stiffness(state), state)

    def factorize(self, K):
        """Take the assembled tangent ``K``; factorise it unless ``reuse`` keeps earlier factors."""
        self._take(K, None)

    def _take(self, K, state):
        self._K = K
        self._K_at = None if state is None else built_from(state)
        self._op = K
        self.info["setup_s"] = 0.0
        if self.policy.must_factorize():
            self._refactor()
        else:
            self.policy.kept()

    def solve(self, r, rtol=None):
        t0 = time.perf_counter()
        setup0 = self.info["setup_s"]
        r = np.asarray(r, float)
        x = None
        if not self.policy.exact:
            target = self.rtol if rtol is None else max(float(rtol), 1e-14)
            x, its, ok = self._krylov(self._op, r, target, gmres=not self.engine.definite)
            self.info["iterations"] = its
            self.info["krylov_iterations"] += its
            if not ok:
                x = None
                if self._K is None:  # matrix-free reuse: assemble the current tangent now
                    t1 = time.perf_counter()
                    self._K = self._system.stiffness(self._state)
                    self._K_at = built_from(self._state)
                    self.info["setup_s"] += time.perf_counter() - t1
                self._refactor()
            else:
                self.policy.solved(its)
        if x is None:
            x = self._accurate_solve(r)
        self.info["solve_s"] = time.perf_counter() - t0 - (self.info["setup_s"] - setup0)
        if not np.all(np.isfinite(x)):
            raise SolverError("direct solver returned non-finite values (singular stiffness)")
        return x

    def memory(self) -> SolverMemory | None:
        """The state whose tangent the kept factors are of, and what the reuse rule holds of them
        (None when they came from :meth:`factorize` without a state, or the next system
        refactorises anyway)."""
        if self._factored_at is None or not self.policy.keep():  # none, or refactorised at the next system anyway
            return None
        d, t, alpha, pressure = self._factored_at
        return SolverMemory(d, t, alpha, pressure=pressure, backend=self.memory_tag, counters={
            "factors": float(_FACTORS.index(self.policy.factors)), "level": float(getattr(self.engine, "level", 0))})

    def recall(self, system, memory: SolverMemory) -> None:
        """Factorise the tangent at ``memory``'s state and restore the reuse rule's verdict on it."""
        state = memory_state(system, memory)
        self._system = self._state = None
        self._K, self._op = system.stiffness(state), None
        self._K_at = built_from(state)
        if hasattr(self.engine, "level"):  # SuperLU's pivoting level, raised by earlier tangents
            self.engine.level = int(memory.counters.get("level", self.engine.level))
        self._refactor()
        self._op = self._K
        self.policy.factors = _FACTORS[int(memory.counters["factors"])]

    def statistics(self) -> dict:
        """Name, engine (``linear_engine``), ``factorizations``, ``krylov_iterations`` (with kept
        factors) and, from PARDISO, ``factor_nnz`` (entries of L of the last factorisation)."""
        out = super().statistics() | {"linear_engine": self.info["engine"], "factorizations": self.info["factorizations"],
                                      "krylov_iterations": self.info["krylov_iterations"]}
        if "factor_nnz" in self.info:
            out["factor_nnz"] = int(self.info["factor_nnz"])
        return out

"""Interface of a linear-solver backend, the backend registry, and the Krylov pieces the backends share.

A backend is one module of this package: a :class:`LinearSolver` subclass registered in
:data:`BACKENDS` under the backend's name with its own frozen options dataclass, which is the
config section ``solve.solver: {backend: <name>, …options}``::

    @dataclasses.dataclass(frozen=True)
    class MyOptions(Iterative):          # rtol and maxiter, plus the backend's own fields
        omega: float = field(default=1.0, metadata={"gt": 0, "doc": "relaxation factor"})

    @BACKENDS.register("mybackend", options=MyOptions)
    class MySolver(LinearSolver):
        name = "mybackend"

        @classmethod
        def from_options(cls, opts, X, *, ijk=None, width=(4, 4, 4)):
            return cls(rtol=opts.rtol, maxiter=opts.maxiter, omega=opts.omega)

The package imports its modules when it loads (:meth:`~pixmuscle.registry.Registry.discover`), so
the backend is then known to the config, to :func:`pixmuscle.mechanics.linsolve.make_solver` and
to :func:`pixmuscle.mechanics.solve.solve`, which merges its :meth:`LinearSolver.statistics`
into the results' ``info``; nothing else changes.
"""

from __future__ import annotations

import dataclasses
from dataclasses import field

import numpy as np
import scipy.sparse as sp

from ...registry import Registry

#: Registered linear-solver backends: ``solve.solver: {backend: <name>, …options}``.
BACKENDS = Registry("linear-solver backend", key="backend", package="pixmuscle.mechanics.linsolve")


@dataclasses.dataclass(frozen=True)
class Tolerance:
    """Options every backend has: the accuracy of a linear solve when Newton asks for none."""

    rtol: float = field(default=1.0e-10, metadata={"gt": 0, "doc": "relative residual of the Krylov iterations when "
                                                                    "Newton gives none; also the floor of Newton's "
                                                                    "adaptive tolerance"})


@dataclasses.dataclass(frozen=True)
class Iterative(Tolerance):
    """Options of an iterative backend: tolerance and iteration limit."""

    maxiter: int = field(default=2000, metadata={"range": (1, None), "doc": "Krylov iterations per linear solve"})


class LinearSolver:
    """Interface of a linear-solver backend.

    ``info`` holds the counters of the last solve (``iterations``, ``setup_s``, ``solve_s``) and
    the backend's running totals; :meth:`statistics` is what the results keep of them.
    """

    name = "base"

    def __init__(self):
        self.info = {"iterations": 0, "setup_s": 0.0, "solve_s": 0.0}
        self.warnings: list[str] = []  # what the results' warnings should say about this solver's choices

    @classmethod
    def from_options(cls, opts, X: np.ndarray, *, ijk: np.ndarray | None = None, width=(4, 4, 4)) -> LinearSolver:
        """The backend for nodes ``X`` (N, 3) cm, configured by its options dataclass ``opts``.

        ``ijk`` (N, 3) int are the voxel indices of the nodes; ``width`` (3,) int the coupling
        reach of the stiffness per axis, in cells (2·⌊a/h + ½⌋).
        """
        raise NotImplementedError  # pragma: no cover - interface

    def prepare(self, system, state) -> None:
        """Set up for the tangent of ``state`` (default: factorise the assembled stiffness)."""
        self.factorize(system.stiffness(state))

    def factorize(self, K: sp.spmatrix) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def solve(self, r: np.ndarray, rtol: float | None = None) -> np.ndarray:  # pragma: no cover - interface
        """Solve K x = r; ``rtol`` is the accuracy the caller needs (iterative backends)."""
        raise NotImplementedError

    @property
    def memory_tag(self) -> str:
        """What a checkpoint's solver memory names its solver by: a memory is recalled only by a
        solver with the same tag (the backend's name; with its multigrid for the AMG backends)."""
        return self.name

    def statistics(self) -> dict:
        """Totals of the whole solve for the results' ``info`` (merged as they are): the backend's
        name under ``linear_solver`` and whatever counts the backend keeps."""
        return {"linear_solver": self.name}

    def finish(self) -> None:
        """The prepared system's solve is done: let go of its operator, which reads the state's
        moduli, until the next :meth:`prepare` (the factors or preconditioner stay). The load-step
        driver calls it after each solve, so that the line search's trial state is not evaluated
        beside the moduli of the iterate. Default: nothing to let go."""

    def release(self) -> None:
        """Let go of the factors, preconditioner and operators of the last prepared system (the
        counters, statistics and :meth:`memory` stay; a later :meth:`prepare` builds afresh). The
        load-step driver calls it after the last step, before the results are made, so that they
        do not share the peak with the preconditioner. Default: nothing to let go."""

    def memory(self) -> SolverMemory | None:
        """What a resumed solve needs to take this solver's next decisions as the uninterrupted one
        would (a checkpoint keeps it with the last converged step); None: nothing kept, a resumed
        solve starts the backend afresh."""
        return None

    def recall(self, system, memory: SolverMemory) -> None:
        """Rebuild what :meth:`memory` described: the preconditioner or factors of the tangent at
        ``memory``'s state, and the counters of the rules that decide when to rebuild them."""


def built_from(state) -> tuple:
    """(d (N, 3) cm, copied; t; α; the tangent's carried patch pressure or None) of an evaluated
    ``state``: what a backend keeps to say which tangent its factors or preconditioner are of
    (:class:`SolverMemory`)."""
    p = getattr(state, "pressure", None)
    return np.array(state.d, float), float(state.t), float(state.alpha), None if p is None else np.array(p, float)


def memory_state(system, memory: SolverMemory):
    """The state whose tangent ``memory`` was built from, evaluated again."""
    return system.evaluate(np.asarray(memory.d, float), memory.t, memory.alpha, pressure=memory.pressure)


@dataclasses.dataclass
class SolverMemory:
    """A backend's kept preconditioner or factors, as a state to rebuild them from, and its counters.

    Attributes
    ----------
    d : (N, 3) float
        RK coefficients of the state whose tangent they were built from, cm.
    t, alpha : float
        Load factor and activation at which that state was evaluated.
    counters : dict of str to float
        The backend's decision counters (e.g. the reference rate and the extra iterations of the
        AMG rebuild rule); NaN for "not set".
    backend : str
        :attr:`LinearSolver.memory_tag` of the solver that kept it (a resumed solve with another, e.g.
        ``auto`` on a machine without MKL or petsc4py, does not use it).
    pressure : (N_p,) float or None
        The patch pressure of that tangent when Newton carried one (N/cm²), else None.
    """

    d: np.ndarray
    t: float
    alpha: float
    counters: dict
    backend: str = ""
    pressure: np.ndarray | None = None


def rigid_body_modes(X: np.ndarray) -> np.ndarray:
    """Six rigid-body modes (3 translations, 3 rotations about the centroid) as (3N, 6) columns."""
    X = np.asarray(X, float)
    Xc = X - X.mean(axis=0)
    n = X.shape[0]
    B = np.zeros((n, 3, 6))
    for k in range(3):
        B[:, k, k] = 1.0
    x, y, z = Xc.T
    B[:, 0, 3], B[:, 1, 3] = -y, x
    B[:, 1, 4], B[:, 2, 4] = -z, y
    B[:, 0, 5], B[:, 2, 5] = z, -x
    return B.reshape(3 * n, 6)


def pcg(A, b: np.ndarray, M, rtol: float, maxiter: int, x0: np.ndarray | None = None):
    """Preconditioned conjugate gradients for a symmetric positive definite operator.

    Parameters
    ----------
    A, M : objects with ``@`` (operator and preconditioner)
    b : (n,) float
    rtol : float
        Stop when ‖b − A x‖ ≤ rtol ‖b‖ (recursively updated residual).
    maxiter : int
    x0 : (n,) float, optional

    Returns
    -------
    x : (n,) float
    iterations : int
    status : str
        ``"converged"``, ``"maxiter"`` or ``"breakdown"`` (pᵀ A p ≤ 0: A is not positive definite).
    """
    x = np.zeros_like(b) if x0 is None else np.array(x0, float)
    r = b - A @ x if x0 is not None else b.copy()
    bn = float(np.linalg.norm(b))
    if bn == 0.0:
        return x, 0, "converged"
    if float(np.linalg.norm(r)) <= rtol * bn:
        return x, 0, "converged"
    z = M @ r
    p = z.copy()
    rz = float(r @ z)
    for it in range(1, maxiter + 1):
        q = A @ p
        pq = float(p @ q)
        if not pq > 0.0:
            return x, it, "breakdown"
        a = rz / pq
        x += a * p
        r -= a * q
        if float(np.linalg.norm(r)) <= rtol * bn:
            return x, it, "converged"
        z = M @ r
        rz_new = float(r @ z)
        p *= rz_new / rz
        p += z
        rz = rz_new
    return x, maxiter, "maxiter"

"""Interface of a linear-solver backend, the backend registry, and the Krylov pieces the backends share.

A backend is one module: a :class:`LinearSolver` subclass and a factory registered under the
backend's name with :func:`register`. The factory takes the node coordinates and the options of
``solve.solver`` (keyword arguments; each factory takes the ones it needs and ignores the others)::

    @register("mybackend")
    def _make(X, *, ijk=None, rtol=1e-10, **_):
        return MySolver(X, rtol=rtol)

:func:`pixmuscle.mechanics.linsolve.make_solver` then builds it by name; nothing else changes.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import scipy.sparse as sp

#: backend name → factory ``(X, **options) -> LinearSolver``
BACKENDS: dict[str, Callable] = {}


def register(name: str) -> Callable:
    """Decorator: register a backend factory under ``name`` (the value of ``solve.solver.backend``)."""

    def deco(factory: Callable) -> Callable:
        BACKENDS[name] = factory
        return factory

    return deco


class LinearSolver:
    """Interface of a linear-solver backend."""

    name = "base"

    def __init__(self):
        self.info = {"iterations": 0, "setup_s": 0.0, "solve_s": 0.0}

    def prepare(self, system, state) -> None:
        """Set up for the tangent of ``state`` (default: factorise the assembled stiffness)."""
        self.factorize(system.stiffness(state))

    def factorize(self, K: sp.spmatrix) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def solve(self, r: np.ndarray, rtol: float | None = None) -> np.ndarray:  # pragma: no cover - interface
        """Solve K x = r; ``rtol`` is the accuracy the caller needs (iterative backends)."""
        raise NotImplementedError


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

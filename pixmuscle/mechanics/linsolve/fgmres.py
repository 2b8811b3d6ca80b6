"""GMRES with right preconditioning, flexible (Saad 1993) or not, restarted.

References
----------
Y. Saad, "A flexible inner-outer preconditioned GMRES algorithm", SIAM J. Sci. Comput. 14(2),
461–469, 1993.
Y. Saad, *Iterative Methods for Sparse Linear Systems*, 2nd ed., SIAM, 2003, §9.3.2 (right
preconditioned GMRES) and §9.4.1 (flexible GMRES).
"""

from __future__ import annotations

import numpy as np


def fgmres(A, b: np.ndarray, M, rtol: float, maxiter: int, restart: int = 60, x0: np.ndarray | None = None,
           check=None, flexible: bool = True):
    """Solve A x = b by restarted GMRES, preconditioned from the right by M.

    Flexible (default): the preconditioner may change from one iteration to the next (an inner
    iteration, a Krylov smoother): the preconditioned directions z_j = M v_j are kept, and the
    update is x = x0 + Z y with y minimising ‖b − A (x0 + Z y)‖ over the Krylov basis (Arnoldi
    with classical Gram–Schmidt applied twice, Givens rotations on the Hessenberg matrix). With
    ``flexible=False`` M must be one fixed linear operator (a multigrid cycle with fixed
    smoothing sweeps is): then Z = M V and the update is x = x0 + M (V y), so the directions
    z_j are not kept — half the memory of the basis, for one more application of M per restart
    (and per ``check``). In exact arithmetic both give the same iterates.

    Parameters
    ----------
    A, M : objects with ``@`` (operator and preconditioner), (n,) → (n,)
    b : (n,) float
    rtol : float
        Stop when ‖b − A x‖ ≤ rtol ‖b‖ (the least-squares residual of the Arnoldi relation,
        recomputed exactly at every restart).
    maxiter : int
        Total iterations (products with A) over all restarts.
    restart : int
        Basis vectors kept before a restart.
    x0 : (n,) float, optional
    check : callable, optional
        ``check(x) -> float | None``, called with the iterate whenever the residual meets the
        target: ``None`` accepts it, a number is a new relative target to go on to (a caller
        whose own stopping test is another norm of the residual). The iteration goes on in the
        same Krylov basis, so a tightened target costs no restart (a restart forgets the
        directions of the few outlying eigenvalues, which GMRES then has to find again).
    flexible : bool
        Keep the preconditioned directions (M may vary); ``False`` for a fixed M.

    Returns
    -------
    x : (n,) float
    iterations : int
    status : str
        ``"converged"``, ``"maxiter"``, ``"breakdown"`` (a zero Hessenberg pivot before convergence)
        or ``"stalled"`` (``check`` asked for a target no tighter than the one met).
    """
    b = np.asarray(b, float)
    x = np.zeros_like(b) if x0 is None else np.array(x0, float)
    bn = float(np.linalg.norm(b))
    if bn == 0.0:
        return np.zeros_like(b), 0, "converged"
    target = rtol * bn
    its = 0
    m = max(1, int(restart))
    while True:
        r = b - A @ x if its or x0 is not None else b.copy()
        beta = float(np.linalg.norm(r))
        while beta <= target and check is not None:
            more = check(x)
            if more is None:
                check = None
            elif float(more) * bn >= target:
                return x, its, "stalled"  # a check that does not tighten its target: no progress to make
            else:
                target = float(more) * bn
        if beta <= target:
            return x, its, "converged"
        if its >= maxiter:
            return x, its, "maxiter"
        V = np.empty((m + 1, b.size))
        Z = np.empty((m, b.size)) if flexible else None
        H = np.zeros((m + 1, m))
        cs = np.zeros(m)
        sn = np.zeros(m)
        g = np.zeros(m + 1)
        g[0] = beta
        V[0] = r / beta
        k = 0
        breakdown = False
        for j in range(m):
            if flexible:
                Z[j] = M @ V[j]
                w = A @ Z[j]
            else:
                w = A @ (M @ V[j])
            h = V[: j + 1] @ w
            w -= V[: j + 1].T @ h
            h2 = V[: j + 1] @ w  # second pass: orthogonality to round-off
            w -= V[: j + 1].T @ h2
            h += h2
            hn = float(np.linalg.norm(w))
            H[: j + 1, j] = h
            H[j + 1, j] = hn
            for i in range(j):  # previous rotations
                t = cs[i] * H[i, j] + sn[i] * H[i + 1, j]
                H[i + 1, j] = -sn[i] * H[i, j] + cs[i] * H[i + 1, j]
                H[i, j] = t
            rho = float(np.hypot(H[j, j], H[j + 1, j]))
            if rho == 0.0:
                breakdown = True
                break
            cs[j], sn[j] = H[j, j] / rho, H[j + 1, j] / rho
            H[j, j] = rho
            H[j + 1, j] = 0.0
            g[j + 1] = -sn[j] * g[j]
            g[j] = cs[j] * g[j]
            its += 1
            k = j + 1
            if abs(g[j + 1]) <= target and check is not None and hn != 0.0:
                more = check(x + _update(Z, V, M, _least_squares(H, g, k)))
                if more is None:
                    check = None  # accepted: stop here
                else:
                    target = min(target, float(more) * bn)
            if abs(g[j + 1]) <= target or its >= maxiter or hn == 0.0:
                break
            V[j + 1] = w / hn
        if k:
            x += _update(Z, V, M, _least_squares(H, g, k))
        if breakdown:
            r = b - A @ x
            return x, its, "converged" if float(np.linalg.norm(r)) <= target else "breakdown"


def _update(Z: np.ndarray | None, V: np.ndarray, M, y: np.ndarray) -> np.ndarray:
    """The update Z y of the first ``len(y)`` directions: kept (flexible), or M (V y)."""
    k = y.size
    return Z[:k].T @ y if Z is not None else M @ (V[:k].T @ y)


def _least_squares(H: np.ndarray, g: np.ndarray, k: int) -> np.ndarray:
    """Coefficients y of the first ``k`` basis directions: the triangular solve R y = g of the
    rotated Hessenberg matrix."""
    return np.linalg.solve(np.triu(H[:k, :k]), g[:k])

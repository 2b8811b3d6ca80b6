"""Complete monomial basis H(x - x_I) of the RK correction function (paper eqs. 1 and 4)."""

from __future__ import annotations

import itertools

import numpy as np


def exponents(dim, order):
    """Multi-indices α with |α| <= n, graded by degree (paper eq. 1).

    Parameters
    ----------
    dim : int
        Spatial dimension d.
    order : int
        Basis order n.

    Returns
    -------
    ndarray, shape (m, d), int
        Row i is α_i; row 0 is the constant, rows 1..d are the linear monomials x_1..x_d.
        m = (n + d)! / (n! d!).
    """
    rows = []
    for degree in range(order + 1):
        for combo in itertools.combinations_with_replacement(range(dim), degree):
            alpha = np.zeros(dim, dtype=int)
            for k in combo:
                alpha[k] += 1
            rows.append(alpha)
    return np.array(rows, dtype=int).reshape(-1, dim)


def monomials(r, alphas):
    """Evaluate H(r) = {r^α} for a batch of vectors.

    Parameters
    ----------
    r : ndarray, shape (n, d)
    alphas : ndarray, shape (m, d), from :func:`exponents`

    Returns
    -------
    ndarray, shape (n, m)
    """
    out = np.ones((r.shape[0], alphas.shape[0]))
    for i, alpha in enumerate(alphas):
        for k, power in enumerate(alpha):
            if power:
                out[:, i] *= r[:, k] ** power
    return out


def derivative_matrices(alphas):
    """Constant matrices G_k with ∂H(r)/∂r_k = G_k H(r).

    Differentiating a monomial of the complete basis gives a multiple of a lower monomial,
    which is again in the basis, so the derivative is an exact linear map.

    Returns
    -------
    ndarray, shape (d, m, m)
    """
    m, dim = alphas.shape
    index = {tuple(a): i for i, a in enumerate(alphas)}
    g = np.zeros((dim, m, m))
    for k in range(dim):
        for i, alpha in enumerate(alphas):
            if alpha[k] > 0:
                lower = alpha.copy()
                lower[k] -= 1
                g[k, i, index[tuple(lower)]] = alpha[k]
    return g

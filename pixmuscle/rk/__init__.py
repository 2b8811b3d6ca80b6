"""Reproducing-kernel (RK) approximation: kernels, neighbour search, shape functions (paper §2).

Main entry point: :func:`shape_functions` (paper eq. 7) returning sparse Ψ (P, N) and, on
request, its exact gradients; :func:`rk_evaluate` gives the approximation Σ Ψ_J d_J (eq. 2) at any
points. :func:`kernel` evaluates a 1-D kernel and its derivative.
"""

from pixmuscle.rk.coverage import covering_supports
from pixmuscle.rk.evaluate import rk_evaluate
from pixmuscle.rk.kernels import KERNELS, SUPPORT_SHAPES, kernel
from pixmuscle.rk.shape import SingularMomentError, shape_functions

__all__ = ["KERNELS", "SUPPORT_SHAPES", "SingularMomentError", "covering_supports", "kernel", "rk_evaluate", "shape_functions"]

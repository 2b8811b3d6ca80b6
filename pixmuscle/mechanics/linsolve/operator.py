"""What a linear-solver backend may use of the discrete system: :class:`SystemOperator`.

A backend sees the problem only through these methods (and the ``state`` objects they return and
take, which it passes back without reading them); it reads no attribute of the system. The serial
:class:`~pixmuscle.mechanics.system.MechanicalSystem` implements them for a system that owns every
row. The interface is phrased in *owned rows* — a set of node indices whose rows of the tangent a
process assembles and applies — so that a distributed system (owned rows plus a halo of about one
support radius) can implement the same methods for its own rows.

Units: displacements cm, forces N, the tangent N/cm, pressures N/cm². Vectors are node-major
(dof 3I + i of node I, component i), N nodes, N_p pressure patches.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np
import scipy.sparse as sp


@runtime_checkable
class SystemOperator(Protocol):
    """The narrow interface between the discrete system and the linear solvers.

    Attributes
    ----------
    n_nodes : int
        N, the nodes; the displacement unknowns are 3N (:attr:`n_dofs`).
    """

    n_nodes: int

    @property
    def n_dofs(self) -> int:
        """3N, the unknowns of the displacement block."""

    def evaluate(self, d: np.ndarray, t: float, alpha: float, pressure: np.ndarray | None = None):
        """The state at coefficients ``d`` (N, 3) cm, load factor ``t``, activation ``alpha`` (and the
        carried patch ``pressure`` (N_p,) N/cm², or None): its residual ``r`` (N, 3) N and its
        tangent. A backend calls it only to rebuild a kept preconditioner at a recorded state."""

    def tangent_operator(self, state):
        """The consistent tangent K at ``state`` as a matrix-free operator (3N × 3N, N/cm): ``K @ v``
        for v (3N,), exact and never assembled."""

    def stiffness(self, state, pressure_free: bool = False) -> sp.spmatrix:
        """K assembled (3N × 3N sparse, N/cm), for direct factorisation; ``pressure_free``: the
        displacement block K_d of the mixed form."""

    def preconditioner_matrix(self, state, reach: int = 2, volumetric: str = "nodal") -> sp.spmatrix:
        """The positive definite stand-in of the tangent (3N × 3N BSR, N/cm) that multigrid is built
        from: node pairs at most ``reach`` voxels apart, each node's tangent replaced by a positive
        one; ``volumetric="held"``: the stand-in of K_d."""

    def near_null_space(self, nodes: np.ndarray | None = None) -> np.ndarray:
        """Rigid-body modes of ``nodes`` (default all), (3n, 6): the near-null space for multigrid."""

    def owned_rows(self, owned: np.ndarray):
        """The rows of the tangent of the nodes ``owned`` (n,) int: an object whose
        ``rows(state, pressure_free=False)`` gives them as CSR (3n × 3N, model dof columns, N/cm) and
        whose ``cells`` (n_c,) int are the integration cells they need (owned plus halo)."""

    def pressure_space(self):
        """The patch pressures as unknowns of the mixed form
        (:class:`~pixmuscle.mechanics.pressure.PressureSpace`: free patches, V_p, K̄_p, μ_p, the
        scale w, patch-grid boxes); None without a projected volumetric energy (no mixed form)."""

    def displacement_operator(self, state, tangent=None):
        """The displacement block K_d of the mixed form, matrix-free (3N × 3N, N/cm), with
        ``apply(v, extra=None)`` (``extra(grad) -> (N, 3, 3)`` adds a nodal stress to the product);
        ``tangent``: the :meth:`tangent_operator` of the same state, whose moduli it may share."""

    def patch_divergence(self, state, patches: np.ndarray):
        """G of ``patches`` (n,) int at ``state`` (n × 3N, 1/cm), matrix-free
        (:class:`~pixmuscle.mechanics.pressure.PatchDivergence`: ``G @ x``, ``G.T(q)``,
        ``G.sparse()``, ``G.of_gradient(grad)``, ``G.stress(q)``)."""

    def stiff_regions(self) -> list[np.ndarray]:
        """Node sets (sorted (n_i,) int, may overlap) of the stiff rank-one couplings of the
        boundary conditions and held single-node patches, to be solved exactly after a V-cycle."""

    def region_solves(self, regions: list[np.ndarray], ijk: np.ndarray, single: bool = False,
                      coupling: str = "auto"):
        """Solves of K_d on ``regions``: an object with ``update(state)`` (factorise),
        ``correct(r, z)`` (the multiplicative correction z ← z + R_i K_i⁻¹ R_iᵀ (r − K_d z)),
        ``release()`` and ``n_nodes``; ``ijk`` (N, 3) int orders the factorisations; ``single``:
        single-precision PARDISO factors, each solve refined in double precision; ``coupling``:
        K_i is each displacement component's diagonal block (``components``), the whole block
        (``full``), or the whole block only where a held single-node patch couples the
        components (``auto``)."""

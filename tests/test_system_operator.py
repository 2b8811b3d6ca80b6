"""The seam between the system and the linear solvers (pixmuscle.mechanics.linsolve.operator).

Each backend runs on a proxy of the system that answers only the methods of
:class:`SystemOperator`; its update must equal, to the last bit, the update it gives on the system
itself. So a backend that reads anything else of the system fails here (AttributeError).
"""

import numpy as np
import pytest
from test_mixed_solver import _system

from pixmuscle.mechanics.linsolve import SystemOperator, make_solver, petsc
from pixmuscle.mechanics.system import MechanicalSystem

#: the names of the interface
NAMES = {n for n in vars(SystemOperator) if not n.startswith("_")} | {"n_nodes"}


class OnlyInterface:
    """The system as a backend may see it: the interface's methods, nothing else."""

    def __init__(self, system):
        self._system = system

    def __getattr__(self, name):
        if name not in NAMES:
            raise AttributeError(f"a backend read {name!r}, which is not in SystemOperator")
        return getattr(self._system, name)


def test_the_system_implements_the_interface():
    assert NAMES >= {"tangent_operator", "owned_rows", "pressure_space", "patch_divergence", "near_null_space"}
    for name in NAMES:
        assert hasattr(MechanicalSystem, name) or name == "n_nodes", name
    _, system = _system()
    assert isinstance(system, SystemOperator) and system.n_dofs == 3 * system.n_nodes


@pytest.mark.parametrize("backend", ["direct", "cg_amg", "mixed_amg", "petsc", "petsc_mixed"])
def test_every_backend_uses_only_the_interface(backend):
    if backend.startswith("petsc") and not petsc.available():
        pytest.skip("petsc4py not importable")
    model, system = _system(muscle={"K": 5000.0}, connective_tissue={"K": 50000.0})
    state = system.evaluate(np.zeros((model.n_nodes, 3)), 0.5, 0.6)
    # the condensed tangent of this nearly incompressible body defeats GAMG (docs/petsc.md): LU instead
    kw = {"petsc_options": {"pc_type": "lu"}} if backend == "petsc" else {}
    out = []
    for seen in (system, OnlyInterface(system)):
        solver = make_solver(backend, model.X, ijk=model.ijk, rtol=1e-10, **kw)
        solver.prepare(seen, state)
        x = solver.solve(state.r.ravel(), rtol=1e-8)
        rm = system.mixed_residual(state)
        mixed = solver.solve_mixed(rm[0].ravel(), rm[1], rtol=1e-8) if hasattr(solver, "solve_mixed") else (x, None)
        out.append((x, mixed[0]))
    assert np.array_equal(out[0][0], out[1][0]) and np.array_equal(out[0][1], out[1][1])

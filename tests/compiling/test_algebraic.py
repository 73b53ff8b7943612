"""The algebraic variables solved from a method's states (daemodel/compiling/algebraic.py)."""

import dataclasses

import numpy as np

import daemodel as dm
from daemodel.compiling import algebraic
from daemodel.compiling.initial_states import constraint_checks
from daemodel.problems.families import pendulum_chain


def test_affine_determining_equations_take_one_whole_newton_step(monkeypatch):
    """A chain of 20 pendulums (index 3, solved at index 2: its multipliers' determining equations are
    affine in them): from radau's collocation values, the 21 outputs of an adaptive solve settle in one
    whole Newton step, the equations evaluated twice.  Before, the step was halved three times where the
    start was at the rounding level of the residual (5 evaluations, 16 of the solve's 64 ms)."""
    sol = dm.solve(pendulum_chain(20).compile(), (0.0, 1.0), rtol=1e-6, atol=1e-6)
    compiled = sol.compiled
    checks, calls = constraint_checks(compiled), []

    def H(*arguments):
        calls.append(1)
        return checks.H(*arguments)

    monkeypatch.setattr(algebraic, "constraint_checks", lambda _: dataclasses.replace(checks, H=H))
    Y = np.stack([sol[name] for name in compiled.state_names], axis=-1)[None]
    Z = np.stack([sol[name] for name in compiled.algebraic_names], axis=-1)[None]
    P = np.asarray(compiled.parameter_values, dtype=float)[None]
    found = algebraic.algebraic_from_states(compiled, sol.t, Y, Z, P)
    assert found.converged.all()
    assert len(calls) == 2
    np.testing.assert_allclose(found.z, Z, rtol=1e-12, atol=1e-12)  # (the returned values: solved so already)

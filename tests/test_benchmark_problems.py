"""Standard DAE benchmark problems with published reference solutions (Test Set for IVP Solvers).

Each problem's reference values at its end time come from the test set, not from daemodel; the
tests check that the problem is transcribed right (scipy's tight reference reproduces them) and
measure how many correct digits each method delivers at growing accuracy.
"""

import numpy as np
import pytest

import daemodel as dm
from daemodel.problems import AKZO_NOBEL


def digits(sol, problem) -> float:
    """Correct significant digits at the end time: -log10 of the worst relative error."""
    worst = max(abs(sol[name][-1] - value) / abs(value) for name, value in problem.reference.items())
    return float(-np.log10(max(worst, 1e-17)))


@pytest.fixture(scope="module")
def akzo():
    return AKZO_NOBEL.model().compile()


def test_akzo_nobel_is_transcribed_as_published(akzo):
    """Index 1 (the fast equilibrium y6 = Ks y1 y4), y6(0) from it, and scipy at 1e-12 meets the
    test set's reference at t = 180 to 12 digits: the equations and constants are the test set's."""
    assert akzo.index == 1 and akzo.z0[0] == pytest.approx(115.83 * 0.444 * 0.007, rel=1e-15)
    ref = dm.solve(akzo, AKZO_NOBEL.t_span, method="reference", rtol=1e-12, atol=1e-14, t_eval=[0.0, 180.0])
    assert digits(ref, AKZO_NOBEL) > 12


@pytest.mark.parametrize(("rtol", "at_least"), [(1e-6, 6), (1e-8, 8), (1e-10, 11)])
def test_akzo_nobel_adaptive_radau_digits(akzo, rtol, at_least):
    sol = dm.solve(akzo, AKZO_NOBEL.t_span, rtol=rtol, atol=rtol * 1e-4, t_eval=[0.0, 180.0])
    print(
        f"akzo-nobel, radau s = {sol.stats['stages']} at rtol {rtol:g}: {digits(sol, AKZO_NOBEL):.1f} digits, "
        f"{sol.stats['steps']} steps"
    )
    assert digits(sol, AKZO_NOBEL) >= at_least


def test_akzo_nobel_idas_digits(akzo):
    sol = dm.solve(akzo, AKZO_NOBEL.t_span, method="casadi-idas", rtol=1e-10, atol=1e-14, t_eval=[0.0, 180.0])
    assert digits(sol, AKZO_NOBEL) >= 9

"""The problem library: the bouncing ball's closed form against radau and against its own formulas."""

import numpy as np
import pytest

import daemodel as dm
from daemodel.problems import BALL_E, BALL_G, BOUNCING_BALL, PROBLEMS


def test_the_bouncing_balls_closed_form_and_its_impacts():
    exact = BOUNCING_BALL.exact_solution()
    floor = exact.events["floor"]
    t1 = np.sqrt(2 / BALL_G)  # the first impact; each flight after lasts 2 u_k / g, u_k = e^k sqrt(2 g)
    speeds = BALL_E ** np.arange(1, 13) * np.sqrt(2 * BALL_G)
    times = np.concatenate([[t1], t1 + np.cumsum(2 * speeds[:-1] / BALL_G)])
    np.testing.assert_allclose(floor["t"][0], times, rtol=1e-15)
    # (sympy distributes g over (t - t_k): rounding of g t, 1e-14)
    np.testing.assert_allclose(floor["before"]["v"][0], -speeds / BALL_E, rtol=0, atol=2e-14)
    np.testing.assert_allclose(floor["after"]["v"][0], speeds, rtol=0, atol=2e-14)
    np.testing.assert_allclose(floor["before"]["h"][0], 0.0, atol=2e-15)
    np.testing.assert_allclose(floor["after"]["h"][0], 0.0, atol=2e-15)
    # at an impact the values after it (as a Solution holds them), just before it the free fall's
    at = exact(np.array([0.0, 0.3, times[0], times[1]]))
    assert at["h"][:2] == pytest.approx([1.0, 1 - BALL_G / 2 * 0.09], abs=1e-15)
    assert at["v"][2:] == pytest.approx(speeds[:2], abs=2e-14)
    assert np.sum(times < BOUNCING_BALL.t_span[1]) == 6  # the span ends before the Zeno point 4.06
    assert PROBLEMS["bouncing-ball"] is BOUNCING_BALL


def test_the_bouncing_ball_against_radau_at_a_tight_tolerance():
    exact = BOUNCING_BALL.exact_solution()
    sol = dm.solve(BOUNCING_BALL.model(), BOUNCING_BALL.t_span, method="radau", rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(sol.events["floor"]["t"][0], exact.events["floor"]["t"][0, :6], rtol=0, atol=2e-12)
    for side in ("before", "after"):
        for name in ("h", "v"):
            np.testing.assert_allclose(
                sol.events["floor"][side][name][0], exact.events["floor"][side][name][0, :6], rtol=0, atol=5e-11
            )
    # away from the impacts, the values at every output time
    keep = np.min(np.abs(sol.t[:, None] - exact.events["floor"]["t"][0, :6]), axis=1) > 1e-9
    values = exact(sol.t[keep])
    for name in ("h", "v"):
        np.testing.assert_allclose(sol[name][keep], values[name], rtol=0, atol=5e-11)

"""casadi-idas's start from consistent values (backends/casadi/plumbing.consistent_start): IDACalcIC's own step
a share of IDAS's first one, so that it leaves nearly consistent algebraic values where they are."""

import dataclasses

import numpy as np
import pytest
from daemodel.backends.casadi import plumbing

import daemodel as dm
from daemodel.compiling.switches import lock_branches
from daemodel.problems import WHEELSET

# The wheelset where casadi-idas's event search reached t = 0.81155608891 at rtol = atol = 1e-6, 1e-8 past a
# crossing of its creep saturation (a look-ahead on the locked branch): its states and algebraic values, consistent
# to |g| = 2.6e-12.  The trial solve over [T, T1] that locates the next crossing raised ConvergenceError there
# (IDA_ERR_FAIL, the error test failed at every step down to 7.2e-17): IDACalcIC, its step 0.001 of casadi's
# first_time (the last output, 2.2e-5 away), had moved TYR by 13 of its tolerances off its constraint.
T, T1 = 0.8115560889136104, 0.8115781121447475
Y = [
    -0.004160263378508821, 2.9363219001865505e-06, 9.060160520809165e-05, -0.009413904758934371,
    -0.0007367584099011857, -0.2789740171683475, 0.00043162030518329483, -0.0016198300283115233,
    0.399193503313408, -0.04940415894270352, -0.1140270443351618, 0.0002397720017557609, 0.15488465587070618,
    -0.000253643956563191, -0.14632800460004539,
]  # fmt: skip
Z = [
    -0.010633161630523852, 0.2863285107468595, 0.01029123273048152, 0.2874203606712894, -0.005231514052616074,
    -0.010572780708842445, 52.3321065760535, 105.76617955098278, 6.253033140947233, 2.359445670556237,
    -12.69106033055181, -0.14942131264881994,
]  # fmt: skip


def test_idacalcic_s_step_is_a_share_of_idas_s_first_step():
    # (casadi's first_time: IDAS's hic = 0.001 first_time)
    share = plumbing.IC_STEP_SHARE
    assert plumbing.consistent_start(0.5, 1e-9) == {"calc_ic": True, "first_time": pytest.approx(1e3 * share * 1e-9)}
    # (no step0: IDAS's own first guess, 0.001 of the first output's distance)
    assert plumbing.consistent_start(0.5, None) == {"calc_ic": True, "first_time": pytest.approx(share * 0.5)}


def test_the_wheelset_past_a_creep_saturation_starts_from_its_consistent_values():
    compiled = WHEELSET.model().compile()
    P = np.array([list(compiled.parameter_values)], dtype=float)
    locked = lock_branches(compiled, T, np.array(Y), np.array(Z), P[0])  # (the branch past the crossing)
    model = dataclasses.replace(locked, t0=T, y0=np.array(Y), z0=np.array(Z))
    sol = dm.solve(model, (T, T1), method="casadi-idas", rtol=1e-6, atol=1e-6)
    ref = dm.solve(model, (T, T1), method="radau", rtol=1e-9, atol=1e-9, jit=False)
    assert sol.status == "success" and ref.status == "success"
    # (within a few of IDAS's tolerances of radau's at 1e-9: the states 0.014 of them, TYR 4.2)
    for name in (*compiled.state_names, *compiled.algebraic_names):
        off = abs(sol[name][-1] - ref[name][-1]) / (1e-6 + 1e-6 * abs(ref[name][-1]))
        assert off < 10.0, (name, off)


def test_idacalcic_is_never_given_a_step_of_zero():
    # (a first output at t0: IDACalcIC's step 0, on which casadi's call never returned)
    with pytest.raises(
        dm.errors.TimeSpanError, match=r"casadi-idas: its first output lies at its start .*step would be 0\.0"
    ):
        plumbing.consistent_start(0.0, None)


def test_a_span_of_a_few_float64_spacings_at_a_large_t_is_solved():
    """A trial solve of the ball's first impact at t0 = 1e13 (a fall over 0.0215, 11 float64 spacings of t): the
    default outputs of linspace rounded onto t0 and onto one another, and IDAS, its first output at t0, never
    returned (300 s).  Now the outputs are float64's distinct times, and the fall is exact on them."""
    t0, span, h0, v0 = 1e13 + 0.4296875, 0.021484375, 0.09438324, -4.21523437
    m = dm.Model("fall")
    m.states("h v")
    m.ode("h", "v")
    m.ode("v", "-9.81")
    m.initial(t=t0, h=h0, v=v0)
    sol = dm.solve(m, (t0, t0 + span), method="casadi-idas", rtol=1e-10, atol=1e-10)
    s = sol.t - t0
    assert sol.status == "success" and sol.t[0] == t0 and sol.t[-1] == t0 + span
    assert np.all(np.diff(sol.t) > 0) and len(sol.t) == 12  # (t0 and the 11 float64 times after it)
    np.testing.assert_allclose(sol["h"], h0 + v0 * s - 0.5 * 9.81 * s**2, rtol=0, atol=1e-9)

"""Radau never returns a result it cannot vouch for, and every loop of it ends in a named error.

A fixed step checks its embedded local error estimate against LOCAL_ERROR_BOUND; adaptive mode
counts every attempt against max_steps; grids, tolerances, devices and output times are checked
before anything is allocated or integrated.
"""

import functools
import itertools
import re
import tracemalloc

import numpy as np
import pytest
import sympy as sp
from daemodel.backends import radau
from daemodel.backends.grids import MAX_GRID_POINTS, fixed_grid
from scipy.integrate import solve_ivp

import daemodel as dm
from daemodel import errors as E
from daemodel.problems import HESSENBERG, PENDULUM

# radau's default on casadi's virtual machine, but in the tests marked machine_code (tests/conftest.py)
pytestmark = pytest.mark.virtual_machine


@pytest.fixture(scope="module")
def pendulum():
    return PENDULUM.model().compile()


@pytest.fixture(scope="module")
def pole():
    """``x' = -1, y' = 1/x``, x(0) = 1: y = -log(1 - t) ends at t = 1."""
    m = dm.Model("pole")
    x, y = m.states("x y")
    m.ode(x, -1 + 0 * y)
    m.ode(y, 1 / x)
    m.initial(x=1.0, y=0.0)
    return m.compile()


@pytest.fixture(scope="module")
def switch():
    """``x' = -sign(x)``, x(0) = 0.5: at t = 0.5 the right-hand side switches."""
    m = dm.Model("switch")
    (x,) = m.states("x")
    m.ode(x, -sp.sign(x))
    m.initial(x=0.5)
    return m.compile()


# ---- fixed step: the local error estimate -------------------------------------------------


# (stages, h) that returned finite garbage for y(2) before the estimate was checked (y(2) = 1.005 at (3, 0.03))
@pytest.mark.parametrize(("stages", "h"), [(1, 0.03), (2, 0.13), (3, 0.03), (3, 0.3), (4, 0.07), (4, 0.13)])
def test_a_step_across_a_pole_raises_local_error_bound(pole, stages, h):
    with pytest.raises(
        E.LocalErrorBoundError,
        match=rf"radau: step \d+ from t = 0\.9\d* with h = {h:g}: the local error estimate of 'y' \(sample 0\) "
        r"is .* times the solution's size 1 \+ max\|y\| so far, beyond LOCAL_ERROR_BOUND = 0\.1: .*"
        r"take a smaller h, or the adaptive mode \(rtol=\.\.\.\)",
    ):
        dm.solve(pole, (0.0, 2.0), stages=stages, h=h)


def test_the_bound_names_the_sample_of_a_batch(pole):
    # x(0) = 3, 1, 5: only sample 1 reaches its pole (at t = 1) within t_span
    with pytest.raises(E.LocalErrorBoundError, match=r"step 34 from t = 0\.99 .*'y' \(sample 1\)"):
        dm.solve(pole, (0.0, 2.0), stages=3, h=0.03, y0={"x": [3.0, 1.0, 5.0], "y": [0.0, 0.0, 0.0]})


def test_before_the_pole_the_solution_is_returned_with_its_estimate(pole):
    sol = dm.solve(pole, (0.0, 0.9), stages=3, h=0.03)
    assert sol.stats["mode"] == "fixed"
    assert 0 < sol.stats["max_local_error_estimate"] < radau.LOCAL_ERROR_BOUND
    np.testing.assert_allclose(sol["y"][-1], -np.log(0.1), rtol=1e-5)


@pytest.mark.parametrize("s", [1, 2, 3])
def test_smooth_problems_report_a_small_estimate_that_shrinks_with_h(pendulum, s):
    estimates = []
    for h in (0.125, 0.0625, 0.03125):
        sol = dm.solve(pendulum, (0.0, 1.0), stages=s, h=h)
        estimates.append(sol.stats["max_local_error_estimate"])
    hessenberg = dm.solve(HESSENBERG.model().compile(), (0.0, 1.0), stages=s, h=0.05)
    print(f"pendulum s={s}: estimates {estimates}; hessenberg h=0.05: {hessenberg.stats['max_local_error_estimate']}")
    assert 0 < estimates[-1] < estimates[0] < 0.05
    # the estimate is O(h^(s+1)): halving h shrinks it by at least 2^s
    assert all(a / b > 2**s for a, b in itertools.pairwise(estimates))
    assert 0 < hessenberg.stats["max_local_error_estimate"] < 0.05


def test_stiff_decay_and_a_batch_do_not_trip_the_bound(pendulum):
    m = dm.Model("decay")
    (y,) = m.states("y")
    m.ode(y, -1e6 * y)  # the first step's estimate needs the second stiff filter
    m.initial(y=1.0)
    sol = dm.solve(m, (0.0, 1.0), stages=3, h=0.1)
    assert sol.stats["max_local_error_estimate"] < 1e-3 and abs(sol["y"][-1]) < 1e-12
    angles = np.linspace(0.2, 2.8, 50)
    y0 = {"y1": np.sin(angles), "y2": -np.cos(angles), "y3": 0 * angles, "y4": 0 * angles}
    batch = dm.solve(pendulum, (0.0, 2.0), stages=3, h=0.05, y0=y0)
    assert 0 < batch.stats["max_local_error_estimate"] < 1e-3


def test_non_finite_values_name_the_equation_stage_and_time():
    m = dm.Model("root")
    x, y = m.states("x y")
    m.ode(x, -1 + 0 * y)
    m.ode(y, sp.sqrt(x))  # NaN once x < 0
    m.initial(x=0.05, y=0.0)
    with pytest.raises(
        E.ConvergenceError,
        match=r"Newton failed in step 1 from t = 0 with h = 0\.1 \(non-finite values: the right-hand side of y' "
        r"at stage 2 \(t = 0\.06\d*\); damped Newton: the Newton matrix at iterate 2 is singular \(the Jacobian "
        r"of f and g is not finite there\), sample 0\)",
    ):
        dm.solve(m, (0.0, 1.0), stages=3, h=0.1)
    m = dm.Model("log")
    (x,) = m.states("x")
    (z,) = m.algebraics("z")
    m.ode(x, -1 + 0 * z)
    m.constraint(z - sp.log(x), name="logx")
    m.initial(x=0.05)
    with pytest.raises(E.ConvergenceError, match=r"non-finite values: constraint 'logx' at stage 2 \(t = 0\.06"):
        dm.solve(m, (0.0, 1.0), stages=3, h=0.1)


# ---- adaptive: every attempt counts ----------------------------------------------------------


@pytest.mark.parametrize("options", [{"rtol": 1e-3, "max_steps": 300}, {"max_steps": 300}])
def test_a_chattering_switch_slides(switch, options):
    """The switch is located (daemodel.solving.events) and both sides push onto it: the solution slides along
    x = 0 (Filippov) (before switches were located, the step size control chattered into max_steps; one Newton
    iteration "converged" on the last step's contraction rate and returned x(0.9) = -0.12; then it was refused)."""
    sol = dm.solve(switch, (0.0, 1.0), t_eval=np.linspace(0.0, 1.0, 11), **options)
    assert sol.status == "success"
    np.testing.assert_allclose(sol["x"], np.maximum(0.5 - sol.t, 0.0), atol=1e-12)


def test_adaptive_steps_meet_the_tolerance(pendulum):
    times = np.linspace(0.0, 4.0, 9)
    sol = dm.solve(pendulum, (0.0, 4.0), rtol=1e-6, t_eval=times)
    ref = dm.solve(pendulum, (0.0, 4.0), method="reference", t_eval=times)
    errors = sol.errors(ref)
    print(f"pendulum on [0, 4], rtol = 1e-6: {sol.stats['steps']} steps, errors {errors}")
    # without checking one-iteration Newton convergence: 1.4e-5 (y4) in 112 steps, 24 rejected
    assert max(errors[name]["max"] for name in pendulum.state_names) < 1e-6


def test_endless_span_raises_step_limit(pendulum, switch):
    with pytest.raises(
        E.StepLimitError,
        match=r"max_steps = 200 (reached|cannot suffice .* stopped early) at t = .* before t1 = 1e\+300, .*the steps "
        r"are accepted, but .* the rest of t_span needs about .* more attempts: t_span is too long for max_steps",
    ):
        dm.solve(pendulum, (0.0, 1e300), max_steps=200)
    # the default budget is not spent: the projection stops after the first windows of steady steps
    with pytest.raises(
        E.StepLimitError, match=r"max_steps = 100000 cannot suffice \(.*, 99[5-9]00 left\), stopped early"
    ):
        dm.solve(pendulum, (0.0, 1e300))
    with pytest.raises(E.StepLimitError, match=r"max_steps = 200 (reached|cannot suffice).* before t1 = 1e\+300"):
        dm.solve(switch, (0.0, 1e300), max_steps=200)


def test_a_held_step_is_judged_by_the_growth_its_error_estimate_asks_for():
    """radau holds h (and its factors) while the step its estimate asks for is within the keep band above it:
    a held h whose estimate falls (a stiff transient decaying) projects at the asked growth, and one whose
    estimate stays (an endless span at a steady pace) still stops after HOPELESS_WINDOWS."""
    from daemodel.backends.progress import HOPELESS_WINDOWS, PROGRESS_WINDOW, ProgressWatch

    def windows_until_stop(err_ratio, h_rounding=0.0, h_shrink=0.0):
        h, err, watch = 2.5e-6, 0.4, ProgressWatch(0.0, 2.5e-6)
        for window in range(1, 20):
            count = window * PROGRESS_WINDOW
            held = h * (1 + h_rounding * (-1) ** window) * (1 - h_shrink) ** window
            t, err = count * h, err * err_ratio
            if watch.hopeless(count, t, held, 5.0, 100_000, accepted=count, err=err, exponent=1 / 3) is not None:
                return window
        return None

    assert windows_until_stop(1.0) == HOPELESS_WINDOWS  # (the first window has no estimate to compare)
    assert windows_until_stop(1.01) == HOPELESS_WINDOWS
    assert windows_until_stop(0.78) is None  # (the transient above: 0.40 -> 0.27 a window, growth 1.14)
    assert windows_until_stop(0.78, h_rounding=1e-13) is None  # (t's rounding moves a held h)
    assert windows_until_stop(0.78, h_shrink=1e-3) == HOPELESS_WINDOWS  # (h moved: h's own growth)


def test_a_first_step_rejected_at_once_does_not_make_an_endless_span_a_dip():
    """x' = v, v' = -x over (0, 1e300) from h0 = 1e3: the guess, rejected at once, was the progress watch's largest
    step, so every later window (h ~ 0.05) looked like a stiff layer's dip and took DIP_SHARE of the budget: 25,100
    attempts where h0 = 100 or none stops after ~300."""
    m = dm.Model("endless_oscillator")
    m.states("x v")
    m.ode("x", "v")
    m.ode("v", "-x")
    m.initial(x=1.0, v=0.0)
    with pytest.raises(E.StepLimitError, match=r"cannot suffice \(.*, 99[5-9]00 left\), stopped early"):
        dm.solve(m, (0.0, 1e300), rtol=1e-6, atol=1e-6, h0=1e3)


def test_a_stiff_transient_held_at_the_start_is_not_taken_for_an_endless_span():
    """a' = -b - a/10, b' = a - b/10, c' = -1000 c + a from c = 0, two stages at rtol 1e-9: the fast mode's
    decay holds h = 2.53e-6 for 260 attempts, and the watch projected 1.97e6 more at that pace and raised
    StepLimitError after 200 attempts where the solve takes 4,701 (max_steps = 10**7)."""
    m = dm.Model("transient")
    m.states("a b c")
    m.ode("a", "-b - 0.1*a")
    m.ode("b", "a - 0.1*b")
    m.ode("c", "-1000*c + a")
    m.initial(a=1.0, b=0.0, c=0.0)
    sol = dm.solve(m, (0.0, 5.0), method="radau", stages=2, rtol=1e-9, atol=1e-12)
    assert sol.status == "success" and sol.stats["attempts"] < 10_000
    assert np.max(np.abs(sol["a"] - np.exp(-0.1 * sol.t) * np.cos(sol.t))) < 1e-8


@pytest.mark.parametrize("eps", [1e-6, 1e-8])
def test_a_stiff_layer_is_not_taken_for_an_endless_span(eps):
    """Van der Pol's fast jumps take ~300 accepted attempts at h ~ 4e-8 (eps = 1e-6): the progress watch
    projected past the budget at that pace and stopped at t = 0.807 a solve that finishes in 866
    attempts.  A dip three orders below the steps taken before, mostly accepted, gets more windows."""
    m = dm.Model("vdp")
    m.states("y1 y2")
    m.ode("y1", "y2")
    m.ode("y2", f"((1 - y1**2)*y2 - y1)/{eps}")
    m.initial(y1=2.0, y2=-0.66)
    t_eval = np.linspace(0.0, 2.0, 5)
    sol = dm.solve(m, (0.0, 2.0), stages=3, rtol=1e-6, atol=1e-6, t_eval=t_eval)
    assert sol.status == "success"

    def f(t, y):
        return [y[1], ((1 - y[0] ** 2) * y[1] - y[0]) / eps]

    def jac(t, y):
        return [[0.0, 1.0], [(-2 * y[0] * y[1] - 1) / eps, (1 - y[0] ** 2) / eps]]

    ref = solve_ivp(f, (0.0, 2.0), [2.0, -0.66], method="Radau", rtol=1e-11, atol=1e-11, jac=jac, t_eval=t_eval)
    assert np.abs(sol["y1"] - ref.y[0]).max() < 1e-5


@pytest.mark.parametrize(("eps", "t1", "rtol"), [(1e-6, 11.0, 1e-6), (1e-10, 2.0, 1e-8)])
def test_a_stiff_layer_longer_than_ten_windows_is_not_taken_for_an_endless_span(eps, t1, rtol):
    """Van der Pol's jumps at three stages take more windows than the dip's first allowance (10) at a tighter
    rtol or over more jumps: over [0, 11] at eps = 1e-6, rtol 1e-6 (5,505 attempts to finish) and over
    [0, 2] at eps = 1e-10, rtol 1e-8 (4,289) the watch stopped at t = 8.88 and 0.807 with a StepLimitError
    projecting 5.6e7 and 8e11 more attempts (the second even at max_steps = 10**7).  A dip may now take a
    quarter of max_steps."""
    m = dm.Model("vdp")
    m.states("y1 y2")
    m.ode("y1", "y2")
    m.ode("y2", f"((1 - y1**2)*y2 - y1)/{eps}")
    m.initial(y1=2.0, y2=-0.66)
    t_eval = np.linspace(0.0, t1, 5)
    sol = dm.solve(m, (0.0, t1), stages=3, rtol=rtol, atol=rtol, t_eval=t_eval)
    assert sol.status == "success"

    def f(t, y):
        return [y[1], ((1 - y[0] ** 2) * y[1] - y[0]) / eps]

    def jac(t, y):
        return [[0.0, 1.0], [(-2 * y[0] * y[1] - 1) / eps, (1 - y[0] ** 2) / eps]]

    # (1e-10 from scipy at 1e-11, in half the time)
    ref = solve_ivp(f, (0.0, t1), [2.0, -0.66], method="Radau", rtol=1e-9, atol=1e-9, jac=jac, t_eval=t_eval)
    print(f"eps = {eps}: {sol.stats['attempts']} attempts, y1 error {np.abs(sol['y1'] - ref.y[0]).max():.2g}")
    assert np.abs(sol["y1"] - ref.y[0]).max() < 10 * rtol


def test_chattering_in_a_dip_still_stops_after_two_windows():
    """The dip's extra windows are for accepted steps: mostly rejected attempts at a step far below the
    earlier ones (chattering at a switch) stop after HOPELESS_WINDOWS, as before.  Accepted ones stop once
    the dip has taken DIP_SHARE of the budget, at least DIP_WINDOWS windows."""
    from daemodel.backends.progress import DIP_SHARE, DIP_WINDOWS, HOPELESS_WINDOWS, PROGRESS_WINDOW, ProgressWatch

    def windows_until_stop(accepted_per_window, budget=100_000):
        watch, t, count, accepted = ProgressWatch(0.0, 1e-2), 0.0, 0, 0
        t += 100 * 1e-2  # one window of large steps, then steps of 1e-9
        count, accepted = PROGRESS_WINDOW, PROGRESS_WINDOW
        assert watch.hopeless(count, t, 1e-2, 10.0, budget, accepted=accepted) is None
        for window in range(1, budget // PROGRESS_WINDOW):
            t += accepted_per_window * 1e-9
            count, accepted = count + PROGRESS_WINDOW, accepted + accepted_per_window
            if watch.hopeless(count, t, 1e-9, 10.0, budget, accepted=accepted) is not None:
                return window

    # (+ 1: the window in which h falls by more than COLLAPSE_FACTOR is left to the step-size failure)
    assert windows_until_stop(95) == DIP_SHARE * 100_000 / PROGRESS_WINDOW + 1 == 251
    assert windows_until_stop(95, budget=3_000) == DIP_WINDOWS + 1
    assert windows_until_stop(10) == HOPELESS_WINDOWS + 1


def test_max_steps_counts_every_attempt_and_has_per_mode_defaults(pendulum):
    sol = dm.solve(pendulum, (0.0, 4.0), rtol=1e-6)
    stats = sol.stats
    assert stats["attempts"] == stats["steps"] + stats["rejected_steps"] + stats["newton_failures"]
    assert stats["rejected_steps"] + stats["newton_failures"] > 0  # the budget below is spent by failed attempts too
    with pytest.raises(E.StepLimitError, match=f"max_steps = {stats['attempts'] - 1} reached"):
        dm.solve(pendulum, (0.0, 4.0), rtol=1e-6, max_steps=stats["attempts"] - 1)
    assert radau.RadauOptions().max_steps == radau.DEFAULT_MAX_ADAPTIVE_STEPS
    assert radau.RadauOptions(h=0.1).max_steps == radau.DEFAULT_MAX_FIXED_STEPS
    assert "max_local_error_estimate" not in stats


def pendulum_invariants_drift(sol) -> tuple[float, float]:
    """Largest drift of the pendulum's energy (y3^2 + y4^2) / 2 + lam y2 (lam = 1, conserved since
    y1 y3 + y2 y4 = 0) and of its rod length y1^2 + y2^2 = 1: exact references along any span."""
    energy = (sol["y3"] ** 2 + sol["y4"] ** 2) / 2 + sol["y2"]
    return float(np.abs(energy - energy[0]).max()), float(np.abs(sol["y1"] ** 2 + sol["y2"] ** 2 - 1).max())


def test_default_budget_runs_a_long_span(pendulum):
    """[0, 250] at rtol = 1e-6 with three stages takes about 6,800 attempts: refused by the old default of
    5,000 (the default's five stages take about 3,200)."""
    sol = dm.solve(pendulum, (0.0, 250.0), rtol=1e-6, stages=3)
    assert sol.status == "success" and sol.t[-1] == 250.0 and sol.stats["attempts"] > 5_000
    energy, rod = pendulum_invariants_drift(sol)
    assert energy < 2e-6 and rod < 2e-7


@pytest.mark.slow
def test_default_budget_runs_the_pendulum_over_a_thousand(pendulum):
    """The issue's case: about 12,900 attempts with the default's five stages (27,600 with three)."""
    sol = dm.solve(pendulum, (0.0, 1000.0), rtol=1e-6)
    assert sol.status == "success" and sol.t[-1] == 1000.0
    energy, rod = pendulum_invariants_drift(sol)
    assert energy < 1e-5 and rod < 1e-6  # measured 4.2e-7 and 1.4e-8 (three stages: 1.7e-6 and 2.6e-7)


def test_five_stages_run_the_pendulum_over_a_thousand(pendulum):
    """s = 5 at rtol 1e-6 failed Newton at ever shorter steps, down to 2.5e-8 (z 0.39 off its hidden
    constraint there, the guess of the next step's z by hundreds of its units: formulas.high_index_pattern);
    now 12,900 attempts (s = 3: 27,600) with the invariants held as well as s = 3 holds them."""
    sol = dm.solve(pendulum, (0.0, 1000.0), rtol=1e-6, atol=1e-8, stages=5)
    assert sol.status == "success" and sol.t[-1] == 1000.0 and sol.stats["stages"] == 5
    assert sol.stats["h_min"] > 1e-3 and sol.stats["attempts"] < 16_000  # measured 4.6e-3 and 12,884
    energy, rod = pendulum_invariants_drift(sol)
    assert energy < 2e-6 and rod < 1e-7  # measured 4.2e-7 and 1.4e-8 (s = 3: 1.7e-6 and 2.6e-7)
    z = ((sol["y3"] ** 2 + sol["y4"] ** 2) - sol["y2"]) / (sol["y1"] ** 2 + sol["y2"] ** 2)  # the hidden constraint
    assert float(np.abs(sol["y5"] - z).max()) < 1e-3


@pytest.mark.parametrize("atol", [1e-4, 1e-6])
def test_seven_stages_at_a_loose_rtol_run_the_pendulum(pendulum, atol):
    """Seven stages at rtol 1e-4 on index 2: RADAU5's Newton tolerance (min(0.03, rtol^0.5), 0.01 here) left
    stage errors that the s = 7 estimate did not see shrink with h, and h collapsed (rtol = atol = 1e-4: a
    StepLimitError at t = 4.1; atol 1e-6: a step size underflow at t = 4.4).  Now radau.f's rule,
    rtol^((s - 1) / (s + 1)) (control.adaptive_newton_tol) with RADAU5's geometric contraction
    (formulas.mean_contraction): 114 and 139 attempts, 0.013 and 0.16 of atol + rtol off the reference
    (the tolerance alone: 325 and 476)."""
    from scipy.integrate import solve_ivp

    rtol, times = 1e-4, np.linspace(0.0, 20.0, 21)
    sol = dm.solve(pendulum, (0.0, 20.0), rtol=rtol, atol=atol, stages=7, t_eval=times)
    assert sol.status == "success" and sol.stats["attempts"] < 5_000
    # the pendulum's angle: phi'' = -cos(phi) (m = lam = 1), x = cos(phi), y = sin(phi)
    phi = solve_ivp(
        lambda t, u: [u[1], -np.cos(u[0])], (0.0, 20.0), [0.0, 1.0], method="DOP853", rtol=1e-13, atol=1e-13,
        t_eval=times,
    ).y[0]  # fmt: skip
    assert float(np.abs(np.ravel(sol["y1"]) - np.cos(phi)).max()) < 10 * rtol  # (newton_tol=1e-10: < 0.05 rtol)
    assert float(np.abs(np.ravel(sol["y2"]) - np.sin(phi)).max()) < 10 * rtol


@pytest.mark.parametrize("stages", [5, 7])
@pytest.mark.parametrize("rtol", [1e-3, 1e-4, 1e-5])
@pytest.mark.parametrize("key", ["pendulum", "pendulum-index3", "car-axis"])
def test_five_and_seven_stages_at_a_loose_rtol_meet_it_on_index_2_and_3(key, rtol, stages):
    """Five and seven stages at rtol 1e-3 to 1e-5 on the pendulum (index 2, and its index-3 form) over [0, 20]
    against its angle by DOP853 at 1e-13, and on the car axis (index 3) against the Test Set's reference at
    t = 3: within atol + rtol |u| (atol = rtol on the pendulum, rtol / 100 on the car axis).  RADAU5's Newton
    tolerance gave s = 7 on the pendulum step size underflows and max_steps, s = 5 there 0.98-7.3 x off
    (rtol 1e-3, 1e-4), and both on the car axis 1.7-8.9 x; radau.f's rule and the geometric contraction:
    at most 0.16 x, 0.44 x and 192 attempts."""
    from scipy.integrate import solve_ivp

    from daemodel.problems import PROBLEMS

    problem = PROBLEMS[key]
    compiled = _compiled(key)
    if key == "car-axis":
        atol, t_span, times = rtol / 100, tuple(problem.t_span), None
    else:
        atol, t_span, times = rtol, (0.0, 20.0), np.linspace(0.0, 20.0, 21)
    sol = dm.solve(compiled, t_span, rtol=rtol, atol=atol, stages=stages, t_eval=times)
    assert sol.status == "success" and sol.stats["stages"] == stages and sol.stats["attempts"] < 1_000
    if key == "car-axis":
        for name, value in problem.reference.items():
            if name in compiled.state_names:
                assert abs(float(np.ravel(sol[name])[-1]) - value) < atol + rtol * abs(value), name
        return
    phi = solve_ivp(
        lambda t, u: [u[1], -np.cos(u[0])], t_span, [0.0, 1.0], method="DOP853", rtol=1e-13, atol=1e-13, t_eval=times
    ).y[0]  # the angle: phi'' = -cos(phi), x = cos(phi), y = sin(phi)
    assert float(np.abs(np.ravel(sol["y1"]) - np.cos(phi)).max()) < atol + rtol
    assert float(np.abs(np.ravel(sol["y2"]) - np.sin(phi)).max()) < atol + rtol


@functools.cache
def _compiled(key):
    """A Test Set problem, compiled once."""
    from daemodel.problems import PROBLEMS

    return PROBLEMS[key].model().compile()


# ---- grids, tolerances, devices, output times ----------------------------------------------


def test_tiny_h_is_refused_before_the_grid_is_allocated(pendulum):
    with pytest.raises(
        E.ResourceLimitError,
        match=r"h = 1e-11 over t_span = \(0, 1\) needs 1e\+11 steps, more than max_steps = 100,000; "
        r"raise max_steps or take h >= 1e-05",
    ):
        dm.solve(pendulum, (0.0, 1.0), h=1e-11)
    with pytest.raises(E.ResourceLimitError, match=r"needs 100 steps, more than max_steps = 50"):
        dm.solve(pendulum, (0.0, 1.0), h=0.01, max_steps=50)
    tracemalloc.start()
    try:
        with pytest.raises(
            E.ResourceLimitError,
            match=rf"needs 1e\+11 steps, more than MAX_GRID_POINTS = {MAX_GRID_POINTS:,}; a fixed grid holds at most",
        ):
            fixed_grid((0.0, 1.0), 1e-11)  # casadi-collocation's and the PINN's grids
        assert tracemalloc.get_traced_memory()[1] < 2**20
    finally:
        tracemalloc.stop()
    with pytest.raises(E.StepSizeError, match=r"h = 1e-07 is below the float64 resolution of t on t_span"):
        fixed_grid((1e10, 1e10 + 1.0), 1e-7)
    assert len(fixed_grid((0.0, 1.0), 0.1)) == 11


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"rtol": 10.0, "atol": 10.0}, r"rtol = 10 is outside the meaningful range \[1e-14, 0\.1\]: that asks for no"),
        ({"rtol": 1e-20}, r"rtol = 1e-20 is outside .* float64 cannot deliver more digits; use rtol >= 1e-14"),
        ({"rtol": 1e-6, "atol": -1.0}, "atol must be positive"),
        ({"rtol": 1e-8, "dtype": "float32"}, "below what float32 can deliver"),
    ],
)
def test_tolerances_out_of_range(pendulum, kwargs, match):
    with pytest.raises(E.InvalidOptionError, match=match):
        dm.solve(pendulum, (0.0, 1.0), **kwargs)


@pytest.mark.parametrize(
    ("device", "match"),
    [
        ("meta", r"device = 'meta': daemodel's torch solvers run on the CPU or a CUDA device, not on 'meta'"),
        ("mps", r"not on 'mps' .*; the choices here are 'cpu'"),
        (5, r"device must be a string such as 'cpu'; got 5; the choices here are 'cpu'"),
        ("gpu", r"device = 'gpu' names no torch device; the choices here are 'cpu'"),
        ("cuda:99", r"device = 'cuda:99' but torch sees (no CUDA device|\d+ CUDA device)"),
    ],
)
def test_devices_torch_cannot_use_here(pendulum, device, match):
    with pytest.raises(E.InvalidOptionError, match=match):
        dm.solve(pendulum, (0.0, 1.0), h=0.1, device=device)


def test_cpu_devices_are_accepted(pendulum):
    import torch

    assert dm.solve(pendulum, (0.0, 0.2), h=0.1, device=torch.device("cpu")).settings["device"] == "cpu"
    assert dm.solve(pendulum, (0.0, 0.2), h=0.1, device="cpu:0").stats["device"] == "cpu:0"


@pytest.mark.parametrize(
    ("t_eval", "match"),
    [
        ("abc", r"t_eval must be a sequence of real numbers; got 'abc' \(dtype <U3\)"),
        (["0.1", "0.2"], "t_eval must be a sequence of real numbers"),
        ([0.1j], r"real numbers; got \[0\.1j\] \(dtype complex128\)"),
        ([[0.1], [0.2, 0.3]], r"real numbers; .* \(no array\)"),
        ([0.1, None], r"t_eval must hold finite times only"),
        ([], "t_eval must hold at least one finite time"),
    ],
)
def test_t_eval_must_be_numbers(pendulum, t_eval, match):
    with pytest.raises(E.TimeSpanError, match=match):
        dm.solve(pendulum, (0.0, 1.0), h=0.1, t_eval=t_eval)


def test_a_step_across_a_point_where_z_is_not_determined_is_refused():
    # q' = (0.7 - t) z, 0 = q - sin t: z = cos t / (0.7 - t) blows up at t = 0.7, where g_y f_z = 0.
    # Index-2 z is measured against (atol + rtol |z|) / h, so the error estimate alone stepped over it.
    m = dm.Model("sing2")
    m.states("q")
    m.algebraics("z")
    m.ode("q", "z*(0.7 - t)")
    m.constraint("q - sin(t)", name="track")
    m.initial(q=0.0)
    for options in ({}, {"h": 0.03}):
        with pytest.raises(
            E.ConvergenceError,
            match=r"radau: the constraints \('track'\) stop determining the algebraic variables between t = "
            r"0\.\d+ and 0\.7\d* \(sample 0\): the determinant of their iteration matrix .* changes sign",
        ):
            dm.solve(m, (0.0, 1.0), **options)
    sol = dm.solve(m, (0.0, 0.6), h=0.03)  # before it: fine
    np.testing.assert_allclose(sol["z"][-1], np.cos(0.6) / 0.1, rtol=1e-6)


def test_a_sign_change_that_is_the_steps_own_asks_for_a_smaller_h():
    """y' = -10 y, 0 = (y + 0.05) z - 1: y = exp(-10 t) > 0 keeps g_z = y + 0.05 positive, but three stages
    at h = 0.25 (h lambda = -2.5) leave the solution there. Before: "reformulate the constraints"; h/4
    passes, so the advice is a smaller h, and at h/4 the values are the exact ones."""
    m = dm.Model("inverse")
    m.states("y")
    m.algebraics("z")
    m.ode("y", "-10*y + 0*z")
    m.constraint("(y + 0.05)*z - 1", name="inverse")
    m.initial(y=1.0)
    with pytest.raises(
        E.ConvergenceError,
        match=r"radau: with h = 0\.25 the determinant .* changes sign between t = 0\.25 and 0\.5, but with "
        r"h = 0\.0625 the solve passes t = 0\.75 without it: the change is the step's own, too large for the "
        r"solution there; take h = 0\.0625 or smaller",
    ):
        dm.solve(m, (0.0, 3.0), h=0.25, stages=3)
    sol = dm.solve(m, (0.0, 3.0), h=0.0625, stages=3)
    np.testing.assert_allclose(sol["z"], 1 / (np.exp(-10 * sol.t) + 0.05), rtol=2e-3)


def test_too_few_newton_iterations_are_named_as_the_cause():
    """With max_newton_iterations = 1 the pendulum's steps shrink to nothing: the budget's error said the
    right-hand side was likely discontinuous (chattering); it names the iterations."""
    with pytest.raises(
        E.StepLimitError,
        match=r"radau: max_steps = 100000 cannot suffice .*: \d+ attempts failed in Newton, which stops at "
        r"max_newton_iterations = 1: raise it \(the default is 10\)",
    ):
        dm.solve(PENDULUM.model(), (0.0, 0.5), rtol=1e-8, atol=1e-8, max_newton_iterations=1)
    from daemodel.backends.radau.control import underflow_error

    message = str(underflow_error(1e-15, 0.25, "not converged in 1 iteration", 0))
    assert message == (
        "radau: step size underflow at t = 0.25 (h = 1e-15; last failure: not converged in 1 iteration, sample 0); "
        "Newton stops at max_newton_iterations before it converges: raise it (the default is 10)"
    )


def test_an_underflow_by_the_error_estimate_names_newtons_tolerance_too():
    """The step size underflow where the error estimate kept shrinking the step said only that the solution may
    blow up or leave f's domain; the pendulum at s = 7, rtol 1e-4, atol 1e-6 (smooth, bounded) ended there at
    t = 4.4 because Newton's tolerance left stage errors that do not shrink with h (newton_tol=1e-10 ran it in
    625 attempts: test_seven_stages_at_a_loose_rtol_run_the_pendulum)."""
    from daemodel.backends.radau.control import underflow_error

    message = str(underflow_error(4.4e-14, 4.42153, "the error estimate kept shrinking the step", None))
    assert message == (
        "radau: step size underflow at t = 4.42153 (h = 4.4e-14; last failure: the error estimate kept shrinking "
        "the step); the solution may blow up or leave the domain of f there, or, where it stays smooth, Newton's "
        "tolerance leaves stage errors that do not shrink with h (more stages at a looser rtol need a tighter one): "
        "give a smaller newton_tol (e.g. 1e-10), or leave stages out"
    )


def test_a_newton_tol_looser_than_the_stages_default_flags_the_solution(pendulum):
    """The error estimate does not see the stage errors a loose Newton leaves: seven stages at rtol = atol = 1e-4
    with newton_tol = 0.03 (the stages' default: 1e-3) said "success" over [0, 6] 1.7e-2 from the reference (170x
    the tolerance; the default: 3e-6), and over [0, 20], where only the progress watch stopped it, 1.1.  Such a
    solve is flagged; a newton_tol at the default is not.  (Over [0, 6]: since each step is the one t's float64
    spacing makes of h, h underflows at t = 4.13 on this solve, a named error; over [0, 4] it is 1.5e-2 off.)"""
    t_eval = np.linspace(0.0, 4.0, 7)
    ref = dm.solve(pendulum, (0.0, 4.0), method="reference", t_eval=t_eval)
    states = pendulum.state_names
    with pytest.warns(E.LocalErrorWarning, match=r"newton_tol = 0\.03 is looser than these stages' default"):
        sol = dm.solve(pendulum, (0.0, 4.0), rtol=1e-4, atol=1e-4, stages=7, newton_tol=0.03, t_eval=t_eval)
    assert sol.status == (
        "flagged: radau's newton_tol = 0.03 is looser than these stages' default (0.001): the error estimate does "
        "not see the stage errors Newton leaves, and the values may be further from the solution than rtol and "
        "atol say (seven stages at rtol 1e-4 on the pendulum over [0, 4]: 1.5e-2 off); leave newton_tol out"
    )
    assert max(sol.errors(ref)[name]["max"] for name in states) > 1e-3  # (the flag is earned)
    sol = dm.solve(pendulum, (0.0, 4.0), rtol=1e-4, atol=1e-4, stages=7, newton_tol=1e-3, t_eval=t_eval)
    assert sol.status == "success"
    assert max(sol.errors(ref)[name]["max"] for name in states) < 1e-4


def test_a_newton_tol_looser_than_the_stages_default_is_named_where_h_collapses(pendulum):
    """A newton_tol given above adaptive_newton_tol's (seven stages at rtol 1e-4: 0.03 against 1e-3) is taken
    as given; on the pendulum over [0, 20] it collapsed h to ~4e-6 by t ~ 3.9, and the budget's error said only
    that t_span was too long for max_steps (raise it, loosen rtol/atol or shorten t_span).  It names newton_tol
    now; the default runs the same solve in 114 attempts (test_seven_stages_at_a_loose_rtol_run_the_pendulum).
    (max_steps = 5,000: since a dip may take a quarter of the budget, the default budget lets these dips
    through, 83,777 attempts, to a flagged solution: test_a_newton_tol_looser_than_the_stages_default_flags_...;
    since each step is the one t's float64 spacing makes of h, to an underflow at t = 4.13 that names newton_tol
    too, beyond max_steps = 20,000)"""
    from daemodel.backends.radau.control import underflow_error

    with pytest.raises(
        E.StepLimitError,
        match=r"the steps are accepted, but .*shorten t_span; or newton_tol = 0\.03 is looser than these stages' "
        r"default \(0\.001\): the stage errors it leaves may not shrink with h, which then collapses where the "
        r"solution is smooth: leave newton_tol out$",
    ):
        dm.solve(pendulum, (0.0, 20.0), rtol=1e-4, atol=1e-4, stages=7, newton_tol=0.03, max_steps=5_000)
    hint = "; or newton_tol = 0.03 is looser than ..."
    message = str(underflow_error(4.4e-14, 4.42153, "the error estimate kept shrinking the step", None, hint))
    assert message.endswith("give a smaller newton_tol (e.g. 1e-10), or leave stages out" + hint)
    assert str(underflow_error(1e-15, 0.25, "not converged in 1 iteration", 0, hint)).endswith("(the default is 10)")
    # a newton_tol at or below the stages' default adds nothing
    with pytest.raises(E.StepLimitError) as caught:
        dm.solve(pendulum, (0.0, 1e300), max_steps=200, stages=7, rtol=1e-4, atol=1e-4, newton_tol=1e-3)
    assert "newton_tol" not in str(caught.value)


# ---- a time limit's signal is not a singular system ------------------------------------------------
def test_a_time_limit_inside_a_factorisation_is_not_taken_for_a_singular_system(monkeypatch):
    """SuperLU says "exactly singular" with a RuntimeError, and radau takes that for a singular matrix;
    a TimeLimitError (a RuntimeError too) raised by the limit's signal as the call returns went the same
    way, and the solve went on past its limit. Now a daemodel error goes through."""
    import scipy.sparse as sparse
    import scipy.sparse.linalg as splinalg
    from daemodel.backends.radau import linalg

    def struck(_):
        raise E.TimeLimitError("the limit struck")

    def singular(_):
        raise RuntimeError("Factor is exactly singular")

    matrix = sparse.diags([1.0, 2.0, 1.0], [-1, 0, 1], shape=(3, 3)).tocsc()  # (not triangular: SuperLU's)
    monkeypatch.setattr(splinalg, "splu", struck)
    for call in (linalg.sparse_lu, linalg.sparse_sign_det):
        with pytest.raises(E.TimeLimitError, match="the limit struck"):
            call(matrix)
    monkeypatch.setattr(splinalg, "splu", singular)
    assert linalg.sparse_lu(matrix)[0] == ("singular",) and linalg.sparse_sign_det(matrix) == 0.0


@pytest.mark.machine_code
@pytest.mark.parametrize("jit", [False, "auto"])
def test_a_time_limit_stops_a_long_radau_solve_where_it_strikes(jit):
    """The ring modulator at rtol 1e-10 (tens of thousands of steps, seconds) under a 0.3 s limit: the
    TimeLimitError comes out within a second of the limit, whichever casadi call it strikes in."""
    import time

    from daemodel.executors import time_limit
    from daemodel.problems import RING_MODULATOR

    model = RING_MODULATOR.model().compile()
    dm.solve(model, (0.0, 1e-6), rtol=1e-10, atol=1e-10, jit=jit)  # (any compiling done before the clock)
    for _ in range(3):
        began = time.perf_counter()
        with pytest.raises(E.TimeLimitError, match="stop here"), time_limit(0.3, "stop here"):
            dm.solve(model, RING_MODULATOR.t_span, rtol=1e-10, atol=1e-10, jit=jit)
        assert time.perf_counter() - began < 1.3


def test_a_time_limit_in_the_smaller_step_check_is_not_the_sign_change_error(monkeypatch):
    """A fixed grid's determinant sign change is checked again at h / 4 (RadauBackend._at_a_smaller_step);
    any daemodel error of that check gave back the sign change's ConvergenceError, a time limit's too."""
    from daemodel.backends.radau.backend import RadauBackend
    from daemodel.backends.radau.options import RadauOptions

    def struck(*_, **__):
        raise E.TimeLimitError("stop here")

    monkeypatch.setattr(RadauBackend, "_solve", struck)
    compiled = PENDULUM.model().compile()
    sign_change = E.ConvergenceError("the determinant changes sign")
    with pytest.raises(E.TimeLimitError, match=r"^stop here$"):
        RadauBackend()._at_a_smaller_step(compiled, (0.0, 1.0), None, RadauOptions(h=0.1), sign_change, (0.2, 0.3))


def _oscillator(t0: float) -> dm.Model:
    """``x' = v, v' = -x`` from ``x = 1, v = 0`` at t0: exactly ``x = cos(t - t0)``, ``x^2 + v^2 = 1``."""
    m = dm.Model("oscillator")
    x, v = m.states("x v")
    m.ode(x, v)
    m.ode(v, -x)
    m.initial(t=t0, x=1.0, v=0.0)
    return m


@pytest.mark.parametrize(
    "t0, rtol", [(1e15, 1e-6), (1e16, 1e-6), (1e17, 1e-6), (1e18, 1e-6), (-1e17, 1e-6), (1e17, 1e-2)]
)
def test_an_oscillator_started_where_t_is_coarse_is_not_damped_away_as_success(t0, rtol):
    """From t0 = 1e17 (float64's spacing 16 there, the steps rtol 1e-6 asks for ~0.05) the first step's floor,
    1e-10 |t0| = 1e7, was accepted on the refiltered estimate (0.1 at h omega = 1e7, the L-stable step's damping
    unseen): "success" on a solution damped to 1e-79.  At 1e15 and 1e16 the floor's step was rejected and h
    underflowed, as a ConvergenceError that blamed a blow-up or Newton.  Now no estimate above the probe's step
    is refiltered before a step is accepted, and the underflow names t's resolution and the probe's step."""
    message = (
        rf"radau: the steps that rtol and atol ask for at t = {re.escape(f'{t0:.17g}')} are shorter than float64 "
        rf"resolves there: .* \(spacing {np.spacing(abs(t0)):.3g}\), where the start's probe asked for "
        r"h = (0\.\d+), [0-9.e-]+ of t_span; start t_span nearer 0"
    )
    with pytest.raises(E.StepSizeError, match=message) as caught:
        dm.solve(_oscillator(t0).compile(), (t0, t0 + 9 * abs(t0)), rtol=rtol, atol=rtol)
    probe = float(re.search(message, str(caught.value)).group(1))
    assert probe < 1e-14 * abs(t0)  # (below the underflow's threshold: t cannot resolve it)


@pytest.mark.machine_code
@pytest.mark.parametrize("h0", [1e3, 1e7])
@pytest.mark.parametrize("rtol, jit", [(1e-6, "auto"), (1e-6, False), (1e-2, "auto")])
def test_a_first_step_far_above_the_probe_s_shrinks_unfiltered(h0, rtol, jit):
    """A user's h0 = 1e7 on the oscillator from t0 = 0 over (0, 1e8) (h omega = 1e7) was accepted on the
    refiltered estimate and damped x^2 + v^2 to 1e-22 as "success" in 4 steps (h0 = 1e3 too at rtol 1e-2).
    Unfiltered, the estimate reads the step's damping (-y0: rejected), and h shrinks to the probe's step, where
    RADAU5's refiltering starts: at rtol 1e-6 the span then needs ~1e8 steps, which max_steps cannot give
    (named); at 1e-2 the first step keeps x^2 + v^2 within 10 rtol.  (Over that span, at rtol 1e-2, the local
    errors then add up to damping the oscillation away in 2,500 steps, as without h0: local error control.)
    Over (0, 50) the same h0 ends within 40 rtol of the exact cos t (3.6e-9 at rtol 1e-6, 3.2e-2 at 1e-2)."""
    compiled = _oscillator(0.0).compile()
    if rtol < 1e-3:
        with pytest.raises(E.StepLimitError, match=r"radau: max_steps = 100000 cannot suffice"):
            dm.solve(compiled, (0.0, 1e8), rtol=rtol, atol=rtol, h0=h0, jit=jit)
    else:
        sol = dm.solve(compiled, (0.0, 1e8), rtol=rtol, atol=rtol, h0=h0, jit=jit)
        assert sol.t[1] < 10 and abs(np.hypot(sol["x"][1], sol["v"][1]) - 1) < 10 * rtol
    sol = dm.solve(compiled, (0.0, 50.0), rtol=rtol, atol=rtol, h0=h0, jit=jit)
    assert sol.status == "success" and sol.stats["rejected_steps"] >= 2
    assert np.abs(sol["x"] - np.cos(sol.t)).max() < 40 * rtol
    assert np.abs(np.hypot(sol["x"], sol["v"]) - 1).max() < 40 * rtol


def test_a_large_first_step_on_a_decaying_mode_still_solves():
    """Where the flow damps the mode, the large first steps still end right: y' = -1e6 (y - cos t) from y0 = 0.95
    with h0 = 1 or 1e3 (the exact solution: the slow manifold plus the transient) and y' = -y with h0 = 1e7."""
    m = dm.Model("stiff")
    m.states("y")
    m.ode("y", "-1e6*(y - cos(t))")
    m.initial(y=0.95)
    compiled = m.compile()
    slow = lambda t: (1e12 * np.cos(t) + 1e6 * np.sin(t)) / (1e12 + 1)  # noqa: E731
    for h0 in (1.0, 1e3):
        sol = dm.solve(compiled, (0.0, 10.0), rtol=1e-6, atol=1e-6, h0=h0)
        exact = slow(sol.t) + (0.95 - slow(0.0)) * np.exp(-1e6 * sol.t)
        assert sol.status == "success" and np.abs(sol["y"] - exact).max() < 4e-6
    m = dm.Model("decay")
    m.states("y")
    m.ode("y", "-y")
    m.initial(y=1.0)
    sol = dm.solve(m.compile(), (0.0, 100.0), rtol=1e-6, atol=1e-6, h0=1e7)
    assert sol.status == "success" and np.abs(sol["y"] - np.exp(-sol.t)).max() < 1e-8


@pytest.mark.machine_code
@pytest.mark.parametrize("jit", [False, "auto"])
def test_a_non_finite_constraint_is_named_where_the_increment_is_written_over_the_residual(jit):
    """On sparse systems (120 unknowns) Newton's increment is written over the residual's R and G
    (.engines.AbstractEngine.newton_step); a failure on non-finite values evaluates the residual once more to
    name its culprit: log(x37) with x37 = 0.05 - t, each constraint coupled to its neighbours (the LU solve
    spreads a NaN over the whole increment: named from it, the culprit read 'c0' at stage 1)."""
    K = 60
    m = dm.Model("logs")
    x = m.states(" ".join(f"x{k}" for k in range(K)))
    z = m.algebraics(" ".join(f"z{k}" for k in range(K)))
    for k in range(K):
        m.ode(x[k], -1 + 0 * z[k])
        near = (z[k - 1] if k else 0) + (z[k + 1] if k < K - 1 else 0)
        m.constraint(z[k] - sp.log(x[k]) - near / 10, name=f"c{k}")
    m.initial(**{f"x{k}": (0.05 if k == 37 else 1.0) for k in range(K)})
    with pytest.raises(
        E.ConvergenceError,
        match=r"step size underflow at t = 0\.05 .*last failure: non-finite values: constraint 'c37' at stage 3 ",
    ):
        dm.solve(m, (0.0, 1.0), rtol=1e-6, atol=1e-8, jit=jit)

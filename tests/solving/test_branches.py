"""Which side an event's or a switch's function goes on to where it is at zero (daemodel/solving/branches.py): a
declared event that crosses too slowly for one look-ahead, and a jump switch whose function rests on zero on both
branches; against the exact crossing times and counts."""

import math

import numpy as np
import pytest

import daemodel as dm
from daemodel import errors as E

# radau's default on casadi's virtual machine, but in the tests marked machine_code (tests/conftest.py)
pytestmark = pytest.mark.virtual_machine

METHODS = [
    ("radau", {"rtol": 1e-8, "atol": 1e-8}),
    ("radau", {"stages": 3, "h": 0.01}),
    ("casadi-idas", {}),
    ("reference", {}),
]


@pytest.mark.parametrize("reset", [False, True])
@pytest.mark.parametrize(("method", "options"), [("reference", {}), ("radau", {"stages": 3, "h": 0.01})])
@pytest.mark.parametrize("depth", [1e-12, 1e-11])
def test_an_event_that_crosses_slowly_and_back_soon_counts_both_crossings(reset, method, options, depth):
    # x = (t - 1)^2 - depth crosses zero at 1 -+ sqrt(depth) (1e-6, 3.2e-6): at the first, x moves by 4e-15 over the
    # look-ahead (2e-9), below rounding, so its side was 0 (not armed), and its crossing back was taken for its first
    # leaving of zero: one crossing recorded (n = 1), "success", under the reference and a fixed radau grid
    m = dm.Model("slow_crossing")
    m.states("x n")
    m.ode("x", "2*(t - 1)")
    m.ode("n", "0")
    m.initial(x=1.0 - depth, n=0.0)
    m.event("level", "x", **({"reset": {"n": "n + 1"}} if reset else {}))
    sol = dm.solve(m, (0.0, 2.0), method=method, **options)
    assert sol.status == "success"
    np.testing.assert_allclose(
        sol.events["level"]["t"].ravel(), [1 - math.sqrt(depth), 1 + math.sqrt(depth)], atol=1e-9
    )
    assert sol["n"][-1] == (2.0 if reset else 0.0)


@pytest.mark.parametrize("depth", [1e-14, 2e-15])
def test_an_event_whose_crossing_back_lies_within_the_longer_look_aheads_counts_both(depth):
    # x = (t - 1)^2 - depth crosses zero at 1 -+ sqrt(depth) (1e-7, 2e-7 apart): after the first, the look-ahead
    # that resolved its side (64 x 2e-9) had passed the crossing back and read it above zero, the side it came
    # from: one crossing recorded, of a function above zero at both ends, "success" (the reference, exact here)
    m = dm.Model("crossing_back_soon")
    m.states("x")
    m.ode("x", "2*(t - 1)")
    m.initial(x=1.0 - depth)
    m.event("level", "x")
    sol = dm.solve(m, (0.0, 2.0), method="reference")
    assert sol.status == "success"
    half = math.sqrt(depth)  # (x within 2e-15 of the exact moves a crossing by 2e-15 / x' = 2e-15 / (2 half))
    np.testing.assert_allclose(sol.events["level"]["t"].ravel(), [1 - half, 1 + half], atol=1e-15 / half)


@pytest.mark.parametrize(("method", "options"), [("reference", {}), ("casadi-collocation", {"h": 0.25})])
def test_a_touch_that_the_solution_crosses_within_rounding_records_an_even_count(method, options):
    # x = (t - 1)^2 touches zero at t = 1; these methods' solutions dip ~3e-15 below it (crossings 1 -+ 5e-8): one
    # crossing was recorded, "success", where a function above zero at both ends crosses an even number of times
    # (casadi-collocation's Newton leaves its x ~1e-12 off: a dip this shallow may be below what it resolves, named)
    m = dm.Model("touch")
    m.states("x")
    m.ode("x", "2*(t - 1)")
    m.initial(x=1.0)
    m.event("level", "x")
    try:
        sol = dm.solve(m, (0.0, 2.0), method=method, **options)
    except E.ZenoError as error:
        assert method != "reference" and "closer together than it resolves" in str(error)
        return
    times = sol.events["level"]["t"].ravel()
    assert len(times) % 2 == 0 and np.all(np.abs(times - 1.0) < 1e-6), times


@pytest.mark.parametrize(("method", "options"), [("reference", {}), ("radau", {"rtol": 1e-10, "atol": 1e-14})])
def test_a_slow_bounce_goes_back_to_the_side_it_came_from(method, options):
    # x' = v, v' = -1e-8 from x = 1e-6, v -> -0.8 v at the floor (both ways counted): the impacts move x by 2e-16
    # over the look-ahead, and the longer ones read it going back up, as the reset sends it; taken for a crossing
    # back (the side it crossed to kept, as a counter's), it was a ZenoError at the first impact
    g, x0, e = 1e-8, 1e-6, 0.8
    m = dm.Model("slow_bounce")
    m.states("x v")
    m.ode("x", "v")
    m.ode("v", f"-{g!r}")
    m.event("floor", "x", reset={"v": f"-{e!r}*v"})
    m.initial(x=x0, v=0.0)
    sol = dm.solve(m, (0.0, 100.0), method=method, **options)
    first = math.sqrt(2 * x0 / g)
    flights = 2 * first * e ** np.arange(1, 7)  # (each flight 2 v / g, v = g * first * e^k)
    exact = first + np.concatenate([[0.0], np.cumsum(flights)])
    assert sol.status == "success"
    np.testing.assert_allclose(sol.events["floor"]["t"].ravel(), exact[exact < 100.0], rtol=1e-9)


def _ball(x0: float, v0: float = 0.0, g: float = 9.81, e: float = 0.8) -> dm.Model:
    m = dm.Model("ball")
    m.states("x v")
    m.ode("x", "v")
    m.ode("v", f"-{g!r}")
    m.event("floor", "x", direction=-1, reset={"v": f"-{e!r}*v"})
    m.initial(x=x0, v=v0)
    return m


def _impacts_by_scipy(x0: float, v0: float, span: float, g: float = 9.81, e: float = 0.8) -> np.ndarray:
    # (an independent reference: scipy's solve_ivp with a terminal event, restarted by hand after each bounce)
    from scipy.integrate import solve_ivp

    def floor(t, u):
        return u[0]

    floor.terminal, floor.direction = True, -1
    t, u, times = 0.0, [x0, v0], []
    while len(times) < 20:
        sol = solve_ivp(
            lambda t, u: [u[1], -g], (t, span), u, events=floor, rtol=1e-12, atol=1e-12 * max(x0, v0**2 / g)
        )
        if not len(sol.t_events[0]):
            return np.array(times)
        t, v = sol.t_events[0][0], sol.y_events[0][0][1]
        times.append(t)
        u = [0.0, -e * v]
    raise AssertionError(times)


BALL_METHODS = [("radau", {"rtol": 1e-10}), ("reference", {}), ("casadi-idas", {"rtol": 1e-10})]


@pytest.mark.machine_code
@pytest.mark.parametrize(("method", "options"), BALL_METHODS)
@pytest.mark.parametrize("x0", [1e-20, 1e-14, 1e-8, 1.0, 1e8])
def test_a_ball_at_any_scale_bounces_at_the_exact_times(method, options, x0):
    # a side was read against an absolute rounding floor (64 eps max(1, |values|), 1.4e-14): a ball dropped from
    # 1e-14 (or 1e-20) never left that band, its bounce was never armed, and radau recorded 1 of its 6 impacts and
    # let it fall to -23 x0, "success"; the side is now read within the rounding of the function's own terms
    g, e, span = 9.81, 0.8, 3e-7 * math.sqrt(x0 / 1e-14)  # (the same ball in other units: t scales as sqrt(x0))
    first = math.sqrt(2 * x0 / g)
    exact = first + np.concatenate([[0.0], np.cumsum(2 * first * e ** np.arange(1, 9))])
    exact = exact[exact < span]
    assert len(exact) == 6
    try:
        sol = dm.solve(_ball(x0, g=g, e=e), (0.0, span), method=method, atol=1e-10 * x0, **options)
    except E.EventLimitError:  # (refused by name: acceptable)
        return
    assert sol.status == "success"
    np.testing.assert_allclose(sol.events["floor"]["t"].ravel(), exact, rtol=1e-6)
    assert sol["x"].min() > -1e-6 * x0


@pytest.mark.parametrize("x0", [1e-14, 1.0])
def test_the_exact_impact_times_agree_with_scipy_restarted_by_hand(x0):
    # (the exact times used above, checked against an independent solver: the formula, not only daemodel)
    g, e, span = 9.81, 0.8, 3e-7 * math.sqrt(x0 / 1e-14)
    first = math.sqrt(2 * x0 / g)
    exact = first + np.concatenate([[0.0], np.cumsum(2 * first * e ** np.arange(1, 9))])
    by_scipy = _impacts_by_scipy(x0, 0.0, span, g, e)
    np.testing.assert_allclose(by_scipy, exact[exact < span], rtol=1e-8)
    sol = dm.solve(_ball(x0, g=g, e=e), (0.0, span), method="radau", rtol=1e-10, atol=1e-10 * x0)
    np.testing.assert_allclose(sol.events["floor"]["t"].ravel(), by_scipy, rtol=1e-8)


@pytest.mark.parametrize(("method", "options"), BALL_METHODS)
@pytest.mark.parametrize("x0", [1e-20, 1e-14, 1e8])
def test_an_accumulating_ball_at_any_scale_is_refused_at_its_accumulation_point(method, options, x0):
    # past its accumulation point first (1 + 2e / (1 - e)): ZenoError there, in any units (before, at 1e-14 and
    # 1e-20: radau 1 impact, the reference 17, both "success" with the ball 89 and 6 x0 below the floor)
    g, e = 9.81, 0.8
    limit = math.sqrt(2 * x0 / g) * (1 + 2 * e / (1 - e))
    with pytest.raises(E.ZenoError, match=r"event 'floor'") as caught:
        dm.solve(_ball(x0, g=g, e=e), (0.0, 1.25 * limit), method=method, atol=1e-10 * x0, **options)
    assert limit * (1 - 1e-4) < caught.value.t < limit * (1 + 1e-6)  # (IDAS stops 7e-6 early at 1e-20: its error)


@pytest.mark.parametrize(("method", "options"), BALL_METHODS)
@pytest.mark.parametrize("v0", [1e-7, 1.0, 1e4])
def test_a_ball_thrown_up_from_the_floor_at_any_scale_bounces_at_the_exact_times(method, options, v0):
    # x = 0 exactly at t0, its side read off the flow: a throw of 1e-7 moves x by 1e-24 over the look-ahead
    g, e = 9.81, 0.8
    flights = 2 * v0 / g * e ** np.arange(0, 8)  # (each flight 2 v / g)
    exact = np.cumsum(flights)
    span = 0.5 * (exact[5] + exact[6])
    try:
        sol = dm.solve(_ball(0.0, v0, g, e), (0.0, span), method=method, atol=1e-10 * v0**2 / g, **options)
    except E.EventLimitError:
        return
    assert sol.status == "success"
    np.testing.assert_allclose(sol.events["floor"]["t"].ravel(), exact[:6], rtol=1e-6)
    assert sol["x"].min() > -1e-6 * v0**2 / g


@pytest.mark.parametrize(("method", "options"), BALL_METHODS)
@pytest.mark.parametrize("size", [1e-300, 1e-30, 1e-14])
def test_an_event_function_that_is_tiny_but_never_zero_never_fires(method, options, size):
    # size (2 + sin(x)) > 0 throughout, down to 1e-300: within any absolute floor of zero, but never on it
    m = dm.Model("tiny_function")
    m.states("x")
    m.ode("x", "1")
    m.event("never", f"{size!r}*(2 + sin(x))", reset={"x": "x + 1"})
    m.initial(x=0.0)
    sol = dm.solve(m, (0.0, 10.0), method=method, **options)
    assert sol.status == "success" and len(sol.events["never"]["t"].ravel()) == 0
    assert abs(sol["x"][-1] - 10.0) < 1e-8


@pytest.mark.parametrize(("method", "options"), BALL_METHODS)
def test_a_tiny_sawtooth_reset_off_its_guard_fires_at_each_tooth(method, options):
    # y' = 1e-15, reset y -> y - 1e-14 at y = 1e-14: the reset moves its function off zero by 1e-14, below the old
    # absolute floor (1.4e-14), within the new one's reach; teeth at t = 10, 20, ..., 50 either way
    m = dm.Model("tiny_sawtooth")
    m.states("y")
    m.ode("y", "1e-15")
    m.event("tooth", "y - 1e-14", direction=1, reset={"y": "y - 1e-14"})
    m.initial(y=0.0)
    sol = dm.solve(m, (0.0, 55.0), method=method, atol=1e-24, **options)
    assert sol.status == "success"
    np.testing.assert_allclose(sol.events["tooth"]["t"].ravel(), [10.0, 20.0, 30.0, 40.0, 50.0], rtol=1e-6)
    np.testing.assert_allclose(sol["y"][-1], 0.5e-14, rtol=1e-6)


def test_two_resets_of_a_tiny_state_to_different_values_are_refused():
    # a floor and a twin fire together on a ball dropped from 1e-31 (v = -1.4e-15 at impact) and set v to -0.8 v and
    # -0.5 v, 4.2e-16 apart: within the old absolute floor (1.4e-14), so the last reset held, "success"; refused now
    m = _ball(1e-31)
    m.event("twin", "x", direction=-1, reset={"v": "-0.5*v"})
    with pytest.raises(E.ResetConflictError, match=r"events 'floor' and 'twin' fire together at t = .* and reset 'v'"):
        dm.solve(m, (0.0, 1e-15), method="reference", atol=1e-41)
    twin = _ball(1e-31)
    twin.event("twin", "x", direction=-1, reset={"v": "-v*4/5"})  # (the same value, rounded otherwise: no conflict)
    sol = dm.solve(twin, (0.0, 1e-15), method="reference", atol=1e-41)
    assert sol.status == "success" and len(sol.events["twin"]["t"].ravel()) >= 1


@pytest.mark.parametrize("rate", ["Piecewise((1, x > 0), (2, True))", "sign(x)", "Heaviside(x)"])
@pytest.mark.parametrize(("method", "options"), METHODS)
def test_a_jump_switch_whose_function_rests_on_zero_on_both_branches_is_refused(rate, method, options):
    # x = 0 throughout (x' = 0): neither branch moves x off zero, and the default branch (x > 0) was taken: y(1) = 1
    # where the model says 2 (Piecewise) or 0 (sign(0)), "success" in every method
    m = dm.Model("resting_jump")
    m.states("x y")
    m.ode("x", "0")
    m.ode("y", rate)
    m.initial(x=0.0, y=0.0)
    with pytest.raises(E.ZenoError, match=r"x rests on zero on both of its branches .* which one holds is not decided"):
        dm.solve(m, (0.0, 1.0), method=method, **options)


def test_a_continuous_switch_whose_function_rests_on_zero_solves():
    # (Max(x, 0) at x = 0 moves the states alike on both branches: no error)
    m = dm.Model("resting_max")
    m.states("x y")
    m.ode("x", "0")
    m.ode("y", "1 + Max(x, 0)")
    m.initial(x=0.0, y=0.0)
    sol = dm.solve(m, (0.0, 1.0), method="radau", rtol=1e-8, atol=1e-8)
    assert sol.status == "success" and abs(sol["y"][-1] - 1.0) < 1e-12

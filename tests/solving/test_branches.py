"""Which side an event's or a switch's function goes on to where it is at zero (daemodel/solving/branches.py): a
declared event that crosses too slowly for one look-ahead, and a jump switch whose function rests on zero on both
branches; against the exact crossing times and counts."""

import math

import numpy as np
import pytest

import daemodel as dm
from daemodel import errors as E

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


@pytest.mark.xfail(
    strict=True,
    reason="a side is read against an absolute rounding floor (branches._side: 64 eps max(1, |values|), 1.4e-14): "
    "a ball dropped from 1e-14 never leaves that band, its bounce is never armed, and radau records 1 of its 6 "
    "impacts and lets it fall to -2.3e-13 (23 atol below the floor), 'success'; the reference and casadi-idas "
    "record all 6",
)
def test_a_ball_in_units_below_the_rounding_floor_bounces_or_is_refused():
    g, x0, e, span = 9.81, 1e-14, 0.8, 3e-7
    m = dm.Model("tiny_ball")
    m.states("x v")
    m.ode("x", "v")
    m.ode("v", f"-{g!r}")
    m.event("floor", "x", direction=-1, reset={"v": f"-{e!r}*v"})
    m.initial(x=x0, v=0.0)
    first = math.sqrt(2 * x0 / g)
    exact = first + np.concatenate([[0.0], np.cumsum(2 * first * e ** np.arange(1, 9))])
    try:
        sol = dm.solve(m, (0.0, span), method="radau", rtol=1e-10, atol=1e-14)
    except E.EventLimitError:  # (refused by name: acceptable)
        return
    if sol.status == "success":
        np.testing.assert_allclose(sol.events["floor"]["t"].ravel(), exact[exact < span], rtol=1e-6)
        assert sol["x"].min() > -1e-14


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

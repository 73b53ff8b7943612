"""Events and switches past their design (issue 40): accumulating events (Zeno), the branch after a
crossing (never the switch's value at zero), floor of a state, sliding modes, a crossing exactly at a
step end, a switch at zero where the solve starts, flights shorter than a step; every method, against
exact piecewise solutions, and a property test over random switches and balls."""

import math
import re

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

import daemodel as dm
from daemodel import errors as E

# radau's default on casadi's virtual machine, but in the tests marked machine_code (tests/conftest.py)
pytestmark = pytest.mark.virtual_machine

G = 9.81
METHODS = [
    ("radau", {"rtol": 1e-8, "atol": 1e-8}),
    ("radau", {"stages": 3, "h": 0.01}),
    ("casadi-idas", {}),
    ("casadi-collocation", {}),
    ("reference", {}),
]


def _ball(e=0.8, h0=1.0):
    m = dm.Model("ball")
    m.states("h v")
    m.ode("h", "v")
    m.ode("v", f"-{G}")
    m.initial(h=h0, v=0.0)
    m.event("floor", "h", direction=-1, reset={"v": f"-{e}*v"})
    return m


def _accumulation(e=0.8, h0=1.0) -> float:
    """Where the ball's impacts accumulate: the first fall, then flights 2 v_k / g with v_k = e^k v_0."""
    v0 = math.sqrt(2.0 * G * h0)
    return math.sqrt(2.0 * h0 / G) + 2.0 * e * v0 / (G * (1.0 - e))


def _ball_exact(t: float, e: float, h0: float = 1.0) -> float:
    """The ball's height at ``t`` before its accumulation point."""
    start, v = math.sqrt(2.0 * h0 / G), math.sqrt(2.0 * G * h0)
    if t <= start:
        return h0 - 0.5 * G * t * t
    while True:
        v *= e
        flight = 2.0 * v / G
        if t <= start + flight:
            s = t - start
            return v * s - 0.5 * G * s * s
        start += flight


@pytest.mark.machine_code
@pytest.mark.parametrize(("method", "options"), METHODS)
def test_zeno_stops_at_the_accumulation_point_in_every_method(method, options):
    # (before: "success" with the ball 4-9 m below the floor at t = 5 in every method)
    message = (
        r"event 'floor' accumulates at t ≈ 4\.0637\d*: its last 5 gaps shrink by 0\.8 each.*end t_span before "
        r"t ≈ 4\.0637\d*, or make the event terminal=True"
    )
    with pytest.raises(E.ZenoError, match=message) as caught:
        dm.solve(_ball(), (0.0, 5.0), method=method, **options)
    assert abs(caught.value.t - _accumulation()) < 1e-8
    assert isinstance(caught.value, E.EventLimitError)  # (the documented chattering error)


def test_zeno_in_the_pinn():
    with pytest.raises(E.ZenoError) as caught:
        dm.solve(_ball(), (0.0, 5.0), method="pinn", h=0.1)
    assert abs(caught.value.t - _accumulation()) < 1e-8


def test_a_reset_that_leaves_the_ball_on_the_floor_is_refused():
    # (restitution 0: after the reset the ball rests on the guard; its event would fire again at once)
    with pytest.raises(E.ZenoError, match=r"event 'floor' at t = 0\.4515\d*: after its reset h stays on the guard"):
        dm.solve(_ball(e=0.0), (0.0, 1.0), rtol=1e-8, atol=1e-8)


@pytest.mark.parametrize("h", [0.2, 0.5])
def test_flights_shorter_than_a_step_are_all_seen(h):
    # e = 0.5: flights 0.45, 0.23, 0.11, 0.056 s, each shorter than the step after the first
    sol = dm.solve(_ball(e=0.5), (0.0, 1.3), stages=3, h=h)
    t = sol.events["floor"]["t"][0]
    expected, start, v = [], math.sqrt(2.0 / G), math.sqrt(2.0 * G)
    while start < 1.3:
        expected.append(start)
        v *= 0.5
        start += 2.0 * v / G
    assert len(t) == len(expected) and np.abs(t - expected).max() < 1e-11
    assert abs(sol["h"][-1] - _ball_exact(1.3, 0.5)) < 1e-11


def _heaviside(x0=0.0):
    m = dm.Model("heaviside")
    m.states("x y")
    m.algebraics("z")
    m.ode("x", "1")
    m.ode("y", "Heaviside(0.5 - x)")
    m.constraint("z - Heaviside(x - 0.5)")
    m.initial(x=x0, y=0.0)
    return m


@pytest.mark.parametrize(("method", "options"), [*METHODS, ("radau", {"stages": 3, "h": 0.05}), ("pinn", {"h": 0.1})])
def test_the_branch_after_a_state_switch(method, options):
    # (before: y(1) = 0.75 and z = 0.5 after the crossing, from H(0) = 1/2, in every method; h = 0.05 puts the
    # crossing exactly on a step end)
    sol = dm.solve(_heaviside(), (0.0, 1.0), method=method, **options)
    assert sol.status == "success"
    assert abs(sol["y"][-1] - 0.5) < 1e-10 and abs(sol["z"][-1] - 1.0) < 1e-12
    np.testing.assert_allclose(sol.at([0.25, 0.75])["z"], [0.0, 1.0], atol=1e-12)


@pytest.mark.parametrize(("method", "options"), METHODS[:3])
def test_a_switch_at_zero_where_the_solve_starts(method, options):
    # x(0) = 0.5: the switches are at zero at t0; the flow (x' = 1) takes x above, so y' = 0 and z = 1 at once
    sol = dm.solve(_heaviside(0.5), (0.0, 1.0), method=method, **options)
    assert sol["y"][-1] == 0.0 or abs(sol["y"][-1]) < 1e-15
    assert np.all(sol["z"] == 1.0)


@pytest.mark.parametrize(
    ("rhs", "exact"),
    [
        # from 0.05: rate 1 to x = 0.5 (t = 0.45), 2 to 1 (0.7), 3 to 1.5 (0.8667), 4 to 2 (0.9917), then 5
        ("1 + floor(2*x)", 2.0 + 5.0 * (1.0 - (0.45 + 0.25 + 0.5 / 3 + 0.125))),
        # ceiling(2x) is 1 + floor(2x) off the integers: the same path
        ("ceiling(2*x)", 2.0 + 5.0 * (1.0 - (0.45 + 0.25 + 0.5 / 3 + 0.125))),
    ],
)
@pytest.mark.parametrize(("method", "options"), METHODS[:3])
def test_floor_and_ceiling_of_a_state_step_at_every_integer(rhs, exact, method, options):
    # (before: x' = 1 + floor(2x) never switched in radau: x(1) = 1.05 with "success"; scipy: 2.0417)
    m = dm.Model("floor")
    m.states("x")
    m.ode("x", rhs)
    m.initial(x=0.05)
    sol = dm.solve(m, (0.0, 1.0), method=method, **options)
    assert abs(sol["x"][-1] - exact) < 1e-9
    assert len(sol.events[next(iter(sol.events))]["t"][0]) == 4


@pytest.mark.machine_code
def test_a_floor_that_goes_down():
    # x' = -1 - floor(x) from 2.5: rate -3 to x = 2 (t = 1/6), -2 to 1 (2/3), -1 to 0 (5/3), then 0: x stays 0
    m = dm.Model("down")
    m.states("x")
    m.ode("x", "-1 - floor(x)")
    m.initial(x=2.5)
    sol = dm.solve(m, (0.0, 2.0), rtol=1e-10, atol=1e-10)
    assert abs(sol["x"][-1]) < 1e-9
    np.testing.assert_allclose(sol.events["floor in x'"]["t"][0], [1 / 6, 2 / 3, 5 / 3], atol=1e-10)


@pytest.mark.parametrize(("method", "options"), [*METHODS, ("pinn", {"h": 0.05})])
def test_a_sliding_mode_in_every_method(method, options):
    # x' = 2 below the line x = t, 0.5 above it: from -0.1, x meets t at 0.1 and slides along it (Filippov:
    # x' = 1 there) (before: "success" with x' = 0.5 throughout, x(1) = 0.55, in every method)
    m = dm.Model("slide")
    m.states("x")
    m.ode("x", "Piecewise((2, x < t), (0.5, True))")
    m.initial(x=-0.1)
    sol = dm.solve(m, (0.0, 1.0), method=method, **options)
    assert sol.status == "success"
    assert abs(sol["x"][-1] - 1.0) < 1e-9 and abs(sol.events["Piecewise in x'"]["t"][0, 0] - 0.1) < 1e-10
    np.testing.assert_allclose(sol.at([0.05, 0.5])["x"], [0.0, 0.5], atol=1e-9)


@pytest.mark.machine_code
def test_a_sliding_motion_that_ends():
    # x' = -sign(x) + 2t - 3 from 1: x = 1 - 4t + t^2 down to 0 at 2 - sqrt(3), through it (both sides push
    # down), x = t^2 - 2t - 3 + 2 sqrt(3) back up to 0 at sqrt(3), where both sides push onto it: it slides
    # until the rate above, 2t - 4, turns at t = 2; then x = (t - 2)^2
    m = dm.Model("exit")
    m.states("x")
    m.ode("x", "-sign(x) + 2*t - 3")
    m.initial(x=1.0)
    sol = dm.solve(m, (0.0, 4.0), rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(sol.events["sign in x'"]["t"][0], [2 - math.sqrt(3), math.sqrt(3), 2.0], atol=1e-9)
    np.testing.assert_allclose(sol.at([1.9, 3.0, 4.0])["x"], [0.0, 1.0, 4.0], atol=1e-8)


@pytest.mark.parametrize("method", ["radau", "casadi-idas", "reference"])
def test_a_sliding_motion_along_a_switch_with_a_switch_inside_it(method):
    # x' = -sign(|x| - 1) + t/2 from 1.5: x = 1.5 - t + t^2/4 down to 1 at 2 - sqrt(2), slides along |x| = 1 until
    # the rate above, t/2 - 1, turns at t = 2, then x = 1 + (t - 2)^2/4.  The sliding motion differentiated
    # sign's function as written: d|x|/dx is sympy's Derivative(im(x), x) for a symbol not known real, and the
    # printer raised PrintMethodNotImplementedError (no named error) in every method
    m = dm.Model("nested-slide")
    m.states("x")
    m.ode("x", "-sign(Abs(x) - 1) + t/2")
    m.initial(x=1.5)
    sol = dm.solve(m, (0.0, 3.0), method=method, rtol=1e-10, atol=1e-10)
    assert sol.status == "success"
    np.testing.assert_allclose(sol.events["sign in x'"]["t"][0], [2 - math.sqrt(2), 2.0], atol=1e-8)
    np.testing.assert_allclose(sol.at([0.3, 1.5, 3.0])["x"], [1.5 - 0.3 + 0.0225, 1.0, 1.25], atol=1e-8)


def test_a_sliding_mode_daemodel_does_not_integrate_is_refused():
    # the switching function is an algebraic variable: the sliding motion would move it through the constraint
    m = dm.Model("refused")
    m.states("x")
    m.algebraics("z")
    m.ode("x", "-sign(z)")
    m.constraint("z + z**3 - x")
    m.initial(x=1.0)
    with pytest.raises(
        E.SlidingModeError,
        match=r"switch 'sign in x'' at t = 1(\.0+\d*)?: neither branch goes on: above zero z turns back down.*"
        r"daemodel integrates only where the switching function is of t and the states",
    ) as caught:
        dm.solve(m, (0.0, 2.0), rtol=1e-8, atol=1e-8)
    assert abs(caught.value.t - 1.0) < 1e-9


def test_a_repelling_switch_keeps_the_side_it_crossed_to():
    # x' = sign(x) + 2 crosses 0 upwards at t = 1/3 from x = -1 (rate 1), then goes on at rate 3
    m = dm.Model("repel")
    m.states("x")
    m.ode("x", "sign(x) + 2")
    m.initial(x=-1.0)
    sol = dm.solve(m, (0.0, 2.0), rtol=1e-10, atol=1e-10)
    assert abs(sol["x"][-1] - 3.0 * (2.0 - 1.0)) < 1e-9


@pytest.mark.machine_code
def test_the_event_machinery_is_inside_the_clocks():
    import time

    started = time.perf_counter()
    sol = dm.solve(_heaviside(), (0.0, 1.0), rtol=1e-8, atol=1e-8)
    wall = time.perf_counter() - started
    assert sol.setup_time + sol.solve_time >= 0.5 * wall  # (before: 0.23 s of 2.97 s on the thermostat)


@pytest.mark.machine_code
def test_event_functions_code_made_at_first_use_is_setup(monkeypatch):
    """Code made once (the event functions' numpy code, printed at their first use inside the events'
    loop) is setup, as compiling is (issue 42): measured by slowing each such making down by a known
    DELAY each (7 makings a solve).  Before, all of it landed on the solve's clock (radau's first solve of the
    bouncing ball: 62.6 ms of CPU against 23.7 ms for the next ones, 39 ms of it the events' numpy code).
    DELAY = 1 s: the solve itself took up to 0.44 s on 2 cores at load 13 (0.3 s was too tight there)."""
    import time

    from daemodel.compiling import batch_function
    from daemodel.problems import PROBLEMS

    DELAY = 1.0
    made = batch_function.BatchFunction.__init__

    def slow_init(self, exprs, symbols, lambdify):
        def slow(exprs):
            time.sleep(DELAY)
            return lambdify(exprs)

        made(self, exprs, symbols, slow)

    monkeypatch.setattr(batch_function.BatchFunction, "__init__", slow_init)
    for method in ("radau", "reference"):
        problem = PROBLEMS["bouncing-ball"]
        sol = dm.solve(problem.model(), problem.t_span, method=method, rtol=1e-6, atol=1e-8)
        assert sol.stats["events"] >= 1 and sol.setup_time >= DELAY and sol.solve_time < DELAY, (method, sol)


# ---- a property test: random piecewise-linear switches and bouncing balls --------------------------


def _linear_exact(x0, a, b, c, t1):
    """x' = a below c, b at or above it: x(t1), sliding along x = c where both sides push onto it."""
    rate = a if x0 < c else b
    if x0 == c:
        rate = b if b > 0 else (a if a < 0 else None)
        if rate is None:
            return c
    reach = (c - x0) / rate if (c - x0) * rate > 0 else math.inf
    if reach >= t1:
        return x0 + rate * t1
    after = b if rate > 0 else a  # (the branch on the far side)
    if (rate > 0 and after < 0) or (rate < 0 and after > 0):
        return c  # (Filippov: x' = 0 on the switch)
    return c + after * (t1 - reach)


@settings(max_examples=40, derandomize=True, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    x0=st.floats(-2.0, 2.0),
    a=st.floats(-3.0, 3.0).filter(lambda v: abs(v) > 0.05),
    b=st.floats(-3.0, 3.0).filter(lambda v: abs(v) > 0.05),
    c=st.floats(-1.0, 1.0),
    t1=st.floats(0.1, 3.0),
    how=st.sampled_from(["Piecewise", "Heaviside"]),
)
def test_property_piecewise_linear_switches(x0, a, b, c, t1, how):
    m = dm.Model("pl")
    m.states("x")
    if how == "Piecewise":
        m.ode("x", f"Piecewise(({a!r}, x < {c!r}), ({b!r}, True))")
    else:
        m.ode("x", f"{a!r} + ({b!r} - {a!r})*Heaviside(x - {c!r})")
    m.initial(x=x0)
    value = _linear_exact(x0, a, b, c, t1)
    try:
        sol = dm.solve(m, (0.0, t1), rtol=1e-10, atol=1e-10)
    except E.DaemodelError as error:  # (a refusal must be named: DaemodelError covers every named error)
        pytest.fail(f"refused: {type(error).__name__}: {error}")
    assert sol.status == "success"
    assert abs(sol["x"][-1] - value) < 1e-8 * max(1.0, abs(value))


@pytest.mark.machine_code
@settings(max_examples=25, derandomize=True, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(e=st.floats(0.05, 0.95), h0=st.floats(0.1, 2.0), t1=st.floats(0.2, 8.0))
def test_property_bouncing_balls(e, h0, t1):
    limit = _accumulation(e, h0)
    try:
        sol = dm.solve(_ball(e, h0), (0.0, t1), rtol=1e-10, atol=1e-10)
    except E.ZenoError as error:
        # (the gaps' extrapolation, or where the flights fall below the look-ahead and the ball rests)
        assert limit < t1 and abs(error.t - limit) < 1e-5 * max(1.0, limit)
        return
    assert limit >= t1 - 1e-6, f"success past the accumulation point {limit}"
    assert sol.status == "success"
    assert abs(sol["h"][-1] - _ball_exact(t1, e, h0)) < 1e-7


@pytest.mark.parametrize(("switch", "level"), [(0.76, 1.6), (1.0, 1.6), (0.76, 2.0)])
def test_an_event_and_a_time_switch_on_sparse_output_times(switch, level):
    # (before: TimeSpanError "t_eval must hold at least one finite time" where a piece's last segment held none)
    m = dm.Model("sparse")
    m.states("x")
    m.ode("x", f"1 + Heaviside(t - {switch})")
    m.initial(x=0.0)
    m.event("mark", f"x - {level}")
    sol = dm.solve(m, (0.0, 1.5), t_eval=[0.0, 0.75, 1.5], rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(sol["x"], [0.0, 0.75, switch + 2.0 * (1.5 - switch)], atol=1e-9)
    crossing = switch + (level - switch) / 2.0
    assert len(sol.events["mark"]["t"][0]) == (crossing < 1.5)


def test_a_batch_whose_samples_end_at_their_own_terminal_events():
    # (before: SwitchError "the samples of this batch end at different times")
    m = dm.Model("drop")
    m.states("h v")
    m.ode("h", "v")
    m.ode("v", f"-{G}")
    m.initial(h=1.0, v=0.0)
    m.event("floor", "h", direction=-1, terminal=True)
    grid = np.linspace(0.0, 0.5, 6)
    sol = dm.solve(m, (0.0, 0.5), t_eval=grid, y0={"h": [1.0, 2.0], "v": [0.0, 0.0]}, rtol=1e-10, atol=1e-10)
    first = math.sqrt(2.0 / G)  # (sample 0 lands then; sample 1, from 2 m, is still falling at 0.5)
    np.testing.assert_allclose(sol.stats["t_end"], [first, 0.5], atol=1e-10)
    np.testing.assert_allclose(sol.t, np.sort([*grid, first]), rtol=0, atol=1e-10)
    exact = np.array([h0 - 0.5 * G * sol.t**2 for h0 in (1.0, 2.0)])
    exact[0, sol.t > first + 1e-12] = np.nan
    np.testing.assert_allclose(sol["h"], exact, atol=1e-9)
    assert np.isnan(sol.at([0.48])["h"][0, 0]) and abs(sol.at([0.48])["h"][1, 0] - (2.0 - 0.5 * G * 0.48**2)) < 1e-9


# ---- found by review ------------------------------------------------------------------------------


@pytest.mark.parametrize(("method", "options"), METHODS)
def test_a_reset_that_moves_the_function_off_its_guard(method, options):
    # a sawtooth: x back to 0 and v doubled at x = 1 (the function is -1 after the reset: not on the guard)
    m = dm.Model("saw")
    m.states("x v")
    m.ode("x", "v")
    m.ode("v", "0")
    m.initial(x=0.0, v=1.0)
    m.event("top", "x - 1", direction=1, reset={"x": "0", "v": "2*v"})
    sol = dm.solve(m, (0.0, 1.6), method=method, **options)
    assert abs(sol["x"][-1] - 0.4) < 1e-9 and abs(sol["v"][-1] - 4.0) < 1e-10  # (collocation: v to 4e-12)


@pytest.mark.parametrize("span", [120.0, pytest.param(1000.0, marks=pytest.mark.slow)])
@pytest.mark.parametrize("method", ["reference", "casadi-idas"])
def test_flights_on_a_long_span_are_each_located(method, span):
    # (before: "success" with h(1000) = -4.9e6, the first impact found twice and the ball through the floor:
    # the first trial after an impact sat within the integrator's error of the floor)
    sol = dm.solve(_ball(e=1.0), (0.0, span), method=method, max_events=2000)
    flight = 2.0 * math.sqrt(2.0 / G)
    expected = math.sqrt(2.0 / G) + flight * np.arange(len(sol.events["floor"]["t"][0]))
    assert len(expected) == math.floor((span - math.sqrt(2.0 / G)) / flight) + 1
    assert np.abs(sol.events["floor"]["t"][0] - expected).max() < 1e-6


@pytest.mark.parametrize(("rhs", "event"), [("floor(2*x)", None), ("0", "x - 1")])
def test_an_event_exactly_at_the_end_of_the_span(rhs, event):
    # 2x reaches 3 (x - 1 reaches 0) exactly at t1 (before: InvalidOptionError "h must be positive" at h = 0.05)
    m = dm.Model("end")
    m.states("x y")
    m.ode("x", "1")
    m.ode("y", rhs)
    m.initial(x=0.5 if event is None else 0.0, y=0.0)
    if event is not None:
        m.event("one", event, reset={"y": "1"})
    sol = dm.solve(m, (0.0, 1.0), stages=3, h=0.05)
    assert sol.t[-1] == 1.0 and abs(sol["y"][-1] - (1.5 if event is None else 1.0)) < 1e-12


@pytest.mark.parametrize("t1", [1.5, 10.0])
def test_zeno_reports_the_accumulation_point_whichever_check_fires(t1):
    # e = 0.5: on (0, 1.5) the ball comes to rest on the floor before the gaps are small enough; the error's t
    # is still the accumulation point (before: the bounce time, 5.6e-5 off)
    with pytest.raises(E.ZenoError) as caught:
        dm.solve(_ball(e=0.5), (0.0, t1), rtol=1e-10, atol=1e-10)
    assert abs(caught.value.t - _accumulation(0.5)) < 1e-9


@pytest.mark.parametrize(("method", "options"), METHODS)
def test_a_switch_a_hair_after_the_start(method, options):
    # the crossing 1e-10 after t0: its trial solves are shorter than a method's own grid resolves, so each is one
    # step (before the fix adaptive radau refused the fixed h it was given beside its rtol)
    m = dm.Model("hair")
    m.states("x y")
    m.ode("x", "1")
    m.ode("y", "Heaviside(x - 0.5)")
    m.initial(x=0.5 - 1e-10, y=0.0)
    sol = dm.solve(m, (0.0, 1.0), method=method, **options)
    tol = 1e-6 if method == "casadi-idas" else 1e-9  # (IDAS at its default rtol 1e-6)
    assert abs(sol["y"][-1] - 1.0) < tol and abs(sol.events["Piecewise in y'"]["t"][0, 0] - 1e-10) < tol


def _humps(c=0.99, event=None):
    """s = sin t; w' = the part of s above c: humps 2 acos(c) long (0.283 s at 0.99), 2 pi apart.
    ``event``: a declared event on 0.99 - s ... instead (``direction``), counting its crossings in n."""
    m = dm.Model("humps")
    m.states("s c w n")
    m.ode("s", "c")
    m.ode("c", "-s")
    m.ode("w", f"(s - {c})*Heaviside(s - {c})" if event is None else "0")
    m.ode("n", "0")
    m.initial(s=0.0, c=1.0, w=0.0, n=0.0)
    if event is not None:
        m.event("hump", f"{c} - s", direction=event, reset={"n": "n + 1"})
    return m


def _hump_times(c: float, t1: float) -> np.ndarray:
    """Where sin t crosses c before t1: up at pi/2 - acos(c), down at pi/2 + acos(c), every 2 pi."""
    k = 2.0 * math.pi * np.arange(int(t1 / (2.0 * math.pi)) + 2)
    times = np.sort(np.concatenate([math.pi / 2 - math.acos(c) + k, math.pi / 2 + math.acos(c) + k]))
    return times[times < t1]


def _humps_exact(c: float, t1: float) -> float:
    """The integral of max(sin t - c, 0) over [0, t1] (the last hump cut at t1)."""
    times = np.append(_hump_times(c, t1), t1)
    up, down = times[0:-1:2], times[1::2]
    return float(np.sum(np.cos(up) - np.cos(down) - c * (down - up)))


@pytest.mark.machine_code
@pytest.mark.parametrize("c", [0.99, 0.9999])
@pytest.mark.parametrize(
    "method, options, t1, t_tol, w_tol",
    [
        ("radau", {"rtol": 1e-10, "atol": 1e-10}, 10.0, 1e-11, 1e-12),  # (steps of 0.57: two crossings each)
        ("radau", {"rtol": 1e-4}, 100.0, 1e-2, 1e-2),
        ("radau", {"stages": 5, "h": 0.5}, 10.0, 1e-8, 1e-11),
        ("casadi-collocation", {}, 10.0, 1e-6, 1e-8),
        # (IDAS's own error in w, 1000x rtol: 8.9e-8 with one output a second; 1.10e-7 since its search restarts
        # the trial solves that locate each of the 64 crossings from an output about half a step before it (6b9dcca),
        # 1.23x at every t1 from 60 to 120: a measured loss, traded for 956 of 956 humps found at rtol 1e-7, not 14)
        ("casadi-idas", {"rtol": 1e-10, "atol": 1e-10}, 100.0, 1e-5, 1.5e-7),
        ("reference", {}, 10.0, 1e-6, 1e-8),
    ],
)
def test_a_switch_crossed_and_crossed_back_within_a_step_is_seen(c, method, options, t1, t_tol, w_tol):
    # the part of sin t above c, between outputs that are both below it (before: radau at rtol 1e-10 saw 2 of the
    # 4 crossings, w 1.9e-3 off; casadi-idas 14 of 32, with status "success")
    sol = dm.solve(_humps(c), (0.0, t1), method=method, t_eval=[0.0, t1], **options)
    found, exact = sol.events["Piecewise in w'"]["t"][0], _hump_times(c, t1)
    assert sol.status == "success" and len(found) == len(exact)
    assert np.abs(found - exact).max() < t_tol
    assert abs(sol["w"][-1] - _humps_exact(c, t1)) < w_tol


@pytest.mark.parametrize("direction", [1, -1])
@pytest.mark.parametrize(
    "method, options", [("radau", {"rtol": 1e-10, "atol": 1e-10}), ("casadi-idas", {"rtol": 1e-10, "atol": 1e-10})]
)
def test_an_event_whose_direction_is_the_way_back_is_located(direction, method, options):
    # 0.99 - sin t is positive at the outputs about each hump: a falling event is its first crossing, a rising one
    # the crossing back (an excursion whose first crossing the direction refuses)
    t1 = 10.0 if method == "radau" else 40.0
    sol = dm.solve(_humps(event=direction), (0.0, t1), method=method, t_eval=[0.0, t1], **options)
    exact = _hump_times(0.99, t1)[(0 if direction == -1 else 1) :: 2]
    found = sol.events["hump"]["t"][0]
    assert len(found) == len(exact) and np.abs(found - exact).max() < 1e-6
    assert sol["n"][-1] == len(exact)


@pytest.mark.parametrize(
    "method, options",
    [("radau", {"rtol": 1e-10, "atol": 1e-10}), ("radau", {"rtol": 1e-6}), ("radau", {"h": 0.5})],
)
def test_a_switch_the_solution_only_touches_makes_no_event(method, options):
    # sin t touches 1 at its peaks and never exceeds it: an extremum at zero, inside the method's error of it, is
    # no crossing (no event, w stays 0)
    sol = dm.solve(_humps(1.0), (0.0, 30.0), method=method, **options)
    assert sol.status == "success" and len(sol.events["Piecewise in w'"]["t"][0]) == 0 and sol["w"][-1] == 0.0
    # a declared event on 1 - sin t: the dense output goes past 1 at a peak and stops the search, the trial solve
    # does not, and the search goes on from there, the outputs as one solve's.  (At rtol 1e-10 whether the
    # polynomial passes 1, by ~1e-11, is rounding: one machine's did at a peak, another's at none)
    sol = dm.solve(_humps(1.0, event=0), (0.0, 30.0), method=method, **options)
    assert len(sol.events["hump"]["t"][0]) == 0 and sol["n"][-1] == 0.0
    # (a touch within the method's error: "success" until the check of crossings within it (solving/undecided.py),
    # which cannot tell it from a crossing by less than its error, 1e-10 deep: that one says it is undecided)
    assert sol.status == "success" or all(
        part.startswith("event 'hump' does not cross zero between") and part.endswith("tighten rtol/atol")
        for part in re.split(r"; (?=event ')", sol.status)
    ), sol.status
    assert (sol.stats["searches_continued"] >= 1 or options.get("rtol") == 1e-10) and np.all(np.diff(sol.t) > 0)
    assert np.abs(sol["s"] - np.sin(sol.t)).max() < (0.1 if "h" in options else 100 * options["rtol"])


@pytest.mark.parametrize("c", [0.99998, 0.99999])
def test_a_narrow_hump_at_a_tight_rtol_with_five_stages_is_seen(c):
    # a hump 1e-5 deep and 0.0089 wide whose peak falls 0.01 after an output (rtol 1e-11, five stages): the extremum
    # at a scan's first sample, its left neighbour in the scan before, was never looked into and the hump was
    # integrated through with "success" (4 of 6 crossings, w 1.193e-7 against 1.789e-7; found by hypothesis in
    # test_humps_of_any_width_are_each_seen)
    t1 = 20.0
    sol = dm.solve(_humps(c), (0.0, t1), rtol=1e-11, atol=1e-11, stages=5, t_eval=[0.0, t1])
    found, exact = sol.events["Piecewise in w'"]["t"][0], _hump_times(c, t1)
    assert len(found) == len(exact) == 6 and np.abs(found - exact).max() < 1e-9
    assert abs(sol["w"][-1] - _humps_exact(c, t1)) < 1e-9


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@example(c=0.99999, rtol=1e-5, stages=3)  # (the humps' w below rtol: integrated through)
@given(
    c=st.floats(0.9, 0.99999),
    rtol=st.sampled_from([1e-5, 1e-7, 1e-9, 1e-11]),
    stages=st.sampled_from([3, 5, 7]),
)
def test_humps_of_any_width_are_each_seen(c, rtol, stages):
    # every hump of sin t above c, however narrow against radau's steps (2 acos(c): 0.9 down to 0.0089 wide), is
    # two events at their exact times and w is its exact integral, within the tolerance; a hump whose whole w is
    # below it over a step (depth 1 - c times the step, in atol + rtol |y|) may be integrated on the branch below
    sol = dm.solve(_humps(c), (0.0, 20.0), rtol=rtol, atol=rtol, stages=stages, t_eval=[0.0, 20.0])
    found, exact = sol.events["Piecewise in w'"]["t"][0], _hump_times(c, 20.0)
    assert sol.status == "success" and len(found) <= len(exact)
    assert len(found) == len(exact) or 1.0 - c < 1e3 * rtol  # (a hump 1e3 rtol deep changes w past rtol in a step)
    near = np.abs(found[:, None] - exact[None, :]).min(axis=1)  # (each found one at an exact crossing)
    assert np.all(near < 1e3 * rtol / math.sqrt(1.0 - c**2))  # (the crossing's slope: sqrt(1 - c^2))
    assert abs(sol["w"][-1] - _humps_exact(c, 20.0)) < 100 * rtol


@pytest.mark.parametrize("flat", ["x**3", "x**5", "tanh(x)**3"])
@pytest.mark.parametrize("beside", [False, True])
@pytest.mark.parametrize("rtol", [1e-4, 1e-8])
def test_a_flat_root_is_located(flat, beside, rtol):
    # x = 0.7 - t: the event function's root at t = 0.7 is triple (quintuple), alone or declared before x's own
    # crossing at the same instant (before: EventLocationError after 100 trial solves, the secant creeping 1e-14 a
    # trial from the end next to the root; the slow fuzz corpus's r1-0042 crosses tanh(y)^3 and y at once)
    m = dm.Model("flat")
    m.states("x n k")
    m.ode("x", "-1")
    m.ode("n", "0")
    m.ode("k", "0")
    m.initial(x=0.7, n=0.0, k=0.0)
    m.event("flat", flat, reset={"n": "n + 1"})
    if beside:
        m.event("plain", "x", reset={"k": "k + 1"})
    sol = dm.solve(m, (0.0, 2.0), rtol=rtol, atol=rtol)
    assert sol.status == "success" and abs(sol.events["flat"]["t"][0, 0] - 0.7) < 1e-11
    assert sol["n"][-1] == 1.0 and sol["k"][-1] == (1.0 if beside else 0.0) and sol.stats["location_trials"] <= 100


def test_searches_that_stop_for_nothing_are_bounded_by_max_events():
    # each search stopped at a peak of sin t past 1 on the dense output but not in the method's own solution goes
    # on from there; more of them than max_events is an error that says so
    with pytest.raises(
        E.EventLimitError,
        match=r"1 crossings of zero on the dense output that the method's own solution does not confirm, by t = "
        r"[0-9.]+ \(max_events = 0\): the event functions graze zero within the method's error that often",
    ):
        dm.solve(_humps(1.0, event=0), (0.0, 30.0), rtol=1e-6, max_events=0)


# ---- found by attacking the events as a hostile user (helper evatk) --------------------------------------


@pytest.mark.parametrize(("method", "options"), METHODS)
def test_an_event_of_an_algebraic_variable_with_a_reset_of_another_state(method, options):
    # z = x^2 - 1/4 falls through 0 at t = ln 2 (x = e^-t); the reset counts it in c, which z does not
    # depend on. Before: ZenoError "after its reset z stays on the guard" in adaptive radau and IDAS: the
    # drift before the reset started from the method's z (8e-14 off its constraint, against a drift of 1e-9
    # over the look-ahead), the one after from the z solved anew, so the reset seemed to change the motion
    m = dm.Model("count")
    m.states("x c")
    m.algebraics("z")
    m.ode("x", "-x")
    m.ode("c", "0")
    m.constraint("z - x**2 + 0.25", name="zdef")
    m.initial(x=1.0, c=0.0)
    m.event("zz", "z", direction=-1, reset={"c": "c + 1"})
    sol = dm.solve(m, (0.0, 2.0), method=method, **options)
    tol = 1e-6 if method == "casadi-idas" else 1e-9
    assert sol.status == "success" and abs(sol["c"][-1] - 1.0) < 1e-9  # (collocation: c' = 0 to 2e-13)
    assert abs(sol.events["zz"]["t"][0, 0] - math.log(2.0)) < tol
    assert np.abs(sol["x"] - np.exp(-sol.t)).max() < tol


@pytest.mark.parametrize(("method", "options"), METHODS)
def test_an_event_function_that_rests_on_zero_before_it_crosses(method, options):
    # (before: located wherever a trial landed on the flat zero, all 'success': radau rtol 1e-8 at 1.99119609,
    # h = 0.01 at 1.99605469, IDAS, collocation and the reference at 1.99804687; the crossing is at t = 2)
    m = dm.Model("rest")
    m.states("x y")
    m.ode("x", "1")
    m.ode("y", "0")
    m.initial(x=0.0, y=0.0)
    m.event("f", "Min(x - 1, 0) + Max(x - 2, 0)", direction=1, reset={"y": "t"})  # (-1 ... 0 on [1, 2] ... +1)
    sol = dm.solve(m, (0.0, 3.0), method=method, **options)
    assert sol.status == "success" and sol.events["f"]["t"].shape == (1, 1)
    assert abs(sol.events["f"]["t"][0, 0] - 2.0) < 1e-9 and abs(sol["y"][-1] - 2.0) < 1e-9


@pytest.mark.parametrize(("method", "options"), METHODS)
def test_a_reset_to_a_value_that_is_not_finite_is_named(method, options):
    # log(v - 1) at v = 1 (before: radau "the Newton matrix is singular ... a stiff mode", the reference a bare
    # ValueError from scipy about its y0)
    m = dm.Model("nanreset")
    m.states("x v")
    m.ode("x", "1")
    m.ode("v", "0")
    m.initial(x=0.0, v=1.0)
    m.event("e", "x - 0.5", reset={"v": "log(v - 1)"})
    # (v = 1 to the method's rounding: log(0) = -inf, or log of a hair below 0, nan)
    with pytest.raises(E.InvalidValueError, match=r"event 'e' at t = 0\.5\d*: its reset sets 'v' to (-inf|nan) \(log"):
        dm.solve(m, (0.0, 1.0), method=method, **options)


@pytest.mark.parametrize("method", ["radau", "casadi-idas", "reference"])
def test_events_in_a_span_much_shorter_than_1_are_located_on_its_scale(method):
    """x' = (1 + Heaviside(x - 0.5))/w over (0, w), w = 1e-12, an event at x = 1.2 resets x to 0.1: the switch at
    w/2, the event at 0.85 w, x(t1) = 0.25.  The location's width in t was 1e-12 max(1, ...), the whole span:
    radau put the event "at t1" (x(t1) = 0.1, "success"), casadi-idas and the reference looked ahead 100 times
    that past the switch (ZenoError at t = 0)."""
    w = 1e-12
    m = dm.Model("brief")
    m.states("x")
    m.parameter("w", w)
    m.ode("x", "(1 + Heaviside(x - 0.5))/w")
    m.initial(x=0.0)
    m.event("e", "x - 1.2", reset={"x": "0.1"})
    sol = dm.solve(m, (0.0, w), method=method, rtol=1e-8, atol=1e-8)
    assert sol.status == "success"
    assert abs(sol.events["e"]["t"][0, 0] / w - 0.85) < 1e-6 and abs(sol["x"][-1] - 0.25) < 1e-6
    assert abs(sol.events["Piecewise in x'"]["t"][0, 0] / w - 0.5) < 1e-6


@pytest.mark.parametrize("method", ["radau", "casadi-idas", "reference"])
def test_events_in_a_span_of_a_few_float64_spacings_are_flagged_or_named(method):
    """The same model over (1000, 1000 + 1e-12), 9 float64 spacings of t: no method can locate its events there.
    Before, casadi-idas raised a bare ZeroDivisionError (a trial solve from a to a, divided by its span), the
    reference ZenoError "within 0 of its last crossing"; radau flags the event it cannot resolve."""
    w = 1e-12
    m = dm.Model("brief")
    m.states("x")
    m.parameter("w", w)
    m.ode("x", "(1 + Heaviside(x - 0.5))/w")
    m.initial(t=1000.0, x=0.0)
    m.event("e", "x - 1.2", reset={"x": "0.1"})
    if method == "radau":
        with pytest.warns(E.EventResolutionWarning):
            sol = dm.solve(m, (1000.0, 1000.0 + w), method=method, rtol=1e-8, atol=1e-8)
        assert sol.status.startswith("flagged: event 'e'")
        return
    with pytest.raises(E.EventLocationError, match=r"at t = 1000: float64 holds no time between it and the next out"):
        dm.solve(m, (1000.0, 1000.0 + w), method=method, rtol=1e-8, atol=1e-8)


@pytest.mark.parametrize(("method", "options"), METHODS)
def test_a_reset_to_a_max_of_a_value_that_is_not_finite_is_named(method, options):
    # Max(-0.8 v, sqrt(h - 2)) at the floor: sqrt of -2 is nan, which numpy's maximum passes on; casadi's fmax,
    # which evaluates a reset's one sample since eff7d0c, dropped it: v = 3.54 after the impact, "success"
    m = dm.Model("maxnanreset")
    m.states("h v")
    m.ode("h", "v")
    m.ode("v", "-9.81")
    m.initial(h=1.0, v=0.0)
    m.event("floor", "h", direction=-1, reset={"v": "Max(-0.8*v, sqrt(h - 2))"})
    with pytest.raises(E.InvalidValueError, match=r"event 'floor' at t = 0\.4515\d*: its reset sets 'v' to nan \(Max"):
        dm.solve(m, (0.0, 1.0), method=method, **options)


@pytest.mark.parametrize(("method", "options"), METHODS)
def test_an_event_function_that_is_not_finite_where_the_solution_goes_is_named(method, options):
    # sqrt(x) - 1/2 with x = 1 - t: NaN past t = 1 (before: a bare ValueError "cannot convert float NaN to integer")
    m = dm.Model("nanwhen")
    m.states("x")
    m.ode("x", "-1")
    m.initial(x=1.0)
    m.event("e", "sqrt(x) - 0.5", direction=-1)
    with pytest.raises(E.SwitchError, match=r"event 'e': its function sqrt\(x\) - 0\.5 is nan at t = .*x = -"):
        dm.solve(m, (0.0, 2.0), method=method, **options)
    sol = dm.solve(m, (0.0, 0.9), method=method, **options)  # (defined up to there: located)
    assert abs(sol.events["e"]["t"][0, 0] - 0.75) < 1e-6


def test_a_floor_that_steps_down_through_zero_in_idas():
    # the step of floor at x = 0 (t = 2): each trial is its own IDAS run, whose error in x (1e-7 at rtol 1e-8)
    # moves with the trial's length, so the function is not monotone in the trial time within a 2.6e-9 bracket
    # (before: EventLocationError after 100 trials; now bisected from trial 24 on, _locate's BISECT_AFTER)
    m = dm.Model("down")
    m.states("x y")
    m.ode("x", "-1")
    m.ode("y", "floor(x)")
    m.initial(x=2.0, y=0.0)
    sol = dm.solve(m, (0.0, 3.0), method="casadi-idas", rtol=1e-8, atol=1e-8)
    assert abs(sol["y"][-1] - 0.0) < 1e-6  # (1 on [0, 1], 0 on [1, 2], -1 on [2, 3])


@pytest.mark.parametrize("method", ["radau", "casadi-collocation", "casadi-idas", "reference"])
@pytest.mark.parametrize(
    ("rate", "x0", "x2", "y2"),
    [
        ("-2*(t - 1)", -0.7, -0.7, 0.0),  # x = 0.3 - (t - 1)^2: touches the switch from below at t = 1
        ("2*(t - 1)", 1.3, 1.3, 2.0),  # x = 0.3 + (t - 1)^2: touches it from above
        ("3*(t - 1)**2", -0.7, 1.3, 1.0),  # x = 0.3 + (t - 1)^3: crosses it at t = 1 with rate 0
    ],
)
def test_a_switching_function_that_touches_zero_at_a_grid_point(method, rate, x0, x2, y2):
    # t = 1 is a grid point of collocation's default h, where its x is a rounding off 0.3: a crossing is located
    # there, and the flow's look-ahead (2e-9) moves x by (2e-9)^2, below rounding on both branches.  The side the
    # switch "crossed to" was kept: above, for the touch from below, whose return raised ZenoError ("does not
    # leave zero to the side the flow takes").  The look-ahead now grows until the motion is resolved
    m = dm.Model("touch")
    m.states("x y")
    m.ode("x", rate)
    m.ode("y", "Heaviside(x - 0.3)")
    m.initial(x=x0, y=0.0)
    tolerances = {} if method == "casadi-collocation" else {"rtol": 1e-8, "atol": 1e-8}
    sol = dm.solve(m, (0.0, 2.0), method=method, **tolerances)
    assert sol.status == "success"
    # (y is ill-conditioned in x where the switch's function has a multiple root: an error d in x moves a
    # crossing by d^(1/2) at a touch, d^(1/3) at the cubic; collocation's x at its default h is ~1e-10 off)
    bound = 1e-2 if rate.startswith("3") else (1e-4 if method == "casadi-collocation" else 1e-8)
    assert abs(sol["x"][-1] - x2) < 1e-6 and abs(sol["y"][-1] - y2) < bound


@pytest.mark.parametrize(("method", "options"), [("radau", {"h": 0.005}), ("reference", {"rtol": 1e-8, "atol": 1e-8})])
def test_a_touch_at_the_end_of_t_span(method, options):
    # x = 0.3 - (t - 1)^2 touches the switch at t1 = 1: a crossing is located a rounding before it, where the look-ahead
    # grown past t1 saw x go down (the flow after t1, not solved), chose below, and the method's own x, on zero within
    # rounding up to t1, never got below it: ZenoError ("does not leave zero to the side the flow takes")
    m = dm.Model("touch")
    m.states("x y")
    m.ode("x", "-2*(t - 1)")
    m.ode("y", "Heaviside(x - 0.3)")
    m.initial(x=-0.7, y=0.0)
    sol = dm.solve(m, (0.0, 1.0), method=method, **options)
    assert sol.status == "success" and abs(sol["x"][-1] - 0.3) < 1e-8 and abs(sol["y"][-1]) < 1e-7


@pytest.mark.parametrize("method", ["radau", "casadi-collocation", "casadi-idas", "reference"])
@pytest.mark.parametrize(("jerk", "y1"), [(-6.0, 0.0), (6.0, 1.0)])
def test_a_crossing_whose_first_two_rates_are_zero_along_the_states(method, jerk, y1):
    # x = 0.3 +- t^3 from t0 through a chain of states (x' = w, w' = v, v' = +-6, all 0 at t0): the look-ahead's
    # explicit midpoint step moves x by h w_mid = h (w + h v / 2) = 0 over every h, so the side was never resolved;
    # the default (above) raised ZenoError for the crossing downward in every method ("does not leave zero to the side
    # the flow takes").  The longer look-aheads take a fourth-order step (x moves +-h^3)
    m = dm.Model("jerk")
    m.states("x w v y")
    m.ode("x", "w")
    m.ode("w", "v")
    m.ode("v", str(jerk))
    m.ode("y", "Heaviside(x - 0.3)")
    m.initial(x=0.3, w=0.0, v=0.0, y=0.0)
    tolerances = {} if method == "casadi-collocation" else {"rtol": 1e-8, "atol": 1e-8}
    sol = dm.solve(m, (0.0, 1.0), method=method, **tolerances)
    assert sol.status == "success"
    assert abs(sol["x"][-1] - (0.3 + jerk / 6)) < 1e-6 and abs(sol["y"][-1] - y1) < 1e-8


def _narrow_jumps(c: float, k: float):
    """s = sin t; w' = k where s > c (a jump of k, on for 2 acos(c) every 2 pi), else 0."""
    m = dm.Model("narrow_jumps")
    m.states("s c w")
    m.ode("s", "c")
    m.ode("c", "-s")
    m.ode("w", f"{k}*Heaviside(s - {c})")
    m.initial(s=0.0, c=1.0, w=0.0)
    return m


def test_switch_excursions_skipped_one_by_one_stay_within_the_tolerance_together():
    # every hump of sin t above 0.99 (0.28 wide) adds 0.28 k to w; radau's steps at rtol 1e-6 with 7 stages are
    # about 1 long, so each hump's other branch changes w by k x step <= atol in its step and is integrated
    # through on the branch below; 477 such humps were 477 x 0.28 k off, one sign: w 104 rtol off, 'success'.  Together
    # they are held to the tolerance (branches.EXCURSION_BUDGET): past it, each is located
    c, k, t1, rtol = 0.99, 8.5e-7, 3000.0, 1e-6
    sol = dm.solve(_narrow_jumps(c, k), (0.0, t1), rtol=rtol, atol=rtol, stages=7, t_eval=[0.0, t1])
    times = _hump_times(c, t1)
    exact = k * float(np.sum(np.minimum(times[1::2], t1) - times[0::2][: len(times[1::2])]))
    if len(times) % 2:  # (a hump still on at t1)
        exact += k * (t1 - times[-1])
    assert sol.status != "success" or abs(sol["w"][-1] - exact) < 100 * rtol * (1.0 + abs(exact))


@pytest.mark.xfail(
    strict=True,
    reason="casadi-idas at rtol 1e-7 counts all 6 crossings of 0.99999 - sin(t + 1.5779) (n = 6) but locates them up "
    "to 1.45e-3 off: its own solution is that far off (s 6.5e-6 low at t = 18.8; 9.8e-6 at t = 20 without events, 100 "
    "rtol, radau's 4.5e-11) times the crossing's condition 1/sqrt(1 - c^2) = 224. The search locates the crossings of "
    "IDAS's solution to 1e-12 in t; the bound needs IDAS's error below 4.5e-7 (rtol 1e-8: 2.2e-4 off; 1e-9: 1.0e-5)",
)
def test_a_declared_event_on_a_hump_10_to_100_tolerances_deep_under_casadi_idas():
    c, phi, t1 = 0.99999, 1.5779, 20.0
    m = dm.Model("humps")
    m.states("s c n")
    m.ode("s", "c")
    m.ode("c", "-s")
    m.ode("n", "0")
    m.initial(s=math.sin(phi), c=math.cos(phi), n=0.0)
    m.event("hump", f"{c} - s", reset={"n": "n + 1"})
    sol = dm.solve(m, (0.0, t1), method="casadi-idas", rtol=1e-7, atol=1e-7, t_eval=[0.0, t1])
    exact = _hump_times(c, t1 + phi) - phi
    exact = exact[exact > 0]
    found = sol.events["hump"]["t"][0]
    assert sol["n"][-1] == len(exact) == 6 and np.abs(found - exact).max() < 1e-4


def test_a_hump_midway_between_a_scans_first_sample_and_its_neighbour_is_looked_into():
    # 0.99999 - sin t sampled symmetrically about its minimum: the output 0.03 before the peak and the first inner
    # sample 0.03 after it read the same value, so neither was nearer zero than the other and the hump (1e-5 deep,
    # 0.0089 wide) was looked into by neither the edge nor the interior test
    from daemodel.solving.between import excursions

    c, peak = 0.99999, math.pi / 2
    T = np.array([peak - 0.03, peak + 0.27])  # (four inner samples 0.06 apart: the first at peak + 0.03)

    def read(t):
        return (c - np.sin(np.asarray(t, dtype=float)))[:, None]

    F = read(T)
    found = list(excursions(read, T, F, np.ones(F.shape, dtype=bool), 4))
    assert len(found) == 1 and abs(found[0].t - peak) < math.acos(c) and found[0].side == 1.0


def _phase_hump(c: float, phi: float):
    """A declared event on c - sin(t + phi), its crossings counted in n."""
    m = dm.Model("humps")
    m.states("s c n")
    m.ode("s", "c")
    m.ode("c", "-s")
    m.ode("n", "0")
    m.initial(s=math.sin(phi), c=math.cos(phi), n=0.0)
    m.event("hump", f"{c} - s", reset={"n": "n + 1"})
    return m


# (and the check of crossings within the method's error, solving/undecided.py, where it reads one undecided too)
AUDITED = (
    r"(; event 'hump' (does not cross zero|crosses zero once|crosses zero [0-9]+ times) between t = [^;]*; tighten "
    r"rtol/atol)*"
)
NEAR_MISS = (
    r"event 'hump' near t = [0-9.]+: its function stays [0-9.]+e-0[5-9] from zero in casadi-idas's solution, where "
    r"a solve 100 times tighter crosses to -[0-9.]+e-0[6-9]: a crossing within the method's error, not located; "
    r"tighten rtol/atol( \(and [0-9] more, the last near t = [0-9.]+\))?" + AUDITED
)


@pytest.mark.parametrize("c", [0.99999, 0.999999, 1.000001, 1.00001])
def test_declared_events_on_shallow_humps_in_every_phase_under_casadi_idas(c):
    # humps of sin(t + phi) 10 and 100 tolerances above c (and 10, 100 below it: never crossed), 16 phases, rtol 1e-7.
    # IDAS's own solution loses up to 1e-5 of its amplitude by t = 20, so at c = 0.999999 its peaks stayed 1e-6 to
    # 7e-6 below c: 0 to 4 of the 6 to 8 crossings counted in each of the 16 phases, "success".  Now each crossing is
    # found (at the exact time within IDAS's error, 100 rtol, over the crossing's slope), or the status names the
    # crossing a solve 100 times tighter makes and IDAS's does not; a hump that never crosses makes no event and no flag
    t1, rtol = 20.0, 1e-7
    for phi in np.linspace(0.0, 2.0 * math.pi, 16, endpoint=False):
        sol = dm.solve(_phase_hump(c, phi), (0.0, t1), method="casadi-idas", rtol=rtol, atol=rtol, t_eval=[0.0, t1])
        exact = (_hump_times(c, t1 + phi) - phi) if c < 1.0 else np.zeros(0)
        exact = exact[exact > 0]
        found = sol.events["hump"]["t"][0]
        assert sol["n"][-1] == len(found) <= len(exact), phi
        if len(found):
            near = np.abs(found[:, None] - exact[None, :]).min(axis=1)
            assert np.all(near < 100 * rtol / math.sqrt(1.0 - c * c)), phi
        if sol.status == "success":
            assert len(found) == len(exact), phi
        else:
            assert c < 1.0 and re.fullmatch(NEAR_MISS, sol.status), (phi, sol.status)


def test_humps_between_idas_outputs_far_apart_are_each_seen():
    # (before: its detection solve read at its 101 default outputs, 30 s apart over (0, 3000), 4.8 periods: 14 of
    # the 956 crossings, status success; the search now reads its windows at two outputs or more an IDAS step)
    t1 = 3000.0
    sol = dm.solve(_humps(0.99, event=0), (0.0, t1), method="casadi-idas", rtol=1e-7, atol=1e-7, t_eval=[0.0, t1])
    found, exact = sol.events["hump"]["t"][0], _hump_times(0.99, t1)
    assert sol.status != "success" or len(found) == len(exact) == 956

"""radau's controllers (backends/radau/control.py): where a caller's ``stop`` ends an integration
(the backend contract's rule 8, backends/base.py)."""

import math
import sys
from pathlib import Path

import numpy as np
import pytest
from daemodel.backends.radau.backend import RadauBackend
from daemodel.backends.radau.control import Radau5Controller
from daemodel.backends.radau.options import RadauOptions
from scipy.integrate import solve_ivp

import daemodel as dm
from daemodel import errors as E
from daemodel.compiling.initial_states import InitialStates
from daemodel.problems import PENDULUM


def _solve(options, stop=None, size=1):
    compiled = PENDULUM.model().compile()
    y0, z0 = np.tile(compiled.y0, (size, 1)), np.tile(compiled.z0, (size, 1))
    P = np.tile(compiled.parameter_values, (size, 1))
    start = InitialStates(y0=y0, z0=z0, p=P, batched=size > 1)
    return compiled, RadauBackend().solve(compiled, (0.0, 3.0), start, options, stop=stop)


@pytest.mark.parametrize(
    "options",
    [
        RadauOptions(rtol=1e-8, atol=1e-8, jit=False),  # the Python controller
        RadauOptions(rtol=1e-8, atol=1e-8, engine="torch"),  # (torch: attempts one at a time)
        RadauOptions(h=0.01),  # the fixed grid
    ],
)
def test_a_stop_ends_the_integration_after_the_block_where_it_is_true(options):
    """The solve ends after the first block of outputs where ``stop`` is True (y4 < 0: the speed turns),
    with the outputs of a solve to t1 up to there, bit for bit; every output was shown to ``stop`` once,
    in order, the start value first, with the block's dense output from the output before it (its values
    at the block's outputs are the outputs)."""
    compiled, whole = _solve(options)
    shown = []

    def stop(times, Y, Z, dense):
        assert Y.shape == (len(times), len(compiled.states)) and Z.shape == (len(times), len(compiled.algebraics))
        if not shown:
            assert dense is None  # (the start value)
        else:
            assert dense.starts[0] == shown[-1][-1] and np.allclose(dense(times)[0], np.hstack([Y, Z]), atol=1e-12)
        shown.append(times)
        return bool((Y[:, 3] < 0).any())

    _, stopped = _solve(options, stop)
    seen = np.concatenate(shown)
    assert seen[0] == 0.0 and np.all(np.diff(seen) > 0)
    np.testing.assert_array_equal(stopped.t, seen)
    first = int(np.argmax(whole["y4"] < 0))  # (the first output past the crossing)
    assert stopped.t[-1] >= whole.t[first] and stopped.t[-1] < 3.0
    k = len(stopped.t)
    np.testing.assert_array_equal(stopped.t, whole.t[:k])
    for name in ("y1", "y4", "y5"):
        np.testing.assert_array_equal(stopped[name], whole[name][:k])
    assert stopped.stats["steps"] == k - 1 < whole.stats["steps"]


def test_a_stop_without_a_crossing_changes_nothing():
    options = RadauOptions(rtol=1e-8, atol=1e-8, jit=False)
    _, whole = _solve(options)
    _, stopped = _solve(options, lambda times, Y, Z, dense: False)
    np.testing.assert_array_equal(stopped.t, whole.t)
    np.testing.assert_array_equal(stopped["y5"], whole["y5"])


def test_the_compiled_run_looks_at_the_outputs_every_few_attempts():
    """With the compiled run (jit), a stop is seen within STOP_ATTEMPTS steps of the crossing, and the
    outputs up to there are those of the solve to t1."""
    from daemodel.backends.radau.compiled import find_compiler
    from daemodel.backends.radau.control import STOP_ATTEMPTS

    if find_compiler() is None:
        pytest.skip("no C compiler")
    options = RadauOptions(rtol=1e-8, atol=1e-8, jit=True)
    _, whole = _solve(options)
    _, stopped = _solve(options, lambda times, Y, Z, dense: bool((Y[:, 3] < 0).any()))
    first = int(np.argmax(whole["y4"] < 0))
    assert first <= len(stopped.t) - 1 <= first + STOP_ATTEMPTS
    np.testing.assert_array_equal(stopped["y1"], whole["y1"][: len(stopped.t)])


def test_a_stop_reads_one_sample():
    with pytest.raises(E.InvalidOptionError, match=r"stop=\.\.\. reads one sample's outputs; this solve has 2 samples"):
        _solve(RadauOptions(rtol=1e-6, atol=1e-6, engine="torch"), lambda *a: False, size=2)


def test_the_first_step_probes_how_fast_f_changes():
    """A stirred tank started near its unstable steady state: f(u0) is ~1e-5 of the state, so the
    first guess 0.01 |u0| / |f(u0)| alone is the whole interval [0, 200], and one implicit step of 200
    lands on that steady state (T = 350.005, and "success").  The Euler probe sizes the first step by
    f's change (0.12 here; scipy's Radau takes 0.10), and radau follows the tank to scipy's T(200) =
    324.476 at every tolerance, its default included."""
    sys.path.insert(0, str(Path(__file__).parent / "pinn"))
    from pinn_hard_models import cstr

    def rhs(t, u):
        C, T = u
        r = 7.2e10 * np.exp(-8750.0 / T) * C
        return [1.0 - C - r, (350.0 - T) + 209.2 * r + 2.092 * (300.0 - T)]

    exact = solve_ivp(rhs, (0.0, 200.0), [0.5, 350.0], method="Radau", rtol=1e-12, atol=1e-12).y[:, -1]
    c = cstr().compile()
    for rtol in (1e-4, 1e-6, 1e-8):
        sol = dm.solve(c, (0.0, 200.0), rtol=rtol, atol=rtol)
        assert sol.status == "success" and 1e-3 < sol.t[1] < 1.0 and sol.stats["steps"] > 10
        assert abs(sol["T"][-1] - exact[1]) < 1e3 * rtol * exact[1] and abs(sol["C"][-1] - exact[0]) < 1e3 * rtol


# (y, f at y, f at the probe, atol, rtol, stages, t0, t1): a step from the probe's d2, f at rest (the first guess
# 1e-6), the probe outside f's domain (NaN: h0 1e-3), f unchanged and tiny (the flat branch), a span shorter
# than the step, a start at t0 = 1e9 (the floor times |t0|)
FIRST_STEPS = [
    ([1.0, -2.0], [0.5, 3.0], [0.7, 2.0], 1e-6, 1e-4, 3, 0.0, 10.0),
    ([1.0, 2.0], [0.0, 0.0], [1e-3, 0.0], 1e-8, 1e-6, 5, 0.0, 1.0),
    ([1.0, 2.0], [0.5, 3.0], [math.nan, 2.0], 1e-6, 1e-4, 3, 0.0, 10.0),
    ([1e-9, 0.0], [1e-20, 0.0], [1e-20, 0.0], 1e-3, 1e-3, 3, 0.0, 10.0),
    ([1.0, -2.0], [0.5, 3.0], [0.7, 2.0], 1e-6, 1e-4, 7, 0.0, 1e-4),
    ([1.0, -2.0], [1e-9, 0.0], [1e-9, 0.0], 1e-6, 1e-4, 3, 1e9, 2e9),
]


@pytest.mark.parametrize("case", FIRST_STEPS)
def test_the_first_step_is_one_formula_on_floats_and_on_casadi_symbols(case):
    """formulas.initial_step on Python floats (the controller's, on an engine's arrays) and on casadi symbols
    (backends/radau/start.py: the casadi engine's, one call): the same step, to 1e-15."""
    import casadi
    from daemodel.backends.radau import formulas

    y, f0, f1, atol, rtol, stages, t0, t1 = case
    y, f0, f1 = (np.array([v]) for v in (y, f0, f1))  # (one sample: the controller's (B, n))
    ops = formulas.ArrayOps(np)
    on_floats = formulas.initial_step(
        formulas.SCALAR, lambda x: float(ops.rms(x).max()), y, f0, lambda h0: f1, atol, rtol, stages, t0, t1
    )
    x = casadi.SX.sym("x", 2)
    probe = lambda h0: casadi.DM(f1[0]) + 0 * h0  # noqa: E731  (f1, as a symbol of h0)
    h = formulas.initial_step(
        formulas.CASADI, formulas.CASADI.rms, x, casadi.DM(f0[0]), probe, atol, rtol, stages, t0, t1
    )
    on_casadi = float(casadi.Function("h", [x], [h])(y[0]))
    assert on_casadi == pytest.approx(on_floats, rel=1e-15, abs=0) and 0 < on_floats <= t1 - t0
    if math.isnan(f1[0, 0]):
        assert on_floats < 1e-2  # (1e-3 of the first guess)


@pytest.mark.parametrize("name", ["pendulum", "akzo-nobel", "car-axis", "robertson"])
def test_the_casadi_engine_makes_the_first_step_in_one_call(monkeypatch, name):
    """The casadi engine's first step (backends/radau/start.py), made in the setup and called once: the same
    h and f at the start as the controller's numpy path, bit for bit, and the same solve."""
    from daemodel.backends.radau import control

    from daemodel.problems import PROBLEMS

    found = []
    initial_step = control.Radau5Controller.initial_step

    def both(self, stepper, t_span):
        assert stepper.engine.first_step is not None
        h, f0 = initial_step(self, stepper, t_span), stepper._f_start.copy()
        kept, stepper.engine.first_step, stepper._f_start = stepper.engine.first_step, None, None
        found.append((h, f0, initial_step(self, stepper, t_span), stepper._f_start.copy()))
        stepper.engine.first_step = kept
        return h

    monkeypatch.setattr(control.Radau5Controller, "initial_step", both)
    compiled = PROBLEMS[name].model().compile()
    span = PROBLEMS[name].t_span
    sol = dm.solve(compiled, span, rtol=1e-5, atol=1e-5)
    ((h, f0, h_numpy, f0_numpy),) = found
    assert h == h_numpy and np.array_equal(f0, f0_numpy) and sol.status == "success"


def test_above_the_inlined_residuals_size_the_controller_makes_the_first_step(monkeypatch):
    """No casadi function of the first step above INLINED_RESIDUAL_MAX_SIZE unknowns (its work and input, 6.8 MB
    at 10^5 unknowns of reaction-diffusion, were held for the solve's life): the controller's formula on numpy,
    the same f at the start as that function's and h to rounding; at the bound, the function."""
    from daemodel.backends.radau import control
    from daemodel.backends.radau.compiled import INLINED_RESIDUAL_MAX_SIZE
    from daemodel.backends.radau.start import Start

    from daemodel.problems.families import reaction_diffusion

    found = []
    initial_step = control.Radau5Controller.initial_step

    def both(self, stepper, t_span):
        made = stepper.engine.first_step
        h, f0 = initial_step(self, stepper, t_span), stepper._f_start.copy()
        stepper.engine.first_step = Start(stepper.engine)
        found.append((made, h, f0, initial_step(self, stepper, t_span), stepper._f_start.copy()))
        stepper.engine.first_step = made
        return h

    monkeypatch.setattr(control.Radau5Controller, "initial_step", both)
    for cells in (INLINED_RESIDUAL_MAX_SIZE // 2, INLINED_RESIDUAL_MAX_SIZE // 2 + 1):
        sol = dm.solve(reaction_diffusion(cells).compile(), (0.0, 1.0), rtol=1e-5, atol=1e-7)
        assert sol.status == "success"
    (at, *first), (above, *second) = found
    assert isinstance(at, Start) and above is None
    for h, f0, h_start, f0_start in (first, second):
        assert h == pytest.approx(h_start, rel=1e-15, abs=0) and np.array_equal(f0, f0_start) and 0 < h < 1


def _near_rest(seed: int):
    """A random stiff system near rest, ``u' = A u - c u^3 + b forcing(t)`` with ``u = y - y_rest``,
    ``u(0)`` 1e-7 of ``y_rest`` (of size 1-10) and ``forcing(0) = 0``: f(t0) is ~1e-7 of the state,
    so the first guess 0.01 |y0| / |f(y0)| alone is the whole span (the stirred tank's trap).  A is
    symmetric negative definite with eigenvalues in [-1e3, -0.1]; the model and its right-hand side
    for scipy, and y(0)."""
    import sympy as sp

    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 4))
    Q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    A = -(Q * 10 ** rng.uniform(-1, 3, size=n)) @ Q.T
    w, k = float(10 ** rng.uniform(-1, 1.5)), int(rng.integers(1, 5))
    c, b = float(rng.uniform(0, 2)), rng.normal(size=n)
    rest = rng.choice([-1.0, 1.0], size=n) * 10 ** rng.uniform(0, 1, size=n)
    y0 = rest * (1 + 1e-7 * rng.normal(size=n))
    t = sp.Symbol("t")
    kind = seed % 4
    forcing = (sp.sin(w * t), t**k / (1 + t**k), 1 - sp.cos(w * t), sp.tanh(w * t) ** 2)[kind]
    numeric = (
        lambda s: np.sin(w * s), lambda s: s**k / (1 + s**k), lambda s: 1 - np.cos(w * s), lambda s: np.tanh(w * s) ** 2
    )[kind]  # fmt: skip
    m = dm.Model(f"rest{seed}")
    ys = m.states([f"y{i}" for i in range(n)])
    us = [ys[i] - float(rest[i]) for i in range(n)]
    for i in range(n):
        m.ode(ys[i], sum(float(A[i, j]) * us[j] for j in range(n)) - c * us[i] ** 3 + float(b[i]) * forcing)
    m.initial(**{f"y{i}": float(y0[i]) for i in range(n)})
    return m, lambda s, y: A @ (y - rest) - c * (y - rest) ** 3 + b * numeric(s), y0


@pytest.mark.parametrize("seed", range(6))
def test_a_start_near_rest_is_followed_to_the_tolerance(seed):
    """Near rest (f(t0) ~ 1e-7 of the state), the probed first step is no leap: radau's end values are
    scipy's at 1e-13 to within 100 rtol (relative to 1 + |y|), for 2, 3 and 5 stages.  With the first
    guess alone, seed 4 (3 stages, rtol 1e-4) ended 190 rtol off and said success."""
    model, rhs, y0 = _near_rest(seed)
    n = len(y0)
    T = float(10 ** np.random.default_rng(100 + seed).uniform(-1, 2))
    # (DOP853 at 1e-13: within 1.6e-15 of scipy's Radau at 1e-13 on these six, in 5.7 s against 25 s)
    exact = solve_ivp(rhs, (0.0, T), y0, method="DOP853", rtol=1e-13, atol=1e-13).y[:, -1]
    compiled = model.compile()
    for stages in (2, 3, 5):
        for rtol in (1e-4, 1e-7):
            sol = dm.solve(compiled, (0.0, T), rtol=rtol, atol=rtol, stages=stages, jit=False)
            got = np.array([float(np.ravel(sol[f"y{i}"])[-1]) for i in range(n)])
            assert sol.status == "success"
            assert np.max(np.abs(got - exact) / (1 + np.abs(exact))) < 100 * rtol, (stages, rtol)


def test_implicit_euler_is_refused_adaptive_steps_and_two_stages_meet_the_tolerance():
    """One stage (implicit Euler) with adaptive steps ended 20 rtol off at rtol 1e-4 and 197 rtol at 1e-6
    on this stiff linear pair, and said success: its local error O(h^2) held at rtol over ~rtol^(-1/2)
    steps adds up to ~rtol^(1/2).  It is refused, naming why and what to give; two and three stages end
    within rtol of the exact solution (matrix exponential), and one stage on a fixed grid still runs."""
    from scipy.linalg import expm

    A = np.array([[-1.0, 1.0], [50.0 * np.cos(1.0), -50.0]])
    m = dm.Model("stiff_pair")
    x, y = m.states("x y")
    m.ode(x, A[0, 0] * x + A[0, 1] * y)
    m.ode(y, A[1, 0] * x + A[1, 1] * y)
    m.initial(x=1.0, y=0.0)
    c = m.compile()
    exact = expm(5.0 * A) @ [1.0, 0.0]
    for rtol in (1e-4, 1e-6):
        with pytest.raises(E.InvalidOptionError, match=r"stages = 1 \(implicit Euler, order 1\) cannot take adaptive"):
            dm.solve(c, (0.0, 5.0), rtol=rtol, atol=rtol, stages=1)
        for stages in (2, 3):
            sol = dm.solve(c, (0.0, 5.0), rtol=rtol, atol=rtol, stages=stages)
            assert sol.status == "success"
            assert max(abs(sol["x"][-1] - exact[0]), abs(sol["y"][-1] - exact[1])) < rtol, (stages, rtol)
    with pytest.raises(E.InvalidOptionError, match=r"give stages >= 2 \(or leave stages out\), or h=\.\.\."):
        dm.solve(c, (0.0, 5.0), stages=1)  # the default tolerances are adaptive too
    fixed = dm.solve(c, (0.0, 5.0), stages=1, h=5e-4)  # (its estimate 6e-4 of the size: 1e-3 is flagged)
    assert fixed.status == "success" and abs(fixed["x"][-1] - exact[0]) < 1e-4


def test_newtons_adaptive_tolerance_follows_the_stages():
    """RADAU5's min(0.03, rtol^(1/2)) up to three stages (the same float), radau.f's rtol^((s - 1) / (s + 1))
    above, capped at HIGH_ORDER_NEWTON_TOL, never below the rounding floor 10 eps / rtol."""
    from daemodel.backends.radau.control import HIGH_ORDER_NEWTON_TOL, HIGH_ORDER_ROUNDING_MARGIN, adaptive_newton_tol

    eps = float(np.finfo(np.float64).eps)
    for rtol in (1e-1, 3e-3, 1e-4, 1e-6, 7e-8, 1e-9, 1e-12):
        for stages in (2, 3):
            assert adaptive_newton_tol(rtol, stages, eps) == max(10 * eps / rtol, min(0.03, rtol**0.5))
    assert adaptive_newton_tol(1e-4, 7, eps) == pytest.approx(1e-3, rel=1e-12)  # rtol^(3/4)
    assert adaptive_newton_tol(1e-6, 5, eps) == pytest.approx(1e-4, rel=1e-12)  # rtol^(2/3)
    assert adaptive_newton_tol(1e-3, 7, eps) == HIGH_ORDER_NEWTON_TOL == adaptive_newton_tol(1e-3, 5, eps)
    # rtol^(3/4) = 1.8e-7 is below the floor 10 eps / rtol, and three stages' rule (3.2e-5) is above ten floors
    assert adaptive_newton_tol(1e-9, 7, eps) == HIGH_ORDER_ROUNDING_MARGIN * 10 * eps / 1e-9
    assert adaptive_newton_tol(1e-8, 7, eps) == HIGH_ORDER_ROUNDING_MARGIN * 10 * eps / 1e-8  # (rtol^(3/4): 1e-6)
    for rtol in (5e-10, 1e-10, 1e-12):  # where three stages' rule is within ten floors, more stages take it
        assert (
            adaptive_newton_tol(rtol, 5, eps) == adaptive_newton_tol(rtol, 7, eps) == adaptive_newton_tol(rtol, 3, eps)
        )
    # where the rule is RADAU5's, the predictive controller is off below rtol ~5e-10 only, as before
    for stages, rtol, floor in ((7, 1e-9, False), (5, 1e-9, False), (7, 1e-10, True), (3, 1e-10, True)):
        options = RadauOptions(rtol=rtol, atol=rtol, stages=stages)
        assert Radau5Controller(options).rounding_floor is floor
        assert Radau5Controller(options).policy.tol == adaptive_newton_tol(rtol, stages, eps)


@pytest.mark.parametrize("t0", [3e4, -3e4])
def test_a_span_shorter_than_1e_13_of_its_end_is_integrated(t0):
    """x' = cos(x) from 0 over 1e-9 at t0 = 3e4 (2.7e5 float64 spacings of t): the end test was relative to |t1|
    (1e-13 of 3e4 = 3e-9, more than the span), so radau ended where it started, 0 steps, x = 0, "success"."""
    m = dm.Model("short")
    m.states("x")
    m.ode("x", "cos(x)")
    m.initial(t=t0, x=0.0)
    t1 = t0 + 1e-9
    sol = dm.solve(m, (t0, t1), method="radau", rtol=1e-10, atol=1e-12)
    assert sol.status == "success" and sol.stats["steps"] >= 1
    assert abs(sol["x"][-1] - math.asin(math.tanh(t1 - t0))) < 1e-20  # (x = gd(t - t0), 1.0004e-9)


def test_a_span_below_the_resolution_of_its_steps_is_not_success():
    """At t0 = 1e15 (float64 spacing 0.125) a span of 2: radau took 0 steps and said "success" with the initial
    values at t1 (u = 0 for 1.68); now each step ends where it ends, and steps too short for t there are named."""
    m = dm.Model("far")
    m.states("x v u")
    m.ode("x", "v")
    m.ode("v", "-x")
    m.ode("u", "x")
    m.initial(t=1e15, x=math.cos(1.0), v=math.sin(1.0), u=0.0)
    with pytest.raises(E.StepSizeError, match=r"at t = 1000000000000000 are shorter than float64 resolves there"):
        dm.solve(m, (1e15, 1e15 + 2.0), method="radau", rtol=1e-8, atol=1e-8)


def test_steps_below_t_s_resolution_are_a_step_size_error_naming_t_s_spacing():
    """x = cos(t - t0 - 1), u' = Max(0, x - 0.5) from t0 = 1e14 over 2.5 at rtol 1e-6 (benchmarks/events_large_t0.py):
    the steps the error estimate asks for (~0.13) are below the underflow threshold, 1e-14 |t| = 1 (64 spacings of t
    there).  Before: ConvergenceError "the solution may blow up or leave the domain of f there, or ... Newton's
    tolerance": not the cause.  Seven stages (longer steps) run it, flagged by t's resolution at the switch."""
    t0 = 1e14
    m = dm.Model("cap")
    m.states("x v u")
    m.ode("x", "v")
    m.ode("v", "-x")
    m.ode("u", "Max(0, x - 0.5)")
    m.initial(t=t0, x=math.cos(1.0), v=math.sin(1.0), u=0.0)
    message = (
        r"radau: the steps that rtol and atol ask for at t = 100000000000000 are shorter than float64 resolves there: "
        r"h = [0-9.]+ \(last failure: error estimate [0-9.e+]+ > 1\) reached the step size underflow's threshold, "
        r"1e-14 \|t\| = 1, 64 float64 spacings of t at \|t\| = 1e\+14 \(spacing 0\.0156\), "
        r"where the start's probe asked for h = 0\.0[0-9]+, 0\.4 "
        r"of t_span; start t_span nearer 0 \(shift the model's time\), loosen rtol and atol, or take more stages"
    )
    with pytest.raises(E.StepSizeError, match=message):
        dm.solve(m, (t0, t0 + 2.5), method="radau", rtol=1e-6, atol=1e-6)
    with pytest.warns(E.EventResolutionWarning):
        sol = dm.solve(m, (t0, t0 + 2.5), method="radau", rtol=1e-6, atol=1e-6, stages=7)
    assert sol.status.startswith('flagged: event "Max in u\'" at t = ')


def test_an_underflow_near_zero_or_on_a_long_span_is_no_step_size_error():
    """The same underflow where 1e-14 |t| is below a millionth of t_span (t = 4.4, or t = 1e14 over 1e9) keeps
    its ConvergenceError: the solution may blow up there."""
    from daemodel.backends.radau.control import SHRUNK_BY_ESTIMATE, underflow_error

    assert type(underflow_error(4.4e-14, 4.4, SHRUNK_BY_ESTIMATE, None, "", 6.0)) is E.ConvergenceError
    assert type(underflow_error(0.5, 1e14, SHRUNK_BY_ESTIMATE, None, "", 1e9)) is E.ConvergenceError
    assert type(underflow_error(0.5, 1e14, "not converged in 10 iterations", None, "", 2.5)) is E.ConvergenceError
    assert type(underflow_error(0.5, 1e14, SHRUNK_BY_ESTIMATE, None, "", 2.5)) is E.StepSizeError


@pytest.mark.parametrize("t0", [1.0, 1e6, -1e6, 1e15])
@pytest.mark.parametrize("spacings", [1, 3, 10])
def test_a_span_of_a_few_float64_spacings_is_one_step(t0, spacings):
    """x' = 1/w over (t0, t0 + w), w a few float64 spacings of t0: x(t1) = 1.  Within 4 eps of t1 the end test
    held at t0 itself (1 and 3 spacings): radau took no step and returned x(t0) = 0 alone, "success"; from 10
    spacings h fell below the underflow threshold (1e-14 |t|) at once: "step size underflow ... the solution
    may blow up".  A step that reaches t1 is now taken however short (exact: Sterbenz)."""
    t1 = t0 + spacings * math.ulp(t0)
    m = dm.Model("ulps")
    m.states("x")
    m.parameter("w", t1 - t0)
    m.ode("x", "1/w")
    m.initial(t=t0, x=0.0)
    sol = dm.solve(m, (t0, t1), method="radau", rtol=1e-8, atol=1e-8)
    assert sol.status == "success" and list(sol.t) == [t0, t1]
    assert abs(sol["x"][-1] - 1.0) < 1e-14


def test_seven_stages_near_the_rounding_floor_do_not_fail_newton_at_every_other_attempt():
    """The transistor amplifier at rtol = atol = 1e-9 (the default's seven stages) against the Test Set's
    reference at t = 0.2.  Newton's tolerance at the rounding floor (10 eps / rtol = 2.2e-6, where
    rtol^(3/4) fell below it) stalled on rounding: 2,264 attempts, 850 Newton failures, 7,620 iterations
    (three stages' rule, 3.2e-5, before 1429be5: 902, 137, 4,943).  At HIGH_ORDER_ROUNDING_MARGIN floors:
    913, 132, 5,056, within 0.011 of atol + rtol |u|."""
    from daemodel.problems import PROBLEMS

    problem = PROBLEMS["transistor-amplifier"]
    sol = dm.solve(problem.model().compile(), tuple(problem.t_span), rtol=1e-9, atol=1e-9)
    assert sol.status == "success" and sol.stats["stages"] == 7
    assert sol.stats["attempts"] < 1_300 and sol.stats["newton_failures"] < 300
    for name, value in problem.reference.items():
        assert abs(float(np.ravel(sol[name])[-1]) - value) < 1e-9 + 1e-9 * abs(value), name

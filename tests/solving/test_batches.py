"""A batch without t_eval whose model switches on its states (daemodel/solving/batches.py): each sample's
switch located, as one sample alone or a batch on t_eval has it.  Before: x' = -Min(1, x) from x0 = 1.2, 2,
2.8 stepped across the switch at x = 1 and ended up to 9.2e-7 off at the default tolerance (3 rtol of
x(3) = 0.30), "success" (one at a time, or on t_eval: 7e-12)."""

import dataclasses
import math

import numpy as np
import pytest

import daemodel as dm

# radau's default on casadi's virtual machine, but in the tests marked machine_code (tests/conftest.py)
pytestmark = pytest.mark.virtual_machine

X0 = np.array([1.2, 2.0, 2.8])


def _exact(x0, t):
    """x = x0 - t until x = 1 (t = x0 - 1), then x = exp(-(t - (x0 - 1)))."""
    switch = x0 - 1.0
    return x0 - t if t <= switch else math.exp(-(t - switch))


def _model():
    m = dm.Model("min")
    m.states("x")
    m.ode("x", "-Min(1, x)")
    m.initial(x=2.0)
    return m


def test_a_batch_without_t_eval_locates_each_samples_switch():
    sol = dm.solve(_model(), (0.0, 3.0), y0={"x": X0})
    assert sol.status == "success" and sol["x"].shape == (len(X0), len(sol.t))
    for b, x0 in enumerate(X0):
        exact = np.array([_exact(x0, t) for t in sol.t])
        assert np.all(np.abs(sol["x"][b] - exact) <= 1e-8 + 1e-6 * np.abs(exact))  # (the default tolerance)
        assert abs(sol["x"][b][-1] - exact[-1]) <= 1e-10  # (was 9.2e-7 at t = 3; located: 7e-12)
        assert np.abs(sol.t - (x0 - 1.0)).min() <= 1e-10  # (each sample's switch is an output time)
    assert sol.stats["events"] == len(X0)


def test_a_batch_without_t_eval_agrees_with_its_samples_alone():
    sol = dm.solve(_model(), (0.0, 3.0), y0={"x": X0}, rtol=1e-9, atol=1e-9)
    for b, x0 in enumerate(X0):
        m = _model()
        m.initial(x=float(x0))
        alone = dm.solve(m, (0.0, 3.0), rtol=1e-9, atol=1e-9)
        shared = np.isin(sol.t, alone.t)
        assert shared.sum() == len(alone.t)  # (the batch's times hold every sample's own)
        np.testing.assert_allclose(sol["x"][b][shared], alone["x"], rtol=0, atol=1e-11)
        assert abs(alone["x"][-1] - _exact(x0, 3.0)) <= 1e-9


def _jump_exact(x0, t):
    """x' = -1 while x > 1, then -1/4: x = x0 - t until t = x0 - 1, then 1 - (t - (x0 - 1)) / 4."""
    return x0 - t if t <= x0 - 1.0 else 1.0 - 0.25 * (t - (x0 - 1.0))


@pytest.mark.parametrize("samples", [1, 7])
def test_float32_locates_its_switches(samples):
    """float32 stepped across the switches (one trajectory or a batch): the jump of x' at x = 1 ended 3,700
    tolerances off at rtol 1e-5 (7 samples), 'success'; the area under Max(0, x - 1) 35 of them."""
    x0 = np.linspace(1.2, 2.8, samples) if samples > 1 else np.array([1.7])
    jump = dm.Model("jump")
    jump.states("x")
    jump.ode("x", "Piecewise((-1, x > 1), (-0.25, True))")
    jump.initial(x=2.0)
    area = dm.Model("area")
    area.states("x y")
    area.ode("x", "-1")
    area.ode("y", "Max(0, x - 1)")  # (y = (x0 - 1)^2 / 2 - Max(0, x0 - 1 - t)^2 / 2)
    area.initial(x=2.0, y=0.0)
    rtol = 1e-5
    for model, name, exact in (
        (jump, "x", _jump_exact),
        (area, "y", lambda a, t: (a - 1.0) ** 2 / 2 - max(a - 1.0 - t, 0.0) ** 2 / 2),
    ):
        sol = dm.solve(model, (0.0, 3.0), y0={"x": x0}, dtype="float32", rtol=rtol)
        values = np.asarray(sol[name], dtype=float).reshape(samples, -1)
        for b, a in enumerate(x0):
            reference = np.array([exact(a, t) for t in sol.t])
            # (float32 holds x and y to 6e-8; the errors located: <= 0.2 rtol |x| + 1e-7)
            assert np.all(np.abs(values[b] - reference) <= rtol * np.abs(reference) + 1e-6), (name, a)
        assert sol.status == "success" and sol.stats["events"] == samples


G, E_BALL = 9.81, 0.8


def _ball(**event):
    m = dm.Model("ball")
    m.states("h v")
    m.ode("h", "v")
    m.ode("v", f"-{G}")
    m.initial(h=1.0, v=0.0)
    m.event("floor", "h", direction=-1, **event)
    return m


def _ball_exact(h0: float, t: float, t1: float) -> tuple[float, list]:
    """h at t of a ball dropped from h0 at rest (restitution E_BALL), and its impact times up to t1."""
    t_hit, v = math.sqrt(2.0 * h0 / G), math.sqrt(2.0 * G * h0)
    impacts, start, h, up = [], 0.0, None, 0.0
    while start <= t1:
        end = t_hit if not impacts else start + 2.0 * up / G
        if h is None and t <= end:
            tau = t - start
            h = h0 - G * tau**2 / 2 if not impacts else up * tau - G * tau**2 / 2
        if end <= t1:
            impacts.append(end)
        start, up = end, (v if not impacts[:-1] else up) * E_BALL
    return h, impacts


def test_a_batch_of_bouncing_balls_without_t_eval():
    """Refused before (SwitchError: 'pass t_eval'): each sample's impacts located, its values at every
    sample's times (the others' from its dense output) against the closed form."""
    heights = np.array([0.5, 1.0, 1.7, 2.3])
    rtol = atol = 1e-8
    sol = dm.solve(_ball(reset={"v": f"-{E_BALL}*v"}), (0.0, 2.5), y0={"h": heights}, rtol=rtol, atol=atol)
    assert sol.status == "success" and sol["h"].shape == (len(heights), len(sol.t))
    impacts = sol.events["floor"]["t"]
    for b, h0 in enumerate(heights):
        exact = [_ball_exact(h0, t, 2.5)[0] for t in sol.t]
        assert np.all(np.abs(sol["h"][b] - exact) <= atol + rtol * np.abs(exact)), h0
        times = _ball_exact(h0, 0.0, 2.5)[1]
        assert len(times) >= 2 and np.abs(impacts[b, : len(times)] - times).max() <= 1e-9
        assert np.isnan(impacts[b, len(times) :]).all()  # (padded: the others bounce more often)
        assert np.abs(sol.t[:, None] - np.array(times)[None, :]).min(axis=0).max() <= 1e-9  # (output times)
    assert sol.stats["events"] == sum(len(_ball_exact(h0, 0.0, 2.5)[1]) for h0 in heights)


def test_a_terminal_event_ends_each_sample_of_a_batch_at_its_own_time():
    heights = np.array([0.5, 1.2, 2.0])
    sol = dm.solve(_ball(terminal=True), (0.0, 1.0), y0={"h": heights}, rtol=1e-8, atol=1e-8)
    ends = np.sqrt(2.0 * heights / G)  # (0.32, 0.49, 0.64 s: all before t1 = 1)
    np.testing.assert_allclose(sol.stats["t_end"], ends, rtol=0, atol=1e-9)
    np.testing.assert_allclose(sol.events["floor"]["t"][:, 0], ends, rtol=0, atol=1e-9)
    assert sol.t[-1] == sol.stats["t_end"].max()
    for b, h0 in enumerate(heights):
        before = sol.t <= sol.stats["t_end"][b]
        exact = h0 - G * sol.t[before] ** 2 / 2
        assert np.all(np.abs(sol["h"][b][before] - exact) <= 1e-8 + 1e-8 * np.abs(exact)), h0
        assert np.isnan(sol["h"][b][~before]).all()  # (the sample ended there)
    assert sol.status == "success"


def test_a_batch_without_t_eval_reads_the_others_times_off_each_samples_dense_output():
    """Before, each sample was solved alone, then all again on the union of their times (t_eval): 103 steps
    where the samples alone took 68.  Now the samples' own solves are the answer, each sample's values at the
    others' times its collocation polynomial's (what t_eval evaluates): the same values, within the tolerance
    of the closed form (0.04 of it at rtol 1e-4, 3 stages; at the step ends 0.003)."""
    rtol, atol = 1e-4, 1e-6
    sol = dm.solve(_model(), (0.0, 3.0), y0={"x": X0}, rtol=rtol, atol=atol)
    assert sol.stats["steps"] == sol.stats["samples_alone_steps"]  # (nothing solved again)
    on_times = dm.solve(_model(), (0.0, 3.0), y0={"x": X0}, rtol=rtol, atol=atol, t_eval=sol.t)
    np.testing.assert_allclose(sol["x"], on_times["x"], rtol=0, atol=1e-13)
    for b, x0 in enumerate(X0):
        exact = np.array([_exact(x0, t) for t in sol.t])
        assert np.all(np.abs(sol["x"][b] - exact) <= 0.5 * (atol + rtol * np.abs(exact)))
    assert sol.status == "success"


def test_a_flagged_sample_of_a_batch_without_t_eval_is_said():
    """The samples' own solves are kept: their warnings are said (before, by the solve again on the union)
    and the flagged samples named in the status."""
    with pytest.warns(dm.errors.LocalErrorWarning, match=r"flagged: radau's local error estimate reaches"):
        sol = dm.solve(_model(), (0.0, 3.0), y0={"x": X0}, h=0.5, stages=1, estimate_bound=1e-6)
    assert sol.status.startswith("samples [0]: on [0.2, 3]: flagged")  # (x0 = 1.2: its switch at t = 0.2)
    assert sol.stats["steps"] == sol.stats["samples_alone_steps"]


def test_float32_locates_its_switches_by_trials_in_float64():
    """float32's event function is its rounding near a crossing: x hit 1.0 exactly over 6e-8 in t, and the search
    crept along that plateau (32 trials for x0 = 2; 301 for the 7 samples; float64: 23).  Its trials in float64:
    28, 4 a sample, the pieces between the switches in float32, the errors as small (0.02 of the tolerance).  (The
    batch's count was its first sample's until every sample's was summed, and the bound here, 2 a sample, held
    on that one's 4.)"""
    x0 = np.linspace(1.2, 2.8, 7)
    jump = dm.Model("jump")
    jump.states("x")
    jump.ode("x", "Piecewise((-1, x > 1), (-0.25, True))")
    jump.initial(x=2.0)
    sol = dm.solve(jump, (0.0, 3.0), y0={"x": x0}, dtype="float32", rtol=1e-5)
    assert sol.stats["dtype"] == "float32" and sol.stats["events"] == len(x0)
    assert sol.stats["location_trials"] <= 4 * len(x0)
    for b, a in enumerate(x0):
        reference = np.array([_jump_exact(a, t) for t in sol.t])
        assert np.all(np.abs(sol["x"][b] - reference) <= 1e-5 * np.abs(reference) + 1e-6)


class _NoTimes:
    """A method plugged in without ``t_eval`` and without a dense output (scipy's, through the reference)."""

    @staticmethod
    def register():
        from daemodel.backends.reference import ReferenceBackend, ReferenceOptions

        @dataclasses.dataclass(frozen=True, kw_only=True)
        class Options:
            rtol: float = 1e-4
            atol: float = 1e-6

        class NoTimes(ReferenceBackend):
            name = "no-times"

            def solve(self, compiled, t_span, start, options):
                own = ReferenceOptions(rtol=options.rtol, atol=options.atol)
                return dataclasses.replace(super().solve(compiled, t_span, start, own), dense=None)

        NoTimes.Options = Options
        dm.methods.register("no-times", NoTimes)


@pytest.fixture
def no_times():
    _NoTimes.register()
    yield "no-times"
    dm.methods.unregister("no-times")


def test_a_batch_on_a_method_without_t_eval_does_not_step_across_its_switches(no_times):
    """A method without t_eval (plugged in) stepped across a batch's switches, x' = -Min(1, x): 2.7 tolerances
    off at x(3) with rtol = atol = 1e-10 (one sample alone: 0.04), "success"; and a batch with a declared event
    was told to 'pass t_eval', an option the method does not have.  Each sample is solved alone, its switch
    located; where their outputs do not share times and the method can neither evaluate between them nor take
    t_eval, a SwitchError says so."""
    for model, name in ((_model(), "x"), (_ball(), "h")):
        with pytest.raises(dm.errors.SwitchError, match="method 'no-times' has no t_eval and no dense output"):
            dm.solve(model, (0.0, 3.0), method=no_times, y0={name: X0})
    one = dm.solve(_model(), (0.0, 3.0), method=no_times, y0={"x": X0[:1]}, rtol=1e-10, atol=1e-10)
    assert one.status == "success" and abs(one["x"][0][-1] - _exact(X0[0], 3.0)) <= 1e-10
    same = dm.solve(_model(), (0.0, 3.0), method=no_times, y0={"x": X0[[1, 1]]}, rtol=1e-10, atol=1e-10)
    assert same.status == "success" and same.stats["events"] == 2
    np.testing.assert_allclose(same["x"][:, -1], _exact(X0[1], 3.0), rtol=0, atol=1e-10)


def test_a_batch_on_t_eval_reads_its_pieces_off_the_steps_that_located_their_switches():
    """Each piece of a solve on t_eval was solved twice, once to find its event and again on t_eval: 74 steps
    where its samples alone take 51 (50 samples: 1,214 for 823).  Now t_eval is read off the steps that found
    the event (radau's collocation polynomials, what t_eval evaluates): the values as before to 2e-15, against
    the closed form to 1e-10 at rtol 1e-9, the steps those of the samples alone."""
    grid = np.linspace(0.0, 3.0, 301)
    alone = dm.solve(_model(), (0.0, 3.0), y0={"x": X0}, rtol=1e-9, atol=1e-9)
    sol = dm.solve(_model(), (0.0, 3.0), y0={"x": X0}, rtol=1e-9, atol=1e-9, t_eval=grid)
    assert sol.status == "success" and sol.stats["events"] == len(X0)
    assert sol.stats["steps"] == alone.stats["samples_alone_steps"]  # (51; was 74)
    np.testing.assert_allclose(sol["x"], alone.at(grid)["x"], rtol=0, atol=1e-13)
    for b, x0 in enumerate(X0):
        np.testing.assert_allclose(sol["x"][b], [_exact(x0, t) for t in grid], rtol=0, atol=1e-10)


@pytest.mark.parametrize("method", ["radau", "casadi-idas", "reference"])
def test_code_a_batch_with_events_makes_at_its_first_use_is_setup(monkeypatch, method):
    """Issue 42: every one-off code generation is setup.  A batch of bouncing balls without t_eval is solved sample
    by sample and, where the dense output solves again (casadi-idas, the reference), again on the union of their
    times: the first pass's clocks were dropped, and its events' numpy code (made at its first use in the search)
    landed on the call's solve clock (setup 0.013-0.046 s with that making slowed down by a known 0.3 s).  The
    call's wall time stays setup + solve, within 5 % or 5 ms."""
    import time

    from daemodel.compiling import batch_function

    made = batch_function.BatchFunction.__init__

    def slow_init(self, exprs, symbols, lambdify):
        def slow(exprs):
            time.sleep(0.3)
            return lambdify(exprs)

        made(self, exprs, symbols, slow)

    m = dm.Model("balls")
    m.states("h v")
    m.ode("h", "v")
    m.ode("v", "-9.81")
    m.initial(h=1.0, v=0.0)
    m.event("floor", "h", direction=-1, reset={"v": "-0.8*v"})
    compiled = m.compile()
    monkeypatch.setattr(batch_function.BatchFunction, "__init__", slow_init)
    started = time.perf_counter()
    sol = dm.solve(compiled, (0.0, 2.0), method=method, y0={"h": np.array([1.0, 1.5, 2.0])}, rtol=1e-8, atol=1e-8)
    wall = time.perf_counter() - started
    assert sol.setup_time >= 0.3, sol
    assert abs(wall - sol.setup_time - sol.solve_time) <= max(5e-3, 0.05 * wall)
    # (the impacts of h0 = 1 at sqrt(2 h0 / g), each sample's own)
    assert abs(sol.events["floor"]["t"][0][0] - math.sqrt(2.0 / 9.81)) < 1e-7

"""Solution.plot (daemodel/plotting.py) draws the solution, not its output grid: the bouncing ball's
flights as parabolas from the dense output, each line broken at every impact with both limits drawn,
the impacts marked on the time axis; without a dense output, the output points broken the same way.

The bouncing ball (PROBLEMS["bouncing-ball"]): h' = v, v' = -g, dropped from h = 1 at rest, v = -e v at
each impact; its closed form (Problem.exact_solution) gives the impact times and the values on each side,
and between impacts k and k+1 the apex u_k^2 / (2 g) with u_k the speed after impact k."""

from __future__ import annotations

import dataclasses
from itertools import pairwise

import numpy as np
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg

import daemodel as dm
from daemodel.plotting import BREAKPOINTS, DRAWN_POINTS, broken_curve, instants_of
from daemodel.problems import BALL_G, PROBLEMS

SPAN = (0.0, 2.5)  # four impacts (0.45, 1.17, 1.75, 2.21), the last flight's apex at 2.40
OUTPUTS = np.linspace(*SPAN, 22)
RTOL = 1e-6


@pytest.fixture(scope="module")
def ball():
    problem = PROBLEMS["bouncing-ball"]
    exact = problem.exact_solution()
    impacts = exact.events["floor"]
    inside = impacts["t"][0] <= SPAN[1]
    limits = {
        "t": impacts["t"][0][inside],
        "before": {k: v[0][inside] for k, v in impacts["before"].items()},
        "after": {k: v[0][inside] for k, v in impacts["after"].items()},
    }
    return problem.model(), exact, limits


def rendered(solution, **kwargs) -> dict:
    """The figure drawn by Agg, and per panel title its lines by gid."""
    fig = solution.plot(**kwargs)
    FigureCanvasAgg(fig).draw()
    panels = {}
    for ax in fig.axes:
        lines = {}
        for line in ax.get_lines():
            lines.setdefault(line.get_gid(), []).append(line)
        panels[ax.get_title()] = lines
    return panels


def pieces(line) -> list[tuple[np.ndarray, np.ndarray]]:
    """A drawn line's runs between its NaN breaks."""
    t, y = np.asarray(line.get_xdata(), dtype=float), np.asarray(line.get_ydata(), dtype=float)
    cuts = np.flatnonzero(np.isnan(t) | np.isnan(y))
    bounds = [-1, *cuts, len(t)]
    return [(t[a + 1 : b], y[a + 1 : b]) for a, b in pairwise(bounds) if b > a + 1]


def check_broken_at_the_impacts(line, limits, name: str, atol: float) -> list:
    """The line has one piece per flight, none crossing an impact, each starting at the impact's value
    after it and ending at the next one's value before it (to ``atol``)."""
    runs = pieces(line)
    impacts = limits["t"]
    assert len(runs) == len(impacts) + 1
    edges = [SPAN[0], *impacts, SPAN[1]]
    for k, (t, y) in enumerate(runs):
        assert t[0] == pytest.approx(edges[k], abs=1e-8) and t[-1] == pytest.approx(edges[k + 1], abs=1e-8)
        assert np.all(np.diff(t) >= 0)
        if k > 0:  # starts at the right limit of impact k
            assert y[0] == pytest.approx(limits["after"][name][k - 1], abs=atol)
        if k < len(impacts):  # ends at the left limit of impact k + 1
            assert y[-1] == pytest.approx(limits["before"][name][k], abs=atol)
    # and no drawn segment joins points on both sides of an impact
    t = np.asarray(line.get_xdata(), dtype=float)
    for impact in impacts:
        joined = (t[:-1] < impact - 1e-8) & (t[1:] > impact + 1e-8)
        assert not joined.any(), f"a segment crosses the impact at t = {impact:.6g}"
    return runs


def test_the_ball_is_drawn_from_its_dense_output_broken_at_each_impact(ball):
    model, _, limits = ball
    sol = dm.solve(model, SPAN, method="radau", rtol=RTOL, atol=1e-8, t_eval=OUTPUTS)
    assert sol.dense is not None and len(sol.t) == 22
    panels = rendered(sol)
    (h_line,) = panels["h"]["solution"]
    (v_line,) = panels["v"]["solution"]
    # v jumps at each impact from -v_impact to e*v_impact, to the method's accuracy
    scale = np.abs(limits["before"]["v"]).max()
    v_runs = check_broken_at_the_impacts(v_line, limits, "v", atol=10 * RTOL * scale)
    assert [y[-1] for _, y in v_runs[:-1]] == pytest.approx(limits["before"]["v"], rel=10 * RTOL)
    assert [y[0] for _, y in v_runs[1:]] == pytest.approx(-0.8 * limits["before"]["v"], rel=10 * RTOL)
    h_runs = check_broken_at_the_impacts(h_line, limits, "h", atol=10 * RTOL)
    # between impacts, the drawn maximum of h is the parabola's apex: to the method's accuracy plus the
    # drawing grid's (a parabola sampled every dt misses its apex by at most g dt^2 / 8)
    dt = (SPAN[1] - SPAN[0]) / (DRAWN_POINTS - 1)
    for k, (t, y) in enumerate(h_runs[1:]):
        speed = limits["after"]["v"][k]
        apex, when = speed**2 / (2 * BALL_G), limits["t"][k] + speed / BALL_G
        assert t[0] < when < t[-1]  # every flight's apex is inside the span
        bound = 10 * RTOL * apex + BALL_G * dt**2 / 8
        assert abs(y.max() - apex) <= bound, (k, y.max(), apex)
        # the 22 output points joined by chords miss it by far more: the test tells the two apart
        flight = (sol.t > t[0]) & (sol.t < t[-1])
        assert abs(sol["h"][flight].max() - apex) > 100 * bound
    # the impacts are ticks on the time axis, one legend entry
    for panel in panels.values():
        (marks,) = panel["instant"]
        assert marks.get_label() == "floor"
        assert np.asarray(marks.get_xdata()) == pytest.approx(limits["t"], abs=1e-8)


def test_a_reference_is_drawn_broken_at_its_own_impacts(ball):
    model, exact, limits = ball
    sol = dm.solve(model, SPAN, method="radau", rtol=RTOL, atol=1e-8, t_eval=OUTPUTS)
    panels = rendered(sol, reference=exact)
    (v_line,) = panels["v"]["reference"]
    runs = check_broken_at_the_impacts(v_line, limits, "v", atol=1e-12)
    assert sum(len(t) for t, _ in runs) >= DRAWN_POINTS  # on the fine grid, not the outputs
    # a Solution as the reference: drawn from its own dense output, broken at its own impacts
    tight = dm.solve(model, SPAN, method="radau", rtol=1e-10, atol=1e-10)
    (v_line,) = rendered(sol, reference=tight)["v"]["reference"]
    runs = check_broken_at_the_impacts(v_line, limits, "v", atol=1e-8)
    assert v_line.get_linestyle() == "--" and sum(len(t) for t, _ in runs) >= DRAWN_POINTS


def test_without_a_dense_output_the_output_points_are_drawn_broken_at_each_impact(ball):
    model, _, limits = ball
    sol = dm.solve(model, SPAN, method="radau", rtol=RTOL, atol=1e-8, t_eval=OUTPUTS, dense_output=False)
    assert sol.dense is None
    panels = rendered(sol)
    (v_line,) = panels["v"]["solution"]
    assert v_line.get_marker() == "o"
    scale = np.abs(limits["before"]["v"]).max()
    runs = check_broken_at_the_impacts(v_line, limits, "v", atol=10 * RTOL * scale)
    # each run: the output points of its flight between the two limits
    drawn = np.concatenate([t[1:-1] for t in (t for t, _ in runs)])
    assert drawn == pytest.approx(sol.t[1:-1], abs=0)
    assert np.concatenate([y[1:-1] for _, y in runs]) == pytest.approx(sol["v"][1:-1], abs=0)


def test_a_batch_breaks_each_sample_at_its_own_impacts(ball):
    """Two gravities: the impacts differ per sample, and each sample's line breaks at its own."""
    model, _, _ = ball
    sol = dm.solve(model, SPAN, method="radau", rtol=RTOL, atol=1e-8, parameters={"g": [BALL_G, 5.0]}, t_eval=OUTPUTS)
    panels = rendered(sol, names=["v"])
    lines = panels["v"]["solution"]
    assert len(lines) == 2
    for b, line in enumerate(lines):
        times = sol.events["floor"]["t"][b]
        times = times[np.isfinite(times)]
        assert len(pieces(line)) == len(times) + 1
        t = np.asarray(line.get_xdata(), dtype=float)
        assert set(times) <= set(t[np.isfinite(t)])


def test_broken_curve_draws_both_limits_and_skips_an_instant_at_the_end():
    """The drawing of one piecewise curve: y = t, reset to 0 at t = 1 and cut again at t = 2, the end."""
    grid = np.linspace(0.0, 2.0, 9)
    values = np.where(grid < 1, grid, grid - 1)
    nan = np.array([[np.nan]])
    records = {
        "reset": {"t": np.array([[1.0, 2.0]]), "before": {"y": np.ones((1, 2))}, "after": {"y": np.zeros((1, 2))}},
        BREAKPOINTS: {"t": nan, "before": {"y": nan}, "after": {"y": nan}},
    }
    instants = instants_of(records, 0, ["y"], (0.0, 2.0))
    assert [i.t for i in instants] == [1.0, 2.0]  # (the NaN padding left out)
    t, y = broken_curve(grid, values, instants, "y")
    np.testing.assert_array_equal(t, [0, 0.25, 0.5, 0.75, 1, np.nan, 1, 1.25, 1.5, 1.75, 2])
    np.testing.assert_array_equal(y, [0, 0.25, 0.5, 0.75, 1, np.nan, 0, 0.25, 0.5, 0.75, 1])


def test_an_alias_is_broken_with_its_limits_computed_from_the_states(ball):
    """An eliminated alias, w = -v (the constraint w + v = 0): the events record the states, and w's
    values on each side of an impact come from theirs."""
    _, _, limits = ball
    m = dm.Model("ball-with-alias")
    h, v = m.states("h v")
    (w,) = m.algebraics("w")
    m.ode(h, v)
    m.ode(v, -m.parameter("g", BALL_G))
    m.constraint(w + v, name="alias")
    m.initial(h=1.0, v=0.0)
    m.event("floor", when=h, direction=-1, reset={"v": "-0.8*v"})
    sol = dm.solve(m, SPAN, method="radau", rtol=RTOL, atol=1e-8, t_eval=OUTPUTS)
    assert sol.compiled.alias_names == ("w",) and "w" not in sol.events["floor"]["before"]
    (line,) = rendered(sol, names=["w"])["w"]["solution"]
    scale = np.abs(limits["before"]["v"]).max()
    negated = {"t": limits["t"], "before": {"w": -limits["before"]["v"]}, "after": {"w": -limits["after"]["v"]}}
    check_broken_at_the_impacts(line, negated, "w", atol=10 * RTOL * scale)


def test_a_solution_without_instants_is_one_unbroken_line():
    sol = dm.solve(PROBLEMS["hessenberg"].model(), (0.0, 1.0), h=0.1)
    panels = rendered(sol, names=["y1"])
    (line,) = panels["y1"]["solution"]
    assert len(pieces(line)) == 1 and "instant" not in panels["y1"]
    assert len(line.get_xdata()) >= DRAWN_POINTS
    np.testing.assert_allclose(line.get_ydata(), np.exp(2 * np.asarray(line.get_xdata())), rtol=1e-5)
    assert dataclasses.replace(sol, dense=None).plot(names=["y1"]).axes[0].get_lines()[0].get_marker() == "o"

"""The method plugged in from outside (examples/plugin_method/whole_span_pinn.py) through dm.solve and
dm.compare with no change to daemodel: its error against the exact Hessenberg solution, its estimate
against that error, its flag when training is cut short, its options' checks, and the models it refuses."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

import daemodel as dm
from daemodel import errors as E
from daemodel.problems import HESSENBERG

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "plugin_method"
NAME = "whole-span-pinn"


@pytest.fixture
def method(monkeypatch):
    """The example's module, its method registered for one test."""
    monkeypatch.syspath_prepend(str(EXAMPLE))
    import whole_span_pinn

    dm.methods.register(NAME, whole_span_pinn.WholeSpanPINN)
    yield whole_span_pinn
    dm.methods.unregister(NAME)


def relative_errors(sol, exact) -> dict[str, float]:
    """Each variable's largest error relative to 1 + max|u| of the exact one (the method's own units)."""
    truth = exact(sol.t)
    return {
        name: float(np.abs(np.asarray(sol[name]) - truth[name]).max() / (1 + np.abs(truth[name]).max()))
        for name in truth
    }


def test_through_compare_it_meets_its_accuracy_against_the_exact_solution(method, capsys):
    result = method.main(["--quick"])  # (the example as CI runs it: compare beside radau, and its assertion)
    (run,) = [run for run in result.runs if run.method == NAME]
    assert run.status == "success" and run.failure is None and result.reference == "the exact solution"
    worst = max(error["max"] for error in run.errors.values())
    # measured 2.1e-4 (y5), the default tol 1e-3 relative to 1 + max|u| (y1 reaches e^2)
    assert 1e-6 < worst < 1e-3
    assert run.drift["invariant"] < 1e-13  # the hard constraint layer: y1 y4 = y2 y3 to rounding
    assert run.setup_time > 0 and run.solve_time > 0  # training is setup, the outputs and the estimate solve
    assert f"\n{NAME}  " in capsys.readouterr().out


def test_its_estimate_is_its_distance_from_the_exact_solution(method):
    exact = HESSENBERG.exact_solution()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sol = dm.solve(HESSENBERG.model(), (0.0, 1.0), method=NAME, iterations=40, t_eval=np.linspace(0, 1, 41))
    true = max(relative_errors(sol, exact).values())
    estimate = sol.stats["error_estimate"]
    # radau at rtol 1e-10 is exact to ~1e-10 here: the estimate is the true error, to its digits
    assert estimate == pytest.approx(true, rel=1e-4)
    assert (sol.status == "success") == (estimate <= 1e-3) == (not caught)
    assert sol.stats["iterations"] == [40] and np.isfinite(sol.stats["final_loss"][0])
    assert sol.setup_time + sol.solve_time > sol.stats["training_seconds"]


def test_training_cut_short_is_flagged_with_its_estimate(method):
    with pytest.warns(method.AccuracyWarning, match="error estimate .* reaches .* beyond tol = 0.001"):
        sol = dm.solve(HESSENBERG.model(), (0.0, 1.0), method=NAME, iterations=3)
    estimate = sol.stats["error_estimate"]
    assert sol.status.startswith(f"flagged: {NAME}'s error estimate (its distance to radau at rtol = 1e-10) reaches")
    assert estimate > 1e-3
    assert estimate == pytest.approx(max(relative_errors(sol, HESSENBERG.exact_solution()).values()), rel=1e-4)


def test_its_options_are_checked_by_solve(method):
    m = HESSENBERG.model()
    with pytest.raises(E.UnknownOptionError, match=f"method '{NAME}' has no option 'iteration'; its options are"):
        dm.solve(m, (0.0, 1.0), method=NAME, iteration=10)
    with pytest.raises(E.InvalidOptionError, match=r"check_rtol = 0\.01 must be below tol = 0\.001"):
        dm.solve(m, (0.0, 1.0), method=NAME, check_rtol=1e-2)
    with pytest.raises(E.InvalidOptionError, match="points must be at least 8"):
        dm.solve(m, (0.0, 1.0), method=NAME, points=4)
    with pytest.raises(E.InvalidOptionError, match="width must be positive"):
        dm.solve(m, (0.0, 1.0), method=NAME, width=0)


def test_a_method_that_solves_the_whole_span_refuses_events_and_switches(method):
    ball = dm.Model("ball")
    ball.states("h v")
    ball.ode("h", "v")
    ball.ode("v", "-9.81")
    ball.initial(h=1.0, v=0.0)
    ball.event("floor", "h", direction=-1, reset={"v": "-0.8*v"})
    with pytest.raises(
        E.UnsupportedModelError,
        match=f"method '{NAME}' solves the whole span at once \\(solves_pieces = False\\), but model 'ball' has the "
        "event 'floor', across which daemodel solves piece by piece: use a method that solves pieces, e.g. 'radau'",
    ):
        dm.solve(ball, (0.0, 1.0), method=NAME)
    switch = dm.Model("switched")
    switch.states("x")
    switch.ode("x", "Piecewise((1, t < 0.5), (-1, True))")
    switch.initial(x=0.0)
    with pytest.raises(
        E.UnsupportedModelError,
        match=r"but model 'switched' has a switch \(Piecewise in x': t - 0.5 crosses 0 \(time breakpoint\)\), across",
    ):
        dm.solve(switch, (0.0, 1.0), method=NAME)


def test_a_constraint_on_z_is_a_penalty_and_still_meets_the_accuracy(method):
    m = dm.Model("index1")
    m.states("x")
    m.algebraics("w")
    m.ode("x", "-w")
    m.constraint("w + w**3/10 - x", name="c")  # (index 1: g involves w, so no hard layer for it)
    m.initial(x=1.0)
    sol = dm.solve(m, (0.0, 1.0), method=NAME, iterations=60)
    reference = dm.solve(m, (0.0, 1.0), method="radau", rtol=1e-11, atol=1e-11, t_eval=sol.t)
    error = max(float(np.abs(sol[name] - reference[name]).max()) for name in ("x", "w"))
    assert sol.status == "success" and error < 1e-5  # measured 1.9e-6 (w)
    assert sol.stats["error_estimate"] == pytest.approx(error / 2, rel=0.1)  # (relative to 1 + max|u| ~ 2)
    assert 1e-10 < sol.drift()["c"] < 1e-5  # a penalty, not kept to rounding: measured 6.7e-7


def test_a_model_without_a_symbolic_jacobian_is_refused_with_the_reason(method):
    """Fekete's 4,080 Jacobian nonzeros are past the 400 up to which daemodel writes a symbolic Jacobian:
    the message said "equations whose derivatives daemodel does not generate (e.g. of Abs)", which
    Fekete does not have; it names the count now."""
    from daemodel.problems import FEKETE

    with pytest.raises(
        E.UnsupportedModelError,
        match=r"model 'fekete' has no symbolic Jacobian, which the constraint layer needs \(daemodel writes one for "
        r"at most 400 nonzeros, this one has 4080, and none where an equation's derivative is not generated",
    ):
        dm.solve(FEKETE.model(), FEKETE.t_span, method=NAME, iterations=5)

"""Adaptive radau's outputs of algebraic variables of index 2 (backends/radau/outputs.py): solved from
the returned states, so that "success" holds for them as for the states, at the step ends, at t_eval,
between the steps (``at()``), in a batch and in a file; the collocation's distance from them reported.

Measured before (collocation values, their estimate weighed by h as in RADAU5; status success): three
stages at rtol = atol = 1e-8 and 1e-10 left the circle's z 57 and 212 tolerances off its closed form
at the step ends, the Hessenberg example's y5 3.3 and 10.5; solved from the states, 0.00 and 0.04-0.05.
"""

import warnings

import numpy as np
import pytest
import sympy as sp

import daemodel as dm
from daemodel.compiling import algebraic
from daemodel.errors import InitialisationError, LocalErrorWarning
from daemodel.problems import HESSENBERG, PENDULUM


def _circle():
    """A Hessenberg index-2 system with a closed form (as tests/backends/test_radau_error.py's):
    ``y = (cos t, sin t, e^-t)``, ``z = 1 + sin(3t)/2``, y3 stiff (rate 1000)."""
    m = dm.Model("circle")
    y1, y2, y3 = m.states("y1 y2 y3")
    (z,) = m.algebraics("z")
    t = m.t
    ze = 1 + sp.sin(3 * t) / 2
    m.ode(y1, -y2 - y1 * ze + y1 * z)
    m.ode(y2, y1 - y2 * ze + y2 * z)
    m.ode(y3, -1000.0 * (y3 - sp.exp(-t)) - sp.exp(-t) - y3 * ze + y3 * z)
    m.constraint(y1**2 + y2**2 - 1, name="circle")
    m.initial(y1=1.0, y2=0.0, y3=1.0)
    exact = {"y1": np.cos, "y2": np.sin, "y3": lambda t: np.exp(-t), "z": lambda t: 1 + np.sin(3 * t) / 2}
    return m, exact


def _hessenberg():
    closed = HESSENBERG.exact_solution()
    return HESSENBERG.model(), {n: (lambda t, n=n: np.ravel(closed(t)[n])) for n in ("y1", "y2", "y3", "y4", "y5")}


def _in_tolerances(values, exact, tol) -> float:
    """The largest ``|value - exact| / (tol + tol |exact|)``."""
    values, exact = np.asarray(values, dtype=float), np.asarray(exact, dtype=float)
    return float(np.max(np.abs(values - exact) / (tol + tol * np.abs(exact))))


@pytest.mark.parametrize("problem", [_circle, _hessenberg])
@pytest.mark.parametrize("rtol", [1e-8, 1e-10])
def test_index2_algebraic_outputs_are_within_the_tolerance_of_the_closed_form(problem, rtol):
    """Three stages: z at every step end, at t_eval and at() between the steps within one tolerance of
    the closed form (measured 0.00-0.13; before 3.3-212 at the step ends), with the collocation's
    distance (the estimate of its error) reported, above a tolerance here."""
    model, exact = problem()
    compiled = model.compile()
    (name,) = compiled.algebraic_names
    sol = dm.solve(compiled, (0.0, 1.0), rtol=rtol, atol=rtol, stages=3)
    assert sol.status == "success"
    assert _in_tolerances(sol[name], exact[name](sol.t), rtol) < 1.0
    assert sol.stats["algebraic_resolved"] is True
    assert sol.stats["algebraic_correction"] > 1.0
    assert sol.stats["algebraic_correction_at"].startswith(f"'{name}' at t = ")
    between = np.linspace(0.0, 1.0, 41)
    assert _in_tolerances(sol.at(between)[name], exact[name](between), rtol) < 1.0
    asked = dm.solve(compiled, (0.0, 1.0), rtol=rtol, atol=rtol, stages=3, t_eval=between)
    assert _in_tolerances(asked[name], exact[name](between), rtol) < 1.0
    np.testing.assert_allclose(sol.at(between)[name], asked[name], rtol=1e-12, atol=1e-14)  # the same evaluation


def test_the_pendulum_at_index_2_against_scipy_and_its_energy():
    """The pendulum (velocity-level constraint) over [0, 10], three stages at rtol = atol = 1e-7: y5 at
    every step end within one tolerance of scipy's at 1e-12 (the reference method, z solved from its
    states), and of the value its conserved energy gives at radau's own y2:
    ``y5 = (y3^2 + y4^2 - lam y2) / (y1^2 + y2^2)`` with ``y3^2 + y4^2 = 2 (E - lam y2)``."""
    compiled = PENDULUM.model().compile()
    sol = dm.solve(compiled, (0.0, 10.0), rtol=1e-7, atol=1e-7, stages=3)
    assert sol.status == "success"
    ref = dm.solve(compiled, (0.0, 10.0), method="reference", rtol=1e-12, atol=1e-12, t_eval=sol.t)
    assert _in_tolerances(sol["y5"], ref["y5"], 1e-7) < 1.0
    lam = PENDULUM.parameters["lam"]
    energy = 0.5 * (0.0**2 + 1.0**2) + lam * 0.0  # y3(0) = 0, y4(0) = 1, y2(0) = 0, m = 1
    from_energy = (2 * (energy - lam * sol["y2"]) - lam * sol["y2"]) / (sol["y1"] ** 2 + sol["y2"] ** 2)
    assert _in_tolerances(sol["y5"], from_energy, 1e-7) < 1.0


def test_a_batch_on_the_torch_engine_and_a_file_keep_them(tmp_path):
    """Two samples on the torch engine: z within one tolerance at the step ends and between them; saved
    and loaded, at() still solves them from the states (the mark is in the file)."""
    model, exact = _circle()
    compiled = model.compile()
    sol = dm.solve(compiled, (0.0, 1.0), rtol=1e-8, atol=1e-8, stages=3, y0={"y3": [1.0, 1.0]}, engine="torch")
    assert sol.status == "success"
    assert _in_tolerances(sol["z"], exact["z"](sol.t)[None, :], 1e-8) < 1.0
    between = np.linspace(0.0, 1.0, 17)
    assert _in_tolerances(sol.at(between)["z"], exact["z"](between)[None, :], 1e-8) < 1.0
    single = dm.solve(compiled, (0.0, 1.0), rtol=1e-8, atol=1e-8, stages=3)
    path = single.save(tmp_path / "circle.npz")
    loaded = dm.Solution.load(path, compiled)
    np.testing.assert_allclose(loaded.at(between)["z"], single.at(between)["z"], rtol=0, atol=1e-15)
    assert _in_tolerances(loaded.at(between)["z"], exact["z"](between), 1e-8) < 1.0


def test_fixed_steps_keep_the_collocation_values():
    """A fixed grid returns the collocation solution (what h asks for; the Radau-PINN's certificate is
    measured against it): no algebraic variable solved again, the dense output not marked."""
    compiled = HESSENBERG.model().compile()
    sol = dm.solve(compiled, (0.0, 1.0), h=0.1, stages=3)
    assert "algebraic_resolved" not in sol.stats
    assert not sol.dense.resolves_algebraic
    index1 = dm.solve(compiled.reduced(index=1), (0.0, 1.0), rtol=1e-6, atol=1e-6)  # (index 1: nothing to do)
    assert "algebraic_resolved" not in index1.stats


def test_outputs_where_newton_fails_keep_the_collocation_values_and_are_flagged(monkeypatch):
    """Where the algebraic variables cannot be solved from the states (here: no Newton step allowed), the
    outputs keep the collocation's values, and the status says so with a LocalErrorWarning."""
    monkeypatch.setattr(algebraic, "RESOLVE_MAX_ITERATIONS", 0)
    model, exact = _hessenberg()
    with pytest.warns(LocalErrorWarning, match="could not be solved from the states"):
        sol = dm.solve(model.compile(), (0.0, 1.0), rtol=1e-10, atol=1e-10, stages=3)
    assert sol.status.startswith("flagged: radau: the algebraic variables could not be solved from the states at t = ")
    assert "their values there are the collocation's" in sol.status
    assert _in_tolerances(sol["y5"], exact["y5"](sol.t), 1e-10) > 1.0  # (the collocation's: several tolerances off)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InitialisationError, match=r"at\(\): the algebraic variables could not be solved"):
            sol.at([0.5])


def test_outputs_solved_a_few_at_a_time_are_the_same(monkeypatch):
    """The outputs are solved in chunks within RESOLVE_BYTES of z Jacobians: three at a time gives the
    values of all at once (on the numpy path: the Hessenberg example's determining equation is affine in y5,
    which the affine step would otherwise solve)."""
    monkeypatch.setattr(algebraic, "affine_step", lambda _: None)
    compiled = HESSENBERG.model().compile()
    whole = dm.solve(compiled, (0.0, 1.0), rtol=1e-8, atol=1e-8, stages=3)
    monkeypatch.setattr(algebraic, "RESOLVE_BYTES", 3 * 8)  # (m = 1: three outputs a chunk)
    chunked = dm.solve(compiled, (0.0, 1.0), rtol=1e-8, atol=1e-8, stages=3)
    assert len(chunked.t) > 10
    np.testing.assert_array_equal(chunked["y5"], whole["y5"])


def test_an_event_search_reads_the_algebraic_variables_that_at_gives():
    """columns_at (what an event search reads between outputs) gives at()'s values: a guard on an index-2
    variable is searched on the values the solution reports (it read the collocation's, 57 tolerances off
    at rtol 1e-8 on the circle)."""
    model, exact = _circle()
    sol = dm.solve(model.compile(), (0.0, 1.0), rtol=1e-8, atol=1e-8, stages=3)
    times = np.linspace(0.0, 1.0, 23)
    read = sol.columns_at(times, ("y1", "z"))
    np.testing.assert_allclose(read[:, 1], sol.at(times)["z"], rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(read[:, 0], sol.at(times)["y1"], rtol=0, atol=0)
    assert _in_tolerances(read[:, 1], exact["z"](times), 1e-8) < 1.0


def test_each_pieces_affine_step_is_made_in_the_setup(monkeypatch):
    """Between breakpoints radau solves each piece's own model, which solve() did not prepare: its affine step (the
    algebraic variables' solve at the outputs) is made in radau's setup, never inside the solve at the outputs (on
    the solve clock)."""
    from daemodel.backends.radau import backend

    m = dm.Model("pushed_pendulum")
    x, y, u, v = m.states("x y u v")
    (lam,) = m.algebraics("lam")
    push = sp.Piecewise((0.0, m.t < 0.5), (2.0, True))
    m.ode(x, u)
    m.ode(y, v)
    m.ode(u, -lam * x + push)
    m.ode(v, -lam * y - 9.81)
    m.constraint(x**2 + y**2 - 1, name="rod")
    m.initial(x=1.0, y=0.0, u=0.0, v=0.0)
    compiled = m.compile()
    made, inside = [], []
    make, resolve = algebraic._make_affine_step, backend.resolve_outputs
    monkeypatch.setattr(algebraic, "_make_affine_step", lambda c: made.append(bool(inside)) or make(c))

    def resolving(*arguments):
        inside.append(1)
        try:
            return resolve(*arguments)
        finally:
            inside.clear()

    monkeypatch.setattr(backend, "resolve_outputs", resolving)
    sol = dm.solve(compiled, (0.0, 1.0), rtol=1e-6, atol=1e-6)
    assert sol.status == "success" and sol.stats["segments"] == 2
    assert made and not any(made)  # (made, and never inside the solve at the outputs)

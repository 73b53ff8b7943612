"""Consistent initialisation: checks, z0 from the hidden constraints, least-change repair."""

import numpy as np
import pytest
import sympy as sp

import daemodel as dm
from daemodel import errors as E


@pytest.mark.parametrize("theta", [0.3, 1.2, -2.0])
@pytest.mark.parametrize("omega", [0.0, 0.7])
def test_pendulum_z0_matches_closed_form(pendulum, theta, omega):
    # y = (cos, sin) on the circle, velocity tangent; g' = 0 gives y5 = (omega^2 - lam y2 / m) / 1 for m = lam = 1
    y1, y2 = np.cos(theta), np.sin(theta)
    pendulum.initial(y1=y1, y2=y2, y3=-omega * y2, y4=omega * y1)
    c = pendulum.compile()
    assert c.z0[0] == pytest.approx(omega**2 - y2, abs=1e-14)


def test_index3_pendulum_z0(pendulum3):
    theta, omega = 0.4, 1.5
    pendulum3.initial(y1=np.cos(theta), y2=np.sin(theta), y3=-omega * np.sin(theta), y4=omega * np.cos(theta))
    assert pendulum3.compile().z0[0] == pytest.approx(omega**2 - np.sin(theta), abs=1e-14)


def test_given_algebraic_value_checked(hessenberg):
    hessenberg.initial(y5=1.0)
    assert hessenberg.compile().notes == ()
    hessenberg.initial(y5=2.0)
    with pytest.raises(
        E.InconsistentAlgebraicValueError,
        match=r"initial value y5 = 2 disagrees with the consistent value y5 = 1\.0 determined by the constraints",
    ):
        hessenberg.compile()
    c = hessenberg.compile(repair=True)
    assert c.z0[0] == pytest.approx(1.0, abs=1e-15)
    assert c.notes == ("replaced y5 = 2 by the consistent value 1.0",)


def test_inconsistent_state_is_named(hessenberg):
    hessenberg.initial(y1=1.1)
    with pytest.raises(
        E.InconsistentInitialStateError,
        match=r"violates constraint 'invariant' \(#5\): invariant = 0\.1 \(tolerance .*compile\(repair=True\)",
    ):
        hessenberg.compile()


def _kkt_residual(c, y0_given, levels):
    """Distance of y - y0 from the row space of the constraint Jacobian (zero at the least change)."""
    y = c.y0
    jac = sp.Matrix(levels).jacobian(list(c.states))
    C = np.array(jac.subs(dict(zip(c.states, y, strict=True))).evalf(), dtype=float).reshape(len(levels), len(y))
    d = y - y0_given
    coef = np.linalg.lstsq(C.T, d, rcond=None)[0]
    return np.linalg.norm(C.T @ coef - d), np.linalg.norm(d)


def test_repair_is_least_change_projection(hessenberg):
    hessenberg.initial(y1=1.1, y2=0.9)
    c = hessenberg.compile(repair=True)
    y1, y2, y3, y4 = c.y0
    assert abs(y1 * y4 - y2 * y3) < 1e-14
    off_normal, moved = _kkt_residual(c, np.array([1.1, 0.9, 1.0, 1.0]), [c.g[0]])
    assert moved > 0.05 and off_normal < 1e-12
    assert c.notes[0].startswith("repaired y0 (least change")
    assert c.z0[0] == pytest.approx(_hessenberg_z(c.y0), rel=1e-12)  # z0 follows the repaired y0


def _hessenberg_z(y):
    # invariant' = 0 is linear in y5: y5 (y4 (y1 y2 + y3 y4) + y2^2 y3^2 y4^2) = 3 y1 y2^2 y3 y4
    y1, y2, y3, y4 = y
    return 3 * y1 * y2**2 * y3 * y4 / (y4 * (y1 * y2 + y3 * y4) + y2**2 * y3**2 * y4**2)


def test_hidden_constraint_of_index3_checked_and_repaired(pendulum3):
    pendulum3.initial(y1=1.2, y2=0.1, y3=0.3, y4=1.0)
    with pytest.raises(
        E.InconsistentInitialStateError,
        match=r"constraint 'rod' \(#5\): rod = 0\.45; hidden constraint rod' of constraint 'rod' \(#5\): rod' = 0\.92",
    ):
        pendulum3.compile()
    c = pendulum3.compile(repair=True)
    y1, y2, y3, y4 = c.y0
    assert abs(y1**2 + y2**2 - 1) < 1e-14 and abs(y1 * y3 + y2 * y4) < 1e-14
    chain = c.constraints[0].chain
    off_normal, _ = _kkt_residual(c, np.array([1.2, 0.1, 0.3, 1.0]), [chain[0], chain[1]])
    assert off_normal < 1e-12


def test_repair_fails_without_real_solution():
    m = dm.Model("imaginary")
    (y,) = m.states("y")
    (z,) = m.algebraics("z")
    m.ode(y, z)
    m.constraint(y**2 + 1, name="circle")
    m.initial(y=0.5)
    with pytest.raises(
        E.InitialisationError, match=r"repair could not project the initial state onto constraint 'circle'"
    ):
        m.compile(repair=True)


def test_newton_failure_asks_for_a_start_value():
    m = dm.Model("logarithmic")
    (y,) = m.states("y")
    (z,) = m.algebraics("z")
    m.ode(y, -z)
    m.constraint(sp.log(z) - y, name="law")
    m.initial(y=0.5)
    with pytest.raises(
        E.InitialisationError, match=r"did not converge: constraint 'law' \(#2\).*m\.guess\(<algebraic>=\.\.\.\)"
    ):
        m.compile()
    m.guess(z=1.0)  # a starting value picks the root and claims nothing
    assert m.compile().z0[0] == pytest.approx(np.exp(0.5), rel=1e-15)
    m.initial(z=1.0)  # an initial value is also a claim: it is checked against the root found
    with pytest.raises(E.InconsistentAlgebraicValueError, match=r"consistent value z = 1\.6487212707"):
        m.compile()
    assert m.compile(repair=True).z0[0] == pytest.approx(np.exp(0.5), rel=1e-15)


def test_consistent_projects_a_batch_with_the_least_change():
    """compiled.consistent(y0=...) moves each sample to the nearest state on the constraints (for a
    linear constraint, the orthogonal projection), for one sample or a batch; solve accepts the
    result, and the error for inconsistent states points to it."""
    m = dm.Model("line")
    a, b = m.states("a b")
    (w,) = m.algebraics("w")
    m.ode(a, w)
    m.ode(b, -a)
    m.constraint(a + b - 1, name="line")  # index 2: the hidden level a' + b' = w - a = 0 fixes w
    m.initial(a=0.25, b=0.75)
    c = m.compile()
    y0 = {"a": np.array([0.0, 1.0, 0.5]), "b": np.array([0.0, 1.0, 0.2])}
    with pytest.raises(dm.errors.InconsistentInitialStateError, match=r"compiled\.consistent\(y0=\.\.\.\)"):
        dm.solve(c, (0.0, 0.1), h=0.05, y0=y0)
    fixed = c.consistent(y0=y0)
    shift = (y0["a"] + y0["b"] - 1) / 2  # the orthogonal projection onto a + b = 1
    np.testing.assert_allclose(fixed["a"], y0["a"] - shift, rtol=0, atol=1e-15)
    np.testing.assert_allclose(fixed["b"], y0["b"] - shift, rtol=0, atol=1e-15)
    sol = dm.solve(c, (0.0, 0.1), h=0.05, y0=fixed)
    assert sol.drift()["line"] < 1e-14
    assert c.consistent(y0={"a": 0.5, "b": 0.7}) == pytest.approx({"a": 0.4, "b": 0.6}, abs=1e-15)
    assert c.consistent() == {"a": 0.25, "b": 0.75}  # the model's own, consistent already


def test_consistent_pendulum_positions_and_velocities():
    """Index 3: the position and the velocity levels both hold after the projection."""
    from daemodel.problems import PENDULUM_INDEX3

    c = PENDULUM_INDEX3.model().compile()
    rng = np.random.default_rng(0)
    y0 = dict(zip(c.state_names, rng.normal(size=(len(c.state_names), 20)), strict=True))
    fixed = c.consistent(y0=y0)
    sol = dm.solve(c, (0.0, 0.2), h=0.05, y0=fixed)
    assert max(sol.drift().values()) < 1e-8


def _square_root_model() -> dm.Model:
    m = dm.Model("square_root")
    (x,) = m.states("x")
    (z,) = m.algebraics("z")
    m.ode(x, -z)
    m.constraint(z**2 - x, name="root")  # z = +-sqrt(x); g_z = 2 z vanishes at z = 0
    m.initial(x=1.0)
    return m


def test_guess_picks_the_root_and_claims_nothing():
    """0 = z^2 - x has two roots: m.guess picks one without claiming it, and without a guess the
    error says that z = 0 is only Newton's starting point and how to give one."""
    m = _square_root_model()
    message = (
        r"g_z is singular at t=0 .* at the initial point: that point is Newton's starting guess z = 0, from which "
        r"it cannot take a step; no guess was given for z\. Give a guess near the root you want, e\.g\. "
        r"m\.guess\(z=1\.0\) \(a starting value that picks the root, not a claim\)"
    )
    with pytest.raises(dm.errors.SingularSystemError, match=message):
        m.compile()
    m.guess(z=-0.3)
    assert m.compile().z0 == pytest.approx([-1.0], abs=1e-14)
    m.guess(z=5.0)  # far from the root: a guess, not a claim that must agree
    assert m.compile().z0 == pytest.approx([1.0], abs=1e-14)
    with pytest.raises(dm.errors.UnknownSymbolError, match=r"m\.guess: 'x' is a differential variable"):
        m.guess(x=2.0)
    with pytest.raises(dm.errors.UnknownSymbolError, match=r"m\.guess: 'q' is not declared"):
        m.guess(q=2.0)


def test_repair_beyond_the_dense_limit_is_refused_before_the_projection(hessenberg, monkeypatch):
    import daemodel.files

    monkeypatch.setattr(daemodel.files, "DENSE_MAX_ORDER", 1)  # (one constraint on 4 states: order 2)
    hessenberg.initial(y1=1.1, y2=0.9)
    with pytest.raises(
        E.ResourceLimitError,
        match=r"projection onto the constraints \(1 constraint levels on 4 states\) works on dense 2 x 2 matrices "
        r".*above its limit of 1 x 1: give initial states that satisfy",
    ):
        hessenberg.compile(repair=True)

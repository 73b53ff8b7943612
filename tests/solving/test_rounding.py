"""The size at which an event function's or a reset's evaluation rounds (daemodel/solving/rounding.py): its terms in
absolute value, each input at its own size, never an absolute 1; against sizes worked out by hand."""

import numpy as np
import pytest
import sympy as sp

import daemodel as dm
from daemodel.solving.rounding import ROUNDING, floor_at, magnitude, within_rounding

x, y, t, z = sp.symbols("x y t z", real=True)


@pytest.mark.parametrize(
    ("expr", "values", "size"),
    [
        (x, {x: 1e-25}, 1e-25),  # (a height at 1e-25 rounds at 1e-25, not at 1)
        (x - 1, {x: 1.0}, 2.0),  # (at zero, its terms are 1 and 1)
        (1e8 * x - 1, {x: 1e-8}, 2.0),  # (not |x| = 1e-8: the coefficient counts)
        (x * y - 1, {x: -4.0, y: -0.25}, 2.0),
        (x**2 - 1, {x: -1.0}, 2.0),
        (1 / x - 1e14, {x: 1e-14}, 2e14),  # (a power by its relative error: 1/x's is x's)
        (sp.sin(x) - sp.Rational(1, 2), {x: float(sp.pi / 6)}, 0.5 + 0.5 + float(sp.pi / 6)),
        (sp.exp(x) - 1, {x: 2.0}, float(sp.exp(2.0)) * 3 + 1),
        (sp.Max(x, y) - 3, {x: 3.0, y: -2.0}, 3 + 3 + 2 + 3),
        (x - t, {x: 5.0, t: 5.0}, 10.0),  # (t at its own size where the function names it)
        (z, {z: 1e-25}, 1.0 + 1e-25),  # (an algebraic variable at 1 + |z|: Newton's unit for it)
    ],
)
def test_magnitude_is_the_size_of_the_terms(expr, values, size):
    got = float(magnitude(expr, frozenset({z})).subs(values))
    assert got == pytest.approx(size, rel=1e-12)


def test_a_power_of_a_difference_at_zero_has_no_finite_floor():
    # sqrt(x - 1) at x = 1: the relative error of x - 1 is unbounded there (no size tells a value from zero); sqrt(x)
    # at x = 0 rounds at 0 (x's relative error is its own)
    m = dm.Model("root")
    m.states("x")
    m.ode("x", "1")
    m.initial(x=1.0)
    compiled = m.compile()
    (state,) = compiled.states
    exprs = (sp.sqrt(state - 1), sp.sqrt(state), state - 2)
    floor = floor_at(compiled, exprs, 0.0, np.array([[1.0]]), np.zeros((1, 0)), np.zeros((1, 0)))
    assert floor.tolist() == [np.inf, ROUNDING * 1.0, ROUNDING * 3.0]
    floor = floor_at(compiled, exprs, 0.0, np.array([[0.0]]), np.zeros((1, 0)), np.zeros((1, 0)))
    assert floor[1:].tolist() == [0.0, ROUNDING * 2.0]


def test_within_rounding_zeroes_only_what_is_within_its_own_floor():
    change = within_rounding(np.array([1e-22, -1e-22, 3e-14, -1e-16]), np.array([1e-38, 2e-22, 1e-14, 1e-16]))
    assert change.tolist() == [1e-22, 0.0, 3e-14, 0.0]

"""The residue of an expression's exact value modulo a prime: the residue of :func:`exact_value`, None where
it is None, checked on random rational expressions against Python's fractions."""

from fractions import Fraction

import sympy as sp
from hypothesis import given, settings
from hypothesis import strategies as st

from daemodel.compiling.prune import find_alias
from daemodel.compiling.zero_test import MODULUS, exact_value, modular_value, point_value

x, y, z = sp.symbols("x y z")
LEAVES = [x, y, z, sp.Integer(3), sp.Rational(-2, 7), sp.Integer(0), sp.Float("0.5"), sp.sqrt(2)]
UNARY = [lambda e: -e, lambda e: 1 / e, lambda e: e**2, lambda e: e**-3, sp.sin]
BINARY = [sp.Add, sp.Mul, lambda a, b: a - b, lambda a, b: a / b]


def expressions():
    return st.recursive(
        st.sampled_from(LEAVES),
        lambda inner: st.one_of(
            st.tuples(st.sampled_from(UNARY), inner).map(lambda p: p[0](p[1])),
            st.tuples(st.sampled_from(BINARY), inner, inner).map(lambda p: p[0](p[1], p[2])),
        ),
        max_leaves=10,
    ).filter(lambda e: not e.has(sp.zoo, sp.nan))


def residue(value: Fraction) -> int:
    return value.numerator * pow(value.denominator, -1, MODULUS) % MODULUS


@settings(max_examples=200, deadline=None)
@given(expressions())
def test_the_residue_is_that_of_the_exact_value(expr):
    exact, modular = exact_value(expr), modular_value(expr)
    if exact is None:
        assert modular is None
    else:
        assert modular == residue(exact)


def test_what_has_no_exact_value_has_no_residue():
    assert modular_value(x + sp.Float("0.5")) is None  # (a float: rounding)
    assert modular_value(sp.sqrt(x)) is None
    assert modular_value(x**65) is None  # (beyond MAX_EXACT_POWER, as exact_value)
    at = point_value(y)
    assert modular_value(1 / (y - sp.Rational(at.numerator, at.denominator))) is None  # (a pole at the point)
    assert exact_value(1 / (y - sp.Rational(at.numerator, at.denominator))) is None
    assert modular_value(x / MODULUS) is None  # (a denominator that is a multiple of the modulus)


def test_aliases_are_found_through_the_residues():
    symbols = {x, y, z}
    assert find_alias(3 * (x - y), [x], symbols) == (x, y)
    assert find_alias(-2 * x - 2 * y, [x], symbols) == (x, -y)
    assert find_alias(sp.Rational(1, 5) * x - sp.Rational(1, 5) * z, [x], symbols) == (x, z)
    assert find_alias(x - y**2 / (1 + y), [x], symbols) is None
    assert find_alias(x - y - z + z, [x], symbols) == (x, y)
    assert find_alias(x - y * (y + 1) / (y + 1), [x], symbols) == (x, y)  # (sympy cancels: a plain alias)
    assert find_alias(x - (y**2 + y) / (y + 1), [x], symbols) == (x, y)  # (the same rational function)

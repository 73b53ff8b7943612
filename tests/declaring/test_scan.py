"""The one walk of a declared expression answers as sympy's own questions do (free symbols, ``has``,
``check_numbers``), checked on random expressions and on the cases where it must defer to sympy."""

import pytest
import sympy as sp
from hypothesis import given, settings
from hypothesis import strategies as st

from daemodel.declaring.parse import check_numbers
from daemodel.declaring.scan import scan
from daemodel.errors import ExpressionParseError

x, y, z = sp.symbols("x y z")
LEAVES = [x, y, z, sp.Integer(2), sp.Rational(1, 3), sp.Float("0.25"), sp.pi, sp.Integer(-7)]
UNARY = [sp.sin, sp.exp, sp.sqrt, sp.Abs, lambda a: -a, lambda a: 1 / a]
BINARY = [
    sp.Add,
    sp.Mul,
    lambda a, b: a**b,
    lambda a, b: sp.Piecewise((a, x > 1), (b, True)),
    lambda u, v: _max_of_sizes(u, v),
]


def _max_of_sizes(u, v):
    """Max(|u|, |v|), unevaluated where sympy cannot compare the two (|a complex constant| it keeps as a
    nested radical: a ValueError "not comparable" while the example was generated)."""
    try:
        return sp.Max(sp.Abs(u), sp.Abs(v))
    except (ValueError, TypeError):
        return sp.Max(sp.Abs(u), sp.Abs(v), evaluate=False)


def expressions():
    leaf = st.sampled_from(LEAVES)
    return st.recursive(
        leaf,
        lambda inner: st.one_of(
            st.tuples(st.sampled_from(UNARY), inner).map(lambda p: p[0](p[1])),
            st.tuples(st.sampled_from(BINARY), inner, inner).map(lambda p: p[0](p[1], p[2])),
        ),
        max_leaves=12,
    )


def numbers_pass(expr) -> bool:
    try:
        check_numbers(expr, "test")
    except (ExpressionParseError, OverflowError, TypeError):
        return False
    return True


@settings(max_examples=300, deadline=None)
@given(expressions())
def test_the_walk_answers_as_sympy(expr):
    found = scan(expr)
    if found.symbols is not None:
        assert found.symbols == expr.free_symbols
    for kind in (sp.Piecewise, sp.Pow, sp.sin, sp.Symbol, sp.Max, sp.ITE):
        assert found.holds(kind) == expr.has(kind)
    if found.numbers_plain:  # (False only sends the expression to check_numbers)
        assert numbers_pass(expr)


@pytest.mark.parametrize(
    "expr",
    [x / 0, x + sp.oo, x * sp.nan, x + sp.I, sp.exp(1000) * x, sp.sqrt(2) * x, x + 2 * sp.pi, sp.Integer(1) / 0],
)
def test_constants_that_need_a_closer_look_are_left_to_check_numbers(expr):
    assert not scan(expr).numbers_plain


def test_bound_variables_leave_the_free_symbols_to_sympy():
    integral = sp.Integral(x * y, (x, 0, 1))
    found = scan(integral)
    assert found.symbols is None and integral.free_symbols == {y}
    assert not found.numbers_plain  # (an integral over x is a number where y is absent)


def test_a_plain_equation_is_answered_by_the_walk():
    found = scan(y - x**2 / (1 + x) + sp.Rational(1, 3) * sp.sin(z))
    assert found.symbols == {x, y, z} and found.numbers_plain
    assert scan(x).symbols == {x} and scan(sp.Integer(3)).symbols == frozenset()


def test_the_declaration_hands_each_equation_s_free_symbols_to_the_compiler():
    import daemodel as dm

    m = dm.Model("seeded")
    (u,) = m.states("u")
    v = m.states("v", 3)
    (w,) = m.algebraics("w")
    k = m.parameter("k", 2.0)
    m.ode(u, -k * u + w)
    m.ode(v, [v[1] - v[0], sp.sin(v[2]) * u, "2*v[0]"])
    m.constraint(w - u**2 / (1 + u), name="rate")
    declared = m.declared()
    equations = [*declared.odes.values(), *declared.constraints]
    assert all(declared.free_symbols[eq.expr] == eq.expr.free_symbols for eq in equations)
    assert declared.free_symbols[declared.odes["v[1]"].expr] == {v[2], u}

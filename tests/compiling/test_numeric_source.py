"""Expressions of one shape are printed once: every expression's text is what printing it alone gives,
character for character (so the generated functions, and their numbers, are those printed one by one)."""

import numpy as np
import pytest
import scipy.optimize
import sympy as sp
from hypothesis import given, settings
from hypothesis import strategies as st

import daemodel as dm
from daemodel.compiling.numeric_source import NumericPrinter, holds_re, shape_key, shared_subexpressions

SYMBOLS = sp.symbols("a b c d")
NAMES = {s: f"_y[{k}]" for k, s in enumerate(SYMBOLS)}
LEAVES = [*SYMBOLS, sp.Integer(2), sp.Rational(-1, 3), sp.Float("0.5"), sp.pi]
UNARY = [sp.sin, sp.exp, sp.sqrt, sp.Abs, lambda e: -e, lambda e: 1 / e, lambda e: e**2]
BINARY = [
    sp.Add,
    sp.Mul,
    lambda u, v: sp.Piecewise((u, SYMBOLS[0] > 1), (v, True)),
    lambda u, v: sp.Max(sp.Abs(u), sp.Abs(v)),
]


def expressions():
    return st.recursive(
        st.sampled_from(LEAVES),
        lambda inner: st.one_of(
            st.tuples(st.sampled_from(UNARY), inner).map(lambda p: p[0](p[1])),
            st.tuples(st.sampled_from(BINARY), inner, inner).map(lambda p: p[0](p[1], p[2])),
        ),
        max_leaves=8,
    ).filter(lambda e: not e.has(sp.zoo, sp.oo, -sp.oo, sp.nan, sp.I))  # (the declaration refuses these)


def alone(expr, shared) -> str:
    """The text of ``expr`` printed by a printer that has printed nothing else, without shapes."""
    return NumericPrinter(NAMES, shared, False)._doprint(expr, None)


@settings(max_examples=60, deadline=None)
@given(st.lists(expressions(), min_size=1, max_size=6), st.permutations(range(4)))
def test_each_text_is_the_text_printed_alone(exprs, order):
    # the same shapes again over other variables: the printer's second sight of each shape
    renamed = [e.xreplace({s: SYMBOLS[order[k]] for k, s in enumerate(SYMBOLS)}) for e in exprs]
    exprs = [sp.sympify(e) for e in exprs + renamed]
    shared = shared_subexpressions(exprs)
    printer = NumericPrinter(NAMES, shared, False)
    for expr in exprs:
        assert printer.doprint(expr) == alone(expr, shared)


def test_one_shape_over_other_variables_has_one_key():
    a, b, c, d = SYMBOLS
    first, second = shape_key(a - b**2 / (1 + b), NAMES, {}), shape_key(c - d**2 / (1 + d), NAMES, {})
    assert first[0] == second[0] and first[1] == [a, b] and second[1] == [c, d]
    assert shape_key(a - b**2 / (1 + a), NAMES, {})[0] != first[0]  # (another variable at a leaf)
    assert shape_key(a - b**3 / (1 + b), NAMES, {})[0] != first[0]  # (another number)
    assert shape_key(a - b**2 / (2 + b), NAMES, {})[0] != first[0]


def test_what_has_no_shape_is_printed_alone():
    a, b = SYMBOLS[:2]
    assert shape_key(a + sp.Symbol("other"), NAMES, {}) is None  # a symbol with no name given
    inner = 1 + b
    assert shape_key(a * inner, NAMES, {inner: "_c0"}) is None  # (a shared subexpression prints as its name)
    assert shape_key(inner, NAMES, {inner: "_c0"}) is not None  # (except at the top: its definition)
    printer = NumericPrinter(NAMES, {inner: "_c0"}, False)
    assert printer.doprint(a * inner) == "_y[0]*(_c0)"  # (as printed without shapes)


@settings(max_examples=60, deadline=None)
@given(st.lists(expressions(), min_size=1, max_size=6), st.lists(st.booleans(), min_size=6, max_size=6))
def test_holds_re_is_any_has_re(exprs, wrap):
    # re(...) around some of them (at the top, or deeper inside a sum): shaped or not, shared or not
    exprs = [sp.sympify(e) for e in exprs]
    exprs = [
        (sp.re(e) if k % 2 else SYMBOLS[1] + 2 * sp.re(e)) if w else e
        for k, (e, w) in enumerate(zip(exprs, wrap, strict=False))
    ]
    shared = shared_subexpressions(exprs)
    shapes = [shape_key(e, NAMES, shared) for e in exprs]
    assert holds_re(exprs, shapes) == any(e.has(sp.re) for e in exprs)


def test_holds_re_reads_an_re_from_a_shape_key_alone():
    a, b = SYMBOLS[:2]
    exprs = [a + sp.re(b * a), b + sp.re(a * b)]  # (one shape: its key says re)
    shapes = [shape_key(e, NAMES, {}) for e in exprs]
    assert all(s is not None for s in shapes) and holds_re(exprs, shapes)
    plain = [a + sp.sin(b), b + sp.sin(a)]
    assert not holds_re(plain, [shape_key(e, NAMES, {}) for e in plain])


def test_a_constraint_summing_thousands_of_variables_compiles():
    # one row coupling a whole grid: the printed sum was one chain of '+', which Python's compiler
    # recursed through (3,000 terms: a RecursionError from compile)
    K = 3_000
    m = dm.Model("mean")
    c = m.states("c", K)
    w = m.algebraics("w", K)
    (mean,) = m.algebraics("mean")
    C, W = dm.stencil(c), dm.stencil(w)
    m.ode(c, -C - W - mean)
    m.constraint(W - C**2 / (1 + C), name="rate")
    m.constraint(mean + mean**3 / 10 - sp.Add(*c) / K, name="mean")  # (nonlinear: solved by Newton)
    y0 = 1 + np.cos(np.arange(K)) / 2
    m.initial(c=y0)
    compiled = m.compile()
    root = scipy.optimize.brentq(lambda z: z + z**3 / 10 - np.mean(y0), 0.0, 2.0, xtol=1e-15)
    assert compiled.z0[-1] == pytest.approx(root, rel=0, abs=1e-14)
    assert np.allclose(compiled.z0[:-1], y0**2 / (1 + y0), rtol=1e-14, atol=0)

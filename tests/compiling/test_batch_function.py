"""The numeric system's batched functions: casadi evaluates a few samples, numpy larger batches, each made on
first use (daemodel/compiling/batch_function.py)."""

import itertools

import numpy as np
import pytest
import sympy as sp

from daemodel.compiling import batch_function
from daemodel.compiling.init import NumericSystem

t, x, y, z, k = sp.symbols("t x y z k")
EXPRS = [
    sp.sin(x * t) + sp.exp(-z) * y**2,
    sp.sqrt(x) / (1 + y**2),  # (not finite where x < 0: nan on both)
    sp.Piecewise((x * k, y > 0.5), (-z, True)),
    sp.Max(x, y, 0.25) - sp.Min(z, 1),
    sp.Integer(0),  # (a structural zero: a column of the output all the same)
    sp.Float(2.5),
]


def rows(B: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    Y = rng.uniform(0, 2, (B, 2))
    Y[1:, 0] = -Y[1:, 0]  # (x < 0 after the first sample: sqrt(x) is nan there)
    return rng.uniform(-0.5, 1.5, B), Y, rng.uniform(-1, 2, (B, 1)), rng.uniform(1, 3, (B, 1))


@pytest.mark.parametrize("B", [1, 2, batch_function.SAMPLE_ROWS])
def test_a_few_samples_are_evaluated_on_casadi_without_numpy_code(monkeypatch, B):
    """A function evaluated at up to SAMPLE_ROWS samples runs on casadi, and its numpy code is never printed
    (before: lambdified when the function was made, ~1 ms an evaluation at one sample of the wheelset's
    determining equations, 70 ms to print for each locked piece); its values are numpy's to rounding."""
    printed = []
    original = NumericSystem._lambdify
    monkeypatch.setattr(NumericSystem, "_lambdify", lambda self, exprs: printed.append(1) or original(self, exprs))
    numeric = NumericSystem(t, (x, y), (z,), (k,))
    F = numeric.batch_function(EXPRS)
    T, Y, Z, P = rows(B)
    with np.errstate(invalid="ignore"):
        few = F(T, Y, Z, P)
        assert not printed
        # numpy on the same rows and more (a batch above CASADI_ROWS_MAX), the rows compared
        more = rows(batch_function.CASADI_ROWS_MAX, seed=1)
        T5, Y5, Z5, P5 = (np.concatenate([a, b]) for a, b in zip((T, Y, Z, P), more, strict=True))
        many = F(T5, Y5, Z5, P5)[:B]
    assert printed == [1]
    assert few.shape == (B, len(EXPRS))
    np.testing.assert_array_equal(np.isnan(few), np.isnan(many))
    np.testing.assert_allclose(few, many, rtol=4e-16, atol=0)
    assert np.isnan(few[1:, 1]).all() and np.isfinite(few[0]).all()
    # one sample, t a number and Z, P one row for all (as numpy broadcasts them)
    one = F(0.25, Y[:1], Z[:1], P[:1])
    np.testing.assert_allclose(one, F(np.array([0.25] * 5), np.repeat(Y[:1], 5, 0), Z[[0] * 5], P[[0] * 5])[:1])
    np.testing.assert_allclose(F(0.25, Y, Z[:1], P[:1]), F(np.full(B, 0.25), Y, np.repeat(Z[:1], B, 0), P[[0] * B]))

    # a nan among the values: numpy's (Max passes it on, where casadi's fmax would drop it)
    Yn = Y.copy()
    Yn[0, 1] = np.nan
    with np.errstate(invalid="ignore"):
        assert np.isnan(F(T, Yn, Z, P)[0, [0, 1, 3]]).all()
    # the Heaviside of a Max's derivative has no casadi translation: numpy evaluates it, one sample too
    G = numeric.batch_function([sp.diff(sp.Max(x, 0), x), x])
    np.testing.assert_array_equal(G(0.0, np.array([[-1.0], [2.0]]), Z[:1], P[:1]), [[0.0, -1.0], [1.0, 2.0]])
    np.testing.assert_array_equal(G(0.0, np.array([[3.0]]), Z[:1], P[:1]), [[1.0, 3.0]])
    assert printed == [1, 1]


def test_many_expressions_stay_on_numpy_at_one_sample(monkeypatch):
    """A function of more than SAMPLE_EXPRESSIONS expressions (a discretised PDE's 10^4-10^5) is not converted
    to casadi for one sample (one expression at a time, seconds at that size): numpy evaluates it."""
    from daemodel.compiling import codegen

    converted = []
    init = codegen.CasadiConverter.__init__
    monkeypatch.setattr(
        codegen.CasadiConverter, "__init__", lambda self, symbols: converted.append(1) or init(self, symbols)
    )
    n = batch_function.SAMPLE_EXPRESSIONS + 1
    states = sp.symbols(f"u0:{n}")
    numeric = NumericSystem(t, states, (), ())
    F = numeric.batch_function([u**2 - t for u in states])
    Y = np.arange(n, dtype=float)[None, :]
    np.testing.assert_array_equal(F(0.5, Y, np.zeros((1, 0)), np.zeros((1, 0))), Y**2 - 0.5)
    assert not converted
    G = numeric.batch_function([u**2 - t for u in states[:3]])  # (few: converted)
    np.testing.assert_array_equal(G(0.5, Y, np.zeros((1, 0)), np.zeros((1, 0))), Y[:, :3] ** 2 - 0.5)
    assert converted == [1]


def test_a_nan_among_a_max_or_min_s_arguments_is_passed_on_at_a_few_samples():
    """Max(0, sqrt(x)) at x = -1 is nan on numpy (maximum passes a nan on) and was 0 on casadi (fmax drops it)
    at one sample from finite values: a reset to such a Max (InvalidValueError on numpy) went on with "success"
    (tests/solving/test_events_edges.py).  Evaluated on numpy there, at any batch; finite values on casadi."""
    numeric = NumericSystem(t, (x, y), (z,), (k,))
    F = numeric.batch_function([sp.Max(0, sp.sqrt(x)), sp.Min(1, sp.log(x)) + y, sp.Max(1, x / y), sp.sqrt(x) + y])
    for B in (1, 2, batch_function.SAMPLE_ROWS, batch_function.SAMPLE_ROWS + 1):
        with np.errstate(invalid="ignore", divide="ignore"):
            out = F(0.0, np.array([[-1.0, 1.0], [0.0, 0.0]] * B)[:B], np.zeros((1, 1)), np.zeros((1, 1)))
        assert np.isnan(out[0, [0, 1, 3]]).all() and out[0, 2] == 1.0, (B, out)  # (x = -1, y = 1)
        if B > 1:  # (x = y = 0: Max(1, 0/0) is nan)
            assert out[1, 0] == 0.0 and out[1, 1] == -np.inf and np.isnan(out[1, 2]) and out[1, 3] == 0.0, (B, out)
    G = numeric.batch_function([sp.Max(0, sp.sqrt(x)), sp.Min(x, y)])
    np.testing.assert_array_equal(G(0.0, np.array([[4.0, -3.0]]), np.zeros((1, 1)), np.zeros((1, 1))), [[2.0, -3.0]])


def test_more_samples_go_to_casadi_where_the_cost_model_says_it_is_cheaper(monkeypatch):
    """Above SAMPLE_ROWS a function runs on casadi one sample at a time where rows x (1 + I / 1000) us is below
    numpy's 0.2 I us (I its casadi instructions; fitted at 21 samples: 20 pendulums' determining equations
    283 us on numpy, 42.5 on casadi): a tiny function at 21 samples stays on numpy, a large one goes to
    casadi with numpy's values to rounding, and past CASADI_ROWS_MAX everything is numpy's."""
    assert not batch_function.on_casadi(21, 19)  # (the pendulum's determining equation: 5.7 us on numpy)
    assert batch_function.on_casadi(21, 904) and batch_function.on_casadi(5, 60)
    assert not batch_function.on_casadi(batch_function.CASADI_ROWS_MAX + 1, 10**6)
    assert batch_function.on_casadi(batch_function.SAMPLE_ROWS, 1)
    printed = []
    original = NumericSystem._lambdify
    monkeypatch.setattr(NumericSystem, "_lambdify", lambda self, exprs: printed.append(1) or original(self, exprs))
    xs = sp.symbols("x0:40")
    numeric = NumericSystem(t, xs, (z,), (k,))
    large = [
        sum(sp.sin(a * t) * b + sp.exp(-z * a) / (1 + b**2) for a, b in itertools.pairwise(xs)) * (i + k)
        for i in range(8)
    ]
    F = numeric.batch_function(large)
    rng = np.random.default_rng(3)
    K = 300
    T, Y, Z, P = rng.uniform(0, 1, K), rng.uniform(-1, 1, (K, 40)), rng.uniform(0, 1, (K, 1)), rng.uniform(1, 2, (K, 1))
    casadi = F(T[:21], Y[:21], Z[:21], P[:21])
    assert not printed and F._instructions > 400
    numpy = F(T, Y, Z, P)[:21]  # (past CASADI_ROWS_MAX: numpy's code)
    assert printed == [1]
    np.testing.assert_allclose(casadi, numpy, rtol=1e-14, atol=1e-14)
    tiny = numeric.batch_function([xs[0] * k + z])
    tiny(T[:21], Y[:21], Z[:21], P[:21])
    assert printed == [1, 1]  # (a few instructions at 21 samples: numpy's)


def test_many_expressions_are_printed_in_pieces_with_the_same_values(monkeypatch):
    """Above LAMBDIFY_CHUNK expressions the numpy code is several functions, their lists joined in order (one
    code object of 10^4 expressions made each traced allocation look its line up across the whole code): the
    same values bit for bit as one function, a subexpression shared across pieces included, in the function,
    batch function and Jacobian."""
    from daemodel.compiling import init

    n = 3 * init.LAMBDIFY_CHUNK + 7
    states = sp.symbols(f"u0:{n}")
    shared = sp.exp(-states[0] * t)  # (in every expression: each piece computes it once)
    exprs = [shared * u**2 + sp.sin(u * k) / (1 + shared) for u in states]
    rng = np.random.default_rng(3)
    Y, P = rng.uniform(-1, 1, (5, n)), rng.uniform(0.5, 2, (5, 1))
    T = rng.uniform(0, 1, 5)

    def values(numeric):
        F, J = numeric.batch_function(exprs), numeric.batch_jacobian(exprs[:40], states[:40])
        f = numeric.function(exprs)
        return F(T, Y, np.zeros((5, 0)), P), J(T, Y, np.zeros((5, 0)), P), f(0.3, Y[0], np.zeros(0), P[0])

    pieces = values(NumericSystem(t, states, (), (k,)))
    monkeypatch.setattr(init, "LAMBDIFY_CHUNK", n)
    whole = values(NumericSystem(t, states, (), (k,)))
    for a, b in zip(pieces, whole, strict=True):
        np.testing.assert_array_equal(a, b)
    s = np.exp(-Y[:, :1, None] * T[:, None, None])[..., 0]
    np.testing.assert_allclose(pieces[0], s * Y**2 + np.sin(Y * P) / (1 + s), rtol=1e-14)

"""Every number a user gives (options, initial and parameter values, t_span, tolerances) may be a
Python, numpy or sympy real number: one check (daemodel.reals.real) takes them all alike, and
refuses anything else by name."""

import json
import math

import numpy as np
import pytest
import sympy as sp
from daemodel.backends import get_backend

import daemodel as dm
from daemodel import errors as E
from daemodel.reals import real


def decay():
    """x' = -k x, x(0) = 1: x(t) = exp(-k t)."""
    m = dm.Model("decay")
    (x,) = m.states("x")
    k = m.parameter("k", np.float32(1.0))
    m.ode(x, -k * x)
    m.initial(x=1.0)
    return m


@pytest.mark.parametrize(
    ("value", "expected"),
    [
        (0.25, 0.25),
        (3, 3.0),
        (np.float32(0.5), 0.5),
        (np.int64(3), 3.0),
        (sp.Rational(1, 3), 1 / 3),
        (sp.pi, math.pi),
        (sp.sqrt(2), math.sqrt(2)),
        (sp.Float("0.1"), 0.1),
    ],
)
def test_every_kind_of_real_number_is_a_python_float(value, expected):
    number = real(value, "h")
    assert type(number) is float and number == expected


def test_integers_of_every_kind_are_python_ints():
    for value in (3, np.int64(3), np.int32(3), sp.Integer(3)):
        number = real(value, "max_steps", integer=True)
        assert type(number) is int and number == 3


@pytest.mark.parametrize(
    ("value", "kwargs", "message"),
    [
        (sp.Symbol("x"), {}, r"h must be a real number; got the sympy expression 'x', which has no numeric value"),
        (2 * sp.Symbol("x") + 1, {}, r"got the sympy expression '2\*x \+ 1', which has no numeric value"),
        (sp.I, {}, r"h must be a real number; got the complex number 'I'"),
        (np.bool_(True), {}, r"h must be a real number; got np\.True_ \(bool\)"),
        (True, {}, r"h must be a real number; got True \(bool\)"),
        ("0.1", {}, r"h must be a real number; got '0\.1' \(str\)"),
        (sp.oo, {}, r"h must be finite; got oo"),
        (np.float64("nan"), {}, r"h must be finite; got np\.float64\(nan\)"),
        (3.0, {"integer": True}, r"h must be a finite integer; got 3\.0 \(float\)"),
        (sp.Rational(1, 2), {"integer": True}, r"h must be a finite integer; got '1/2'"),
    ],
)
def test_anything_else_is_refused_by_name(value, kwargs, message):
    with pytest.raises(E.InvalidValueError, match=message):
        real(value, "h", **kwargs)


@pytest.mark.parametrize(
    ("method", "options"),
    [
        ("radau", {"h": np.float32(0.0625)}),
        ("radau", {"h": sp.Rational(1, 16)}),
        ("radau", {"rtol": np.float32(1e-6), "atol": sp.Float("1e-8"), "max_steps": np.int64(10_000)}),
        ("casadi-collocation", {"h": np.float32(0.0625)}),
        ("casadi-collocation", {"h": sp.Rational(1, 16), "stages": 3}),
        ("casadi-idas", {"rtol": np.float32(1e-6), "atol": sp.Rational(1, 10**8), "max_num_steps": sp.Integer(10**4)}),
        ("reference", {"rtol": sp.Rational(1, 10**10), "atol": np.float64(1e-12)}),
    ],
)
def test_step_options_and_tolerances_take_numpy_and_sympy_numbers(method, options):
    sol = dm.solve(decay(), (0.0, 1.0), method=method, **options)
    assert sol["x"][-1] == pytest.approx(math.exp(-1.0), rel=1e-5)
    stored = get_backend(method).Options(**options)
    for name in options:  # the options hold Python numbers: casadi, torch and JSON take them
        assert type(getattr(stored, name)) in (float, int)
    json.dumps({name: sol.settings[name] for name in options})  # numpy's float32 is not JSON


def test_pinn_options_take_numpy_and_sympy_numbers():
    config = dm.PINNConfig(h=np.float32(0.25), width=np.int64(8), depth=sp.Integer(2), eta=sp.Rational(1, 2))
    assert (config.h, config.width, config.depth, config.eta) == (0.25, 8, 2, 0.5)
    assert (type(config.h), type(config.width), type(config.depth)) == (float, int, int)


def test_initial_and_parameter_values_and_t_span_take_numpy_and_sympy_numbers():
    m = decay()
    m.initial(x=sp.pi)
    m.set_parameters(k=sp.Rational(1, 3))
    sol = dm.solve(m, (sp.Integer(0), sp.Rational(3, 2)), method="radau", rtol=1e-10, atol=1e-12)
    assert sol.t[-1] == 1.5
    assert sol["x"][-1] == pytest.approx(math.pi * math.exp(-0.5), rel=1e-8)
    m.set_parameters(k=np.float32(0.5))
    m.initial(x=np.int64(2))
    # y0 and parameters given to solve: a sympy number alone, or in a list; numpy scalars
    sol = dm.solve(
        m, (0.0, np.float32(1.0)), method="radau", rtol=1e-10, atol=1e-12, y0={"x": sp.E}, parameters={"k": sp.S.Half}
    )
    assert sol["x"][-1] == pytest.approx(math.e * math.exp(-0.5), rel=1e-8)
    sol = dm.solve(m, (0.0, 1.0), method="radau", rtol=1e-10, atol=1e-12, y0={"x": [sp.Integer(1), sp.pi]})
    np.testing.assert_allclose(sol["x"][:, -1], [math.exp(-0.5), math.pi * math.exp(-0.5)], rtol=1e-8)


def test_symbols_where_a_number_belongs_are_refused_by_name():
    m = decay()
    k = sp.Symbol("k")
    with pytest.raises(
        E.InvalidValueError, match=r"initial value of 'x' must be a real number; got the sympy expression 'k'"
    ):
        m.initial(x=k)
    with pytest.raises(
        E.InvalidValueError, match=r"parameter 'k' must be a real number; got the complex number '1 \+ I'"
    ):
        m.set_parameters(k=1 + sp.I)
    with pytest.raises(E.InvalidValueError, match=r"y0\['x'\] must be a real number; got the sympy expression 'k'"):
        dm.solve(m, (0.0, 1.0), method="radau", y0={"x": k})
    with pytest.raises(E.TimeSpanError, match=r"t_span must be a pair \(t0, t1\) of numbers; got \(0, t\)"):
        dm.solve(m, (0, sp.Symbol("t")), method="radau")
    with pytest.raises(E.InvalidOptionError, match=r"h must be a real number; got the sympy expression 'k'"):
        dm.solve(m, (0.0, 1.0), method="radau", h=k)
    with pytest.raises(E.InvalidOptionError, match=r"max_steps must be a finite integer; got np\.float32\(100\.0\)"):
        dm.solve(m, (0.0, 1.0), method="radau", max_steps=np.float32(100))

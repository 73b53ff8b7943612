"""``texts`` (daemodel/compiling/texts.py): str of many expressions, each shape printed once, character for
character what str gives; the fingerprint it makes is the one str made (files saved before still load)."""

import hashlib
import sys
from pathlib import Path

import numpy as np
import pytest
import sympy as sp

import daemodel as dm
from daemodel.compiling.texts import texts
from daemodel.problems import CAR_AXIS, PENDULUM_INDEX3, TRANSISTOR_AMPLIFIER

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import scaling_models


def mixed() -> dm.Model:
    """Names of several lengths and cases (x, x1, x10, X, xa), floats, rationals, functions, Min and a
    Piecewise, repeated over 12 elements whose indices cross from one digit to two."""
    m = dm.Model("mixed")
    u = m.states("u", 12)
    x, x1, x10, X, xa = m.states("x x1 x10 X xa")
    (z,) = m.algebraics("z")
    k = m.parameter("k", 0.5)
    for i in range(12):
        left = u[i - 1] if i else x
        m.ode(u[i], -k * u[i] + sp.Rational(1, 3) * left - 2.5 * sp.sin(u[i]) * sp.exp(-left) + sp.Min(u[i], 1))
    m.ode(x, sp.Piecewise((-x, x > x1), (-2 * x1, True)) + z)
    m.ode(x1, -x10 * X + xa**2)
    m.ode(x10, -x10 + sp.atan2(X, xa))
    m.ode(X, -X)
    m.ode(xa, -xa + m.t)
    m.constraint(z - x * x10 - u[11], name="c")
    m.initial(u=np.linspace(0.1, 1.2, 12), x=1.0, x1=0.5, x10=0.2, X=0.3, xa=0.4)
    return m


MODELS = {
    "mixed": mixed,
    "arrays across 99 -> 100": lambda: scaling_models.DECLARATIONS["stencils"](150),
    "loop names c_1, ...": lambda: scaling_models.DECLARATIONS["loop"](120),
    "pendulum chain": lambda: scaling_models.pendulum_chain(12),
    "car axis": CAR_AXIS.model,
    "transistor amplifier": TRANSISTOR_AMPLIFIER.model,
    "pendulum, index 3": PENDULUM_INDEX3.model,
}


@pytest.mark.parametrize("name", MODELS)
def test_texts_are_what_str_prints(name):
    c = MODELS[name]().compile()
    symbols = (c.t, *c.states, *c.algebraics, *c.parameters)
    for exprs in (c.rhs, c.g, [e for k in c.constraints for e in k.chain]):
        assert texts(exprs, symbols) == [str(e) for e in exprs]


def test_the_fingerprint_is_the_one_str_made():
    for build in (mixed, lambda: scaling_models.DECLARATIONS["stencils"](150)):
        c = build().compile()
        equations = (
            c.state_names,
            c.algebraic_names,
            c.parameter_names,
            [str(e) for e in c.rhs],
            [str(e) for e in c.g],
        )
        assert c.fingerprints()["equations"] == hashlib.sha256(repr(equations).encode()).hexdigest()


def test_the_fingerprint_prints_each_shape_once(monkeypatch):
    """A solution of the reaction-diffusion grid at 10^4 unknowns took 7.2 s to save (every equation printed
    by sympy's str: ~0.3 ms each), about 10 times that at 10^5; now a few prints whatever the size."""
    from sympy.printing.str import StrPrinter

    c = scaling_models.DECLARATIONS["stencils"](1000).compile()
    printed, depth, doprint = [0], [0], StrPrinter.doprint

    def counted(self, expr):
        printed[0] += depth[0] == 0
        depth[0] += 1
        try:
            return doprint(self, expr)
        finally:
            depth[0] -= 1

    monkeypatch.setattr(StrPrinter, "doprint", counted)
    c.fingerprints()
    assert printed[0] <= 20  # (the shapes: a boundary row at each end, the interior, three digit counts)


def test_models_whose_coefficients_differ_in_the_last_bit_have_different_fingerprints():
    def compiled(rate: float):
        m = dm.Model("decay")
        (y,) = m.states("y")
        m.ode("y", rate * y)
        m.initial(y=1.0)
        return m.compile()

    a, b = compiled(-0.1), compiled(-0.10000000000000002)
    assert a.rhs[0] != b.rhs[0]
    assert a.fingerprint() != b.fingerprint()


def test_events_whose_resets_differ_in_the_last_bit_have_different_fingerprints():
    def compiled(e: float):
        m = dm.Model("ball")
        _, v = m.states("x v")
        m.ode("x", v)
        m.ode("v", -9.81)
        m.event("floor", "x", direction=-1, reset={"v": -e * v})
        m.initial(x=1.0, v=0.0)
        return m.compile()

    a, b = compiled(0.3), compiled(0.30000000000000004)
    assert a.fingerprints()["equations"] == b.fingerprints()["equations"]
    assert a.fingerprints()["events"] != b.fingerprints()["events"]


@pytest.mark.parametrize("value", [0.1, 2.0, 1e-300, -7.25, 0.30000000000000004, 1 / 3, 5e-324, 1.7976931348623157e308])
def test_a_float_prints_as_str_does_where_that_gives_its_value_back(value):
    from daemodel.compiling.texts import exact_str

    y = sp.Symbol("y")
    expr = value * y + sp.Float(value) * sp.exp(y)
    exact, rounded = exact_str(expr), str(expr)
    assert sp.Float(exact.split("*")[0], precision=53) == sp.Float(value)  # (the value back)
    assert (exact == rounded) == (sp.Float(rounded.split("*")[0], precision=53) == sp.Float(value))

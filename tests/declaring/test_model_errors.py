"""Every user mistake of the front end raises its own ValueError subclass naming the culprit."""

import pytest
import sympy as sp

import daemodel as dm
from daemodel import errors as E


def small() -> tuple:
    m = dm.Model("small")
    y1, y2 = m.states("y1 y2")
    (z,) = m.algebraics("z")
    mu = m.parameter("mu", 2.0)
    return m, y1, y2, z, mu


def test_every_error_is_a_user_mistake_or_a_solver_failure():
    """User mistakes are ValueErrors (ModelError), method failures RuntimeErrors (SolverError), never both."""
    classes = [getattr(E, name) for name in dir(E)]
    classes = [c for c in classes if isinstance(c, type) and issubclass(c, Exception) and not issubclass(c, Warning)]
    assert len(classes) > 30
    for cls in classes:
        if cls is E.DaemodelError:
            continue
        assert issubclass(cls, E.DaemodelError), cls.__name__
        mistake, failure = issubclass(cls, E.ModelError), issubclass(cls, E.SolverError)
        assert mistake != failure or cls is E.DaemodelError, cls.__name__
        assert issubclass(cls, ValueError) == mistake and issubclass(cls, RuntimeError) == failure, cls.__name__
    assert issubclass(E.ConvergenceError, E.SolverError) and issubclass(E.TrainingError, E.SolverError)


@pytest.mark.parametrize(
    ("names", "pattern"),
    [
        ("1x", r"'1x' is not an identifier"),
        ("_x", r"'_x' is not an identifier"),
        ("lambda", r"'lambda' is not an identifier"),
        ("t", r"'t' is reserved for time"),
        ("sin", r"'sin' is the name of a supported function"),
        ("y1", r"'y1' is already declared as a differential variable"),
        ("mu", r"'mu' is already declared as a parameter"),
        ("", r"no differential variable names given"),
    ],
)
def test_invalid_names(names, pattern):
    m, *_ = small()
    with pytest.raises(E.InvalidNameError, match=pattern):
        m.states(names)


def test_a_refused_declaration_declares_none_of_its_names():
    m = dm.Model("partial")
    with pytest.raises(E.InvalidNameError, match="'1c' is not an identifier"):
        m.states("a b 1c")
    with pytest.raises(E.InvalidNameError, match="'a' is given twice"):
        m.algebraics("z a a")
    with pytest.raises(E.InvalidValueError, match="parameter 'k' must be a real number; got 'abc'"):
        m.parameter("k", "abc")
    assert m.declared().symbols() == {}
    a, b, c = m.states("a b c")  # (the names the refused calls gave are free)
    (z,) = m.algebraics("z")
    k = m.parameter("k", 2.0)
    declared = m.declared()
    assert declared.symbols() == {"a": a, "b": b, "c": c, "z": z, "k": k}
    assert dict(declared.parameter_values) == {"k": 2.0}


def test_constraint_names():
    m, y1, y2, z, _ = small()
    m.constraint(y1 - z, name="c")
    with pytest.raises(E.InvalidNameError, match="constraint name 'c' is already used"):
        m.constraint(y2 - z, name="c")
    with pytest.raises(E.InvalidNameError, match="constraint name 'a b' is not an identifier"):
        m.constraint(y2 - z, name="a b")


def test_unknown_symbols_are_named():
    m, y1, *_ = small()
    with pytest.raises(E.UnknownSymbolError, match=r"the ODE for 'y1' \(#1\): unknown name\(s\) 'q' in"):
        m.ode(y1, "y1 + q")
    with pytest.raises(E.UnknownSymbolError, match=r"unknown name\(s\) 'w'"):
        m.ode(y1, y1 * sp.Symbol("w"))
    with pytest.raises(E.UnknownSymbolError, match=r"constraint 'g1' \(#1\): unknown function\(s\) foo"):
        m.constraint("foo(y1) - z")
    with pytest.raises(E.UnknownSymbolError, match="unknown function"):
        m.constraint(sp.Function("y")(m.t) - 1)
    with pytest.raises(E.UnknownSymbolError, match=r"m\.initial: 'q' is not a declared variable"):
        m.initial(q=1.0)
    with pytest.raises(E.UnknownSymbolError, match="set_parameters: 'q' is not a declared parameter"):
        m.set_parameters(q=1.0)


def test_parse_errors():
    m, y1, *_ = small()
    with pytest.raises(E.ExpressionParseError, match=r"the ODE for 'y1' \(#1\): cannot parse 'y1 \+\* \('"):
        m.ode(y1, "y1 +* (")
    with pytest.raises(E.ExpressionParseError, match="is not an expression"):
        m.ode(y1, object())
    with pytest.raises(E.ExpressionParseError, match="is not a scalar expression"):
        m.ode(y1, sp.Matrix([1, 2]))


def test_invalid_values():
    m, *_ = small()
    with pytest.raises(E.InvalidValueError, match="initial value of 'y1' must be finite; got nan"):
        m.initial(y1=float("nan"))
    with pytest.raises(E.InvalidValueError, match="parameter 'k' must be a real number; got 'abc'"):
        m.parameter("k", "abc")
    with pytest.raises(E.InvalidValueError, match="initial time t must be finite"):
        m.initial(t=float("inf"))


def test_ode_targets():
    m, y1, _, z, mu = small()
    with pytest.raises(E.ODETargetError, match="'z' is an algebraic variable; algebraic variables get constraints"):
        m.ode(z, y1)
    with pytest.raises(E.ODETargetError, match="'mu' is a parameter"):
        m.ode(mu, y1)
    with pytest.raises(
        E.ODETargetError, match="'q' is not a declared differential variable; differential variables: 'y1', 'y2'"
    ):
        m.ode("q", y1)
    with pytest.raises(E.ODETargetError, match="not a declared differential variable"):
        m.ode(sp.Symbol("q"), y1)


def test_duplicate_ode():
    m, y1, *_ = small()
    m.ode(y1, -y1)
    with pytest.raises(E.DuplicateODEError, match=r"'y1' already has an ODE \(the ODE for 'y1' \(#1\): y1' = -y1\)"):
        m.ode("y1", 2 * y1)


@pytest.mark.parametrize(
    "rhs", ["y1' + 1", "Derivative(y1, t)", "diff(y1, t) * 2", sp.Derivative(sp.Symbol("y1"), sp.Symbol("t"))]
)
def test_derivative_on_right_hand_side(rhs):
    m, _, y2, *_ = small()
    with pytest.raises(E.DerivativeInEquationError, match=r"the ODE for 'y2' \(#1\): derivative .*y1"):
        m.ode(y2, rhs)


def test_missing_ode():
    m, y1, _, z, _ = small()
    m.ode(y1, -z)
    m.constraint(z - y1**2)
    with pytest.raises(E.MissingODEError, match=r"differential variable\(s\) 'y2' of model 'small' have no ODE"):
        m.compile()


def test_unbalanced():
    m, y1, y2, z, _ = small()
    m.ode(y1, -z)
    m.ode(y2, z)
    with pytest.raises(
        E.UnbalancedSystemError, match=r"1 algebraic variable\(s\) \('z'\) but 0 constraint\(s\) \(none\)"
    ):
        m.compile()
    m.constraint(z - y1**2, name="a")
    m.constraint(y2 - y1, name="b")
    with pytest.raises(E.UnbalancedSystemError, match=r"but 2 constraint\(s\) \('a', 'b'\)"):
        m.compile()


def test_parameter_without_value_then_set():
    m, y1, y2, z, mu = small()
    k = m.parameter("k")
    m.ode(y1, -k * z)
    m.ode(y2, mu)
    m.constraint(z - y1**2)
    m.initial(y1=1.0, y2=0.0)
    with pytest.raises(E.MissingParameterValueError, match=r"parameter\(s\) 'k' of model 'small' have no value"):
        m.compile()
    m.set_parameters(k=3.0)
    c = m.compile()
    assert c.parameter_names == ("mu", "k") and list(c.parameter_values) == [2.0, 3.0]


def test_missing_initial_value():
    m, y1, y2, z, _ = small()
    m.ode(y1, -z)
    m.ode(y2, z)
    m.constraint(z - y1**2)
    m.initial(y1=1.0)
    with pytest.raises(E.MissingInitialValueError, match=r"'y2' of model 'small' have no initial value"):
        m.compile()


def test_unsupported_function_names_function_and_equation():
    m, y1, y2, z, _ = small()
    m.ode(y1, sp.gamma(y1))
    m.ode(y2, z)
    m.constraint(z - y1**2, name="shape")
    m.initial(y1=1.0, y2=0.0)
    with pytest.raises(E.UnsupportedFunctionError, match=r"the ODE for 'y1' \(#1\): function 'gamma' in gamma\(y1\)"):
        m.compile()


def test_piecewise_needs_otherwise_branch():
    m, y1, y2, z, _ = small()
    m.ode(y1, sp.Piecewise((y1, y1 > 0)))
    m.ode(y2, z)
    m.constraint(z - y1**2)
    m.initial(y1=1.0, y2=0.0)
    with pytest.raises(E.UnsupportedFunctionError, match="has no otherwise branch"):
        m.compile()


def test_constraint_string_with_equals_sign():
    m, y1, y2, z, _ = small()
    m.ode(y1, -z)
    m.ode(y2, z)
    m.constraint("z = y1^2 + mu")  # '^' is accepted as power
    m.initial(y1=3.0, y2=0.0)
    c = m.compile()
    assert c.g[0] == z - y1**2 - sp.Symbol("mu")
    assert c.z0[0] == 11.0


# ---- numeric functions on declared symbols ---------------------------------------------------
def test_math_and_numpy_functions_on_a_declared_symbol_name_the_fix():
    """math.sin(x) raised sympy's 'Cannot convert expression to float' and np.sin(x) numpy's 'loop of
    ufunc does not support argument 0 of type Symbol'; neither said what to write instead."""
    import math

    import numpy as np

    m = dm.Model("pendulum")
    (theta,) = m.states("theta")
    k = m.parameter("k", 2.0)
    fix = r"which has no value until the solve: write the equation with sympy's functions, "
    cases = [
        (
            lambda: math.sin(theta),
            r"^math\.sin\(theta\), math\.exp\(theta\), \.\.\. or float\(theta\) on the declared "
            r"symbol 'theta', " + fix + r"sp\.sin\(theta\), sp\.exp\(theta\), \.\.\. \(import sympy as sp\), or as a "
            r"string, \"sin\(theta\), exp\(theta\), \.\.\.\"$",
        ),
        (lambda: math.exp(k), r"^math\.sin\(k\), .* on the declared symbol 'k'"),
        (lambda: float(m.t), r"or float\(t\) on the declared symbol 't'"),
        (
            lambda: np.sin(theta),
            r"^np\.sin\(theta\) on the declared symbol 'theta', "
            + fix
            + r"sp\.sin\(theta\) \(import sympy as sp\), or as a string, \"sin\(theta\)\"$",
        ),
        (lambda: np.arcsin(theta), r"^np\.arcsin\(theta\) on .* sp\.asin\(theta\) .* \"asin\(theta\)\"$"),
        (lambda: np.arctan2(theta, 1.0), r"^np\.arctan2\(theta, \.\.\.\) on .* sp\.atan2\(theta, \.\.\.\)"),
        (lambda: np.log10(k), r"^np\.log10\(k\) on .* sp\.log\(k, 10\) .* \"log\(k, 10\)\"$"),
    ]
    for call, message in cases:
        with pytest.raises(E.NumericFunctionError, match=message) as raised:
            call()
        assert isinstance(raised.value, TypeError)  # as Python's and numpy's own refusals were


def test_declared_symbols_are_sympy_symbols_in_every_other_respect():
    """The class that refuses math.sin is sympy.Symbol as far as sympy can tell: equal to a user's
    sp.Symbol of the same name (same hash, same srepr), substituted for it both ways, pickled, and a
    user's own sp.Symbol("x") in an equation is the declared x."""
    import pickle

    import numpy as np

    plain = sp.Symbol("x")  # made before the declaration: sympy's cache must not hand it back
    m = dm.Model("decay")
    (x,) = m.states("x")
    assert type(x) is not sp.Symbol and x == plain and plain == x and not (x != plain) and hash(x) == hash(plain)
    assert sp.srepr(x) == "Symbol('x')" and {plain: 1}[x] == 1 and x + plain == 2 * x
    assert (x + 1).subs(plain, 2) == 3 and (plain + 1).subs(x, 3) == 4 and (sp.sin(plain) + plain).subs(x, 0) == 0
    copy = pickle.loads(pickle.dumps(x))
    assert copy == x and type(copy) is type(x)
    m.ode(x, -plain + sp.sin(sp.Symbol("t")))  # a user's own sp.Symbol("x") and ("t") are the declared x and t
    m.initial(x=1.0)
    assert m.compile().rhs[0].free_symbols == {x, m.t}
    sol = dm.solve(m, (0.0, 1.0), rtol=1e-10, atol=1e-12)
    # x' = -x + sin t, x(0) = 1: x = 1.5 e^-t + (sin t - cos t) / 2
    np.testing.assert_allclose(sol["x"], 1.5 * np.exp(-sol.t) + (np.sin(sol.t) - np.cos(sol.t)) / 2, atol=1e-8)


def test_an_event_with_a_function_the_emitters_lack_is_refused_where_it_is_declared():
    """Before: accepted, then sympy's NotImplementedError ("Only definite integrals") at the solve."""
    m = dm.Model("ball")
    h, v = m.states("h v")
    m.ode("h", "v")
    m.ode("v", "-9.81")
    m.initial(h=1.0, v=0.0)
    with pytest.raises(
        E.UnsupportedFunctionError,
        match=r"model 'ball', event 'floor' \(when\): function 'Integral' in Integral\(h, t\)",
    ):
        m.event("floor", sp.Integral(h, m.t) - 0.1, direction=-1)
    with pytest.raises(E.UnsupportedFunctionError, match=r"event 'floor' \(reset of 'v'\): function 'Integral'"):
        m.event("floor", h, reset={"v": sp.Integral(v, m.t)})
    m.event("floor", h, direction=-1, reset={"v": -0.8 * v})  # (nothing of the refused ones was kept)
    assert dm.solve(m, (0.0, 0.5), rtol=1e-8).stats["events"] == 1


def test_what_is_declared_is_read_only_and_is_what_compile_reads():
    """``Declaration.declared()``: views the compiler reads, which a caller cannot change."""
    m = dm.Model("decay")
    (x,) = m.states("x")
    (w,) = m.algebraics("w")
    k = m.parameter("k", 2.0)
    m.ode(x, -w)
    m.constraint(w - k * x, name="rate")
    m.initial(x=1.0)
    d = m.declared()
    assert list(d.states) == ["x"] and list(d.algebraics) == ["w"] and dict(d.parameter_values) == {"k": 2.0}
    assert d.symbols() == {"x": x, "w": w, "k": k}
    assert [c.name for c in d.constraints] == ["rate"] and d.odes["x"].expr == -w
    with pytest.raises(TypeError):
        d.initial["x"] = 5.0  # a view: the declaration changes through m.initial only
    m.initial(x=3.0)
    assert d.initial["x"] == 3.0  # (a view, not a copy)
    assert m.compile().z0 == pytest.approx([6.0])

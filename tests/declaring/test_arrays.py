"""Arrays of variables and parameters (``m.states("u", 1000)``), of ODEs and of constraints: names,
shapes, strings with elements, initial values and every error message."""

import numpy as np
import pytest
import sympy as sp

import daemodel as dm
from daemodel import errors as E
from daemodel.declaring.arrays import compact_listing, element_names, identifier, split_element

# radau's default on casadi's virtual machine, but in the tests marked machine_code (tests/conftest.py)
pytestmark = pytest.mark.virtual_machine


def test_an_array_of_states_is_a_numpy_array_of_named_symbols():
    m = dm.Model("a")
    u = m.states("u", 4)
    T = m.states("T", (2, 3))
    assert isinstance(u, np.ndarray) and u.shape == (4,) and u.dtype == object
    assert [s.name for s in u] == ["u[0]", "u[1]", "u[2]", "u[3]"]
    assert T.shape == (2, 3) and T[1, 2].name == "T[1,2]" and T[0, 1] == sp.Symbol("T[0,1]")
    assert [s.name for s in T.flat] == element_names("T", (2, 3))  # numpy's order, last index fastest
    assert m.declared().arrays["T"][:2] == ("states", (2, 3))
    assert list(m.declared().states)[:5] == ["u[0]", "u[1]", "u[2]", "u[3]", "T[0,0]"]
    z = m.algebraics("z", np.int64(2))
    assert [s.name for s in z] == ["z[0]", "z[1]"] and "z[1]" in m.declared().algebraics
    with pytest.raises(ValueError, match="read-only"):
        u[0] = sp.Symbol("x")  # the model's record of the array


def test_parameter_arrays_take_one_value_or_an_array_of_their_shape():
    m = dm.Model("p")
    k = m.parameters("k", 3, value=2.0)
    c = m.parameters("c", (2, 2), value=[[1, 2], [3, 4]])
    free = m.parameters("free", 2)
    declared = m.declared()
    assert [declared.parameter_values[s.name] for s in k] == [2.0, 2.0, 2.0]
    assert declared.parameter_values["c[1,0]"] == 3.0 and declared.parameter_values["free[1]"] is None
    m.set_parameters(k=np.array([5.0, 6.0, 7.0]), free=0.5)
    assert [declared.parameter_values[s.name] for s in (*k, *free)] == [5.0, 6.0, 7.0, 0.5, 0.5]
    assert c[1, 1].name == "c[1,1]"
    with pytest.raises(
        E.ShapeError,
        match=r"the parameter values of the array 'k' must be one number or of shape \(3,\); got shape \(2,\)",
    ):
        m.set_parameters(k=[1.0, 2.0])
    with pytest.raises(E.InvalidValueError, match=r"parameter value of 'k\[1\]' must be a real number"):
        m.set_parameters(k=[1.0, "x", 2.0])
    with pytest.raises(E.ShapeError, match="of shape \\(2,\\); got shape \\(3,\\)"):
        m.parameters("q", 2, value=[1, 2, 3])
    assert "q" not in m.declared().arrays and "q[0]" not in declared.parameters  # refused: nothing declared


@pytest.mark.parametrize(
    ("call", "error", "pattern"),
    [
        (
            lambda m: m.states("x", "y"),
            E.ShapeError,
            r"got the string 'y' \(to declare several names, give them in one string",
        ),
        (
            lambda m: m.states("x y", 3),
            E.InvalidNameError,
            r"takes one name and a shape, e.g. m.states\('u', 1000\); got the name 'x y'",
        ),
        (lambda m: m.states(["u"], 3), E.InvalidNameError, r"got the name \['u'\]"),
        (
            lambda m: m.algebraics("u", 0),
            E.ShapeError,
            r"algebraic variable array 'u': every axis needs at least one element; got shape \(0,\)",
        ),
        (lambda m: m.states("u", (3, -1)), E.ShapeError, r"got shape \(3, -1\)"),
        (lambda m: m.states("u", ()), E.ShapeError, r"the shape must be an int or a tuple of ints; got \(\)"),
        (lambda m: m.states("u", 2.5), E.ShapeError, "got 2.5"),
        (lambda m: m.states("u", True), E.ShapeError, "got True"),
        (lambda m: m.states("u", (10_000, 10_000)), E.ShapeError, "more than the 10,000,000 elements"),
        (lambda m: m.states("sin", 3), E.InvalidNameError, "'sin' is the name of a supported function"),
        (lambda m: m.states("t", 3), E.InvalidNameError, "'t' is reserved for time"),
        (lambda m: m.states("u[0]", 3), E.InvalidNameError, r"got the name 'u\[0\]'"),
        (lambda m: m.parameters("lambda", 3), E.InvalidNameError, "'lambda' is not an identifier"),
    ],
)
def test_array_declaration_errors_name_the_culprit(call, error, pattern):
    m = dm.Model("e")
    with pytest.raises(error, match=pattern):
        call(m)
    assert not m.declared().arrays and not m.declared().states  # all or none


def test_an_array_name_clashes_with_a_scalar_of_that_name_and_with_another_array():
    m = dm.Model("clash")
    m.states("u", 3)
    m.states("x")
    with pytest.raises(
        E.InvalidNameError, match=r"'u' is already declared as an array of differential variables of shape \(3,\)"
    ):
        m.states("u")
    with pytest.raises(E.InvalidNameError, match=r"parameter name 'u' is already declared as an array"):
        m.parameter("u", 1.0)
    with pytest.raises(E.InvalidNameError, match=r"algebraic variable array name 'u' is already declared as an array"):
        m.algebraics("u", 2)
    with pytest.raises(
        E.InvalidNameError, match=r"parameter array name 'x' is already declared as a differential variable"
    ):
        m.parameters("x", 2)


def chain(n: int = 4):
    m = dm.Model("chain")
    u = m.states("u", n)
    b = m.algebraics("b", n)
    k = m.parameters("k", n, value=np.arange(1.0, n + 1))
    return m, u, b, k


def test_an_array_of_odes_and_of_constraints_is_declared_in_one_call():
    m, u, b, k = chain()
    m.ode(u, -k * b)
    m.constraint(b - u, name="eq")
    m.initial(u=1.0)
    d = m.declared()
    assert [eq.number for eq in d.odes.values()] == [1, 2, 3, 4]
    assert d.odes["u[2]"].expr == -k[2] * b[2]
    assert [c.name for c in d.constraints] == ["eq[0]", "eq[1]", "eq[2]", "eq[3]"]
    assert [c.number for c in d.constraints] == [5, 6, 7, 8]
    c = m.compile()
    assert c.arrays == {"u": (4,), "b": (4,)} and c.algebraic_names == ()  # b = u: aliases
    sol = dm.solve(c, (0.0, 0.5), rtol=1e-10, atol=1e-12)
    assert np.allclose(sol["u"][:, -1], np.exp(-np.arange(1.0, 5.0) * 0.5), rtol=1e-8, atol=0)
    assert np.array_equal(sol["b"], sol["u"])


def test_odes_for_a_slice_strings_and_the_array_by_name():
    m, u, b, k = chain(3)
    m.ode(u[:2], ["-u[0] + b[1]", -u[1]])
    with pytest.raises(E.DuplicateODEError, match=r"'u\[0\]' already has an ODE"):
        m.ode("u", [0, 0, 0])  # (the array by its name: its first element has an ODE)
    m.ode(u[2:], ["k[2]*u[2]"])
    assert m.declared().odes["u[0]"].expr == -u[0] + b[1]
    assert m.declared().odes["u[2]"].expr == k[2] * u[2]
    T = dm.Model("grid").states("T", (2, 2))
    assert T[1, 0].name == "T[1,0]"


def test_an_array_of_odes_is_all_or_none():
    m, u, _, _ = chain(3)
    with pytest.raises(E.UnknownSymbolError, match=r"the ODE for 'u\[2\]' \(#3\): unknown name\(s\) 'w'"):
        m.ode(u, [-u[0], -u[1], "w"])
    assert not m.declared().odes  # nothing declared: the first two are not there
    m.ode(u, [-u[0], -u[1], -u[2]])
    assert [eq.number for eq in m.declared().odes.values()] == [1, 2, 3]


@pytest.mark.parametrize(
    ("states", "rhs", "error", "pattern"),
    [
        (
            "u",
            [0, 0],
            E.ShapeError,
            r"m.ode: 3 differential variable\(s\) of shape \(3,\) need expressions of that shape; got shape \(2,\)",
        ),
        ("u", 0, E.ShapeError, r"need expressions of that shape; got 0"),
        ("b", [0, 0, 0], E.ODETargetError, r"'b' is an array of algebraic variables, not of differential variables"),
        ("k", [0, 0, 0], E.ODETargetError, r"'k' is an array of parameters"),
        ("b_symbols", [0, 0, 0], E.ODETargetError, r"'b\[0\]' is an algebraic variable"),
        ("twice", [0, 0], E.DuplicateODEError, r"'u\[0\]' is given twice in one array"),
        ("matrix", [[0, 0, 0]], E.ShapeError, r"got shape \(1, 3\)"),
    ],
)
def test_ode_array_errors_name_the_culprit(states, rhs, error, pattern):
    m, u, b, _ = chain(3)
    target = {"b_symbols": b, "twice": np.array([u[0], u[0]], dtype=object), "matrix": u}.get(states, states)
    with pytest.raises(error, match=pattern):
        m.ode(target, rhs)
    assert not m.declared().odes


def test_constraint_arrays_are_named_by_element_and_refuse_clashes():
    m = dm.Model("c")
    z = m.algebraics("z", (2, 2))
    (x,) = m.states("x")
    m.constraint(z - x, name="eq")
    assert [c.name for c in m.declared().constraints] == ["eq[0,0]", "eq[0,1]", "eq[1,0]", "eq[1,1]"]
    with pytest.raises(E.InvalidNameError, match="constraint name 'eq' is already used"):
        m.constraint(x - 1, name="eq")
    with pytest.raises(E.InvalidNameError, match="constraint name 'eq' is already used"):
        m.constraint([x - 1], name="eq")
    m.constraint([x - 1, "x = 2"])  # unnamed: g<k> each, numbered on
    assert [c.name for c in m.declared().constraints][4:] == ["g5", "g6"]
    assert m.declared().constraints[5].expr == x - 2
    with pytest.raises(E.ShapeError, match="the array of constraints 'none' is empty"):
        m.constraint([], name="none")
    with pytest.raises(E.InvalidNameError, match=r"constraint array name 'a b' is not an identifier"):
        m.constraint([x], name="a b")
    m.constraint(x - 3, name="g8")  # (the 7th: the next unnamed ones would be g8, g9)
    with pytest.raises(E.InvalidNameError, match="constraint name 'g8' is already used; name the array"):
        m.constraint([x, x])
    before = len(m.declared().constraints)
    with pytest.raises(E.UnknownSymbolError, match=r"constraint 'late\[1\]' \(#\d+\): unknown name\(s\) 'w'"):
        m.constraint([x, "w"], name="late")
    assert len(m.declared().constraints) == before  # all or none
    m.constraint([x], name="late")  # (the refused name stays free)


@pytest.mark.parametrize(
    ("text", "error", "pattern"),
    [
        (
            "u[3]",
            E.UnknownSymbolError,
            r"the ODE for 'x' \(#1\): index 3 is out of range for axis 0 of 'u', shape \(3,\) \(0 to 2\)",
        ),
        ("T[1]", E.UnknownSymbolError, r"T\[1\] gives 1 index\(es\) for the 2-d array 'T' of shape \(2, 2\)"),
        (
            "u[-1]",
            E.ExpressionParseError,
            r"the subscript 'u\[-1\]' is not allowed: an array's element is written with integer indices, e.g. u\[0\]",
        ),
        ("T[0, x]", E.ExpressionParseError, r"e.g. T\[0, 0\]"),
        ("u[1.0]", E.ExpressionParseError, "the subscript 'u\\[1.0\\]' is not allowed"),
        ("x[0]", E.ExpressionParseError, r"subscript 'x\[0\]' is not allowed in an equation"),
        (
            "2*T",
            E.ExpressionParseError,
            r"'T' is an array of shape \(2, 2\): an equation takes its elements, e.g. T\[0, 0\]",
        ),
        (
            "u(1)",
            E.ExpressionParseError,
            r"'u' is an array of shape \(3,\): an equation takes its elements, e.g. u\[0\]",
        ),
        ("w", E.UnknownSymbolError, r"declared: 'x', 'u\[...\]' \(3 elements\), 'T\[...\]' \(4 elements\), 't'"),
    ],
)
def test_elements_in_strings(text, error, pattern):
    m = dm.Model("s")
    (x,) = m.states("x")
    u = m.states("u", 3)
    T = m.states("T", (2, 2))
    with pytest.raises(error, match=pattern):
        m.ode(x, text)
    m.ode(x, "u[2] + T[1, 0] - T[0,1]")
    assert m.declared().odes["x"].expr == u[2] + T[1, 0] - T[0, 1]


def test_initial_values_and_guesses_by_array_and_by_element():
    m, u, b, _ = chain(3)
    m.initial(u=np.array([1.0, 2.0, 3.0]))
    m.initial(**{"u[1]": 5.0})
    m.guess(b=0.5)
    d = m.declared()
    assert [d.initial[s.name] for s in u] == [1.0, 5.0, 3.0]
    assert [d.guess[s.name] for s in b] == [0.5, 0.5, 0.5]
    with pytest.raises(
        E.ShapeError,
        match=r"the initial values of the array 'u' must be one number or of shape \(3,\); got shape \(2, 2\)",
    ):
        m.initial(u=np.zeros((2, 2)))
    with pytest.raises(E.UnknownSymbolError, match=r"m.initial: 'k' is an array of parameters of shape \(3,\)"):
        m.initial(k=1.0)
    with pytest.raises(E.UnknownSymbolError, match=r"m.guess: 'u' is an array of differential variables"):
        m.guess(u=1.0)
    with pytest.raises(
        E.UnknownSymbolError,
        match=r"m.initial: 'u\[3\]' is not a declared variable; variables: 'u\[...\]' \(3 elements\), 'b\[...\]' \(3 ",
    ):
        m.initial(**{"u[3]": 1.0})


def test_outputs_take_an_array_name_or_elements():
    m, u, b, _ = chain(3)
    m.ode(u, [-u[0], -u[1] + u[0], -u[2]])
    m.constraint(b - 2 * u + b**3, name="eq")
    m.initial(u=1.0)
    assert m.compile(outputs=["u[1]"]).state_names == ("u[0]", "u[1]")
    assert m.compile(outputs=["b"]).algebraic_names == ("b[0]", "b[1]", "b[2]")
    with pytest.raises(
        E.UnknownOutputError,
        match=r"compile\(outputs=...\): index 3 is out of range for axis 0 of 'u', shape \(3,\) \(0 to 2\)",
    ):  # (as sol["u[3]"] says it; it said "'u[3]' not a variable of model 'chain'")
        m.compile(outputs=["u[3]"])
    with pytest.raises(E.UnknownOutputError, match=r"'v\[0\]' not a variable of model 'chain'; variables: 'u\[...\]'"):
        m.compile(outputs=["v[0]"])


def test_outputs_read_elements_as_a_solution_does_and_take_the_declared_symbols():
    """sol["u[ 1 ]"] and sol["u[01]"] read u[1], sol[u[1]] takes the symbol; compile(outputs=...) refused
    all three ("not a variable", for the symbols m.states returned too)."""
    m, u, b, _ = chain(3)
    m.ode(u, [-u[0], -u[1] + u[0], -u[2]])
    m.constraint(b - 2 * u + b**3, name="eq")
    m.initial(u=1.0)
    for outputs in ("u[ 1 ]", "u[01]", ["u[1]"], u[1], [u[1]], np.array([[u[1]]], dtype=object)):
        assert m.compile(outputs=outputs).state_names == ("u[0]", "u[1]")
    assert m.compile(outputs=u).state_names == ("u[0]", "u[1]", "u[2]")
    sol = dm.solve(m.compile(outputs=u[1]), (0.0, 1.0), rtol=1e-10, atol=1e-12)
    assert abs(sol["u[1]"][-1] - 2 * np.exp(-1.0)) < 1e-8  # (u1 = (1 + t) e^-t)


def test_an_unknown_output_error_does_not_repeat_a_huge_request():
    m, u, b, _ = chain(3)
    m.ode(u, -u)
    m.constraint(b - 2 * u + b**3, name="eq")
    m.initial(u=1.0)
    with pytest.raises(E.UnknownOutputError, match=r"'aaaa+\.\.\. \(1,000,002 characters\) not a variable") as caught:
        m.compile(outputs="a" * 10**6)
    assert len(str(caught.value)) < 300
    with pytest.raises(E.UnknownOutputError, match=r"'x9' and 99,990 more not a variable") as caught:
        m.compile(outputs=[f"x{i}" for i in range(100_000)])
    assert len(str(caught.value)) < 300


def test_element_names_are_split_and_made_identifiers():
    assert split_element("T[3,4]") == ("T", (3, 4)) and split_element("T[3, 4]") == ("T", (3, 4))
    assert split_element("u") is None and split_element("u[x]") is None and split_element("u[-1]") is None
    assert identifier("T[3,4]") == "T_3_4" and identifier("u") == "u"
    with pytest.raises(ValueError, match="refusing to emit"):
        identifier("u[0]; import os")
    assert compact_listing(["x", "u[0]", "u[1]", "y"]) == "'x', 'u[...]' (2 elements), 'y'"
    assert compact_listing([]) == "(none)"


def test_an_array_whose_symbols_alone_pass_the_memory_limit_is_refused_before_they_are_made(monkeypatch):
    """10^6 elements under a 100 MB limit (0.33 GiB of symbols): refused at once, naming the size and the
    limit; the name stays free, and an array that fits is declared as before."""
    monkeypatch.setenv("DAEMODEL_MEMORY_LIMIT", "100M")
    m = dm.Model("big")
    message = r"array 'u': shape \(1000, 1000\) makes 1,000,000 elements, about 0.326 GiB .* limit of 0.0977 GiB"
    with pytest.raises(E.ResourceLimitError, match=message):
        m.states("u", (1000, 1000))
    assert m.states("u", 1000).shape == (1000,)  # (nothing of the refused one was declared)

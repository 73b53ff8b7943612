"""Stencils (``dm.stencil``): array expressions recorded once, whose element equations are the very trees
numpy's arithmetic on the arrays of symbols builds (so the same compiled model, the same answers), and
every error message."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest
import sympy as sp
from hypothesis import given, settings
from hypothesis import strategies as st

import daemodel as dm
from daemodel import errors as E
from daemodel.declaring.stencils import expand, stencil
from daemodel.declaring.symbols import Symbol

# radau's default on casadi's virtual machine, but in the tests marked machine_code (tests/conftest.py)
pytestmark = pytest.mark.virtual_machine

ROOT = Path(__file__).resolve().parents[2]


def reaction_diffusion(K: int, stencils: bool) -> dm.Model:
    """The reaction-diffusion family as arrays: by numpy's arithmetic or by stencils, the same text."""
    m = dm.Model(f"rd_{K}")
    c, w = m.states("c", K), m.algebraics("w", K)
    D = m.parameter("D", 0.1)
    p = np.array([0, *c, 0], dtype=object)  # the Dirichlet boundary values around the interior
    if stencils:
        p, c, w = dm.stencil(p), dm.stencil(c), dm.stencil(w)
    m.ode("c", D * (p[:-2] - 2 * p[1:-1] + p[2:]) * sp.Integer(K + 1) ** 2 - w)
    m.constraint(w - c**2 / (1 + c), name="rate")
    m.initial(c=np.sin(np.pi * np.arange(1, K + 1) / (K + 1)))
    return m


def heat_2d(n: int, stencils: bool) -> dm.Model:
    """examples/heat_2d.py's model: by stencils, the example's own; by numpy's arithmetic, as it was."""
    if stencils:
        spec = importlib.util.spec_from_file_location("heat_2d", ROOT / "examples" / "heat_2d.py")
        example = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(example)
        return example.build_model(n)[0]
    h = 1.0 / (n + 1)
    m = dm.Model("heat_2d")
    T, edge = m.states("T", (n, n)), m.algebraics("edge", (2, n))
    kappa = m.parameter("kappa", 1.0)
    grid = np.zeros((n + 2, n + 2), dtype=object)
    grid[1:-1, 1:-1], grid[0, 1:-1], grid[-1, 1:-1] = T, edge[0], edge[1]
    m.ode(T, kappa / h**2 * (grid[2:, 1:-1] + grid[:-2, 1:-1] + grid[1:-1, 2:] + grid[1:-1, :-2] - 4 * T))
    m.constraint(np.stack([3 * edge[0] - 4 * T[0] + T[1], 3 * edge[1] - 4 * T[-1] + T[-2]]), name="insulated")
    x, y = np.meshgrid(h * np.arange(1, n + 1), h * np.arange(1, n + 1), indexing="ij")
    m.initial(T=np.cos(np.pi * x) * np.sin(np.pi * y))
    return m


def equations(m: dm.Model) -> list:
    declared = m.declared()
    return [(n, e.number, e.expr) for n, e in declared.odes.items()] + [
        (e.name, e.number, e.expr) for e in declared.constraints
    ]


@pytest.mark.parametrize("build, size", [(reaction_diffusion, 40), (heat_2d, 6)])
def test_a_stencil_declares_the_equations_numpy_arithmetic_builds(build, size):
    by_numpy, by_stencil = build(size, False), build(size, True)
    # the same trees (== compares them node by node, arguments in order), so the same generated source
    assert equations(by_stencil) == equations(by_numpy)
    assert [type(e[2]) for e in equations(by_stencil)] == [type(e[2]) for e in equations(by_numpy)]
    assert by_stencil.compile().fingerprint() == by_numpy.compile().fingerprint()
    # the declaration recorded each element's free symbols (the compiler starts from them): exact ones
    free = by_stencil.declared().free_symbols
    assert all(free.get(e, e.free_symbols) == e.free_symbols for _, _, e in equations(by_stencil))


def test_a_stencil_model_solves_to_the_same_numbers():
    a = dm.solve(reaction_diffusion(20, False), (0.0, 0.1), method="radau", rtol=1e-6)
    b = dm.solve(reaction_diffusion(20, True), (0.0, 0.1), method="radau", rtol=1e-6)
    assert a.status == b.status == "success"
    np.testing.assert_array_equal(a["c"], b["c"])
    np.testing.assert_array_equal(a["w"], b["w"])
    assert b["c"].shape == (20, len(b.t)) and b.stats["steps"] == a.stats["steps"]


def test_elements_sympy_evaluates_are_the_ones_numpy_evaluates():
    """Numbers at a leaf (boundary values), two leaves of one symbol at an element, a function whose
    evaluation flips a sign: each element equal to numpy's, also where the renaming would not do."""
    u = np.array([Symbol(f"u[{i}]") for i in range(12)], dtype=object)
    a = Symbol("a")
    padded = np.array([sp.Rational(1, 2), *u, 0], dtype=object)
    reversed_u = u[::-1]  # meets u in no element (even length): renamed
    odd = u[:11]  # meets its reverse at u[5]: 0 there, as numpy makes it
    P, U, R = stencil(padded), stencil(u), stencil(reversed_u)
    cases = [
        (P[2:] - P[:-2], padded[2:] - padded[:-2]),
        (sp.cos(a) * (U - R) ** 2 / (a + U), sp.cos(a) * (u - reversed_u) ** 2 / (a + u)),
        ((U - R).apply(sp.cos), np.array([sp.cos(x) for x in u - reversed_u], dtype=object)),
        ((U - R).apply(sp.sin) * U, np.array([sp.sin(x) for x in u - reversed_u], dtype=object) * u),
        (P[1:-1] * P[1:-1] - U**2 + 3, padded[1:-1] * padded[1:-1] - u**2 + 3),
        (1 / (P[:-2] + U), 1 / (padded[:-2] + u)),
        (stencil(odd) - stencil(odd[::-1]) + a, odd - odd[::-1] + a),
    ]
    for s, reference in cases:
        exprs, symbols = expand(s)
        assert exprs == list(reference.flat), s
        assert all(f is None or f == e.free_symbols for e, f in zip(exprs, symbols, strict=True))


@settings(max_examples=60, deadline=None)
@given(
    program=st.lists(
        st.tuples(st.sampled_from(["+", "-", "*", "/", "**", "sin", "exp", "neg"]), st.integers(0, 3)),
        min_size=1,
        max_size=6,
    ),
    shifts=st.lists(st.integers(0, 4), min_size=3, max_size=3),
)
def test_any_arithmetic_of_shifted_views_builds_numpy_s_trees(program, shifts):
    """Random programs over shifted views of one array (names c[9] < c[10] as strings: every order of
    arguments occurs) and a scalar, against numpy's arithmetic on the same views."""
    c = np.array([Symbol(f"c[{i}]") for i in range(16)], dtype=object)
    k = Symbol("k")
    views = [c[s : s + 12] for s in shifts]
    operands = [(stencil(v), v) for v in views] + [(k, k)]
    s, ref = stencil(views[0]), views[0]
    for op, j in program:
        o_s, o_ref = operands[j]
        if op == "+":
            s, ref = s + o_s, ref + o_ref
        elif op == "-":
            s, ref = o_s - s, o_ref - ref
        elif op == "*":
            s, ref = s * o_s, ref * o_ref
        elif op == "/":
            s, ref = s / (o_s + 2), ref / (o_ref + 2)
        elif op == "**":
            s, ref = s**2, ref**2
        elif op == "neg":
            s, ref = -s, -ref
        else:
            f = {"sin": sp.sin, "exp": sp.exp}[op]
            s, ref = s.apply(f), np.array([f(x) for x in np.broadcast_to(ref, (12,))], dtype=object)
    ref = np.broadcast_to(np.asarray(ref, dtype=object), (12,))
    assert expand(s)[0] == list(ref)


def test_slices_of_one_stencil_are_distinct_and_equal_views_are_one_placeholder():
    m = dm.Model("v")
    u = m.states("u", 5)
    U = dm.stencil(u)
    s = U[1:] - U[:-1]
    assert len(s.leaves) == 2 and s.shape == (4,)
    assert len((U[1:] * U[1:]).leaves) == 1  # u[1:] twice: one placeholder, so u[k]**2
    assert expand(U[1:] * U[1:])[0] == [x**2 for x in u[1:]]
    assert dm.stencil(U) is U and U.ndim == 1 and U.size == 5 and "Stencil(shape=(5,)" in repr(U)
    T = dm.stencil(m.algebraics("T", (2, 3)))
    assert T[:, 1:].shape == (2, 2) and T[1:, :].shape == (1, 3)


def test_a_stencil_and_a_numeric_array_combine():
    m = dm.Model("n")
    u = m.states("u", 3)
    x = np.array([1.0, 2.0, 3.0])
    m.ode(u, x * dm.stencil(u) + 1)  # numpy defers to the stencil (its reflected operator)
    assert [e.expr for e in m.declared().odes.values()] == list(x * u + 1)


def test_stencil_errors_name_the_shapes_the_index_and_the_element():
    m = dm.Model("errors")
    u, v = m.states("u", 4), m.algebraics("v", 3)
    U, V = dm.stencil(u), dm.stencil(v)
    with pytest.raises(E.ShapeError, match=r"stencil \+: operands of shapes \(3,\) and \(4,\)"):
        U + V
    with pytest.raises(E.ShapeError, match=r"stencil of shape \(4,\): index 7 is out of range"):
        U[7]
    with pytest.raises(E.ShapeError, match=r"index 2 selects shape \(\); a stencil keeps"):
        U[2]
    with pytest.raises(E.ShapeError, match=r"index slice\(4, None, None\) selects shape \(0,\)"):
        U[4:]
    with pytest.raises(E.ShapeError, match=r"stencil: needs an array of at least one element; got shape \(\)"):
        dm.stencil(np.array(1.0))
    with pytest.raises(E.ExpressionParseError, match=r"stencil: element \(1,\) is 'x' \(str\); a stencil's array"):
        dm.stencil(np.array([u[0], "x"], dtype=object))
    with pytest.raises(E.ExpressionParseError, match=r"stencil: element \(1,\) is u\[0\] \+ 1 \(Add\)"):
        dm.stencil(np.array([u[1], 1 + u[0]], dtype=object))
    with pytest.raises(E.ExpressionParseError, match=r"apply\(<lambda>\): the result .* is not a sympy expression"):
        U.apply(lambda x: sp.Eq(x, 1))
    with pytest.raises(E.ExpressionParseError, match=r"apply\(atan2\): 'a' is neither a stencil"):
        U.apply(sp.atan2, "a")
    with pytest.raises(E.ShapeError, match=r"m.ode: 3 differential variable.* need .* got a stencil of shape \(4,\)"):
        m.ode(u[1:], U)


def test_a_stencil_of_another_model_s_symbols_or_an_undeclared_name_is_refused():
    m, other = dm.Model("m"), dm.Model("other")
    u = m.states("u", 3)
    q = other.states("q", 3)
    x = sp.Symbol("x")
    with pytest.raises(E.UnknownSymbolError, match=r"the stencil's arrays hold 'q\[\.\.\.\]' \(3 elements\), not "):
        m.ode(u, dm.stencil(q))
    with pytest.raises(E.UnknownSymbolError, match=r"the ODE for 'u\[0\]' \(#1\): unknown name\(s\) 'x'"):
        m.ode(u, x * dm.stencil(u))
    with pytest.raises(E.DerivativeInEquationError, match=r"the ODE for 'u\[0\]' \(#1\): derivative"):
        m.ode(u, sp.Derivative(sp.Function("f")(m.t), m.t) + dm.stencil(u))
    assert not m.declared().odes  # all or none
    m.ode(u, -dm.stencil(u))
    assert [e.expr for e in m.declared().odes.values()] == list(-u)


def test_only_the_elements_sympy_must_evaluate_are_evaluated():
    """Renaming makes every interior element of the Laplacian; the two at the boundary (a number at a
    leaf) are evaluated.  Names c[9] < c[10] < c[2] as strings: the orders of arguments differ along the
    array, and each element is still numpy's."""
    c = np.array([Symbol(f"c[{i}]") for i in range(30)], dtype=object)
    D = Symbol("D")
    padded = np.array([0, *c, 0], dtype=object)
    P = stencil(padded)
    exprs, symbols = expand(D * (P[:-2] - 2 * P[1:-1] + P[2:]))
    assert [k for k, f in enumerate(symbols) if f is None] == [0, 29]
    assert exprs == list(D * (padded[:-2] - 2 * padded[1:-1] + padded[2:]))
    laplacians = [next(a for a in e.args if a.is_Add) for e in exprs[1:-1]]
    first_terms = {str(sum_.args[0]) == f"c[{k}]" for k, sum_ in enumerate(laplacians)}
    assert first_terms == {True, False}  # (c[8], -2*c[9], c[10] in sympy's order: c[10] first)


def test_the_collector_is_paused_while_a_block_is_declared_and_restored_after():
    import gc

    from daemodel.declaring import stencils

    seen = []
    real_expand = stencils.expand

    def spy(s):
        seen.append(gc.isenabled())
        return real_expand(s)

    m = dm.Model("gc")
    u = m.states("u", 3)
    was = gc.isenabled()
    try:
        gc.enable()
        with pytest.MonkeyPatch.context() as patch:
            patch.setattr("daemodel.declaring.model.expand", spy)
            m.ode(u, -dm.stencil(u))
            assert seen == [False] and gc.isenabled()
            gc.disable()
            m.constraint(dm.stencil(m.algebraics("z", 3)) - dm.stencil(u), name="z")
            assert seen == [False, False] and not gc.isenabled()  # (left as the caller had it)
    finally:
        (gc.enable if was else gc.disable)()


def test_symbols_with_assumptions_are_evaluated_as_numpy_evaluates_them():
    """A positive symbol changes sympy's evaluation (sqrt(x**2) is x): no renaming, numpy's trees."""
    x = np.array([sp.Symbol(f"x{i}", positive=True) for i in range(4)], dtype=object)
    exprs, symbols = expand(stencil(x).apply(lambda e: sp.sqrt(e**2)) + 1)
    assert exprs == [xi + 1 for xi in x] and symbols == [None] * 4


def test_what_a_paused_block_made_is_not_scanned_as_young_after_it():
    import gc

    from daemodel.declaring.stencils import paused_collection

    was = gc.isenabled()
    try:
        gc.enable()
        with paused_collection():
            made = [[k] for k in range(50_000)]  # (tracked objects: the youngest generation's count grows)
            assert gc.get_count()[0] >= 50_000
        assert gc.isenabled() and gc.get_freeze_count() == 0
        # in the oldest generation, unscanned (else the first allocation after the block scans them all
        # as the youngest, and the survivors sit in the middle generation)
        assert any(o is made[-1] for o in gc.get_objects(generation=2)) and made[-1] == [49_999]
        gc.collect()
        gc.freeze()  # a caller's frozen objects stay frozen
        frozen = gc.get_freeze_count()
        with paused_collection():
            more = [[k] for k in range(1000)]
        # (neither unfrozen, 0, nor the block's 1,000 lists frozen too; a frozen object freed meanwhile by
        # reference counting leaves the count: 2 of 726,122 did in a full run)
        assert frozen - 100 <= gc.get_freeze_count() <= frozen and gc.isenabled() and len(more) == 1000
    finally:
        gc.unfreeze()
        (gc.enable if was else gc.disable)()

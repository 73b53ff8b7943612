"""Index classification per constraint, singularity checks naming the culprits, reduction."""

import numpy as np
import pytest
import sympy as sp

import daemodel as dm
from daemodel import errors as E
from daemodel.compiling import zero_test
from daemodel.problems import PROBLEMS


@pytest.mark.parametrize("name", list(PROBLEMS))
def test_problem_library_index(name):
    assert PROBLEMS[name].model().compile().index == PROBLEMS[name].index


def test_index1():
    m = dm.Model("index1")
    (y,) = m.states("y")
    (z,) = m.algebraics("z")
    m.ode(y, -z)
    m.constraint(z - y**2 - sp.sin(m.t), name="law")
    m.initial(y=3.0)
    c = m.compile()
    assert c.index == 1 and c.constraint_index == {"law": 1}
    assert c.z0[0] == 9.0
    assert c.invariant_names == ("law",)


def mixed() -> dm.Model:
    """One index-2 and one index-1 constraint, starting at t0 = 0.5."""
    m = dm.Model("mixed")
    y1, y2 = m.states("y1 y2")
    a, b = m.algebraics("a b")
    m.ode(y1, a)
    m.ode(y2, b - y2)
    m.constraint(y1 - m.t**2, name="path")  # index 2: path' = a - 2t  ->  a = 2t
    m.constraint(b - y1 * a, name="law")  # index 1: b = y1 a
    m.initial(t=0.5, y1=0.25, y2=0.0)
    return m


def test_mixed_system_is_classified_per_constraint():
    c = mixed().compile()
    assert c.constraint_index == {"path": 2, "law": 1}
    assert c.index == 2 and c.t0 == 0.5
    np.testing.assert_allclose(c.z0, [1.0, 0.25], rtol=0, atol=1e-15)
    assert c.determined_by == (0, 1)


def test_hessenberg_z0_from_hidden_constraint(hessenberg):
    c = hessenberg.compile()
    assert c.index == 2 and c.state_names == ("y1", "y2", "y3", "y4") and c.algebraic_names == ("y5",)
    assert c.z0[0] == pytest.approx(1.0, abs=1e-15)
    assert "from hidden constraint invariant' = 0" in c.report()


def test_pendulum_index3_and_reduction_to_velocity_form(pendulum3):
    c = pendulum3.compile()
    assert c.index == 3 and c.constraint_index == {"rod": 3}
    y1, y2, y3, y4 = c.states
    assert sp.expand(c.constraints[0].chain[1] - 2 * (y1 * y3 + y2 * y4)) == 0
    v = c.reduced(index=2)
    assert v.index == 2 and v.constraint_names == ("rod'",)
    assert sp.expand(v.g[0] - 2 * (y1 * y3 + y2 * y4)) == 0
    assert v.invariant_names == ("rod", "rod'")  # the original constraint is kept for drift
    np.testing.assert_array_equal(v.z0, c.z0)
    one = c.reduced(index=1)
    assert one.index == 1 and one.constraint_names == ("rod''",)
    assert one.reduced(index=1).constraint_names == ("rod''",)
    assert "reduced from index 3" in one.report()


def test_reduced_velocity_pendulum_matches_paper_pendulum(pendulum, pendulum3):
    # The index-3 model reduced to index 2 is the paper's pendulum up to the factor 2.
    paper, reduced = pendulum.compile(), pendulum3.compile().reduced(index=2)
    assert sp.expand(reduced.g[0] - 2 * paper.g[0]) == 0
    np.testing.assert_allclose(reduced.z0, paper.z0, atol=1e-15)


def test_index2_to_index1(hessenberg):
    c = hessenberg.compile().reduced(index=1)
    assert c.index == 1 and c.constraint_names == ("invariant'",) and c.invariant_names == ("invariant",)
    y5 = c.algebraics[0]
    assert sp.diff(c.g[0], y5) != 0  # now determines y5 directly (g_z nonsingular)


@pytest.mark.parametrize("bad", [0, 3, 1.0, True])
def test_reduction_errors(hessenberg, bad):
    with pytest.raises(
        E.ReductionError,
        match=rf"reduced\(index={bad!r}\): the target must be an integer from 1 to the current index 2",
    ):
        hessenberg.compile().reduced(index=bad)


def test_algebraic_in_no_jacobian():
    m = dm.Model("dangling")
    y1, y2 = m.states("y1 y2")
    lam, _ = m.algebraics("lam mu")
    m.ode(y1, lam)
    m.ode(y2, -y2)
    m.constraint(y1 - sp.sin(m.t), name="rod")
    m.constraint(y2 + lam - 1, name="other")
    m.initial(y1=0.0, y2=0.0)
    with pytest.raises(
        E.SingularSystemError,
        match=r"algebraic variable 'mu' appears in no constraint's Jacobian: no constraint determines it "
        r"\(constraint 'rod' \(#3\) \(index 2: through g_y f_z\); constraint 'other' \(#4\)",
    ):
        m.compile()


def test_structurally_singular_block():
    m = dm.Model("competing")
    y1, y2, y3 = m.states("y1 y2 y3")
    a, b, c = m.algebraics("a b c")
    m.ode(y1, a)
    m.ode(y2, a)
    m.ode(y3, b + c)
    m.constraint(y1 - m.t, name="c1")
    m.constraint(y2 - 2 * m.t, name="c2")
    m.constraint(y3 * b - c, name="c3")
    m.initial(y1=0.0, y2=0.0, y3=0.0)
    with pytest.raises(
        E.SingularSystemError,
        match=r"structurally singular: 2 constraint\(s\) constraint 'c1' \(#4\) .*, constraint 'c2' \(#5\) .* can only "
        r"determine 1 algebraic variable\(s\) 'a'",
    ):
        m.compile()


def chain_of_algebraics(K: int, orientation: str):
    """K states c and K algebraic w, c' = -c + w / 100, with a bidiagonal g_z: ``w[i] + w[i-1] / 2 = c[i]``
    from ``w[0] = c[0]^3`` (lower), or ``w[i] + 2 w[i+1] = c[i]`` closed by ``w[0] = c[K-1]^3`` (upper, whose
    matching needs one augmenting path through the whole chain); and g_z as a scipy matrix."""
    import scipy.sparse

    m = dm.Model(f"chain_{orientation}")
    c, w = m.states("c", K), m.algebraics("w", K)
    m.ode(c, -c + 0.01 * w)
    i = np.arange(K - 1)
    if orientation == "lower":
        m.constraint(dm.stencil(w[1:]) + 0.5 * dm.stencil(w[:-1]) - dm.stencil(c[1:]), name="pair")
        m.constraint(w[0] - c[0] ** 3, name="end")  # (not an alias: w stays)
        rows, cols, values = np.r_[i, i, K - 1], np.r_[i + 1, i, 0], np.r_[np.ones(K - 1), np.full(K - 1, 0.5), 1.0]
        right = np.r_[1 + i, 0]  # (c[i + 1] for pair[i], c[0] for end)
    else:
        m.constraint(dm.stencil(w[:-1]) + 2 * dm.stencil(w[1:]) - dm.stencil(c[:-1]), name="pair")
        m.constraint(w[0] - c[K - 1] ** 3, name="end")
        rows, cols, values = np.r_[i, i, K - 1], np.r_[i, i + 1, 0], np.r_[np.ones(K - 1), np.full(K - 1, 2.0), 1.0]
        right = np.r_[i, K - 1]
    y0 = np.cos(np.arange(K))
    m.initial(c=y0)
    g_c = y0[right]
    g_c[-1] **= 3
    return m, scipy.sparse.csc_matrix((values, (rows, cols)), shape=(K, K)), g_c


@pytest.mark.parametrize("orientation", ["lower", "upper"])
def test_a_long_chain_of_algebraic_variables_is_matched(orientation):
    # the matching's augmenting paths were recursive: a chain of 1,200 algebraic variables stopped compile
    # with a RecursionError (and a lower chain took O(n^2) steps: each row walked back the whole chain)
    import scipy.sparse.linalg

    m, g_z, g_c = chain_of_algebraics(1_200, orientation)
    c = m.compile()
    assert c.index == 1 and len(c.algebraics) == 1_200
    assert np.allclose(c.z0, scipy.sparse.linalg.spsolve(g_z, g_c), rtol=1e-12, atol=1e-12)


def test_structural_messages_name_at_most_a_dozen_of_many_culprits():
    # the messages listed every constraint of the model, or of the block (at 10^5: megabytes of text)
    K = 40
    m = dm.Model("dangling_many")
    c, w = m.states("c", K), m.algebraics("w", K + 1)
    m.ode(c, -c + w[:-1])
    m.constraint(w[:-1] - c**2, name="rate")
    m.constraint("c[0]**2 - 1", name="level")  # (its hidden form holds w[0], again: w[40] is in none)
    m.initial(c=1.0)
    with pytest.raises(
        E.SingularSystemError,
        match=r"algebraic variable 'w\[40\]' appears in no constraint's Jacobian: no constraint determines it "
        r"\(constraint 'rate\[0\]' \(#41\) \(index 1: through g_z\); .*; constraint 'rate\[11\]' \(#52\) "
        r"\(index 1: through g_z\); \.\.\. \(41 in all; the first 12 listed\)\)\. Make 'w\[40\]' enter",
    ):
        m.compile()
    K = 20
    m = dm.Model("competing_many")
    c, w = m.states("c", K), m.algebraics("w", K)
    m.ode(c, -c + w)
    m.constraint(dm.stencil(w[: K - 3]) + 2 * dm.stencil(w[1 : K - 2]) - dm.stencil(c[: K - 3]) ** 2, name="pair")
    m.constraint("c[0]**2 - 1", name="a")  # (hidden forms: a holds w[0], b w[17]; 19 rows on w[0] ... w[17])
    m.constraint("c[17]**2 - 1", name="b")
    m.constraint("w[18] + w[19] - c[19]**2", name="last")
    m.initial(c=1.0)
    with pytest.raises(
        E.SingularSystemError,
        match=r"structurally singular: 19 constraint\(s\) constraint 'pair\[0\]' \(#21\) .*, constraint "
        r"'pair\[11\]' \(#32\) \(index 1: through g_z\), \.\.\. \(19 in all; the first 12 listed\) can only "
        r"determine 18 algebraic variable\(s\) 'w\[0\]', .*'w\[11\]', \.\.\. \(18 in all; the first 12 listed\);",
    ):
        m.compile()


def test_numerically_singular_at_initial_point():
    m = dm.Model("degenerate")
    y1, y2 = m.states("y1 y2")
    (a,) = m.algebraics("a")
    m.ode(y1, y2 * a)  # g_y f_z = y2, zero at the initial point
    m.ode(y2, 1)
    m.constraint(y1 - 1, name="level")
    m.initial(y1=1.0, y2=0.0)
    with pytest.raises(
        E.SingularSystemError,
        match=r"constraint 'level' \(#3\) do not determine the algebraic variable\(s\) 'a': g_y f_z is singular "
        r"at t=0 \(smallest singular value 0",
    ):
        m.compile()
    m.initial(y2=0.5)
    assert m.compile().z0[0] == 0.0


def test_numerically_singular_names_all_culprits():
    m = dm.Model("rank1")
    y1, y2 = m.states("y1 y2")
    a, b = m.algebraics("a b")
    m.ode(y1, a + b)
    m.ode(y2, 2 * a + 2 * b)
    m.constraint(y1 - m.t, name="p")
    m.constraint(y2 - 2 * m.t, name="q")
    m.initial(y1=0.0, y2=0.0)
    with pytest.raises(E.SingularSystemError, match=r"'p' \(#3\), constraint 'q' \(#4\) do not determine .*'a', 'b'"):
        m.compile()


def test_constraint_that_never_meets_an_algebraic():
    m = dm.Model("chain")
    y1, y2, y3 = m.states("y1 y2 y3")
    (z,) = m.algebraics("z")
    m.ode(y1, y2)
    m.ode(y2, y3)
    m.ode(y3, z)  # index 4 for a constraint on y1
    m.constraint(y1 - sp.sin(m.t), name="deep")
    m.initial(y1=0.0, y2=1.0, y3=0.0)
    with pytest.raises(
        E.IndexTooHighError, match=r"constraint 'deep' \(#4\): no algebraic variable appears in it or in its first 2"
    ):
        m.compile()


def test_constraint_that_is_an_ode_invariant():
    m = dm.Model("invariant")
    y1, y2 = m.states("y1 y2")
    (z,) = m.algebraics("z")
    m.ode(y1, 0)
    m.ode(y2, z)
    m.constraint(y1 - 1, name="fixed")
    m.initial(y1=1.0, y2=0.0)
    with pytest.raises(
        E.IndexTooHighError, match=r"constraint 'fixed' \(#3\): fixed' is identically zero along the ODE"
    ):
        m.compile()


# ---- the zero test: numbers first, a bounded expansion last ---------------------------------------
zx, zy, zz = sp.symbols("x y z")


@pytest.fixture
def no_expansion(monkeypatch):
    """sympy's expand, made to fail: what passes with it decided without expanding."""

    def refuse(*args, **kwargs):
        raise AssertionError("expanded")

    monkeypatch.setattr(zero_test.sp, "expand", refuse)


@pytest.mark.parametrize(
    "expr",
    [
        sp.sin(zx) * sp.cos(zy) ** 3 + sp.tanh(zx * zy) - 1,
        # two nearly equal terms of sqrt and atan of trig: a difference of ~1e-13 that float64 could
        # not tell from round-off, and 40 digits can
        sp.sqrt(1 + sp.sin(zx) ** 2) * sp.atan(sp.cos(zy) / zz)
        - sp.sqrt(1 + sp.sin(zx) ** 2 + sp.Rational(1, 10**12) * zx) * sp.atan(sp.cos(zy) / zz),
        sp.sqrt(0.06**2 - (zx - 0.15) ** 2) + zy,  # imaginary at every point tried: complex values decide too
        sp.Max(zx, zy) - zx,  # vanishes where x > y only
    ],
)
def test_nonzero_expressions_are_decided_without_expansion(expr, no_expansion):
    assert zero_test.is_zero(expr) is False


@pytest.mark.parametrize(
    "expr",
    [
        sp.sin(zx) ** 2 + sp.cos(zx) ** 2 - 1,  # sympy's expand leaves it as it is
        sp.exp(zx + zy) - sp.exp(zx) * sp.exp(zy),
        sp.tan(zx * zy) - sp.sin(zx * zy) / sp.cos(zx * zy),
        (zx + 1) ** 2 - zx**2 - 2 * zx - 1,
        (sp.sin(zx) + sp.cos(zy)) ** 3 - sp.expand((sp.sin(zx) + sp.cos(zy)) ** 3),
    ],
)
def test_analytic_zeros_are_decided_zero_without_expansion(expr, no_expansion):
    assert zero_test.is_zero(expr) is True


def test_numbers_do_not_decide_a_zero_that_holds_on_part_of_the_domain():
    """sqrt(x**2) - x vanishes for x > 0 only: the values at the first (positive) points vanish,
    but sqrt is not analytic, so the numbers do not decide; the expansion keeps it (not zero)."""
    for expr in (sp.sqrt(zx**2) - zx, sp.sqrt(zx * zy) - sp.sqrt(zx) * sp.sqrt(zy)):
        assert zero_test.numeric_zero_test(expr) is None
        assert zero_test.is_zero(expr) is False


def test_an_expression_that_has_no_value_at_a_point_is_tried_at_the_next():
    """1/(x - x0) with x0 the first point's value of x: a pole there, decided at the next point."""
    x0 = zero_test.numeric_point(zx, 0)
    expr = 1 / (zx - sp.Float(x0, 60)) + sp.sin(zx)
    with pytest.raises(zero_test._NoValue):
        zero_test._numeric_value(expr, 0, zero_test.ZERO_TEST_DIGITS[0])
    assert zero_test.numeric_zero_test(expr) is False


def test_expansion_size_counts_the_terms_expand_makes():
    for expr in [(zx + zy) ** 3, (zx + zy) * (zx - zy + 1), (zx + zy + zz + 1) ** 6]:
        assert zero_test.expansion_size(expr) >= len(sp.Add.make_args(sp.expand(expr)))
    assert zero_test.expansion_size((zx + zy + zz + 1) ** 20) == 1771  # C(23, 3) monomials


def test_the_expansion_bound(monkeypatch):
    """What the numbers cannot decide (Piecewise is not evaluated) is expanded when small, and
    taken for "not zero" without expanding when the expansion would exceed the bound."""
    piece = sp.Piecewise((zx, zy > 0), (0, True))
    expanded = []
    real_expand = sp.expand
    monkeypatch.setattr(zero_test.sp, "expand", lambda e: expanded.append(e) or real_expand(e))
    small = piece * (zx + 1) ** 2 - piece * (zx**2 + 2 * zx + 1)
    assert zero_test.numeric_zero_test(small) is None
    assert zero_test.is_zero(small) is True and len(expanded) == 1
    large = piece * (zx + zy + zz + 1) ** 20 - piece * (zx + zy + zz + 1) ** 20 * (1 + zx - zx * piece / piece)
    assert zero_test.expansion_size(large) > zero_test.MAX_EXPANSION_TERMS
    assert zero_test.is_zero(large) is False and len(expanded) == 1  # not expanded: the safe answer


def test_alias_that_only_the_trigonometric_identity_reveals():
    m = dm.Model("trig-alias")
    (c,) = m.states(["c"])
    q, w = m.algebraics(["q", "w"])
    m.ode(c, -w - q)
    m.constraint(w - c**2, name="rate")
    m.constraint(q - c * (sp.sin(c) ** 2 + sp.cos(c) ** 2), name="same")
    m.initial(c=0.5)
    assert m.compile().alias_names == ("q",)

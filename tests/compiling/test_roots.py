"""Roots of the constraints: the branch the guess selects at t0, every method staying on it, claims
checked against it, and consistent(fix=...)."""

import numpy as np
import pytest

import daemodel as dm
from daemodel import errors as E
from daemodel.compiling.init import NewtonTolerances, solve_algebraic


def square_root(guess: float) -> dm.Model:
    """``0 = z^2 - x``, x' = -z/10, x(0) = 4: z = +-2 at t0, each root a branch of its own."""
    m = dm.Model("square_root")
    (x,) = m.states("x")
    (z,) = m.algebraics("z")
    m.ode(x, -z / 10)
    m.constraint(z**2 - x, name="root")
    m.initial(x=4.0)
    m.guess(z=guess)
    return m


def circle(guess: float) -> dm.Model:
    """``0 = u^2 + v^2 - 1``, ``0 = v - x u``: u = +-1/sqrt(1 + x^2), v = x u."""
    m = dm.Model("circle")
    (x,) = m.states("x")
    u, v = m.algebraics("u v")
    m.ode(x, 1)
    m.constraint(u**2 + v**2 - 1, name="circle")
    m.constraint(v - x * u, name="ray")
    m.initial(x=0.75)
    m.guess(u=guess, v=0.0)
    return m


def crossing() -> dm.Model:
    """``0 = z^2 - x^2``, x' = -1, x(0) = 1: the branches z = x and z = -x cross at t = 1, where
    dH/dz = 2 z vanishes; past it Newton from the last z lands on the other branch, z = |x|."""
    m = dm.Model("crossing")
    (x,) = m.states("x")
    (z,) = m.algebraics("z")
    m.ode(x, -1)
    m.constraint(z**2 - x**2, name="cross")
    m.initial(x=1.0)
    m.guess(z=0.5)
    return m


def fold() -> dm.Model:
    """``0 = z^3 - 3 z - x``, x' = -1, x(0) = 0, z(0) = sqrt(3): the upper branch turns back at
    z = 1, x = -2 (t = 2); past it the only root is on the lower branch, z < -2."""
    m = dm.Model("fold")
    (x,) = m.states("x")
    (z,) = m.algebraics("z")
    m.ode(x, -1)
    m.constraint(z**3 - 3 * z - x, name="cubic")
    m.initial(x=0.0)
    m.guess(z=2.0)
    return m


# ---- the root at t0 ------------------------------------------------------------------------


@pytest.mark.parametrize("guess, root", [(0.3, 2.0), (-0.3, -2.0), (7.0, 2.0), (-1.5, -2.0)])
def test_the_guess_selects_the_nearest_root_and_the_report_names_it(guess, root):
    c = square_root(guess).compile()
    assert c.z0[0] == pytest.approx(root, abs=1e-15)
    assert f"root chosen by the guess: z = {root:.10g} (Newton from m.guess z = {guess:.6g})" in c.report()
    sol = dm.solve(c, (0.0, 1.0), method="reference", t_eval=[0.0, 1.0])
    # exact: z' = x'/(2z) = -1/20, so z = z0 - t/20 on either branch
    assert sol["z"][-1] == pytest.approx(root - 0.05, abs=1e-11)


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_a_circle_root_is_chosen_by_the_guess_sign(sign):
    c = circle(0.5 * sign).compile()
    u0 = sign / np.sqrt(1 + 0.75**2)  # 0.8 or -0.8
    np.testing.assert_allclose(c.z0, [u0, 0.75 * u0], rtol=0, atol=1e-15)
    sol = dm.solve(c, (0.0, 1.0), method="reference", t_eval=[0.0, 0.5, 1.0])
    x = 0.75 + sol.t
    np.testing.assert_allclose(sol["u"], sign / np.sqrt(1 + x**2), rtol=0, atol=1e-12)
    np.testing.assert_allclose(sol["v"], sign * x / np.sqrt(1 + x**2), rtol=0, atol=1e-12)


# ---- claims --------------------------------------------------------------------------------


def test_a_claimed_root_of_another_branch_is_refused_with_both_values():
    m = square_root(1.0)
    m.initial(z=-2.0)  # a root, but the guess selects z = 2
    with pytest.raises(
        E.WrongBranchError,
        match=r"initial value z = -2 is a root of the constraints, but of another branch than the one the guess "
        r"selects: the root nearest the guess is z = 2\.0\. Drop the initial value, or move m\.guess",
    ):
        m.compile()
    m.initial(z=2.0)  # the same root: accepted
    assert m.compile().z0[0] == 2.0
    m.initial(z=-1.0)  # no root at all: the old message, which names the consistent value
    with pytest.raises(E.InconsistentAlgebraicValueError, match=r"z = -1 disagrees with the consistent value z = 2\.0"):
        m.compile()
    with pytest.raises(E.InconsistentAlgebraicValueError) as caught:
        m.compile()
    assert not isinstance(caught.value, E.WrongBranchError)


def test_a_solve_z0_on_another_branch_is_the_users_choice():
    """Before: refused as another branch than the guess selects (WrongBranchError). A z0 that is a root
    is an explicit, consistent choice: each sample follows its own root; one that is none is refused."""
    c = square_root(1.0).compile()
    for method, options in (
        ("reference", {}),
        ("radau", {"rtol": 1e-10, "atol": 1e-10}),
        ("casadi-idas", {"rtol": 1e-10, "atol": 1e-10}),
    ):
        sol = dm.solve(c, (0.0, 1.0), method=method, z0={"z": [-2.0, 2.0]}, t_eval=[0.0, 1.0], **options)
        # z z' = x' / 2 = -z / 20 on either root: z = z0 - t / 20
        assert sol["z"][:, -1] == pytest.approx([-2.05, 1.95], abs=1e-8), method
    with pytest.raises(
        E.InconsistentAlgebraicValueError,
        match=r"z0: z = -1 of sample 1 disagrees with the consistent value 2\.0 \(and is no root of the constraints\)",
    ):
        dm.solve(c, (0.0, 1.0), method="reference", z0={"z": [-2.0, -1.0]})
    sol = dm.solve(c, (0.0, 1.0), method="reference", z0={"z": 2.0}, t_eval=[0.0, 1.0])
    assert sol["z"][-1] == pytest.approx(1.95, abs=1e-11)
    # with new states the compiled root is still the start that selects the branch
    sol = dm.solve(c, (0.0, 1.0), method="reference", y0={"x": 9.0}, t_eval=[0.0, 1.0])
    assert sol["z"][0] == pytest.approx(3.0, abs=1e-14)


# ---- staying on the branch -----------------------------------------------------------------


def test_newton_from_the_last_root_would_jump_branches_at_the_crossing():
    """The failure the reference now refuses: past t = 1, Newton from the previous z (the naive
    continuation) converges to z = |x|, the other branch, without any sign of trouble."""
    x_before, x_after = 0.01, -0.05
    result = solve_algebraic(
        lambda z: z**2 - x_after**2, lambda z: (2 * z)[:, :, None], np.array([[x_before]]), NewtonTolerances()
    )
    assert result.converged[0]
    assert result.x[0, 0] == pytest.approx(-x_after, abs=1e-15)  # z = |x|: not the branch z = x


def test_the_reference_refuses_to_cross_to_another_branch():
    c = crossing().compile()
    sol = dm.solve(c, (0.0, 0.9), method="reference", t_eval=[0.0, 0.5, 0.9])
    np.testing.assert_allclose(sol["z"], 1 - sol.t, rtol=0, atol=1e-12)  # on the branch z = x
    with pytest.raises(
        E.BranchError,
        match=r"reference: near t = (1|0\.99999\d*) \(sample 0 of 'crossing', integrator DOP853\): the algebraic "
        r"variables leave their branch of roots: det\(dH/dz\) changes sign between t = .* so dH/dz is singular in "
        r"between: the branch turns back \(a fold\) or meets another one",
    ):
        dm.solve(c, (0.0, 2.0), method="reference", t_eval=[0.0, 0.5, 1.5, 2.0])


def test_the_reference_reports_the_end_of_a_folding_branch():
    c = fold().compile()
    assert c.z0[0] == pytest.approx(np.sqrt(3), abs=1e-15)
    sol = dm.solve(c, (0.0, 1.9), method="reference", t_eval=[0.0, 1.0, 1.9])
    exact = [max(np.roots([1, 0, -3, t]).real) for t in sol.t]  # the upper root of z^3 - 3 z + t
    np.testing.assert_allclose(sol["z"], exact, rtol=0, atol=1e-11)
    with pytest.raises(
        E.BranchError,
        match=r"reference: near t = (2|1\.99999\d*) .*Newton for z did not converge.*; the branch of roots ends "
        r"here: at the last accepted point, t = .* \(z = 1\.0\d*\), dH/dz is nearly singular \(smallest singular "
        r"value .*\): the root meets another one and both vanish \(a fold\)",
    ):
        dm.solve(c, (0.0, 3.0), method="reference")


def test_the_reference_refuses_a_jump_far_from_the_continuation():
    """Past the fold of z^3 - 3 z = x, Newton from the branch's tangent prediction converges to the
    lower root, where det(dH/dz) has the same sign as on the upper branch: the jump test refuses it,
    and accepts a nearby point that continues the branch."""
    from daemodel.backends.reference import AlgebraicSolver

    from daemodel.compiling.init import NumericSystem

    c = fold().compile()
    solver = AlgebraicSolver(c, NumericSystem(c.t, c.states, c.algebraics, c.parameters), 30)
    p = np.zeros(0)
    upper = max(np.roots([1, 0, -3, 1.9]).real)  # the upper branch at x = -1.9
    point = solver.branch_point(1.9, np.array([-1.9]), np.array([upper]), p, None)
    near = np.array([-1.95])
    predicted = point.predict(1.95, near)
    z = solver.solve(1.95, near, predicted, p)
    assert z[0] == pytest.approx(max(np.roots([1, 0, -3, 1.95]).real), abs=1e-14)
    assert solver.leaves_branch(1.95, near, z, p, predicted, point) is None
    far = np.array([-2.5])
    predicted = point.predict(2.5, far)
    z = solver.solve(2.5, far, predicted, p)
    assert z[0] == pytest.approx(min(np.roots([1, 0, -3, 2.5]).real), abs=1e-14)  # the lower branch
    why = solver.leaves_branch(2.5, far, z, p, predicted, point)
    assert why is not None
    assert why.startswith(
        "the algebraic variables leave their branch of roots: continuing it from t = 1.9 (z = 1.1774) predicts "
        "z = 0.659646, but Newton converged to another root, z = -2.05362 (a jump of 2.71, allowed 0.518)"
    )


def test_every_method_refuses_a_solution_that_leaves_the_branch():
    c = crossing().compile()
    message = (
        r"{}: the algebraic variables leave the branch of roots chosen at t0 between t = .* "
        r"\(sample 0 of 'crossing'\): det\(dH/dz\) changes sign there"
    )
    for method, options in (("casadi-idas", {}), ("casadi-collocation", {"h": 0.05}), ("radau", {"rtol": 1e-8})):
        with pytest.raises(E.BranchError, match=message.format(method)):
            dm.solve(c, (0.0, 3.0), method=method, **options)


# ---- consistent(fix=...) -------------------------------------------------------------------


def plane() -> dm.Model:
    """States a, b, c on the plane a + b + c = 1 (index 2: w = 0 from a' + b' + c' = w = 0)."""
    m = dm.Model("plane")
    a, b, c = m.states("a b c")
    (w,) = m.algebraics("w")
    m.ode(a, w)
    m.ode(b, -a)
    m.ode(c, a)
    m.constraint(a + b + c - 1, name="plane")
    m.initial(a=0.2, b=0.3, c=0.5)
    return m


def test_consistent_fix_holds_the_named_states_and_moves_the_others_least():
    c = plane().compile()
    # a + b + c = 1.6: the unfixed b and c each move by 0.3 (the least change for them), a stays
    assert c.consistent(y0={"a": 0.8, "b": 0.3, "c": 0.5}, fix=["a"]) == pytest.approx(
        {"a": 0.8, "b": 0.0, "c": 0.2}, abs=1e-15
    )
    assert c.consistent(y0={"a": 0.8, "b": 0.3, "c": 0.5}, fix=("a", "b")) == pytest.approx(
        {"a": 0.8, "b": 0.3, "c": -0.1}, abs=1e-15
    )
    batch = c.consistent(y0={"a": [0.8, 0.2], "b": 0.3, "c": 0.5}, fix="a")
    np.testing.assert_allclose(batch["a"], [0.8, 0.2], rtol=0, atol=0)
    np.testing.assert_allclose(batch["b"], [0.0, 0.3], rtol=0, atol=1e-15)
    np.testing.assert_allclose(batch["c"], [0.2, 0.5], rtol=0, atol=1e-15)
    # without fix, all three move by 0.2: the previous behaviour
    assert c.consistent(y0={"a": 0.8, "b": 0.3, "c": 0.5}) == pytest.approx({"a": 0.6, "b": 0.1, "c": 0.3}, abs=1e-15)


def test_consistent_fix_on_a_circle():
    """x^2 + y^2 = 1 (index 3, a pendulum): holding the position x moves y to the nearer root."""
    from daemodel.problems import PENDULUM_INDEX3

    c = PENDULUM_INDEX3.model().compile()
    names = c.state_names
    x, y = names[0], names[1]
    start = {n: 0.0 for n in names}
    start.update({x: 0.6, y: -0.7})
    fixed = c.consistent(y0=start, fix=[x])
    assert fixed[x] == 0.6
    assert fixed[y] == pytest.approx(-0.8, abs=1e-14)  # the root nearest -0.7, not +0.8


def test_consistent_fix_errors_name_the_culprit():
    c = plane().compile()
    with pytest.raises(
        E.UnknownSymbolError,
        match=r"consistent\(fix=\.\.\.\): 'w', 'q' are not a state of model 'plane'; the states are \['a', 'b', 'c'\]",
    ):
        c.consistent(fix=["w", "q"])
    with pytest.raises(
        E.FixedStateError,
        match=r"consistent\(fix=\.\.\.\) holds every state \(a, b, c\), so nothing can move, but sample 0 violates "
        r"constraint 'plane' .*: plane = 0\.6 .*leave at least one state out of fix",
    ):
        c.consistent(y0={"a": 0.8}, fix=["a", "b", "c"])
    assert c.consistent(fix=["a", "b", "c"]) == pytest.approx({"a": 0.2, "b": 0.3, "c": 0.5})  # consistent already

    from daemodel.problems import PENDULUM_INDEX3

    d = PENDULUM_INDEX3.model().compile()
    x, y = d.state_names[:2]
    others = ", ".join(d.state_names[1:])
    with pytest.raises(
        E.FixedStateError,
        match=rf"consistent\(fix=\.\.\.\): with {x} held at sample 0's values, no values of the other states "
        rf"\({others}\) satisfy .*fix fewer states, or values that the constraints allow",
    ):
        d.consistent(y0={x: 2.0, y: 0.1}, fix=[x])  # x^2 + y^2 = 1 has no y for x = 2


def test_the_branch_check_reads_the_outputs_in_chunks(monkeypatch):
    """One matrix per evaluation of H_z: the same refusal as all at once."""
    import daemodel.compiling.initial_states as initial_states

    monkeypatch.setattr(initial_states, "BRANCH_CHECK_BYTES", 8)
    with pytest.raises(E.BranchError, match=r"casadi-idas: the algebraic variables leave the branch of roots"):
        dm.solve(crossing().compile(), (0.0, 3.0), method="casadi-idas")
    sol = dm.solve(crossing().compile(), (0.0, 0.9), method="casadi-idas", t_eval=np.linspace(0, 0.9, 10))
    np.testing.assert_allclose(sol["z"], 1 - sol.t, rtol=0, atol=1e-6)


def test_the_branch_check_holds_one_copy_of_h_z_s_entries():
    """H_z's nonzeros at 200 outputs of 2,000 algebraic variables are 6.4 MB: the check holds them once (their
    evaluation's transposed view, not a C-ordered copy beside it: 4.4 MB of a cold solve's peak at 10^5 unknowns),
    with the same values, and reads the signs from them."""
    import tracemalloc

    import daemodel.compiling.initial_states as initial_states

    model, K = dm.Model("roots2000"), 2000
    u, w = model.states("u", K), model.algebraics("w", K)
    for k in range(K):
        model.ode(u[k], u[(k + 1) % K] - u[k])
        model.constraint(w[k] ** 2 - u[k] - w[(k + 1) % K] / 10, name=f"root{k}")  # (H_z: 2 w_k, -1/10 beside)
    model.initial(u=np.ones(K))
    compiled = model.compile()
    n, m = len(compiled.states), len(compiled.algebraics)
    rng = np.random.default_rng(3)
    values = np.concatenate([rng.uniform(0.5, 1.5, (1, 200, n)), rng.uniform(0.5, 1.5, (1, 200, m))], axis=-1)
    times, P = np.linspace(0.0, 1.0, 200), np.asarray(compiled.parameter_values)[None]
    *_, entries = initial_states.branch_check_functions(compiled)
    rows = values[0]
    view = entries(times, rows[:, :n], rows[:, n:], np.repeat(P, 200, axis=0), contiguous=False)
    whole = entries(times, rows[:, :n], rows[:, n:], np.repeat(P, 200, axis=0))
    assert whole.flags.c_contiguous and not view.flags.c_contiguous and np.array_equal(view, whole)
    size = whole.nbytes
    del view, whole
    initial_states.check_branch("radau", compiled, times, values, P)  # (its functions made before the count)
    tracemalloc.start()
    initial_states.check_branch("radau", compiled, times, values, P)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert size == 200 * 2 * m * 8 and peak < 1.75 * size  # (and the lambdified function's list of its 4,000 rows)
    values[0, 150, n + 7] *= -1  # (one output's z on the other side: det H_z changes sign there)
    with pytest.raises(E.BranchError, match="leave the branch of roots"):
        initial_states.check_branch("radau", compiled, times, values, P)


def test_newton_reports_convergence_and_singularity_for_the_caller_to_judge():
    """0 = z^2 + 1 has no real root and a singular Jacobian at z = 0; 0 = z^2 - 4 converges from 1 and
    from -1 to the root on its side."""
    F, J = (lambda z: z**2 + 1), (lambda z: (2 * z)[:, :, None])
    result = solve_algebraic(F, J, np.array([[0.0]]))
    assert not result.converged[0] and result.singular[0]
    result = solve_algebraic(lambda z: z**2 - 4, J, np.array([[1.0], [-1.0]]))
    assert result.converged.all() and not result.singular.any()
    np.testing.assert_allclose(result.x[:, 0], [2.0, -2.0], rtol=0, atol=1e-15)
    capped = solve_algebraic(lambda z: z**2 - 4, J, np.array([[1.0]]), NewtonTolerances(max_iterations=2))
    assert not capped.converged[0] and capped.iterations == 2


def test_a_kink_in_the_constraints_is_no_jump():
    """z1^3 + z1 = cosh(tanh(min(y3, k1, 1.96))) has one real root for every y3; where y3 crosses
    k1 the tangent prediction turns wrong (the kink), and the root lies closer to the last root than
    to it: no BranchError (the fuzz case r1-0015 was refused so), and the values are the roots."""
    m = dm.Model("index1")
    m.states("y1 y2 y3")
    m.algebraics("z1 z2")
    m.parameter("k1", 0.85)
    m.ode("y1", "-0.95*y1 + 0.57*z2 + 0.27*tanh(z1/(2 + z2**2))**3")
    m.ode("y2", "-1.26*y2 + 0.31*z1 + 0.23*(1 + (y2/(1.5 + cos(t)))**2)**1.5")
    m.ode("y3", "-1.54*y3 + 0.27*z2 + 0.22*sign(0.47*y1*y2)*(0.47*y1*y2)")
    m.constraint("z1**3 + z1 - cosh(tanh(Min(y3, k1, 1.96)))")
    m.constraint("z2 + 0.5*sin(z2) - Max(0.63, sin(8/6), y3, k1)")
    m.initial(y1=0.981, y2=-0.782, y3=-0.253)
    sol = dm.solve(m, (0.0, 1.0), method="reference")
    assert sol.status == "success"
    z1, y3 = sol["z1"], sol["y3"]
    np.testing.assert_allclose(z1**3 + z1, np.cosh(np.tanh(np.minimum(y3, 0.85))), rtol=1e-10)

"""The algebraic variables solved from a method's states (daemodel/compiling/algebraic.py)."""

import dataclasses
import threading
import warnings

import numpy as np
import pytest
import sympy as sp

import daemodel as dm
from daemodel.compiling import algebraic
from daemodel.compiling.initial_states import constraint_checks
from daemodel.problems import PENDULUM
from daemodel.problems.families import pendulum_chain

# radau's default on casadi's virtual machine, but in the tests marked machine_code (tests/conftest.py)
pytestmark = pytest.mark.virtual_machine


def _outputs(sol):
    """``(Y, Z, P)`` of a solution's outputs, one sample: (1, K, n), (1, K, m), (1, k)."""
    compiled = sol.compiled
    Y = np.stack([sol[name] for name in compiled.state_names], axis=-1)[None]
    Z = np.stack([sol[name] for name in compiled.algebraic_names], axis=-1)[None]
    return Y, Z, np.asarray(compiled.parameter_values, dtype=float)[None]


def _counting(monkeypatch, compiled) -> list:
    """Counts the numpy path's evaluations of the determining equations and their z Jacobian."""
    checks, calls = constraint_checks(compiled), []

    def H(*arguments):
        calls.append("H")
        return checks.H(*arguments)

    def Hz(*arguments):
        calls.append("Hz")
        return checks.Hz(*arguments)

    monkeypatch.setattr(algebraic, "constraint_checks", lambda _: dataclasses.replace(checks, H=H, Hz=Hz))
    return calls


def test_affine_determining_equations_take_one_whole_newton_step(monkeypatch):
    """A chain of 20 pendulums (index 3, solved at index 2: its multipliers' determining equations are
    affine in them): from radau's collocation values, the 21 outputs of an adaptive solve settle in one
    whole Newton step of the batched numpy path (without the affine step), the equations evaluated twice.
    Before, the step was halved three times where the start was at the rounding level of the residual
    (5 evaluations, 16 of the solve's 64 ms)."""
    sol = dm.solve(pendulum_chain(20).compile(), (0.0, 1.0), rtol=1e-6, atol=1e-6)
    compiled = sol.compiled
    monkeypatch.setattr(algebraic, "affine_step", lambda _: None)
    calls = _counting(monkeypatch, compiled)
    Y, Z, P = _outputs(sol)
    found = algebraic.algebraic_from_states(compiled, sol.t, Y, Z, P)
    assert found.converged.all()
    assert calls.count("H") == 2
    np.testing.assert_allclose(found.z, Z, rtol=1e-12, atol=1e-12)  # (the returned values: solved so already)


def test_the_affine_step_solves_without_the_numpy_path(monkeypatch):
    """Affine determining equations are solved by one casadi function of the outputs (AffineStep, made in the
    setup): no numpy evaluation of H or H_z (the numpy path cost ~1 ms at 21 outputs of 20 pendulums, more than
    half of radau's solve at rtol 1e-4), and the values of the numpy path's Newton from the same start, here
    100 tolerances off the root, to rounding; 37 outputs (batches of 32, 4 and 1)."""
    sol = dm.solve(pendulum_chain(20).compile(), (0.0, 1.0), rtol=1e-6, atol=1e-6, t_eval=np.linspace(0, 1, 37))
    compiled = sol.compiled
    assert isinstance(algebraic.affine_step(compiled), algebraic.AffineStep)
    Y, Z = _outputs(sol)[:2]
    P = np.asarray(compiled.parameter_values, dtype=float)[None]
    start = Z * (1 + 1e-4)
    with monkeypatch.context() as patch:
        patch.setattr(algebraic, "affine_step", lambda _: None)
        numpy_path = algebraic.algebraic_from_states(compiled, sol.t, Y, start, P)
    calls = _counting(monkeypatch, compiled)
    found = algebraic.algebraic_from_states(compiled, sol.t, Y, start, P)
    assert calls == []
    assert found.converged.all() and numpy_path.converged.all()
    np.testing.assert_allclose(found.z, numpy_path.z, rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(found.z, Z, rtol=1e-12, atol=1e-12)


def test_the_affine_step_against_the_pendulums_closed_form():
    """The pendulum's tension from its determining equation (index 2), in closed form at any state:
    ``y5 = (y3^2 + y4^2 - y2 lam / m) / (y1^2 + y2^2 / m)``; random states and parameters, a start far off."""
    compiled = PENDULUM.model().compile()
    rng = np.random.default_rng(7)
    K = 45
    Y = rng.normal(size=(1, K, 4))
    P = np.array([[1.7, 9.81]])  # (m, lam: the parameters' order)
    assert compiled.parameter_names == ("m", "lam")
    y1, y2, y3, y4 = Y[0].T
    m, lam = P[0]
    exact = (y3**2 + y4**2 - y2 * lam / m) / (y1**2 + y2**2 / m)
    found = algebraic.algebraic_from_states(compiled, np.linspace(0, 1, K), Y, np.full((1, K, 1), 1e3), P)
    assert algebraic.affine_step(compiled) is not None
    assert found.converged.all()
    np.testing.assert_allclose(found.z[0, :, 0], exact, rtol=1e-13, atol=1e-13)


def test_where_the_affine_step_does_not_settle_the_numpy_path_decides(monkeypatch):
    """A singular H_z (the pendulum at y1 = y2 = 0) and states that are not finite: the affine step's values
    there are not finite, and those outputs get what the numpy path's Newton gives them (not converged: the
    caller flags them); the others keep the step's values, equal to the numpy path's."""
    compiled = PENDULUM.model().compile()
    rng = np.random.default_rng(3)
    Y = rng.normal(size=(1, 9, 4))
    Y[0, 2, :2] = 0.0  # (H_z = y1^2 + y2^2 / m = 0)
    Y[0, 6, 3] = np.nan
    Z, P, times = np.ones((1, 9, 1)), np.array([[1.0, 9.81]]), np.linspace(0, 1, 9)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # (no warning from the non-finite values either)
        found = algebraic.algebraic_from_states(compiled, times, Y, Z, P)
    monkeypatch.setattr(algebraic, "affine_step", lambda _: None)
    numpy_path = algebraic.algebraic_from_states(compiled, times, Y, Z, P)
    np.testing.assert_array_equal(found.converged, numpy_path.converged)
    assert not found.converged[0, 2] and not found.converged[0, 6] and found.converged.sum() == 7
    np.testing.assert_allclose(found.z, numpy_path.z, rtol=1e-14, atol=0)


def test_determining_equations_not_affine_in_z_have_no_affine_step():
    """A circle whose z enters as ``z + z^3``: its determining equation ``z + z^3 = 2 + sin t`` is cubic in z, so
    there is no affine step (the numpy path's damped Newton solves it), and the values at the outputs solve it."""
    m = dm.Model("cubic")
    y1, y2 = m.states("y1 y2")
    (z,) = m.algebraics("z")
    rate = 2 + sp.sin(m.t) - z - z**3
    m.ode(y1, -y2 + rate * y1)
    m.ode(y2, y1 + rate * y2)
    m.constraint(y1**2 + y2**2 - 1, name="circle")
    m.initial(y1=1.0, y2=0.0)
    m.guess(z=1.0)
    sol = dm.solve(m.compile(), (0.0, 1.0), rtol=1e-8, atol=1e-8)
    assert sol.status == "success" and sol.stats["algebraic_resolved"]
    assert algebraic.affine_step(sol.compiled) is None
    np.testing.assert_allclose(sol["z"] + sol["z"] ** 3, 2 + np.sin(sol.t), rtol=1e-8)


def test_the_affine_step_is_made_in_the_setup(monkeypatch):
    """prepare (the solve's setup, before any method's clock) makes the affine step; solving at the outputs then
    makes nothing."""
    made = []
    make = algebraic._make_affine_step
    monkeypatch.setattr(algebraic, "_make_affine_step", lambda compiled: made.append(1) or make(compiled))
    compiled = PENDULUM.model().compile()
    algebraic.prepare(compiled)
    assert made == [1]
    sol = dm.solve(compiled, (0.0, 1.0), rtol=1e-6, atol=1e-6)
    assert sol.stats["algebraic_resolved"] and made == [1]


def test_the_affine_step_in_threads_at_once():
    """Each thread evaluates on its own buffers: four threads at once, each on its own states, get the values of
    one thread alone."""
    compiled = pendulum_chain(8).compile()
    sol = dm.solve(compiled, (0.0, 1.0), rtol=1e-6, atol=1e-6, t_eval=np.linspace(0, 1, 23))
    assert isinstance(algebraic.affine_step(compiled), algebraic.AffineStep)
    Y, Z, P = _outputs(sol)
    scales = [1.0 + 1e-5 * k for k in range(4)]
    alone = [algebraic.algebraic_from_states(compiled, sol.t, Y, Z * s, P).z for s in scales]
    results, barrier = {}, threading.Barrier(4)

    def work(k: int) -> None:
        barrier.wait()
        results[k] = [algebraic.algebraic_from_states(compiled, sol.t, Y, Z * scales[k], P).z for _ in range(50)]

    threads = [threading.Thread(target=work, args=(k,)) for k in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    for k in range(4):
        for z in results[k]:
            np.testing.assert_array_equal(z, alone[k])


def test_prepare_makes_no_numpy_code_where_the_affine_step_solves_if_asked():
    """``prepare(numpy=False)`` (radau's setup of each piece between events): the affine step, and no numpy code of
    the determining equations (~70 ms of printing a piece, which the numpy path needs only where the step does not
    settle); ``prepare()`` (solve()'s own model) makes both."""
    compiled = PENDULUM.model().compile()
    algebraic.prepare(compiled, numpy=False)
    assert algebraic.affine_step(compiled) is not None
    assert constraint_checks(compiled).H._numpy is None
    algebraic.prepare(compiled)
    assert constraint_checks(compiled).H._numpy is not None


def test_the_affine_step_reads_the_sign_of_det_h_z_as_the_branch_check():
    """The sign of det H_z at each output, read off the affine step's QR (Resolved.signs, which radau's branch check
    takes), against the branch check's own evaluation (H_z's nonzeros from the states, numpy's LU): equal at the 37
    outputs of a chain of 20 pendulums (H_z of 20 multipliers, 58 nonzeros) and at states off the solution; the
    pendulum's 1 x 1 H_z (a multiple of y1^2 + y2^2 / m): its sign, unknown (NaN) where it is 0 or not finite."""
    from daemodel.compiling.determinants import determinant_signs
    from daemodel.compiling.initial_states import branch_check_functions

    sol = dm.solve(pendulum_chain(20).compile(), (0.0, 1.0), rtol=1e-6, atol=1e-6, t_eval=np.linspace(0, 1, 37))
    compiled = sol.compiled
    Y, Z, P = _outputs(sol)
    rng = np.random.default_rng(5)
    for states in (Y, Y * (1 + 0.3 * rng.standard_normal(Y.shape))):
        found = algebraic.algebraic_from_states(compiled, sol.t, states, Z, P)
        at, to, entries = branch_check_functions(compiled)
        reference = determinant_signs(at, to, entries(sol.t, states[0], found.z[0], np.repeat(P, 37, axis=0)), 20)
        assert found.signs.shape == (1, 37) and set(np.unique(reference)) <= {-1.0, 1.0}
        np.testing.assert_array_equal(found.signs[0], reference)
    pendulum = PENDULUM.model().compile()
    Y = rng.normal(size=(1, 9, 4))
    Y[0, 2, :2] = 0.0  # (H_z = 0)
    Y[0, 5, 0] = np.nan  # (H_z not finite)
    Y[0, 6, 3] = np.nan  # (H not finite, H_z finite: its sign known)
    times, P = np.linspace(0, 1, 9), np.array([[1.0, 9.81]])
    found = algebraic.algebraic_from_states(pendulum, times, Y, np.ones((1, 9, 1)), P)
    at, to, entries = branch_check_functions(pendulum)
    (dH_dz,) = entries(times, Y[0], found.z[0], np.repeat(P, 9, axis=0)).T  # (1 x 1: y1^2 + y2^2 / m, times a constant)
    assert (np.abs(dH_dz[[0, 1, 3, 4, 6, 7, 8]]) > 0.01).all() and dH_dz[2] == 0 and np.isnan(dH_dz[5])
    np.testing.assert_array_equal(found.signs[0], np.where(np.isfinite(dH_dz) & (dH_dz != 0), np.sign(dH_dz), np.nan))


def _flip() -> dm.Model:
    """``x' = -1``, ``y' = x z``, ``0 = y + t - t^2 / 2`` (index 2): ``H = (1 - t) + x z``, so z = -1 and
    ``H_z = x = 1 - t``, whose sign changes at t = 1."""
    m = dm.Model("flip")
    x, y = m.states("x y")
    (z,) = m.algebraics("z")
    m.ode(x, -1)
    m.ode(y, x * z)
    m.constraint(y + m.t - m.t**2 / 2, name="g")
    m.initial(x=1.0, y=0.0)
    m.guess(z=-1.0)
    return m


def test_radaus_branch_check_reads_the_signs_of_its_solve_at_the_outputs(monkeypatch):
    """radau's branch check takes the signs its solve at the outputs read (no LU of H_z there: 97 of 1,400 us at
    rtol 1e-4 on a chain of 20 pendulums, 207 of 2,700 on 40), and still refuses a solution past a sign change of
    det H_z (the model of :func:`_flip`, past t = 1), as casadi-idas's check, which evaluates them, does."""
    from daemodel import errors as E
    from daemodel.compiling import initial_states

    counted, signs_of = [], initial_states.determinant_signs
    monkeypatch.setattr(initial_states, "determinant_signs", lambda *a: counted.append(1) or signs_of(*a))
    compiled = _flip().compile()
    sol = dm.solve(compiled, (0.0, 0.9), rtol=1e-6, atol=1e-6, t_eval=np.linspace(0, 0.9, 5))
    assert sol.status == "success" and counted == []
    np.testing.assert_allclose(sol["z"], -1.0, rtol=0, atol=1e-12)
    message = r"{}: the algebraic variables leave the branch of roots chosen at t0 between t = 0\.5 .* and t = 1 "
    with pytest.raises(E.BranchError, match=message.format("radau")):
        dm.solve(compiled, (0.0, 2.0), rtol=1e-6, atol=1e-6, t_eval=np.linspace(0, 2, 5))
    assert counted == []
    with pytest.raises(E.BranchError, match=message.format("casadi-idas")):
        dm.solve(compiled, (0.0, 2.0), method="casadi-idas", rtol=1e-6, atol=1e-6, t_eval=np.linspace(0, 2, 5))
    assert counted == [1]
    chain = dm.solve(pendulum_chain(5).compile(), (0.0, 1.0), rtol=1e-4, atol=1e-4)
    assert chain.status == "success" and counted == [1]


def test_the_sign_is_left_out_where_it_would_take_the_affine_step_past_its_bound(monkeypatch):
    """An affine step within AFFINE_MAX_INSTRUCTIONS without the sign and beyond it with: kept, without the sign
    (the branch check evaluates H_z), where before the sign cost the step itself (the numpy path then solved)."""
    signed = algebraic.affine_step(PENDULUM.model().compile())
    assert signed is not None and signed._parity is not None
    monkeypatch.setattr(algebraic, "AFFINE_MAX_INSTRUCTIONS", signed.instructions - 1)
    compiled = PENDULUM.model().compile()
    step = algebraic.affine_step(compiled)
    assert step is not None and step._parity is None and step.instructions < signed.instructions
    Y = np.random.default_rng(2).normal(size=(1, 5, 4))
    P = np.array([[1.0, 9.8]])
    found = algebraic.algebraic_from_states(compiled, np.linspace(0, 1, 5), Y, np.ones((1, 5, 1)), P)
    assert found.converged.all() and found.signs is None

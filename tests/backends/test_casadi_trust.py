"""casadi backends you can trust: IDAS solves valid models, failures are one line, and a
collocation step over a singularity is refused instead of returned."""

import re

import casadi
import numpy as np
import pytest
import scipy.linalg
import sympy as sp
from daemodel.backends.casadi.collocation import LOCAL_ERROR_BOUND, LocalErrorCheck, collocation_failure
from daemodel.backends.casadi.idas import IDAS_REASONS, idas_failure
from daemodel.backends.casadi.plumbing import first_non_finite

import daemodel as dm
from daemodel import errors as E
from daemodel.problems import HESSENBERG, PENDULUM

T = sp.Symbol("t")
# The RLC circuit: source sin t -> R -> node a -> L -> node b -> C -> ground.
R, L, C = 1.0, 0.5, 0.2


def max_error(sol, reference) -> float:
    return max(e["max"] for e in sol.errors(reference).values())


@pytest.fixture(scope="module")
def pendulum():
    return PENDULUM.model().compile()


def rlc_circuit() -> dm.Model:
    """States: inductor current i, capacitor voltage v; algebraic: node voltages va, vb (index 1)."""
    m = dm.Model("rlc")
    i, v = m.states("i v")
    va, vb = m.algebraics("va vb")
    m.ode(i, (va - vb) / L)
    m.ode(v, i / C)
    m.constraint((sp.sin(T) - va) / R - i, name="resistor")
    m.constraint(vb - v, name="capacitor")
    m.initial(i=0.0, v=0.0)
    return m


def rlc_exact(times):
    """x = (i, v) solves x' = A x + b sin t: x = e^{At} (x0 - a) + a cos t + A a sin t, (A^2 + I) a = -b."""
    A = np.array([[-R / L, -1 / L], [1 / C, 0.0]])
    a = -np.linalg.solve(A @ A + np.eye(2), np.array([1 / L, 0.0]))
    times = np.atleast_1d(np.asarray(times, dtype=float))
    x = np.stack([scipy.linalg.expm(A * t) @ -a for t in times]) + np.outer(np.cos(times), a)
    x += np.outer(np.sin(times), A @ a)
    return {"i": x[:, 0], "v": x[:, 1], "va": np.sin(times) - R * x[:, 0], "vb": x[:, 1]}


def tracking() -> dm.Model:
    """q' = z, 0 = q - sin t: index 2, q = sin t, z = cos t."""
    m = dm.Model("tracking")
    (q,) = m.states("q")
    (z,) = m.algebraics("z")
    m.ode(q, z)
    m.constraint(q - sp.sin(T), name="track")
    m.initial(q=0.0)
    return m


def random_dae(seed: int, index: int) -> dm.Model:
    """y' = A y + B z + small nonlinear and forcing terms; index 1: 0 = C y + D z + 0.1 z^3 - 0.3,
    index 2: 0 = C y - 0.2 sin t with C B invertible."""
    rng = np.random.default_rng(seed)
    n, k = int(rng.integers(2, 5)), 1
    m = dm.Model(f"random{index}_{seed}")
    ys = m.states(" ".join(f"y{j}" for j in range(n)))
    (z,) = m.algebraics("z")
    A, B = rng.normal(size=(n, n)) * 0.5, rng.normal(size=(n, k))
    for j in range(n):
        rhs = sum(A[j, i] * ys[i] for i in range(n)) + B[j, 0] * z
        m.ode(ys[j], rhs + 0.2 * sp.sin(ys[(j + 1) % n]) + 0.1 * sp.cos((j + 1) * T))
    Cm = rng.normal(size=(k, n))
    if index == 1:
        m.constraint(sum(Cm[0, i] * ys[i] for i in range(n)) + 3.5 * z + 0.1 * z**3 - 0.3, name="g")
    else:
        while abs((Cm @ B).item()) < 0.3:
            Cm = rng.normal(size=(k, n))
        m.constraint(sum(Cm[0, i] * ys[i] for i in range(n)) - 0.2 * sp.sin(T), name="g")
    y0 = rng.normal(size=n)
    if index == 2:
        y0 -= np.linalg.pinv(Cm) @ (Cm @ y0)
    m.initial(**{f"y{j}": float(y0[j]) for j in range(n)})
    return m


def singular_ode() -> dm.Model:
    """x' = -1, y' = 1/x: y = -log(1 - t) ends at t = 1."""
    m = dm.Model("singular")
    x, y = m.states("x y")
    m.ode(x, -1)
    m.ode(y, 1 / x)
    m.initial(x=1.0, y=0.0)
    return m


def singular_dae() -> dm.Model:
    """The same as an index-1 DAE, z = 1/x through 0 = x z - 1, whose g_z = x vanishes at t = 1."""
    m = dm.Model("singular_dae")
    x, y = m.states("x y")
    (z,) = m.algebraics("z")
    m.ode(x, -1)
    m.ode(y, z)
    m.constraint(x * z - 1, name="reciprocal")
    m.initial(x=1.0, y=0.0)
    return m


def without_line_search(monkeypatch):
    """casadi's Newton without its line search (casadi 3.8's default has one): it then converges
    to a wrong root of a step over the pole of singular_ode, as the issue observed."""
    real = casadi.integrator

    def integrator(*args):
        *head, options = args
        root = {**options.get("rootfinder_options", {}), "line_search": False}
        return real(*head, {**options, "rootfinder_options": root})

    monkeypatch.setattr(casadi, "integrator", integrator)


# ---- IDAS solves what radau and the reference solve -----------------------------------------


def test_idas_pendulum_at_11_output_times_matches_the_reference(pendulum):
    t_eval = np.linspace(0.0, 1.0, 11)
    sol = dm.solve(PENDULUM.model(), (0.0, 1.0), method="casadi-idas", t_eval=t_eval)
    ref = dm.solve(pendulum, (0.0, 1.0), method="reference", t_eval=t_eval)
    assert max_error(sol, ref) < 1e-7
    assert sol.stats["initial_slope_fallbacks"] == 0  # IDACalcIC found y'(t0)


def test_idas_first_step_is_not_sized_by_a_far_end_of_t_span(pendulum):
    """IDAS's first step was floored at 16 ulp of the farther end of t_span: on (0, 1e20) with outputs at
    0.5 and 1 it was 2.6e5, and the pendulum failed at t = 0 ("the error test failed repeatedly ... the
    problem may be singular there").  The first step is floored at t's resolution at t0, where it is taken."""
    t_eval = np.array([0.0, 0.5, 1.0])
    near = dm.solve(pendulum, (0.0, 1.0), method="casadi-idas", t_eval=t_eval)
    far = dm.solve(pendulum, (0.0, 1e20), method="casadi-idas", t_eval=t_eval)
    ref = dm.solve(pendulum, (0.0, 1.0), method="reference", t_eval=t_eval)
    assert far.status == "success"
    for name in pendulum.state_names:
        np.testing.assert_array_equal(far[name], near[name])
    assert max(far.errors(ref)[name]["max"] for name in pendulum.state_names) < 1e-6
    # the default outputs (the first at 1e198): the step limit, named, where the first step was 1e183 (16 ulp
    # of 1e200) and the pendulum's evaluation failed at t = 0 ("it leaves its domain there")
    with pytest.raises(E.StepLimitError, match=r"max_num_steps = 100,000 steps ended at t = \d+"):
        dm.solve(pendulum, (0.0, 1e200), method="casadi-idas")


def test_idas_pendulum_at_rtol_1e_10(pendulum):
    t_eval = np.linspace(0.0, 1.0, 11)
    sol = dm.solve(pendulum, (0.0, 1.0), method="casadi-idas", rtol=1e-10, atol=1e-12, t_eval=t_eval)
    ref = dm.solve(pendulum, (0.0, 1.0), method="reference", t_eval=t_eval)
    assert max_error(sol, ref) < 1e-8


@pytest.mark.parametrize("rtol", [1e-8, 1e-10])
def test_idas_rlc_circuit_against_the_exact_solution(rtol):
    """z moves at t0 (va' = cos 0 - R i' = 1): IDAS could not start here with z in its error test."""
    sol = dm.solve(rlc_circuit(), (0.0, 1.0), method="casadi-idas", rtol=rtol, atol=rtol / 100)
    assert set(sol.names) == {"i", "v", "va", "vb"}
    assert max_error(sol, rlc_exact) < 100 * rtol


def test_collocation_rlc_circuit_against_the_exact_solution():
    sol = dm.solve(rlc_circuit(), (0.0, 1.0), method="casadi-collocation", stages=3, h=0.05)
    assert max_error(sol, rlc_exact) < 1e-8
    assert 0 < sol.stats["max_local_error_estimate"] < 1e-8


@pytest.mark.parametrize("options", [{"t_eval": np.linspace(0, 1, 11)}, {"rtol": 1e-10, "atol": 1e-12}])
def test_idas_index2_tracking_is_reduced_and_solved(options):
    sol = dm.solve(tracking(), (0.0, 1.0), method="casadi-idas", **options)
    assert sol.compiled.index == 1  # solve() handed IDAS the index-1 reduction
    exact = {"q": np.sin(sol.t), "z": np.cos(sol.t)}
    assert max_error(sol, lambda t: {"q": np.sin(t), "z": np.cos(t)}) < 1e-6
    np.testing.assert_allclose(sol["q"], exact["q"], atol=1e-7)


@pytest.mark.parametrize("index", [1, 2])
@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_idas_small_random_daes_match_the_reference(seed, index):
    model = random_dae(seed, index).compile()
    assert model.index == index
    t_eval = np.linspace(0.0, 1.0, 11)
    ref = dm.solve(model, (0.0, 1.0), method="reference", t_eval=t_eval)
    for rtol in (1e-8, 1e-10):
        sol = dm.solve(model, (0.0, 1.0), method="casadi-idas", rtol=rtol, atol=rtol / 100, t_eval=t_eval)
        scale = 1 + max(np.max(np.abs(ref[n])) for n in ref.names)
        assert max_error(sol, ref) < 1e3 * rtol * scale


def test_idas_batch_of_initial_states_each_gets_its_own_slope(pendulum):
    """One integrator for the batch: IDACalcIC computes y'(t0) per sample inside the call."""
    angles, speeds = np.array([0.3, 1.2, 2.5]), np.array([0.0, 0.5, -1.0])
    y0 = {"y1": np.sin(angles), "y2": -np.cos(angles), "y3": speeds * np.cos(angles), "y4": speeds * np.sin(angles)}
    t_eval = np.linspace(0.0, 1.0, 11)
    batch = dm.solve(pendulum, (0.0, 1.0), method="casadi-idas", y0=y0, t_eval=t_eval)
    assert batch["y5"].shape == (3, 11) and batch.stats["initial_slope_fallbacks"] == 0
    for k in range(3):
        one = {name: values[k : k + 1] for name, values in y0.items()}
        single = dm.solve(pendulum, (0.0, 1.0), method="casadi-idas", y0=one, t_eval=t_eval)
        ref = dm.solve(pendulum, (0.0, 1.0), method="reference", y0=one, t_eval=t_eval)
        for name in batch.names:  # the batch shares IDAS's first step (the shortest any sample needs)
            np.testing.assert_allclose(batch[name][k], single[name][0], atol=1e-7)
            np.testing.assert_allclose(batch[name][k], ref[name][0], atol=1e-6)


def test_idas_falls_back_to_the_exact_slope_where_idacalcic_fails(monkeypatch):
    """w = log y with w(0) = 0: IDACalcIC's line search fails at atol = 1e-10 where its own step is 0.001 of the
    last output (casadi's first_time left as it is); y'(t0) = f(t0, y0, z0) works.  With its step a share of
    IDAS's first one (plumbing.consistent_start) it does not fail."""
    from daemodel.backends.casadi import idas

    m = dm.Model("logarithm")
    (y,) = m.states("y")
    (w,) = m.algebraics("w")
    m.ode(y, -1)
    m.constraint(w - sp.log(y), name="log")
    m.initial(y=1.0)
    sol = dm.solve(m, (0.0, 0.9), method="casadi-idas")
    assert sol.stats["initial_slope_fallbacks"] == 0
    np.testing.assert_allclose(sol["w"], np.log(1 - sol.t), atol=1e-7)
    monkeypatch.setattr(idas, "consistent_start", lambda first_output, step0: {"calc_ic": True})
    sol = dm.solve(m, (0.0, 0.9), method="casadi-idas")
    assert sol.stats["initial_slope_fallbacks"] == 1
    np.testing.assert_allclose(sol["w"], np.log(1 - sol.t), atol=1e-7)


# ---- IDAS failures: one line, the reason, the time, the fix ----------------------------------


def test_idas_too_much_work_is_a_step_limit_error(pendulum, capfd):
    with pytest.raises(
        E.StepLimitError,
        match=r"casadi-idas: max_num_steps = 5 steps ended at t = \S+, before the output time t = 0\.1 "
        r"\(sample 0 of 'pendulum'\); raise max_num_steps \(the limit per output interval\) or loosen rtol/atol",
    ) as caught:
        dm.solve(pendulum, (0.0, 1.0), method="casadi-idas", max_num_steps=5, t_eval=np.linspace(0, 1, 11))
    assert "\n" not in str(caught.value)
    out, err = capfd.readouterr()
    assert out == "" and err == ""


def test_idas_stopping_at_a_pole_names_the_output_time():
    with pytest.raises(
        E.StepLimitError,
        match=r"max_num_steps = 300 steps ended (just before|at t = 0\.99\d*, before) the output time t = 1 "
        r"\(sample 0 of 'singular'\).* if the solution is singular there, shorten t_span",
    ):
        dm.solve(singular_ode(), (0.0, 2.0), method="casadi-idas", max_num_steps=300)


def test_idas_failure_is_one_line_without_casadi_output(capfd):
    """g_z = x vanishes at t = 1: IDAS's Newton fails there; before, casadi printed its own text."""
    with pytest.raises(
        E.ConvergenceError,
        match=r"^casadi-idas: the Newton iteration failed repeatedly at t = 1 with step size \S+ "
        r"\(sample 0 of 'singular_dae', IDA_CONV_FAIL\); the constraints may stop determining the "
        r"algebraic variables there \(g_z singular\)",
    ) as caught:
        dm.solve(singular_dae(), (0.0, 2.0), method="casadi-idas")
    assert "\n" not in str(caught.value)
    out, err = capfd.readouterr()
    assert out == "" and err == ""


def test_idas_domain_error_names_the_time():
    m = dm.Model("logarithm")
    (y,) = m.states("y")
    (w,) = m.algebraics("w")
    m.ode(y, -1)
    m.constraint(w - sp.log(y), name="log")
    m.initial(y=1.0)
    with pytest.raises(
        E.ConvergenceError,
        match=r"casadi-idas: the model's evaluation failed repeatedly at t = 1 .*IDA_REP_RES_ERR\); it leaves "
        r"its domain there",
    ):
        dm.solve(m, (0.0, 2.0), method="casadi-idas")


def test_idas_tolerances_are_checked(pendulum):
    with pytest.raises(E.InvalidOptionError, match=r"rtol = 1e-15 is outside the meaningful range \[1e-14, 0\.1\]"):
        dm.solve(pendulum, (0.0, 1.0), method="casadi-idas", rtol=1e-15)
    with pytest.raises(E.InvalidOptionError, match="max_num_steps must be a finite integer"):
        dm.solve(pendulum, (0.0, 1.0), method="casadi-idas", max_num_steps=10.5)


# ---- casadi-collocation: every step checked ---------------------------------------------------


def test_collocation_estimate_is_small_on_smooth_problems():
    """Pendulum and Hessenberg, s = 1..5, h = 0.1..0.0125: far below the bound (measured <= 0.034)."""
    worst = 0.0
    for problem in (PENDULUM, HESSENBERG):
        model = problem.model().compile()
        for s in (1, 2, 3, 4, 5):
            for h in (0.1, 0.05, 0.025, 0.0125):
                sol = dm.solve(model, (0.0, 1.0), method="casadi-collocation", stages=s, h=h)
                worst = max(worst, sol.stats["max_local_error_estimate"])
    assert worst < LOCAL_ERROR_BOUND / 2


@pytest.mark.parametrize("s", [1, 2, 3])
def test_collocation_estimate_is_the_true_local_error(s):
    """One step from the exact start: the estimate (in units of 1 + max|u|, y5 over h) is the error."""
    model = HESSENBERG.model().compile()
    exact = HESSENBERG.exact_solution()
    for h in (0.1, 0.05):
        sol = dm.solve(model, (0.0, h), method="casadi-collocation", stages=s, h=h)
        truth = exact(sol.t)
        errors = [
            abs(sol[n][-1] - truth[n][-1]) * (h if n == "y5" else 1.0) / (1 + np.max(np.abs(sol[n]))) for n in sol.names
        ]
        assert sol.stats["max_local_error_estimate"] == pytest.approx(max(errors), rel=0.1)


def test_collocation_singular_dae_wrong_root_raises_local_error_bound(capfd):
    """casadi's Newton crosses g_z = 0 (x z = 1 has no pole in the residual) and lands on a finite,
    wrong root; before, y(2) = 1.005 came back as the answer."""
    with pytest.raises(
        E.LocalErrorBoundError,
        match=r"^casadi-collocation: step 34 from t = 0\.99 to 1\.02 \(h = 0\.03\) of sample 0 of 'singular_dae' "
        r"is not trustworthy: the local error estimate of 'y' is \S+ times its scale 1 \+ max\|y\|, beyond "
        r"LOCAL_ERROR_BOUND = 0\.1 .*the solution may be singular there; take a smaller h, or an adaptive "
        r"method \(method=\"radau\" with rtol=\.\.\., or method=\"casadi-idas\"\)$",
    ) as caught:
        dm.solve(singular_dae(), (0.0, 2.0), method="casadi-collocation", stages=3, h=0.03)
    assert "\n" not in str(caught.value)
    out, err = capfd.readouterr()
    assert out == "" and err == ""


def test_collocation_singular_ode_newton_failure_is_one_line(capfd):
    """casadi 3.8's Newton (with line search) cannot cross the pole of 1/x: a failure, not a dump."""
    with pytest.raises(
        E.ConvergenceError,
        match=r"^casadi-collocation: casadi's Newton iteration did not solve the collocation equations of step 34 "
        r"from t = 0\.99 to 1\.02 \(h = 0\.03\) for sample 0 of 'singular'; the solution may be singular there; "
        r"take a smaller h",
    ) as caught:
        dm.solve(singular_ode(), (0.0, 2.0), method="casadi-collocation", stages=3, h=0.03)
    assert "\n" not in str(caught.value)
    out, err = capfd.readouterr()
    assert out == "" and err == ""


def test_collocation_singular_ode_wrong_root_is_caught(monkeypatch):
    """The issue's case: a Newton without line search returns y(2) = 1.005 at s = 3, h = 0.03."""
    without_line_search(monkeypatch)
    with pytest.raises(
        E.LocalErrorBoundError, match=r"step 34 from t = 0\.99 to 1\.02 .* of 'singular' is not trustworthy: .* of 'y'"
    ):
        dm.solve(singular_ode(), (0.0, 2.0), method="casadi-collocation", stages=3, h=0.03)


@pytest.mark.parametrize("line_search", [True, False])
@pytest.mark.parametrize("model", [singular_ode, singular_dae])
def test_collocation_never_returns_a_solution_across_the_pole(model, line_search, monkeypatch):
    """Stages 1..4 x 4 step sizes over (0, 2): every setting raises (before: up to 16 of 32 returned)."""
    if not line_search:
        without_line_search(monkeypatch)
    compiled = model().compile()
    for s in (1, 2, 3, 4):
        for h in (0.3, 0.15, 0.07, 0.03):
            with pytest.raises(E.SolverError, match=r"t = (0\.\d+|1\.\d+|1)\b.*sample 0"):
                dm.solve(compiled, (0.0, 2.0), method="casadi-collocation", stages=s, h=h)


def test_collocation_non_finite_values_name_the_variable_and_time(monkeypatch):
    without_line_search(monkeypatch)
    with pytest.raises(
        E.ConvergenceError,
        match=r"casadi-collocation: 'x' is not finite at t = 1\.2 \(sample 0 of 'singular', after t = 1\): the "
        r"solution may be singular there or leave the domain of the equations; take a smaller h",
    ):
        dm.solve(singular_ode(), (0.0, 2.0), method="casadi-collocation", stages=2, h=0.2)


def test_collocation_batch_reports_the_failing_sample():
    """Two samples; only the second one's solution reaches the pole inside (0, 1)."""
    m = singular_dae()
    with pytest.raises(E.LocalErrorBoundError, match=r"step \d+ from t = 0\.4.* of sample 1 of 'singular_dae'"):
        dm.solve(m, (0.0, 1.0), method="casadi-collocation", stages=3, h=0.03, y0={"x": [2.0, 0.5], "y": [0.0, 0.0]})


# ---- every message, from casadi's own text ----------------------------------------------------

IDAS_SAID = "At t = 0.25 and h = 1e-09, the error test failed repeatedly or with |h| = hmin.\n"


def casadi_error(function: str, code: str) -> str:
    return (
        "Error in Function::call for 'idas' [IdasInterface] at .../casadi/core/function.cpp:1655:\n"
        f'.../casadi/interfaces/sundials/idas_interface.cpp:620: {function} returned "{code}". '
        "Consult IDAS documentation."
    )


def test_idas_error_test_failure_message():
    error = idas_failure(
        casadi_error("IDASolve", "IDA_ERR_FAIL"), IDAS_SAID, sample=2, model="m", grid=[1.0], max_num_steps=9
    )
    assert isinstance(error, E.ConvergenceError)
    assert str(error) == (
        "casadi-idas: the error test failed repeatedly at t = 0.25 with step size 1e-09 (sample 2 of 'm', "
        "IDA_ERR_FAIL); the problem may be singular there or need a smaller atol"
    )


@pytest.mark.parametrize("code", sorted(IDAS_REASONS))
def test_every_idas_flag_becomes_one_line_with_its_fix(code):
    _, fix = IDAS_REASONS[code]
    error = idas_failure(casadi_error("IDASolve", code), IDAS_SAID, sample=0, model="m", grid=[1.0], max_num_steps=9)
    with pytest.raises(
        E.ConvergenceError, match=rf"^casadi-idas: .* at t = 0\.25 .*\(sample 0 of 'm', {code}\); {re.escape(fix)}$"
    ):
        raise error


def test_idas_failure_names_the_time_since_t0_plus_t0():
    """IDAS integrates on the time since t0 (plumbing.shifted_dae): the time it prints is read back as t0 + s.
    y' = y^2 from y = 1 at t0 = 1000 blows up at 1001."""
    m = dm.Model("blow")
    m.states("y")
    m.ode("y", "y**2")
    m.initial(t=1000.0, y=1.0)
    with pytest.raises(E.StepLimitError, match=r"ended just before the output time t = 1001 \(sample 0") as caught:
        dm.solve(m, (1000.0, 1002.0), method="casadi-idas")
    assert abs(caught.value.t - 1001.0) < 1e-3


def test_idas_unknown_flag_and_budget_without_a_time():
    unknown = idas_failure(
        casadi_error("IDASolve", "IDA_MEM_FAIL"), "out of memory\n", sample=1, model="m", grid=[1.0], max_num_steps=9
    )
    with pytest.raises(
        E.ConvergenceError, match=r"^casadi-idas: IDASolve failed \(sample 1 of 'm', IDA_MEM_FAIL\): out of memory$"
    ):
        raise unknown
    budget = idas_failure(
        casadi_error("IDASolve", "IDA_TOO_MUCH_WORK"), "", sample=0, model="m", grid=[1.0], max_num_steps=9
    )
    with pytest.raises(
        E.StepLimitError, match=r"^casadi-idas: max_num_steps = 9 steps did not reach the next output time \(sample 0"
    ):
        raise budget


def test_collocation_failure_without_a_dump_quotes_casadi():
    error = collocation_failure(
        "Error in Function::call\n.../casadi/core/oracle_function.cpp:370: NaN detected",
        "",
        sample=3,
        model="m",
        grid=[0.0, 1.0],
    )
    with pytest.raises(
        E.ConvergenceError,
        match=r"^casadi-collocation: casadi failed for sample 3 of 'm': Error in Function::call \| .*NaN detected; "
        r"take a smaller h",
    ):
        raise error


def test_idas_non_finite_value_message(pendulum):
    values = np.zeros((2, 3, 5))
    values[1, 2, 4] = np.inf
    error = first_non_finite(
        "casadi-idas", pendulum, np.array([0.0, 0.5, 1.0]), values, "tighten rtol/atol or shorten t_span"
    )
    with pytest.raises(
        E.ConvergenceError,
        match=r"^casadi-idas: 'y5' is not finite at t = 1 \(sample 1 of 'pendulum', after t = 0\.5\): .*; "
        r"tighten rtol/atol",
    ):
        raise error


def test_local_error_bound_names_an_index2_algebraic_variable_with_its_weight(pendulum):
    """y5 is determined through the index-2 constraint: its estimate is weighted by h (as in RADAU5)."""
    check = LocalErrorCheck(pendulum, 3)
    grid = np.linspace(0.0, 0.2, 5)
    estimates = np.zeros((1, 4, 5))
    estimates[0, 2, 4] = 0.5
    with pytest.raises(
        E.LocalErrorBoundError,
        match=r"^casadi-collocation: step 3 from t = 0\.1 to 0\.15 \(h = 0\.05\) of sample 0 of 'pendulum' is not "
        r"trustworthy: the local error estimate of 'y5' is 0\.5 times its scale 1 \+ max\|y5\| over h\^1, beyond",
    ):
        check.raise_beyond_bound("casadi-collocation", grid, estimates)


def test_collocation_that_leaves_the_domain_of_f_is_caught():
    # sqrt(x) with x < 0 after t = 2: casadi's root finder returns its last iterate (x stuck at 0)
    m = dm.Model("sqrt")
    m.states("x y")
    m.ode("x", "-0.5")
    m.ode("y", "sqrt(x)")
    m.initial(x=1.0, y=0.0)
    with pytest.raises(
        E.ConvergenceError,
        match=r"casadi-collocation: the right-hand side of y' is not finite at the returned values at t = 2 "
        r"\(sample 0 of 'sqrt'",
    ):
        dm.solve(m, (0.0, 4.0), method="casadi-collocation", h=0.05)
    sol = dm.solve(m, (0.0, 1.9), method="casadi-collocation", h=0.05)  # before it: fine
    np.testing.assert_allclose(sol["y"][-1], (2 - 2 * (1 - 0.95) ** 1.5) / 1.5 * 1.0, rtol=1e-6)


def test_collocation_accepts_a_start_at_rest_to_rounding_and_refuses_an_inconsistent_one():
    """A step that returns its start value because its whole change h |f| is rounding (x' = 1e-14,
    or x' = w - 0.3 with w = 0.1 x + 0.2 = 0.30000000000000004 at x = 1) is steady, not stuck: the
    root finder accepts its start guess.  A start that violates a constraint beyond rounding is
    still refused by name (the stuck step itself: the Akzo Nobel test below)."""
    drift = dm.Model("drift")
    (x,) = drift.states("x")
    drift.ode(x, 1e-14 + 0 * x)
    drift.initial(x=1.0)
    sol = dm.solve(drift, (0.0, 1.0), method="casadi-collocation", h=0.1)
    assert sol.status == "success"
    np.testing.assert_allclose(sol["x"], 1.0 + 1e-14 * sol.t, rtol=0, atol=1e-13)  # exact: 1 + 1e-14 t

    rest = dm.Model("rest")
    (x,) = rest.states("x")
    (w,) = rest.algebraics("w")
    rest.ode(x, w - 0.3)
    rest.constraint(w - 0.1 * x - 0.2, name="tie")
    rest.initial(x=1.0)
    sol = dm.solve(rest, (0.0, 1.0), method="casadi-collocation", h=0.1)
    assert sol.status == "success"
    # exact: x' = 0.1 (x - 1) from x = 1 is x = 1 (w = 0.3), up to the start's rounding
    np.testing.assert_allclose(sol["x"], 1.0, rtol=0, atol=1e-15)
    np.testing.assert_allclose(sol["w"], 0.3, rtol=0, atol=1e-15)

    held = dm.Model("held")
    (x,) = held.states("x")
    (lam,) = held.algebraics("lam")
    held.ode(x, lam)
    held.constraint(x - 0.3, name="hold")
    held.initial(x=0.1 + 0.2)  # 0.30000000000000004: on the constraint to rounding
    sol = dm.solve(held, (0.0, 1.0), method="casadi-collocation", h=0.1)
    assert sol.status == "success" and np.all(sol["x"] == 0.1 + 0.2) and np.all(sol["lam"] == 0.0)
    held.initial(x=0.3 + 1e-6)
    with pytest.raises(E.InconsistentInitialStateError, match=r"violates constraint 'hold' \(#2\): hold = 1e-06"):
        dm.solve(held, (0.0, 1.0), method="casadi-collocation", h=0.1)


def test_collocation_that_returns_its_start_value_is_refused():
    """On the Akzo Nobel chemistry at h = 2.25, casadi's Newton meets sqrt of a negative y2 inside
    a step and returns the step's start value, then every later one: finite values 0.29 off, which
    the s + 1 check cannot see (both solves are stuck alike).  daemodel names the step instead."""
    from daemodel.problems import AKZO_NOBEL

    c = AKZO_NOBEL.model().compile()
    with pytest.raises(
        dm.errors.ConvergenceError,
        match=r"step 2 from t = 2\.25 \(h = 2\.25\) of sample 0 of 'akzo-nobel' returned its start value although f",
    ):
        dm.solve(c, AKZO_NOBEL.t_span, method="casadi-collocation", h=2.25)
    sol = dm.solve(c, AKZO_NOBEL.t_span, method="casadi-collocation", h=18.0)  # long steps that do converge
    assert abs(sol["y1"][-1] - AKZO_NOBEL.reference["y1"]) < 1e-4


def test_collocation_whose_root_finder_accepts_its_start_value_at_every_stage_is_not_stuck():
    """x' = 2 (t - h) from x = 0 over one step h = 7.4e-7: h |f| is 1.1e-12 at the step's start, above the root
    finder's abstol (1e-12), but its stage increments h A f are 0.5e-12 at most (f falls to 0 at the end): the
    root finder stops at the start value, 5.5e-13 off the exact -h^2.  The guard read f at the start alone and
    named the step stuck, "casadi's Newton iteration gave up (f or g likely turned NaN)" (after an event, as
    x = (t - c)^2 - 1.1e-12 at a crossing: the solve refused)."""
    h = 7.4e-7
    m = dm.Model("slow_end")
    m.states("x")
    m.ode("x", f"2*(t - {h!r})")
    m.initial(x=0.0)
    sol = dm.solve(m, (0.0, h), method="casadi-collocation", h=h, stages=3)
    assert sol.status == "success" and abs(sol["x"][-1] + h * h) <= 1e-12


def test_idas_initial_slopes_are_exact_sparse_and_made_once(monkeypatch):
    """z'(t0) = -g_z^-1 (g_t + g_y f) by a sparse LU, its function made once per model (at 4,000
    unknowns its dense g_z and the function's rebuild took 2.2 s of every call's setup)."""
    from daemodel.backends.casadi import idas
    from daemodel.backends.casadi.plumbing import dae_of

    from daemodel.compiling.initial_states import InitialStates

    m = dm.Model("split")
    y, z1, z2 = m.states("y") + m.algebraics("z1 z2")
    m.ode(y, -y)
    m.constraint(z1 + z2 - y)
    m.constraint(z1 - z2 - m.t)  # z1 = (y + t) / 2, z2 = (y - t) / 2
    m.initial(y=2.0, z1=1.0, z2=1.0)
    compiled = m.compile()
    built = []
    monkeypatch.setattr(idas, "slopes_function", lambda dae, make=idas.slopes_function: built.append(1) or make(dae))
    start = InitialStates(
        y0=np.array([[2.0], [4.0]]), z0=np.array([[1.0, 1.0], [2.0, 2.0]]), p=np.zeros((2, 0)), batched=True
    )
    for _ in range(2):
        ydot, zdot = idas.initial_slopes(compiled, dae_of(compiled), 0.0, start)
        np.testing.assert_allclose(ydot, [[-2.0], [-4.0]], rtol=1e-15)
        np.testing.assert_allclose(zdot, [[-0.5, -1.5], [-1.5, -2.5]], rtol=1e-15)  # ((y' + 1) / 2, (y' - 1) / 2)
    assert len(built) == 1
    sol = dm.solve(compiled, (0.0, 1.0), method="casadi-idas", rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(sol["z1"], (2 * np.exp(-sol.t) + sol.t) / 2, atol=1e-8)

    singular = dm.Model("fold")
    (x, w) = singular.states("x") + singular.algebraics("w")
    singular.ode(x, 1 + 0 * x)
    singular.constraint(w**2 - x)  # g_z = 2 w = 0 at w = 0: no slope
    singular.initial(x=1.0, w=1.0)  # (compiles where g_z = 2; the fold is at w = 0)
    folded = singular.compile()
    at_fold = InitialStates(y0=np.zeros((1, 1)), z0=np.zeros((1, 1)), p=np.zeros((1, 0)), batched=False)
    ydot, zdot = idas.initial_slopes(folded, dae_of(folded), 0.0, at_fold)
    assert ydot[0, 0] == 1.0 and np.isnan(zdot[0, 0])


@pytest.mark.parametrize("seed", range(4))
def test_idas_initial_slopes_match_finite_differences_of_the_constraints(seed):
    """Random sparse index-1 models with a parameter, a batch of samples: z'(t0) from the sparse LU and
    the directional derivative equals -g_z^-1 (g_t + g_y f) with g_z, g_y, g_t by central differences
    of the constraints written here in numpy (an independent reference)."""
    import sympy as sp
    from daemodel.backends.casadi import idas
    from daemodel.backends.casadi.plumbing import dae_of

    from daemodel.compiling.initial_states import InitialStates

    rng = np.random.default_rng(seed)
    n, m = 3, 5
    A, Bz, C = rng.normal(size=(n, n)), rng.normal(size=(n, m)), rng.normal(size=(m, n))
    G = np.where(rng.random((m, m)) < 0.3, rng.normal(size=(m, m)), 0.0) + 4 * np.eye(m)
    model = dm.Model(f"random{seed}")
    ys, zs = model.states(" ".join(f"y{i}" for i in range(n))), model.algebraics(" ".join(f"z{i}" for i in range(m)))
    k = model.parameter("k", 0.7)
    for i in range(n):
        model.ode(
            ys[i],
            sum(A[i, j] * ys[j] for j in range(n)) + sum(Bz[i, j] * zs[j] for j in range(m)) + sp.sin(k * model.t),
        )
    for i in range(m):
        linear = sum(C[i, j] * ys[j] for j in range(n)) + sum(G[i, j] * zs[j] for j in range(m) if G[i, j])
        model.constraint(linear + 0.1 * zs[i] ** 2 + k * model.t * (i + 1) + 0.2 * sp.sin(ys[i % n]) * zs[i])
    model.initial(**{f"y{i}": 0.1 * (i + 1) for i in range(n)})
    model.guess(**{f"z{i}": 0.0 for i in range(m)})
    compiled = model.compile()

    def f(t, y, z, p):
        return A @ y + Bz @ z + np.sin(p * t)

    def g(t, y, z, p):
        return C @ y + G @ z + 0.1 * z**2 + p * t * np.arange(1, m + 1) + 0.2 * np.sin(y[np.arange(m) % n]) * z

    def derivative(fun, x, eps=1e-6):  # (central differences, one column per unknown)
        return np.stack([(fun(x + eps * e) - fun(x - eps * e)) / (2 * eps) for e in np.eye(x.size)], axis=-1)

    B, t0 = 3, 0.4
    y0, z0, p = rng.normal(size=(B, n)), 0.3 * rng.normal(size=(B, m)), rng.uniform(0.5, 2, size=(B, 1))
    start = InitialStates(y0=y0, z0=z0, p=p, batched=True)
    ydot, zdot = idas.initial_slopes(compiled, dae_of(compiled), t0, start)
    for b in range(B):
        y, z, k_ = y0[b], z0[b], p[b, 0]
        slope = f(t0, y, z, k_)
        g_z = derivative(lambda v, y=y, k_=k_: g(t0, y, v, k_), z)
        g_y = derivative(lambda v, z=z, k_=k_: g(t0, v, z, k_), y)
        g_t = derivative(lambda v, y=y, z=z, k_=k_: g(v[0], y, z, k_), np.array([t0]))[:, 0]
        np.testing.assert_allclose(ydot[b], slope, rtol=1e-13, atol=1e-13)
        np.testing.assert_allclose(zdot[b], -np.linalg.solve(g_z, g_t + g_y @ slope), rtol=1e-7, atol=1e-8)


def test_a_time_limit_that_strikes_inside_idas_is_a_time_limit_error_not_idas_failure():
    """casadi reports an exception raised while IDAS runs (the limit's signal) as the call's own failure
    (IDA_RES_FAIL): that was a ConvergenceError saying the model leaves its domain, which an ensemble
    chunk took for failing samples and bisected.  IDAS needs seconds for the transistor amplifier at
    rtol 1e-9: the limit strikes inside it."""
    import time

    from daemodel.executors import time_limit
    from daemodel.problems import TRANSISTOR_AMPLIFIER

    compiled = TRANSISTOR_AMPLIFIER.model().compile()
    began = time.perf_counter()
    with pytest.raises(E.TimeLimitError, match="stop here"), time_limit(0.5, "stop here"):
        dm.solve(compiled, TRANSISTOR_AMPLIFIER.t_span, method="casadi-idas", rtol=1e-9, atol=1e-9)
    assert time.perf_counter() - began < 3


@pytest.mark.parametrize("t0", [0.5, 1e3])
def test_idas_moves_over_a_span_shorter_than_casadis_own_threshold(t0):
    # casadi's IDAS took no step towards an output within about 1e-9 of its start (x came back unchanged), so the
    # trial solves that located a crossing from an output on it saw nothing move and settled 1e-7 late
    m = dm.Model("line")
    m.states("x")
    m.ode("x", "1")
    m.initial(t=t0, x=t0)
    for span in (1e-12 * t0, 1e-9, 1e-7):
        sol = dm.solve(m, (t0, t0 + span), method="casadi-idas", t_eval=[t0, t0 + span])
        assert sol.status == "success" and abs((sol["x"][-1] - t0) - span) < 1e-3 * span + 4e-16 * t0, span


def test_idas_keeps_the_integrators_of_a_short_and_a_long_span_apart():
    """A span under SHORT_SPAN runs on normalised time (two more parameters), a longer one on the time since t0
    (one more): with the same relative outputs and settings both had one key among the kept integrators, and the
    second solve of the model raised ConvergenceError (IDAS handed parameters of the other length)."""
    m = dm.Model("decay")
    m.states("x")
    m.parameter("k", 2.0)
    m.ode("x", "-k*x + t")
    m.initial(x=1.0)
    compiled = m.compile()
    for span in (1.0, 1e-9, 1.0):
        sol = dm.solve(compiled, (0.0, span), method="casadi-idas", t_eval=np.linspace(0.0, span, 5), rtol=1e-10)
        exact = 1.25 * np.exp(-2 * span) + span / 2 - 0.25
        assert sol.status == "success" and abs(sol["x"][-1] - exact) < 1e-8 * span + 1e-15, span


def test_collocations_dense_output_solver_is_made_in_the_setup(monkeypatch):
    """Issue 42: every one-off code generation is setup.  The stage solver of casadi-collocation's dense
    output was made on the solve's clock (a chain of 20 pendulums' first solve: 198 ms of CPU against
    183 ms for the next); measured by slowing its making down by a known 0.3 s."""
    import time

    from daemodel.backends.casadi import collocation

    made = collocation.CollocationStages.__init__

    def slow(self, *args):
        time.sleep(0.3)
        made(self, *args)

    monkeypatch.setattr(collocation.CollocationStages, "__init__", slow)
    sol = dm.solve(HESSENBERG.model().compile(), (0.0, 1.0), method="casadi-collocation", h=0.05)
    assert sol.setup_time >= 0.3 and sol.solve_time < 0.3, sol

"""radau's compiled run: many attempts of the RADAU5 controller in one casadi call (backends/radau/loop.py).

The run must take the steps the controller takes one attempt at a time, bit for bit (the same
arithmetic in the same order), hand back to Python what only Python does (retries past the
compiled ones, errors), and stop where the controller checks its budget.
"""

import numpy as np
import pytest
from daemodel.backends.radau import casadi_engine, loop, sequence
from daemodel.backends.radau.casadi_engine import CasadiEngine
from daemodel.backends.radau.compiled import Buffered, find_compiler

import daemodel as dm
from daemodel import errors as E
from daemodel.problems import HESSENBERG, PENDULUM, PROBLEMS

COUNTS = (
    "steps", "attempts", "rejected_steps", "newton_failures", "newton_iterations", "max_newton_iterations",
    "jacobian_evaluations", "lu_decompositions", "residual_evaluations", "compiled_retries", "h_min", "h_max",
)  # fmt: skip


def _with_and_without_run(monkeypatch, model, t_span, **options):
    """The solve with the compiled run, and with the compiled attempt alone (one attempt per call)."""
    run = dm.solve(model, t_span, **options)
    monkeypatch.setattr(CasadiEngine, "make_compiled_run", lambda self, iterations: None)
    single = dm.solve(model, t_span, **options)
    monkeypatch.undo()
    return run, single


@pytest.mark.parametrize(
    ("problem", "span", "rtol"),
    [
        (PENDULUM, (0.0, 1.0), 1e-6),
        (PENDULUM, (0.0, 3.0), 1e-9),
        (HESSENBERG, None, 1e-6),
        (PROBLEMS["akzo-nobel"], None, 1e-8),  # Newton failures, inside the run
        (PROBLEMS["akzo-nobel"], None, 1e-4),  # values leaving the domain (a sqrt), inside the run
        (PROBLEMS["robertson"], None, 1e-6),
        (PROBLEMS["transistor-amplifier"], (0.0, 0.01), 1e-6),  # rejections
    ],
    ids=["pendulum", "pendulum-1e-9", "hessenberg", "akzo-nobel", "akzo-nobel-1e-4", "robertson", "transistor"],
)
def test_the_run_takes_the_controllers_steps_bit_for_bit(monkeypatch, problem, span, rtol):
    compiled = problem.model().compile()
    span = span or problem.t_span
    run, single = _with_and_without_run(monkeypatch, compiled, span, rtol=rtol, atol=rtol)
    assert run.stats["compiled_runs"] > 0 and "compiled_runs" not in single.stats
    for key in COUNTS:
        assert run.stats[key] == single.stats[key], key
    assert np.array_equal(run.t, single.t)
    for name in (*compiled.state_names, *compiled.algebraic_names):
        assert np.array_equal(run[name], single[name]), name


def _ends(monkeypatch):
    """How each compiled run ended (sequence.FULL, FINISHED, HANDBACK, LIMIT), recorded as the solve goes."""
    ends = []
    advance = loop.CompiledRun.advance

    def recorded(self, *args):
        out = advance(self, *args)
        ends.append(out[-1])
        return out

    monkeypatch.setattr(loop.CompiledRun, "advance", recorded)
    return ends


def test_newton_failures_are_handled_inside_the_run(monkeypatch):
    """Akzo-Nobel at 1e-8: Newton fails with kept Jacobians (retried with fresh ones) and outright
    (z checked over the step, h halved), all inside the run, counted as the one-attempt path counts."""
    ends = _ends(monkeypatch)
    run = dm.solve(PROBLEMS["akzo-nobel"].model(), (0.0, 180.0), rtol=1e-8, atol=1e-8)
    # (5 retries with Newton's tolerance 1e-4 of RADAU5's rule; 8 with five stages' rtol^(2/3), 4.6e-6)
    assert run.stats["newton_failures"] == 2 and run.stats["compiled_retries"] == 8
    assert sequence.HANDBACK not in ends and ends[-1] == sequence.FINISHED
    # (in as few calls as the run's attempts allow: loop.RUN_ATTEMPTS, or MACHINE_RUN_ATTEMPTS in machine code)
    size = casadi_engine.MACHINE_RUN_ATTEMPTS if run.stats["jit"].startswith("machine") else loop.RUN_ATTEMPTS
    assert run.stats["compiled_runs"] == len(ends) == -(-run.stats["attempts"] // size)


def test_dense_output_from_the_runs_steps(monkeypatch):
    t_eval = np.linspace(0.0, 2.0, 37)
    run, single = _with_and_without_run(monkeypatch, PENDULUM.model(), (0.0, 2.0), rtol=1e-7, atol=1e-7, t_eval=t_eval)
    assert np.array_equal(run.t, t_eval)
    compiled = PENDULUM.model().compile()
    for name in (*compiled.state_names, *compiled.algebraic_names):
        assert np.array_equal(run[name], single[name]), name
    reference = dm.solve(compiled, (0.0, 2.0), method="reference", t_eval=t_eval)
    for name in compiled.state_names:  # the collocation polynomials between steps: order s = 3 there
        assert np.abs(run[name] - reference[name]).max() < 1e-5, name


def test_the_budget_is_checked_where_the_controller_checks_it(monkeypatch):
    """max_steps and the progress watch see the same attempts: the same error, word for word."""
    messages = []
    for make_run in (True, False):
        if not make_run:
            monkeypatch.setattr(CasadiEngine, "make_compiled_run", lambda self, iterations: None)
        for max_steps in (7, 40, 5000):
            with pytest.raises(E.StepLimitError) as raised:
                dm.solve(PENDULUM.model(), (0.0, 1e300), rtol=1e-6, atol=1e-6, max_steps=max_steps)
            messages.append(str(raised.value))
    assert messages[:3] == messages[3:]
    assert "max_steps = 7 reached" in messages[0] and "max_steps = 5000 cannot suffice" in messages[2]


def test_a_sign_change_of_the_iteration_matrix_is_refused_from_the_run(monkeypatch):
    """q' = (0.7 - t) z, 0 = q - sin t: g_y f_z passes through zero at t = 0.7; the run hands the
    attempt whose fresh Jacobian flips the sign back, and the stepper names the constraint."""
    m = dm.Model("vanishing")
    m.states("q")
    m.algebraics("z")
    m.ode("q", "z*(0.7 - t)")
    m.constraint("q - sin(t)", name="track")
    m.initial(q=0.0)
    ends = _ends(monkeypatch)
    with pytest.raises(E.ConvergenceError, match=r"the constraints \('track'\) stop determining the algebraic"):
        dm.solve(m, (0.0, 1.5), rtol=1e-6, atol=1e-6)
    assert ends[-1] == sequence.HANDBACK


def test_an_exactly_singular_newton_matrix_is_named_from_the_run(monkeypatch, capfd):
    """0 = (t - 0.5) (z - 1): g_z vanishes at t = 0.5, where LAPACK refuses the factorisation inside
    the run; the stepper makes that attempt and names the cause, and casadi's dump stays quiet."""
    m = dm.Model("pinch")
    m.states("y")
    m.algebraics("z")
    m.ode("y", "-y + z")
    m.constraint("(t - 0.5)*(z - 1)", name="pinch")
    m.initial(y=1.0, z=1.0)
    ends = _ends(monkeypatch)
    with pytest.raises(
        E.ConvergenceError, match=r"the Newton matrix is singular for sample 0 at t = 0.5 with h = 0.5; "
    ):
        dm.solve(m, (0.0, 1.0), rtol=1e-3, atol=1e-3, h0=0.5, reuse_jacobian=False)
    assert ends[-1] == sequence.HANDBACK
    printed = capfd.readouterr()
    assert "Input 0" not in printed.out + printed.err and "LapackLu" not in printed.out + printed.err


def test_values_leaving_the_domain_shorten_the_step_inside_the_run(monkeypatch):
    """sqrt of a state that a long step drives negative: the attempt fails as a diverging Newton does
    and h shrinks, inside the run (before, the run handed each such attempt to the general path, which
    failed it the same way), and the solve finishes on the exact solution."""
    m = dm.Model("draining")
    m.states("v")
    m.ode("v", "-sqrt(v)")
    m.initial(v=1.0)
    ends = _ends(monkeypatch)
    sol = dm.solve(m, (0.0, 1.99), rtol=1e-6, atol=1e-8)
    exact = (1.0 - sol.t / 2.0) ** 2
    assert np.abs(sol["v"] - exact).max() < 1e-6
    assert sequence.HANDBACK not in ends and sol.stats["newton_failures"] > 0


def test_akzo_nobel_leaves_the_domain_once_inside_the_run(monkeypatch):
    """Akzo Nobel at rtol 1e-4: the second step's extrapolated guess (h grown 6.6 x) puts a
    concentration under a sqrt below zero; the run halves h itself (one Newton failure, 16 steps,
    one call), where it handed the attempt to the general path before (0.65 ms of a 1.5 ms solve),
    and it ends on the Test Set's reference at t = 180 (within rtol of each variable's peak: 1.7e-5 at most)."""
    problem = PROBLEMS["akzo-nobel"]
    ends = _ends(monkeypatch)
    sol = dm.solve(problem.model(), problem.t_span, rtol=1e-4, atol=1e-4)
    assert sequence.HANDBACK not in ends and ends == [sequence.FINISHED]
    assert sol.status == "success" and sol.stats["newton_failures"] == 1 and sol.stats["steps"] == 16
    for name, value in problem.reference.items():
        assert abs(sol[name][-1] - value) <= 1e-4 * np.abs(sol[name]).max(), name


def test_values_non_finite_at_every_step_are_named_by_the_general_path(monkeypatch):
    """v' = -sqrt(v) - 1 empties v at t = 0.6137: no step passes, h shrinks inside the run until it
    underflows, and the last attempt, made on the general path, names the equation and the stage."""
    m = dm.Model("emptying")
    m.states("v")
    m.ode("v", "-sqrt(v) - 1")
    m.initial(v=1.0)
    ends = _ends(monkeypatch)
    with pytest.raises(
        E.ConvergenceError,
        match=r"step size underflow at t = 0\.6137\d* .*last failure: non-finite values: the right-hand side of v' "
        r"at stage \d",
    ):
        dm.solve(m, (0.0, 3.0), rtol=1e-6, atol=1e-8)
    assert ends[-1] == sequence.HANDBACK  # (the shrunk h underflows: Python makes that attempt)


@pytest.mark.skipif(find_compiler() is None, reason="no C compiler on PATH")
def test_the_run_on_machine_code_gives_the_same_bits(monkeypatch):
    """With jit the systems are factored by the C loop of .kernel (a fixed pivot order, here on a dense
    6 x 6 pattern): the run takes the steps of one attempt per call bit for bit, and the virtual
    machine's (LAPACK's inverses) to rounding."""
    compiled = PROBLEMS["akzo-nobel"].model().compile()
    options = dict(rtol=1e-7, atol=1e-7, t_eval=np.linspace(0.0, 180.0, 19))
    run, single = _with_and_without_run(monkeypatch, compiled, (0.0, 180.0), jit=True, **options)
    assert run.stats["compiled_runs"] > 0
    for key in COUNTS:
        assert run.stats[key] == single.stats[key], key
    for name in compiled.state_names:
        assert np.array_equal(run[name], single[name]), name
    vm = dm.solve(compiled, (0.0, 180.0), **options)
    for key in COUNTS[:-2]:  # (h_min and h_max to rounding)
        assert run.stats[key] == vm.stats[key], key
    for name in compiled.state_names:
        np.testing.assert_allclose(run[name], vm[name], rtol=1e-12, atol=1e-15, err_msg=name)


@pytest.mark.skipif(find_compiler() is None, reason="no C compiler on PATH")
def test_the_loop_in_c_is_its_attempt_called_until_the_run_ends(monkeypatch):
    """radau_run_machine_code (.loop.run_loop_source) gives, bit for bit, what its exported attempt gives
    called one attempt at a time from the same state: the state after the last attempt that ran and each
    attempt's record; the records after the run ended are not written (the output buffer holds an
    earlier call's there), and the state's count of attempts names the records that ran, the first ones
    (car axis at 1e-4: 318 attempts in four calls, the last ending with the integration; and a call whose
    state is already inactive)."""
    libraries, calls = [], []
    build = casadi_engine.machine_library
    monkeypatch.setattr(casadi_engine, "machine_library", lambda *args: libraries.append(build(*args)) or libraries[-1])
    advance = loop.CompiledRun.advance

    def recorded(self, *args):
        out = advance(self, *args)
        calls.append([inputs.copy() for inputs in self.buffered.inputs])
        return out

    monkeypatch.setattr(loop.CompiledRun, "advance", recorded)
    compiled = PROBLEMS["car-axis"].model().compile()  # (its own caches: the library is built or loaded here)
    sol = dm.solve(compiled, (0.0, 3.0), rtol=1e-4, atol=1e-4, jit=True)
    assert sol.stats["compiled_runs"] == len(calls) >= 4
    functions = libraries[-1].functions
    run, attempt = functions["radau_run_machine_code"], functions["radau_attempt_machine_code"]
    state_size, record_size = attempt.nnz_out(0), attempt.nnz_out(1)
    attempts = (run.nnz_out(0) - state_size) // record_size
    active = sequence.SCALARS["active"]
    idle = calls[-1][0].copy()
    idle[active] = 0.0
    calls.append([idle, calls[-1][1]])
    buffered = Buffered(run, inputs=2)
    ran_flag = sequence.RECORD.index("ran")
    for given, settings in calls:
        state, records, called = given, np.zeros((attempts, record_size)), 0
        for k in range(attempts):
            if not state[active]:
                break
            state, records[k] = (np.asarray(out).ravel() for out in attempt(state, settings))
            called += 1
        buffered.inputs[0][:], buffered.inputs[1][:] = given, settings  # (the output buffer reused, as a solve does)
        out = buffered.evaluate()
        assert np.array_equal(out[:state_size], state)
        written = out[state_size : state_size + called * record_size].reshape(called, record_size)
        assert np.array_equal(written, records[:called])
        ran = int(out[sequence.SCALARS["attempts"]])
        assert ran == int(records[:, ran_flag].sum()) and records[:ran, ran_flag].all()


def test_a_run_that_finishes_the_integration_leaves_no_factors(monkeypatch):
    """The last run's Jacobian and factors are not written back into the stepper (nothing reads them
    after the integration ends): the pendulum at 1e-4 (6 attempts, one run) builds no Factors from a
    run's packed factors, and its steps are those of one attempt per call, bit for bit."""
    ends, built = _ends(monkeypatch), []
    packed = CasadiEngine._packed_factors
    monkeypatch.setattr(CasadiEngine, "_packed_factors", lambda self, *args: built.append(1) or packed(self, *args))
    run = dm.solve(PENDULUM.model(), (0.0, 1.0), rtol=1e-4, atol=1e-4)
    assert ends == [sequence.FINISHED] and run.stats["compiled_runs"] == 1
    assert built == []
    monkeypatch.setattr(CasadiEngine, "make_compiled_run", lambda self, iterations: None)
    single = dm.solve(PENDULUM.model(), (0.0, 1.0), rtol=1e-4, atol=1e-4)
    for key in COUNTS:
        assert run.stats[key] == single.stats[key], key
    for name in PENDULUM.model().compile().state_names:
        assert np.array_equal(run[name], single[name]), name


@pytest.mark.parametrize("m", [0, 1, 2, 3, 4, 6])
def test_signs_of_determinants(m):
    sign = loop.sign_det_function(m)
    rng = np.random.default_rng(m)
    for _ in range(40):
        matrix = rng.standard_normal((m, m))
        assert float(sign(matrix.ravel(order="F"))) == (np.sign(np.linalg.det(matrix)) if m else 1.0)
    if m:
        assert float(sign(np.zeros(m * m))) == 0.0
        assert float(sign(np.full(m * m, np.nan))) == 0.0
        singular = rng.standard_normal((m, m))
        singular[:, -1] = 0.0
        assert float(sign(singular.ravel(order="F"))) == 0.0


def test_a_kept_step_keeps_its_factors_across_the_rounding_of_t(monkeypatch):
    """The pendulum at rtol 1e-4 over [0, 1]: h kept by the band moves by t's float64 spacing from step to step
    (formulas.step_length), and its factors still serve: 5 factorisations of two LU each (6 before, one of
    them for such a move alone), the same steps on both paths; the states within 1e-3 of IDAS at 1e-12."""
    compiled = PENDULUM.model().compile()
    grid = np.linspace(0.0, 1.0, 21)
    run, single = _with_and_without_run(monkeypatch, compiled, (0.0, 1.0), rtol=1e-4, atol=1e-4, t_eval=grid)
    for key in COUNTS:
        assert run.stats[key] == single.stats[key], key
    assert run.stats["steps"] == 6 and run.stats["jacobian_evaluations"] == 3
    assert run.stats["lu_decompositions"] == 10
    reference = dm.solve(compiled, (0.0, 1.0), method="casadi-idas", rtol=1e-12, atol=1e-12, t_eval=grid)
    for name in compiled.state_names:
        assert np.max(np.abs(run[name] - reference[name])) < 1e-3, name

"""radau's compiled adaptive attempt: the general path's algorithm in one casadi call per step.

The compiled attempt (start guess, simplified Newton with its tests, error estimate) must take
the same steps with the same Newton iterations as the general path that it replaces; machine code
(``jit=True``) must give the same bits as casadi's virtual machine; its options fail by name.
"""

import os

import numpy as np
import pytest
from daemodel.backends.radau import compiled as radau_compiled
from daemodel.backends.radau import control, formulas, linalg, step
from daemodel.backends.radau.casadi_engine import CasadiEngine
from daemodel.backends.radau.compiled import find_compiler

import daemodel as dm
from daemodel import errors as E
from daemodel.collocation import extrapolation_matrix, extrapolation_polynomial, horner
from daemodel.problems import HESSENBERG, PENDULUM, PROBLEMS
from daemodel.tableau import radau_iia

needs_compiler = pytest.mark.skipif(find_compiler() is None, reason="no C compiler on PATH")


def _solve_both(monkeypatch, compiled, t_span, **options):
    """The casadi engine with and without the compiled attempt, at the general path's reuse thresholds,
    both on casadi's virtual machine (LAPACK's factors: machine code factors with a fixed pivot order)."""
    monkeypatch.setattr(step, "REUSE_THETA_COMPILED", step.REUSE_THETA)
    monkeypatch.setattr(control, "KEEP_H_BAND_COMPILED", control.KEEP_H_BAND)
    fast = dm.solve(compiled, t_span, engine="casadi", jit=False, **options)
    monkeypatch.setattr(CasadiEngine, "make_compiled_step", lambda self, *args, **kwargs: False)
    general = dm.solve(compiled, t_span, engine="casadi", jit=False, **options)
    monkeypatch.undo()
    return fast, general


@pytest.mark.parametrize(
    ("problem", "rtol"),
    [(PENDULUM, 1e-6), (PENDULUM, 1e-8), (HESSENBERG, 1e-6), (PROBLEMS["akzo-nobel"], 1e-6)],
    ids=["pendulum-1e-6", "pendulum-1e-8", "hessenberg-1e-6", "akzo-nobel-1e-6"],
)
def test_compiled_attempt_takes_the_general_paths_steps(monkeypatch, problem, rtol):
    compiled = problem.model().compile()
    span = problem.t_span if problem.name != "pendulum" else (0.0, 1.0)
    # (at fixed output times: the step ends differ by rounding, 3.4e-8 on the pendulum at 1e-8 on one
    # machine, and the values there by as much as the steps' slope times that)
    times = np.linspace(*span, 12)
    fast, general = _solve_both(monkeypatch, compiled, span, rtol=rtol, atol=rtol, t_eval=times)
    assert "compiled_retries" in fast.stats and "compiled_retries" not in general.stats
    counts = ("steps", "attempts", "rejected_steps", "newton_failures", "newton_iterations", "jacobian_evaluations")
    for key in (*counts, "residual_evaluations"):
        assert fast.stats[key] == general.stats[key], key
    # the same iterates up to rounding; Newton stops within newton_tol of the solution (1e-4 of the
    # error scale at rtol 1e-8, 0.03 at 1e-6), and rounding moves where: 1.6e-10 on the pendulum at 1e-8.
    # Those moves add up over the steps like local errors, which the controller holds to the solve's
    # accuracy: that accuracy (atol + rtol |y|) is the bound, not one machine's BLAS (the same comparison
    # on the 20-chain measured 0.03 of it here, 0.41 elsewhere; tests/backends/test_radau_sparse.py)
    for name in compiled.state_names:
        np.testing.assert_allclose(fast[name], general[name], rtol=rtol, atol=rtol)


@needs_compiler
@pytest.mark.parametrize("problem", [PENDULUM, PROBLEMS["akzo-nobel"]], ids=["pendulum", "akzo-nobel"])
def test_machine_code_gives_the_virtual_machines_bits(problem):
    """Fixed steps: the same bits.  Adaptive ones: jit factors with the C loop of .kernel (a fixed pivot
    order) where the virtual machine inverts with LAPACK, so the same steps and values to rounding."""
    compiled = problem.model().compile()
    t_eval = np.linspace(*problem.t_span, 11)
    for options in ({"rtol": 1e-6, "atol": 1e-6}, {"h": (problem.t_span[1] - problem.t_span[0]) / 20}):
        vm = dm.solve(compiled, problem.t_span, t_eval=t_eval, jit=False, **options)
        jit = dm.solve(compiled, problem.t_span, jit=True, t_eval=t_eval, **options)
        assert jit.stats["jit"] == f"machine code ({find_compiler()})"
        assert vm.stats["jit"] == "casadi's virtual machine (jit=False)"
        assert jit.stats["steps"] == vm.stats["steps"]
        assert jit.stats["newton_iterations"] == vm.stats["newton_iterations"]
        for name in (*compiled.state_names, *compiled.algebraic_names):
            if "h" in options:
                assert np.array_equal(jit[name], vm[name]), name
            else:
                # (an index-2 multiplier takes its stages' rounding amplified by 1/h: the pendulum's y5 with
                # the default's five stages at rtol 1e-6, 1.2e-11 apart, as before the index-2 guess changed)
                close = 1e-10 if name in compiled.algebraic_names and problem is PENDULUM else 1e-12
                np.testing.assert_allclose(jit[name], vm[name], rtol=close, atol=1e-15, err_msg=name)


@needs_compiler
@pytest.mark.parametrize("name", ["car-axis", "pendulum"])
def test_how_the_library_is_compiled_changes_no_bit(monkeypatch, tmp_path, name):
    """One compiler run at -O2, or the source cut into translation units compiled at once (daemodel.
    translation_units) with GCC's -O2 less the passes of GCC_FLAGS: the same steps, the same values."""
    from daemodel import cache

    monkeypatch.setenv(cache.CACHE_VARIABLE, str(tmp_path / "cache"))
    problem, options = PROBLEMS[name], {"rtol": 1e-6, "atol": 1e-6}
    runs = []
    original = cache.run_compiler
    monkeypatch.setattr(
        cache, "run_compiler", lambda commands, *args: (runs.append(commands), original(commands, *args))
    )
    monkeypatch.setattr(cache, "workers", lambda: 4)
    cut = dm.solve(problem.model().compile(), problem.t_span, jit=True, **options)
    assert len(runs) == 2 and len(runs[0]) > 1  # (units at once, then the link)
    assert all(flag in runs[0][0] for flag in radau_compiled.GCC_FLAGS) or "clang" in cache.compiler_version(
        find_compiler()
    )
    monkeypatch.setattr(radau_compiled, "COMPILE_UNITS", 1)
    monkeypatch.setattr(radau_compiled, "compiler_flags", lambda compiler: radau_compiled.COMPILER_FLAGS)
    whole = dm.solve(problem.model().compile(), problem.t_span, jit=True, **options)
    assert len(runs) == 3 and len(runs[2]) == 1 and not set(radau_compiled.GCC_FLAGS) & set(runs[2][0])
    assert cut.stats["compiled_cache"] == whole.stats["compiled_cache"] == "miss"
    assert (
        cut.stats["steps"] == whole.stats["steps"]
        and cut.stats["newton_iterations"] == whole.stats["newton_iterations"]
    )
    compiled = problem.model().compile()
    for key in (*compiled.state_names, *compiled.algebraic_names):
        assert np.array_equal(cut[key], whole[key]), key


def test_gcc_flags_only_for_gcc(monkeypatch):
    monkeypatch.setattr(radau_compiled, "compiler_version", lambda compiler: "Apple clang version 15.0.0")
    assert radau_compiled.compiler_flags("cc") == radau_compiled.COMPILER_FLAGS
    monkeypatch.setattr(radau_compiled, "compiler_version", lambda compiler: "cc (Debian 12.2.0-14) 12.2.0")
    assert radau_compiled.compiler_flags("cc") == radau_compiled.COMPILER_FLAGS + radau_compiled.GCC_FLAGS


def test_the_compiled_step_keeps_radau5s_thresholds_where_newton_meets_rounding():
    """At rtol 1e-13 Newton's tolerance is 10 eps / rtol; a Jacobian kept while Newton contracts at
    0.1 there left stage errors the estimate read as the step's: the pendulum (s = 7) underflowed."""
    sol = dm.solve(PENDULUM.model(), (0.0, 1.0), rtol=1e-13, atol=1e-13, stages=7)
    reference = dm.solve(PENDULUM.model(), (0.0, 1.0), method="reference")
    for name in PENDULUM.model().compile().state_names:
        assert abs(sol[name][-1] - reference[name][-1]) < 1e-10


def test_no_predictive_control_where_the_estimates_are_rounding_noise():
    """Gustafsson's prediction squares the estimates: at rtol 1e-13 (rounding) it drove a chain of 40
    pendulums (s = 7, the sparse general path) to step size underflow at t = 0.76."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
    import scaling_models

    compiled = scaling_models.pendulum_chain(40).compile()
    span = scaling_models.T_SPAN["pendulum_chain"]
    sol = dm.solve(compiled, span, rtol=1e-13, atol=1e-13, stages=7, jit=False)
    assert sol.stats["steps"] < 300  # 120 measured


def test_jit_option_errors(monkeypatch):
    for wrong in (1, "yes", "AUTO", None):
        with pytest.raises(E.InvalidOptionError, match=rf"jit must be 'auto', True or False; got {wrong!r}"):
            dm.solve(PENDULUM.model(), (0.0, 1.0), jit=wrong)
    monkeypatch.setattr(radau_compiled, "find_compiler", lambda: "/usr/bin/cc")
    with pytest.raises(E.InvalidOptionError, match=r"engine='torch' has nothing to compile"):
        dm.solve(PENDULUM.model(), (0.0, 1.0), jit=True, engine="torch")
    with pytest.raises(E.InvalidOptionError, match=r"this solve \(2 sample\(s\), float64, device 'cpu'\) runs on"):
        dm.solve(PENDULUM.model(), (0.0, 1.0), jit=True, parameters={"m": [1.0, 2.0]})
    from daemodel.backends.radau import options

    monkeypatch.setattr(options, "find_compiler", lambda: None)
    with pytest.raises(E.InvalidOptionError, match=r"jit=True needs a C compiler on PATH \(tried cc, gcc, clang\)"):
        dm.solve(PENDULUM.model(), (0.0, 1.0), jit=True)


def test_auto_says_which_code_ran_and_goes_on_where_the_compiler_fails(monkeypatch, tmp_path):
    """jit="auto" (the default): machine code where a compiler is found, said in stats["jit"]; where
    none is found, or it fails, casadi's virtual machine, said there with the reason; jit=True raises."""
    compiled = PENDULUM.model().compile()
    span, options = (0.0, 1.0), {"rtol": 1e-6, "atol": 1e-6}
    vm = dm.solve(compiled, span, jit=False, **options)
    assert vm.stats["jit"] == "casadi's virtual machine (jit=False)" and "compiled_cache" not in vm.stats
    batch = dm.solve(compiled, span, parameters={"m": [1.0, 2.0]}, **options)
    assert "jit" not in batch.stats  # (the torch engine compiles nothing)
    failing = tmp_path / "cc"
    failing.write_text("#!/bin/sh\necho 'cc: fatal error: out of licences' >&2\nexit 1\n")
    failing.chmod(0o755)
    monkeypatch.setenv("PATH", str(tmp_path))
    fresh = PENDULUM.model().compile()  # (nothing compiled for it in this process)
    sol = dm.solve(fresh, span, **options)
    assert sol.stats["jit"].startswith(
        "casadi's virtual machine: the C compiler failed (radau's machine code: compiling"
    )
    assert "cc: fatal error: out of licences" in sol.stats["jit"] and sol.status == "success"
    for name in compiled.state_names:  # (the virtual machine's answer, bit for bit)
        assert np.array_equal(sol[name], vm[name]), name
    with pytest.raises(E.CompileError, match=r"out of licences; solve with jit=False"):
        dm.solve(PENDULUM.model().compile(), span, jit=True, **options)
    monkeypatch.setenv("PATH", str(tmp_path / "nothing"))
    none = dm.solve(fresh, span, **options)
    assert none.stats["jit"] == "casadi's virtual machine: no C compiler on PATH (tried cc, gcc, clang)"


def test_auto_tries_a_failing_compiler_once_per_model(monkeypatch, tmp_path):
    """jit="auto" remembers a failed compile of a model for the process: a failing (or hanging: up to
    10 minutes each) compiler was run again by every solve and by every piece between events; jit=True
    still tries, and a model compiled anew is tried anew."""
    from daemodel.problems import BOUNCING_BALL

    runs = tmp_path / "runs"
    failing = tmp_path / "cc"
    failing.write_text(
        f'#!/bin/sh\n[ "$1" = --version ] && exit 0\necho run >> {runs}\necho "cc: no licence" >&2\nexit 1\n'
    )
    failing.chmod(0o755)
    monkeypatch.setenv("PATH", str(tmp_path))
    from daemodel import cache

    monkeypatch.setattr(cache, "workers", lambda: 1)  # (one compiler run a compile: several CPUs run one per unit)
    ball = BOUNCING_BALL.model().compile()
    sol = dm.solve(ball, BOUNCING_BALL.t_span, rtol=1e-8, atol=1e-8)
    assert sol.stats["events"] >= 3 and sol.status == "success"
    assert (
        sol.stats["jit"].startswith("casadi's virtual machine: the C compiler failed")
        and "no licence" in sol.stats["jit"]
    )
    assert runs.read_text().count("run") == 1  # (the first piece's; the pieces after each bounce remember it)
    again = dm.solve(ball, BOUNCING_BALL.t_span, rtol=1e-8, atol=1e-8)
    assert again.stats["jit"] == sol.stats["jit"] + ", earlier in this process"
    assert runs.read_text().count("run") == 1
    for name in ball.state_names:
        assert np.array_equal(again[name], sol[name]), name
    with pytest.raises(E.CompileError, match=r"no licence"):
        dm.solve(ball, BOUNCING_BALL.t_span, rtol=1e-8, atol=1e-8, jit=True)
    assert runs.read_text().count("run") == 2
    dm.solve(BOUNCING_BALL.model().compile(), BOUNCING_BALL.t_span, rtol=1e-8, atol=1e-8)
    assert runs.read_text().count("run") == 3


@needs_compiler
def test_stats_say_the_virtual_machine_where_nothing_was_compiled():
    """Fixed steps on sparse systems (above 100 unknowns) compile nothing, even with jit=True: stats["jit"]
    said "machine code" there, with no compiled_cache."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
    import scaling_models

    sparse = scaling_models.reaction_diffusion(60).compile()  # 120 unknowns, sparse
    sol = dm.solve(sparse, (0.0, 2e-3), h=1e-3, jit=True)
    assert sol.stats["jit"].startswith("casadi's virtual machine: nothing to compile for this solve")
    assert "compiled_cache" not in sol.stats
    adaptive = dm.solve(sparse, (0.0, 2e-3), rtol=1e-6, atol=1e-6, jit=True)  # (static factors: compiled)
    assert adaptive.stats["jit"] == f"machine code ({find_compiler()})" and "compiled_cache" in adaptive.stats


@needs_compiler
def test_auto_leaves_models_above_its_size_on_the_virtual_machine(monkeypatch):
    """jit="auto" compiles up to JIT_AUTO_MAX_SIZE unknowns (the first compile of reaction-diffusion
    took 16 s at 200 unknowns, 96 s at 1,000 for nothing saved; 10^5 would not finish): above it the
    virtual machine, said in stats["jit"]; jit=True still compiles."""
    import sys
    from pathlib import Path

    from daemodel.backends.radau import backend

    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
    import scaling_models

    large = scaling_models.reaction_diffusion(101).compile()  # 202 unknowns
    sol = dm.solve(large, (0.0, 1e-3), rtol=1e-6, atol=1e-6)
    assert sol.stats["jit"] == (
        "casadi's virtual machine: 202 unknowns, above jit='auto''s 200 (compiling would take minutes for "
        "little saved per solve; jit=True compiles at any size)"
    )
    assert "compiled_cache" not in sol.stats
    compiled = PENDULUM.model().compile()  # (5 unknowns)
    monkeypatch.setattr(backend, "JIT_AUTO_MAX_SIZE", 4)
    assert dm.solve(compiled, (0.0, 1.0), h=0.1).stats["jit"].startswith("casadi's virtual machine: 5 unknowns")
    assert dm.solve(compiled, (0.0, 1.0), h=0.1, jit=True).stats["jit"] == f"machine code ({find_compiler()})"
    monkeypatch.setattr(backend, "JIT_AUTO_MAX_SIZE", 5)
    assert dm.solve(compiled, (0.0, 1.0), h=0.1).stats["jit"] == f"machine code ({find_compiler()})"


@needs_compiler
def test_no_temporary_directory_is_a_compile_error(monkeypatch):
    import tempfile

    import casadi

    def refuse(**kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(tempfile, "mkdtemp", refuse)
    x = casadi.MX.sym("x")
    with pytest.raises(E.CompileError, match=r"no private temporary directory for the compiler \(\[Errno 28\]"):
        radau_compiled.machine_code(casadi.Function("f", [x], [2 * x]), "/usr/bin/cc")


@needs_compiler
def test_a_failing_compiler_is_a_compile_error(tmp_path):
    failing = tmp_path / "cc"
    failing.write_text("#!/bin/sh\necho 'cc: fatal error: no space left on device' >&2\nexit 1\n")
    failing.chmod(0o755)
    import casadi

    x = casadi.MX.sym("x")
    with pytest.raises(
        E.CompileError, match=r"radau's machine code: compiling the step of 'f' with .*cc failed: .*jit=False"
    ):
        radau_compiled.machine_code(casadi.Function("f", [x], [2 * x]), str(failing))


@pytest.mark.parametrize("stages", range(1, 8))
def test_horner_extrapolation_equals_the_product_form(stages):
    c = radau_iia(stages).c
    C = extrapolation_polynomial(c)
    for ratio in (0.0, 0.2, 1.0, 2.5, 8.0):
        exact = extrapolation_matrix(c, ratio)
        np.testing.assert_allclose(horner(C, ratio), exact, rtol=0, atol=1e-14 * max(1.0, np.abs(exact).max()))
    # at ratio 0 the new stages sit on the last node: the polynomial's value there
    np.testing.assert_allclose(horner(C, 0.0), np.eye(stages + 1)[[-1] * stages], atol=1e-15)


@pytest.mark.parametrize("stages", [3, 5, 7])
def test_index2_guess_is_blind_to_the_stages_defect_pattern(stages):
    """Index-2 stage values carry (A^-1 1) g(y_n) / (h g_y f_z) (formulas.high_index_pattern), which the
    whole polynomial carries 19,530 times as large to the next stages at s = 5 (ratio 1): the index-2
    guess carries polynomials of degree s - 1 exactly and that pattern not at all."""
    tableau = radau_iia(stages)
    c, pattern = np.asarray(tableau.c, dtype=float), formulas.high_index_pattern(tableau.A)
    np.testing.assert_allclose(np.asarray(tableau.A, dtype=float) @ pattern, np.ones(stages), atol=1e-12)
    C = extrapolation_polynomial(c, pattern)
    nodes, at_nodes = np.concatenate([[0.0], c]), np.concatenate([[0.0], pattern])
    poly = lambda x: 1 - 2 * x + 0.5 * x ** (stages - 1)  # noqa: E731
    for ratio in (0.0, 0.5, 1.0, 1.5):
        L = horner(C, ratio)
        np.testing.assert_allclose(L @ poly(nodes), poly(1 + c * ratio), atol=1e-11)
        assert np.abs(L @ at_nodes).max() < 1e-10
        if ratio == 1.0 and stages == 5:
            assert np.abs(horner(extrapolation_polynomial(c), ratio) @ at_nodes).max() == pytest.approx(19_530)
    assert formulas.high_index_columns(stages, 4, [2]) == (None if stages == 3 else [4])
    assert formulas.high_index_columns(stages, 4, [1, 3, 2]) == (None if stages == 3 else [5, 6])
    assert formulas.high_index_columns(stages, 4, [1]) is None


def test_index2_guess_takes_the_general_paths_steps_with_five_stages(monkeypatch):
    """The compiled attempt guesses index-2 z as the general path does (blind to their stages' pattern)."""
    compiled = PENDULUM.model().compile()
    fast, general = _solve_both(monkeypatch, compiled, (0.0, 5.0), rtol=1e-6, atol=1e-8, stages=5)
    for key in ("steps", "attempts", "rejected_steps", "newton_failures", "newton_iterations"):
        assert fast.stats[key] == general.stats[key], key
    for name in (*compiled.state_names, *compiled.algebraic_names):
        np.testing.assert_allclose(fast[name], general[name], rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("m", [1, 2, 3, 4])
def test_small_determinant_signs(m):
    rng = np.random.default_rng(m)
    for _ in range(50):
        matrix = rng.standard_normal((m, m))
        assert linalg.small_sign_det(matrix.ravel(order="F"), m) == np.sign(np.linalg.det(matrix))
    assert linalg.small_sign_det(np.zeros(m * m), m) == 0.0
    assert linalg.small_sign_det(np.full(m * m, np.nan), m) == 0.0


def test_a_right_hand_side_of_t_alone_compiles():
    """f = f(t): the Jacobian has no nonzeros (casadi refuses an empty value vector unless told)."""
    m = dm.Model("clock")
    m.states("x")
    m.ode("x", "cos(t)")
    m.initial(x=0.0)
    for options in ({"rtol": 1e-8, "atol": 1e-10}, {"h": 0.05}):
        sol = dm.solve(m, (0.0, 1.0), **options)
        assert abs(sol["x"][-1] - np.sin(1.0)) < 1e-8


def test_the_stage_jacobians_are_the_jacobians_function_at_each_stage():
    """casadi_functions' stage Jacobians call the Jacobian's function at each stage (MX, nothing inlined):
    bit for bit the Jacobian at each stage's time and values."""
    from daemodel.backends.radau.compiled import casadi_functions

    from daemodel.tableau import radau_iia

    compiled = PENDULUM.model().compile().reduced(2)
    rng = np.random.default_rng(3)
    for s in (1, 3):
        tableau = radau_iia(s)
        _, _, jacobian, stage_jacobians, rows, cols = casadi_functions(compiled, tableau)
        D, k = len(compiled.states) + len(compiled.algebraics), len(compiled.parameters)
        t, h, W, p = 0.3, 0.01, rng.normal(size=s * D), rng.normal(size=k)
        values = np.array(stage_jacobians()(np.r_[t, h, W, p])).ravel().reshape(s, -1)
        for i in range(s):
            at = np.r_[t + float(tableau.c[i]) * h, W[i * D : (i + 1) * D], p]
            assert np.array_equal(values[i], np.array(jacobian(at)).ravel())
        assert values.shape[1] == rows.size == cols.size


def test_f_at_the_stages_alone_is_the_residuals_bit_for_bit(first_engine, monkeypatch):
    """Above INLINED_RESIDUAL_MAX_SIZE the error estimate's evaluation after Newton computes f at the stages
    alone (no stage equations): the residual's stage_f bit for bit, so a solve's values do not change."""
    from daemodel.backends.radau import stencil

    from daemodel.problems.families import reaction_diffusion

    model = reaction_diffusion(150)  # 300 unknowns
    compiled, engine = first_engine(model)
    assert engine.D > radau_compiled.INLINED_RESIDUAL_MAX_SIZE
    rng = np.random.default_rng(5)
    y = rng.random((1, engine.n))
    W = rng.random((1, engine.s, engine.D))
    alone, full = engine.stage_values(0.3, 0.01, y, W), engine.residual(0.3, 0.01, y, W)
    assert alone.R is None and alone.G is None
    np.testing.assert_array_equal(alone.stage_f, full.stage_f)
    _, small_engine = first_engine(reaction_diffusion(40))  # 80 unknowns: the residual inlines f
    assert small_engine._stage_f is None
    options = {"rtol": 1e-6, "atol": 1e-8, "jit": False}
    fast = dm.solve(model, (0.0, 1.0), **options)
    monkeypatch.setattr(stencil, "stage_f_of", lambda *args: None)
    full_residuals = dm.solve(model, (0.0, 1.0), **options)
    assert fast.stats["steps"] == full_residuals.stats["steps"]
    for name in compiled.state_names + compiled.algebraic_names:
        np.testing.assert_array_equal(fast[name], full_residuals[name])


def test_the_compiler_found_is_kept_per_path_while_it_exists(monkeypatch, tmp_path):
    """find_compiler searches PATH once per value of PATH (90 us a search, twice in each of the wheelset's
    2,700 solves and trial solves), and again where the compiler found is gone."""
    import shutil

    from daemodel.backends.radau import compiled as machine

    fake = tmp_path / "cc"
    fake.write_text("#!/bin/sh\nexit 0\n")
    fake.chmod(0o755)
    monkeypatch.setenv("PATH", str(tmp_path))
    searches = []
    which = shutil.which
    monkeypatch.setattr(shutil, "which", lambda name, *args, **kw: searches.append(name) or which(name, *args, **kw))
    assert machine.find_compiler() == str(fake) and searches == ["cc"]
    assert machine.find_compiler() == str(fake) and searches == ["cc"]  # (kept: no search)
    fake.unlink()
    assert machine.find_compiler() is None and searches[1:] == list(machine.COMPILERS)  # (gone: searched again)
    monkeypatch.setenv("PATH", str(tmp_path / "other"))
    assert machine.find_compiler() is None


@needs_compiler
def test_a_compiler_found_through_a_relative_path_entry_compiles(tmp_path, monkeypatch):
    """A PATH entry relative to the working folder (``bin``) gave the compiler as ``bin/cc``, which the
    compile, run inside its private temporary folder, could not find: jit=True raised "No such file or
    directory: 'bin/cc'" and jit="auto" never ran machine code.  The compiler is named by its absolute
    path, found again where the working folder changes."""
    real = find_compiler()
    for place in ("one", "two"):
        (tmp_path / place / "bin").mkdir(parents=True)
        (tmp_path / place / "bin" / "cc").symlink_to(real)
    monkeypatch.chdir(tmp_path / "one")
    monkeypatch.setenv("PATH", "bin" + os.pathsep + os.environ["PATH"])  # (the rest: gcc's assembler)
    assert find_compiler() == str(tmp_path / "one" / "bin" / "cc")
    sol = dm.solve(PENDULUM.model(), (0.0, 1.0), rtol=1e-6, jit=True)
    assert sol.status == "success" and sol.stats["jit"] == f"machine code ({tmp_path / 'one' / 'bin' / 'cc'})"
    monkeypatch.chdir(tmp_path / "two")
    assert find_compiler() == str(tmp_path / "two" / "bin" / "cc")


class _TakenSince(list):
    """A pool that another thread emptied between a check and a pop: it reads as holding one, and has none."""

    def __bool__(self) -> bool:
        return True

    def __len__(self) -> int:
        return 1


def test_a_pool_emptied_by_another_thread_makes_a_new_buffer():
    """compiled.lend and the band kernel's factors take a pooled buffer where one is left, else make one: a pool that
    another thread emptied since a check (two threads both saw its last item) makes a new one, not IndexError."""
    import casadi

    x = casadi.SX.sym("x", 3)
    function = casadi.Function("twice", [x], [2 * x])

    class Owner:
        pass

    radau_compiled._LENDABLE[function] = {1: _TakenSince()}
    lent = radau_compiled.lend(Owner(), function)
    np.testing.assert_array_equal(lent(np.array([1.0, 2.0, 3.0])), [2.0, 4.0, 6.0])
    if radau_compiled.find_compiler() is None:
        return
    from daemodel.backends.radau import band

    from daemodel.problems.families import reaction_diffusion

    compiled = reaction_diffusion(60).compile()
    dm.solve(compiled, (0.0, 0.1))
    kernel = compiled._cache["radau-band-kernel"]
    assert isinstance(kernel, band.BandKernel)
    kernel._spare = {False: _TakenSince(), True: _TakenSince()}
    factors, singular = kernel.factor(np.ones(kernel.nnz))
    assert factors[0] in ("sparse", "singular") and singular.shape == (1,)


def test_buffered_functions_are_lent_to_one_owner_at_a_time(monkeypatch):
    """Each solve's engine took ~9 new Buffered (~17 us each, 24,486 in the wheelset's solve at rtol 1e-6): they
    are lent, to one owner alive at a time, and taken back, zeroed, when it is gone; a second solve of a model
    builds none."""
    import gc

    import casadi

    x, y = casadi.SX.sym("x", 3), casadi.SX.sym("y", 2)
    function = casadi.Function("f", [x, y], [x * casadi.sum1(y)])

    class Owner:
        pass

    a, b = Owner(), Owner()
    fa, fb = radau_compiled.lend(a, function, inputs=2), radau_compiled.lend(b, function, inputs=2)
    fa.inputs[1][:] = [1.0, 2.0]
    np.testing.assert_array_equal(fa(np.array([1.0, 2.0, 3.0])), [3.0, 6.0, 9.0])
    np.testing.assert_array_equal(fb(np.array([1.0, 2.0, 3.0])), [0.0, 0.0, 0.0])  # (b's inputs are its own)
    kept = fa.inputs[1]
    del a, fa
    gc.collect()
    fc = radau_compiled.lend(Owner(), function, inputs=2)  # (its owner gone at once: taken back again)
    assert fc.inputs[1] is kept and not kept.any()
    np.testing.assert_array_equal(fc(np.array([1.0, 1.0, 1.0])), [0.0, 0.0, 0.0])

    built = []
    init = radau_compiled.Buffered.__init__
    monkeypatch.setattr(
        radau_compiled.Buffered, "__init__", lambda self, *a, **k: built.append(1) or init(self, *a, **k)
    )
    compiled = PENDULUM.model().compile()
    first = dm.solve(compiled, (0.0, 1.0), method="radau", rtol=1e-8, atol=1e-8)
    count = len(built)
    gc.collect()
    second = dm.solve(compiled, (0.0, 1.0), method="radau", rtol=1e-8, atol=1e-8)
    assert len(built) == count
    np.testing.assert_array_equal(first["y1"], second["y1"])


@needs_compiler
def test_the_machine_codes_iteration_transforms_in_loops_without_copies(monkeypatch):
    """In machine code on static factors the compiled attempt's Newton iteration makes the transforms
    (T^-1 A^-1, T^-1, then T) and the increment's norm in the loops of .kernel (transform_in, transform_out):
    its MX graph holds no matrix product and no transpose (before: 3 of each, whose copies, slices and
    transposes between them took 27 % of the chain of 20 pendulums' run at rtol 1e-4).  The same bits as
    the MX transforms: test_radau_kernel's test_the_step_on_the_loops_gives_the_virtual_machines_bits."""
    import collections

    import casadi
    from daemodel.backends.radau import casadi_engine

    from daemodel.problems.families import pendulum_chain

    made, original = [], radau_compiled.step_function

    def spied(*args):
        made.append(original(*args))
        return made[-1]

    monkeypatch.setattr(casadi_engine, "step_function", spied)
    compiled = pendulum_chain(10).compile()
    sol = dm.solve(compiled, (0.0, 1.0), rtol=1e-4, atol=1e-4, jit=True, t_eval=np.linspace(0.0, 1.0, 5))
    assert sol.stats["pivot_failures"] == 0 and sol.stats["compiled_runs"] >= 1  # (static factors, the run)
    iteration = made[-1].find_function("iteration")
    names = {getattr(casadi, name): name for name in dir(casadi) if name.startswith("OP_")}
    operations = collections.Counter(names[iteration.instruction_id(k)] for k in range(iteration.n_instructions()))
    assert operations["OP_MTIMES"] == 0 and operations["OP_TRANSPOSE"] == 0, operations
    called = {iteration.instruction_MX(k).which_function().name() for k in range(iteration.n_instructions())
              if names[iteration.instruction_id(k)] == "OP_CALL"}  # fmt: skip
    assert {"transform_in", "transform_out"} <= called, called
    reference = dm.solve(compiled, (0.0, 1.0), rtol=1e-10, atol=1e-10, t_eval=np.linspace(0.0, 1.0, 5))
    for name in compiled.state_names:  # (within the tolerance's meaning: 1.4e-4 at most, measured)
        bound = 1e-4 + 1e-4 * np.max(np.abs(reference[name]))
        assert np.max(np.abs(sol[name] - reference[name])) < 10 * bound, name

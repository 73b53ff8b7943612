"""The fixed-pivot sparse factors as a C loop (backends/radau/kernel.py) and the compiled run on them.

The kernel must give the straight-line SX factors bit for bit (real and complex systems, with and
without an error system of its own), the sign of a determinant as LAPACK's LU gives it, and, with
``jit=True``, let the compiled run take the families above 24 unknowns: the same steps and values
as one attempt per call, bit for bit, handing back what Python must do (growth past the bound, a
singular system).  A compiler that fails is named.
"""

import re
import sys
from pathlib import Path

import numpy as np
import pytest
from daemodel.backends.radau import backend as radau_backend
from daemodel.backends.radau import casadi_engine, increments, kernel, loop, sequence
from daemodel.backends.radau.compiled import Buffered, compiler_flags, find_compiler
from daemodel.backends.radau.increments import StaticFactors, static_factor_function
from daemodel.backends.radau.linalg import dense_sign_det
from daemodel.backends.radau.transform import StageTransform, embedded_weights

import daemodel as dm
from daemodel import cache
from daemodel import errors as E
from daemodel.problems import PROBLEMS
from daemodel.tableau import radau_iia

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import scaling_models
from test_radau_loop import COUNTS, _ends, _with_and_without_run  # (pytest puts tests/ on the path)
from test_radau_sparse import _pinches

pytestmark = pytest.mark.skipif(find_compiler() is None, reason="no C compiler on PATH")


@pytest.mark.parametrize(("family", "size"), [("reaction_diffusion", 50), ("pendulum_chain", 20)])
@pytest.mark.parametrize("stages", [2, 3, 5])  # (s = 2: the error estimate's system is no block's)
def test_the_kernel_gives_the_sx_factors_bit_for_bit(first_engine, family, size, stages):
    compiled, engine = first_engine(getattr(scaling_models, family)(size))
    tableau = radau_iia(stages)
    transform = StageTransform.of(tableau.A, embedded_weights(tableau)[0])
    lu = engine._static_pattern()
    factors = StaticFactors(lu, transform)
    sx = Buffered(static_factor_function(lu, transform))
    c = Buffered(kernel.factor_kernel(lu, transform, factors, engine.m, find_compiler())[0])
    assert c.function.nnz_out(0) == factors.size
    J = engine.jacobian(0.0, np.array([compiled.y0]), np.array([compiled.z0]))
    rng = np.random.default_rng(stages)
    for h in (1e-4, 0.01, 0.3):
        x = np.concatenate([[h], J * (1 + 0.5 * rng.standard_normal(len(J)))])
        expected, got = sx(x), c(x)
        assert np.array_equal(expected, got)  # (growth and smallest pivot included)
        assert 0 < got[-2] < 1e3 and got[-1] > 0


@pytest.mark.parametrize("m", [1, 2, 4, 7])
def test_signs_of_determinants_in_c(first_engine, m):
    _, engine = first_engine(scaling_models.reaction_diffusion(15))
    lu = engine._static_pattern()
    functions = kernel.factor_kernel(lu, engine.transform, StaticFactors(lu, engine.transform), m, find_compiler())
    sign = Buffered(functions[1])
    rng = np.random.default_rng(m)
    for _ in range(50):
        matrix = rng.standard_normal((m, m)) * 10.0 ** rng.uniform(-3, 3, (m, m))
        assert sign(matrix.ravel(order="F"))[0] == np.sign(np.linalg.det(matrix)) == dense_sign_det(matrix)
    singular = rng.standard_normal((m, m))
    singular[:, -1] = 0.0
    assert sign(singular.ravel(order="F"))[0] == 0.0 == dense_sign_det(singular)
    assert sign(np.full(m * m, np.nan))[0] == 0.0 == dense_sign_det(np.full((m, m), np.nan))
    assert sign(np.full(m * m, np.inf))[0] == 0.0


@pytest.mark.parametrize("m", [2, 7, 100])
def test_signs_of_triangular_determinants_in_c_are_their_diagonals(first_engine, m):
    # a triangular matrix's sign is read off its diagonal (no LU): lower, upper and diagonal ones with
    # diagonals of either sign, against the product of the diagonal's signs (LAPACK's LU, which
    # dense_sign_det took before, gave 7 of 20 of the badly scaled 100 x 100 lower triangles the wrong
    # sign or 0); a 0 on the diagonal and a NaN or inf off it give 0
    _, engine = first_engine(scaling_models.reaction_diffusion(15))
    lu = engine._static_pattern()
    functions = kernel.factor_kernel(lu, engine.transform, StaticFactors(lu, engine.transform), m, find_compiler())
    sign = Buffered(functions[1])
    rng = np.random.default_rng(m)
    for shape in (np.tril, np.triu, lambda a: np.diag(np.diag(a))):
        for _ in range(20):
            matrix = shape(rng.standard_normal((m, m)) * 10.0 ** rng.uniform(-3, 3, (m, m)))
            expected = np.prod(np.sign(np.diag(matrix)))
            assert sign(matrix.ravel(order="F"))[0] == expected == dense_sign_det(matrix)
        singular = shape(rng.standard_normal((m, m)) + 3.0)
        singular[m // 2, m // 2] = 0.0
        assert sign(singular.ravel(order="F"))[0] == 0.0
        for bad in (np.nan, np.inf):
            broken = shape(rng.standard_normal((m, m)) + 3.0)
            broken[(m - 1, 0) if shape is np.tril else (0, m - 1)] = bad
            assert sign(broken.ravel(order="F"))[0] == 0.0


@pytest.mark.parametrize(
    ("family", "size", "rtol", "stages"),
    [("reaction_diffusion", 15, 1e-6, None), ("pendulum_chain", 10, 1e-6, None), ("pendulum_chain", 10, 1e-8, 5)],
)
def test_the_run_on_static_factors_takes_the_controllers_steps_bit_for_bit(monkeypatch, family, size, rtol, stages):
    compiled = getattr(scaling_models, family)(size).compile()
    options = dict(rtol=rtol, atol=rtol, jit=True, t_eval=np.linspace(0.0, 1.0, 11))
    if stages:
        options["stages"] = stages
    run, single = _with_and_without_run(monkeypatch, compiled, (0.0, 1.0), **options)
    assert len(compiled.state_names) + len(compiled.algebraic_names) > casadi_engine.COMPILED_FACTOR_MAX_SIZE
    assert run.stats["compiled_runs"] > 0 and "compiled_runs" not in single.stats
    for key in COUNTS:
        assert run.stats[key] == single.stats[key], key
    for name in (*compiled.state_names, *compiled.algebraic_names):
        assert np.array_equal(run[name], single[name]), name


def test_growth_past_the_bound_hands_the_attempt_back(monkeypatch):
    """Every static factorisation refused (bound 0): each run hands its first attempt back, and Python
    factors with LAPACK: the steps of a solve without static factors."""
    monkeypatch.setattr(casadi_engine, "MAX_GROWTH", 0.0)
    monkeypatch.setattr(loop, "MAX_GROWTH", 0.0)
    model = scaling_models.reaction_diffusion(15)
    ends = _ends(monkeypatch)
    refused = dm.solve(model, (0.0, 1.0), rtol=1e-6, atol=1e-6, jit=True)
    monkeypatch.undo()
    assert ends and set(ends) == {sequence.HANDBACK}
    monkeypatch.setattr(casadi_engine, "STATIC_MAX_FLOPS", -1)
    general = dm.solve(model, (0.0, 1.0), rtol=1e-6, atol=1e-6, jit=True)
    assert refused.stats["steps"] == general.stats["steps"]
    for name in model.compile().state_names:
        np.testing.assert_allclose(refused[name], general[name], rtol=1e-7, atol=1e-7)


def test_a_singular_system_in_the_run_is_named_by_the_fallback():
    """Thirty copies of 0 = (t - 0.5) (z - 1): at t = 0.5 a pivot of the static factors is 0; the run
    hands the attempt back and SuperLU's factorisation names the cause."""
    m = _pinches()
    with pytest.raises(E.ConvergenceError, match=r"the Newton matrix is singular .* at t = 0.5 .*do not determine"):
        dm.solve(m, (0.0, 1.0), rtol=1e-3, atol=1e-3, h0=0.5, reuse_jacobian=False, jit=True)


def test_a_compiler_that_fails_is_named(first_engine, tmp_path):
    _, engine = first_engine(scaling_models.reaction_diffusion(15))
    lu = engine._static_pattern()
    factors = StaticFactors(lu, engine.transform)
    with pytest.raises(E.CompileError, match=r"compiling the sparse factors with /bin/false failed: no message; solve"):
        kernel.factor_kernel(lu, engine.transform, factors, engine.m, "/bin/false")
    missing = str(tmp_path / "no-such-cc")
    with pytest.raises(E.CompileError, match=r"compiling the sparse factors with .*no-such-cc failed: .*No such file"):
        kernel.factor_kernel(lu, engine.transform, factors, engine.m, missing)


def test_the_kernel_source_holds_numbers_only(first_engine):
    """What differs between models is sizes, arrays of integers and hexadecimal floats, never a name."""
    _, engine = first_engine(scaling_models.reaction_diffusion(15))
    lu = engine._static_pattern()
    source = kernel.kernel_source(lu, engine.transform, StaticFactors(lu, engine.transform), engine.m)
    assert source.endswith(kernel._KERNEL)
    allowed = re.compile(
        r"/\* daemodel: radau's fixed-pivot sparse factors \(generated; numbers only\) \*/|#include <math.h>"
        r"|#define [A-Z_]+ \d+|static const (int|double) [a-z_]+\[\d+\] = \{[-0-9a-fx.p+,]+\};"
    )
    for line in source[: -len(kernel._KERNEL)].splitlines():
        assert allowed.fullmatch(line), line[:80]


def _static_engine(first_engine, model, monkeypatch, **options):
    """The casadi engine of ``model``'s first solve (a short one: conftest's ``first_engine``) on static factors,
    on casadi's virtual machine (their pivot order is the one a solve with ``jit`` takes: it does not depend on
    jit), and the compiled model."""
    with monkeypatch.context() as patch:
        # (static factors at any size on the virtual machine, as with jit)
        patch.setattr(casadi_engine, "COMPILED_FACTOR_MAX_SIZE", 0)
        patch.setattr(casadi_engine, "STATIC_MAX_FLOPS_VM", 10**12)
        patch.setattr(casadi_engine, "STATIC_MAX_FILL", 1.0)
        # (the engine is what is tested: two stages' adaptive solves of an index-2 system are refused
        # (options.check_index_stages), but their factors' solves are still the kernel's to match)
        patch.setattr(radau_backend, "check_index_stages", lambda *args: None)
        compiled, engine = first_engine(model, rtol=1e-6, atol=1e-6, **options)
    assert engine.static is not None
    return compiled, engine


def _kernel_solves(engine) -> dict:
    """The library's ``static_solve`` and ``static_solve_complex`` (:func:`.kernel.kernel_source`'s loops) for
    ``engine``'s static factors, compiled with the flags of a solve's library (:func:`.compiled.machine_library`),
    without the step's functions around them (which cost the compiler 2-20 s a model here: 15 libraries).  How a
    solve's library hands them to the engine is test_the_step_on_the_loops_gives_the_virtual_machines_bits's."""
    compiler = find_compiler()
    static = engine.static
    build = cache.Build(compiler, compiler_flags(compiler), "the kernel's solves", "", libraries=("-lm",))
    source = kernel.kernel_source(static.lu, engine.transform, static, engine.m)
    library = cache.cached_library(source, ["static_solve", "static_solve_complex"], build)
    return {complex_: Buffered(library.functions[name], inputs=2) for complex_, name in
            [(False, "static_solve"), (True, "static_solve_complex")]}  # fmt: skip


@pytest.mark.parametrize(
    "model",
    [
        lambda: scaling_models.reaction_diffusion(50),
        lambda: scaling_models.pendulum_chain(20),
        lambda: scaling_models.pendulum_chain(40),
        lambda: PROBLEMS["squeezer"].model(),
        lambda: PROBLEMS["car-axis"].model(),
    ],
    ids=["reaction_diffusion-50", "pendulum_chain-20", "pendulum_chain-40", "squeezer", "car-axis"],
)
@pytest.mark.parametrize("stages", [2, 3, 5])
def test_the_c_solves_give_the_sx_solves_bit_for_bit(model, stages, monkeypatch, first_engine):
    """The triangular solves of the library (the loops of .kernel, which the compiled step calls above
    UNROLLED_SOLVE_MAX_ENTRIES, and the general path's solves with jit) against the straight-line SX of
    .sparse, on the factors of the model's own Jacobian and random right-hand sides."""
    compiled, engine = _static_engine(first_engine, model(), monkeypatch, stages=stages)
    solves = _kernel_solves(engine)
    static, lu = engine.static, engine.static.lu
    J = engine.jacobian(0.0, np.array([compiled.y0]), np.array([compiled.z0]))
    rng = np.random.default_rng(stages)
    for h in (1e-3, 0.05):
        packed = engine._static["factor"](np.concatenate([[h], J * (1 + 0.3 * rng.standard_normal(len(J)))]))
        systems = [(static.offsets[k], bool(lam.imag)) for k, (_, lam) in enumerate(engine.transform.blocks)]
        for offset, complex_ in [*systems, (static.error_offset, False)]:
            sx = Buffered(lu.solve_function(complex_), inputs=2)
            c = solves[complex_]  # (the library's static_solve or static_solve_complex)
            for _ in range(3):
                b = rng.standard_normal((2 if complex_ else 1) * engine.D) * 10.0 ** rng.uniform(-3, 3)
                for solve in (sx, c):
                    solve.inputs[0][:] = packed[offset : offset + lu.size(complex_)]
                    solve.inputs[1][:] = b
                expected, got = sx.evaluate(), c.evaluate()
                assert np.isfinite(expected).all() and np.array_equal(expected, got)


def test_the_step_on_the_loops_gives_the_virtual_machines_bits(monkeypatch):
    """The compiled step's solves as the loops of .kernel (at any size here) take the virtual machine's
    steps (straight-line SX solves) bit for bit (s = 2: the error estimate's system is no block's).
    (The pendulum chain's machine code differs from the virtual machine in the last bits, as before the
    loops: its run and single attempts agree bit for bit, test_the_run_on_static_factors_...)"""
    monkeypatch.setattr(casadi_engine, "STATIC_MAX_FLOPS_VM", 10**9)  # (the virtual machine takes them too)
    monkeypatch.setattr(increments, "UNROLLED_SOLVE_MAX_ENTRIES", 0)
    for model, stages in [(scaling_models.reaction_diffusion(15), 5), (scaling_models.reaction_diffusion(25), 3),
                          (scaling_models.reaction_diffusion(15), 2)]:  # fmt: skip
        compiled = model.compile()
        options = dict(rtol=1e-6, atol=1e-6, stages=stages)
        vm = dm.solve(compiled, (0.0, 1.0), **options)
        jit = dm.solve(compiled, (0.0, 1.0), jit=True, **options)
        assert "compiled_retries" in vm.stats and jit.stats["steps"] == vm.stats["steps"] > 5
        for name in (*compiled.state_names, *compiled.algebraic_names):
            assert np.array_equal(jit[name], vm[name]), name


def _count_compiles(monkeypatch, tmp_path):
    """A fresh disk cache, and the list of compiler runs that fills as solves compile."""
    monkeypatch.setenv(cache.CACHE_VARIABLE, str(tmp_path / "cache"))
    runs = []
    original = cache.compile_library

    def counted(source, folder, build):
        runs.append(build.what)
        return original(source, folder, build)

    monkeypatch.setattr(cache, "compile_library", counted)
    return runs


@pytest.mark.parametrize(
    ("name", "options", "static"),
    [
        ("pendulum_chain-10", dict(rtol=1e-6, atol=1e-6), True),  # (the loops, the compiled run)
        ("akzo-nobel", dict(rtol=1e-6, atol=1e-6), True),  # (straight-line solves)
        ("pendulum", dict(rtol=1e-6, atol=1e-6), False),  # (dense inverses: the step and the Newton step)
        ("pendulum", dict(h=0.01), False),  # (no compiled step: the general path's Newton step alone)
    ],
)
def test_one_library_serves_the_whole_solve(monkeypatch, tmp_path, name, options, static):
    """One compiler run per model and stages holds all the machine code a solve runs; a second solve in
    the process compiles nothing."""
    runs = _count_compiles(monkeypatch, tmp_path)
    if not static:
        monkeypatch.setattr(casadi_engine, "STATIC_MAX_FLOPS", -1)
    model = scaling_models.pendulum_chain(10) if name == "pendulum_chain-10" else PROBLEMS[name].model()
    compiled = model.compile()
    span = (0.0, 1.0) if name == "pendulum_chain-10" else PROBLEMS[name].t_span
    first = dm.solve(compiled, span, jit=True, **options)
    assert len(runs) == 1 and first.stats["compiled_cache"] == "miss"
    again = dm.solve(compiled, span, jit=True, **options)
    assert len(runs) == 1 and again.stats["compiled_cache"] == "memory"
    assert np.array_equal(first[compiled.state_names[0]], again[compiled.state_names[0]])
    if "rtol" in options:  # (another stage count: one more library)
        dm.solve(compiled, span, jit=True, rtol=1e-9, atol=1e-9, stages=7)  # (1e-6: 3 on index 2, 5 below it)
        assert len(runs) == 2


@pytest.mark.parametrize(
    ("name", "span", "rtol"),
    [
        ("car-axis", (0.0, 3.0), 1e-4),  # (m = 2: the run's own sign formula)
        ("pendulum_chain-4", (0.0, 2.0), 1e-6),  # (m = 4: the kernel's sign, sign_call)
        ("pendulum_chain-20", (0.0, 1.0), 1e-5),  # (100 unknowns: machine code up to MACHINE_RUN_MAX_SIZE)
        ("akzo-nobel", (0.0, 180.0), 1e-8),  # (Newton failures and fresh Jacobians inside the run)
    ],
)
def test_the_run_in_machine_code_gives_the_virtual_machines_run_bit_for_bit(monkeypatch, name, span, rtol):
    """Up to MACHINE_RUN_MAX_SIZE unknowns the whole run is machine code, in the step's library (the
    factors and the sign through the kernel's C): the steps, counts and values of the run on casadi's
    virtual machine around the same step, bit for bit, in fewer calls (MACHINE_RUN_ATTEMPTS a call)."""
    chain = name.startswith("pendulum_chain-")
    model = lambda: scaling_models.pendulum_chain(int(name[15:])) if chain else PROBLEMS[name].model()  # noqa: E731
    options = dict(rtol=rtol, atol=rtol, jit=True, t_eval=np.linspace(*span, 11))
    sizes, advance = [], loop.CompiledRun.advance

    def recorded(self, *args):
        sizes.append(self.attempts)
        return advance(self, *args)

    monkeypatch.setattr(loop.CompiledRun, "advance", recorded)
    machine = dm.solve(model().compile(), span, **options)
    assert set(sizes) == {casadi_engine.MACHINE_RUN_ATTEMPTS}
    monkeypatch.setattr(casadi_engine, "MACHINE_RUN_MAX_SIZE", 0)
    compiled = model().compile()  # (another model: its own cache of casadi functions and libraries)
    sizes.clear()
    virtual = dm.solve(compiled, span, **options)
    assert set(sizes) == {loop.RUN_ATTEMPTS}
    for key in COUNTS:
        assert machine.stats[key] == virtual.stats[key], key
    for name_ in (*compiled.state_names, *compiled.algebraic_names):
        assert np.array_equal(machine[name_], virtual[name_]), name_
    assert machine.stats["compiled_runs"] <= virtual.stats["compiled_runs"]

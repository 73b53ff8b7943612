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
from daemodel.backends.radau import casadi_engine, kernel, loop, sequence
from daemodel.backends.radau.compiled import Buffered, StaticFactors, find_compiler, static_factor_function
from daemodel.backends.radau.linalg import dense_sign_det
from daemodel.backends.radau.transform import StageTransform, embedded_weights

import daemodel as dm
from daemodel import errors as E
from daemodel.tableau import radau_iia

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import scaling_models
from test_radau_loop import COUNTS, _ends, _with_and_without_run  # (pytest puts tests/ on the path)
from test_radau_sparse import _engine, _pinches

pytestmark = pytest.mark.skipif(find_compiler() is None, reason="no C compiler on PATH")


@pytest.mark.parametrize(("family", "size"), [("reaction_diffusion", 50), ("pendulum_chain", 20)])
@pytest.mark.parametrize("stages", [2, 3, 5])  # (s = 2: the error estimate's system is no block's)
def test_the_kernel_gives_the_sx_factors_bit_for_bit(family, size, stages):
    compiled, engine = _engine(getattr(scaling_models, family)(size))
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
def test_signs_of_determinants_in_c(m):
    _, engine = _engine(scaling_models.reaction_diffusion(15))
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


def test_a_compiler_that_fails_is_named(tmp_path):
    _, engine = _engine(scaling_models.reaction_diffusion(15))
    lu = engine._static_pattern()
    factors = StaticFactors(lu, engine.transform)
    with pytest.raises(E.CompileError, match=r"compiling the sparse factors with /bin/false failed: no message; solve"):
        kernel.factor_kernel(lu, engine.transform, factors, engine.m, "/bin/false")
    missing = str(tmp_path / "no-such-cc")
    with pytest.raises(E.CompileError, match=r"compiling the sparse factors with .*no-such-cc failed: .*No such file"):
        kernel.factor_kernel(lu, engine.transform, factors, engine.m, missing)


def test_the_kernel_source_holds_numbers_only():
    """What differs between models is sizes, arrays of integers and hexadecimal floats, never a name."""
    _, engine = _engine(scaling_models.reaction_diffusion(15))
    lu = engine._static_pattern()
    source = kernel.kernel_source(lu, engine.transform, StaticFactors(lu, engine.transform), engine.m)
    assert source.endswith(kernel._KERNEL)
    allowed = re.compile(
        r"/\* daemodel: radau's fixed-pivot sparse factors \(generated; numbers only\) \*/|#include <math.h>"
        r"|#define [A-Z_]+ \d+|static const (int|double) [a-z_]+\[\d+\] = \{[-0-9a-fx.p+,]+\};"
    )
    for line in source[: -len(kernel._KERNEL)].splitlines():
        assert allowed.fullmatch(line), line[:80]

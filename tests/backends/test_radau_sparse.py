"""Sparse LU factors with a fixed pivot order in compiled code (backends/radau/sparse.py).

The factors must solve the transformed systems (real and complex) to rounding on the patterns of
chains and grids, report their growth, and give the compiled step the general path's steps; where
the growth or a zero pivot says the fixed order does not hold, SuperLU factors and names why.
"""

import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sparse
from daemodel.backends.radau import casadi_engine
from daemodel.backends.radau import fill as radau_fill
from daemodel.backends.radau import linalg as radau_linalg
from daemodel.backends.radau import sparse as radau_sparse
from daemodel.backends.radau.compiled import Buffered, find_compiler
from daemodel.backends.radau.increments import StaticFactors, static_factor_function

import daemodel as dm
from daemodel import errors as E

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import scaling_models


@pytest.mark.parametrize(
    ("family", "size"), [("reaction_diffusion", 50), ("pendulum_chain", 20), ("pendulum_chain", 40)]
)
def test_the_factors_solve_every_transformed_system(first_engine, family, size):
    compiled, engine = first_engine(getattr(scaling_models, family)(size))
    static = StaticFactors(engine._static_pattern(), engine.transform)
    assert static.lu.L_size + static.lu.U_size < 0.1 * engine.D**2
    rng = np.random.default_rng(size)
    D, n = engine.D, engine.n
    M = sparse.diags(np.r_[np.ones(n), np.zeros(D - n)])
    J = engine.jacobian(0.0, np.array([compiled.y0]), np.array([compiled.z0]))
    J = J * (1 + 0.3 * rng.random(len(engine.rows)))
    h = 0.01
    factor = Buffered(static_factor_function(static.lu, engine.transform))
    packed = factor(np.concatenate([[h], J]))
    growth, pivot = packed[-2:]
    assert 0 < growth < 10 and pivot > 0  # the pivots SuperLU picked still hold at other values
    Jm = sparse.csc_matrix((J, (engine.rows, engine.cols)), shape=(D, D))
    for index, (_, lam) in enumerate(engine.transform.blocks):
        complex_ = bool(lam.imag)
        solve = Buffered(static.solves[complex_], inputs=2)
        offset = static.offsets[index]
        solve.inputs[0][:] = packed[offset : offset + static.lu.size(complex_)]
        b = rng.standard_normal(2 * D if complex_ else D)
        solve.inputs[1][:] = b
        x = solve.evaluate()
        A = (lam / h * M - Jm).toarray() if complex_ else (lam.real / h * M - Jm).toarray()
        if complex_:
            residual = A @ (x[:D] + 1j * x[D:]) - (b[:D] + 1j * b[D:])
        else:
            residual = A @ x - b
        assert np.abs(residual).max() < 1e-10 * np.abs(A).max() * max(1.0, np.abs(x).max()), index


def _without_static(monkeypatch):
    monkeypatch.setattr(casadi_engine, "STATIC_MAX_FLOPS", -1)
    monkeypatch.setattr(casadi_engine, "STATIC_MAX_FLOPS_VM", -1)


@pytest.mark.parametrize(("family", "size", "rtol"), [("reaction_diffusion", 50, 1e-6), ("pendulum_chain", 20, 1e-7)])
def test_the_compiled_step_on_static_factors_takes_the_general_paths_steps(monkeypatch, family, size, rtol):
    """The families above 24 unknowns now run the compiled step (SuperLU's or LAPACK's factors before)."""
    model = getattr(scaling_models, family)(size)
    times = np.linspace(0.0, 1.0, 11)  # (the step ends differ by rounding: compare at the same times)
    fast = dm.solve(model, (0.0, 1.0), rtol=rtol, atol=rtol, t_eval=times)
    assert "compiled_retries" in fast.stats
    _without_static(monkeypatch)
    general = dm.solve(model, (0.0, 1.0), rtol=rtol, atol=rtol, t_eval=times)
    for key in ("steps", "rejected_steps", "newton_failures", "jacobian_evaluations"):
        assert fast.stats[key] == general.stats[key], key
    # The same steps, not the same bits: each run's Newton stops within newton_tol (RADAU5's sqrt(rtol),
    # 3.2e-4 of the error scale at 1e-7) of each step's collocation solution, and the two factorisations'
    # rounding picks different iterates there; over 29 steps of a chain whose perturbations grow, those
    # differences add up like local errors, which the controller holds to the solve's accuracy. So the
    # bound is that accuracy, atol + rtol |y| (measured: 0.03 of it here, 0.41 on another machine's BLAS).
    compiled = model.compile()
    for name in compiled.state_names:
        np.testing.assert_allclose(fast[name], general[name], rtol=rtol, atol=rtol)


def test_above_200_unknowns_the_virtual_machine_builds_no_static_factors(monkeypatch):
    """On casadi's virtual machine the straight-line factors stop at STATIC_MAX_SIZE_VM unknowns (above, they
    cost seconds of setup for solves within 20 % of SuperLU's): reaction-diffusion at 202 unknowns solves on
    SuperLU, at 200 on static factors, and both meet IDAS at rtol 1e-10."""
    built = []
    monkeypatch.setattr(casadi_engine, "StaticFactors", lambda *args: built.append(args) or StaticFactors(*args))
    times = np.linspace(0.0, 1.0, 5)
    for K, static in ((100, True), (101, False)):
        built.clear()
        compiled = scaling_models.reaction_diffusion(K).compile()
        assert 2 * K - casadi_engine.STATIC_MAX_SIZE_VM == (0 if static else 2)
        sol = dm.solve(compiled, (0.0, 1.0), rtol=1e-6, atol=1e-8, t_eval=times, jit=False)
        assert bool(built) is static and ("compiled_retries" in sol.stats) is static, K
        ref = dm.solve(compiled, (0.0, 1.0), method="casadi-idas", rtol=1e-10, atol=1e-12, t_eval=times)
        for name in compiled.state_names:
            np.testing.assert_allclose(sol[name], ref[name], rtol=1e-5, atol=1e-7)


def test_growth_past_the_bound_falls_back_to_superlu(monkeypatch):
    monkeypatch.setattr(casadi_engine, "MAX_GROWTH", 0.0)  # every static factorisation refused
    model = scaling_models.reaction_diffusion(50)
    refused = dm.solve(model, (0.0, 1.0), rtol=1e-6, atol=1e-6)
    monkeypatch.undo()
    _without_static(monkeypatch)
    general = dm.solve(model, (0.0, 1.0), rtol=1e-6, atol=1e-6)
    assert refused.stats["steps"] == general.stats["steps"]
    assert refused.stats["compiled_retries"] == 0  # (no compiled attempt ran: each factored by LAPACK)
    for name in model.compile().state_names:
        np.testing.assert_allclose(refused[name], general[name], rtol=1e-7, atol=1e-7)


def _pinches():
    """Thirty copies of 0 = (t - 0.5) (z - 1): g_z vanishes at t = 0.5."""
    m = dm.Model("pinches")
    for k in range(30):
        m.states(f"y{k}")
        m.algebraics(f"z{k}")
        m.ode(f"y{k}", f"-y{k} + z{k}")
        m.constraint(f"(t - 0.5)*(z{k} - 1)", name=f"pinch{k}")
        m.initial(**{f"y{k}": 1.0, f"z{k}": 1.0})
    return m


def test_a_singular_system_is_named_by_the_fallback():
    """The static factors are not finite where g_z vanishes; SuperLU's names the cause."""
    m = _pinches()
    with pytest.raises(E.ConvergenceError, match=r"the Newton matrix is singular .* at t = 0.5 .*do not determine"):
        dm.solve(m, (0.0, 1.0), rtol=1e-3, atol=1e-3, h0=0.5, reuse_jacobian=False)


@pytest.mark.skipif(find_compiler() is None, reason="no C compiler on PATH")
def test_machine_code_on_static_factors_gives_the_virtual_machines_bits(monkeypatch):
    monkeypatch.setattr(casadi_engine, "STATIC_MAX_FLOPS_VM", 10**9)  # (the virtual machine takes them too)
    compiled = scaling_models.reaction_diffusion(15).compile()
    vm = dm.solve(compiled, (0.0, 1.0), rtol=1e-6, atol=1e-6)
    jit = dm.solve(compiled, (0.0, 1.0), rtol=1e-6, atol=1e-6, jit=True)
    assert "compiled_retries" in vm.stats and jit.stats["steps"] == vm.stats["steps"]
    for name in compiled.state_names:
        assert np.array_equal(jit[name], vm[name]), name


def test_dense_patterns_keep_lapack(first_engine):
    """All-pairs coupling (160 unknowns): the fixed-order factors would fill in; LAPACK keeps them."""
    _, engine = first_engine(scaling_models.sphere_particles(20))
    assert engine._static_pattern() is None and engine.static is None


@pytest.mark.parametrize("pivoting", ["partial", "matched"])
def test_a_pivot_grown_small_is_refused(first_engine, monkeypatch, pivoting):
    """0 = 2 exp(-40 t) z1 + z2 - 1: partial pivoting's order picked at t = 0 pivots on 2 exp(-40 t), 5e-16 at
    t = 0.9, under entries of order 1 (found by review: a growth measured against a stiff entry elsewhere,
    -1e9, let it pass with 13 % error in z); the multiplier |L| ~ 1e15 refuses it, and LAPACK factors.
    Static pivoting's order eliminates the other constraint first, and holds there."""
    monkeypatch.setattr(casadi_engine, "PIVOTING", (pivoting,))
    m = dm.Model("fading")
    m.states("y0")
    m.ode("y0", "-1e9*(y0 - cos(t))")
    m.initial(y0=1.0)
    for k in range(1, 25):
        m.states(f"y{k}")
        m.ode(f"y{k}", f"-{k}*y{k}")
        m.initial(**{f"y{k}": 1.0})
    m.algebraics("z1")
    m.algebraics("z2")
    m.constraint("2*exp(-40*t)*z1 + z2 - 1", name="g1")
    m.constraint("z1 - z2 - 0.01*sin(z2)", name="g2")
    compiled, engine = first_engine(m)
    assert engine.static is not None  # (27 unknowns: the sparse factors apply)
    y, z = np.array([compiled.y0]), np.array([[1.0, 1.0]])
    assert engine._static_factor(engine.jacobian(0.1, y, z), 0.05) is not None
    J = engine.jacobian(0.9, y, z)
    if pivoting == "matched":
        assert engine._static_factor(J, 0.05) is not None
        return
    assert engine._static_factor(J, 0.05) is None
    factor = engine._static["factor"]  # (the factor function on its buffer, made by the first factorisation)
    assert factor(np.concatenate([[0.05], J]))[-2] > 1e12 > 1e6 == radau_sparse.MAX_GROWTH  # (|L|: ~1e15)


def test_no_pivot_order_leaves_lapack(first_engine, monkeypatch):
    """SuperLU refusing the start's matrix (exactly singular) leaves the factors to LAPACK."""

    def refuse(*args, **kwargs):
        raise RuntimeError("Factor is exactly singular")

    monkeypatch.setattr(casadi_engine, "StaticLU", refuse)
    compiled, engine = first_engine(scaling_models.reaction_diffusion(20))
    assert engine._static_pattern() is None and engine.static is None
    sol = dm.solve(compiled, (0.0, 1.0), rtol=1e-6, atol=1e-6)
    assert sol.status == "success" and sol.stats["steps"] > 0


def test_the_code_a_first_solve_generates_is_setup_not_solve(monkeypatch):
    """Issue 42: the first adaptive solve of a chain of pendulums generated its static factorisation
    (0.4 s of 0.44) and the branch check's functions (50 ms) inside its solve clock.  Each is slowed by
    a known 0.3 s here and must land in setup_time."""
    import time

    from daemodel.compiling.init import NumericSystem

    factor_function, lambdify = casadi_engine.static_factor_function, NumericSystem._lambdify

    def slow_factor_function(*args, **kwargs):
        time.sleep(0.3)
        return factor_function(*args, **kwargs)

    def slow_lambdify(self, exprs):
        time.sleep(0.3)
        return lambdify(self, exprs)

    monkeypatch.setattr(casadi_engine, "static_factor_function", slow_factor_function)
    monkeypatch.setattr(NumericSystem, "_lambdify", slow_lambdify)
    compiled = scaling_models.pendulum_chain(16).compile()
    sol = dm.solve(compiled, (0.0, 1.0), rtol=1e-6, atol=1e-6)
    assert "compiled_retries" in sol.stats  # (the compiled step, on static factors)
    assert sol.setup_time >= 0.6 and sol.solve_time < 0.3, (sol.setup_time, sol.solve_time)


def test_the_memory_estimate_of_sparse_systems_counts_their_factors_fill(first_engine):
    """The memory guard assumed dense Newton matrices: (2s + 1) D^2 (reaction-diffusion at 5 x 10^4
    unknowns refused for 130 GiB).  On the casadi engine's sparse systems it counts the Jacobian's
    nonzeros and s factors of the fill SuperLU makes: within 2x of the solve's own factors."""
    from daemodel.backends.radau import backend

    compiled, engine = first_engine(scaling_models.reaction_diffusion(300))  # 600 unknowns, sparse
    span = scaling_models.T_SPAN["reaction_diffusion"]
    options = backend.RadauOptions(rtol=1e-6, atol=1e-6, stages=3, jit=False)  # (SuperLU: no band LU in C)
    dense = backend.memory_parts(compiled, span, 1, options, "torch")
    assert dense == {"Newton matrices": 7 * 600**2 * 8}
    rows, cols = radau_sparse.jacobian_pattern(compiled)
    assert sorted(zip(rows, cols, strict=True)) == sorted(zip(engine.rows, engine.cols, strict=True))
    values = engine.jacobian(0.0, np.array([compiled.y0]), np.array([compiled.z0]))
    for sigma in (3.6 + 0j, 2.7 + 3.0j):  # (s = 3's shifts over h = 1, about)
        lu = engine._factor_shift(values, sigma)[0][1]
        estimate = radau_fill.factor_entries(rows, cols, len(compiled.states), 600)
        assert (lu.L.nnz + lu.U.nnz) / 2 <= estimate <= 2 * (lu.L.nnz + lu.U.nnz)
    parts = backend.memory_parts(compiled, span, 1, options, "casadi")
    # (factored in its band order, whose fill may be up to BAND_FILL_RATIO times COLAMD's: counted so)
    assert radau_sparse.band_orders(compiled, rows, cols, len(compiled.states), 600) is not None
    counted = radau_linalg.BAND_FILL_RATIO * estimate
    assert parts == {"Newton matrices (sparse)": int(rows.size * 8 * 4 + 3 * counted * 16)}
    assert lu.L.nnz + lu.U.nnz <= counted  # (the engine's own factors, in that order)
    assert parts["Newton matrices (sparse)"] < dense["Newton matrices"] / 20
    # systems the engine factors densely keep the dense estimate
    chain = scaling_models.pendulum_chain(30).compile()  # 150 unknowns, a dense enough pattern?
    dense_chain = radau_linalg.dense_systems(150, radau_sparse.jacobian_pattern(chain)[0].size)
    chain_parts = backend.memory_parts(chain, span, 1, options, "casadi")
    assert ("Newton matrices" in chain_parts) == dense_chain
    small = backend.memory_parts(scaling_models.reaction_diffusion(40).compile(), span, 1, options, "casadi")
    assert small == {"Newton matrices": 7 * 80**2 * 8}  # (80 unknowns: dense, LAPACK)


def test_the_pattern_is_factored_for_the_memory_estimate_once_per_model(monkeypatch):
    """The estimate's one LU of the pattern is made once per model (an adaptive solve made it twice: for
    the guard, then again for the step records' budget; every solve, a fit's or an event's piece, again)."""
    from daemodel.backends.radau import fill

    compiled = scaling_models.reaction_diffusion(300).compile()  # 600 unknowns, sparse
    made = []
    # (the count factors the matrix it is given: fill.matrix_entries, which factor_entries calls too)
    monkeypatch.setattr(fill, "matrix_entries", lambda *args, count=fill.matrix_entries: made.append(1) or count(*args))
    sol = dm.solve(compiled, (0.0, 1e-3), rtol=1e-6, atol=1e-6, jit=False)
    assert sol.status == "success" and len(made) == 1
    again = dm.solve(compiled, (0.0, 1e-3), h=5e-4, jit=False)  # (and kept with the model: fits, events' pieces)
    assert again.status == "success" and len(made) == 1


def test_the_memory_estimate_of_fixed_steps_counts_the_full_newton_system(first_engine):
    """A fixed step's full Newton (where simplified Newton fails, or from start_guess) factors the system
    of s D unknowns, whose SuperLU fill is 2-6x s times one D-sized system's: the estimate counts it."""
    from daemodel.backends.radau import backend

    compiled, engine = first_engine(scaling_models.reaction_diffusion(300), h=1e-3, stages=7)  # 600 unknowns, sparse
    span = scaling_models.T_SPAN["reaction_diffusion"]
    rows = radau_sparse.jacobian_pattern(compiled)[0]
    values = engine.jacobian(0.0, np.array([compiled.y0]), np.array([compiled.z0]))
    transformed = 0
    for sigma in engine.transform.shifts(0.01):
        lu = engine._factor_shift(values, sigma)[0][1]
        transformed += (lu.L.nnz + lu.U.nnz) * 16
    stage = engine.factor_stages([values] * 7, 0.01).lu[1]
    full = (stage.L.nnz + stage.U.nnz) * 8  # (real: the stages' system of 4,200 unknowns)
    options = backend.RadauOptions(h=0.01, stages=7, jit=False)  # (SuperLU's factors: no band LU in C)
    fixed = backend.memory_parts(compiled, span, 1, options, "casadi")["Newton matrices (sparse)"]
    assert transformed + full <= fixed <= 3 * (transformed + full + rows.size * 8 * 13)


@pytest.mark.parametrize(("family", "size"), [("reaction_diffusion", 50), ("pendulum_chain", 20)])
def test_the_entry_bound_is_below_the_factors_entries(first_engine, family, size):
    """unique_entries bounds the static factors' entries from below (fill only adds), so that a pattern
    whose bound passes STATIC_MAX_ENTRIES is refused before any elimination is traced."""
    _, engine = first_engine(getattr(scaling_models, family)(size))
    lu = engine._static_pattern()
    bound = radau_sparse.unique_entries(engine.rows, engine.cols, engine.n, engine.D)
    distinct = {(int(i), int(j)) for i, j in zip(engine.rows, engine.cols, strict=True)}
    assert bound == max(engine.D, len(distinct | {(i, i) for i in range(engine.n)}))
    assert engine.D < bound <= lu.entries


def test_the_entry_bound_keys_in_int64_from_an_int32_pattern():
    """The model's pattern is int32 (CompiledDAE.casadi_jacobian_pattern) and rows * D + cols passes 2^31 at
    46,341 unknowns: its keys are made in int64.  Here D = 10^5 and entry (k + 42949, k + 67296)'s key is
    2^32 + k (D + 1), which an int32 product wraps onto the diagonal entry (k, k)'s: counted, not merged."""
    D, extra = 100_000, 1_000
    k = np.arange(extra)
    rows = np.concatenate([np.arange(D), k + 42_949]).astype(np.int32)
    cols = np.concatenate([np.arange(D), k + 67_296]).astype(np.int32)
    assert int(rows[-1]) * D + int(cols[-1]) > 2**32  # (and (rows * D + cols)[-1] in int32 wraps to k (D + 1))
    assert radau_sparse.unique_entries(rows, cols, 0, D) == D + extra
    assert radau_sparse.unique_entries(rows, cols, D, D) == D + extra  # (M's diagonal: the same keys as J's)


def test_the_model_pattern_is_int32():
    compiled = scaling_models.reaction_diffusion(5).compile()
    rows, cols = compiled.casadi_jacobian_pattern()
    assert rows.dtype == cols.dtype == np.int32
    assert {(int(i), int(j)) for i, j in zip(rows, cols, strict=True)} == set(
        zip(*(a.tolist() for a in compiled.jacobian_pattern()), strict=True)
    )


def test_a_pattern_beyond_the_entry_limit_traces_no_elimination(first_engine, monkeypatch):
    traced = []
    monkeypatch.setattr(radau_sparse.StaticLU, "__init__", lambda self, *a: traced.append(a) or None)
    monkeypatch.setattr(casadi_engine, "STATIC_MAX_ENTRIES", 100)  # (reaction-diffusion of 100 unknowns: 298+)
    _, engine = first_engine(scaling_models.reaction_diffusion(50))
    assert engine._static_pattern() is None
    assert traced == []


def test_sorted_unique_is_numpys_unique():
    rng = np.random.default_rng(5)
    for keys in (np.array([], dtype=np.int64), np.array([7]), rng.integers(0, 50, 400), rng.integers(0, 10**12, 1000)):
        assert np.array_equal(radau_sparse.sorted_unique(keys), np.unique(keys))


def test_the_band_order_solves_every_shifted_system(first_engine):
    """Reaction-diffusion (600 unknowns, banded): its shifted systems are factored in the reverse
    Cuthill-McKee order, which holds no more entries than COLAMD's, and each solve is A^-1 b."""
    compiled, engine = first_engine(scaling_models.reaction_diffusion(300))
    order = engine._order
    assert order is not None and np.array_equal(np.sort(order.columns), np.arange(engine.D))
    D, n = engine.D, engine.n
    rows, cols = radau_sparse.jacobian_pattern(compiled)
    fill = radau_fill.factor_entries(rows, cols, n, D)
    rng = np.random.default_rng(3)
    J = engine.jacobian(0.0, np.array([compiled.y0]), np.array([compiled.z0])) * (
        1 + 0.3 * rng.random(len(engine.rows))
    )
    Jm = sparse.csc_matrix((J, (engine.rows, engine.cols)), shape=(D, D)).toarray()
    M = np.diag(np.r_[np.ones(n), np.zeros(D - n)])
    for sigma in engine.transform.shifts(0.01):
        (kind, lu), singular = engine._factor_shift(J, sigma)
        assert kind == "sparse" and not singular.any()
        assert lu.lu.L.nnz + lu.lu.U.nnz <= fill
        b = rng.standard_normal(D) + (1j * rng.standard_normal(D) if sigma.imag else 0)
        x = engine.solve(("sparse", lu), b[None])[0]
        exact = np.linalg.solve(sigma * M - Jm, b)
        assert np.abs(x - exact).max() < 1e-12 * np.abs(exact).max()


def test_a_two_dimensional_grid_keeps_superlus_order():
    """A 5-point Laplacian on a 30 x 30 grid: its band is 30 wide, where COLAMD fills less (None)."""
    q = 30
    k = np.arange(q * q)
    i, j = divmod(k, q)
    pairs = [(k, k)]
    pairs += [(k[i > 0], k[i > 0] - q), (k[i < q - 1], k[i < q - 1] + q)]
    pairs += [(k[j > 0], k[j > 0] - 1), (k[j < q - 1], k[j < q - 1] + 1)]
    rows, cols = (np.concatenate(a) for a in zip(*pairs, strict=True))
    fill = radau_fill.factor_entries(rows, cols, q * q, q * q)
    assert radau_linalg.band_order(rows, cols, q * q, q * q, fill) is None
    chain = (np.r_[k, k[1:], k[:-1]], np.r_[k, k[:-1], k[1:]])  # a tridiagonal pattern: banded
    assert radau_linalg.band_order(*chain, q * q, q * q, radau_fill.factor_entries(*chain, q * q, q * q)) is not None


def test_the_band_order_takes_the_same_steps_as_colamd(monkeypatch):
    """Only the factors' rounding differs: the same steps, values within the solve's accuracy."""
    _without_static(monkeypatch)
    model = scaling_models.reaction_diffusion(300)
    times = np.linspace(0.0, 1.0, 11)  # (the step ends differ by rounding: compare at the same times)
    options = dict(rtol=1e-6, atol=1e-8, t_eval=times, jit=False)  # (SuperLU in both: no band LU in C)
    band = dm.solve(model, (0.0, 1.0), **options)
    monkeypatch.setattr(radau_sparse, "band_orders", lambda *args: None)
    colamd = dm.solve(model, (0.0, 1.0), **options)
    for key in ("steps", "rejected_steps", "lu_decompositions", "residual_evaluations", "jacobian_evaluations"):
        assert band.stats[key] == colamd.stats[key], key
    for name in model.compile().state_names:
        np.testing.assert_allclose(band[name], colamd[name], rtol=1e-9, atol=1e-12)


def grid_pattern(K: int, seed: int | None) -> tuple:
    """The Jacobian pattern of reaction-diffusion's K points (states c_k = unknown k, rates w_k = K + k;
    equation k: c_k' from c_{k-1}, c_k, c_{k+1}, w_k; equation K + k: w_k from c_k, w_k), with the states,
    the rates and the constraints each numbered in a random order (``seed``; None: in order)."""
    rng = np.random.default_rng(seed)
    state, rate, constraint = (np.arange(K) if seed is None else rng.permutation(K) for _ in range(3))
    k = np.arange(K)
    rows = [state[k], state[k], state[k[1:]], state[k[:-1]], K + constraint[k], K + constraint[k]]
    cols = [state[k], K + rate[k], state[k[:-1]], state[k[1:]], state[k], K + rate[k]]
    return np.concatenate(rows), np.concatenate(cols)


@pytest.mark.parametrize("seed", [None, 0, 1, 2])
def test_the_band_order_of_a_grid_is_two_wide_in_any_numbering(seed):
    """The narrowest band of the pattern (c_1, w_1, c_2, w_2, ...: kl = ku = 2, 7 rows of LAPACK's
    storage) is found whatever the numbering of the states, the rates and the constraints: before, scipy's
    order gave 13 rows in the declared numbering and no band order (a band hundreds wide) in shuffled ones."""
    K = 400
    rows, cols = grid_pattern(K, seed)
    fill = radau_fill.factor_entries(rows, cols, K, 2 * K)
    order = radau_linalg.band_order(rows, cols, K, 2 * K, fill)
    assert order is not None and radau_linalg.band_storage(order, rows, cols) == 7
    assert np.array_equal(np.sort(order.columns), np.arange(2 * K)) and np.array_equal(
        np.sort(order.rows), np.arange(2 * K)
    )
    assert (order.match is None) == (seed is None)  # (equations paired with unknowns only where needed)
    # the ordered matrix is the pattern's, its rows and columns permuted: a solve in that order is A^-1 b
    A = radau_linalg.pattern_matrix(rows, cols, K, 2 * K)
    b = np.random.default_rng(7).standard_normal(2 * K)
    import scipy.sparse.linalg as splinalg

    (_, lu), singular = radau_linalg.sparse_lu(sparse.csc_matrix(A[order.rows][:, order.columns]), order)
    assert not singular.any()
    assert np.abs(lu.solve(b) - splinalg.spsolve(A.tocsc(), b)).max() < 1e-12 * np.abs(b).max()


def test_constraints_are_paired_only_where_their_block_has_a_perfect_matching():
    """No pairing without constraints, with g_z's diagonal full, or where g_z is structurally singular (an
    index-2 constraint: g_z = 0); a shuffled g_z is paired along its own nonzeros."""
    assert radau_linalg.constraint_match(np.arange(5), np.arange(5), 5, 5) is None  # (an ODE)
    rows, cols = grid_pattern(30, None)
    assert radau_linalg.constraint_match(rows, cols, 30, 60) is None
    # the pendulum at index 2: x' = u, y' = v, u' = -lam x, v' = -lam y - g, 0 = x u + y v
    pendulum = (np.array([0, 1, 2, 2, 3, 3, 4, 4, 4, 4]), np.array([2, 3, 0, 4, 1, 4, 0, 1, 2, 3]))
    assert radau_linalg.constraint_match(*pendulum, 4, 5) is None  # (g_z: the (4, 4) entry absent)
    rows, cols = grid_pattern(30, 3)
    match = radau_linalg.constraint_match(rows, cols, 30, 60)
    assert np.array_equal(match[:30], np.arange(30)) and np.array_equal(np.sort(match[30:]), np.arange(30, 60))
    pairs = set(zip(rows.tolist(), cols.tolist(), strict=True))
    assert all((match[u], u) in pairs for u in range(30, 60))  # (each variable on a row of its own constraint)


def test_many_components_keep_scipys_order():
    """Beyond PERIPHERAL_MAX_COMPONENTS components the peripheral search is not made (a Python loop each):
    scipy's order, which on decoupled 2 x 2 blocks is as narrow."""
    blocks = radau_linalg.PERIPHERAL_MAX_COMPONENTS + 1
    k = np.arange(blocks)
    rows, cols = (
        np.r_[k, k, blocks + k, blocks + k],
        np.r_[k, blocks + k, k, blocks + k],
    )  # x_k' from w_k; 0 = g(x_k, w_k)
    graph = radau_linalg.pattern_matrix(rows, cols, blocks, 2 * blocks)
    assert radau_linalg.peripheral_cuthill_mckee((abs(graph) + abs(graph).T).tocsr()) is None
    fill = radau_fill.factor_entries(rows, cols, blocks, 2 * blocks)
    order = radau_linalg.band_order(rows, cols, blocks, 2 * blocks, fill)
    assert order is not None and radau_linalg.band_storage(order, rows, cols) <= 4  # (kl, ku <= 1)


def test_a_dense_row_is_differentiated_apart_from_the_other_rows(monkeypatch):
    """A constraint reading every state (a dense row) in a model whose rates all read its variable (a dense
    column) made casadi's Jacobian take one sweep per unknown (13.5 s at 2,000 unknowns, quadratic): the
    engine's Jacobian is now made from the dense rows and the others apart, with the same pattern and values."""
    import casadi
    import sympy as sp
    from daemodel.backends.radau.compiled import casadi_functions

    from daemodel.tableau import radau_iia

    K = 300
    m = dm.Model("mean")
    y = m.states("y", K)
    (z,) = m.algebraics("z")
    m.ode(y, np.array([-y[i] * (1 + sp.Rational(i, K)) + z / 10 for i in range(K)], dtype=object))
    m.constraint(z - sum(y) / K, name="mean")
    m.initial(y=np.linspace(0.1, 1.0, K))
    compiled = m.compile()
    dae = compiled.casadi_dae()
    whole = casadi.jacobian(casadi.vertcat(dae["ode"], dae["alg"]), casadi.vertcat(dae["x"], dae["z"]))
    sizes, jacobian = [], casadi.jacobian
    monkeypatch.setattr(casadi, "jacobian", lambda e, v, *rest: sizes.append(e.numel()) or jacobian(e, v, *rest))
    functions = casadi_functions(compiled, radau_iia(3))
    assert K + 1 not in sizes and sorted(sizes) == [1, K]  # (the dense row apart)
    rows, cols = functions[-2:]
    assert np.array_equal(rows, np.asarray(whole.sparsity().get_triplet()[0]))
    assert np.array_equal(cols, np.asarray(whole.sparsity().get_triplet()[1]))
    point = np.random.default_rng(1).uniform(0.5, 1.5, 1 + K + 1 + dae["p"].numel())
    expected = casadi.Function("J", [casadi.vertcat(dae["t"], dae["x"], dae["z"], dae["p"])], [whole.nz[:]])
    assert np.array_equal(np.asarray(functions[2](point)), np.asarray(expected(point)))

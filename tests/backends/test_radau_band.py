"""The band LU in C of narrow band orders (backends/radau/band.py).

Its factors must solve every shifted system (real and complex) to rounding, call a zero pivot or a
value that is not finite singular, and give radau's default solve SuperLU's steps and Newton counts;
the memory guard counts its storage, and a wide band (a 2-D grid) keeps SuperLU.
"""

import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sparse
from daemodel.backends.radau import backend, band, linalg
from daemodel.backends.radau import sparse as radau_sparse
from daemodel.backends.radau.compiled import find_compiler
from daemodel.backends.radau.linalg import BandOrder

import daemodel as dm

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import scaling_models

needs_compiler = pytest.mark.skipif(find_compiler() is None, reason="no C compiler")


def shifted(engine, J, sigma):
    """The CSC values of ``sigma M - J`` in the engine's layout (its band order), as its _factor_shift
    makes them, and the same matrix dense in the unknowns' own order."""
    nnz = engine._csc[2]
    data = np.zeros(nnz, dtype=float if sigma.imag == 0 else complex)
    data[engine._pos_J] = -J
    data[engine._pos_M] += sigma.real if sigma.imag == 0 else sigma
    D, n = engine.D, engine.n
    dense = (
        sigma * np.diag(np.r_[np.ones(n), np.zeros(D - n)])
        - sparse.csc_matrix((J, (engine.rows, engine.cols)), shape=(D, D)).toarray()
    )
    return data, dense if sigma.imag else dense.real


def test_band_widths_of_a_pattern():
    # columns 0..3 of a 4 x 4 matrix with entries (1, 0), (3, 1) below and (0, 2) above the diagonal
    A = sparse.csc_matrix((np.ones(7), ([0, 1, 1, 3, 2, 0, 3], [0, 0, 1, 1, 2, 2, 3])), shape=(4, 4))
    assert band.band_widths(A.indices, A.indptr) == (2, 2)
    identity = sparse.eye(5, format="csc")
    assert band.band_widths(identity.indices, identity.indptr) == (0, 0)


@needs_compiler
@pytest.mark.parametrize(("family", "size"), [("reaction_diffusion", 300), ("pendulum_chain", 40)])
def test_the_band_factors_solve_every_shifted_system(first_engine, family, size):
    compiled, engine = first_engine(getattr(scaling_models, family)(size))
    order = engine._order
    assert order is not None and not isinstance(order, band.BandKernel)  # (jit=False: SuperLU in the order)
    kernel = band.band_kernel(order, *engine._csc[:2], find_compiler())
    assert kernel is not None and kernel.ldab <= band.BAND_KERNEL_MAX_LDAB
    rng = np.random.default_rng(4)
    J = engine.jacobian(0.0, np.array([compiled.y0]), np.array([compiled.z0])) * (
        1 + 0.3 * rng.random(engine.rows.size)
    )
    for sigma in engine.transform.shifts(0.01):
        data, A = shifted(engine, J, sigma)
        (kind, lu), singular = kernel.factor(data)
        assert kind == "sparse" and not singular.any() and lu.complex == bool(sigma.imag)
        b = rng.standard_normal(engine.D) + 1j * rng.standard_normal(engine.D)  # (complex on a real system too)
        exact = np.linalg.solve(A, b)
        x = lu.solve(b if sigma.imag else b.real)
        assert np.abs(x - (exact if sigma.imag else exact.real)).max() < 1e-11 * np.abs(exact).max()
        assert np.abs(lu.solve(b) - exact).max() < 1e-11 * np.abs(exact).max()
        (_, superlu), _ = engine._factor_shift(J, sigma)  # (SuperLU's factors, in the same order)
        real_or_not = b if sigma.imag else b.real  # (SuperLU's real factors take real right-hand sides)
        assert np.abs(superlu.solve(real_or_not) - lu.solve(real_or_not)).max() < 1e-11 * np.abs(exact).max()


SHIFTS = (4.0 + 0j, 3.0 + 2.0j)


def kernel_and_systems(first_engine, J_too: bool = False):
    """Reaction-diffusion's band kernel (300 cells) and ``(engine, [the values of sigma M - J])`` for a real and a
    complex shift (:data:`SHIFTS`), J at the initial values (and J, with ``J_too``)."""
    compiled, engine = first_engine(scaling_models.reaction_diffusion(300))
    kernel = band.band_kernel(engine._order, *engine._csc[:2], find_compiler())
    J = engine.jacobian(0.0, np.array([compiled.y0]), np.array([compiled.z0]))
    found = kernel, engine, [shifted(engine, J, sigma)[0] for sigma in SHIFTS]
    return (*found, J) if J_too else found


@needs_compiler
def test_the_shifted_factors_are_those_of_the_shifted_values_bit_for_bit(first_engine):
    """factor_shifted places -J and sigma in C: the same packed factors as factor() of numpy's sigma M - J (the
    values .sparse.factor_shifts made), for a real and a complex shift, and J's values of another size refused."""
    kernel, engine, _, J = kernel_and_systems(first_engine, J_too=True)
    J = J * (1 + 0.3 * np.random.default_rng(7).random(J.size))  # (entries other than the diagonal's too)
    for sigma in SHIFTS:
        data, _ = shifted(engine, J, sigma)
        (_, want), _ = kernel.factor(data)
        (_, got), singular = kernel.factor_shifted(J, sigma, engine._pos_J, engine._pos_M)
        assert not singular.any() and got.complex == (sigma.imag != 0)
        head = (2 if got.complex else 1) * kernel.ldab * kernel.D + kernel.D + 1  # (the factors' values, the pivots)
        np.testing.assert_array_equal(got.packed[:head], want.packed[:head])
        counts = [lu.packed[head:].view(np.uint8) for lu in (got, want)]  # (then the counts, the distances: the
        used = 2 * kernel.D + int(counts[1][: 2 * kernel.D].sum())  # bytes after them are a reused buffer's)
        np.testing.assert_array_equal(counts[0][:used], counts[1][:used])
        b = np.random.default_rng(8).standard_normal(kernel.D) * (1 + 1j if got.complex else 1)
        np.testing.assert_array_equal(got.solve(b), want.solve(b))
    message = f"the band factors take {J.size} Jacobian entries, got {J.size - 1}"
    with pytest.raises(ValueError, match=message):
        kernel.factor_shifted(J[:-1], SHIFTS[0], engine._pos_J, engine._pos_M)


@needs_compiler
def test_a_zero_pivot_or_a_value_not_finite_is_singular(first_engine):
    kernel, engine, systems = kernel_and_systems(first_engine)
    for data in systems:
        indptr = engine._csc[1]
        zero = data.copy()
        zero[indptr[7] : indptr[8]] = 0  # (a column of zeros: exactly singular)
        assert kernel.factor(zero)[0] == ("singular",) and kernel.factor(zero)[1].all()
        for bad in (np.nan, np.inf):
            broken = data.copy()
            broken[5] = bad
            assert kernel.factor(broken)[0] == ("singular",)
        (kind, _), singular = kernel.factor(data)  # (and the kernel factors again after them)
        assert kind == "sparse" and not singular.any()


@needs_compiler
def test_the_kernel_refuses_values_of_another_layout_and_declares_one_entry_an_argument(first_engine):
    # (its C reads N_NZ values whatever it is given: casadi's check of the buffers' sizes sees one entry each)
    kernel, _, systems = kernel_and_systems(first_engine)
    for data in systems:
        message = f"the band factors take {kernel.nnz} matrix entries, got {kernel.nnz - 1}"
        with pytest.raises(ValueError, match=message):
            kernel.factor(data[:-1])
    for function in kernel.functions.values():  # (no dense vector's row indices kept by casadi: 30 MB at 10^5)
        sizes = [function.nnz_in(k) for k in range(function.n_in())] + [function.nnz_out(0)]
        assert sizes == [1] * len(sizes)


@needs_compiler
def test_the_default_solve_factors_by_the_band_kernel_with_superlus_steps():
    """Reaction-diffusion of 600 unknowns (above jit="auto"'s compiled steps: the general path): the
    default factors in C (stats["band_lu"]), jit=False by SuperLU; the same steps, Newton iterations and
    factorisations, and the same values to rounding."""
    compiled = scaling_models.reaction_diffusion(300).compile()
    span, t_eval = scaling_models.T_SPAN["reaction_diffusion"], np.linspace(0.0, 1.0, 5)
    banded = dm.solve(compiled, span, t_eval=t_eval)
    superlu = dm.solve(compiled, span, t_eval=t_eval, jit=False)
    assert banded.stats["band_lu"].startswith("machine code (band widths 2 and 2; cache: ")
    assert "band_lu" not in superlu.stats and "compiled_cache" not in banded.stats  # (its own: no step compiled)
    for key in ("steps", "rejected_steps", "newton_iterations", "lu_decompositions", "residual_evaluations"):
        assert banded.stats[key] == superlu.stats[key], key
    for name in ("c_1", "c_150", "w_300"):
        assert np.abs(banded[name] - superlu[name]).max() < 1e-12 * np.abs(superlu[name]).max()


@needs_compiler
def test_the_memory_estimate_counts_the_band_storage(first_engine):
    compiled, engine = first_engine(scaling_models.reaction_diffusion(300))
    span = scaling_models.T_SPAN["reaction_diffusion"]
    rows, cols = radau_sparse.jacobian_pattern(compiled)
    n, D, s = engine.n, engine.D, 3
    entries = band.band_entries(engine._order, rows, cols, n, D)
    parts = backend.memory_parts(compiled, span, 1, backend.RadauOptions(rtol=1e-6, atol=1e-6, stages=s), "casadi")
    assert parts == {
        "Newton matrices (sparse)": rows.size * 8 * (s + 1) + (s + 2 * band.BAND_SPARE_BUFFERS) * entries * 16
    }
    kernel = band.band_kernel(engine._order, *engine._csc[:2], find_compiler())
    J = engine.jacobian(0.0, np.array([compiled.y0]), np.array([compiled.z0]))
    for sigma in (4.0 + 0j, 3.0 + 2.0j):
        lu = kernel.factor(shifted(engine, J, sigma)[0])[0][1]
        assert lu.packed.nbytes <= entries * 16  # (each system's buffer within what is counted for it)


@needs_compiler
@pytest.mark.parametrize("stages", [3, 5, 6])
def test_a_solve_reserves_the_band_buffers_of_one_factorisation_in_its_setup(stages):
    """A solve makes, in its setup, the band kernel's buffers for the factors of one factorisation (s = 5:
    one real and two complex systems), and keeps them: the stepper drops its factors before it factors
    anew (a stale Jacobian's too, which the tries still hold), so its integration, and a later solve's,
    factor into those and make none (before, two factorisations' buffers were reserved, since the new
    factors were made while the old ones were held: 66 MB at 10^5 unknowns where one holds 33)."""
    compiled = scaling_models.reaction_diffusion(300).compile()
    span = scaling_models.T_SPAN["reaction_diffusion"]
    first = dm.solve(compiled, span, method="radau", rtol=1e-6, atol=1e-8, stages=stages)
    assert first.stats["band_lu"].startswith("machine code")
    kernel = compiled.cached("radau-band-kernel", lambda: pytest.fail("the kernel was made by the solve"))
    # one real system a factorisation (s odd: the real block, also the error estimate's; s even: the error
    # estimate's), s // 2 complex ones
    assert [len(kernel._spare[False]), len(kernel._spare[True])] == [1, stages // 2]
    assert first.stats["factor_bytes"] == sum(buffer.nbytes for kind in (False, True) for buffer in kernel._spare[kind])
    made = {id(buffer) for kind in (False, True) for buffer in kernel._spare[kind]}
    again = dm.solve(compiled, span, method="radau", rtol=1e-6, atol=1e-8, stages=stages)
    assert again.stats["lu_decompositions"] == first.stats["lu_decompositions"] > 6
    assert {id(buffer) for kind in (False, True) for buffer in kernel._spare[kind]} == made


def test_a_wide_band_keeps_superlu():
    """A 5-point Laplacian on a 30 x 30 grid, in its reverse Cuthill-McKee order: a band ~60 wide."""
    q = 30
    k = np.arange(q * q)
    i, j = divmod(k, q)
    rows = np.concatenate([k, k[i > 0], k[i < q - 1], k[j > 0], k[j < q - 1]])
    cols = np.concatenate([k, k[i > 0] - q, k[i < q - 1] + q, k[j > 0] - 1, k[j < q - 1] + 1])
    from scipy.sparse.csgraph import reverse_cuthill_mckee

    pattern = sparse.csr_matrix((np.ones(rows.size), (rows, cols)), shape=(q * q, q * q))
    order = np.asarray(reverse_cuthill_mckee(pattern, symmetric_mode=True), dtype=np.int64)
    assert band.band_entries(BandOrder(order), rows, cols, q * q, q * q) is None
    position = np.argsort(order)
    ordered = sparse.csc_matrix((np.ones(rows.size), (position[rows], position[cols])), shape=(q * q, q * q))
    assert band.band_kernel(order, ordered.indices, ordered.indptr, find_compiler() or "cc") is None


def shuffled_reaction_diffusion(K: int, seed: int) -> dm.Model:
    """:func:`scaling_models.reaction_diffusion` with its states, algebraic variables, equations and
    constraints each declared in its own random order (the same equations, names and initial values)."""
    import math

    import sympy as sp

    rng = np.random.default_rng(seed)
    m = dm.Model(f"reaction_diffusion_shuffled_{K}")
    c = {k: m.states([f"c_{k}"])[0] for k in rng.permutation(K) + 1}
    w = {k: m.algebraics([f"w_{k}"])[0] for k in rng.permutation(K) + 1}
    D = m.parameter("D", scaling_models.DIFFUSION)
    inv_dx2 = sp.Integer(K + 1) ** 2
    padded = {0: sp.Integer(0), K + 1: sp.Integer(0), **c}
    for k in rng.permutation(K) + 1:
        m.ode(c[k], D * (padded[k - 1] - 2 * padded[k] + padded[k + 1]) * inv_dx2 - w[k])
    for k in rng.permutation(K) + 1:
        m.constraint(w[k] - c[k] ** 2 / (1 + c[k]), name=f"rate_{k}")
    m.initial(**{f"c_{k}": math.sin(math.pi * k / (K + 1)) for k in range(1, K + 1)})
    return m


def grid_reference(K: int, t_eval: np.ndarray) -> np.ndarray:
    """Reaction-diffusion's c_1..c_K at ``t_eval`` by scipy (Radau, rtol 1e-12, atol 1e-14) on its ODE
    (w substituted), shape (K, T): independent of daemodel."""
    import math

    from scipy.integrate import solve_ivp

    L = scaling_models.DIFFUSION * (K + 1) ** 2 * sparse.diags([1.0, -2.0, 1.0], [-1, 0, 1], shape=(K, K))

    def f(t, c):
        return L @ c - c * c / (1 + c)

    def jac(t, c):
        return (L - sparse.diags(c * (2 + c) / (1 + c) ** 2)).tocsc()

    c0 = np.sin(math.pi * np.arange(1, K + 1) / (K + 1))
    sol = solve_ivp(f, (0.0, 1.0), c0, method="Radau", jac=jac, t_eval=t_eval, rtol=1e-12, atol=1e-14)
    assert sol.success, sol.message
    return sol.y


@needs_compiler
@pytest.mark.parametrize("seed", [0, 1])
def test_a_shuffled_declaration_takes_the_same_narrow_band(seed):
    """Reaction-diffusion of 600 unknowns declared in random order: its constraints are paired with their
    variables before the band order (.linalg.constraint_match), so it takes the declared model's band
    (widths 2 and 2; SuperLU in COLAMD's order, before: a 44-wide band was refused), and its values match
    scipy's, by the band kernel and by SuperLU in the same order (jit=False) alike."""
    K, t_eval = 300, np.linspace(0.0, 1.0, 5)
    compiled = shuffled_reaction_diffusion(K, seed).compile()
    rows, cols = radau_sparse.jacobian_pattern(compiled)
    n, D = len(compiled.states), len(compiled.states) + len(compiled.algebraics)
    assert compiled.state_names[:3] != ("c_1", "c_2", "c_3")  # (the declaration is shuffled)
    order = radau_sparse.band_orders(compiled, rows, cols, n, D)
    assert order is not None and order.match is not None
    assert linalg.band_storage(order, rows, cols) == 7  # (2 kl + ku + 1, kl = ku = 2)
    options = backend.RadauOptions(rtol=1e-6, atol=1e-6, stages=3)  # (the memory guard counts the same band)
    declared = scaling_models.reaction_diffusion(K).compile()
    assert backend.memory_parts(compiled, (0.0, 1.0), 1, options, "casadi") == backend.memory_parts(
        declared, (0.0, 1.0), 1, options, "casadi"
    )
    banded = dm.solve(compiled, (0.0, 1.0), t_eval=t_eval, rtol=1e-8, atol=1e-8)
    superlu = dm.solve(compiled, (0.0, 1.0), t_eval=t_eval, rtol=1e-8, atol=1e-8, jit=False)
    assert banded.stats["band_lu"].startswith("machine code (band widths 2 and 2; cache: ")
    assert banded.status == superlu.status == "success"
    reference = grid_reference(K, t_eval)
    for sol in (banded, superlu):
        c = np.stack([sol[f"c_{k}"] for k in range(1, K + 1)])
        w = np.stack([sol[f"w_{k}"] for k in range(1, K + 1)])
        assert np.abs(c - reference).max() < 1e-8  # (rtol = atol = 1e-8; 4.3e-10 found)
        assert np.abs(w - reference**2 / (1 + reference)).max() < 1e-8
    for key in ("steps", "rejected_steps", "newton_iterations", "lu_decompositions"):
        assert banded.stats[key] == superlu.stats[key], key


@needs_compiler
def test_paired_band_factors_solve_real_and_complex_right_hand_sides(first_engine):
    """The band kernel of a shuffled declaration reads the right-hand side through its constraint match
    (b = rhs[match]); every shift's factors solve a real and a complex right-hand side alike, as the
    unpaired kernel does (before: a real one on complex factors raised numpy's TypeError from np.take)."""
    compiled, engine = first_engine(shuffled_reaction_diffusion(60, 0))
    order = engine._order
    assert order is not None and order.match is not None and not isinstance(order, band.BandKernel)
    kernel = band.band_kernel(order, *engine._csc[:2], find_compiler())
    assert kernel is not None and kernel.match is not None
    rng = np.random.default_rng(5)
    J = engine.jacobian(0.0, np.array([compiled.y0]), np.array([compiled.z0])) * (
        1 + 0.3 * rng.random(engine.rows.size)
    )
    for sigma in engine.transform.shifts(0.01):
        data, A = shifted(engine, J, sigma)
        (kind, lu), singular = kernel.factor(data)
        assert kind == "sparse" and not singular.any()
        b = rng.standard_normal(engine.D) + 1j * rng.standard_normal(engine.D)
        for rhs in (b.real, b):
            exact = np.linalg.solve(A, rhs)
            assert np.abs(lu.solve(rhs) - exact).max() < 1e-11 * np.abs(exact).max()


def test_the_kernel_indexes_the_band_in_int32_where_it_fits():
    # (LDAB x D entries: 7 x 306,783,378 = 2^31 - 1 is int32's largest, one unknown more is not)
    assert band.band_index(306_783_378, 7) == np.int32 and band.band_index(306_783_379, 7) == np.int64
    assert "#define INDEX int\n" in band.band_source(1000, 2998, 2, 2)
    assert "#define INDEX long long int\n" in band.band_source(306_783_379, 10**9, 2, 2)


@needs_compiler
def test_a_jacobian_without_entries_is_factored_by_the_band_kernel():
    """x_k' = p k / K (300 states, J has no entry: sigma M - J is sigma I): the shifted factors take J's values,
    none, which casadi refused as a buffer under its one entry's 8 bytes (RuntimeError 'Buffer is not large
    enough', where the CSC values of sigma M, D of them, were given before); x_k(1) = p k / K to rounding."""
    K = 300
    m = dm.Model("no_jacobian_entries")
    x = m.states([f"x_{k}" for k in range(1, K + 1)])
    p = m.parameter("p", 2.0)
    for k in range(1, K + 1):
        m.ode(x[k - 1], p * k / K)
    m.initial(**{f"x_{k}": 0.0 for k in range(1, K + 1)})
    compiled = m.compile()
    assert radau_sparse.jacobian_pattern(compiled)[0].size == 0
    sol = dm.solve(compiled, (0.0, 1.0), rtol=1e-8, atol=1e-10)
    assert sol.stats["band_lu"].startswith("machine code (band widths 0 and 0; cache: ")
    assert sol.status == "success"
    for k in (1, 150, 300):
        assert abs(sol[f"x_{k}"][-1] - 2.0 * k / K) < 1e-14


@needs_compiler
def test_the_shifted_factors_call_the_same_systems_singular_and_take_either_sign_of_a_shift(first_engine):
    """factor_shifted against factor() of numpy's values (bit for bit where factored): a complex shift and its
    conjugate, and J with an algebraic unknown's column zero (singular: no M entry there), with a NaN or an
    infinity (singular: not finite)."""
    kernel, engine, _, J = kernel_and_systems(first_engine, J_too=True)
    zero_column = np.where(engine.cols == engine.n + 7, 0.0, J)
    variants = {"J": J, "zero column": zero_column}
    variants |= {f"{bad}": np.where(np.arange(J.size) == 11, bad, J) for bad in (np.nan, -np.inf)}
    for sigma in (4.0 + 0j, 3.0 + 2.0j, 3.0 - 2.0j):
        for label, values in variants.items():
            (want, *factors), want_singular = kernel.factor(shifted(engine, values, sigma)[0])
            (got, *ours), singular = kernel.factor_shifted(values, sigma, engine._pos_J, engine._pos_M)
            assert (
                (got, bool(singular[0]))
                == (want, bool(want_singular[0]))
                == (("sparse", False) if label == "J" else ("singular", True))
            ), (label, sigma)
            if got == "sparse":
                head = (2 if sigma.imag else 1) * kernel.ldab * kernel.D + kernel.D + 1
                np.testing.assert_array_equal(ours[0].packed[:head], factors[0].packed[:head])


@needs_compiler
def test_the_models_kernel_factors_only_the_layout_it_was_made_for(first_engine):
    """A model's band kernel is made once, from its shifted systems' first layout; a layout of another pattern
    (here J without one entry) gets SuperLU in the same band order, whose factors solve its systems (before: the
    kernel, its positions those of the first layout, placed J's values wrongly: a wrong matrix, no error)."""
    compiled, engine = first_engine(scaling_models.reaction_diffusion(150))  # (jit=False: no kernel made yet)
    rows, cols, n, D = engine.rows, engine.cols, engine.n, engine.D
    first = radau_sparse.shifted_layout(compiled, rows, cols, n, band=[])
    assert isinstance(first[0], band.BandKernel) and first[0].made_for(*first[1][:2])
    keep = np.delete(np.arange(rows.size), np.flatnonzero(rows != cols)[3])  # (an entry off M's diagonal)
    other = radau_sparse.shifted_layout(compiled, rows[keep], cols[keep], n, band=[])
    assert other[1][2] == first[1][2] - 1 and not first[0].made_for(*other[1][:2])
    assert isinstance(other[0], BandOrder) and other[0].same(first[0].order)
    J = 1 + np.random.default_rng(9).random(keep.size)
    b = np.random.default_rng(10).standard_normal(D)
    for sigma in SHIFTS:
        factors, singular = radau_sparse.factor_shifts(J, (sigma,), *other[1:], other[0])
        kind, lu = factors[sigma]
        A = (
            sigma * np.diag(np.r_[np.ones(n), np.zeros(D - n)])
            - sparse.csc_matrix((J, (rows[keep], cols[keep])), shape=(D, D)).toarray()
        )
        exact = np.linalg.solve(A, b)
        assert kind == "sparse" and not singular.any()
        assert np.abs(lu.solve(b) - exact).max() < 1e-11 * np.abs(exact).max()


@needs_compiler
def test_the_kernel_in_int64_solves_bit_for_bit_as_in_int32(monkeypatch):
    """The int64 branch of the kernel's positions and order (LDAB x D past 2^31: 3 x 10^8 unknowns at LDAB 7),
    forced at 300 unknowns: its own library (INDEX long long int), and the same solve, bit for bit."""
    span, options = (0.0, 1.0), {"rtol": 1e-6, "atol": 1e-8, "stages": 5, "t_eval": np.linspace(0.0, 1.0, 5)}
    narrow = dm.solve(scaling_models.reaction_diffusion(150).compile(), span, **options)
    monkeypatch.setattr(band, "band_index", lambda D, ldab: np.int64)
    compiled = scaling_models.reaction_diffusion(150).compile()
    wide = dm.solve(compiled, span, **options)
    kernel = compiled.cached("radau-band-kernel", lambda: pytest.fail("the kernel was made by the solve"))
    assert kernel.positions.dtype == kernel.order_values.dtype == kernel._at[3].dtype == np.int64
    assert wide.stats["band_lu"].startswith("machine code (band widths 2 and 2; cache: ")
    for key in ("steps", "rejected_steps", "newton_iterations", "lu_decompositions"):
        assert wide.stats[key] == narrow.stats[key], key
    for name in ("c_1", "c_75", "w_150"):
        np.testing.assert_array_equal(wide[name], narrow[name])


@needs_compiler
@pytest.mark.parametrize("in_place", [False, True], ids=["copies", "in-place"])
@pytest.mark.parametrize("paired", [False, True], ids=["own-order", "matched"])
def test_a_solve_writes_its_solution_into_out_which_may_be_its_right_hand_side(
    first_engine, monkeypatch, paired, in_place
):
    """BandLU.solve(rhs, out=) and OrderedLU.solve(rhs, out=) give the bits of the solution they return without out,
    in out, also where out is rhs itself (Newton's increment solves in place: .transform.IncrementBuffers), with the
    band solver's own arrays (few unknowns) and on the caller's (band.BAND_SOLVE_IN_PLACE_MIN); a complex
    right-hand side on real factors by parts; an out of another dtype or shape is refused by name."""
    monkeypatch.setattr(band, "BAND_SOLVE_IN_PLACE_MIN", 0 if in_place else 10**9)
    model = shuffled_reaction_diffusion(60, 0) if paired else scaling_models.reaction_diffusion(60)
    compiled, engine = first_engine(model)
    kernel = band.band_kernel(engine._order, *engine._csc[:2], find_compiler())
    assert (kernel.match is not None) == paired
    rng = np.random.default_rng(11)
    J = engine.jacobian(0.0, np.array([compiled.y0]), np.array([compiled.z0])) * (
        1 + 0.3 * rng.random(engine.rows.size)
    )
    for sigma in SHIFTS:
        data, A = shifted(engine, J, sigma)
        (_, lu), _ = kernel.factor(data)
        (_, superlu), _ = engine._factor_shift(J, sigma)
        b = rng.standard_normal(engine.D) + 1j * rng.standard_normal(engine.D)
        for factors in (lu, superlu):
            for rhs in (b, b.real) if sigma.imag else (b.real,):
                want = factors.solve(rhs)
                assert np.abs(want - np.linalg.solve(A, rhs)).max() < 1e-11 * np.abs(want).max()
                out = np.full_like(want, np.nan)
                assert factors.solve(rhs, out=out) is out
                np.testing.assert_array_equal(out, want)
                if rhs.dtype == want.dtype:
                    same = rhs.copy()
                    assert factors.solve(same, out=same) is same
                    np.testing.assert_array_equal(same, want)
            wrong = np.empty(engine.D, dtype=complex if not sigma.imag else float)
            with pytest.raises(ValueError, match=r"a solve's out= is (complex128|float64) \(\d+,\), its solution"):
                factors.solve(b if sigma.imag else b.real, out=wrong)
    (_, lu), _ = kernel.factor(shifted(engine, J, SHIFTS[0])[0])
    out = np.empty(engine.D, dtype=complex)
    np.testing.assert_array_equal(lu.solve(b, out=out), lu.solve(b.real) + 1j * lu.solve(b.imag))  # (by parts)
    assert (kernel.solver(False).b is None) == in_place
    strided = np.repeat(b.real, 2)[::2]  # (not contiguous: read through a contiguous copy)
    np.testing.assert_array_equal(lu.solve(strided), lu.solve(b.real))
    with pytest.raises(ValueError, match=r"the band factors solve for right-hand sides of shape \(\d+,\), got \(3,\)"):
        lu.solve(np.zeros(3))
    solver, given = kernel.solver(False), (np.zeros(engine.D), np.zeros(engine.D))
    with pytest.raises(ValueError, match=r"band_solve: b and out are given to a solver without arrays of its own, and"):
        solver(memoryview(lu.packed), *(given if not in_place else ()))  # (unbound, the C would write nothing)

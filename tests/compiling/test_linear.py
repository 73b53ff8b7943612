"""The algebraic Newton on sparse Jacobians (linear.py): the same roots and flags as the dense path,
singular systems named at large m, and initialisation at large m without a dense m x m."""

import tracemalloc

import numpy as np
import pytest
import scipy.sparse
import sympy as sp

from daemodel import errors as E
from daemodel.compiling.init import initialise, solve_algebraic
from daemodel.compiling.initial_states import initial_states
from daemodel.compiling.linear import DENSE_FALLBACK_MAX, SPARSE_MIN_SIZE, SparseStack, factor
from daemodel.compiling.structure import DENSE_RANK_MAX, check_rank


def _chain(m: int, B: int, coupling: float = 0.3):
    """``F_k = x_k + x_k^3 / 3 + coupling (x_{k-1} x_k + x_{k+1}) - b_k``: a nonlinear tridiagonal
    system with its Jacobian as nonzeros, dense or sparse from the same numbers."""
    rng = np.random.default_rng(0)
    b = rng.normal(size=(B, m))
    k = np.arange(m)
    rows = np.concatenate([k, k[1:], k[:-1]])
    cols = np.concatenate([k, k[:-1], k[1:]])

    def F(x):
        left = np.concatenate([np.zeros((len(x), 1)), x[:, :-1]], axis=1)
        right = np.concatenate([x[:, 1:], np.zeros((len(x), 1))], axis=1)
        return x + x**3 / 3 + coupling * (left * x + right) - b[: len(x)]

    def values(x):
        left = np.concatenate([np.zeros((len(x), 1)), x[:, :-1]], axis=1)
        diagonal = 1 + x**2 + coupling * left
        return np.concatenate([diagonal, coupling * x[:, 1:], np.full((len(x), m - 1), coupling)], axis=1)

    def sparse(x):
        return SparseStack(rows, cols, values(x), m)

    def dense(x):
        return sparse(x).dense()

    return F, dense, sparse


@pytest.mark.parametrize("m", [SPARSE_MIN_SIZE, 2 * SPARSE_MIN_SIZE])
def test_sparse_newton_finds_the_dense_root(m):
    F, dense, sparse = _chain(m, B=3)
    x0 = np.zeros((3, m))
    a, b = solve_algebraic(F, dense, x0), solve_algebraic(F, sparse, x0)
    assert a.converged.all() and b.converged.all()
    np.testing.assert_array_equal(a.singular, b.singular)
    np.testing.assert_allclose(b.x, a.x, rtol=0, atol=1e-12)
    assert np.abs(F(b.x)).max() < 1e-12 and a.iterations == b.iterations


def test_sparse_stack_products_match_dense():
    _, dense, sparse = _chain(50, B=2)
    x = np.random.default_rng(1).normal(size=(2, 50))
    J = dense(x)
    np.testing.assert_allclose(sparse(x).abs_product(x), np.einsum("bij,bj->bi", np.abs(J), np.abs(x)), rtol=1e-15)
    rhs = np.random.default_rng(2).normal(size=(2, 50))
    np.testing.assert_allclose(sparse(x).solve(rhs), np.linalg.solve(J, rhs[..., None])[..., 0], rtol=1e-10)
    A = sparse(x).matrix(0)
    condition = np.linalg.norm(A.toarray(), 1) * np.linalg.norm(np.linalg.inv(A.toarray()), 1)
    assert factor(A)[1] == pytest.approx(condition, rel=1e-6)  # onenormest is exact at this size


@pytest.mark.parametrize("m", [SPARSE_MIN_SIZE, DENSE_FALLBACK_MAX + 100])
def test_singular_sparse_jacobian_flags_as_dense(m):
    """Two equations on x0 + x1 that contradict each other: J is singular everywhere, Newton cannot
    converge; the sparse path says so as the dense one does (pinv below DENSE_FALLBACK_MAX, LSQR above)."""
    k = np.arange(2, m)
    rows = np.concatenate([[0, 0, 1, 1], k])
    cols = np.concatenate([[0, 1, 0, 1], k])

    def F(x):
        return np.concatenate([x[:, :1] + x[:, 1:2] - 1, x[:, :1] + x[:, 1:2] - 2, x[:, 2:] ** 2 - 4], axis=1)

    def sparse(x):
        return SparseStack(rows, cols, np.concatenate([np.ones((len(x), 4)), 2 * x[:, 2:]], axis=1), m)

    x0 = np.ones((1, m))
    b = solve_algebraic(F, sparse, x0)
    assert not b.converged[0] and b.singular[0]
    np.testing.assert_allclose(b.x[0, :2], [0.75, 0.75], atol=1e-9)  # the least-squares point x0 + x1 = 1.5
    np.testing.assert_allclose(b.x[0, 2:], 2.0, rtol=1e-12)
    if m <= 1000:  # the dense path on the same numbers: the same iterate and flags
        a = solve_algebraic(F, lambda x: sparse(x).dense(), x0)
        assert not a.converged[0] and a.singular[0]
        np.testing.assert_allclose(b.x, a.x, atol=1e-12)


class _Row:  # the attributes check_rank's messages read
    def __init__(self, k):
        self.label, self.index = f"constraint 'r{k}' (#{k})", 1


def test_check_rank_names_the_singular_block_at_large_m():
    m = DENSE_RANK_MAX + 500
    symbols = [sp.Symbol(f"w{j}") for j in range(m)]
    rows = [_Row(k) for k in range(m)]
    A = scipy.sparse.lil_matrix((m, m))
    A.setdiag(2.0)
    check_rank(A.tocsc(), rows, symbols, 0.0)  # regular: passes
    A[7, 7], A[7, 1234], A[1234, 7], A[1234, 1234] = 1.0, 2.0, 3.0, 6.0  # a singular 2 x 2 block
    with pytest.raises(E.SingularSystemError, match=r"'r7' \(#7\), constraint 'r1234'.*'w7', 'w1234'.*singular value"):
        check_rank(A.tocsc(), rows, symbols, 0.0)
    # one coupled block of all m rows (tridiagonal) with rows 0 and 1 equal: named by its rows
    T = scipy.sparse.diags([np.ones(m - 1), np.full(m, 4.0), np.ones(m - 1)], [-1, 0, 1], format="lil")
    T[0, 0], T[0, 1], T[1, 0], T[1, 1], T[1, 2] = 1.0, 1.0, 1.0, 1.0, 0.0
    T[2, 1] = 1.0
    with pytest.raises(E.SingularSystemError, match=rf"'r0' \(#0\).*\(of {m}; the first 12 listed\).*block of {m}"):
        check_rank(T.tocsc(), rows, symbols, 0.0)


def test_initialise_at_large_m_without_a_dense_jacobian(diffusion_grid):
    """z0 exact; initialisation again (its functions made) and a batch of initial states: their
    memory peaks far below one dense m x m (32 MB)."""
    K = 2000
    model = diffusion_grid(K)
    compiled = model.compile()
    c = np.sin(np.pi * np.arange(1, K + 1) / (K + 1))
    np.testing.assert_allclose(compiled.z0, c**2 / (1 + c), rtol=1e-14, atol=0)
    p = np.array([model.parameter_values[q.name] for q in compiled.parameters], dtype=float)
    initial_states(compiled, y0=c)  # (its functions made)
    tracemalloc.start()
    values = initialise(
        compiled.numeric,
        list(compiled.constraints),
        [],
        compiled.t0,
        dict(zip(compiled.state_names, compiled.y0, strict=True)),
        p,
        False,
    )
    states = initial_states(compiled, y0=np.stack([c, 0.5 * c]))
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < K * K * 8 / 20
    np.testing.assert_array_equal(values.z0, compiled.z0)
    np.testing.assert_allclose(states.z0, [c**2 / (1 + c), (c / 2) ** 2 / (1 + c / 2)], rtol=1e-14, atol=0)


def test_singular_initial_jacobian_at_large_m_is_named(diffusion_grid):
    """Structurally regular, numerically singular at t0: u + v and 2 u + 2 v."""
    K = SPARSE_MIN_SIZE
    model = diffusion_grid(K)
    y = model.states(["p", "q"])
    u, v = model.algebraics(["u", "v"])
    model.ode(y[0], -u)
    model.ode(y[1], -v)
    model.constraint(u + v - y[0], name="sum")
    model.constraint(2 * u + 2 * v * y[1] - 2 * y[0], name="twice")
    model.initial(p=1.0, q=1.0)
    with pytest.raises(E.SingularSystemError, match=r"constraint 'sum'.*'twice'.*do not determine.*'u', 'v'"):
        model.compile()


def test_a_time_limit_inside_a_sparse_factorisation_is_not_a_singular_matrix(monkeypatch):
    """A time limit's TimeLimitError (a RuntimeError too), raised as SuperLU returns, was taken for
    "Factor is exactly singular": the factorisation said (None, inf), the solve fell back to a
    pseudo-inverse and went on."""
    import scipy.sparse.linalg

    def struck(*_, **__):
        raise E.TimeLimitError("stop here")

    monkeypatch.setattr(scipy.sparse.linalg, "splu", struck)
    A = scipy.sparse.identity(3, format="csc")
    with pytest.raises(E.TimeLimitError, match=r"^stop here$"):
        factor(A)
    with pytest.raises(E.TimeLimitError, match=r"^stop here$"):
        SparseStack(A.tocoo().row, A.tocoo().col, np.ones((1, 3)), 3).solve(np.ones((1, 3)))

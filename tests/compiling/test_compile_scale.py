"""Compile at scale: the sparse structure, derivative and initialisation paths give the same results
as the dense ones, checked against independent computations (numpy, closed forms, sympy's diff).

Sizes are chosen so that the sparse paths are taken (algebraic blocks of at least
``linear.BLOCK_MIN_SIZE``); the tests check numbers and messages, never timings.
"""

import numpy as np
import pytest
import sympy as sp

import daemodel as dm
from daemodel import errors as E
from daemodel.compiling.init import NumericSystem, jacobian_entries
from daemodel.compiling.initial_states import initial_states
from daemodel.compiling.linear import BLOCK_MIN_SIZE, least_squares, square_blocks
from daemodel.compiling.structure import Differentiator, check_rank
from daemodel.compiling.zero_test import is_zero

GRAVITY = 9.81


# ---- model families (the benchmark's families, written here so that the tests stand alone) ----
def reaction_diffusion(K: int, D: float = 0.1) -> dm.Model:
    """c_k' = D (c_{k-1} - 2 c_k + c_{k+1}) / dx^2 - w_k, 0 = w_k - c_k^2 / (1 + c_k): index 1."""
    m = dm.Model(f"grid{K}")
    c = m.states([f"c{k}" for k in range(K)])
    w = m.algebraics([f"w{k}" for k in range(K)])
    diffusion = m.parameter("D", D)
    padded = (0, *c, 0)
    for k in range(K):
        m.ode(c[k], diffusion * (padded[k] - 2 * padded[k + 1] + padded[k + 2]) * (K + 1) ** 2 - w[k])
        m.constraint(w[k] - c[k] ** 2 / (1 + c[k]), name=f"rate{k}")
    m.initial(**{f"c{k}": np.sin(np.pi * (k + 1) / (K + 1)) for k in range(K)})
    return m


def chain_state(N: int, angle: float = 0.6, omega: float = 0.8):
    """Positions of a straight chain at ``angle`` below the horizontal, rotating rigidly at ``omega``."""
    k = np.arange(1, N + 1)
    x, y = k * np.cos(angle), -k * np.sin(angle)
    return x, y, -omega * y, omega * x  # v = omega e_z x r: every rod's velocity constraint holds


def pendulum_chain(N: int) -> dm.Model:
    """N planar pendulums in a chain, Cartesian coordinates, unit masses and rods: index 3."""
    m = dm.Model(f"chain{N}")
    x, y = m.states([f"x{i}" for i in range(N)]), m.states([f"y{i}" for i in range(N)])
    u, v = m.states([f"u{i}" for i in range(N)]), m.states([f"v{i}" for i in range(N)])
    lam = m.algebraics([f"lam{i}" for i in range(N)])
    px, py = (0, *x), (0, *y)
    for i in range(N):
        fx = -lam[i] * (px[i + 1] - px[i]) + (lam[i + 1] * (px[i + 2] - px[i + 1]) if i + 1 < N else 0)
        fy = -lam[i] * (py[i + 1] - py[i]) + (lam[i + 1] * (py[i + 2] - py[i + 1]) if i + 1 < N else 0)
        m.ode(x[i], u[i])
        m.ode(y[i], v[i])
        m.ode(u[i], fx)
        m.ode(v[i], fy - GRAVITY)
    for i in range(N):
        m.constraint((px[i + 1] - px[i]) ** 2 + (py[i + 1] - py[i]) ** 2 - 1, name=f"rod{i}")
    xs, ys, us, vs = chain_state(N)
    m.initial(**{f"{n}{i}": float(a[i]) for n, a in zip("xyuv", (xs, ys, us, vs), strict=True) for i in range(N)})
    return m


def sphere_start(P: int):
    """Points spread on the unit sphere and tangent velocities."""
    i = np.arange(P) + 0.5
    z = 1 - 2 * i / P
    r = np.sqrt(1 - z * z)
    phi = np.pi * (3 - np.sqrt(5)) * i
    x = np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)
    spin = np.stack([np.sin(1.7 * i), np.cos(2.3 * i), 0.5 + 0 * i], axis=1)
    return x, 0.5 * np.cross(spin, x)


def sphere_particles(P: int, eps: float = 0.05) -> dm.Model:
    """P particles on the unit sphere, all-pairs softened repulsion, GGL index-2 form (dense coupling)."""
    m = dm.Model(f"sphere{P}")
    X = [m.states([f"px{i}", f"py{i}", f"pz{i}"]) for i in range(P)]
    V = [m.states([f"vx{i}", f"vy{i}", f"vz{i}"]) for i in range(P)]
    lam, mu = m.algebraics([f"lam{i}" for i in range(P)]), m.algebraics([f"mu{i}" for i in range(P)])
    soft = m.parameter("eps", eps)
    for i in range(P):
        for a in range(3):
            force = sum(
                (X[i][a] - X[j][a]) * (sum((X[i][b] - X[j][b]) ** 2 for b in range(3)) + soft) ** sp.Rational(-3, 2)
                for j in range(P)
                if j != i
            )
            m.ode(X[i][a], V[i][a] - mu[i] * X[i][a])
            m.ode(V[i][a], force - lam[i] * X[i][a])
        m.constraint(sum(X[i][a] ** 2 for a in range(3)) - 1, name=f"sphere{i}")
        m.constraint(sum(X[i][a] * V[i][a] for a in range(3)), name=f"tangent{i}")
    x, v = sphere_start(P)
    start = {f"p{n}{i}": float(x[i, a]) for i in range(P) for a, n in enumerate("xyz")}
    start.update({f"v{n}{i}": float(v[i, a]) for i in range(P) for a, n in enumerate("xyz")})
    m.initial(**start)
    return m


# ---- consistent initial values against independent computations -------------------------------
def test_large_index1_grid_z0_is_the_closed_form():
    c = reaction_diffusion(200).compile()
    assert c.index == 1 and len(c.algebraics) == 200
    cs = c.y0
    np.testing.assert_allclose(c.z0, cs**2 / (1 + cs), rtol=1e-14, atol=0)


def _chain_tensions(x, y, u, v) -> np.ndarray:
    """lam from rod_i'' = 2 |w_i|^2 + 2 d_i . (a_i - a_{i-1}) = 0, solved in numpy.

    d_i = r_i - r_{i-1} and w_i = v_i - v_{i-1} (mass 0 fixed at the origin); the accelerations
    a_i = -lam_i d_i + lam_{i+1} d_{i+1} + g are linear in lam.
    """
    N = len(x)
    r, vel = np.stack([x, y], axis=1), np.stack([u, v], axis=1)
    d, w = np.diff(r, axis=0, prepend=0.0), np.diff(vel, axis=0, prepend=0.0)
    A = np.zeros((N, 2, N))  # a_i = A_i lam + g
    for i in range(N):
        A[i, :, i] -= d[i]
        if i + 1 < N:
            A[i, :, i + 1] += d[i + 1]
    gravity = np.array([0.0, -GRAVITY])
    M, rhs = np.zeros((N, N)), np.zeros(N)
    for i in range(N):
        relative = A[i] - (A[i - 1] if i else 0)  # gravity cancels in a_i - a_{i-1} but for i = 0
        M[i] = 2 * d[i] @ relative
        rhs[i] = -2 * w[i] @ w[i] - (2 * d[i] @ gravity if i == 0 else 0.0)
    return np.linalg.solve(M, rhs)


def test_large_index3_chain_z0_matches_numpy():
    N = 24
    c = pendulum_chain(N).compile()
    assert c.index == 3 and c.constraint_index["rod5"] == 3
    np.testing.assert_allclose(c.z0, _chain_tensions(*chain_state(N)), rtol=1e-10, atol=1e-10)


def _sphere_multipliers(P: int, eps: float = 0.05):
    x, v = sphere_start(P)
    d = x[:, None, :] - x[None, :, :]
    factor = (np.sum(d**2, axis=-1) + eps) ** -1.5
    np.fill_diagonal(factor, 0.0)
    force = np.einsum("ij,ija->ia", factor, d)
    norm2 = np.sum(x * x, axis=1)
    mu = np.sum(x * v, axis=1) / norm2  # sphere' = 2 x . (v - mu x) = 0
    lam = (np.sum((v - mu[:, None] * x) * v, axis=1) + np.sum(x * force, axis=1)) / norm2  # tangent' = 0
    return lam, mu


def test_dense_index2_particles_z0_matches_numpy():
    P = 10
    c = sphere_particles(P).compile()
    assert c.index == 2 and len(c.algebraics) == 2 * P >= BLOCK_MIN_SIZE
    lam, mu = _sphere_multipliers(P)
    np.testing.assert_allclose(c.z0, np.concatenate([lam, mu]), rtol=1e-12, atol=1e-12)


def test_large_chain_repair_is_the_least_change_projection():
    N = 20
    m = pendulum_chain(N)
    x, y, u, v = chain_state(N)
    bent = {f"x{i}": float(x[i] + 0.01 * np.sin(i)) for i in range(N)}
    m.initial(**bent)
    with pytest.raises(E.InconsistentInitialStateError, match=r"violates constraint 'rod1' \(#82\): rod1 = 0.01396"):
        m.compile()
    c = m.compile(repair=True)
    assert c.notes[0].startswith("repaired y0 (least change")
    X, Y, U, V = np.split(c.y0, 4)
    dx, dy = np.diff(np.concatenate([[0.0], X])), np.diff(np.concatenate([[0.0], Y]))
    du, dv = np.diff(np.concatenate([[0.0], U])), np.diff(np.concatenate([[0.0], V]))
    assert np.max(np.abs(dx**2 + dy**2 - 1)) < 1e-12 and np.max(np.abs(dx * du + dy * dv)) < 1e-12
    # least change: y - y_given lies in the row space of the constraint Jacobian (numpy, by hand)
    given = np.concatenate([x + 0.01 * np.sin(np.arange(N)), y, u, v])
    C = np.zeros((2 * N, 4 * N))
    for i in range(N):
        for col, value in ((i, 2 * dx[i]), (N + i, 2 * dy[i])):
            C[i, col] += value
            if i:
                C[i, col - 1] -= value
        for col, value in ((i, du[i]), (N + i, dv[i]), (2 * N + i, dx[i]), (3 * N + i, dy[i])):
            C[N + i, col] += value
            if i:
                C[N + i, col - 1] -= value
    moved = c.y0 - given
    coef = np.linalg.lstsq(C.T, moved, rcond=None)[0]
    assert np.linalg.norm(moved) > 1e-3 and np.linalg.norm(C.T @ coef - moved) < 1e-10
    np.testing.assert_allclose(c.z0, _chain_tensions(X, Y, U, V), rtol=1e-9, atol=1e-9)  # z0 follows the repair


def test_batch_of_initial_states_on_a_large_model():
    c = reaction_diffusion(60).compile()
    Y = np.stack([c.y0, 0.5 * c.y0, 2.0 * c.y0])
    states = initial_states(c, y0=Y)
    np.testing.assert_allclose(states.z0, Y**2 / (1 + Y), rtol=1e-14, atol=0)


def _flat(coupled: bool) -> dm.Model:
    """0 = (c_k - 1/2) w_k - (c_k - 1/2)^2 [+ c_k w_(k+1) / 100, a cycle]: g_z's row 7 vanishes at c_7 = 1/2."""
    K = 2 * BLOCK_MIN_SIZE
    m = dm.Model("flat")
    c = m.states([f"c{k}" for k in range(K)])
    w = m.algebraics([f"w{k}" for k in range(K)])
    for k in range(K):
        m.ode(c[k], -w[k])
        cycle = c[k] * w[(k + 1) % K] / 100 if coupled else 0
        m.constraint((c[k] - 0.5) * w[k] - (c[k] - 0.5) ** 2 + cycle, name=f"r{k}")
    m.initial(**{f"c{k}": 0.5 if k == 7 else 1.0 + k / K for k in range(K)})
    return m


def test_singular_iteration_matrix_of_a_large_model_names_the_culprit():
    m = _flat(coupled=True)
    # row r7 of g_z is (c7 - 0.5) at w7 and c7 / 100 at w8: singular only through the whole cycle,
    # so the block split keeps one block and the whole-matrix message names it
    with pytest.raises(E.SingularSystemError, match=r"g_z is singular at t=0 \(smallest singular value"):
        m.compile()


def test_singular_block_names_its_constraint_and_variable():
    m = _flat(coupled=False)
    with pytest.raises(
        E.SingularSystemError,
        match=r"the constraint\(s\) constraint 'r7' \(#16\) do not determine the algebraic variable\(s\) 'w7': "
        r"g_z is singular at t=0 \(smallest singular value .*, largest ",
    ):
        m.compile()


# ---- the pieces --------------------------------------------------------------------------------
x, y, z, t = sp.symbols("x y z t")
EXPRESSIONS = [
    x**2 + 3 * x * y - y**3 / x,
    (x - y) ** 2 + (x + 2 * y) ** 2 - 1,
    x * (y - z * (x - 1)) * (2 - x) ** 3,
    sp.sqrt(x**2 + y**2) + (x * y + 1) ** sp.Rational(-3, 2),
    x**y + y**x + sp.exp(x * y) * sp.sin(x - t),
    sp.Piecewise((x**2, y > 0), (sp.cos(x), True)) + sp.atan2(y, x),
    sp.erf(x * z) - sp.log(1 + x**2) * sp.tanh(y),
    2.5 * x * (0.1 * y + x) ** 2 - x / (y + 0.3),
    sp.Max(x, y) * x + sp.Abs(y - 1),
    -(x - y) * (x + y) * z + x * y * z,
]


def _real_diff(expr, s):
    """sympy's derivative with every symbol declared real (|u|' = sign(u) u', not in re(u) and im(u))."""
    real = {v: sp.Symbol(v.name, real=True) for v in (*expr.free_symbols, s)}
    return sp.diff(expr.xreplace(real), real[s]).xreplace({r: v for v, r in real.items()})


@pytest.mark.parametrize("expr", EXPRESSIONS, ids=range(len(EXPRESSIONS)))
def test_differentiator_gives_sympys_derivatives(expr):
    calculus = Differentiator()
    assert calculus.free_symbols(expr) == expr.free_symbols
    for s in (x, y, z, t):
        # (Abs of real values: sympy's derivative for real symbols; the others as sympy differentiates them)
        assert calculus.diff(expr, s) == (_real_diff(expr, s) if expr.has(sp.Abs) else sp.diff(expr, s))
        assert calculus.depends(expr, s) == (s in expr.free_symbols and sp.expand(sp.diff(expr, s)) != 0)


@pytest.mark.parametrize("expr", [sp.Abs(x * y - 1), sp.sign(x - y) * x, sp.floor(2 * x) + y, sp.ceiling(x) * x])
def test_differentiator_differentiates_abs_sign_and_floor_as_real_functions(expr):
    """sympy's derivatives of Abs, sign, floor and ceiling of symbols not declared real hold Derivative nodes
    (Derivative(im(u), u), Derivative(sign(u), u)) that no printer prints: the index-1 DAE z |z| + z = x and
    sensitivities to k through Abs(k) failed with sympy's PrintMethodNotImplementedError.  Real values: |u|' =
    sign(u) u', and the steps are constant between their jumps."""
    calculus = Differentiator()
    for s in (x, y):
        derivative = calculus.diff(expr, s)
        assert not derivative.has(sp.Derivative, sp.re, sp.im)
        values = {x: 0.7, y: -1.3}
        step = 1e-7
        above, below = (float(expr.subs({**values, s: values[s] + d})) for d in (step, -step))
        numeric = above - below
        assert abs(float(derivative.subs(values)) - numeric / (2 * step)) < 1e-6


@pytest.mark.parametrize(
    "expr",
    [(x + 1) ** 2 - x**2 - 2 * x - 1, x * y - 1, 0.1 * (x + 1) ** 2 - 0.1 * x**2 - 0.2 * x - 0.1, sp.sin(x) - x, x - x],
)
def test_zero_test_agrees_with_expansion(expr):
    assert is_zero(expr) == (sp.expand(expr) == 0)


def test_alias_that_needs_expansion_is_found_at_scale():
    m = dm.Model("aliases")
    K = 40
    c = m.states([f"c{k}" for k in range(K)])
    w = m.algebraics([f"w{k}" for k in range(K)])
    q = m.algebraics([f"q{k}" for k in range(K)])
    for k in range(K):
        m.ode(c[k], -w[k] - q[k])
        m.constraint(w[k] - c[k] ** 2 / (1 + c[k]), name=f"rate{k}")
        # q_k = c_k once expanded: an alias only the expansion reveals
        m.constraint(q[k] - c[k] + (c[k] + 1) ** 2 - c[k] ** 2 - 2 * c[k] - 1, name=f"same{k}")
    m.initial(**{f"c{k}": 0.1 * k for k in range(K)})
    compiled = m.compile()
    assert compiled.alias_names == tuple(f"q{k}" for k in range(K))
    assert compiled.algebraic_names == tuple(f"w{k}" for k in range(K))


def test_sparse_jacobian_entries_and_numeric_jacobians():
    exprs = [x * y + z, sp.sin(x) * 0 + y**2, sp.Integer(3)]
    rows, cols, entries = jacobian_entries(exprs, [x, y, z])
    assert list(zip(rows, cols, entries, strict=True)) == [(0, 0, y), (0, 1, x), (0, 2, 1), (1, 1, 2 * y)]
    numeric = NumericSystem(t, (x, y), (z,), ())
    dense = sp.Matrix(exprs).jacobian([x, y, z])
    point = {x: 0.3, y: -1.2, z: 2.0}
    expected = np.array(dense.subs(point), dtype=float)
    got = numeric.jacobian(exprs, [x, y, z])(0.0, np.array([0.3, -1.2]), np.array([2.0]), np.zeros(0))
    np.testing.assert_array_equal(got, expected)
    batch = numeric.batch_jacobian(exprs, [x, y, z])(
        0.0, np.array([[0.3, -1.2]] * 2), np.array([[2.0]] * 2), np.zeros((2, 0))
    )
    np.testing.assert_array_equal(batch, np.stack([expected, expected]))


def _permuted_blocks(rng, m, sizes=(1, 2, 3)):
    A = np.zeros((m, m))
    perm, start = rng.permutation(m), 0
    while start < m:
        k = min(int(rng.choice(sizes)), m - start)
        idx = perm[start : start + k]
        A[np.ix_(idx, rng.permutation(idx))] = rng.normal(size=(k, k)) + 3 * np.eye(k)
        start += k
    return A[:, rng.permutation(m)]


def test_block_solve_and_rank_check_agree_with_dense():
    rng = np.random.default_rng(1)
    A = _permuted_blocks(rng, 3 * BLOCK_MIN_SIZE)
    groups = square_blocks(A != 0)
    assert sum(rows.size for rows, _ in groups) == len(A)
    sigma = np.concatenate(
        [np.linalg.svd(A[r[:, :, None], c[:, None, :]], compute_uv=False).ravel() for r, c in groups]
    )
    np.testing.assert_allclose(np.sort(sigma), np.sort(np.linalg.svd(A, compute_uv=False)), rtol=1e-12)
    stack, b = np.stack([A, A.T @ A, 2 * A]), rng.normal(size=(3, len(A)))
    x_blocks = least_squares(stack, b)
    np.testing.assert_allclose(x_blocks, np.linalg.solve(stack, b[..., None])[..., 0], rtol=1e-10, atol=1e-12)
    singular = A.copy()
    singular[:, np.flatnonzero(singular[5])[0]] = 0.0  # a zero column: no square block holds it
    assert square_blocks(singular != 0) is None
    x_singular = least_squares(singular[None], b[:1])  # the pseudo-inverse path
    np.testing.assert_allclose(x_singular, (np.linalg.pinv(singular) @ b[0])[None], atol=1e-10)
    symbols = [sp.Symbol(f"w{j}") for j in range(len(A))]

    class Row:  # the only attributes the message reads
        def __init__(self, k):
            self.label, self.index = f"constraint 'r{k}' (#{k})", 1

    check_rank(A, [Row(k) for k in range(len(A))], symbols, 0.0)  # regular: passes
    with pytest.raises(E.SingularSystemError, match=r"g_z is singular at t=0 \(smallest singular value"):
        check_rank(singular, [Row(k) for k in range(len(A))], symbols, 0.0)


def test_compile_pauses_the_garbage_collector_and_restores_it(monkeypatch):
    import gc

    from daemodel.compiling import compiler

    seen = []
    original = compiler.initialise

    def recording(*args, **kwargs):
        seen.append(gc.isenabled())
        return original(*args, **kwargs)

    monkeypatch.setattr(compiler, "initialise", recording)
    was = gc.isenabled()
    try:
        gc.enable()
        z0 = reaction_diffusion(5).compile().z0
        assert seen == [False] and gc.isenabled()
        c0 = np.sin(np.pi * np.arange(1, 6) / 6)
        np.testing.assert_allclose(z0, c0**2 / (1 + c0), rtol=1e-14)
        gc.disable()  # (a caller's paused collector stays paused)
        reaction_diffusion(4).compile()
        assert seen == [False, False] and not gc.isenabled()
        gc.enable()  # (and an error restores it)
        with pytest.raises(E.MissingInitialValueError):
            broken = dm.Model("broken")
            (x,) = broken.states("x")
            broken.ode(x, -x)
            broken.compile()
        assert gc.isenabled()
    finally:
        (gc.enable if was else gc.disable)()

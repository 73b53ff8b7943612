"""The heat equation on the unit square by lines, declared as arrays, with an algebraic boundary.

    T_t = kappa (T_xx + T_yy)      on (0, 1) x (0, 1)
    T_x = 0 at x = 0 and x = 1     (insulated: the boundary values are algebraic variables)
    T = 0   at y = 0 and y = 1

On an N x N grid of interior nodes (spacing h = 1/(N+1)) the states are ``T[i,j]``, one array
``m.states("T", (N, N))``, whose equations are written with stencils (``dm.stencil``: the five-point
Laplacian recorded once); the boundary values at x = 0 and x = 1 are the algebraic array
``m.algebraics("edge", (2, N))``, fixed by a second-order one-sided difference for T_x = 0,

    3 edge[0,j] - 4 T[0,j] + T[1,j] = 0,      3 edge[1,j] - 4 T[N-1,j] + T[N-2,j] = 0,

one array of constraints ``m.constraint(array, name="insulated")`` (an index-1 DAE of N^2 + 2N
unknowns).  The exact solution from the eigenmode T(x, y, 0) = cos(pi x) sin(pi y) is
T = cos(pi x) sin(pi y) exp(-2 pi^2 kappa t); the grid's error is O(h^2), which the example checks.

Run: python examples/heat_2d.py [--n 100] [--quick]   (--quick: N = 10)
"""

import argparse
import time

import numpy as np

import daemodel as dm

KAPPA = 1.0
T_END = 0.05  # the mode decays to exp(-2 pi^2 T_END) = 37 % of its start
# |error| / h^2 the second-order grid stays below (measured 0.13, 0.20, 0.24, 0.28 for N = 10, 20, 40,
# 100: a bound with room, which a first-order boundary or a wrong sign breaks)
ERROR_PER_H2 = 0.5


def exact(x: np.ndarray, y: np.ndarray, t) -> np.ndarray:
    """T(x, y, t) of the eigenmode, shape (*x.shape, len(t))."""
    decay = np.exp(-2 * np.pi**2 * KAPPA * np.asarray(t))
    return (np.cos(np.pi * x) * np.sin(np.pi * y))[..., None] * decay


def build_model(n: int) -> tuple[dm.Model, np.ndarray, np.ndarray]:
    """The model on an n x n interior grid, and the nodes' coordinates x, y (n, n)."""
    h = 1.0 / (n + 1)
    x, y = np.meshgrid(h * np.arange(1, n + 1), h * np.arange(1, n + 1), indexing="ij")
    m = dm.Model("heat_2d")
    T = m.states("T", (n, n))
    edge = m.algebraics("edge", (2, n))
    kappa = m.parameter("kappa", KAPPA)
    grid = np.zeros((n + 2, n + 2), dtype=object)  # with the boundary: edge at x = 0, 1; zero at y = 0, 1
    grid[1:-1, 1:-1] = T
    grid[0, 1:-1], grid[-1, 1:-1] = edge[0], edge[1]
    # stencils: the arithmetic below is recorded once, not once per node (numpy's arithmetic on the
    # arrays of symbols would build the same equations, node by node)
    G = dm.stencil(grid)
    neighbours = G[2:, 1:-1] + G[:-2, 1:-1] + G[1:-1, 2:] + G[1:-1, :-2] - 4 * G[1:-1, 1:-1]
    # (kappa / h^2 in front: a number times a sum alone would be multiplied out by sympy, term by term)
    m.ode(T, kappa / h**2 * neighbours)
    boundary = dm.stencil(edge)  # row 0 at x = 0, row 1 at x = 1; the first and second nodes inside:
    first, second = dm.stencil(np.stack([T[0], T[-1]])), dm.stencil(np.stack([T[1], T[-2]]))
    m.constraint(3 * boundary - 4 * first + second, name="insulated")
    m.initial(T=exact(x, y, 0.0)[..., 0])
    return m, x, y


def main(argv=None) -> float:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=100, help="interior nodes per side (default 100)")
    parser.add_argument("--quick", action="store_true", help="N = 10, for CI")
    args = parser.parse_args(argv)
    n = 10 if args.quick else args.n
    h = 1.0 / (n + 1)

    start = time.perf_counter()
    m, x, y = build_model(n)
    declared = time.perf_counter()
    sol = dm.solve(m, (0.0, T_END), rtol=1e-7, atol=1e-9)
    solved = time.perf_counter()

    T = sol["T"]  # (n, n, times)
    assert T.shape == (n, n, len(sol.t)), T.shape
    assert sol["edge"].shape == (2, n, len(sol.t))
    error = float(np.max(np.abs(T - exact(x, y, sol.t))))
    # the edge values against the exact boundary values cos(0) = 1, cos(pi) = -1 times sin(pi y)
    edge_exact = np.stack([exact(np.zeros(n), y[0], sol.t), exact(np.ones(n), y[0], sol.t)])
    edge_error = float(np.max(np.abs(sol["edge"] - edge_exact)))
    print(
        f"heat_2d N = {n}: {n * n} states, {2 * n} algebraic; declared in {declared - start:.2f} s, "
        f"solved ({sol.method}, {sol.status}, {sol.stats.get('steps', '?')} steps) in {solved - declared:.2f} s"
    )
    print(f"max |T - exact| = {error:.3e} = {error / h**2:.3f} h^2;  max |edge - exact| = {edge_error:.3e}")
    assert sol.status == "success", sol.status
    assert error < ERROR_PER_H2 * h**2, (error, h)
    assert edge_error < ERROR_PER_H2 * h**2, (edge_error, h)
    return error


if __name__ == "__main__":
    main()

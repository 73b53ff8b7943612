"""The reference values at t = 1 of the families suite (``daemodel.problems.families``), computed
independently of daemodel: scipy's ``solve_ivp`` on each family's index-reduced ODE (the pendulum
chain's tensions from its acceleration-level constraints, a tridiagonal-in-structure linear solve
per call; reaction-diffusion's reaction rate substituted), at rtol 1e-12, atol 1e-14, with two
methods (Radau and DOP853) whose difference bounds the reference's own error.

Run ``python benchmarks/family_references.py`` to print the literal dicts that
``daemodel/problems/families.py`` holds, and the largest relative difference between the methods.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.integrate import solve_ivp

# The same constants as daemodel.problems.families, written again so this script stands alone.
GRAVITY = 9.81
CHAIN_RELEASE_ANGLE = math.pi / 4
DIFFUSION = 0.1
T_END = 1.0
CHAIN_SIZES = (4, 8, 16)
GRID_SIZES = (25, 50, 100)


def chain_tensions(N: int, state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(lam, accelerations) of the chain: lam solves the acceleration-level rod constraints
    ``d_i . (a_i - a_{i-1}) + |w_i|^2 = 0`` (``d_i = p_i - p_{i-1}``, ``w_i = v_i - v_{i-1}``)."""
    x, y, u, v = state.reshape(4, N)
    p = np.stack([np.concatenate([[0.0], x]), np.concatenate([[0.0], y])], axis=1)  # (N + 1, 2)
    w = np.stack([np.concatenate([[0.0], u]), np.concatenate([[0.0], v])], axis=1)
    d = p[1:] - p[:-1]  # d[k] is rod k + 1
    dw = w[1:] - w[:-1]
    # accelerations a = sum_j lam_j A_j + a_g, masses 1..N (index k = i - 1), mass 0 fixed
    columns = np.zeros((N, N, 2))  # columns[j, k]: acceleration of mass k + 1 per unit lam_{j+1}
    for j in range(N):
        columns[j, j] -= d[j]
        if j > 0:
            columns[j, j - 1] += d[j]
    gravity = np.zeros((N, 2))
    gravity[:, 1] = -GRAVITY

    def relative(acc):  # a_i - a_{i-1}, shape (N, 2)
        return acc - np.concatenate([np.zeros((1, 2)), acc[:-1]])

    matrix = np.stack([np.sum(d * relative(columns[j]), axis=1) for j in range(N)], axis=1)
    rhs = -np.sum(dw * dw, axis=1) - np.sum(d * relative(gravity), axis=1)
    lam = np.linalg.solve(matrix, rhs)
    acc = np.tensordot(lam, columns, axes=1) + gravity
    return lam, acc


def chain_start(N: int) -> np.ndarray:
    i = np.arange(1, N + 1)
    c, s = math.cos(CHAIN_RELEASE_ANGLE), math.sin(CHAIN_RELEASE_ANGLE)
    return np.concatenate([i * c, -i * s, np.zeros(N), np.zeros(N)])


def chain_end(N: int, method: str) -> dict:
    def f(t, state):
        _, acc = chain_tensions(N, state)
        return np.concatenate([state[2 * N :], acc[:, 0], acc[:, 1]])

    sol = solve_ivp(f, (0.0, T_END), chain_start(N), method=method, rtol=1e-12, atol=1e-14)
    assert sol.success, sol.message
    end = sol.y[:, -1]
    lam, _ = chain_tensions(N, end)
    x, y, u, v = end.reshape(4, N)
    out = {}
    for name, values in (("x", x), ("y", y), ("u", u), ("v", v), ("lam", lam)):
        out.update({f"{name}_{i}": float(values[i - 1]) for i in range(1, N + 1)})
    return out


def grid_end(K: int, method: str) -> dict:
    inv_dx2 = (K + 1) ** 2

    def f(t, c):
        padded = np.concatenate([[0.0], c, [0.0]])
        return DIFFUSION * inv_dx2 * (padded[:-2] - 2 * c + padded[2:]) - c * c / (1 + c)

    def jac(t, c):
        J = (
            DIFFUSION
            * inv_dx2
            * (np.diag(-2.0 * np.ones(K)) + np.diag(np.ones(K - 1), 1) + np.diag(np.ones(K - 1), -1))
        )
        return J - np.diag(c * (2 + c) / (1 + c) ** 2)

    c0 = np.sin(math.pi * np.arange(1, K + 1) / (K + 1))
    kwargs = {"jac": jac} if method == "Radau" else {}
    sol = solve_ivp(f, (0.0, T_END), c0, method=method, rtol=1e-12, atol=1e-14, **kwargs)
    assert sol.success, sol.message
    c = sol.y[:, -1]
    w = c * c / (1 + c)
    out = {f"c_{k}": float(c[k - 1]) for k in range(1, K + 1)}
    out.update({f"w_{k}": float(w[k - 1]) for k in range(1, K + 1)})
    return out


def components(family: str, size: int) -> tuple:
    """The components the suite reads scd from (as ``daemodel.problems.families.scd_components``):
    the chain's tip (position and velocity) and its first and last tensions; the grid's
    concentration and rate at its first point, a quarter along and in the middle."""
    if family == "pendulum_chain":
        return (f"x_{size}", f"y_{size}", f"u_{size}", f"v_{size}", "lam_1", f"lam_{size}")
    points = (1, (size + 1) // 4, (size + 1) // 2)
    return tuple(f"c_{k}" for k in points) + tuple(f"w_{k}" for k in points)


def largest_relative_difference(a: dict, b: dict) -> float:
    return max(abs(a[k] - b[k]) / max(abs(a[k]), 1e-300) for k in a)


if __name__ == "__main__":
    for family, sizes, end in (
        ("pendulum_chain", CHAIN_SIZES, chain_end),
        ("reaction_diffusion", GRID_SIZES, grid_end),
    ):
        for size in sizes:
            radau, dop = end(size, "Radau"), end(size, "DOP853")
            print(
                f"# {family}-{size}: Radau vs DOP853 differ by {largest_relative_difference(radau, dop):.1e} (relative)"
            )
            chosen = {k: radau[k] for k in components(family, size)}
            print(f'"{family}-{size}": {{' + ", ".join(f'"{k}": {v!r}' for k, v in chosen.items()) + "},")

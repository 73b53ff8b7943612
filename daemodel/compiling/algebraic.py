"""The algebraic variables solved again from a method's states at its outputs (adaptive radau, where
some have index 2 or more, and its dense output between them).

Collocation's values of an algebraic variable of index 2 are of order s at the step ends where the
states are of order 2s - 1, and adaptive steps weigh their error estimate by h, as RADAU5 does: at
rtol = atol = 1e-10 the car axis's multipliers were 3.8 tolerances off their own hidden constraint
at the step ends (s = 3: 13), the Hessenberg example's y5 10.5, and a circle's z 212 at s = 3, with
status success.  The same variables solved from the determining equations (``g_t + g_y f = 0`` at
index 2) at the returned states carry the states' error only: the car axis's multipliers read 13.58
digits so where the collocation's read 8.30, and the circle's and the Hessenberg example's z were
within 0.15 tolerances of the closed form.  So the outputs take those, and the difference
(the collocation's error, estimated) is reported.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from daemodel.compiling.init import NewtonTolerances, jacobian_entries, solve_algebraic
from daemodel.compiling.initial_states import constraint_checks

# Newton steps at most from the collocation's values, which lie within a few tolerances of the root:
# determining equations linear in z (mechanics) settle in one, others in a few.
RESOLVE_MAX_ITERATIONS = 20
# Outputs solved at a time: as many as keep their dense z Jacobians (m x m each) within these bytes (a long run of
# a model with tens of algebraic variables would otherwise hold hundreds of megabytes of them at once).
RESOLVE_BYTES = 64 * 2**20


def resolves_algebraic(compiled) -> bool:
    """Whether ``compiled`` has algebraic variables of index 2 or more (only those are solved again)."""
    return bool(compiled.algebraics) and max(compiled.algebraic_index) >= 2


@dataclass(frozen=True)
class Resolved:
    """Result of :func:`algebraic_from_states`.

    Attributes
    ----------
    z : ndarray, shape (B, K, m)
        The algebraic variables solved from the states; where Newton failed, the values given.
    converged : ndarray of bool, shape (B, K)
    """

    z: np.ndarray
    converged: np.ndarray


def algebraic_from_states(compiled, times, Y, Z, P) -> Resolved:
    """The algebraic variables that the states ``Y`` (B, K, n) determine at ``times`` (K,): one batched
    Newton solve (:func:`~daemodel.compiling.init.solve_algebraic`, the one algebraic Newton) of the
    determining equations of every algebraic variable, started from ``Z`` (B, K, m), with the
    parameters ``P`` (B, k).  The caller decides what a point that did not converge means."""
    Y, Z = np.asarray(Y, dtype=float), np.asarray(Z, dtype=float)
    B, K, n = Y.shape
    m = Z.shape[2]
    if not K or not m:
        return Resolved(Z.copy(), np.ones((B, K), dtype=bool))
    checks, settings = constraint_checks(compiled), tolerances(compiled)
    rows_t, rows_y = np.tile(np.asarray(times, dtype=float), B), Y.reshape(B * K, n)
    rows_p, rows_z = np.repeat(np.asarray(P, dtype=float), K, axis=0), Z.reshape(B * K, m)
    x, converged = rows_z.copy(), np.zeros(B * K, dtype=bool)
    chunk = max(1, RESOLVE_BYTES // (8 * m * m))
    for a in range(0, B * K, chunk):
        rows = slice(a, a + chunk)
        t, y, p = rows_t[rows], rows_y[rows], rows_p[rows]
        result = solve_algebraic(
            lambda z, t=t, y=y, p=p: checks.H(t, y, z, p),
            lambda z, t=t, y=y, p=p: checks.Hz(t, y, z, p),
            rows_z[rows],
            settings,
        )
        x[rows], converged[rows] = np.where(result.converged[:, None], result.x, rows_z[rows]), result.converged
    return Resolved(x.reshape(B, K, m), converged.reshape(B, K))


def prepare(compiled) -> None:
    """Make the functions :func:`algebraic_from_states` evaluates for ``compiled`` (its determining equations and
    their z Jacobian in numpy, and whether they are affine in z), where it has algebraic variables of index 2 or
    more: code generation, done in the setup, before any method's clock."""
    if not resolves_algebraic(compiled):
        return
    tolerances(compiled)
    # (H_z's nonzeros are the branch check's, made with it; a batch of outputs evaluates H in numpy)
    constraint_checks(compiled).H.numpy()


def tolerances(compiled) -> NewtonTolerances:
    """The Newton tolerances of :func:`algebraic_from_states` for ``compiled`` (linear ones settle in a
    step: determining equations whose z Jacobian is free of z), made once per model."""

    def build() -> NewtonTolerances:
        determining = [c.determining for c in compiled.constraints]
        _, _, entries = jacobian_entries(determining, compiled.algebraics, compiled.numeric.calculus)
        linear = not any(e.has(*compiled.algebraics) for e in entries)
        return NewtonTolerances(max_iterations=RESOLVE_MAX_ITERATIONS, linear=linear)

    return compiled.cached("algebraic-from-states-tolerances", build)

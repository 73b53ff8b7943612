"""Consistent initial values.

The initial state y0 must satisfy every z-free level of every derivative chain (the
constraints of index >= 2 and, for index 3, their hidden velocity-level constraints).  The
algebraic values z0 then follow from the determining equations: ``g = 0`` (index 1),
``g_t + g_y f = 0`` (index 2), the second derivative (index 3), solved by Newton from the
user's values (or zero).  ``repair=True`` projects an inconsistent y0 onto the constraint
manifold with the least change in the Euclidean norm and replaces disagreeing z values.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import sympy as sp

from daemodel.errors import (
    InconsistentAlgebraicValueError,
    InconsistentInitialStateError,
    InitialisationError,
)
from daemodel.structure import check_rank

# Residual accepted for y0 on the constraint manifold, relative to 1 + max|y0|: a y0 typed
# with 16 digits passes; one off in the 10th digit is reported.
STATE_TOL = 1e-10
# User-given algebraic values must agree with the consistent ones to this relative accuracy.
ALGEBRAIC_TOL = 1e-9
NEWTON_MAXITER = 50
PROJECTION_MAXITER = 100


@dataclass(frozen=True)
class NumericSystem:
    """Numpy callables of sympy expressions over ``(t, y, z, p)``."""

    t: sp.Symbol
    y: tuple
    z: tuple
    p: tuple

    def function(self, exprs):
        """Return ``F(t, y, z, p) -> ndarray, shape (len(exprs),)``."""
        if not exprs:
            return lambda t, y, z, p: np.zeros(0)
        fn = sp.lambdify((self.t, self.y, self.z, self.p), list(exprs), "numpy")
        return lambda t, y, z, p: np.asarray(fn(t, y, z, p), dtype=float).reshape(len(exprs))

    def jacobian(self, exprs, wrt):
        """Return ``J(t, y, z, p) -> ndarray, shape (len(exprs), len(wrt))``."""
        if not exprs or not wrt:
            return lambda t, y, z, p: np.zeros((len(exprs), len(wrt)))
        matrix = sp.Matrix(list(exprs)).jacobian(list(wrt))
        fn = sp.lambdify((self.t, self.y, self.z, self.p), matrix, "numpy")
        return lambda t, y, z, p: np.asarray(fn(t, y, z, p), dtype=float).reshape(matrix.shape)

    def batch_function(self, exprs):
        """Return ``F(t, Y, Z, P) -> ndarray, shape (B, len(exprs))`` for rows ``Y (B, n)`` etc."""
        fn = sp.lambdify((self.t, self.y, self.z, self.p), list(exprs), "numpy")

        def evaluate(t, Y, Z, P):
            if not exprs:
                return np.zeros((len(Y), 0))
            out = fn(t, Y.T, Z.T, P.T)
            return np.stack([np.broadcast_to(np.asarray(v, dtype=float), (len(Y),)) for v in out], axis=-1)

        return evaluate

    def batch_jacobian(self, exprs, wrt):
        """Return ``J(t, Y, Z, P) -> ndarray, shape (B, len(exprs), len(wrt))``."""
        entries = sp.Matrix(list(exprs)).jacobian(list(wrt)) if exprs and wrt else sp.zeros(len(exprs), len(wrt))
        flat = self.batch_function(list(entries))
        return lambda t, Y, Z, P: flat(t, Y, Z, P).reshape(len(Y), len(exprs), len(wrt))


@dataclass(frozen=True)
class InitialValues:
    """Result of :func:`initialise`: the values and what was changed."""

    y0: np.ndarray
    z0: np.ndarray
    notes: tuple


def hidden_constraints(constraints) -> list[tuple[str, str, sp.Expr]]:
    """``(level name, label, expr)`` for every z-free chain level, in chain order."""
    return [
        (c.level_name(k), c.label if k == 0 else f"hidden constraint {c.level_name(k)} of {c.label}", c.chain[k])
        for c in constraints
        for k in range(c.index - 1)
    ]


def project(y0, residual, jacobian) -> np.ndarray:
    """Nearest point to y0 with ``residual(y) = 0``.

    Iterates ``y = y0 - C^T mu`` with ``C C^T mu = c(y_k) + C (y0 - y_k)``: its fixed points
    satisfy ``c(y) = 0`` and ``y - y0`` in the row space of ``C``, the conditions for the
    least Euclidean change.  Least squares keeps it well defined for redundant constraints.
    """
    y = y0.copy()
    for _ in range(PROJECTION_MAXITER):
        C = jacobian(y)
        mu = np.linalg.lstsq(C @ C.T, residual(y) + C @ (y0 - y), rcond=None)[0]
        y_new = y0 - C.T @ mu
        if np.max(np.abs(y_new - y)) <= 1e-15 * (1 + np.max(np.abs(y))):
            return y_new
        y = y_new
    return y


def newton(F, J, x0):
    """Damped Newton with least-squares steps; returns ``(x, converged)``."""
    with np.errstate(all="ignore"):  # non-finite residuals are detected and reported below
        return _newton(F, J, x0)


def _newton(F, J, x0):
    if x0.size == 0:
        return x0.copy(), True
    x, r = x0.copy(), F(x0)
    for _ in range(NEWTON_MAXITER):
        if not np.all(np.isfinite(r)):
            return x, False
        dx = np.linalg.lstsq(J(x), -r, rcond=None)[0]
        step = 1.0
        while True:
            x_new = x + step * dx
            r_new = F(x_new)
            if np.linalg.norm(r_new) <= np.linalg.norm(r) or step < 1e-4:
                break
            step /= 2
        x, r = x_new, r_new
        if np.max(np.abs(dx)) <= 1e-13 * (1 + np.max(np.abs(x))):
            break
    return x, bool(np.all(np.isfinite(r)))


def initialise(
    numeric: NumericSystem,
    constraints,
    aliases,
    t0: float,
    given: dict,
    p: np.ndarray,
    repair: bool,
) -> InitialValues:
    """Check or repair y0, compute z0, compare with given algebraic values.

    A given algebraic value is both Newton's start (it selects among several roots) and a
    claim: if it disagrees with the root found, that is an error unless ``repair``.

    Parameters
    ----------
    numeric : NumericSystem
    constraints : list of Constraint
    aliases : list of (name, expr)
    t0 : float
    given : dict name -> float
        The user's initial values (states required, algebraic values optional).
    p : ndarray, shape (k,)
    repair : bool
    """
    notes = []
    y0 = np.array([given[y.name] for y in numeric.y], dtype=float)
    empty_z = np.zeros(len(numeric.z))

    hidden = hidden_constraints(constraints)
    exprs = [e for _, _, e in hidden]
    c_fun, c_jac = numeric.function(exprs), numeric.jacobian(exprs, numeric.y)
    residual = c_fun(t0, y0, empty_z, p)
    tol = STATE_TOL * (1 + np.max(np.abs(y0), initial=0.0))
    bad = [(hidden[i], residual[i]) for i in np.flatnonzero(np.abs(residual) > tol)]
    if bad and not repair:
        listing = "; ".join(f"{label}: {name} = {value:.6g}" for (name, label, _), value in bad)
        raise InconsistentInitialStateError(
            f"the initial state violates {listing} (tolerance {tol:.1e}). Fix the initial values "
            "or compile(repair=True) to project them onto the constraint manifold"
        )
    if bad:
        y_new = project(y0, lambda y: c_fun(t0, y, empty_z, p), lambda y: c_jac(t0, y, empty_z, p))
        after = c_fun(t0, y_new, empty_z, p)
        if np.max(np.abs(after)) > tol:
            worst = int(np.argmax(np.abs(after)))
            raise InitialisationError(
                f"repair could not project the initial state onto {hidden[worst][1]} "
                f"(residual {after[worst]:.3g} after projection); the constraints may have no "
                "real solution near the given state"
            )
        changes = ", ".join(
            f"{y.name}: {a:.10g} -> {b:.10g}" for y, a, b in zip(numeric.y, y0, y_new, strict=True) if a != b
        )
        notes.append(f"repaired y0 (least change, |dy| = {np.linalg.norm(y_new - y0):.3g}): {changes}")
        y0 = y_new

    determining = [c.determining for c in constraints]
    H, Hz = numeric.function(determining), numeric.jacobian(determining, numeric.z)
    guess = np.array([given.get(z.name, 0.0) for z in numeric.z], dtype=float)
    z0, ok = newton(lambda z: H(t0, y0, z, p), lambda z: Hz(t0, y0, z, p), guess)
    with np.errstate(all="ignore"):
        jacobian, residual = Hz(t0, y0, z0, p), H(t0, y0, z0, p)
    check_rank(jacobian, constraints, numeric.z, t0)  # a singular H_z explains a failed Newton
    if not ok or np.max(np.abs(residual), initial=0.0) > 1e-8 * (1 + np.max(np.abs(z0), initial=0.0)):
        worst = int(np.argmax(np.abs(residual))) if residual.size else 0
        raise InitialisationError(
            f"Newton for the initial algebraic values did not converge: {constraints[worst].label} "
            f"has residual {residual[worst]:.3g} at z = {dict(zip((z.name for z in numeric.z), z0, strict=True))}; "
            "give a better starting value with m.initial(<algebraic>=...)"
        )

    values = dict(zip((v.name for v in numeric.y + numeric.z), np.concatenate([y0, z0]).tolist(), strict=True))
    alias_fun = numeric.function([e for _, e in aliases])
    values.update(zip((n for n, _ in aliases), alias_fun(t0, y0, z0, p).tolist(), strict=True))
    for name, value in given.items():
        if name in {y.name for y in numeric.y} or name not in values:
            continue
        consistent = values[name]
        if abs(value - consistent) > ALGEBRAIC_TOL * (1 + abs(consistent)):
            if not repair:
                raise InconsistentAlgebraicValueError(
                    f"initial value {name} = {value:.10g} disagrees with the consistent value "
                    f"{name} = {consistent!r} determined by the constraints; drop it, use the "
                    "consistent value, or compile(repair=True)"
                )
            notes.append(f"replaced {name} = {value:.10g} by the consistent value {consistent!r}")
    return InitialValues(y0=y0, z0=z0, notes=tuple(notes))

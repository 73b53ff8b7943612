"""What rounding is for an event's function, a reset's value or a state's motion: :data:`ROUNDING` of the size of
the values that evaluating it rounds at (:func:`magnitude`: its terms taken in absolute value, each input at its
own size), never of an absolute 1.  Below that a drift along the flow is no motion (:func:`within_rounding`), and two
values are one.  Used by :mod:`daemodel.solving.branches` (the side a function at zero goes to), by
:mod:`daemodel.solving.events` (a reset that moves its function off zero) and by :mod:`daemodel.solving.resets`
(two resets of one state that differ).

The floor was ``ROUNDING * max(1, max |y|, |z|)``: an absolute 1.4e-14 where the values are small.  A ball
dropped from 1e-14 (g = 9.81, e = 0.8) moves its height by 1e-22 over the look-ahead after its first impact and
by 3e-17 over the longest one, all within that floor: its bounce was never armed, and radau let it fall to
-2.3e-13 after 1 of its 6 impacts, "success".  A floor of the largest state's size is no better: it compares
the height's motion with the velocity's size, so that the look-ahead must be longer than ~1e-5 / 1e-9 of the
span in the time's own units, whatever the height's units."""

from __future__ import annotations

import numpy as np
import sympy as sp

# A value within ROUNDING of the size its evaluation rounds at (magnitude) is not told from zero: a few hundred
# float64 roundings of the terms (an explicit step's end, the function at both ends, their difference).
ROUNDING = 64 * np.finfo(float).eps


def magnitude(expr: sp.Expr, algebraics: frozenset = frozenset()) -> sp.Expr:
    """The size of the values that evaluating ``expr`` rounds at, as an expression of the same symbols: its
    inputs in absolute value, sums of terms and products of factors taken in absolute value (so that ``x - 1`` at
    ``x = 1`` is 2 in size, and ``1e8 x - 1`` at ``x = 1e-8`` is 2, not its value 0 nor the size 1e-8 of x), a
    power by its relative error (``|b|^n (mag(b) / |b|)^max(1, |n|)``; a positive integer's as the product), any
    other function by its value plus its arguments' sizes (a rate of order 1 in them: sin, Max, Abs, floor),
    ``exp`` by its value times 1 plus its argument's size.  An algebraic variable (in ``algebraics``) is counted at
    ``1 + |z|``, the unit in which the Newton that solves it anew at a drift's end settles
    (:class:`~daemodel.compiling.init.NewtonTolerances`); a state, t and a parameter at their own size, with no
    absolute unit: a function of states in units of 1e-14 rounds at 1e-14's size; t only where the function names
    it (the ball's height at t = 1e13 rose 0.136 over the look-ahead after its third impact, within 64 eps 1e13 =
    0.142, and was read as resting on the floor: ZenoError)."""
    if expr.is_Number or expr.is_NumberSymbol:
        return sp.Abs(expr)
    if expr.is_Symbol:
        return 1 + sp.Abs(expr) if expr in algebraics else sp.Abs(expr)
    if expr.is_Add:
        return sp.Add(*(magnitude(a, algebraics) for a in expr.args))
    if expr.is_Mul:
        return sp.Mul(*(magnitude(a, algebraics) for a in expr.args))
    if expr.is_Pow and expr.exp.is_Number:
        base, n = expr.base, expr.exp
        if n.is_Integer and n > 0:
            return magnitude(base, algebraics) ** n
        return sp.Abs(expr) * (magnitude(base, algebraics) / sp.Abs(base)) ** max(1, abs(n))
    if isinstance(expr, sp.Piecewise):
        inner = [magnitude(e, algebraics) for e, _ in expr.args]
    else:
        inner = [magnitude(a, algebraics) for a in expr.args if isinstance(a, sp.Expr)]
    if isinstance(expr, sp.exp):
        return sp.Abs(expr) * (1 + sp.Add(*inner))
    return sp.Abs(expr) + sp.Add(*inner)


def magnitudes(compiled, exprs: tuple):
    """``M(t, Y, Z, P) -> (B, k)``: :func:`magnitude` of each of ``exprs``, generated once per model."""
    exprs = tuple(exprs)

    def build():
        algebraics = frozenset(compiled.algebraics)
        return compiled.numeric.batch_function([magnitude(e, algebraics) for e in exprs])

    return compiled.cached(("magnitudes", exprs), build)


def floor_at(compiled, exprs: tuple, t: float, Y: np.ndarray, Z: np.ndarray, P: np.ndarray) -> np.ndarray:
    """:data:`ROUNDING` of :func:`magnitude` of each of ``exprs`` at ``(t, Y (1, n), Z (1, m))``, (k,); infinite
    where that is not finite (a power of a base at 0: no size to tell a value from zero by)."""
    with np.errstate(all="ignore"):
        size = np.asarray(magnitudes(compiled, exprs)(np.array([float(t)]), Y, Z, P), dtype=float)[0]
    return ROUNDING * np.where(np.isfinite(size), size, np.inf)


def within_rounding(change: np.ndarray, floor: np.ndarray) -> np.ndarray:
    """``change`` with the entries within their ``floor`` (:func:`floor_at`, the larger of both ends' for a drift)
    set to exactly 0: no motion, no side."""
    change = np.asarray(change, dtype=float)
    return np.where(np.abs(change) <= floor, 0.0, change)

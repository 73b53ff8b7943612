"""Consistent initial values.

The initial state y0 must satisfy every z-free level of every derivative chain (the
constraints of index >= 2 and, for index 3, their hidden velocity-level constraints).  The
algebraic values z0 then follow from the determining equations: ``g = 0`` (index 1),
``g_t + g_y f = 0`` (index 2), the second derivative (index 3), solved by Newton from the
user's values (or zero).  ``repair=True`` projects an inconsistent y0 onto the constraint
manifold with the least change in the Euclidean norm and replaces disagreeing z values.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
import sympy as sp

from daemodel.compiling.batch_function import BatchFunction
from daemodel.compiling.linear import SPARSE_MIN_SIZE, SparseStack, least_squares
from daemodel.compiling.numeric_source import (
    NUMERIC_MODULES,
    NumericPrinter,
    holds_re,
    shape_key,
    shared_subexpressions,
)
from daemodel.compiling.structure import Differentiator, check_rank
from daemodel.errors import (
    InconsistentAlgebraicValueError,
    InconsistentInitialStateError,
    InitialisationError,
    SingularSystemError,
    WrongBranchError,
)
from daemodel.files import check_dense

# Residual accepted for y0 on the constraint manifold, relative to 1 + max|y0|: a y0 typed
# with 16 digits passes; one off in the 10th digit is reported.
STATE_TOL = 1e-10
# User-given algebraic values must agree with the consistent ones to this relative accuracy.
ALGEBRAIC_TOL = 1e-9
NEWTON_MAXITER = 50
# Newton for algebraic values has settled when the estimated error of its last iterate is below
# this, relative to 1 + |z| (quadratic convergence gets there in a few steps from a usable start),
# and its residual is below NEWTON_RESIDUAL_TOL relative to 1 + |z| (NewtonTolerances).
NEWTON_STEP_TOL, NEWTON_RESIDUAL_TOL = 1e-13, 1e-8
# Newton that stalls (contraction above NEWTON_STALL_RATE) with a step below NEWTON_STALL_TOL
# (relative) has reached the rounding level of an ill-conditioned Jacobian: accepted.
NEWTON_STALL_RATE, NEWTON_STALL_TOL = 0.5, 1e-9
# Step halvings per Newton step while the residual grows.
DAMPING_HALVINGS = 14
PROJECTION_MAXITER = 100
# Expressions per generated numpy function: more are printed as several functions whose lists are joined.  A
# line of one code object looked up per allocation (tracemalloc, coverage, a profiler's line events) costs in
# proportion to the code's length: one function of 10^4 expressions took a traced 10^4-unknown first solve 68 s
# of its 1.5 s (each piece computes the subexpressions its own expressions share: the same values).
LAMBDIFY_CHUNK = 256


@dataclass(frozen=True)
class NumericSystem:
    """Numpy callables of sympy expressions over ``(t, y, z, p)``.

    Jacobians are built on the sparsity pattern: an entry is differentiated only where its
    variable occurs in the expression, and only the nonzero derivatives are lambdified and
    scattered into the dense result, so the symbolic work grows with the number of nonzeros,
    not with ``len(exprs) * len(wrt)``.  ``calculus`` shares derivatives already taken (the
    compiler passes the one its structure checks used).
    """

    t: sp.Symbol
    y: tuple
    z: tuple
    p: tuple
    calculus: Differentiator = field(default_factory=Differentiator, compare=False, repr=False)
    # the functions made so far, by kind and expressions: a solution's at() and drift(), the event
    # functions and the initial-value checks ask for the same ones again (see CompiledDAE.numeric)
    _made: dict = field(default_factory=dict, compare=False, repr=False)

    def _once(self, kind: str, exprs, wrt, make):
        key = (kind, tuple(exprs), None if wrt is None else tuple(wrt))
        if key not in self._made:
            self._made[key] = make()
        return self._made[key]

    @cached_property
    def _arguments(self) -> tuple[dict, tuple]:
        """``({variable: "_y[k]", ...}, (_t, _y, _z, _p))``: how the generated function reads each
        variable from its four arguments, and those arguments as symbols."""
        names = {self.t: "_t"}
        for group, name in ((self.y, "_y"), (self.z, "_z"), (self.p, "_p")):
            names.update({s: f"{name}[{k}]" for k, s in enumerate(group)})
        return names, tuple(sp.Symbol(name) for name in ("_t", "_y", "_z", "_p"))

    def _lambdify(self, exprs):
        """The numpy function of ``(t, y, z, p)`` whose value is the list of ``exprs``' values (:data:`LAMBDIFY_CHUNK`
        at a time, the lists joined)."""
        exprs = list(exprs)
        if len(exprs) <= LAMBDIFY_CHUNK:
            return self._lambdify_piece(exprs)
        pieces = [self._lambdify_piece(exprs[i : i + LAMBDIFY_CHUNK]) for i in range(0, len(exprs), LAMBDIFY_CHUNK)]

        def joined(t, y, z, p):
            return [value for piece in pieces for value in piece(t, y, z, p)]

        return joined

    def _lambdify_piece(self, exprs):
        names, arguments = self._arguments
        exprs = [sp.sympify(e) for e in exprs]
        shared = shared_subexpressions(exprs)
        definitions = [(sp.Symbol(name), node) for node, name in shared.items()]
        # docstring_limit=0: lambdify would otherwise print every expression a second time for
        # the docstring
        # use_imps=False: no implemented_function is ever used here, and looking for one walks
        # every expression as a tree
        shapes = [shape_key(e, names, shared) for e in exprs]
        printer = NumericPrinter(names, shared, holds_re(exprs, shapes))
        # an expression of a known shape goes in as its text, the text lambdify would print (it has no
        # Subs, which lambdify would otherwise look for with a walk that rebuilds every expression)
        items = [
            text if (text := printer.shaped_text(e, shape)) is not None else e
            for e, shape in zip(exprs, shapes, strict=True)
        ]
        return sp.lambdify(
            arguments,
            items,
            NUMERIC_MODULES,
            printer=printer,
            docstring_limit=0,
            cse=lambda e: (definitions, e),
            use_imps=False,
        )

    def function(self, exprs):
        """Return ``F(t, y, z, p) -> ndarray, shape (len(exprs),)``."""
        return self._once("function", exprs, None, lambda: self._make_function(exprs))

    def _make_function(self, exprs):
        if not exprs:
            return lambda t, y, z, p: np.zeros(0)
        fn = self._lambdify(exprs)
        return lambda t, y, z, p: np.asarray(fn(t, y, z, p), dtype=float).reshape(len(exprs))

    def jacobian(self, exprs, wrt):
        """Return ``J(t, y, z, p) -> ndarray, shape (len(exprs), len(wrt))``."""
        return self._once("jacobian", exprs, wrt, lambda: self._make_jacobian(exprs, wrt))

    def _make_jacobian(self, exprs, wrt):
        shape = (len(exprs), len(wrt))
        rows, cols, entries = jacobian_entries(exprs, wrt, self.calculus)
        if not entries:
            return lambda t, y, z, p: np.zeros(shape)
        values = self.function(entries)

        def evaluate(t, y, z, p):
            out = np.zeros(shape)
            out[rows, cols] = values(t, y, z, p)
            return out

        return evaluate

    def batch_function(self, exprs):
        """Return ``F(t, Y, Z, P) -> ndarray, shape (B, len(exprs))`` for rows ``Y (B, n)`` etc."""
        return self._once("batch_function", exprs, None, lambda: self._make_batch_function(exprs))

    def _make_batch_function(self, exprs):
        return BatchFunction(exprs, (self.t, self.y, self.z, self.p), self._lambdify)

    def batch_jacobian(self, exprs, wrt):
        """Return ``J(t, Y, Z, P) -> ndarray, shape (B, len(exprs), len(wrt))``."""
        return self._once("batch_jacobian", exprs, wrt, lambda: self._make_batch_jacobian(exprs, wrt))

    def batch_jacobian_entries(self, exprs, wrt):
        """The Jacobian's structural nonzeros: ``(rows, cols, values)`` with ``values(t, Y, Z, P) ->
        ndarray, shape (B, nnz)`` (:func:`jacobian_entries`' order), for sparse use."""
        return self._once("batch_jacobian_entries", exprs, wrt, lambda: self._make_entries(exprs, wrt))

    def _make_entries(self, exprs, wrt):
        rows, cols, entries = jacobian_entries(exprs, wrt, self.calculus)
        values = self.batch_function(entries)
        return rows, cols, values

    def newton_jacobian(self, exprs, wrt):
        """Return ``J(t, Y, Z, P)`` for :func:`solve_algebraic`: :meth:`batch_jacobian`'s dense
        ndarray (B, len(exprs), len(wrt)) below :data:`~daemodel.compiling.linear.SPARSE_MIN_SIZE`
        columns, a :class:`~daemodel.compiling.linear.SparseStack` of the structural nonzeros from
        there on (no dense m x m is made)."""
        if len(wrt) < SPARSE_MIN_SIZE:
            return self.batch_jacobian(exprs, wrt)
        return self._once("newton_jacobian", exprs, wrt, lambda: self._make_sparse_jacobian(exprs, wrt))

    def _make_sparse_jacobian(self, exprs, wrt):
        rows, cols, values = self.batch_jacobian_entries(exprs, wrt)
        size = len(wrt)

        def evaluate(t, Y, Z, P):
            return SparseStack(rows, cols, values(t, Y, Z, P).reshape(len(Y), len(rows)), size)

        return evaluate

    def _make_batch_jacobian(self, exprs, wrt):
        shape = (len(exprs), len(wrt))
        rows, cols, entries = jacobian_entries(exprs, wrt, self.calculus)
        values = self.batch_function(entries)

        def evaluate(t, Y, Z, P):
            out = np.zeros((len(Y), *shape))
            if entries:
                out[:, rows, cols] = values(t, Y, Z, P)
            return out

        return evaluate


def jacobian_entries(exprs, wrt, calculus: Differentiator | None = None) -> tuple[np.ndarray, np.ndarray, list]:
    """The structurally nonzero entries of ``d exprs / d wrt``.

    Each expression is differentiated only by the variables that occur in it; derivatives that
    sympy simplifies to 0 are left out.

    Returns
    -------
    rows, cols : ndarray of int, shape (nnz,)
    entries : list of sympy.Expr, length nnz
        ``entries[k] = d exprs[rows[k]] / d wrt[cols[k]]``, row by row, columns ascending.
    """
    calculus = calculus or Differentiator()
    column = {w: j for j, w in enumerate(wrt)}
    rows, cols, entries = [], [], []
    for i, expr in enumerate(exprs):
        expr = sp.sympify(expr)
        for j in sorted(column[s] for s in calculus.free_symbols(expr) if s in column):
            derivative = calculus.diff(expr, wrt[j])
            if derivative != 0:
                rows.append(i)
                cols.append(j)
                entries.append(derivative)
    return np.array(rows, dtype=int), np.array(cols, dtype=int), entries


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


def project(Y0: np.ndarray, residual, jacobian, free: np.ndarray | None = None) -> np.ndarray:
    """The nearest states to the rows of ``Y0`` (B, n) with ``residual(Y) = 0``: the one projection
    onto the constraints (repair at compile time, ``consistent()``, the states after a switch).

    Iterates ``y = y0 - C^T mu`` with ``C C^T mu = c(y_k) + C (y0 - y_k)``: its fixed points
    satisfy ``c(y) = 0`` and ``y - y0`` in the row space of ``C``, the conditions for the least
    Euclidean change.  The pseudo-inverse keeps it well defined for redundant constraints.

    Parameters
    ----------
    Y0 : ndarray, shape (B, n)
    residual : callable (B, n) -> (B, L)
    jacobian : callable (B, n) -> (B, L, n)
    free : ndarray of bool, shape (n,), optional
        The states allowed to move (default all): the others keep their values, and the change of
        the free ones is the least (the columns of ``C`` of fixed states are left out).
    """
    Y0 = np.array(Y0, dtype=float)
    mask = np.ones(Y0.shape[1], dtype=bool) if free is None else np.asarray(free, dtype=bool)
    y = Y0.copy()
    for k in range(PROJECTION_MAXITER):
        r = residual(y)
        if k == 0:  # (C is dense, L x n, and C C^T is factored: refused above the dense limit, before either)
            L, n = r.shape[1], Y0.shape[1]
            check_dense(
                f"the projection onto the constraints ({L} constraint levels on {n} states)",
                max(L, math.isqrt(L * n)),
                "give initial states that satisfy the constraints (the projection is then not needed)",
            )
        C = jacobian(y) * mask  # (the columns of fixed states zeroed: they neither move nor count)
        rhs = r + np.einsum("bln,bn->bl", C, Y0 - y)
        mu = np.einsum("blk,bk->bl", np.linalg.pinv(C @ C.transpose(0, 2, 1)), rhs)
        y_new = Y0 - np.einsum("bln,bl->bn", C, mu)
        if np.max(np.abs(y_new - y), initial=0.0) <= 1e-15 * (1 + np.max(np.abs(y), initial=0.0)):
            return y_new
        y = y_new
    return y


def violations(residual: np.ndarray, Y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(tolerance (B,), violated (B, L))``: the one test of states on the z-free constraint levels.

    ``residual`` (B, L) of the states ``Y`` (B, n) is violated where above :data:`STATE_TOL`
    relative to ``1 + max|y|`` of its sample.
    """
    tol = STATE_TOL * (1 + np.max(np.abs(Y), axis=1, initial=0.0))
    return tol, np.abs(residual) > tol[:, None]


@dataclass(frozen=True, kw_only=True)
class NewtonTolerances:
    """When :func:`solve_algebraic` calls a sample converged, and how long it tries.

    Attributes
    ----------
    step : float
        The estimated error of the last iterate (the last step, times ``theta / (1 - theta)``
        once the contraction ``theta`` of two successive steps is known; a first step settles
        only when it is zero or the equations are linear) must be below
        ``step * (1 + max|x|)``: the iteration settled on a root instead of drifting towards one
        at infinity (``0 = exp(z)``).
    residual : float
        ... and every residual below ``residual * (1 + max(max|x|, (|J| |x|)_i))``: the rounding
        level of the equations with digits to spare.
    max_iterations : int
        Newton steps at most; a sample still moving then is reported as not converged.
    stall_rate, stall_step : float
        A sample whose contraction exceeds ``stall_rate`` with a step below ``stall_step * (1 +
        max|x|)`` has reached the rounding level of an ill-conditioned ``J``: settled, not failed.
    linear : bool
        ``F`` is affine in ``x`` (``J`` free of ``x``, as in mechanics): the first step is exact up
        to rounding, so it settles without a second.
    """

    step: float = NEWTON_STEP_TOL
    residual: float = NEWTON_RESIDUAL_TOL
    max_iterations: int = NEWTON_MAXITER
    stall_rate: float = NEWTON_STALL_RATE
    stall_step: float = NEWTON_STALL_TOL
    linear: bool = False


@dataclass(frozen=True)
class AlgebraicSolve:
    """Result of :func:`solve_algebraic` for a batch of B systems of size m.

    Attributes
    ----------
    x : ndarray, shape (B, m)
        The last iterate of each sample.
    residual : ndarray, shape (B, m)
        ``F(x)``.
    converged : ndarray of bool, shape (B,)
        Settled by :class:`NewtonTolerances` with a finite residual within its bound.  The caller
        decides what a sample that did not converge means; none may ignore it.
    singular : ndarray of bool, shape (B,)
        ``J`` was numerically singular at the last iterate of a sample that did not converge
        (the reason to report: the equations do not determine ``x`` there).
    iterations : int
    """

    x: np.ndarray
    residual: np.ndarray
    converged: np.ndarray
    singular: np.ndarray
    iterations: int


def solve_algebraic(F, J, x0: np.ndarray, tolerances: NewtonTolerances = NewtonTolerances()) -> AlgebraicSolve:
    """Damped Newton for ``F(x) = 0``, every sample of a batch at once: the one routine that
    solves for algebraic values (consistent initialisation, batched initial states, the states
    after a switch or event, the reference method's ``z(t, y)``, dense output).

    Parameters
    ----------
    F : callable (B, m) -> (B, m)
    J : callable (B, m) -> ndarray (B, m, m) or SparseStack
        A :class:`~daemodel.compiling.linear.SparseStack` (large m,
        :meth:`NumericSystem.newton_jacobian`) is factored sample by sample with a sparse LU, and
        no dense m x m is made.
    x0 : ndarray, shape (B, m)
        Starting values: they select the root (the branch) among several.
    tolerances : NewtonTolerances

    Each step is the least-squares solution of ``J dx = -F`` (well defined where J is singular;
    the caller checks the rank; :func:`~daemodel.compiling.linear.least_squares` or
    :meth:`~daemodel.compiling.linear.SparseStack.solve`), halved per sample until ``|F|`` does not grow (at most
    ``DAMPING_HALVINGS`` times).
    """
    x = np.array(x0, dtype=float, copy=True)
    B, m = x.shape
    if m == 0:
        return AlgebraicSolve(x, np.zeros((B, 0)), np.ones(B, dtype=bool), np.zeros(B, dtype=bool), 0)
    with np.errstate(all="ignore"):  # non-finite iterates end as not converged, reported by the caller
        r = F(x)
        settled = np.zeros(B, dtype=bool)
        previous = np.full(B, np.nan)  # each sample's last step size, for the contraction theta
        iterations = 0
        while iterations < tolerances.max_iterations:
            active = ~settled & np.isfinite(r).all(axis=1)
            if not active.any():
                break
            iterations += 1
            # (the samples still iterating, as a slice of the batch: the whole batch, the common case,
            # without copies)
            rows = slice(None) if active.all() else np.flatnonzero(active)
            xa, ra = x[rows], r[rows]
            Ja = J(x)
            sparse = isinstance(Ja, SparseStack)
            Ja = Ja.take(rows) if sparse else Ja[rows]
            dx = Ja.solve(-ra) if sparse else least_squares(Ja, -ra)
            norm = np.sqrt(np.einsum("bi,bi->b", ra, ra))
            step = np.ones(len(xa))
            trial = x.copy()
            trial[rows] = xa + dx
            r_new = F(trial)[rows]
            # (affine equations: the full step is exact up to rounding, which halving it cannot improve on; from a
            # start at the rounding level of the residual it only took 3 more evaluations of F, and 1/8 of the step)
            for _ in range(0 if tolerances.linear else DAMPING_HALVINGS):
                worse = ~(np.sqrt(np.einsum("bi,bi->b", r_new, r_new)) <= norm)
                if not worse.any():
                    break
                step[worse] /= 2
                trial[rows] = xa + step[:, None] * dx
                r_new = F(trial)[rows]
            x[rows], r[rows] = trial[rows], r_new
            xa = x[rows]
            size = step * np.abs(dx).max(axis=1)
            scale = 1 + np.abs(xa).max(axis=1)
            last = previous[rows]
            theta = size / last  # nan on the first step, inf after a zero step
            contracting = theta < 1
            error = np.where(contracting, size * theta / np.where(contracting, 1 - theta, 1), size)
            # a first step has no contraction to estimate its error from: only a start that was a root
            # (no step at all) settles on it, unless the equations are linear (the step is exact)
            first = np.isnan(last)
            error = np.where(first, 0.0 if tolerances.linear else np.where(size == 0, 0.0, np.inf), error)
            stalled = (theta > tolerances.stall_rate) & (size <= tolerances.stall_step * scale)
            candidate = (error <= tolerances.step * scale) | stalled
            if candidate.any():  # (the residual's bound only where the steps have settled)
                scaled = Ja.abs_product(xa) if sparse else np.einsum("bij,bj->bi", np.abs(Ja), np.abs(xa))
                settled[rows] = candidate & residual_settled(r_new, scale, scaled, tolerances)
            previous[rows] = size
        fine = np.isfinite(r).all(axis=1) & np.isfinite(x).all(axis=1)
        converged = settled & fine
        singular = np.zeros(B, dtype=bool)
        if not converged.all():
            failed = ~converged & np.isfinite(x).all(axis=1)
            if failed.any():
                Jf = J(x)
                if isinstance(Jf, SparseStack):
                    Jf = Jf.take(failed)
                    finite = Jf.finite()
                    singular[failed] = finite & Jf.singular()
                else:
                    Jf = Jf[failed]
                    finite = np.isfinite(Jf).all(axis=(1, 2))
                    rank = np.zeros(len(Jf), dtype=int)
                    if finite.any():
                        rank[finite] = np.linalg.matrix_rank(Jf[finite])
                    singular[failed] = finite & (rank < m)
    return AlgebraicSolve(x, r, converged, singular, iterations)


def residual_settled(r: np.ndarray, scale: np.ndarray, scaled: np.ndarray, tolerances: NewtonTolerances) -> np.ndarray:
    """Whether the residuals ``r`` (B, m) of iterates ``x`` are at the rounding level that :func:`solve_algebraic`
    accepts (:attr:`NewtonTolerances.residual`): every ``|r_i| <= residual (1 + max(max|x|, (|J| |x|)_i))``, given
    ``scale = 1 + max|x|`` (B,) and ``scaled = |J| |x|`` (B, m).  False where ``r`` is not finite."""
    bound = tolerances.residual * (1 + np.maximum((scale - 1)[:, None], scaled))
    return (np.abs(r) <= bound).all(axis=1)


def _guess(symbols, values) -> str:
    return ", ".join(f"{z.name} = {v:.6g}" for z, v in zip(symbols, values, strict=True))


def initialise(
    numeric: NumericSystem,
    constraints,
    aliases,
    t0: float,
    given: dict,
    p: np.ndarray,
    repair: bool,
    guesses: dict | None = None,
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
    guesses : dict name -> float, optional
        Newton's starting values for algebraic variables without a given value (``m.guess``):
        they pick a root and claim nothing.
    """
    guesses = guesses or {}
    notes = []
    y0 = np.array([given[y.name] for y in numeric.y], dtype=float)
    empty_z = np.zeros(len(numeric.z))

    hidden = hidden_constraints(constraints)
    exprs = [e for _, _, e in hidden]
    c_fun = numeric.function(exprs)
    residual = c_fun(t0, y0, empty_z, p)
    (tol,), (violated,) = violations(residual[None, :], y0[None, :])
    bad = [(hidden[i], residual[i]) for i in np.flatnonzero(violated)]
    if bad and not repair:
        listing = "; ".join(f"{label}: {name} = {value:.6g}" for (name, label, _), value in bad)
        raise InconsistentInitialStateError(
            f"the initial state violates {listing} (tolerance {tol:.1e}). Fix the initial values "
            "or compile(repair=True) to project them onto the constraint manifold"
        )
    if bad:
        c_jac = numeric.jacobian(exprs, numeric.y)  # only a repair needs it
        y_new = project(
            y0[None, :],
            lambda Y: c_fun(t0, Y[0], empty_z, p)[None, :],
            lambda Y: c_jac(t0, Y[0], empty_z, p)[None, :, :],
        )[0]
        after = c_fun(t0, y_new, empty_z, p)
        if violations(after[None, :], y0[None, :])[1].any():
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
    H, Hz = numeric.batch_function(determining), numeric.newton_jacobian(determining, numeric.z)
    # the guess selects the branch of roots; a given value without a guess starts Newton too (a
    # claim that is a root is then its own nearest root), and is checked below either way
    guess = np.array([[guesses.get(z.name, given.get(z.name, 0.0)) for z in numeric.z]], dtype=float)
    Y, P = y0[None, :], p[None, :]
    result = solve_algebraic(lambda Z: H(t0, Y, Z, P), lambda Z: Hz(t0, Y, Z, P), guess)
    z0, residual = result.x[0], result.residual[0]
    with np.errstate(all="ignore"):
        jacobian = Hz(t0, Y, result.x, P)
        jacobian = jacobian.matrix(0) if isinstance(jacobian, SparseStack) else jacobian[0]
    try:
        check_rank(jacobian, constraints, numeric.z, t0)  # a singular H_z explains a failed Newton
    except SingularSystemError as error:
        if result.converged[0] or not np.array_equal(result.x, guess):
            raise
        # Newton never left its start: the matrix is singular there, not necessarily at a root
        unguessed = [z.name for z in numeric.z if z.name not in given and z.name not in guesses]
        hint = f"; no guess was given for {', '.join(unguessed)}" if unguessed else ""
        raise SingularSystemError(
            f"{error}: that point is Newton's starting guess {_guess(numeric.z, guess[0])}, from which it cannot "
            f"take a step{hint}. Give a guess near the root you want, e.g. m.guess({numeric.z[0].name}=1.0) "
            "(a starting value that picks the root, not a claim)"
        ) from None
    if not result.converged[0]:
        worst = int(np.argmax(np.where(np.isfinite(residual), np.abs(residual), np.inf))) if residual.size else 0
        values = ", ".join(f"{z.name} = {v:.6g}" for z, v in zip(numeric.z, z0, strict=True))
        raise InitialisationError(
            f"Newton for the initial algebraic values did not converge: {constraints[worst].label} has residual "
            f"{residual[worst]:.3g} at {values} after {result.iterations} steps from {_guess(numeric.z, guess[0])}, "
            "and the steps have not settled (a constraint with no real root, such as 0 = exp(z), drives z "
            "towards infinity). Check that the constraints have a root at t0, or give a starting value with "
            "m.guess(<algebraic>=...)"
        )

    chosen = [(z, g, v) for z, g, v in zip(numeric.z, guess[0], z0, strict=True) if z.name in guesses]
    if chosen:
        notes.append(
            "root chosen by the guess: "
            + ", ".join(f"{z.name} = {v:.10g} (Newton from m.guess {z.name} = {g:.6g})" for z, g, v in chosen)
        )
    claimed = {z.name: given[z.name] for z in numeric.z if z.name in given}
    if claimed and not repair:
        _check_branch_claim(numeric, H, Hz, t0, Y, P, z0, claimed)

    values = dict(zip((v.name for v in numeric.y + numeric.z), np.concatenate([y0, z0]).tolist(), strict=True))
    alias_fun = numeric.function([e for _, e in aliases])
    values.update(zip((n for n, _ in aliases), alias_fun(t0, y0, z0, p).tolist(), strict=True))
    state_names = {y.name for y in numeric.y}
    for name, value in given.items():
        if name in state_names or name not in values:
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


def _check_branch_claim(numeric, H, Hz, t0, Y, P, z0, claimed: dict) -> None:
    """Refuse given algebraic values that are a root of the determining equations but not the root
    that Newton reaches from the guesses (another branch), naming both; other disagreements are left
    to the caller's check against the consistent values."""
    Zc = np.array([[claimed.get(z.name, v) for z, v in zip(numeric.z, z0, strict=True)]])
    off = [
        (z.name, claimed[z.name], v)
        for z, v in zip(numeric.z, z0, strict=True)
        if z.name in claimed and abs(claimed[z.name] - v) > ALGEBRAIC_TOL * (1 + abs(v))
    ]
    if not off or not is_root(H(t0, Y, Zc, P), Hz(t0, Y, Zc, P), Zc)[0]:
        return
    listing = ", ".join(f"{name} = {value:.10g}" for name, value, _ in off)
    nearest = ", ".join(f"{name} = {float(root)!r}" for name, _, root in off)
    raise WrongBranchError(
        f"initial value {listing} is a root of the constraints, but of another branch than the one the guess "
        f"selects: the root nearest the guess is {nearest}. Drop the initial value, or move m.guess(...) next to "
        "it to choose its branch"
    )


def is_root(residual: np.ndarray, jacobian, Z: np.ndarray) -> np.ndarray:
    """``(B,)`` whether the residuals (B, m) of ``Z`` (B, m) are within Newton's residual bound
    (:class:`NewtonTolerances`), with the Jacobian at ``Z`` (ndarray (B, m, m) or SparseStack)
    for its scale."""
    with np.errstate(all="ignore"):
        if isinstance(jacobian, SparseStack):
            scaled = jacobian.abs_product(Z)
        else:
            scaled = np.einsum("bij,bj->bi", np.abs(jacobian), np.abs(Z))
        scale = 1 + np.maximum(np.max(np.abs(Z), axis=1, initial=0.0)[:, None], scaled)
        return np.all(np.abs(residual) <= NEWTON_RESIDUAL_TOL * scale, axis=1)

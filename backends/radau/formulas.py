"""RADAU5's formulas, written once over an array namespace: the step-size controller, the error norm
and Newton's convergence tests.

The Python path (:mod:`.control`, :mod:`.error`, :mod:`.newton`) calls them on Python floats
(:data:`SCALAR`) or on the engine's arrays (:class:`ArrayOps` of numpy or torch); the compiled
attempt and run (:mod:`.compiled`, :mod:`.loop`) call the same functions on casadi symbols
(:data:`CASADI`), so that both make the same arithmetic in the same order and take the same steps,
bit for bit.  A namespace supplies the few operations whose spelling differs (``minimum``,
``maximum``, ``where``, the logical operators, ``isclose``, the root mean square); everything else
is written with Python's operators, which all of them share.  ``where`` evaluates both branches;
``cond`` takes them as functions, evaluated lazily where the namespace branches in Python (a
division by zero in the branch not taken must not raise there).
"""

from __future__ import annotations

import math
from typing import NamedTuple

# ---- the step-size controller (Hairer & Wanner, IV.8; RADAU5's values) ---------------------------
# Safety factor of the next h, and bounds on h_new / h.
SAFETY, MIN_FACTOR, MAX_FACTOR = 0.9, 0.2, 8.0
# A rejected step shrinks h at least by this factor (RADAU5: min(quot, 0.9)); a failed Newton halves it.
REJECTED_MAX_FACTOR, NEWTON_FAILURE_FACTOR = 0.9, 0.5
# Estimates below this count as it (no infinite growth), and Gustafsson's prediction reads the last
# accepted step's estimate as at least ACCEPTED_ERROR_FLOOR (RADAU5's ERRACC).
ERROR_FLOOR, ACCEPTED_ERROR_FLOOR = 1e-10, 1e-2
# Step size underflow: h below this times max(1, |t|).
UNDERFLOW = 1e-14
# The systems factored for a step of h_f serve a step of h within this many float64 epsilons of (|t| + |h|) of
# it (factors_serve): a step is the one t's spacing makes of the controller's h (step_length), so that an h kept
# by the keep band moves by up to eps |t + h| a step, and the chain of 20 pendulums at rtol 1e-4 factored 4 of
# its 15 times for such a move alone.  Newton's matrix is an approximation (its Jacobian is kept while Newton
# contracts): a relative change d of h moves it and the error estimate's by d, 1e-13 here.  64: the walk of the
# roundings stays within it for thousands of kept steps.
FACTORS_ROUNDING = 64
EPS = 2.0**-52
# t has reached t1 within this tolerance relative to |t1 - t0| (a step's end: to its h), or within END_ROUNDING
# of |t1| (a few float64 spacings there: t + (t1 - t) rounds to within one of t1).  Relative to |t1| alone,
# 1e-13 of t1 = 1e15 + 2 is 100, more than the span: radau ended at its start, 0 steps, "success", and at
# t0 = 1e13 each step within 1 of t1 ended at t1 (u 0.61 off at rtol 1e-8, "success"; now 1.1e-3 off, still
# "success": t + h rounds to t's spacing, 2e-3 there, and that is not flagged yet).
END_TOLERANCE, END_ROUNDING = 1e-13, 4 * 2.0**-52
# A step that would leave less than this times h before t1 is stretched to end there.
STRETCH = 1e-10
# ---- the start guess ----------------------------------------------------------------------------
# The stage values of an algebraic variable of index 2 (or 3, reduced) carry a part that is not smooth
# across the nodes: Z_i moves by (A^-1 1)_i g(y_n) / (h g_y f_z), the start value's constraint defect
# over h (A^-1 1 = (11.0, -3.6, 2.3, -2.3, 5.0) at s = 5).  The last step's whole collocation polynomial
# (degree s) carries it to the next stages 19,530 times as large at s = 5 (h / h_old = 1; 1,072,274 at
# s = 7), so that the guess of z was off by hundreds of units of its tolerance, simplified Newton
# failed, h shrank, and z's stages, weighted by h, drifted further (the pendulum over [0, 1000] at
# rtol 1e-6, atol 1e-8, s = 5: 3,924 failures in 21,225 attempts, steps down to 2.5e-8, where z was 0.39
# off its hidden constraint; at rtol 1e-5 and 1e-4 a StepLimitError).  Such variables are guessed from
# the polynomial of degree s - 1 that, with a multiple of that pattern, meets their nodes
# (:func:`~daemodel.collocation.extrapolation_polynomial`'s ``pattern``): blind to the pattern, and
# exact to one degree less.  (A cubic through the last four nodes, as blind to it nearly, was 10x
# less accurate at tight tolerances: car axis at rtol 1e-8, 7.8e-7 from the reference against 7.6e-8.)
# s = 3 keeps the whole polynomial (HIGH_INDEX_GUESS_MIN_STAGES).
HIGH_INDEX_GUESS_MIN_STAGES = 4


def high_index_columns(s: int, n: int, z_index) -> list[int] | None:
    """The columns (of the n + m) of the algebraic variables of index 2 or 3, whose start guess is blind to
    their stages' pattern (:func:`high_index_pattern`); None where there are none or s is below
    :data:`HIGH_INDEX_GUESS_MIN_STAGES`."""
    columns = [n + k for k, index in enumerate(z_index) if index >= 2]
    return columns if columns and s >= HIGH_INDEX_GUESS_MIN_STAGES else None


def high_index_pattern(A):
    """``A^-1 1`` (s,): how an index-2 algebraic variable's stages move with the start value's constraint
    defect (numpy, float64)."""
    import numpy as np

    A = np.asarray(A, dtype=float)
    return np.linalg.solve(A, np.ones(len(A)))


# ---- Newton -------------------------------------------------------------------------------------
# Newton is declared diverging when an increment is not at least this much smaller than the last.
DIVERGENCE_THETA = 0.99
# RADAU5's start: the last step's rate eta (at least eps) to this power predicts the first iteration's.
START_RATE_POWER = 0.8
# The last increment's norm counts as at least this in the contraction (no division by zero).
TINY_NORM = 1e-300
# RADAU5's contraction from the third iteration on, for this many stages or more: the geometric mean
# sqrt(q_k q_(k-1)) of the last two ratios of increments (one ratio alone, at the second), steadier where the
# increments do not shrink evenly (the pendulum over [0, 20] at rtol 1e-3..1e-6: s = 5 2,586 -> 1,497
# attempts, 246 -> 161 Newton failures).  Three stages keep the last ratio: the mean moved their results
# both ways (the squeezer's w at rtol 1e-7: 24 -> 180 rtol, at 1e-4: 138 -> 15).
GEOMETRIC_CONTRACTION_STAGES = 5
# Newton to rounding (the fixed grid): increments that stop shrinking (contraction above
# STAGNATION_THETA) while within STAGNATION_FACTOR of the tolerance have reached the rounding floor
# of the residual (converged, not diverging).
STAGNATION_THETA, STAGNATION_FACTOR = 0.5, 100.0
# How a simplified Newton iteration ends (newton_iteration), the failures in the order in which they win.
CONVERGED, NON_FINITE, DIVERGING, SLOW, NOT_CONVERGED = 0, 1, 2, 3, 4
# A compiled attempt's failure on values that turned non-finite: it fails as a diverging Newton does (h
# shrinks); the compiled step does not tell where they arose, the general path names that where h underflows.
UNNAMED_NON_FINITE = "non-finite values"
# What follows a convergence (after_convergence): iterating on, a check of it by one more increment,
# f evaluated at the final stages (the error estimate reads it).
ITERATING, CHECK, EVALUATE = 0, 1, 2


class ScalarOps:
    """The namespace of Python floats and bools (the controller's scalars on the Python path)."""

    minimum, maximum, abs = staticmethod(min), staticmethod(max), staticmethod(abs)

    @staticmethod
    def where(condition, a, b):
        return a if condition else b

    @staticmethod
    def cond(condition, then, otherwise):
        return then() if condition else otherwise()

    guard = cond

    @staticmethod
    def and_(a, b):
        return a and b

    @staticmethod
    def or_(a, b):
        return a or b

    @staticmethod
    def not_(a):
        return not a

    @staticmethod
    def isclose(a, b, rel_tol, abs_tol=0.0):
        return math.isclose(a, b, rel_tol=rel_tol, abs_tol=abs_tol)

    @staticmethod
    def branch(name, condition, then, otherwise, *operands):
        """``then(*operands)`` where ``condition``, else ``otherwise(*operands)`` (only that one runs)."""
        return then(*operands) if condition else otherwise(*operands)


class ArrayOps:
    """The namespace of an engine's arrays (``xp``: numpy or torch), the samples along the first axis."""

    def __init__(self, xp):
        self.xp = xp

    def maximum(self, a, b):
        """The elementwise larger; a Python float bound clips (torch's maximum takes tensors only)."""
        if isinstance(b, float):
            return self.xp.clip(a, b, None)
        if isinstance(a, float):
            return self.xp.clip(b, a, None)
        return self.xp.maximum(a, b)

    def where(self, condition, a, b):
        """``a`` where ``condition``, else ``b``; a Python bool picks one (the Newton state's Python numbers)."""
        if isinstance(condition, bool):
            return a if condition else b
        return self.xp.where(condition, a, b)

    def cond(self, condition, then, otherwise):
        return then() if condition else otherwise()

    def guard(self, condition, then, otherwise):
        """``then()`` where ``condition``, else ``otherwise()``: only the one taken runs (:meth:`CasadiOps.guard`)."""
        return then() if condition else otherwise()

    def any(self, flags) -> bool:
        """Whether any sample's flag is set: a Python bool (one read of the device), for Python's branches."""
        return flags if isinstance(flags, bool) else bool(flags.any())

    def and_(self, a, b):
        return a & b  # (elementwise; Python bools stay bools)

    def or_(self, a, b):
        return a | b

    def not_(self, a):
        return (not a) if isinstance(a, bool) else ~a

    def rms(self, x):
        """Root mean square over all but the first (batch) axis, shape (B,)."""
        x = x.reshape(x.shape[0], -1)
        return self.xp.sqrt((x * x).sum(axis=-1) / x.shape[-1])

    def rms_ratio(self, a, b, out=None):
        """:meth:`rms` of ``a / b``, squared in place: one temporary of a's size, not two (the same bits), or
        none where ``out`` (an array of a's shape, overwritten) is given."""
        x = a / b if out is None else self.xp.divide(a, b, out=out)
        x *= x
        x = x.reshape(x.shape[0], -1)
        return self.xp.sqrt(x.sum(axis=-1) / x.shape[-1])

    def concat(self, parts):
        return self.xp.concatenate(parts, axis=-1)

    def ones(self, n: int):
        return self.xp.ones(n)

    def powers(self, base, exponents):
        return base**exponents


class CasadiOps:
    """The namespace of casadi symbols (SX or MX; the compiled attempt and run, one trajectory)."""

    def __getattr__(self, name):  # (casadi is imported where the compiled functions are built)
        import casadi

        table = {
            "minimum": casadi.fmin,
            "maximum": casadi.fmax,
            "abs": casadi.fabs,
            "where": casadi.if_else,
            "and_": casadi.logic_and,
            "or_": casadi.logic_or,
            "not_": casadi.logic_not,
        }
        if name not in table:
            raise AttributeError(name)
        return table[name]

    @staticmethod
    def cond(condition, then, otherwise):
        """Both branches, selected (a tuple of values: each selected)."""
        import casadi

        a, b = then(), otherwise()
        if isinstance(a, tuple):
            return tuple(casadi.if_else(condition, x, y) for x, y in zip(a, b, strict=True))
        return casadi.if_else(condition, a, b)

    @staticmethod
    def guard(condition, then, otherwise):
        """``then()`` where ``condition``, else ``otherwise()``, for a ``then`` whose values are already
        ``otherwise``'s where ``condition`` is false (through its own masks and the caller's): here
        ``then()`` alone, no select (Python's namespaces run only the branch taken, and skip ``then``'s
        work where it is idle)."""
        return then()

    @staticmethod
    def branch(name, condition, then, otherwise, *operands):
        """``then(*operands)`` where ``condition``, else ``otherwise(*operands)``, as a casadi switch named
        ``name`` that runs only the branch taken (MX).  ``operands``: expressions, or tuples of them;
        the branches see them as symbols, and must use nothing else from outside, and return the same
        structure of the same shapes (Python numbers: 1 x 1)."""
        import casadi

        flat = flatten(operands)
        symbols = [casadi.MX.sym(f"{name}_{k}", x.sparsity()) for k, x in enumerate(flat)]
        args = unflatten(operands, iter(symbols))
        taken, other = then(*args), otherwise(*args)
        pairs = [
            [casadi.MX(float(x)) if isinstance(x, (bool, int, float)) else x for x in flatten(out)]
            for out in (taken, other)
        ]
        # an operand both branches pass through is the operand itself; the switch takes only the operands
        # its other outputs read (each argument is a copy: the factors are thousands of numbers)
        through = {
            k: i
            for k, (a, b) in enumerate(zip(*pairs, strict=True))
            for i, x in enumerate(symbols)
            if a is x and b is x
        }
        switched = [k for k in range(len(pairs[0])) if k not in through]
        outputs = [[out[k] for k in switched] for out in pairs]
        free = {x.name() for out in outputs for y in out for x in casadi.symvar(y) if x.is_symbolic()}
        read = [i for i, x in enumerate(symbols) if x.is_symbolic() and x.name() in free]  # (an empty one is not)
        functions = [
            casadi.Function(f"{name}_{kind}", [symbols[i] for i in read], out)
            for kind, out in zip(("then", "else"), outputs, strict=True)
        ]
        results = casadi.Function.if_else(name, *functions).call([condition, *(flat[i] for i in read)])
        values = dict(zip(switched, results, strict=True))
        values.update({k: flat[i] for k, i in through.items()})
        return unflatten(taken, iter(values[k] for k in range(len(pairs[0]))))

    @staticmethod
    def any(flag):
        return flag  # (one trajectory: the norm is a scalar)

    @staticmethod
    def isclose(a, b, rel_tol, abs_tol=0.0):
        """``math.isclose``'s formula."""
        import casadi

        diff = casadi.fabs(b - a)
        return casadi.logic_or(
            casadi.logic_or(diff <= casadi.fabs(rel_tol * b), diff <= casadi.fabs(rel_tol * a)),
            casadi.logic_or(diff <= abs_tol, a == b),
        )

    @staticmethod
    def rms(x):
        import casadi

        return casadi.sqrt(casadi.sumsqr(x) / x.numel())

    @staticmethod
    def rms_ratio(a, b):
        return CasadiOps.rms(a / b)

    @staticmethod
    def concat(parts):
        import casadi

        return casadi.vertcat(*parts)

    @staticmethod
    def ones(n: int):
        import casadi

        return casadi.DM.ones(n)

    @staticmethod
    def powers(base, exponents):
        import casadi

        return casadi.vertcat(*(base ** float(k) for k in exponents))


def flatten(values) -> list:
    """The leaves of nested tuples (a value that is no tuple: itself)."""
    if not isinstance(values, tuple):
        return [values]
    return [leaf for value in values for leaf in flatten(value)]


def unflatten(like, leaves):
    """Nested tuples shaped as ``like``, of the next values of the iterator ``leaves``."""
    if not isinstance(like, tuple):
        return next(leaves)
    return tuple(unflatten(value, leaves) for value in like)


SCALAR, CASADI = ScalarOps(), CasadiOps()


# ---- the controller -----------------------------------------------------------------------------
def factors_serve(xp, factors_h, h, t):
    """Whether the systems factored for a step of ``factors_h`` (0: none) serve the step of ``h`` from ``t``:
    ``h`` is theirs to within the rounding of t + h (:data:`FACTORS_ROUNDING`)."""
    close = xp.abs(h - factors_h) <= FACTORS_ROUNDING * EPS * (xp.abs(t) + xp.abs(h))
    return xp.and_(factors_h > 0, close)


def underflow(xp, h, t, t1=None):
    """Whether ``h`` is below the step size underflow's threshold at ``t``; a step ``h`` that reaches ``t1``
    (where given) is no underflow, however short: a span shorter than the threshold is taken in one step."""
    below = h < UNDERFLOW * xp.maximum(1.0, xp.abs(t))
    return below if t1 is None else xp.and_(below, h < t1 - t)


def step_length(xp, h, t, t1):
    """``h`` shortened to end at ``t1``, or stretched to it where less than :data:`STRETCH` h would be left,
    then the step that float64 makes from ``t``: to where it ends (:func:`step_end`), minus t.

    t + h rounds to t's float64 spacing: the step attempted with h ended at t + h rounded, and the solution
    moved as over h there (x' = v, v' = -x from t0 = 1e13 over 2 at rtol 1e-8: 1.1e-3 off, "success").  The
    step taken is exact (t and t + h are within a factor 2 of each other: Sterbenz), so that t advances by the
    very h the stages were solved over.  (On casadi symbols ``(t + h) - t`` would be simplified to h; the
    switch of :func:`step_end` in between is not.)"""
    h = xp.minimum(h, t1 - t)
    h = xp.where((t1 - t) - h < STRETCH * h, t1 - t, h)
    return step_end(xp, t, h, t1) - t


def step_end(xp, t, h, t1):
    """Where the step from ``t`` with ``h`` ends: ``t1`` itself where it ends within rounding of it."""
    return xp.where(xp.isclose(t + h, t1, END_ROUNDING, END_TOLERANCE * xp.abs(h)), t1, t + h)


def finished(xp, t, t0, t1):
    """Whether the integration over ``(t0, t1)`` has reached ``t1`` at ``t``: never at ``t0`` before ``t1`` (a
    span of a few float64 spacings of t1 is within :data:`END_ROUNDING` of it: from t0 = 1e6 over 3e-10, radau
    took no step and returned x(t0) alone, "success", where x' = 1/(t1 - t0) gives x(t1) = x(t0) + 1)."""
    near = xp.and_(xp.isclose(t, t1, END_ROUNDING, END_TOLERANCE * xp.abs(t1 - t0)), t > t0)
    return xp.not_(xp.and_(t < t1, xp.not_(near)))


def error_quotient(xp, err, k, s: int, iterations: int):
    """RADAU5's ``h_new / h`` from the step's error norm ``err`` (order s + 1): the safety factor,
    lowered where Newton needed ``k`` of its ``iterations``, times ``err^(-1/(s+1))``."""
    factor = xp.minimum(SAFETY, SAFETY * (2 * iterations + 1) / (2 * iterations + k))
    return factor * xp.maximum(err, ERROR_FLOOR) ** (-1.0 / (s + 1))


def accepted(xp, failed, err):
    """Whether the attempt is accepted: Newton converged (not ``failed``) and the error norm is at most 1."""
    return xp.and_(xp.not_(failed), err <= 1)


def rejected_step(xp, h, quot, failed):
    """The next h after a rejected attempt: halved after a failed Newton, else by the quotient (bounded)."""
    shrunk = h * xp.maximum(MIN_FACTOR, xp.minimum(quot, REJECTED_MAX_FACTOR))
    return xp.where(failed, h * NEWTON_FAILURE_FACTOR, shrunk)


def next_step(xp, h, err, quot, s: int, last, predictive, rejected_last, keep, jac_kept):
    """The next h after an accepted step of ``h`` with error norm ``err`` (``quot``: :func:`error_quotient`),
    and the ``(h, err)`` that Gustafsson's prediction reads at the next one.

    ``last``: the last accepted step's ``(h, err)`` (h 0: none yet); ``predictive``: Gustafsson's
    predictive controller, the smaller of its h and the quotient's; ``rejected_last``: the attempt
    before was rejected (h does not grow then); ``keep``: the band of ``h_new / h`` within which h
    stays (and with it the factorisations) where the Jacobian is kept (``jac_kept``).
    """
    h_acc, err_acc = last
    change = xp.minimum(MAX_FACTOR, xp.maximum(MIN_FACTOR, quot))

    def gustafsson():
        predicted = SAFETY * (h / h_acc) * (err_acc / xp.maximum(err, ERROR_FLOOR) ** 2) ** (1.0 / (s + 1))
        return xp.minimum(change, xp.minimum(MAX_FACTOR, xp.maximum(MIN_FACTOR, predicted)))

    change = xp.cond(xp.and_(predictive, h_acc > 0), gustafsson, lambda: change)
    new_h = xp.where(rejected_last, h * xp.minimum(1.0, change), h * change)
    quotient = new_h / h
    banded = xp.and_(xp.and_(keep[0] <= quotient, quotient <= keep[1]), jac_kept)
    return xp.where(banded, h, new_h), (h, xp.maximum(err, ACCEPTED_ERROR_FLOOR))


# ---- the first step ------------------------------------------------------------------------------
# The first step is at least this (times max(1, |t0|)): 1e4 times the step size underflow's threshold.
INITIAL_STEP_FLOOR = 1e-10


def initial_step(xp, rms, y, f0, probe, atol, rtol, stages: int, t0, t1):
    """Hairer-Wanner's starting step (see :meth:`.control.Radau5Controller.initial_step`) of the states ``y``
    with ``f0`` = f there: ``rms`` the worst sample's root mean square, ``probe(h0)`` f at ``(t0 + h0, y +
    h0 f0)`` (the algebraic variables held).  Not where there are no states (the caller's).  The probe's
    step, before :func:`floored_step` lifts it: the controller refilters no estimate above it before its
    first accepted step (:func:`refiltered_here`)."""
    sc = error_scale(atol, rtol, xp.abs(y), 1.0)  # (the states: weight 1)
    d0, d1 = rms(y / sc), rms(f0 / sc)
    # (f0 not finite: 1e-6 on every engine, where numpy's minimum passed a NaN on and casadi's dropped it)
    small = xp.or_(xp.or_(d0 < 1e-5, d1 < 1e-5), xp.not_(d1 < math.inf))
    h0 = xp.cond(small, lambda: 1e-6, lambda: 0.01 * d0 / d1)
    h0 = xp.minimum(h0, t1 - t0)
    d2 = rms((probe(h0) - f0) / sc) / h0
    d = xp.maximum(d1, d2)

    def probed():  # (a probe that left f's domain: a step that long is no start)
        flat = lambda: xp.minimum(100 * h0, xp.maximum(1e-6, h0 * 1e-3))  # noqa: E731
        return xp.cond(d <= 1e-15, flat, lambda: xp.minimum(100 * h0, (0.01 / d) ** (1.0 / (stages + 1))))

    h = xp.cond(d2 < math.inf, probed, lambda: h0 * 1e-3)  # (NaN: not finite)
    return xp.minimum(h, t1 - t0)


def floored_step(xp, h, t0, t1):
    """The first step: the probe's ``h`` (:func:`initial_step`) lifted to :data:`INITIAL_STEP_FLOOR`
    ``max(1, |t0|)``, within t_span.  (A start on a state near 0 moving fast, as after an event, made 9e-15
    there: underflow at once.)  The floor is no accuracy claim: from t0 = 1e17 it lifts the oscillator's
    0.013 to 1e7, and only the unfiltered estimate judges such a step (:func:`refiltered_here`)."""
    return xp.minimum(xp.maximum(h, INITIAL_STEP_FLOOR * xp.maximum(1.0, xp.abs(t0))), t1 - t0)


def refiltered_here(xp, first, h, h_acc, trusted):
    """Whether an attempt of ``h`` may have its estimate refiltered (:func:`error_norm`): a ``first`` one
    (the first of a run, or one after a rejection) once a step was accepted (``h_acc`` > 0), and before
    that only up to ``trusted``, the probe's step (:func:`initial_step`).

    The refiltered estimate is ``(I - h gamma0 J)^-1`` applied once more to the estimate: every mode of
    ``|h lambda| >> 1`` is damped in it, as the step damps it (L-stable), and that is right for a decaying
    mode alone.  An oscillator's ``h omega = 1e7`` (a user's h0, or the floor of :func:`floored_step` at
    t0 = 1e17) read 0.1 refiltered, where the step took ``x^2 + v^2`` from 1 to 1e-79 ("success"); the
    unfiltered estimate reads the step's whole damping there (``-y0``: rejected).  Steps up to the probe's
    are RADAU5's own first steps; the ones above it shrink, unfiltered, to it (or underflow by name)."""
    return xp.and_(first, xp.or_(h_acc > 0, h <= trusted))


# ---- the error estimate's norm ------------------------------------------------------------------
def index_weights(xp, h, n: int, exponents):
    """``h^(k-1)`` for each component (``exponents``: each algebraic variable's k - 1), 1 for the n states."""
    return xp.concat([xp.ones(n), xp.powers(h, exponents)])


def error_scale(atol, rtol, u_ref, weights):
    """The error's unit in each component, ``(atol + rtol |u|) / h^(k-1)`` (``u_ref``: |u|)."""
    return (atol + rtol * u_ref) / weights


def error_rhs(xp, quadrature, gamma0, f0, zeros):
    """The right-hand side of the estimate's system, ``[quadrature / gamma0 + f0; 0]`` (the constraint
    rows carry no local error: each step's Newton enforces g at its stages)."""
    return xp.concat([quadrature / gamma0 + f0, zeros])


def error_norm(xp, err, scale, first, refiltered):
    """RADAU5's scaled norm of the estimate ``err``; at a ``first`` (or after a rejected) step where it
    is 1 or more, that of the estimate filtered once more (``refiltered()``, Hairer-Wanner)."""
    norm = xp.rms_ratio(err, scale)  # (squared in place: the same bits as rms(err / scale), 0.8 MB less at 10^5)
    again = xp.and_(first, xp.any(norm >= 1))
    return xp.cond(again, lambda: xp.rms_ratio(refiltered(), scale), lambda: norm)


def finite_or_inf(xp, value):
    """``value``, or inf where it is NaN or infinite (a norm: never negative)."""
    return xp.where(value < math.inf, value, math.inf)


# ---- Newton's tests -----------------------------------------------------------------------------
def start_rate(xp, eta, eps):
    """RADAU5's start: the last step's contraction rate predicts the first iteration's."""
    return xp.maximum(eta, eps) ** START_RATE_POWER


def contraction(xp, norm, previous):
    """The ratio ``q`` of the last increment's norm to the one before."""
    return norm / xp.maximum(previous, TINY_NORM)


def geometric_contraction(stages: int) -> bool:
    """Whether Newton's contraction is RADAU5's geometric mean (:data:`GEOMETRIC_CONTRACTION_STAGES`)."""
    return stages >= GEOMETRIC_CONTRACTION_STAGES


def mean_contraction(xp, ratio, before, geometric):
    """The contraction ``theta`` from this iteration's ratio and the last one's (``before``, 0 where none):
    ``geometric`` (a Python flag), RADAU5's ``sqrt(ratio before)``, the ratio alone at the second
    iteration; else the ratio alone."""
    if not geometric:
        return ratio
    return xp.where(before > 0, (ratio * before) ** 0.5, ratio)


def diverging(theta):
    """Whether Newton diverges at contraction ``theta``."""
    return theta >= DIVERGENCE_THETA


def rate(theta):
    """The rate ``eta = theta / (1 - theta)`` that bounds the error left by the increments to come."""
    return theta / (1 - theta)


def converged(eta, norm, tol):
    """Whether the predicted error ``eta |dW|`` is within Newton's tolerance."""
    return eta * norm <= tol


def too_slow(eta, norm, theta, left, tol):
    """Whether the increment predicted after the ``left`` iterations still exceeds the tolerance (RADAU5)."""
    return eta * norm * theta**left > tol


def sign_flip(before, after):
    """Whether the sign of the algebraic variables' iteration matrix's determinant changed from
    ``before`` to ``after`` (so it passed through zero, where z is not determined)."""
    return before * after < 0


def jacobian_kept(xp, theta, reuse_theta):
    """Whether the next step keeps the Jacobian: Newton contracted at most at ``reuse_theta``."""
    return xp.not_(theta > reuse_theta)


def newton_iteration(
    xp,
    norm,
    previous,
    theta,
    eta,
    active,
    first,
    left,
    tol,
    to_rounding=False,
    slow_ends=True,
    ratio=0.0,
    geometric=False,
):
    """The tests of one simplified Newton iteration (a :class:`NewtonTests`) on its increment's scaled
    norm ``norm``, in their order; the first failure ends the iteration (its outcome wins over the later ones):

    1. :data:`NON_FINITE`: a norm not finite (a NaN or inf anywhere in R or dW ends up there);
    2. :data:`DIVERGING` (not at the ``first`` iteration): the contraction (the ratio to the last norm
       ``previous``; ``geometric``, from the third iteration on, its geometric mean with the last
       ``ratio``, :func:`mean_contraction`) reaches :data:`DIVERGENCE_THETA` (to rounding: only above
       :data:`STAGNATION_FACTOR` times ``tol``, where increments do not wander at the floor);
    3. the rate eta moves, and the samples that converged stop (:func:`converged`; to rounding: the
       increment below ``tol``, or stagnant within :data:`STAGNATION_FACTOR` of it);
    4. :data:`SLOW` (``slow_ends``; with ``left`` iterations still to come): the increment predicted
       after them exceeds ``tol`` (:func:`too_slow`);
    5. :data:`NOT_CONVERGED`: none left and a sample still iterating.

    ``active``: the samples still iterating (only their theta and eta move).  On arrays each test's
    :meth:`ArrayOps.any` is one read of the device and a Python branch (the later tests are not
    evaluated after a failure: no warning from a rate at theta 1); on casadi symbols every branch is
    evaluated and the outcome selected.  With ``slow_ends`` False the caller may refresh its
    matrices where samples are ``slow`` instead.
    """

    NONE = False  # (no sample)

    def contracted():
        q = contraction(xp, norm, previous)
        th = xp.where(active, mean_contraction(xp, q, ratio, geometric), theta)
        flags = xp.and_(active, diverging(th))
        if to_rounding:  # increments at the rounding floor wander: that is not divergence
            flags = xp.and_(flags, norm > STAGNATION_FACTOR * tol)
        return th, flags, xp.where(active, q, ratio)

    def tests():
        th, diverges, q = xp.cond(first, lambda: (theta, False, ratio), contracted)
        return xp.cond(
            xp.any(diverges), lambda: (DIVERGING, th, eta, active, NONE, True, diverges, q), lambda: after(th, q)
        )

    def after(th, q):
        rate_ = xp.cond(first, lambda: eta, lambda: xp.where(active, rate(th), eta))
        if to_rounding:  # the last increment itself is below tol, or rounding stops it near tol
            stagnant = xp.and_(th >= STAGNATION_THETA, norm <= STAGNATION_FACTOR * tol)
            done = xp.or_(norm <= tol, stagnant)
        else:
            done = converged(rate_, norm, tol)
        still = xp.and_(active, xp.not_(done))
        running = xp.any(still)
        slow = xp.cond(
            xp.and_(xp.and_(xp.not_(first), left > 0), running),
            lambda: xp.and_(still, too_slow(rate_, norm, th, left, tol)),
            lambda: NONE,
        )
        ending = xp.cond(xp.and_(left <= 0, running), lambda: NOT_CONVERGED, lambda: CONVERGED)
        # (slow_ends: a Python flag, the policy's and the matrices')
        outcome = xp.cond(xp.any(slow), lambda: SLOW, lambda: ending) if slow_ends else ending
        return outcome, th, rate_, still, slow, running, slow, q

    bad = xp.not_(norm < math.inf)
    return NewtonTests(*xp.cond(xp.any(bad), lambda: (NON_FINITE, theta, eta, active, NONE, True, bad, ratio), tests))


class NewtonTests(NamedTuple):
    """What :func:`newton_iteration` found (arrays: one entry per sample; casadi: symbols)."""

    outcome: object  # CONVERGED (none failed: converged, or iterating on), or the failure
    theta: object  # the contraction
    eta: object  # the rate
    active: object  # still iterating after the iteration
    slow: object  # contracting too slowly (SLOW's test)
    running: object  # any sample still iterating
    failing: object  # the samples that failed the outcome's test (False where none)
    ratio: object  # this iteration's ratio of increments (the next one's mean_contraction reads it)


def after_convergence(xp, k, iterations: int):
    """What follows a convergence at iteration ``k`` on RADAU5's start (the last step's rate trusted):
    at the first, where another iteration is allowed, :data:`CHECK` (one more increment must be
    small too: a non-smooth f, e.g. sign(x), can make one iteration look converged, and trusting
    the rate alone accepted 100 x rtol errors on the pendulum); else :data:`EVALUATE`."""
    return xp.where(xp.and_(k == 1, iterations > 1), CHECK, EVALUATE)


def confirmed(norm, tol):
    """Whether the increment after a one-iteration convergence confirms it (a NaN confirms nothing)."""
    return norm <= tol

"""RADAU5's controller and many adaptive attempts in one casadi call (the casadi engine: dense systems
up to 24 unknowns, and with ``jit`` sparse ones on static factors made in C, :mod:`.kernel`).

With the attempt compiled (:func:`.compiled.step_function`), what Python still did per attempt, the
controller's arithmetic, the Jacobian's refresh and the state's bookkeeping, cost 25-40 us, ten
times the attempt itself in machine code (the pendulum: 3.3 us).  :func:`run_function` makes
:data:`RUN_ATTEMPTS` attempts of :meth:`.control.Radau5Controller.run` one casadi function.  Each
attempt, as :meth:`.step.Stepper.compiled_attempt` and the controller make it:

- refreshes the Jacobian where it was dropped (with its factored systems and the sign of the
  algebraic variables' iteration matrix), or factors anew where h changed;
- runs the compiled attempt, and its retries: with a fresh Jacobian where a kept one failed, then
  from the start value;
- where all failed, checks that z stays determined over the step and halves h; else accepts or
  rejects the step and picks the next h.

The same arithmetic in the same order: the same steps, bit for bit.  What only Python does ends
the run *before* the attempt, which Python then makes on its own path (the attempt runs twice),
where the errors are worded: non-finite values (the general path names where they arose), a sign
change of the iteration matrix's determinant, a singular factorisation (a non-finite inverse; an
exactly singular matrix, which LAPACK refuses, fails the call, and Python makes the next attempt),
a step size underflow.  A run also ends where the integration does and at ``limit`` attempts (the
controller's budget checks).  Each attempt that ran leaves a record (:data:`RECORD`, then the start
value and the stages) from which :class:`CompiledRun` writes the steps and the statistics back
into the stepper.
"""

from __future__ import annotations

import numpy as np
from daemodel.backends.progress import captured_output
from daemodel.backends.radau.compiled import NON_FINITE, Buffered, iteration_matrix
from daemodel.backends.radau.sparse import MAX_GROWTH

# Attempts in one call.  An idle one (after the run ended) costs a copy of the state; measured on
# the pendulum (19 attempts at rtol 1e-6) and car axis (~800), 32 keeps both near their best.
RUN_ATTEMPTS = 32
# How a run ended: every attempt ran, the integration reached t1, Python must make the next attempt,
# or ``limit`` attempts ran (the controller then checks its budget).
FULL, FINISHED, HANDBACK, LIMIT = 0, 1, 2, 3
# The carried scalars, in this order, in front of u (D), the last step's nodes ((s+1) D), f at the
# start (n), J's nonzeros and the packed inverses.  h_old 0: no last step (a constant guess);
# factors_h 0: no factored systems; h_acc 0: no accepted step yet (Gustafsson's prediction waits).
SCALARS = (
    "t", "h", "h_old", "eta", "first", "rejected_last", "h_acc", "err_acc", "jac_kept", "t_jac",
    "factors_h", "det_sign", "t_det", "attempts", "active", "code",
)  # fmt: skip
# The run's settings, in this order, then p.
SETTINGS = (
    "t0", "t1", "limit", "newton_tol", "rtol", "atol", "reuse_theta", "keep_low", "keep_high", "predictive",
)  # fmt: skip
# Each attempt's record, in this order, then the start value (D) and the stages (s D).
RECORD = ("ran", "accepted", "t", "h", "t_next", "iterations", "evaluations", "refreshed", "factored", "retries",
          "newton_failed")  # fmt: skip


def sign_det_function(m: int):
    """casadi function of the sign of the determinant of an (m, m) matrix (column-major values): by
    :func:`.linalg.small_sign_det`'s formula up to m = 3, by an LU with partial pivoting above; 0 where
    it is singular or not finite."""
    import casadi

    a = casadi.SX.sym("a", m * m)
    if m == 0:
        return casadi.Function("sign_det", [a], [casadi.SX(1.0)])
    if m <= 3:
        if m == 1:
            det = a[0]
        elif m == 2:
            det = a[0] * a[3] - a[1] * a[2]
        else:
            det = (
                a[0] * (a[4] * a[8] - a[5] * a[7])
                - a[3] * (a[1] * a[8] - a[2] * a[7])
                + a[6] * (a[1] * a[5] - a[2] * a[4])
            )
        finite = casadi.logic_and(det < casadi.inf, det > -casadi.inf)
        return casadi.Function("sign_det", [a], [casadi.if_else(finite, casadi.sign(det), 0)])
    A = [[a[i + j * m] for j in range(m)] for i in range(m)]
    sign = casadi.SX(1.0)
    for k in range(m):
        for r in range(k + 1, m):  # the largest |A[r][k]| to row k, one comparison at a time
            swap = casadi.fabs(A[r][k]) > casadi.fabs(A[k][k])
            for j in range(k, m):
                A[k][j], A[r][j] = casadi.if_else(swap, A[r][j], A[k][j]), casadi.if_else(swap, A[k][j], A[r][j])
            sign = casadi.if_else(swap, -sign, sign)
        pivot = A[k][k]
        sign = sign * casadi.sign(pivot)
        for r in range(k + 1, m):
            factor = casadi.if_else(pivot != 0, A[r][k] / pivot, 0)
            for j in range(k + 1, m):
                A[r][j] = A[r][j] - factor * A[k][j]
    return casadi.Function("sign_det", [a], [casadi.if_else(casadi.fabs(sign) <= 1, sign, 0)])  # (NaN: 0)


def not_finite(casadi, values):
    """Whether any of ``values`` is NaN or infinite (their sum is then not finite, or overflows: singular enough)."""
    total = casadi.sum1(values)
    return casadi.logic_not(casadi.logic_and(total < casadi.inf, total > -casadi.inf))


def unusable(casadi, packed, static):
    """Whether the packed factors cannot serve: a value not finite (dense inverses), or with ``static``
    (:class:`.compiled.StaticFactors`) also growth beyond :data:`.sparse.MAX_GROWTH` or a zero pivot
    (:meth:`.casadi_engine.CasadiEngine.factor` then factors with LAPACK or SuperLU, on Python's path)."""
    if static is None:
        return not_finite(casadi, packed)
    growth, pivot = packed[static.checks_offset], packed[static.checks_offset + 1]
    return any_of(casadi, not_finite(casadi, packed), growth > MAX_GROWTH, pivot == 0)


def any_of(casadi, *flags):
    """The logical or of casadi ``flags``."""
    out = flags[0]
    for flag in flags[1:]:
        out = casadi.logic_or(out, flag)
    return out


def is_close(casadi, a, b, rel_tol, abs_tol=0.0):
    """``math.isclose(a, b, rel_tol=rel_tol, abs_tol=abs_tol)`` on casadi scalars (its formula)."""
    diff = casadi.fabs(b - a)
    return casadi.logic_or(
        casadi.logic_or(diff <= casadi.fabs(rel_tol * b), diff <= casadi.fabs(rel_tol * a)),
        casadi.logic_or(diff <= abs_tol, a == b),
    )


def head_function():
    """The controller's loop head (SX, scalars): from ``[SCALARS, SETTINGS]``, ``[h (the last step
    shortened to end at t1), limited (the budget is spent), underflow, refreshed (the Jacobian was
    dropped), factored (h changed), ratio (h / h_old, 0 without a last step), first (the estimate
    refiltered)]``."""
    import casadi

    x = casadi.SX.sym("x", len(SCALARS) + len(SETTINGS))
    v = {name: x[i] for i, name in enumerate(SCALARS)}
    c = {name: x[len(SCALARS) + i] for i, name in enumerate(SETTINGS)}
    t, t1 = v["t"], c["t1"]
    limited = v["attempts"] >= c["limit"]
    underflow = v["h"] < 1e-14 * casadi.fmax(1.0, casadi.fabs(t))
    h = casadi.fmin(v["h"], t1 - t)
    h = casadi.if_else((t1 - t) - h < 1e-10 * h, t1 - t, h)
    refreshed = casadi.logic_not(v["jac_kept"])
    factored = casadi.logic_and(casadi.logic_not(refreshed), v["factors_h"] != h)
    ratio = casadi.if_else(v["h_old"] > 0, h / v["h_old"], 0.0)
    first = casadi.logic_or(v["first"], v["rejected_last"])
    return casadi.Function("head", [x], [casadi.vertcat(h, limited, underflow, refreshed, factored, ratio, first)])


# What the tail reads of the attempt, after the scalars and settings.
ATTEMPT = ("h", "limited", "underflow", "refreshed", "factored", "stale", "singular", "sign", "retry_sign",
           "outcome", "k", "theta", "eta", "err", "evaluations", "retries", "newton_failed", "stage_flip")  # fmt: skip


def tail_function(s: int, iterations: int):
    """The controller after the attempt (SX, scalars; :meth:`.control.Radau5Controller.run` in its
    order of operations): from ``[SCALARS, SETTINGS, ATTEMPT]``, ``[the scalars after it, ran,
    taken, the record's scalars (:data:`RECORD`)]``.  An attempt that did not run (the budget, or
    one to hand back) leaves the scalars as they were, inactive, with the code why."""
    import casadi
    from daemodel.backends.radau import control

    x = casadi.SX.sym("x", len(SCALARS) + len(SETTINGS) + len(ATTEMPT))
    v = {name: x[i] for i, name in enumerate(SCALARS)}
    c = {name: x[len(SCALARS) + i] for i, name in enumerate(SETTINGS)}
    a = {name: x[len(SCALARS) + len(SETTINGS) + i] for i, name in enumerate(ATTEMPT)}
    t, t0, t1, h, k, theta, err = v["t"], c["t0"], c["t1"], a["h"], a["k"], a["theta"], a["err"]
    err = casadi.if_else(err < casadi.inf, err, casadi.inf)  # (NaN: inf, as the stepper reads it)
    fac = casadi.fmin(control.SAFETY, control.SAFETY * (2 * iterations + 1) / (2 * iterations + k))
    quot = fac * casadi.fmax(err, 1e-10) ** (-1.0 / (s + 1))
    failed = a["newton_failed"]  # (every compiled try failed, z stays determined: the controller halves h)
    accept = casadi.logic_and(casadi.logic_not(failed), err <= 1)
    floor = 1e-14 * casadi.fmax(1.0, casadi.fabs(t))  # (shrink's underflow)
    h_rejected = casadi.if_else(failed, h * 0.5, h * casadi.fmax(control.MIN_FACTOR, casadi.fmin(quot, 0.9)))
    shrunk_away = casadi.logic_and(casadi.logic_not(accept), h_rejected < floor)
    t_next = casadi.if_else(is_close(casadi, t + h, t1, 1e-13), t1, t + h)
    jac_kept = casadi.logic_not(theta > c["reuse_theta"])  # (Stepper.accept's test)
    change = casadi.fmin(control.MAX_FACTOR, casadi.fmax(control.MIN_FACTOR, quot))
    predicted = control.SAFETY * (h / v["h_acc"]) * (v["err_acc"] / casadi.fmax(err, 1e-10) ** 2) ** (1.0 / (s + 1))
    predicted = casadi.fmin(control.MAX_FACTOR, casadi.fmax(control.MIN_FACTOR, predicted))
    change = casadi.if_else(casadi.logic_and(c["predictive"], v["h_acc"] > 0), casadi.fmin(change, predicted), change)
    new_h = casadi.if_else(v["rejected_last"], h * casadi.fmin(1.0, change), h * change)
    quotient = new_h / h
    banded = casadi.logic_and(casadi.logic_and(c["keep_low"] <= quotient, quotient <= c["keep_high"]), jac_kept)
    new_h = casadi.if_else(banded, h, new_h)
    near_end = is_close(casadi, t_next, t1, 1e-13, 1e-13 * casadi.fabs(t1 - t0))
    done = casadi.logic_and(accept, casadi.logic_not(casadi.logic_and(t_next < t1, casadi.logic_not(near_end))))
    flipped = casadi.logic_or(
        casadi.logic_and(a["refreshed"], v["det_sign"] * a["sign"] < 0),  # (check_determined's test)
        casadi.logic_and(a["stale"], a["sign"] * a["retry_sign"] < 0),
    )
    non_finite = casadi.logic_and(a["outcome"] != 0, casadi.logic_not(failed))  # (the general path names where)
    handback = any_of(casadi, a["underflow"], a["singular"], flipped, non_finite, a["stage_flip"], shrunk_away)
    ran = casadi.logic_not(casadi.logic_or(a["limited"], handback))
    refreshes = a["refreshed"] + a["stale"]
    after = {
        "t": casadi.if_else(accept, t_next, t),
        "h": casadi.if_else(accept, new_h, h_rejected),
        "h_old": casadi.if_else(accept, h, v["h_old"]),
        "eta": casadi.if_else(failed, v["eta"], a["eta"]),
        "first": casadi.if_else(accept, 0, casadi.logic_or(failed, v["first"])),
        "rejected_last": casadi.logic_not(accept),
        "h_acc": casadi.if_else(accept, h, v["h_acc"]),
        "err_acc": casadi.if_else(accept, casadi.fmax(err, 1e-2), v["err_acc"]),
        "jac_kept": casadi.if_else(accept, jac_kept, 1),  # (refreshed if it was not kept)
        "t_jac": casadi.if_else(refreshes > 0, t, v["t_jac"]),
        "factors_h": casadi.if_else(accept, h, 0),  # (a rejected step drops its factors: h changes)
        "det_sign": casadi.if_else(a["stale"], a["retry_sign"], a["sign"]),
        "t_det": casadi.if_else(refreshes > 0, t, v["t_det"]),
        "attempts": v["attempts"] + 1,
        "active": casadi.logic_not(done),
        "code": casadi.if_else(done, FINISHED, FULL),
    }
    stopped = {**v, "active": 0, "code": casadi.if_else(a["limited"], LIMIT, HANDBACK)}
    scalars = [casadi.if_else(ran, after[name], stopped[name]) for name in SCALARS]
    record = [1, accept, t, h, t_next, casadi.if_else(failed, 0, k), a["evaluations"], refreshes, a["factored"]]
    record += [a["retries"], failed]
    record = [casadi.if_else(ran, value, 0) for value in record]
    out = casadi.vertcat(*scalars, ran, casadi.logic_and(ran, accept), *record)
    return casadi.Function("tail", [x], [out])


def run_function(
    engine, step, refresh, inverses, stage_jacobians, sign, static, iterations: int, attempts: int = RUN_ATTEMPTS
):
    """The casadi function of ``attempts`` attempts of the RADAU5 controller (see the module docstring).

    ``step``: the compiled attempt (:func:`.compiled.step_function`, or its machine code);
    ``refresh`` and ``inverses``: :func:`.compiled.refresh_function` and
    :func:`.compiled.inverse_function`, or with ``static`` (the engine's
    :class:`.compiled.StaticFactors`) the packed static factors' (:mod:`.kernel`); ``sign``: a
    function of the sign of det of an (m, m) matrix above m = 3 (None: :func:`sign_det_function`);
    ``stage_jacobians``: the Jacobian's nonzeros at every stage
    (:func:`.compiled.casadi_functions`).  Inputs ``[state, settings]`` (:data:`SCALARS` and the
    arrays, :data:`SETTINGS` and p); output the state, then each attempt's record (:func:`record_size`).
    The scalar logic is in two SX functions (:func:`head_function`, :func:`tail_function`): on casadi's
    virtual machine an MX operation costs ~20 ns, an SX one ~2.
    """
    import casadi

    s, n, D, m = engine.s, engine.n, engine.D, engine.m
    P, nnz, size_inverse = engine.p.size, len(engine.rows), engine.packed_size()
    rows, cols = engine.rows, engine.cols
    layout = state_layout(s, n, D, nnz, size_inverse)
    state = casadi.MX.sym("state", layout["size"])
    settings = casadi.MX.sym("settings", len(SETTINGS) + P)
    scalars = state[: len(SCALARS)]
    u, nodes, f0, J, inverse = (state[layout[name]] for name in ("u", "nodes", "f0", "J", "inverse"))
    given = settings[: len(SETTINGS)]
    p = settings[len(SETTINGS) :]
    t, eta, det_sign = state[layout["t"]], state[layout["eta"]], state[layout["det_sign"]]
    h, limited, underflow, refreshed, factored, ratio, first = casadi.vertsplit(
        head_function()(casadi.vertcat(scalars, given))
    )

    # the Jacobian, refreshed (with its factored systems) where it was dropped; else factored where h changed
    args = [casadi.MX.sym("t"), casadi.MX.sym("u", D), casadi.MX.sym("p", P), casadi.MX.sym("h")]
    kept = [casadi.MX.sym("J", nnz), casadi.MX.sym("sign"), casadi.MX.sym("inverse", size_inverse)]
    sign_det = sign if sign is not None and m > 3 else sign_det_function(m)
    out = refresh(casadi.vertcat(*args))
    fresh = casadi.Function("fresh", [*args, *kept], [out[:nnz], sign_det(out[nnz : nnz + m * m]), out[nnz + m * m :]])
    keep = casadi.Function("keep", [*args, *kept], kept)
    J, sign, inverse = casadi.Function.if_else("refresh", fresh, keep)(refreshed, t, u, p, h, J, det_sign, inverse)
    hJ = [casadi.MX.sym("h"), casadi.MX.sym("J", nnz), casadi.MX.sym("inverse", size_inverse)]
    factor = casadi.Function("factor", hJ, [inverses(casadi.vertcat(hJ[0], hJ[1]))])
    same = casadi.Function("same", hJ, [hJ[2]])
    inverse = casadi.Function.if_else("refactor", factor, same)(factored, h, J, inverse)
    singular = unusable(casadi, inverse, static)

    # the attempt from the last step's polynomial (a constant guess at the first step: ratio 0), then
    # Stepper.compiled_attempt's retries: with a fresh Jacobian where the kept one failed, then from
    # the start value (the state at the start, s+1 times, at ratio 0)
    head = casadi.vertcat(t, h)
    tail = casadi.vertcat(eta, given[SETTINGS.index("newton_tol")], first, given[SETTINGS.index("rtol")])
    tail = casadi.vertcat(tail, given[SETTINGS.index("atol")])
    x = casadi.vertcat(head, ratio, tail, nodes, f0, p)
    result = step(x, inverse)
    failed, evaluations = result[0] != 0, result[2]
    t_jac = casadi.if_else(refreshed, t, state[layout["t_jac"]])
    stale = casadi.logic_and(failed, t_jac != t)
    again = [casadi.MX.sym("x", x.numel()), casadi.MX.sym("result", result.numel())]
    out = refresh(casadi.vertcat(*args))
    fresh_inverse = out[nnz + m * m :]
    retry = casadi.Function(
        "retry", [*args, *kept, *again],
        [out[:nnz], sign_det(out[nnz : nnz + m * m]), fresh_inverse, step(again[0], fresh_inverse)],
    )  # fmt: skip
    keep_result = casadi.Function("keep_result", [*args, *kept, *again], [*kept, again[1]])
    J, retry_sign, inverse, result = casadi.Function.if_else("stale", retry, keep_result)(
        stale, t, u, p, h, J, sign, inverse, x, result
    )
    singular = casadi.logic_or(singular, casadi.logic_and(stale, unusable(casadi, inverse, static)))
    failed_again = result[0] != 0
    evaluations = evaluations + casadi.if_else(stale, result[2], 0)
    constant = casadi.logic_and(failed_again, state[layout["h_old"]] > 0)
    start = casadi.vertcat(head, 0.0, tail, casadi.repmat(u, s + 1, 1), f0, p)
    from_start = casadi.Function("from_start", [*again, kept[2]], [step(again[0], kept[2])])
    same_result = casadi.Function("same_result", [*again, kept[2]], [again[1]])
    result = casadi.Function.if_else("constant", from_start, same_result)(constant, start, result, inverse)
    evaluations = evaluations + casadi.if_else(constant, result[2], 0)
    outcome = result[0]
    retries = failed + casadi.logic_and(stale, failed_again) + casadi.logic_and(constant, outcome != 0)

    # every try failed (values finite): before h is halved, z must stay determined over the step, as
    # Stepper.compiled_attempt checks it (the iteration matrix's sign at each stage of the start value)
    newton_failed = casadi.logic_and(outcome != 0, outcome != NON_FINITE)
    stage = [
        casadi.MX.sym("t"),
        casadi.MX.sym("h"),
        casadi.MX.sym("u", D),
        casadi.MX.sym("p", P),
        casadi.MX.sym("sign"),
    ]
    values = stage_jacobians(casadi.vertcat(stage[0], stage[1], casadi.repmat(stage[2], s, 1), stage[3]))
    chain = [stage[4]]
    sparse = static is not None
    matrices = [iteration_matrix(casadi, values[i * nnz : (i + 1) * nnz], rows, cols, engine, sparse) for i in range(s)]
    chain += [sign_det(matrix) for matrix in matrices]
    flips = sum(chain[i] * chain[i + 1] < 0 for i in range(s))
    check = casadi.Function("check", stage, [flips > 0])
    never = casadi.Function("never", stage, [0])
    final_sign = casadi.if_else(stale, retry_sign, sign)
    stage_flip = casadi.Function.if_else("determined", check, never)(newton_failed, t, h, u, p, final_sign)

    attempt_values = [h, limited, underflow, refreshed, factored, stale, singular, sign, retry_sign,
                      outcome, result[1], result[3], result[4], result[5], evaluations, retries,
                      newton_failed, stage_flip]  # fmt: skip
    after = tail_function(s, iterations)(casadi.vertcat(scalars, given, *attempt_values))
    ran, taken = after[len(SCALARS)], after[len(SCALARS) + 1]
    W = result[6 : 6 + s * D]
    moved = casadi.vertcat(
        after[: len(SCALARS)],
        casadi.if_else(taken, W[(s - 1) * D :], u),
        casadi.if_else(taken, casadi.vertcat(u, W), nodes),
        casadi.if_else(taken, result[6 + s * D + (s - 1) * n :], f0),
        casadi.if_else(ran, casadi.vertcat(J, inverse), state[layout["J"].start :]),
    )
    record = casadi.vertcat(after[len(SCALARS) + 2 :], casadi.if_else(ran, casadi.vertcat(u, W), 0))
    attempt = casadi.Function("attempt", [state, settings], [moved, record])
    idle = casadi.Function("idle", [state, settings], [state, casadi.MX.zeros(record.numel())])
    maybe = casadi.Function.if_else("maybe_attempt", attempt, idle)

    carried, records = state, []
    for _ in range(attempts):
        carried, rec = maybe(carried[layout["active"]], carried, settings)
        records.append(rec)
    return casadi.Function("radau_run", [state, settings], [casadi.vertcat(carried, *records)])


def state_layout(s: int, n: int, D: int, nnz: int, size_inverse: int) -> dict:
    """Where each part of the carried state sits: the scalars' indices, the arrays' slices, the size."""
    layout = {name: i for i, name in enumerate(SCALARS)}
    offset = len(SCALARS)
    for name, size in (("u", D), ("nodes", (s + 1) * D), ("f0", n), ("J", nnz), ("inverse", size_inverse)):
        layout[name] = slice(offset, offset + size)
        offset += size
    layout["size"] = offset
    return layout


def record_size(s: int, D: int) -> int:
    """Entries of one attempt's record: :data:`RECORD`, the start value, the stages."""
    return len(RECORD) + D + s * D


class CompiledRun:
    """The stepper's side of :func:`run_function`: its state packed in, the attempts' steps and
    statistics written back as :meth:`.step.Stepper.accept` and the controller would have."""

    def __init__(self, function, engine):
        s, D = engine.s, engine.D
        self.buffered = Buffered(function, inputs=2)
        self.layout = state_layout(s, engine.n, D, len(engine.rows), engine.packed_size())
        self.record = record_size(s, D)
        self.attempts = (function.nnz_out(0) - self.layout["size"]) // self.record
        self.shifts = len(engine.transform.shifts(1.0))  # LU decompositions a factorisation counts

    def advance(self, stepper, t, h, first, rejected_last, accepted, settings):
        """Up to :attr:`attempts` attempts from ``t`` with ``h`` (``settings``: :data:`SETTINGS`' values),
        the controller's state given and returned: ``(t, h, first, rejected_last, accepted, how the run
        ended)``; the stepper's state and statistics move with the accepted steps."""
        L = self.layout
        state = self.buffered.inputs[0]
        previous, factors, jac = stepper._previous, stepper.factors, stepper._jac
        scalars = {
            "t": t,
            "h": h,
            "h_old": previous[0] if previous is not None else 0.0,
            "eta": float(stepper.eta[0]),
            "first": float(first),
            "rejected_last": float(rejected_last),
            "h_acc": accepted[0] if accepted is not None else 0.0,
            "err_acc": accepted[1] if accepted is not None else 0.0,
            "jac_kept": float(jac is not None),
            "t_jac": jac[1] if jac is not None else 0.0,
            "factors_h": factors.h if factors is not None and factors.inverse is not None else 0.0,
            "det_sign": float(stepper._det_sign[0]) if stepper._det_sign is not None else 0.0,
            "t_det": stepper._det_time,
            "attempts": 0.0,
            "active": 1.0,
            "code": FULL,
        }
        state[: len(SCALARS)] = [scalars[name] for name in SCALARS]
        u = stepper.state()[0]
        state[L["u"]] = u
        state[L["nodes"]] = stepper._previous_nodes if previous is not None else np.tile(u, stepper.s + 1)
        state[L["f0"]] = stepper.start_f(t)[0]
        if jac is not None:
            state[L["J"]] = jac[0]
        if scalars["factors_h"]:
            state[L["inverse"]] = factors.inverse
        inputs = self.buffered.inputs[1]
        inputs[: len(settings)] = settings
        inputs[len(SETTINGS) :] = stepper.engine.p
        try:
            with captured_output():  # (casadi prints a failing call's inputs, all nested functions', before it raises)
                out = self.buffered.evaluate()
        except RuntimeError:
            # a factorisation inside failed (LAPACK refuses an exactly singular matrix): the next attempt
            # on Python's path, which factors with scipy and names why it is singular
            return t, h, first, rejected_last, accepted, HANDBACK
        stepper.stats["compiled_runs"] += 1
        return self._write_back(stepper, out, accepted)

    def _write_back(self, stepper, out, accepted):
        L, stats, engine = self.layout, stepper.stats, stepper.engine
        s, n, D = stepper.s, stepper.n, stepper.n + stepper.m
        v = dict(zip(SCALARS, out[: len(SCALARS)].tolist(), strict=True))
        records = out[L["size"] :].reshape(self.attempts, self.record)
        records = records[records[:, 0] > 0]
        if not len(records):  # (the first attempt handed back: nothing moved)
            return v["t"], v["h"], bool(v["first"]), bool(v["rejected_last"]), accepted, int(v["code"])
        sums = dict(zip(RECORD, records[:, : len(RECORD)].sum(axis=0).tolist(), strict=True))  # (one numpy call)
        failed = int(sums["newton_failed"])
        stats["attempts"] += len(records)
        stats["rejected_steps"] += len(records) - int(sums["accepted"]) - failed
        stats["newton_failures"] += failed
        stats["newton_iterations"] += int(sums["iterations"])
        stats["max_newton_iterations"] = max(
            stats["max_newton_iterations"], int(records[:, RECORD.index("iterations")].max())
        )
        stats["residual_evaluations"] += int(sums["evaluations"])
        stats["jacobian_evaluations"] += int(sums["refreshed"]) + failed  # (the stages' at a failure)
        stats["compiled_retries"] += int(sums["retries"])
        stats["lu_decompositions"] += self.shifts * int(sums["refreshed"] + sums["factored"])
        if sums["refreshed"] and stepper.m:
            stepper._det_sign, stepper._det_time = np.array([v["det_sign"]]), v["t_det"]
        steps = records[records[:, 1] > 0]
        if len(steps):
            nodes = steps[:, len(RECORD) :].reshape(1, len(steps), s + 1, D)  # (the start value, then the stages)
            # (copies: the records' other entries are not kept, as step_record_bytes counts)
            stepper.records.add(
                steps[:, 2].copy(),
                steps[:, 3].copy(),
                steps[:, 4].copy(),
                nodes.copy() if stepper.records.dense else nodes[:, :, -1:].copy(),  # (the end values only)
            )
            stats["steps"] += len(steps)
            lengths = steps[:, 3].tolist()
            stats["h_min"], stats["h_max"] = min(stats["h_min"], *lengths), max(stats["h_max"], *lengths)
            stepper._previous = (float(steps[-1, 3]), nodes[:, -1, 0], nodes[:, -1, 1:])
            stepper._previous_nodes = out[L["nodes"]].copy()
            u = out[L["u"]]
            stepper.y, stepper.z = u[None, :n].copy(), u[None, n:].copy()
            stepper._f_start = out[L["f0"]][None].copy()
            accepted = (v["h_acc"], v["err_acc"])
        stepper.eta = np.array([v["eta"]])
        stepper._jac = (out[L["J"]].copy(), v["t_jac"]) if v["jac_kept"] else None
        factors_h = v["factors_h"]
        stepper.factors = engine._packed_factors(out[L["inverse"]].copy(), factors_h) if factors_h else None
        first, rejected_last = bool(v["first"]), bool(v["rejected_last"])
        return v["t"], v["h"], first, rejected_last, accepted, int(v["code"])

"""RADAU5's attempt sequence, written once over a namespace (:mod:`.formulas`): what the controller
decides before an attempt and after it, what the compiled run carries from one attempt to the next,
and the run statistics that attempts add.

Two callers make the sequence: :meth:`.control.Radau5Controller.run` on Python values
(:data:`.formulas.SCALAR`), one attempt at a time, and the compiled run (:func:`.loop.head_function`
and :func:`.loop.tail_function`: these functions called on casadi SX symbols, their inputs and
outputs named by the layouts here), many attempts in one call.  Both make the same arithmetic in
the same order and so take the same steps, bit for bit.  In order:

1. :func:`before_attempt`: the step size underflow's test, h shortened (or stretched) to end at t1,
   whether the estimate is refiltered (a first step, or one after a rejection);
2. the attempt (the caller's: :meth:`.step.Stepper.attempt_with_error`, or the compiled tries);
3. :func:`after_attempt`: the error norm (inf where not finite), the quotient, accept or reject,
   the rejected h and its underflow, first/rejected_last, the step's end, the next h (Gustafsson's
   prediction, the keep band) and the accepted ``(h, err)`` that prediction reads next;
4. :func:`add_statistics`: what the attempt adds to the run statistics, from its record.

The compiled run alone adds :func:`run_head` (its budget, the Jacobian's refresh and refactor, the
start guess's ratio) and :func:`run_tail` (the state it carries, the attempts it hands back to
Python, the record); what only Python does (the named errors, the budget's and progress's checks,
the stepper's calls) stays in :mod:`.control`.
"""

from __future__ import annotations

from daemodel.backends.radau import formulas
from daemodel.backends.radau.compiled import Layout

# How a compiled run ended: every attempt ran, the integration reached t1, Python must make the next
# attempt, or ``limit`` attempts ran (the controller then checks its budget).
FULL, FINISHED, HANDBACK, LIMIT = 0, 1, 2, 3
# The controller's own carried scalars (the Python controller carries these alone): h_acc 0 means no
# accepted step yet (Gustafsson's prediction waits).
CONTROLLER = ("t", "h", "first", "rejected_last", "h_acc", "err_acc")
# The compiled run's carried scalars, in front of u (D), the last step's nodes ((s+1) D), f at the
# start (n), J's nonzeros and the packed inverses (.loop.state_layout).  h_old 0: no last step (a
# constant guess); factors_h 0: no factored systems.
SCALARS = Layout(
    "t", "h", "h_old", "eta", "first", "rejected_last", "h_acc", "err_acc", "jac_kept", "t_jac",
    "factors_h", "det_sign", "t_det", "attempts", "active", "code",
)  # fmt: skip
# The run's settings (in the compiled run: in front of p).  limit: the attempts the compiled run may
# make (the Python controller checks its budget itself); trusted: the largest h whose estimate is refiltered
# before the first accepted step (.formulas.refiltered_here: the probe's first step).
SETTINGS = Layout(
    "t0", "t1", "limit", "newton_tol", "rtol", "atol", "reuse_theta", "keep_low", "keep_high", "predictive",
    "trusted",
)  # fmt: skip
# What the compiled run's head tells of the attempt to come (.loop.head_function's outputs).
HEAD = ("h", "limited", "underflow", "refreshed", "factored", "ratio", "first")
# What the compiled run's tail reads of the attempt (.loop.tail_function's input).
ATTEMPT = Layout(
    "h", "limited", "underflow", "refreshed", "factored", "stale", "singular", "sign", "retry_sign", "outcome",
    "iterations", "theta", "eta", "error_norm", "evaluations", "retries", "newton_failed", "stage_flip",
)  # fmt: skip
# Each attempt's record, in front of the start value and the stages (.loop.record_layout).
RECORD = ("ran", "accepted", "t", "h", "t_next", "iterations", "evaluations", "refreshed", "factored", "retries",
          "newton_failed")  # fmt: skip
# The statistics the controller counts from its own decisions; the Python stepper counts the others
# (Newton's iterations, the evaluations, the factorisations) as it makes them.
CONTROLLER_STATISTICS = ("attempts", "rejected_steps", "newton_failures")


def before_attempt(xp, carried: dict, settings: dict) -> dict:
    """What the controller decides before an attempt, from the :data:`CONTROLLER` scalars ``carried``
    and the :data:`SETTINGS`: ``underflow`` (the carried h underflows at t: the run ends there),
    ``h`` (shortened to end at t1, or stretched to it) and ``first`` (the error estimate is
    refiltered where it is 1 or more: a first step, or one after a rejection, but before the first
    accepted step only up to the probe's step, :func:`.formulas.refiltered_here`)."""
    t, h = carried["t"], carried["h"]
    step = formulas.step_length(xp, h, t, settings["t1"])
    first = xp.or_(carried["first"], carried["rejected_last"])
    return {
        "underflow": formulas.underflow(xp, h, t, settings["t1"]),
        "h": step,
        "first": formulas.refiltered_here(xp, first, step, carried["h_acc"], settings["trusted"]),
    }


def run_head(xp, carried: dict, settings: dict, h) -> dict:
    """What the compiled run decides before an attempt of ``h`` (:func:`before_attempt`'s), from its
    :data:`SCALARS` ``carried``: ``limited`` (its ``limit`` of attempts is spent), ``refreshed`` and
    ``factored``, and ``ratio`` (h / h_old, the start guess's; 0 without a last step).

    ``refreshed``: the Jacobian was not kept, and ``factored``: else h moved from the factors' beyond the
    rounding of t + h (``factors_h`` 0: no factors; :func:`.formulas.factors_serve`), are
    :meth:`.step.Stepper.current_jacobian`'s and :meth:`.step.Stepper.current_lu`'s decisions on the flags
    the run carries in place of the stepper's objects (None where dropped, as
    :meth:`.loop.CompiledRun.advance` packs them).  The stepper does not call this function: its factors
    can also be partial (the error estimate's system alone, before full Newton), which the run never
    makes, and it refactors those too.
    """
    refreshed = xp.not_(carried["jac_kept"])
    return {
        "limited": carried["attempts"] >= settings["limit"],
        "refreshed": refreshed,
        "factored": xp.and_(
            xp.not_(refreshed), xp.not_(formulas.factors_serve(xp, carried["factors_h"], h, carried["t"]))
        ),
        "ratio": xp.cond(carried["h_old"] > 0, lambda: h / carried["h_old"], lambda: 0.0),
    }


def after_attempt(xp, carried: dict, settings: dict, attempt: dict, s: int, iterations: int):
    """What the controller decides after an attempt: ``(carried, decisions)``, the :data:`CONTROLLER`
    scalars after it and the decisions.

    ``attempt``: ``h`` (the attempt's, :func:`before_attempt`'s), ``iterations`` (Newton's),
    ``error_norm`` (the estimate's, inf or NaN where Newton failed), ``newton_failed`` (every try
    failed with finite values: h is halved) and ``jac_kept`` (accepted, the step keeps its Jacobian:
    :meth:`.step.Stepper.keeps_jacobian`); ``s``: the stages, ``iterations``: Newton's most.

    ``decisions``: ``err`` (the error norm, inf where not finite), ``accepted``, ``t_next`` (where
    the step ends), ``h_rejected`` (the next h after a rejection), ``shrunk_away`` (rejected, and
    that h underflows: the run ends there).
    Every value is computed whichever way the attempt went (casadi evaluates both branches; on
    Python floats the branch not taken costs a few operations and raises nothing).
    """
    t, h, failed = carried["t"], attempt["h"], attempt["newton_failed"]
    err = formulas.finite_or_inf(xp, attempt["error_norm"])  # (NaN: inf)
    quot = formulas.error_quotient(xp, err, attempt["iterations"], s, iterations)
    accept = formulas.accepted(xp, failed, err)
    h_rejected = formulas.rejected_step(xp, h, quot, failed)
    shrunk_away = xp.and_(xp.not_(accept), formulas.underflow(xp, h_rejected, t))
    t_next = formulas.step_end(xp, t, h, settings["t1"])
    last, keep = (carried["h_acc"], carried["err_acc"]), (settings["keep_low"], settings["keep_high"])
    new_h, (h_acc, err_acc) = formulas.next_step(
        xp, h, err, quot, s, last, settings["predictive"], carried["rejected_last"], keep, attempt["jac_kept"]
    )
    after = {
        "t": xp.where(accept, t_next, t),
        "h": xp.where(accept, new_h, h_rejected),
        # (as RADAU5: after a failed Newton the next accepted step does not grow h)
        "first": xp.where(accept, False, xp.or_(failed, carried["first"])),
        "rejected_last": xp.not_(accept),
        "h_acc": xp.where(accept, h_acc, carried["h_acc"]),
        "err_acc": xp.where(accept, err_acc, carried["err_acc"]),
    }
    decisions = dict(err=err, accepted=accept, t_next=t_next, h_rejected=h_rejected, shrunk_away=shrunk_away)
    return after, decisions


def run_tail(xp, carried: dict, settings: dict, attempt: dict, after: dict, decisions: dict):
    """The compiled run after an attempt (:func:`after_attempt`'s ``after`` and ``decisions``), from its
    :data:`SCALARS` ``carried``, the :data:`SETTINGS` and the :data:`ATTEMPT`: ``(scalars, ran,
    taken, record)``, the :data:`SCALARS` after it (inactive where the integration reached t1),
    whether it ran, whether a step was taken, its :data:`RECORD`.

    An attempt does not run where the budget is spent (``limited``), or where Python must make it
    (handed back: the error is worded there): an underflow of h before it or after its rejection,
    factors that cannot serve (``singular``), a sign change of the iteration matrix's determinant
    between fresh Jacobians (:meth:`.step.Stepper.check_determined`'s) or over the stages
    (``stage_flip``), values that turned non-finite outside a Newton failure (a try's non-finite values
    fail the attempt as a diverging Newton does: :func:`.tries.attempt_tries`).  Then the
    scalars stay as they were, inactive, with the code why.
    """
    t, accept, failed = carried["t"], decisions["accepted"], attempt["newton_failed"]
    flipped = xp.or_(
        xp.and_(attempt["refreshed"], formulas.sign_flip(carried["det_sign"], attempt["sign"])),
        xp.and_(attempt["stale"], formulas.sign_flip(attempt["sign"], attempt["retry_sign"])),
    )
    non_finite = xp.and_(attempt["outcome"] != 0, xp.not_(failed))
    handback = attempt["underflow"]
    for flag in (attempt["singular"], flipped, non_finite, attempt["stage_flip"], decisions["shrunk_away"]):
        handback = xp.or_(handback, flag)
    ran = xp.not_(xp.or_(attempt["limited"], handback))
    refreshes = attempt["refreshed"] + attempt["stale"]
    done = xp.and_(accept, formulas.finished(xp, decisions["t_next"], settings["t0"], settings["t1"]))
    moved = {
        **after,
        "h_old": xp.where(accept, attempt["h"], carried["h_old"]),
        "eta": xp.where(failed, carried["eta"], attempt["eta"]),
        "jac_kept": xp.where(accept, attempt["jac_kept"], 1),  # (refreshed if it was not kept)
        "t_jac": xp.where(refreshes > 0, t, carried["t_jac"]),
        # (a rejected step drops its factors: h changes; factors that served keep their own h)
        "factors_h": xp.where(
            accept, xp.where(refreshes + attempt["factored"] > 0, attempt["h"], carried["factors_h"]), 0
        ),
        "det_sign": xp.where(attempt["stale"], attempt["retry_sign"], attempt["sign"]),
        "t_det": xp.where(refreshes > 0, t, carried["t_det"]),
        "attempts": carried["attempts"] + 1,
        "active": xp.not_(done),
        "code": xp.where(done, FINISHED, FULL),
    }
    stopped = {**carried, "active": 0, "code": xp.where(attempt["limited"], LIMIT, HANDBACK)}
    scalars = {name: xp.where(ran, moved[name], stopped[name]) for name in SCALARS.names}
    record = dict(ran=1, accepted=accept, t=t, h=attempt["h"], t_next=decisions["t_next"])
    record.update(iterations=xp.where(failed, 0, attempt["iterations"]), evaluations=attempt["evaluations"])
    record.update(refreshed=refreshes, factored=attempt["factored"], retries=attempt["retries"], newton_failed=failed)
    record = {name: xp.where(ran, record[name], 0) for name in RECORD}
    return scalars, ran, xp.and_(ran, accept), record


def statistics(sums: dict, shifts: int = 0) -> dict:
    """What attempts add to the run statistics, from the sums of their records' entries (:data:`RECORD`
    names; one attempt: its entries), ``shifts`` the LU decompositions of one factorisation.

    The one mapping from attempts to statistics: the compiled run counts its records by it, the
    Python controller its own decisions (:data:`CONTROLLER_STATISTICS`)."""
    failed = sums["newton_failed"]
    return {
        "attempts": sums["ran"],
        "rejected_steps": sums["ran"] - sums["accepted"] - failed,
        "newton_failures": failed,
        "newton_iterations": sums["iterations"],
        "residual_evaluations": sums["evaluations"],
        "jacobian_evaluations": sums["refreshed"] + failed,  # (the stages' at a failure: z's check)
        "compiled_retries": sums["retries"],
        "lu_decompositions": shifts * (sums["refreshed"] + sums["factored"]),
    }


def add_statistics(stats: dict, sums: dict, shifts: int = 0) -> None:
    """Add :func:`statistics` to ``stats``."""
    for name, value in statistics(sums, shifts).items():
        stats[name] += int(value)


def add_attempt(stats: dict, accepted: bool, newton_failed: bool) -> None:
    """Add one attempt of the Python controller to its :data:`CONTROLLER_STATISTICS` (:func:`statistics`
    of its record, made once for each outcome: a few additions per attempt)."""
    for name, value in ATTEMPT_COUNTS[bool(accepted), bool(newton_failed)]:
        stats[name] += value


NO_RECORD = dict.fromkeys(RECORD, 0)
# What one attempt adds to the CONTROLLER_STATISTICS, by (accepted, newton_failed).
ATTEMPT_COUNTS = {
    (accepted, failed): tuple(
        (name, int(value))
        for name, value in statistics(dict(NO_RECORD, ran=1, accepted=accepted, newton_failed=failed)).items()
        if name in CONTROLLER_STATISTICS
    )
    for accepted, failed in ((True, False), (False, False), (False, True))
}

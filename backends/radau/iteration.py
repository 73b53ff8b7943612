"""The simplified Newton iteration's state machine, written once over an array namespace.

A pass reads one increment's scaled norm and moves a :class:`NewtonState`: it iterates (the tests of
:func:`.formulas.newton_iteration`, in their order), checks a one-iteration convergence by one more
increment (:data:`.formulas.CHECK`), or only evaluates f at the final stages for the error estimate
(:data:`.formulas.EVALUATE`), and counts iterations and residual evaluations.  The same function runs

- on the engine's arrays (:class:`.formulas.ArrayOps`) in :meth:`.newton.Newton.simplified`: the
  contraction, the rate, the last norm and the samples still iterating are per sample, the rest are
  Python numbers and the branches Python's (no idle pass, no increment where only f is needed);
- on casadi SX symbols in :func:`.compiled.newton_tests`, one pass of the compiled attempt's unrolled
  loop (:func:`.compiled.step_function`): one trajectory, every branch evaluated and selected;

so that both take the same iterates, outcomes and counts, bit for bit.  What only Python does stays
around it in :mod:`.newton`: the increment itself, the worded failure (which sample, the non-finite
value's culprit) and the fixed grid's rescue (full Newton where the contraction is slow).
"""

from __future__ import annotations

from typing import NamedTuple

from daemodel.backends.radau import formulas
from daemodel.backends.radau.formulas import CHECK, CONVERGED, EVALUATE, ITERATING, NewtonTests


class NewtonState(NamedTuple):
    """Where the simplified Newton iteration of one step stands (arrays: the first three and
    ``iterating`` per sample, the rest Python numbers; casadi: scalar symbols).

    The compiled attempt carries every part but ``iterating`` through its passes, in this order
    (:data:`.compiled.NEWTON_STATE`): on one trajectory ``iterating`` is ``mode == ITERATING``.
    """

    previous: object  # the last increment's scaled norm (read from the second iteration on)
    theta: object  # the contraction of the last increment against the one before (.formulas.mean_contraction)
    ratio: object  # the last ratio of increments (0 before the second iteration)
    eta: object  # the rate theta / (1 - theta) (at the start: the last step's, RADAU5)
    k: object  # the iterations made
    mode: object  # ITERATING, CHECK (of a convergence at k = 1) or EVALUATE (f at the final stages)
    outcome: object  # CONVERGED (so far), or the failure that ended the iteration
    active: object  # another pass is due (neither finished nor failed)
    evaluations: object  # the residual evaluations counted (a refuted check: two, see newton_pass)
    iterating: object  # the samples still iterating


def newton_start(eta, zeros, everyone) -> NewtonState:
    """The state before the first iteration: the start rate ``eta``, ``zeros`` for the last norm and the
    contraction (the first iteration reads neither), ``everyone`` iterating."""
    return NewtonState(
        previous=zeros, theta=zeros, ratio=zeros, eta=eta, k=0, mode=ITERATING, outcome=CONVERGED, active=True,
        evaluations=0, iterating=everyone,
    )  # fmt: skip


class NewtonPass(NamedTuple):
    """What one :func:`newton_pass` found: the state after it, whether it iterated (the caller adds the
    increment where ``iterating`` of the pass, see :attr:`moved`), and the iteration's tests."""

    state: NewtonState
    iterate: object  # this pass was an iteration (the increment is taken)
    moved: object  # the samples whose stage values take this increment
    tests: NewtonTests  # .formulas.newton_iteration's (failing samples, slow ones; idle where not iterated)


def newton_pass(
    xp,
    state: NewtonState,
    norm,
    tol,
    iterations: int,
    to_rounding=False,
    slow_ends=True,
    trust_last_rate=True,
    geometric=False,
) -> NewtonPass:
    """One pass of the simplified Newton iteration on ``norm``, the scaled norm of the increment at the
    current stage values (None on arrays in :data:`.formulas.EVALUATE` mode: nothing is tested there).

    By ``state.mode``:

    - ITERATING: the samples ``state.iterating`` iterate (their increments taken: the caller masks the
      others' to zero before the norm, as it must for :func:`.formulas.newton_iteration`);
    - CHECK (RADAU5's start trusted the last rate and one iteration converged,
      :func:`.formulas.after_convergence`): the samples whose increment is not small too
      (:func:`.formulas.confirmed`) iterate on with it as their second iteration; where none, the
      iteration has converged at the stage values before it.  A refuted check counts two residual
      evaluations (the general path evaluated the second iteration's increment again, at the same
      stage values: the statistics stay as they were);
    - EVALUATE: f at the final stages, one evaluation, and the iteration has converged.

    ``tol``, ``iterations``, ``to_rounding``, ``slow_ends`` and ``geometric`` (the contraction's mean,
    :func:`.formulas.geometric_contraction`): :func:`.formulas.newton_iteration`'s;
    ``trust_last_rate`` (a Python flag): a convergence is checked or followed by an evaluation, else
    (the fixed grid) it ends the iteration at once (f at the last evaluation's stage values serves).
    """
    checking, evaluating = state.mode == CHECK, state.mode == EVALUATE
    # at a check, the samples that the increment refutes iterate on (on arrays only there is `any` a read)
    moved = xp.cond(checking, lambda: xp.not_(formulas.confirmed(norm, tol)), lambda: state.iterating)
    iterate = xp.cond(checking, lambda: xp.any(moved), lambda: xp.not_(evaluating))
    k = state.k + iterate

    def tested():
        return formulas.newton_iteration(
            xp, norm, state.previous, state.theta, state.eta, moved, k <= 1, iterations - k, tol,
            to_rounding=to_rounding, slow_ends=slow_ends, ratio=state.ratio, geometric=geometric,
        )  # fmt: skip

    def idle():  # (where no sample moves, the tests leave theta and eta, and fail nothing)
        return NewtonTests(CONVERGED, state.theta, state.eta, moved, False, False, False, state.ratio)

    tests = xp.guard(iterate, tested, idle)
    failed = xp.and_(iterate, tests.outcome != CONVERGED)
    converged = xp.and_(iterate, xp.not_(tests.running))  # every sample converged at this iteration
    active = xp.and_(iterate, xp.not_(failed))
    if not trust_last_rate:
        active = xp.and_(active, xp.not_(converged))
    after = NewtonState(
        previous=xp.where(iterate, norm, state.previous),
        theta=tests.theta,
        ratio=tests.ratio,
        eta=tests.eta,
        k=k,
        mode=xp.where(converged, formulas.after_convergence(xp, k, iterations), ITERATING),
        outcome=xp.where(failed, tests.outcome, state.outcome),
        active=active,
        evaluations=state.evaluations + 1 + xp.and_(checking, iterate),
        iterating=tests.active,
    )
    return NewtonPass(after, iterate, moved, NewtonTests(*tests))

"""Near misses: an event function that comes within the method's error of zero between two outputs and does
not cross there in the method's own solution.

Whether a function crosses is decided on the method's own solution (a touch is no crossing), but that
solution's error is not its tolerance.  casadi-idas at rtol = atol = 1e-7 loses 9.8e-6 of a unit oscillator's
amplitude in 20 s (radau 4.5e-11): the peaks of sin t stayed up to 6.9e-6 below 0.999999 in its solution,
and the declared event on 0.999999 - sin(t + phase) fired 0 to 4 times of its 6 to 8 crossings in each of 16
phases, each solve "success" (tests/solving/test_events_edges.py).  The probes of
:mod:`daemodel.solving.between` find such an extremum's nearest point to zero where each look solves again
(:class:`~daemodel.solving.between.Excursion` with ``near``); one within :data:`NEAR_MISS_TOLS` tolerances of
zero (in what a tolerance of the variables moves the function: :func:`function_tolerance`) is solved again
:data:`TIGHTER` times tighter, on from the piece's start (one tighter solve of a piece, however many near
misses it holds).  Where that solution crosses, by more than its own error and tolerance, the crossing lies
within the method's error: the solve's status says so (:meth:`NearMiss.status`), never
"success".  The tighter solve starts from the method's own values at the piece's start, which carry the error
of the pieces before it: with an event at each zero of s (a piece every half period), casadi-idas at rtol 1e-7
counted 0 to 2 of the 12 to 14 crossings of 0.999999 - s over (0, 40) in 7 of 8 phases, each "success", its
amplitude lost in earlier pieces and the tighter solve from each piece's start losing it too.  That error is
estimated (:class:`CarriedErrors`: each earlier piece solved again :data:`TIGHTER` times tighter from its own
start, the differences at its end added up, once per piece and only where a near miss asks), and a near miss
whose tighter solve stays within it of zero is flagged too: whether it crosses is not decided at the accuracy
the solution has there.  Adding the pieces' differences ignores how the flow and the resets carry each one on
(an oscillator keeps them, a contracting flow shrinks them: an overestimate there, flagged more often).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from daemodel.errors import InvalidOptionError, SolverError, TimeLimitError

# An extremum towards zero that the method's own solution leaves within this many tolerances of zero (how far
# atol + rtol |v| in its variables moves the event function: function_tolerance) is checked by a tighter
# solve: casadi-idas's error on an oscillator at rtol 1e-7 is 50 tolerances after 3 periods (9.8e-6 at t = 20),
# and it grows with the span.
NEAR_MISS_TOLS = 1000
# The check's solve: rtol and atol this many times smaller (its error, at IDAS's order 5 or less, about
# 100^(1/5) = 2.5 times as many steps).
TIGHTER = 100


@dataclass(frozen=True)
class NearMiss:
    """An event function the method's solution leaves ``value`` from zero at ``t``, where a solve
    :data:`TIGHTER` times tighter reaches ``tight`` on the other side (None: that solve failed)."""

    event: str
    t: float
    value: float
    tight: float | None
    carried: float = 0.0  # (the error in the function carried in from earlier pieces, where the tighter solve stays)

    def status(self, method: str) -> str:
        """The solve's status, naming the event, the time, both values and the fix."""
        said = "a crossing within the method's error, not located"
        if self.tight is None:
            seen = f"a solve {TIGHTER} times tighter, to check it, failed"
        elif self.carried:
            seen = (
                f"a solve {TIGHTER} times tighter from the piece's start stays {self.tight:.3g} from it, within the "
                f"error carried in from earlier pieces ({self.carried:.3g})"
            )
            said = "whether it crosses is not decided at the method's accuracy"
        else:
            seen = f"a solve {TIGHTER} times tighter crosses to {self.tight:.3g}"
        return (
            f"event '{self.event}' near t = {self.t:.10g}: its function stays {self.value:.3g} from zero in "
            f"{method}'s solution, where {seen}: {said}; tighten rtol/atol"
        )


def status_of(missed: list, method: str) -> list[str]:
    """The statuses of the near misses ``missed`` (:class:`NearMiss`): the first one's, with how many more."""
    if not missed:
        return []
    more = f" (and {len(missed) - 1} more, the last near t = {missed[-1].t:.10g})" if len(missed) > 1 else ""
    return [missed[0].status(method) + more]


def function_tolerance(when, options, which: int, t: float, y: np.ndarray, z: np.ndarray, P: np.ndarray) -> float:
    """How far one tolerance of ``options`` (``atol + rtol |v|`` in every state and algebraic variable ``v``) moves
    the event function ``which`` at ``(t, y (1, n), z (1, m))``: the larger move of two, all variables moved up
    and every other one down (so that a difference of two variables does not cancel); 0 for a method without
    rtol and atol."""
    rtol, atol = getattr(options, "rtol", None), getattr(options, "atol", None)
    if rtol is None or atol is None:
        return 0.0
    v = np.concatenate([y, z], axis=1)[0]
    step = atol + rtol * np.abs(v)
    V = np.stack([v, v + step, v + step * (1 - 2 * (np.arange(len(v)) % 2))])
    n = y.shape[1]
    F = when(np.full(3, t), V[:, :n], V[:, n:], np.repeat(P, 3, axis=0))[:, which]
    return float(np.max(np.abs(F[1:] - F[0])))


def tighter(options):
    """``options`` with rtol and atol :data:`TIGHTER` times smaller; None where the method refuses them (an
    rtol already at its floor) or has neither."""
    if getattr(options, "rtol", None) is None or getattr(options, "atol", None) is None:
        return None
    try:
        return dataclasses.replace(options, rtol=options.rtol / TIGHTER, atol=options.atol / TIGHTER)
    except InvalidOptionError:
        return None


class CarriedErrors:
    """The error the pieces before one carry into it (see the module docstring), in tolerances: :meth:`add` each
    piece as it ends, :meth:`total` adds up those not yet solved again."""

    def __init__(self):
        self.pending, self.sum = [], 0.0

    def add(self, solve, y: np.ndarray, z: np.ndarray) -> None:
        """A piece that ended with the method's values ``y`` (1, n), ``z`` (1, m); ``solve(options) -> (y, z)`` solves
        it again from its start with ``options``."""
        self.pending.append((solve, np.concatenate([y, z], axis=1)[0]))

    def total(self, options) -> float:
        """The pieces' differences from their solves :data:`TIGHTER` times tighter, each in tolerances of its end
        values (``atol + rtol |v|``, the largest over the variables: a rotation moves an error from one to
        another), added up; 0 without pieces before or without rtol and atol, infinite where such a solve fails."""
        tight = tighter(options)
        if tight is None:
            return 0.0
        while self.pending:
            solve, v = self.pending.pop(0)
            try:
                y, z = solve(tight)
            except TimeLimitError:
                raise
            except SolverError:
                self.pending.clear()
                self.sum = np.inf
                break
            moved = np.abs(np.concatenate([y, z], axis=1)[0] - v) / (options.atol + options.rtol * np.abs(v))
            self.sum += float(np.max(moved, initial=0.0))
        return self.sum


class NearMisses:
    """The near misses of one piece's scan: :meth:`check` each.  ``trial(options, a, tau, ya, za, which) ->
    (F, y, z)`` solves the piece from ``(a, ya, za)`` to ``tau`` with ``options``, returning the event function
    ``which`` there; ``when(t, Y, Z, P)``: the event functions; ``carried``: the pieces' before it
    (:class:`CarriedErrors`).  The tighter solve goes on from where the last check left it (one solve of the
    piece)."""

    def __init__(self, trial, when, P: np.ndarray, options, a: float, ya: np.ndarray, za: np.ndarray, carried=None):
        self.trial, self.when, self.P, self.options, self.at = trial, when, P, options, (a, ya, za)
        self.tight = tighter(options)
        self.carried = carried

    def check(self, x, name: str, y: np.ndarray, z: np.ndarray) -> NearMiss | None:
        """The near miss ``x`` (:class:`~daemodel.solving.between.Excursion` with ``near``) of the event ``name``,
        ``y`` (1, n) and ``z`` (1, m) the variables about it, as a :class:`NearMiss` where the tighter solve
        crosses by more than its own error and tolerance; else None."""
        scale = function_tolerance(self.when, self.options, x.event, x.t, y, z, self.P)
        a, ya, za = self.at
        if self.tight is None or not x.near <= NEAR_MISS_TOLS * scale or x.t <= a:
            return None
        try:
            value, y_tight, z_tight = self.trial(self.tight, a, x.t, ya, za, x.event)
        except TimeLimitError:  # (the time that ran out is not the check's failure)
            raise
        except SolverError:
            return NearMiss(name, x.t, x.near, None)
        self.at = (x.t, y_tight, z_tight)
        # (past zero by more than its own error, estimated as 1/TIGHTER of the two solves' difference, and its
        # tolerance: a rounding past zero is no crossing.  An exact touch whose tighter solve goes further past
        # is flagged, undecided at that accuracy: 1 - sin(t + phase) at rtol 1e-7, 4 of 16 phases, 6e-9 past)
        if x.side * value < -max(abs(x.side * x.near - value) / TIGHTER, scale / TIGHTER):
            return NearMiss(name, x.t, x.near, value)
        carried = 0.0 if self.carried is None else self.carried.total(self.options) * scale
        if carried and x.side * value <= carried:  # (on its side, but within the error carried in: undecided)
            return NearMiss(name, x.t, x.near, value, carried)
        return None

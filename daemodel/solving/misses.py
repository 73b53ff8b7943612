"""Near misses: an event function that comes within the method's error of zero between two outputs and does
not cross there in the method's own solution.

Whether a function crosses is decided on the method's own solution (a touch is no crossing), but that solution's
error is not its tolerance.  casadi-idas at rtol = atol = 1e-7 loses 9.8e-6 of a unit oscillator's amplitude in 20 s
(radau 4.5e-11): the peaks of sin t stayed up to 6.9e-6 below 0.999999 in its solution, and the declared event on
0.999999 - sin(t + phase) fired 0 to 4 times of its 6 to 8 crossings in each of 16 phases, each solve "success"
(tests/solving/test_events_edges.py).  The probes of :mod:`daemodel.solving.between` find such an extremum's nearest
point to zero where each look solves again (:class:`~daemodel.solving.between.Excursion` with ``near``); one within
:data:`NEAR_MISS_TOLS` tolerances of zero (in what a tolerance of the variables moves the function:
:func:`function_tolerance`) is solved again :data:`TIGHTER` times tighter, on from the piece's start (one tighter
solve of a piece, however many near misses it holds).  Where that solution crosses, by more than its own error and
tolerance, the crossing lies within the method's error: the solve's status says so (:meth:`NearMiss.status`), never
"success".  A tighter solve from the method's own values at the piece's start carries the error of the pieces before
it: with an event at each zero of s (a piece every half period), casadi-idas at rtol 1e-7 counted 0 to 2 of the 12
to 14 crossings of 0.999999 - s over (0, 40) in 7 of 8 phases, each "success", its amplitude lost in earlier pieces
and the tighter solve from each piece's start losing it too.  So the tighter solve starts from the solution
:data:`TIGHTER` times tighter from t0 (:class:`CarriedErrors`: each earlier piece solved again from the last one's
end, after that one's resets, once per piece and only where a near miss asks), which carries the method's error on
as the flow and the resets do; a near miss whose tighter solve stays within that solution's own error carried in
(1/:data:`TIGHTER` of its distance from the method's values at the piece's start) is flagged too: whether it crosses
is not decided.  Before (9361bc5), the pieces' differences were added up, ignoring the flow: a damped oscillator
whose last peak lies 1e-6 below the level, which IDAS at rtol 1e-7 reaches to 3e-8, was flagged as undecided within
6.2e-6 (54 tolerances) "carried in".  The event times are the method's (a tighter solve's would differ by their
error: its resets are applied at the method's times, an error of the method's that the estimate does not see).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from daemodel.errors import InvalidOptionError, ModelError, SolverError, TimeLimitError

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
                f"a solve {TIGHTER} times tighter from t0, through the pieces before, stays {self.tight:.3g} from "
                f"it, within its own error carried in from them ({self.carried:.3g})"
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
    changes = {"rtol": options.rtol / TIGHTER, "atol": options.atol / TIGHTER}
    if getattr(options, "stages_by_default", False):
        # (radau's stages picked by rtol: picked again for the tighter one, as a solve given it picks them; kept,
        # they were refused beside stages_by_default, and radau at rtol 1e-8 went unchecked)
        changes.update(stages=None, stages_by_default=False)
    try:
        return dataclasses.replace(options, **changes)
    except InvalidOptionError:
        return None


class CarriedErrors:
    """The solution :data:`TIGHTER` times tighter from t0 through the pieces before one (see the module docstring):
    :meth:`add` each piece as it ends, :meth:`restart` where the next one starts; :meth:`start` solves them."""

    def __init__(self):
        self.pending, self.tight = [], None
        self.error = 0.0  # (how far the method's values lie from the tighter solution's where the last piece ends)

    def add(self, solve) -> None:
        """A piece that ended: ``solve(options, y0, z0) -> (y (1, n), z (1, m))`` solves it again with ``options``
        from ``(y0, z0)`` (None: the method's own start) to its end."""
        self.pending.append([solve, None, None])

    def restart(self, after, y: np.ndarray, z: np.ndarray) -> None:
        """The next piece starts from the method's ``y`` (1, n), ``z`` (1, m), where ``after(y, z) -> (y, z)`` (the
        resets, the projection onto the constraints, the algebraic variables solved anew; None: none) takes the
        last piece's end."""
        self.pending[-1][1:] = [after, np.concatenate([y, z], axis=1)[0]]

    def start(self, options) -> tuple | None:
        """``(y (1, n), z (1, m))`` of the solution :data:`TIGHTER` times tighter than ``options`` where the last
        piece ends: each piece solved again from the last one's end after that one's resets (the error the method
        carries in, as its flow and resets carry it on: a contracting flow shrinks it), at most once and only when
        asked; :attr:`error` is how far the method's values lie from it there, in their tolerances (``atol + rtol
        |v|``, the largest over the variables: a rotation moves an error from one to another).  None without pieces
        before, without rtol and atol, or where such a solve failed (:attr:`error` infinite)."""
        tight = tighter(options)
        if tight is None:
            return None
        while self.pending and self.pending[0][2] is not None and self.error < np.inf:
            solve, after, v = self.pending.pop(0)
            try:
                y, z = solve(tight, *(self.tight or (None, None)))
                self.tight = (y, z) if after is None else after(y, z)
            except TimeLimitError:
                raise
            except (SolverError, ModelError):  # (the solve, or what follows its end: the resets, the projection)
                self.pending.clear()
                self.tight, self.error = None, np.inf
                break
            moved = np.abs(np.concatenate(self.tight, axis=1)[0] - v) / (options.atol + options.rtol * np.abs(v))
            self.error = float(np.max(moved, initial=0.0))
        return self.tight


class NearMisses:
    """The near misses of one piece's scan: :meth:`check` each.  ``trial(options, a, tau, ya, za, which) ->
    (F, y, z)`` solves the piece from ``(a, ya, za)`` to ``tau`` with ``options``, returning the event function
    ``which`` there; ``when(t, Y, Z, P)``: the event functions; ``carried``: the pieces' before it
    (:class:`CarriedErrors`).  The tighter solve goes on from where the last check left it (one solve of the
    piece)."""

    def __init__(self, trial, when, P: np.ndarray, options, a: float, ya: np.ndarray, za: np.ndarray, carried=None):
        self.trial, self.when, self.P, self.options, self.at = trial, when, P, options, (a, ya, za)
        self.tight = tighter(options)
        self.carried, self.band = carried, None

    def check(self, x, name: str, y: np.ndarray, z: np.ndarray) -> NearMiss | None:
        """The near miss ``x`` (:class:`~daemodel.solving.between.Excursion` with ``near``) of the event ``name``,
        ``y`` (1, n) and ``z`` (1, m) the variables about it, as a :class:`NearMiss` where the tighter solve
        crosses by more than its own error and tolerance; else None."""
        scale = function_tolerance(self.when, self.options, x.event, x.t, y, z, self.P)
        a, ya, za = self.at
        if self.tight is None or not x.near <= NEAR_MISS_TOLS * scale or x.t <= a:
            return None
        if self.band is None:  # (the piece's first check: from the tighter solution through the pieces before)
            start = None if self.carried is None else self.carried.start(self.options)
            ya, za = (ya, za) if start is None else start
            # (that solution's own error carried in, in tolerances: 1/TIGHTER of its distance from the method's)
            self.band = 0.0 if self.carried is None else self.carried.error / TIGHTER
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
        carried = self.band * scale
        if carried and x.side * value <= carried:  # (on its side, but within the error carried in: undecided)
            return NearMiss(name, x.t, x.near, value, carried)
        return None

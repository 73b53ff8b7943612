"""A switch whose function rests on zero: a state that decays onto its guard (x' = -x under Max(x, 0), x = e^-t)
stays within the method's error of zero, where the sign of the method's solution is its error's.

casadi-idas (rtol 1e-8) stepped x across zero at t = 21.6 by its own error and the crossing was located; the
piece after it started on the branch the flow had crossed to, the method's x came back across within its
error, and :func:`daemodel.solving.events._clear_of_zero` raised :class:`~daemodel.errors.ZenoError` ("does not
leave zero to the side the flow takes") for a solution that is smooth (the reference method at t = 33; radau,
whose x stays positive, said "success" 6e-16 off).

Where the two branches of the switch agree there (:func:`rest_or_raise`: their rates at the piece's start over
the rest of t_span, and the algebraic variables solved on each, within :data:`REST_BUDGET` tolerances: Max(x, 0),
Min(1, x), Abs(x) are continuous), either branch is within tolerance while the function stays near zero: the
piece keeps the branch it started on (a :class:`Rest`) and its detection watches the function past a band of
:data:`RESTING_TOLS` tolerances on the other side (:func:`watch`), not past zero.  Past the band on either side
the rest ends (:func:`gone`) and the switch is an event again.  What the choice could cost is measured along the
method's own solution (:meth:`Rest.account`: the two branches' difference in rate integrated, signed, over the
outputs where the function is within the band, and in the algebraic variables, in tolerances): past
:data:`REST_BUDGET` the status says so.  Where the branches differ (sign(x), Heaviside(x), floor(x) at an
integer: a jump), which one holds is not decided at the method's accuracy: :class:`~daemodel.errors.ZenoError`,
which says so.  Used by :mod:`daemodel.solving.events`.
"""

from __future__ import annotations

import dataclasses
import math
from types import SimpleNamespace

import numpy as np

from daemodel.compiling.switches import lock_branches
from daemodel.errors import SwitchError, ZenoError
from daemodel.solving.branches import EXCURSION_BUDGET
from daemodel.solving.misses import function_tolerance
from daemodel.solving.pieces import onto_constraints
from daemodel.solving.switches import for_method

# The band about zero a resting function is watched past, in tolerances of its variables (misses.function_tolerance):
# scipy's solution of x' = -x at rtol = atol = 1e-8 strays 18 atol below zero (x = -1.8e-7 after t = 20).
RESTING_TOLS = 100
# The two branches' difference over a rest, in tolerances (the weighted root mean square the adaptive methods hold
# each step's error to, times the time), that either branch keeps within the tolerance: the excursions' budget.
REST_BUDGET = EXCURSION_BUDGET


@dataclasses.dataclass
class Rest:
    """The switch event ``event`` resting on zero since ``start``: watched past ``band`` on the side other than
    the piece's branch; ``moved``: how far the other branch would have moved each state so far, and ``shifted``:
    its algebraic variables' difference integrated over ``spent``, the time counted (:meth:`account`)."""

    event: int
    name: str
    band: float
    start: float
    moved: np.ndarray | None = None
    shifted: np.ndarray | None = None
    spent: float = 0.0
    flagged: bool = False

    def account(self, compiled, backend, piece, options, P, side: int, T, Y, Z, F) -> str | None:
        """Add to :attr:`moved` the integral of the other branch's rates less ``piece``'s (branch ``side``) over the
        outputs ``T`` (K,) with variables ``Y`` (K, n), ``Z`` (K, m) and this event's function ``F`` (K,), counted
        where the function is within the band (where the other branch may be the solution's; the output past it on
        the other side ends the piece, and one past it on the piece's side is on its branch), signed, so that the
        method's error that takes the function back and forth across zero cancels as it does in the states; and to
        :attr:`shifted` the same integral of how far the algebraic variables solved on the other branch lie from the
        piece's (their mean over the time counted: signed too, the method's error in a state at rest on zero shifts
        them both ways; the reference's x = e^-t rests 1e-11, 37 atol, off zero, each way).  The status where those,
        in tolerances of the last output (the weighted root mean square the adaptive methods hold each step's error
        to), pass :data:`REST_BUDGET`, once; else None."""
        if len(T) < 2 or self.flagged:
            return None
        phi = compiled.events[self.event].when
        other = lock_branches(compiled, T[0], Y[0], Z[0], P[0], {phi: -side})
        tolerances, inside = _tolerances(options), np.abs(F) <= self.band
        change = None if tolerances is None else _differences(compiled, backend, piece, other, T, Y, Z, P, inside)
        if change is None:
            weight = math.inf
        else:
            rates, shifts = change
            moved = np.sum(0.5 * (rates[1:] + rates[:-1]) * np.diff(T)[:, None], axis=0)
            self.moved = moved if self.moved is None else self.moved + moved
            shifted = np.sum(0.5 * (shifts[1:] + shifts[:-1]) * np.diff(T)[:, None], axis=0)
            self.shifted = shifted if self.shifted is None else self.shifted + shifted
            self.spent += float(np.sum(0.5 * (inside[1:] + inside[:-1]) * np.diff(T)))
            rtol, atol = tolerances
            mean = self.shifted / self.spent if self.spent > 0 else 0.0 * self.shifted
            weighted = np.concatenate(
                [self.moved / (atol + rtol * np.abs(Y[-1])), mean / (atol + rtol * np.abs(Z[-1]))]
            )
            weight = float(np.sqrt(np.mean(weighted**2)))
        if weight <= REST_BUDGET:
            return None
        self.flagged = True
        return (
            f"switch '{self.name}' rests on zero within the method's error from t = {self.start:.10g}, where its "
            f"other branch would have moved the states by {weight:.3g} tolerances by t = {T[-1]:.10g}: the branch "
            "kept is not within the tolerance; tighten rtol/atol, or smooth the switch"
        )


def rest_or_raise(
    error: ZenoError,
    compiled,
    backend,
    piece,
    side: int,
    options,
    P,
    which: int,
    t: float,
    y,
    z,
    t1: float,
    ahead: float | None = None,
) -> Rest:
    """A :class:`Rest` for the switch event ``which``, whose function the method's solution does not take off zero
    where ``piece`` (on its branch ``side``) starts from ``(t, y (1, n), z (1, m))`` (``error``, from
    ``_clear_of_zero``, which looked up to ``ahead``), where its two branches there differ by at most
    :data:`REST_BUDGET` tolerances: their rates over the rest of t_span, to ``t1``, and the algebraic variables
    solved on each.

    Raises
    ------
    ZenoError
        ``error`` for a declared event; for a switch whose branches differ there (a jump), one that says so.
    SwitchError
        At ``ahead``, no state near ``y`` satisfies the constraints on either branch: the function does not rest on
        zero, the constraints have no real solution past the switch (|x| = 1 - t past t = 1).
    """
    event = compiled.events[which]
    if not event.strict:
        raise error
    one, other = piece, lock_branches(compiled, t, y[0], z[0], P[0], {event.when: -side})
    if ahead is not None and ahead > t:
        _solvable_past(compiled, event, options, t, ahead, {side: one, -side: other}, y, z, P)
    if event.integer:  # (the levels on each side of the integer: the piece's side is not a branch's)
        one, other = (lock_branches(compiled, t, y[0], z[0], P[0], {event.when: way}) for way in (1, -1))
    tolerances = _tolerances(options)
    change = None if tolerances is None else _differences(compiled, backend, one, other, np.array([t]), y, z, P)
    weight = math.inf
    if change is not None:
        rtol, atol = tolerances
        rates, shifts = change
        weighted = np.concatenate(
            [rates[0] * (t1 - t) / (atol + rtol * np.abs(y[0])), shifts[0] / (atol + rtol * np.abs(z[0]))]
        )
        weight = float(np.sqrt(np.mean(weighted**2)))
    if not weight <= REST_BUDGET:
        said = (
            "with no tolerance to weigh them by: give rtol and atol, or estimate_bound"
            if tolerances is None
            else "the algebraic variables have no solution on the other"
            if change is None
            else f"by {weight:.3g} tolerances over the rest of t_span"
        )
        raise ZenoError(
            f"switch '{event.name}' at t = {t:.12g}: {event.when} rests on zero within the method's error (the "
            f"method's solution does not leave zero to the side the flow takes), where its two branches differ "
            f"({said}): which one holds is not decided at this accuracy; smooth the switch (e.g. tanh(s/eps) for "
            "sign(s)), or end t_span before it",
            t,
        ) from None
    when = compiled.numeric.batch_function([event.when])
    rtol, atol = tolerances
    band = RESTING_TOLS * function_tolerance(when, SimpleNamespace(rtol=rtol, atol=atol), 0, t, y, z, P)
    return Rest(which, event.name, band, t)


def _solvable_past(compiled, event, options, t: float, ahead: float, branches: dict, y, z, P) -> None:
    """Raise :class:`~daemodel.errors.SwitchError` where at ``ahead`` the states near ``y`` (1, n) that satisfy the
    constraints of each of ``branches`` (side -> the model locked to it, from ``t``) lie on the other side of the
    switch ``event``, by more than a tolerance (``options``') and the function's distance from zero at ``y``: the
    function cannot rest on zero there, nor leave it (|x| = 1 - t past t = 1: x = 1 - t on the branch x > 0, t - 1
    on the other).  Before 60745ba (the algebraic variables at radau's outputs solved from the states) radau located
    that switch past t = 1, where the projection after it said so; since, located at 1, the rest's weighing of the
    branches called it a ZenoError."""
    when = compiled.numeric.batch_function([event.when])
    at = np.array([float(ahead)])
    scale = 0.0 if _tolerances(options) is None else function_tolerance(when, options, 0, t, y, z, P)
    here = abs(float(when(np.array([t]), y, z, P)[0, 0]))
    failed = []
    for side, branch in branches.items():
        try:
            projected = onto_constraints(dataclasses.replace(branch, t0=float(ahead)), y, P)
        except SwitchError as error:
            failed.append(str(error))
            continue
        value = float(when(at, projected, z, P)[0, 0])
        if side * value >= -(here + scale):
            return
        failed.append(f"on the branch {event.when} {'>' if side > 0 else '<'} 0 it is {value:.3g} at t = {ahead:.10g}")
    raise SwitchError(
        f"switch '{event.name}' at t = {t:.12g}: past it no state satisfies the constraints on either side of "
        f"{event.when} = 0 ({'; '.join(failed)}): the switch leaves the constraints without a real solution there"
    )


def _tolerances(options) -> tuple | None:
    """``(rtol, atol)`` the variables are solved to: an adaptive method's own, a fixed step's ``estimate_bound`` for
    both (its local error estimate's bound: :func:`daemodel.solving.locate.states_tol`); None where it has neither."""
    if getattr(options, "h", None) is not None:
        bound = getattr(options, "estimate_bound", None)
        return (float(bound), float(bound)) if isinstance(bound, float | int) else None
    rtol, atol = getattr(options, "rtol", None), getattr(options, "atol", None)
    if rtol is None or atol is None:
        return None
    return np.asarray(rtol, dtype=float), np.asarray(atol, dtype=float)


def _differences(compiled, backend, one, other, T, Y, Z, P, counted=None) -> tuple | None:
    """``(rates (K, n), shifts (K, m))``: the rates of the model ``other`` less those of ``one`` at the outputs
    ``(T (K,), Y (K, n), Z (K, m))``, and its algebraic variables less ``Z`` (solved on its constraints where they
    differ from ``one``'s, from ``Z``), 0 at the outputs not ``counted`` (K,); None where they have no solution."""
    from daemodel.compiling.initial_states import algebraic_values
    from daemodel.errors import ModelError

    counted = np.ones(len(T), dtype=bool) if counted is None else counted
    Z_other = Z.copy()
    if one.constraints != other.constraints:
        reduced = for_method(other, backend)
        try:
            for k in np.flatnonzero(counted):
                Z_other[k : k + 1] = algebraic_values(reduced, float(T[k]), Y[k : k + 1], P, Z[k : k + 1])
        except ModelError:
            return None
    numeric, PP = compiled.numeric, np.repeat(P, len(T), axis=0)
    rates = numeric.batch_function(list(other.rhs))(T, Y, Z_other, PP) - numeric.batch_function(list(one.rhs))(
        T, Y, Z, PP
    )
    shifts = Z_other - Z
    rates[~counted], shifts[~counted] = 0.0, 0.0
    return rates, shifts


def watch(begin, rests: dict, when, t: float, Y, Z, P, fired) -> tuple:
    """``(begin, rests, sides)`` for the piece from ``t``: the rests still on (not those whose event fired at ``t``
    after they began, leaving the band, nor those whose function is past their band there), and ``begin`` (a
    :class:`~daemodel.solving.branches.Start`) with each one's function ``F`` seen as ``F + side band``, ``side``
    its branch in the piece (its side at zero, else its value's): of that side until ``F`` leaves the band on the
    other one."""
    if not rests:
        return begin, rests, {}
    F0 = when(np.array([t]), Y, Z, P)[0]
    rests = {e: rest for e, rest in rests.items() if not (e in fired and t > rest.start) and abs(F0[e]) <= rest.band}
    sides = {e: int(begin.sides[e]) or int(np.sign(F0[e])) or 1 for e in rests}
    if not rests:
        return begin, rests, sides
    inner = begin.when

    def watched(t, Y, Z, P):
        out = inner(t, Y, Z, P).copy()
        for e, rest in rests.items():
            out[:, e] += sides[e] * rest.band
        return out

    return dataclasses.replace(begin, when=watched), rests, sides


def gone(rests: dict, sides: dict, F: np.ndarray) -> int | None:
    """The first of a piece's outputs (not its first) where a resting function, in the watched ``F`` (K, E)
    (:func:`watch`), is past its band on the piece's own side: its rest ends there, and a piece from there watches
    it cross zero again (watched past the band on the other side, a crossing after it was located a band late:
    5e-7 in t at rtol 1e-8, where the function falls at 2 a second); None where there is none."""
    ends = [np.flatnonzero(sides[e] * F[1:, e] > 2.0 * rest.band) for e, rest in rests.items()]
    found = [int(k[0]) + 1 for k in ends if len(k)]
    return min(found) if found else None


def account(rests: dict, sides: dict, compiled, backend, piece, options, P, T, Y, Z, F) -> list[str]:
    """:meth:`Rest.account` for each rest over a piece's outputs ``T`` (K,), ``Y``, ``Z`` and its watched functions
    ``F`` (K, E) (:func:`watch`): the statuses of those past :data:`REST_BUDGET`."""
    notes = []
    for e, rest in rests.items():
        raw = F[:, e] - sides[e] * rest.band
        note = rest.account(compiled, backend, piece, options, P, sides[e], T, Y, Z, raw)
        if note is not None:
            notes.append(note)
    return notes

"""Where a piece starts: the branch the flow takes from an event function at zero (just fired, or
where the solve starts), read off one explicit step (:func:`drift`), never the switch's value at zero;
the levels of ``floor`` and ``ceiling`` for the piece; Filippov's sliding motion along a switch where
neither side goes on and the motion on it is integrable, refused where it is not
(:class:`~daemodel.errors.SlidingModeError`); a reset that leaves its function on the guard, and an
event whose times converge inside the span (:class:`~daemodel.errors.ZenoError`); whether a switch's
excursion inside a step may be integrated through (:func:`excursion_weight`).  Used by
:mod:`daemodel.solving.events` after each event."""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass

import numpy as np
import sympy as sp

from daemodel.compiling.switches import lock_branches, lock_functions
from daemodel.errors import SlidingModeError, SwitchError, TimeResolutionError, ZenoError
from daemodel.solving.rounding import ROUNDING, floor_at, within_rounding
from daemodel.solving.switches import for_method

# Width in t to which an event is located (relative to the solve's time scale: event_tol).
EVENT_TOL = 1e-12
# Float64 spacings of t that an event's bracket keeps at least (narrower holds no trial time inside it).
RESOLVE_ULPS = 2
# Zeno: ZENO_GAPS consecutive shrinking gaps between one event's times, the last below ZENO_GAP of
# t_span's length, whose geometric series ends inside t_span: ZenoError at the estimated accumulation point.
ZENO_GAPS, ZENO_GAP = 5, 1e-6
# Switch excursions integrated through on the branch a piece started on, all in one solve, change its states
# by at most this many tolerances together (excursion_weight): 477 humps each within the tolerance over its
# step once left a state 104 rtol off, "success" (tests/solving/test_events_edges.py).
EXCURSION_BUDGET = 1.0
# A switch's side at zero that one look-ahead (delta) does not resolve on a branch (its function moves by less
# than rounding there) is looked at again over look-aheads LOOKAHEAD_GROWTH, LOOKAHEAD_GROWTH^2, ... times
# longer, at most LOOKAHEAD_GROWTHS times: x = 0.3 - (t - 1)^2 touching its switch at t = 1 moves by delta^2
# = 4e-18 over delta = 2e-9, resolved from 8^5 delta on.  Never past t_span's end (``horizon``): the flow after
# it is not solved, and a touch at t1 located a rounding before it saw x turn down there, chose below, and raised
# ZenoError as x stayed on zero within rounding up to t1.  The longer look-aheads take a fourth-order step
# (:func:`drift`'s ``fourth``): x = 0.3 - t^3 through a chain of states (x' = w, w' = v, v' = -6, all 0 at t0) does
# not move over any midpoint step, and kept the default side, above (ZenoError); it moves by -h^3.
LOOKAHEAD_GROWTH, LOOKAHEAD_GROWTHS = 8.0, 6
# A look-ahead within this many resolutions (RESOLVE_ULPS float64 spacings) of t is set by t's resolution, not by
# the span: a function that does not come back within it may be a motion float64 does not resolve there.
RESOLUTION_LOOKAHEAD = 16
# Where t is large the location tolerance is float64's resolution of t, and 100 of them (0.39 at t = 1e13: the
# events' look-ahead) can be longer than the motion after an event (the ball's fourth flight, 0.37: a false
# ZenoError).  A function reset onto its guard is read back over look-aheads down to SHORTEST_TOLS location
# tolerances (_back_sooner), and the side a piece leaves zero to is looked for from there (events._clear_of_zero
# doubles it): a few, so that the located event's own error does not decide the side.
SHORTEST_TOLS = 4
# A reset changes the motion across its guard where the drift after it differs from the drift before by
# more than this (relative): then it must send the function back (else: ZenoError, the state stays on it).
RESET_CHANGE = 1e-6


def resolution(t: float) -> float:
    """The narrowest bracket around ``t`` that an event's location can hold trial times in:
    :data:`RESOLVE_ULPS` float64 spacings at ``t``."""
    return RESOLVE_ULPS * math.ulp(abs(t))


def time_text(t: float) -> str:
    """``t`` in a message: 12 significant digits, and more where |t| is large (up to float64's 17), so that a time
    at t0 = 1e13 reads 10000000000004.062, not 1e+13."""
    digits = 12 + max(0, math.floor(math.log10(abs(t)))) if math.isfinite(t) and t != 0 else 12
    return f"{t:.{min(digits, 17)}g}"


def event_tol(t: float, span: float) -> float:
    """Width in t to which an event near ``t`` is located, in a solve over ``span``: :data:`EVENT_TOL` of the
    time scale, ``max(1, min(|t|, span))`` (a span from t0 = 0 as ever), not of |t| alone: the same
    model started at t0 = 1e6 was located to 1e-6, its states 1356 rtol off at rtol 1e-9, "success"; and
    never more than ``span`` (a span shorter than 1 is its own scale: over (0, 1e-12) every event was
    "at t1", the states after it 0.1 for 0.25, "success"); never below :func:`resolution` at ``t``."""
    return max(EVENT_TOL * min(span, max(1.0, min(abs(t), span))), resolution(t))


def drift(
    compiled,
    backend,
    piece,
    t: float,
    Y,
    Z,
    P,
    functions,
    delta: float,
    flows: dict | None = None,
    fourth=False,
    exprs: tuple | None = None,
) -> np.ndarray:
    """How ``functions`` (``F(t, Y, Z, P) -> (1, k)``) change over ``delta`` along ``piece``'s flow from
    ``(t, Y, Z)``: one explicit midpoint step, the algebraic variables solved anew at its end; (k,).
    Enough to tell which way a function at zero goes (its own rate, or its curvature where the rate
    is 0: a ball at rest on the floor), at no cost of a solve.  ``flows``: the step's ends by piece, kept
    by a caller that asks again from the same ``(t, Y, Z)`` and ``delta`` (:func:`start_piece`: the
    sides of each switch at zero and the rates of all, often on one and the same locked model).  ``fourth``:
    classical Runge-Kutta's fourth-order step instead (no ``flows``), which moves a function whose first two
    rates along the flow are 0 (x' = w, w' = v, v' = 6 from 0: the midpoint's h (w + h v / 2) = 0, any h).
    ``exprs``: the functions' expressions, where given a change within rounding of the values they round at, at
    either end (:func:`~daemodel.solving.rounding.floor_at`), is exactly 0: no motion, no side."""
    change, floor = drift_and_floor(compiled, backend, piece, t, Y, Z, P, functions, delta, flows, fourth, exprs)
    return change if exprs is None else within_rounding(change, floor)


def drift_and_floor(
    compiled, backend, piece, t: float, Y, Z, P, functions, delta: float, flows=None, fourth=False, exprs=None
) -> tuple:
    """:func:`drift`'s change as it is, and the rounding below which it is no motion (the larger of both ends'
    :func:`~daemodel.solving.rounding.floor_at`; None without ``exprs``): both (k,)."""
    key = id(piece)
    if flows is not None and key in flows:
        Y1, Z1 = flows[key][1]
    else:
        Y1, Z1 = _flow_end(compiled, backend, piece, t, Y, Z, P, delta, fourth)
        if flows is not None:
            flows[key] = (piece, (Y1, Z1))  # (the piece kept with its id: no other object takes that id meanwhile)
    change = (functions(np.array([t + delta]), Y1, Z1, P) - functions(np.array([t]), Y, Z, P))[0]
    if exprs is None:
        return change, None
    return change, np.maximum(floor_at(compiled, exprs, t, Y, Z, P), floor_at(compiled, exprs, t + delta, Y1, Z1, P))


def _flow_end(compiled, backend, piece, t: float, Y, Z, P, delta: float, fourth: bool = False) -> tuple:
    """``(Y1, Z1)``: :func:`drift`'s explicit midpoint step (``fourth``: classical Runge-Kutta's) along
    ``piece``'s flow, z held at the start's inside it, and z solved at its end."""
    from daemodel.compiling.initial_states import algebraic_values
    from daemodel.errors import ModelError

    rhs = compiled.numeric.batch_function(list(piece.rhs))
    k1 = rhs(t, Y, Z, P)
    k2 = rhs(t + 0.5 * delta, Y + 0.5 * delta * k1, Z, P)
    if fourth:
        k3 = rhs(t + 0.5 * delta, Y + 0.5 * delta * k2, Z, P)
        k4 = rhs(t + delta, Y + delta * k3, Z, P)
        k2 = (k1 + 2.0 * k2 + 2.0 * k3 + k4) / 6.0
    Y1 = Y + delta * k2
    Z1 = Z
    if Z.shape[1]:
        try:
            Z1 = algebraic_values(for_method(piece, backend), t + delta, Y1, P, Z)
        except ModelError:  # (no root near Z past the start: the rate of z is not needed to tell most sides)
            Z1 = Z
    return Y1, Z1


def jumped(compiled, backend, piece, when, piece_when, t: float, Y, Z, P, delta: float, fired: list) -> list:
    """The declared events (not a switch's own) whose functions a switch firing at ``t`` (in ``fired``) takes across
    zero (their way) by a jump: on the piece's branches (``piece_when``, :func:`_on_piece`) they keep their sign
    over ``delta`` along the flow, as written (``when``, the branches after it) they have the other one there and,
    extrapolated back to ``t`` from ``delta / 2`` (a jump, not a function that goes on continuously across the switch
    and crosses zero within ``delta``, located as any crossing), already at ``t``.
    Locked to the piece, such a function never crossed inside one: floor(x) - 2.5 with x' = 1 + floor(x) from 0 did
    not fire at x = 3 (y' = 1 reset there ended 1.83 off, "success", in every method)."""
    events = compiled.events
    if piece_when is when or all(event.strict for event in events) or not any(events[e].strict for e in fired):
        return []
    Y1, Z1 = _flow_end(compiled, backend, piece, t, Y, Z, P, delta)
    Yh, Zh = _flow_end(compiled, backend, piece, t, Y, Z, P, 0.5 * delta)
    now = piece_when(np.array([t]), Y, Z, P)[0]
    kept = piece_when(np.array([t + delta]), Y1, Z1, P)[0]
    written = when(np.array([t + delta]), Y1, Z1, P)[0]
    halfway = when(np.array([t + 0.5 * delta]), Yh, Zh, P)[0]
    out = []
    for e, event in enumerate(events):
        before, after = np.sign(now[e]), np.sign(written[e])
        if event.strict or e in fired or before == 0 or np.sign(kept[e]) != before or after != -before:
            continue
        if np.sign(2.0 * halfway[e] - written[e]) != after:  # (continuous, back at t: a crossing within delta)
            continue
        if event.direction in (0, after):
            out.append(e)
    return out


def _on_piece(compiled, when, t: float, Y, Z, P, chosen: dict):
    """The event functions on the piece whose switches ``chosen`` and ``(t, Y, Z)`` lock
    (:func:`~daemodel.compiling.switches.lock_functions`: a switch inside one fixed to the piece's branch, so
    that the function is smooth on it, as the piece's equations are); ``when`` (all of them as written) where
    none holds a switch on variables."""
    whens = tuple(event.when for event in compiled.events)
    fixed = lock_functions(compiled, whens, t, Y[0], Z[0], P[0], chosen)
    if fixed == whens:
        return when
    return compiled.cached(("event-functions", fixed), lambda: compiled.numeric.batch_function(list(fixed)))


def _side(change: float) -> int:
    """The sign of a drift that :func:`drift` has read with its ``exprs`` (0 within rounding)."""
    return int(np.sign(change))


def _leveled(when, levels: dict, replaced: dict | None = None):
    """``when`` with the integer events ``levels`` (event -> k) measured as ``(phi - k)(k + 1 - phi)``:
    positive while ``floor(phi)`` stays ``k``, 0 where it steps, one sign change however far it goes;
    and the columns of ``replaced`` (event -> function) by those functions (a sliding motion's exit)."""
    if not levels and not replaced:
        return when

    def leveled(t, Y, Z, P):
        out = when(t, Y, Z, P).copy()
        for e, k in levels.items():
            out[:, e] = (out[:, e] - k) * (k + 1 - out[:, e])
        for e, function in (replaced or {}).items():
            out[:, e] = function(t, Y, Z, P)[:, 0]
        return out

    return leveled


@dataclass
class Start:
    """How a piece starts: its model with the switches on variables locked, the event functions as
    its detection sees them, and each one's side (0: taken from its values) and whether it is armed."""

    model: object
    when: object
    sides: np.ndarray
    armed: np.ndarray
    setup_time: float
    # event -> (rate above, rate below) of the switches the piece slides along
    sliding: dict = dataclasses.field(default_factory=dict)
    # the events whose functions are at zero where the piece starts
    at_zero: frozenset = frozenset()
    # of those, the declared events reset there (their side read back over the shortest look-ahead: _back_sooner)
    reset: frozenset = frozenset()


def start_piece(
    backend,
    compiled,
    when,
    t,
    Y,
    Z,
    P,
    fired,
    crossing,
    preferred,
    delta,
    lock,
    exited=(),
    moved_off=(),
    horizon=math.inf,
    span=math.inf,
    shortest=None,
) -> Start:
    """The piece from ``t``: which side each event function at zero there goes to, by the flow
    (:func:`drift`), never by a switch's value at zero.  ``fired``: the events that fired at ``t``
    (``moved_off``: those whose reset moved their function off zero, which take the side of its value);
    ``crossing``: event -> its function's drift just before its reset; ``preferred``: switch event ->
    the side it crossed to (kept where both sides lead away), and a declared event that crossed zero at ``t`` -> the
    side it crossed to (:func:`_crossed_to`); ``horizon``: how far t_span goes on from ``t``
    (the longest look-ahead); ``span``: t_span's length (the scale of :func:`event_tol`); ``shortest``: the
    shortest look-ahead a reset's function may be read back over (:func:`_back_sooner`; ``delta`` where None).

    Raises
    ------
    SlidingModeError
        A switch at zero whose flow goes back across it on both sides.
    ZenoError
        A reset that leaves its event's function on the guard or going on across it.
    """

    started = time.perf_counter()
    shortest = delta if shortest is None else shortest
    events = compiled.events
    F0 = when(np.array([t]), Y, Z, P)[0]
    at_zero = set(fired) - set(moved_off)
    for e, event in enumerate(events):
        if F0[e] == (round(F0[e]) if event.integer else 0):
            at_zero.add(e)
    whens = tuple(event.when for event in events)  # (their drifts read within rounding of their own values)
    chosen = {}
    flows = {}  # (drift's step ends by piece: every drift below starts from (t, Y, Z) with the same delta)
    for _ in range(len(events) + 1):  # (more rounds for switches that cross within location tolerances of t)
        switches = [e for e in sorted(at_zero) if events[e].strict and events[e].when not in chosen]
        chosen |= {events[e].when: preferred.get(e, 1) for e in switches}
        for e in switches:
            chosen[events[e].when] = _branch(backend, compiled, events[e], t, Y, Z, P, chosen, preferred.get(e, 1),
                                             delta, e in exited, flows, horizon)  # fmt: skip
        if not lock:
            break
        model = lock_branches(compiled, t, Y[0], Z[0], P[0], chosen)
        rates = drift(compiled, backend, model, t, Y, Z, P, _on_piece(compiled, when, t, Y, Z, P, chosen), delta, flows)
        rates = rates / delta
        soon = event_tol(t, span) * 10  # (a crossing this close to t is at t: no piece that short)
        near = {
            e
            for e, event in enumerate(events)
            if event.strict
            and not event.integer
            and e not in at_zero
            and np.sign(F0[e]) == -np.sign(rates[e])
            and abs(F0[e]) <= abs(rates[e]) * soon
        }
        if not near:
            break
        at_zero |= near
    slides = [e for e, event in enumerate(events) if event.strict and chosen.get(event.when) == 0]
    if len(slides) > 1:
        raise SlidingModeError(
            f"switches {', '.join(repr(events[e].name) for e in slides)} at t = {t:.12g}: the solution slides along "
            "two switches at once, which daemodel does not integrate; smooth one of them, or end t_span before it",
            t,
        )
    sliding, replaced = {}, {}
    if slides:
        (e,) = slides
        phi = events[e].when
        others = {f: side for f, side in chosen.items() if f != phi}
        model, leaving, rates = _sliding(compiled, t, Y, Z, P, others, phi)
        sliding[e] = compiled.numeric.batch_function(list(rates))
        replaced[e] = compiled.numeric.batch_function([leaving])
        chosen.pop(phi)
    else:
        model = lock_branches(compiled, t, Y[0], Z[0], P[0], chosen) if lock else compiled
    sides, armed, levels = np.zeros(len(events)), np.ones(len(events), dtype=bool), {}
    for e, event in enumerate(events):
        if event.integer:
            side = chosen.get(event.when)
            levels[e] = (round(F0[e]) - (side < 0)) if side else math.floor(F0[e])
            sides[e] = 1.0  # (inside [k, k + 1] by construction)
        elif e in sliding:
            sides[e] = 1.0  # (the function that leaves the sliding motion: positive on it)
        elif event.strict and e in at_zero:
            sides[e] = chosen[event.when]
    declared = [e for e in sorted(at_zero) if not events[e].strict]
    reset = frozenset(e for e in declared if crossing.get(e) is not None)
    if declared:
        changes = drift(compiled, backend, model, t, Y, Z, P, when, delta, flows, exprs=whens)
        for e in declared:
            side = _side(changes[e])
            before = crossing.get(e)
            if before is not None:  # (a reset: it must send the function back, or leave its motion as it was)
                across = _side(before)
                if across and side != -across and abs(changes[e] - before) > RESET_CHANGE * abs(before):
                    side = _back_sooner(compiled, backend, model, events[e], e, t, Y, Z, P, when, delta, shortest,
                                        across)  # fmt: skip
            if not side and e in fired:  # (it crossed here, too slowly for one look-ahead: read over longer ones)
                side = _crossed_to(compiled, backend, model, t, Y, Z, P, when, e, delta, horizon,
                                   preferred.get(e, 0))  # fmt: skip
            sides[e] = side
            armed[e] = bool(side)  # (a function that stays on zero is armed once it has left it)
    return Start(
        model,
        _leveled(_on_piece(compiled, when, t, Y, Z, P, chosen) if lock else when, levels, replaced),
        sides,
        armed,
        time.perf_counter() - started,
        sliding,
        frozenset(at_zero),
        reset,
    )


def _crossed_to(
    compiled, backend, model, t, Y, Z, P, when, e: int, delta: float, horizon: float, crossed: int = 0
) -> int:
    """The side the function of the declared event ``e``, which crossed zero at ``t`` and moves by less than
    rounding over ``delta`` from there, goes on to: read over look-aheads :data:`LOOKAHEAD_GROWTH` times longer,
    at most :data:`LOOKAHEAD_GROWTHS` of them, never past ``horizon``; 0 where none resolves it (it rests on zero).
    Unread, it was 0 (not armed: "armed once it has left it"), and its way back across zero was taken for that
    leaving: x = (t - 1)^2 - 1e-12 crossed at 1 -+ 1e-6 (moving 4e-15 over delta = 2e-9), and one crossing was
    recorded, "success", under the reference and a fixed radau grid.  ``crossed``: the side it crossed to (0:
    not known, or a reset that sends it back: :func:`reset_keeps_motion`); a look-ahead that reads it back on the
    side it came from has passed its crossing back, which the next piece locates: the side is ``crossed`` (read as
    it was, x = (t - 1)^2 a touch at t = 1 that the reference and casadi-collocation's solutions cross by 1e-15
    at 1 -+ 5e-8, within 64 look-aheads: one crossing recorded, of a function above zero at both ends of the span,
    "success")."""
    for growth in range(1, LOOKAHEAD_GROWTHS + 1):
        if delta * LOOKAHEAD_GROWTH ** (growth - 1) >= horizon:
            break
        longer = min(delta * LOOKAHEAD_GROWTH**growth, horizon)
        whens = tuple(event.when for event in compiled.events)
        side = _side(drift(compiled, backend, model, t, Y, Z, P, when, longer, fourth=True, exprs=whens)[e])
        if side:
            return crossed if side == -crossed else side
    return 0


def reset_keeps_motion(compiled, event) -> bool:
    """Whether the reset of the declared ``event`` (if any) sets no state its function or that function's rate
    depends on: a counter's, not a bounce's, whose reset sends its function back across zero by design (so the
    side it crossed to is not the side it goes on to)."""
    if not event.reset:
        return True
    reads = set(event.when.free_symbols)
    for i, state in enumerate(compiled.states):
        if state in reads:
            reads |= set(compiled.rhs[i].free_symbols)
    return not any(compiled.states[i] in reads for i, _ in event.reset)


def _back_sooner(compiled, backend, model, event, e: int, t, Y, Z, P, when, delta: float, shortest: float,
                 across: int) -> int:  # fmt: skip
    """The side (``-across``) that the function of ``event`` (number ``e``), reset at ``t``, goes back to over a
    look-ahead shorter than ``delta``: ``delta / LOOKAHEAD_GROWTH^k``, and ``shortest`` last (at most
    :data:`LOOKAHEAD_GROWTHS` of them).  The look-ahead is long where t is (a hundred location tolerances, each two
    float64 spacings of t: 0.39 at t = 1e13), and a flight shorter than it (the ball's fourth, 0.37) came back
    down within it: ZenoError, where the ball bounces on.

    Raises
    ------
    ZenoError
        It does not go back over any of them: it stays on the guard (a ball coming to rest).
    TimeResolutionError
        It does not, and ``shortest`` is set by float64's spacing of t (:data:`SHORTEST_TOLS` resolutions of t,
        not the span's share): a motion back sooner than that is not resolved there, so a bounce and a state at
        rest look alike (at t0 = 1e6 over 2.5 the span's 2.5e-9 sets it, and a ball at rest is ZenoError)."""
    shorter, whens = delta, tuple(f.when for f in compiled.events)
    for _ in range(LOOKAHEAD_GROWTHS):
        if shorter <= shortest:
            break
        shorter = max(shorter / LOOKAHEAD_GROWTH, shortest)
        change = drift(compiled, backend, model, t, Y, Z, P, when, shorter, exprs=whens)
        if _side(change[e]) == -across:
            return -across
    if shortest <= (1.0 + 1e-9) * SHORTEST_TOLS * resolution(t):
        raise TimeResolutionError(
            f"event '{event.name}' at t = {time_text(t)}: after its reset {event.when} does not move back to the side "
            f"it came from within {shortest:.3g}, the shortest look-ahead that float64 resolves at |t| = {abs(t):.3g} "
            f"(its spacing of t there is {math.ulp(abs(t)):.3g}, and the event is located to {resolution(t):.3g}): a "
            "motion shorter than that (a bounce) and a state at rest on the guard (Zeno) look alike there; count "
            "time from near the start (t - t0 in the model, t_span from 0)",
            t,
        )
    raise ZenoError(
        f"event '{event.name}' at t = {time_text(t)}: after its reset {event.when} stays on the guard (it does not "
        "move back to the side it came from), so the event would fire again at once, without end (Zeno: a ball "
        "coming to rest); make the event terminal=True to stop there, change the reset, or end t_span at it",
        t,
    )


def _branch(
    backend,
    compiled,
    event,
    t,
    Y,
    Z,
    P,
    chosen: dict,
    preferred: int,
    delta: float,
    exited: bool,
    flows: dict | None = None,
    horizon: float = math.inf,
) -> int:
    """The side (+1, -1) of the switch ``event``, at zero at ``t``, that the flow goes on to: the one whose
    branch moves its function away from zero on its own side; ``preferred`` where both do, or where it
    just left a sliding motion (``exited``); 0 where neither does and the solution slides along it
    (:func:`_slides`).  ``flows``: :func:`drift`'s; ``horizon``: the longest look-ahead (to t_span's end).

    Raises
    ------
    SlidingModeError
        Neither does, and the sliding motion is not one daemodel integrates.
    """

    phi = event.when
    function = compiled.numeric.batch_function([phi])
    candidates = {side: lock_branches(compiled, t, Y[0], Z[0], P[0], {**chosen, phi: side}) for side in (1, -1)}
    read = {side: drift_and_floor(compiled, backend, c, t, Y, Z, P, function, delta, flows, exprs=(phi,))
            for side, c in candidates.items()}  # fmt: skip
    moved = {side: m[0] for side, (m, _) in read.items()}  # (as they are: a motion within rounding is resting's)
    change = {side: _side(within_rounding(m, f)[0]) for side, (m, f) in read.items()}
    # (a branch on which the function does not move within rounding over the look-ahead: a touch, its rate 0
    # and its curvature below the look-ahead's resolution, or a crossing of higher order; looked at again
    # over longer look-aheads, while it stays unresolved, so that a touch from one side keeps that side)
    for growth in range(1, LOOKAHEAD_GROWTHS + 1):
        if exited or all(change.values()) or delta * LOOKAHEAD_GROWTH ** (growth - 1) >= horizon:
            break
        longer = min(delta * LOOKAHEAD_GROWTH**growth, horizon)
        for side in [side for side in change if not change[side]]:
            m, f = drift_and_floor(compiled, backend, candidates[side], t, Y, Z, P, function, longer, fourth=True,
                                   exprs=(phi,))  # fmt: skip
            moved[side], change[side] = m[0], _side(within_rounding(m, f)[0])
    up, down = change[1] >= 0, change[-1] <= 0
    if not exited and all(m == 0 for m in moved.values()) and delta * LOOKAHEAD_GROWTH**LOOKAHEAD_GROWTHS < horizon:
        _rests_on_both(compiled, backend, event, candidates, t, Y, Z, P, delta * LOOKAHEAD_GROWTH**LOOKAHEAD_GROWTHS)
    if not (up or down) and exited:  # (it just left a sliding motion there, tangentially: the side it left to)
        return preferred
    if not (up or down) and _slides(compiled, event):
        return 0  # (Filippov's sliding motion: see _sliding)
    value = float(function(np.array([t]), Y, Z, P)[0, 0]) if not (up or down) else 0.0
    if abs(value) > floor_at(compiled, (phi,), t, Y, Z, P)[0] and all(abs(m) < abs(value) for m in moved.values()):
        # not at zero: a function of the algebraic variables that the event's own solution put at zero, moved off
        # it by their values solved anew there (by the method's error in them: 2e-4 for the wheelset's creep
        # saturation at rtol 1e-4), further than the flow moves it over the look-ahead on either branch, so that
        # their drifts read a point off the switch; the side of its value, whose flow reaches the switch later
        return int(np.sign(value))
    if not (up or down):
        raise SlidingModeError(
            f"switch '{event.name}' at t = {t:.12g}: neither branch goes on: above zero {phi} turns back down, "
            f"below zero it turns back up, so the solution slides along {phi} = 0 (a sliding mode), which "
            "daemodel integrates only where the switching function is of t and the states and the switch and "
            "the constraints are apart (index 1 at most); smooth the switch (e.g. tanh(s/eps) for sign(s)), or "
            "end t_span before it",
            t,
        )
    return preferred if up and down else (1 if up else -1)


def _rests_on_both(compiled, backend, event, candidates: dict, t, Y, Z, P, ahead: float) -> None:
    """Nothing where the branches ``candidates`` (side: model) of the switch ``event``, whose function does not move
    at all from zero at ``t`` over the look-ahead ``ahead`` on either (one that moves within rounding: the method's
    error, :mod:`.resting`'s), move the states alike over it; else a :class:`ZenoError`: the function rests on zero
    on either branch, and which one holds (a jump) is not decided by the flow.  x = 0 throughout (x' = 0) under
    y' = Piecewise((1, x > 0), (2, True)) took the branch x > 0 by default, y(1) = 1 where the model says 2, and
    sign(x) gave y(1) = 1 for 0, "success" in every method."""
    states = compiled.numeric.batch_function(list(compiled.states))
    moved = [drift(compiled, backend, c, t, Y, Z, P, states, ahead, fourth=True) for c in candidates.values()]
    # (each state's motions alike within the rounding of its own values at either end: not of an absolute 1, under
    # which y' = Piecewise((1e-20, x > 0), (2e-20, True)) moved y alike on both)
    size = np.max(np.abs([Y[0], Y[0] + moved[0], Y[0] + moved[1]]), axis=0)
    if np.all(np.abs(moved[0] - moved[1]) <= ROUNDING * size):
        return
    raise ZenoError(
        f"switch '{event.name}' at t = {time_text(t)}: {event.when} rests on zero on both of its branches (neither "
        f"moves it off zero over {ahead:.3g}), where the branches move the states differently: which one holds is "
        "not decided by the flow (daemodel never takes a switch's value at zero); smooth the switch, or state the "
        "rate that holds on zero without it",
        t,
    )


def _slides(compiled, event) -> bool:
    """Whether daemodel integrates the Filippov sliding motion along ``event``'s switch: its switching
    function is of t, the states and parameters, it occurs in no constraint, and no constraint is
    differentiated along the flow (index 1 at most: the sliding flow would change the hidden ones)."""
    phi = event.when
    if event.integer or phi.free_symbols & set(compiled.algebraics):
        return False
    return all(len(c.chain) == 1 and not any(e.has(phi) or e.has(-phi) for e in c.chain) for c in compiled.constraints)


def _sliding(compiled, t, Y, Z, P, chosen: dict, phi):
    """The model of the Filippov sliding motion along ``phi = 0``: ``y' = f- + a (f+ - f-)`` with ``a``
    such that ``phi`` stays put (``a = r- / (r- - r+)``, ``r`` the rates of ``phi`` on each branch), and
    the function that leaves it: ``r- (-r+)``, positive while both branches push onto the switch."""

    plus = lock_branches(compiled, t, Y[0], Z[0], P[0], {**chosen, phi: 1})
    minus = lock_branches(compiled, t, Y[0], Z[0], P[0], {**chosen, phi: -1})
    # (differentiated with the switches inside it on their branch: sign(Abs(x) - 1)'s d|x|/dx is sympy's
    # Derivative(im(x), x) for a symbol not known real, which no printer prints: an unnamed error)
    (smooth,) = lock_functions(compiled, (phi,), t, Y[0], Z[0], P[0], chosen)
    key = ("sliding", smooth, plus.rhs, minus.rhs)
    if key not in compiled._cache:

        def rate(rhs):
            return sp.diff(smooth, compiled.t) + sum(
                sp.diff(smooth, y) * f for y, f in zip(compiled.states, rhs, strict=True)
            )

        up, down = rate(plus.rhs), rate(minus.rhs)
        a = down / (down - up)
        rhs = tuple(fm + a * (fp - fm) for fp, fm in zip(plus.rhs, minus.rhs, strict=True))
        model = dataclasses.replace(minus, rhs=rhs, _cache={})
        compiled._cache[key] = (model, down * (-up), (up, down))
    model, leaves, rates = compiled._cache[key]
    return compiled.rebased(model), leaves, rates


def accumulation_point(times: list) -> float | None:
    """Where ``times`` converge, if their last 3 gaps shrink: the sum of the geometric series they start."""
    if len(times) < 4:
        return None
    gaps = np.diff(np.asarray(times[-4:]))
    if not (np.all(gaps > 0) and np.all(gaps[1:] < gaps[:-1])):
        return None
    ratio = gaps[-1] / gaps[-2]
    return float(times[-1] + gaps[-1] * ratio / (1.0 - ratio))


def check_accumulating(event, times: list, t0: float, t1: float) -> None:
    """Raise :class:`ZenoError` where ``event``'s times converge geometrically to a point inside the span."""
    if len(times) <= ZENO_GAPS:
        return
    gaps = np.diff(np.asarray(times[-ZENO_GAPS - 1 :]))
    if not (np.all(gaps > 0) and np.all(gaps[1:] < gaps[:-1]) and gaps[-1] <= ZENO_GAP * (t1 - t0)):
        return
    ratio = gaps[-1] / gaps[-2]
    limit = times[-1] + gaps[-1] * ratio / (1.0 - ratio)
    if limit < t1:
        raise ZenoError(
            f"event '{event.name}' accumulates at t ≈ {time_text(limit)}: its last {ZENO_GAPS} gaps shrink by "
            f"{ratio:.3g} each, down to {gaps[-1]:.3g} at t = {time_text(times[-1])} (Zeno: infinitely many events "
            f"before it); the solution past it is not defined by the events: end t_span before t ≈ {time_text(limit)}, "
            "or make the event terminal=True (or set max_events) to stop earlier",
            limit,
        )


def excursion_weight(compiled, piece, options, P, t: float, y: np.ndarray, z: np.ndarray, span: float) -> float:
    """How much of the solve's tolerance integrating a switch's excursion to its other branch at ``(t, y (1, n),
    z (1, m))`` (its deepest point), inside one step of length ``span``, on ``piece``'s branch would use: the
    difference of the two branches' rates there times the whole step, in the weighted norm the adaptive
    methods hold each step's local error to (``atol + rtol |y|``, root mean square).  The difference bounds
    the excursion's effect where it is largest at its deepest point (a kink, ``Min(1, x)``: it grows with the
    distance from the switch) or the same throughout (a jump).  Excursions integrated through all push the
    states the same way, so their weights add up: the caller integrates one through only while their sum
    stays within 1 (:data:`EXCURSION_BUDGET`).  Infinite without ``rtol`` and ``atol`` (fixed steps) and
    where the branches' constraints differ (the algebraic variables would change with them)."""
    rtol, atol = getattr(options, "rtol", None), getattr(options, "atol", None)
    if rtol is None or atol is None:
        return math.inf
    other = lock_branches(compiled, t, y[0], z[0], P[0])
    if other.constraints != piece.constraints:
        return math.inf
    numeric, at = compiled.numeric, np.array([float(t)])
    change = numeric.batch_function(list(other.rhs))(at, y, z, P) - numeric.batch_function(list(piece.rhs))(at, y, z, P)
    weighted = np.abs(change[0]) * span / (np.asarray(atol, dtype=float) + np.asarray(rtol, dtype=float) * np.abs(y[0]))
    return float(np.sqrt(np.mean(weighted**2)))


def finite_functions(compiled, F: np.ndarray, T: np.ndarray, Y: np.ndarray, upto: int) -> None:
    """Raise :class:`SwitchError` where an event function ``F`` (T, E) is not finite at the first ``upto``
    outputs (those the search for the first crossing read)."""
    bad = np.argwhere(~np.isfinite(F[:upto]))
    if len(bad):
        k, e = bad[0]
        at = ", ".join(f"{n} = {v:.6g}" for n, v in zip(compiled.state_names, Y[k], strict=True))
        raise SwitchError(
            f"event '{compiled.events[e].name}': its function {compiled.events[e].when} is {float(F[k, e])} at "
            f"t = {T[k]:.12g} ({at}), where the solution goes; an event function must be finite along the "
            "solution: write it without a sqrt, log or division that the solution takes out of its domain"
        )

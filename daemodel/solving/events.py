"""Declared events: impacts, resets and stops, located during the solve, in every method.

``m.event(name, when, direction=0, reset=None, terminal=False)`` declares an event at each zero
crossing of ``when`` (an expression of t, the variables and parameters): ``direction`` +1 for a
rising, -1 for a falling crossing, 0 for both.  At the event ``reset`` (state name -> expression
of the values just before) sets states; the states are then projected onto the constraints where
the reset left them (least change, reported), the algebraic variables are solved anew with the
routine that initialises them at t0, and the integration starts again.  ``terminal=True`` ends
the solve there.

How (:func:`solve_with_events`, for every method alike): integrate to t1 on the method's own
outputs, evaluate every event function there, and take the first crossing; locate it between the
two outputs that bracket it by the Illinois variant of regula falsi, each trial time a short solve
from the output before it (so the located state has the method's own accuracy, not an
interpolant's), to :data:`EVENT_TOL` in t; keep the outputs before it, apply the reset, go on
from there.  A crossing between two outputs whose function changes sign twice is not seen, except
from where a piece starts: an event function at zero there (just fired, or where the solve starts)
takes the side the flow goes to (:func:`_start_piece`: one explicit step, :func:`_drift`), so a
flight shorter than an output step is a crossing too.  At most ``max_events`` events a solve
(default :data:`DEFAULT_MAX_EVENTS`); events whose times converge stop earlier, at their estimated
accumulation point, and so does a reset that leaves its function on the guard
(:class:`~daemodel.errors.ZenoError`).

Switches on states and algebraic variables (:mod:`daemodel.solving.switches`) are events too
(:func:`with_state_events`: no reset, named after the switch), with the switch locked to the
branch the flow takes where each piece starts (:func:`daemodel.compiling.switches.lock_branches`,
never the switch's value at zero), so that every piece is smooth; a switch where neither branch
goes on (a sliding mode) is refused (:class:`~daemodel.errors.SlidingModeError`).
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from dataclasses import dataclass

import numpy as np
import sympy as sp

from daemodel.compiling.switches import has_state_switches, has_time_switches, lock_branches
from daemodel.errors import EventLimitError, EventLocationError, SlidingModeError, SwitchError, ZenoError
from daemodel.solving.pieces import join_samples, merge_stats, onto_constraints, segment_steps
from daemodel.solving.switches import for_method, settings_as_given, solve_with_breakpoints

# Events one solve may handle, unless dm.solve(max_events=...) says otherwise.
DEFAULT_MAX_EVENTS = 1000
# Width in t to which an event is located (relative to max(1, |t|)).
EVENT_TOL = 1e-12
# Chattering: more than CHATTER_EVENTS events within CHATTER_SPAN of t_span's length end the solve
# (EventLimitError) before max_events does; a sliding mode makes thousands, each a few trial solves.
CHATTER_EVENTS, CHATTER_SPAN = 20, 1e-9
# Trial solves of the location of one event before EventLocationError.
MAX_LOCATION_ITERATIONS = 100
# Which way an event function at zero goes (after an event, or where it starts) is read off one explicit
# step this long: LOOKAHEAD_SPAN of t_span's length, and at least LOOKAHEAD_TOLS location tolerances (so
# that a located event's own error in t cannot decide the side).
LOOKAHEAD_SPAN, LOOKAHEAD_TOLS = 1e-9, 100
# A drift within ROUNDING of the values' size (at least 1) is no motion.
ROUNDING = 64 * np.finfo(float).eps
# A reset changes the motion across its guard where the drift after it differs from the drift before by
# more than this (relative): then it must send the function back (else: ZenoError, the state stays on it).
RESET_CHANGE = 1e-6
# A trial solve this short (relative to max(1, |t|)) is one step, whatever the method's own grid.
TINY_SPAN = 1e-9
# Zeno: ZENO_GAPS consecutive shrinking gaps between one event's times, the last below ZENO_GAP of
# t_span's length, whose geometric series ends inside t_span: ZenoError at the estimated accumulation point.
ZENO_GAPS, ZENO_GAP = 5, 1e-6


def _functions(compiled):
    """Numeric event functions of ``compiled``: ``F(t, Y, Z, P) -> (B, E)`` and the resets, cached."""

    def build():
        numeric = compiled.numeric
        when = numeric.batch_function([e.when for e in compiled.events])
        resets = [numeric.batch_function([expr for _, expr in e.reset]) if e.reset else None for e in compiled.events]
        return when, resets

    return compiled.cached(("events", compiled.events), build)


def _span_solve(backend, compiled, a: float, b: float, Y, Z, P, batched: bool, options, **changes):
    """One solve of ``compiled`` over [a, b] from the states ``Y``, ``Z`` (its time switches cut, as
    :func:`daemodel.solving.switches.solve_with_breakpoints` does)."""
    from daemodel.compiling.initial_states import InitialStates

    model = dataclasses.replace(compiled, t0=float(a), y0=Y[0].copy(), z0=Z[0].copy())
    start = InitialStates(y0=Y, z0=Z, p=P, batched=batched)
    fields = {f.name for f in dataclasses.fields(options)}
    if "h" not in changes and getattr(options, "h", None) is not None:  # (a piece shorter than h: equal steps)
        changes["h"] = segment_steps(a, b, options.h)
    options = dataclasses.replace(options, **{k: v for k, v in changes.items() if k in fields})  # (pinn: no t_eval)
    if has_time_switches(model):
        return solve_with_breakpoints(backend, model, (float(a), float(b)), start, options)
    return backend.solve(for_method(model, backend), (float(a), float(b)), start, options)


def _outputs(sol, compiled):
    """``(t, Y (T, n), Z (T, m))`` of a one-sample solution."""
    T = len(sol.t)
    Y = np.stack([np.asarray(sol.values[n])[0] for n in compiled.state_names], axis=-1).reshape(T, -1)
    Z = [np.asarray(sol.values[n])[0] for n in compiled.algebraic_names]
    Z = np.stack(Z, axis=-1).reshape(T, -1) if Z else np.zeros((T, 0))
    return np.asarray(sol.t, dtype=float), Y, Z


def _crossing(values: np.ndarray, direction: int, armed: bool, side: float = 0.0) -> np.ndarray:
    """``[j, i]``: the first output j where the function is on the other side of zero (in
    ``direction``) than at output i, the last before it off zero (values exactly 0 have no side: a
    function that stays on zero crosses nothing); empty where there is none.  ``armed`` False: not
    until it has left zero and stayed on one side; ``side`` (+1 or -1): the side the function
    starts on, whatever its first value (a switch just crossed)."""
    sign = np.sign(values)
    current, at = (side, 0) if side else (sign[0], 0)
    armed = armed or bool(side)
    for j in range(1, len(values)):
        if sign[j] == 0:
            continue
        if not armed:
            armed = sign[j] == current
            current, at = sign[j], j
            continue
        if current != 0 and sign[j] != current:
            if direction == 0 or (direction > 0) == (sign[j] > current):
                return np.array([j, at], dtype=int)
        current, at = sign[j], j
    return np.zeros(0, dtype=int)


def solve_with_events(backend, compiled, t_span, start, options, max_events: int = DEFAULT_MAX_EVENTS):
    """Solve with ``compiled.events`` located and applied (see the module docstring); one sample at a
    time (each its own event times), a batch on the common output times ``t_eval``.

    Raises
    ------
    EventLimitError
        More than ``max_events`` events.
    EventLocationError
        An event that the trial solves do not locate.
    SwitchError
        A batch without ``t_eval``: its samples' outputs would not share times.
    """

    P = np.asarray(start.p, dtype=float)
    if len(P) == 1:
        return _one_sample(backend, compiled, t_span, start, options, max_events)
    if getattr(options, "t_eval", None) is None:
        raise SwitchError(
            f"a batch of {len(P)} samples with events: each sample has its own event times and steps; pass "
            "t_eval to have them on common output times, or solve them one at a time"
        )
    from daemodel.compiling.initial_states import InitialStates

    parts = []
    for b in range(len(P)):
        sub = InitialStates(y0=start.y0[b : b + 1], z0=start.z0[b : b + 1], p=start.p[b : b + 1], batched=True)
        parts.append((np.array([b]), _one_sample(backend, compiled, t_span, sub, options, max_events)))
    return join_samples(parts, len(P), start.batched)


def _drift(compiled, backend, piece, t: float, Y, Z, P, functions, delta: float) -> np.ndarray:
    """How ``functions`` (``F(t, Y, Z, P) -> (1, k)``) change over ``delta`` along ``piece``'s flow from
    ``(t, Y, Z)``: one explicit midpoint step, the algebraic variables solved anew at its end; (k,).
    Enough to tell which way a function at zero goes (its own rate, or its curvature where the rate
    is 0: a ball at rest on the floor), at no cost of a solve."""
    from daemodel.compiling.initial_states import algebraic_values
    from daemodel.errors import ModelError

    rhs = compiled.numeric.batch_function(list(piece.rhs))
    k1 = rhs(t, Y, Z, P)
    Y1 = Y + delta * rhs(t + 0.5 * delta, Y + 0.5 * delta * k1, Z, P)
    Z1 = Z
    if Z.shape[1]:
        try:
            Z1 = algebraic_values(for_method(piece, backend), t + delta, Y1, P, Z)
        except ModelError:  # (no root near Z past the start: the rate of z is not needed to tell most sides)
            Z1 = Z
    return (functions(np.array([t + delta]), Y1, Z1, P) - functions(np.array([t]), Y, Z, P))[0]


def _side(change: float, scale: float) -> int:
    """The sign of a drift, 0 within rounding of values of size ``scale``."""
    return 0 if abs(change) <= ROUNDING * max(1.0, scale) else int(np.sign(change))


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
class _Start:
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


def _start_piece(
    backend, compiled, when, t, Y, Z, P, fired, crossing, preferred, delta, lock, exited=(), moved_off=()
) -> _Start:
    """The piece from ``t``: which side each event function at zero there goes to, by the flow
    (:func:`_drift`), never by a switch's value at zero.  ``fired``: the events that fired at ``t``
    (``moved_off``: those whose reset moved their function off zero, which take the side of its value);
    ``crossing``: event -> its function's drift just before its reset; ``preferred``: switch event ->
    the side it crossed to (kept where both sides lead away).

    Raises
    ------
    SlidingModeError
        A switch at zero whose flow goes back across it on both sides.
    ZenoError
        A reset that leaves its event's function on the guard or going on across it.
    """

    started = time.perf_counter()
    events = compiled.events
    F0 = when(np.array([t]), Y, Z, P)[0]
    at_zero = set(fired) - set(moved_off)
    for e, event in enumerate(events):
        if F0[e] == (round(F0[e]) if event.integer else 0):
            at_zero.add(e)
    scale = float(np.max(np.abs(np.concatenate([Y[0], Z[0], [t]]))))
    chosen = {}
    for _ in range(len(events) + 1):  # (more rounds for switches that cross within location tolerances of t)
        switches = [e for e in sorted(at_zero) if events[e].strict and events[e].when not in chosen]
        chosen |= {events[e].when: preferred.get(e, 1) for e in switches}
        for e in switches:
            chosen[events[e].when] = _branch(backend, compiled, events[e], t, Y, Z, P, chosen, preferred.get(e, 1),
                                             delta, scale, e in exited)  # fmt: skip
        if not lock:
            break
        model = lock_branches(compiled, t, Y[0], Z[0], P[0], chosen)
        rates = _drift(compiled, backend, model, t, Y, Z, P, when, delta) / delta
        soon = EVENT_TOL * max(1.0, abs(t)) * 10  # (a crossing this close to t is at t: no piece that short)
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
    if declared:
        changes = _drift(compiled, backend, model, t, Y, Z, P, when, delta)
        for e in declared:
            side = _side(changes[e], scale)
            before = crossing.get(e)
            if before is not None:  # (a reset: it must send the function back, or leave its motion as it was)
                across = _side(before, scale)
                if across and side != -across and abs(changes[e] - before) > RESET_CHANGE * abs(before):
                    raise ZenoError(
                        f"event '{events[e].name}' at t = {t:.12g}: after its reset {events[e].when} stays on the "
                        "guard (it does not move back to the side it came from), so the event would fire again at "
                        "once, without end (Zeno: a ball coming to rest); make the event terminal=True to stop "
                        "there, change the reset, or end t_span at it",
                        t,
                    )
            sides[e] = side
            armed[e] = bool(side)  # (a function that stays on zero is armed once it has left it)
    return _Start(
        model,
        _leveled(when, levels, replaced),
        sides,
        armed,
        time.perf_counter() - started,
        sliding,
        frozenset(at_zero),
    )


def _branch(
    backend, compiled, event, t, Y, Z, P, chosen: dict, preferred: int, delta: float, scale: float, exited: bool
) -> int:
    """The side (+1, -1) of the switch ``event``, at zero at ``t``, that the flow goes on to: the one whose
    branch moves its function away from zero on its own side; ``preferred`` where both do, or where it
    just left a sliding motion (``exited``); 0 where neither does and the solution slides along it
    (:func:`_slides`).

    Raises
    ------
    SlidingModeError
        Neither does, and the sliding motion is not one daemodel integrates.
    """

    phi = event.when
    function = compiled.numeric.batch_function([phi])
    change = {}
    for side in (1, -1):
        candidate = lock_branches(compiled, t, Y[0], Z[0], P[0], {**chosen, phi: side})
        change[side] = _side(_drift(compiled, backend, candidate, t, Y, Z, P, function, delta)[0], scale)
    up, down = change[1] >= 0, change[-1] <= 0
    if not (up or down) and exited:  # (it just left a sliding motion there, tangentially: the side it left to)
        return preferred
    if not (up or down) and _slides(compiled, event):
        return 0  # (Filippov's sliding motion: see _sliding)
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
    key = ("sliding", phi, plus.rhs, minus.rhs)
    if key not in compiled._cache:

        def rate(rhs):
            return sp.diff(phi, compiled.t) + sum(
                sp.diff(phi, y) * f for y, f in zip(compiled.states, rhs, strict=True)
            )

        up, down = rate(plus.rhs), rate(minus.rhs)
        a = down / (down - up)
        rhs = tuple(fm + a * (fp - fm) for fp, fm in zip(plus.rhs, minus.rhs, strict=True))
        model = dataclasses.replace(minus, rhs=rhs, _cache={})
        compiled._cache[key] = (model, down * (-up), (up, down))
    return compiled._cache[key]


def _limit(times: list) -> float | None:
    """Where ``times`` converge, if their last 3 gaps shrink: the sum of the geometric series they start."""
    if len(times) < 4:
        return None
    gaps = np.diff(np.asarray(times[-4:]))
    if not (np.all(gaps > 0) and np.all(gaps[1:] < gaps[:-1])):
        return None
    ratio = gaps[-1] / gaps[-2]
    return float(times[-1] + gaps[-1] * ratio / (1.0 - ratio))


def _accumulating(event, times: list, t0: float, t1: float) -> None:
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
            f"event '{event.name}' accumulates at t ≈ {limit:.12g}: its last {ZENO_GAPS} gaps shrink by "
            f"{ratio:.3g} each, down to {gaps[-1]:.3g} at t = {times[-1]:.12g} (Zeno: infinitely many events before "
            f"it); the solution past it is not defined by the events: end t_span before t ≈ {limit:.6g}, or make "
            "the event terminal=True (or set max_events) to stop earlier",
            limit,
        )


def _one_sample(backend, compiled, t_span, start, options, max_events: int):
    from daemodel.backends.grids import output_times
    from daemodel.compiling.initial_states import algebraic_values
    from daemodel.dense import Held, joined_in_time
    from daemodel.solution import Solution

    started = time.perf_counter()
    t0, t1 = (float(v) for v in t_span)
    when, resets = _functions(compiled)
    events = compiled.events
    P = np.asarray(start.p, dtype=float)
    Y, Z = np.asarray(start.y0, dtype=float), np.asarray(start.z0, dtype=float)
    user_grid = None if getattr(options, "t_eval", None) is None else output_times(options.t_eval, t_span, ())
    pieces, all_stats, record = [], [], {e.name: {"t": [], "before": [], "after": [], "moved": []} for e in events}
    t, count, setup_time, last = t0, 0, 0.0, None
    recent = []  # (the event times, to see chattering before max_events)
    history = {e: [] for e in range(len(events))}  # (each event's times, to see them accumulate)
    fired, crossing, preferred, exited, moved_off = [], {}, {}, set(), set()  # (what happened at t: _start_piece)
    lock = has_state_switches(compiled)

    def delta_at(time_: float) -> float:
        return max(LOOKAHEAD_SPAN * (t1 - t0), LOOKAHEAD_TOLS * EVENT_TOL * max(1.0, abs(time_)))

    while True:
        # (switches on variables locked to the branch the flow takes from the piece's start: smooth until an event)
        try:
            begin = _start_piece(
                backend, compiled, when, t, Y, Z, P, fired, crossing, preferred, delta_at(t), lock, exited, moved_off
            )
        except ZenoError as error:  # (a ball at rest: where its bounces accumulate, if their times tell)
            limit = max((_limit(history[e]) or -math.inf for e in fired), default=-math.inf)
            if limit > -math.inf:
                raise ZenoError(f"{error}; its events accumulate at t ≈ {limit:.12g}", limit) from None
            raise
        setup_time += begin.setup_time
        piece, piece_when = begin.model, begin.when
        if t == t0 and Z.shape[1] and any(e.strict for e, side in zip(events, begin.sides, strict=True) if side):
            Z = algebraic_values(for_method(piece, backend), t, Y, P, Z)  # (z0 on the branch taken, not at zero)
        with warnings.catch_warnings(record=True) as caught:  # (said only where the solve is the last piece's)
            warnings.simplefilter("always")
            sol = _span_solve(backend, piece, t, t1, Y, Z, P, start.batched, options, t_eval=None)
        all_stats.append(sol.stats)
        setup_time += sol.setup_time
        last = sol
        T, Ys, Zs = _outputs(sol, compiled)
        F = piece_when(T, Ys, Zs, np.repeat(P, len(T), axis=0))
        first, which, hit, before_index = None, None, {}, None
        for e, event in enumerate(events):
            hits = _crossing(F[:, e], event.direction, bool(begin.armed[e]), begin.sides[e])
            if len(hits):
                hit[e] = int(hits[0])
                if first is None or hits[0] < first:
                    first, which, before_index = int(hits[0]), e, int(hits[1])
        if first is None:
            for warning in caught:
                warnings.warn(warning.message, warning.category, stacklevel=4)
            pieces.append((t, t1, Y, Z, None, piece, sol.dense))
            break
        count += 1
        if count > max_events:
            raise EventLimitError(
                f"event '{events[which].name}' would be event number {count} by t = {T[first]:.10g} (max_events = "
                f"{max_events}): events this close together are chattering (Zeno); raise max_events, or end t_span "
                "before it"
            )
        a, b, Fa, Fb = T[before_index], T[first], F[before_index, which], F[first, which]
        ya, za = Ys[before_index : before_index + 1], Zs[before_index : before_index + 1]
        if before_index == 0 and which in begin.at_zero and begin.sides[which]:
            # (at zero where the piece starts, going to its side: the bracket starts a look-ahead later, where the
            # method's own solution is on that side, clear of its error at the start)
            a, Fa, ya, za = _clear_of_zero(
                backend, piece, options, start.batched, P, which, piece_when, a, b, ya, za, begin.sides[which],
                delta_at(a), events[which],
            )  # fmt: skip
        t_event, y_event, z_event, located = _locate(
            backend, piece, options, start.batched, P, which, piece_when, a, b, Fa, Fb, ya, za
        )
        all_stats += located
        ends = t_event >= t1 - EVENT_TOL * max(1.0, abs(t1))  # (an event at t1: applied there, and the solve ends)
        t_event = t1 if ends else t_event
        recent.append(t_event)
        if len(recent) > CHATTER_EVENTS and recent[-1] - recent[-1 - CHATTER_EVENTS] <= CHATTER_SPAN * (t1 - t0):
            first_time = recent[-1 - CHATTER_EVENTS]
            raise ZenoError(
                f"event '{events[which].name}': {CHATTER_EVENTS} events between t = {first_time:.12g} and "
                f"{recent[-1]:.12g}: chattering (Zeno); end t_span before it, or make the event terminal=True",
                recent[-1],
            )
        pieces.append((t, t_event, Y, Z, (which, t_event), piece, sol.dense))
        # every event whose function changed sign (its way) between the bracket's start and the located
        # time fires there, in declaration order (identical or simultaneous events)
        F_event = piece_when(np.array([t_event]), y_event, z_event, P)[0]
        fired = [
            e
            for e, event in enumerate(events)
            if e == which
            or (
                hit.get(e) == first
                and (
                    len(_crossing(np.array([F[before_index, e], F_event[e]]), event.direction, True)) or F_event[e] == 0
                )
            )
        ]
        for e in fired:
            history[e].append(t_event)
            _accumulating(events[e], history[e], t0, t1)
        with_reset = [e for e in fired if resets[e] is not None]
        crossing = {}
        if with_reset:  # (how the functions moved just before the resets: a reset must send them back)
            changes = _drift(compiled, backend, piece, t_event, y_event, z_event, P, when, delta_at(t_event))
            crossing = {e: changes[e] for e in with_reset}
        preferred = {e: int(np.sign(F[first, e])) or 1 for e in fired if events[e].strict and not events[e].integer}
        exited = {e for e in fired if e in begin.sliding}
        for e in exited:  # (it leaves the sliding motion to the side whose rate reached 0)
            up, down = begin.sliding[e](np.array([t_event]), y_event, z_event, P)[0]
            preferred[e] = 1 if abs(up) <= abs(down) else -1
        before = np.concatenate([y_event, z_event], axis=1)
        F_raw = when(np.array([t_event]), y_event, z_event, P)[0]
        Y = y_event.copy()
        for e in with_reset:
            new = resets[e](t_event, Y, z_event, P)
            for k, (index, _) in enumerate(events[e].reset):
                Y[:, index] = new[:, k]
        F_reset = when(np.array([t_event]), Y, z_event, P)[0]
        scale = float(np.max(np.abs(np.concatenate([Y[0], z_event[0], [t_event]]))))
        moved_off = {e for e in with_reset if abs(F_reset[e] - F_raw[e]) > ROUNDING * max(1.0, scale)}
        terminal = any(events[e].terminal for e in fired)
        reduced = for_method(compiled, backend)
        if terminal:
            Z = algebraic_values(reduced, t_event, Y, P, z_event) if with_reset else z_event
            moved = np.zeros(1)
        else:
            projected = onto_constraints(dataclasses.replace(compiled, t0=float(t_event)), Y, P)
            moved = np.max(np.abs(projected - Y), axis=1, initial=0.0)
            Y = projected
            if lock and Z.shape[1]:  # (z on the branch the next piece takes)
                delta = delta_at(t_event)
                after = _start_piece(
                    backend, compiled, when, t_event, Y, z_event, P, fired, crossing, preferred, delta, lock, exited,
                    moved_off,
                )  # fmt: skip
                setup_time += after.setup_time
                reduced = for_method(after.model, backend)
            Z = algebraic_values(reduced, t_event, Y, P, z_event)
        for e in fired:
            entry = record[events[e].name]
            entry["t"].append(t_event)
            entry["before"].append(before[0])
            entry["after"].append(np.concatenate([Y, Z], axis=1)[0])
            entry["moved"].append(float(moved[0]))
        count += len(fired) - 1
        if terminal or ends:
            break
        t = t_event
    # the outputs: each piece solved again on the user's times (t_eval), or on its own steps (the last
    # piece's detection solve is its solve); a piece ending at an event leaves its time to the next one,
    # which starts with the values after it
    names = (*compiled.state_names, *compiled.algebraic_names)
    times, rows, failing = [], [], []  # (failing: the pieces whose solve did not meet its accuracy)
    dense = []  # each piece's dense output: its output solve's, else its detection solve's (that ran past b)
    for a, b, Ya, Za, event, model, detection in pieces:
        closed, sol = event is None, None
        dense.append(detection)
        if user_grid is not None:
            grid = user_grid[(user_grid >= a) & ((user_grid <= b) if closed else (user_grid < b))]
            if not len(grid):
                continue
            if len(grid) == 1 and grid[0] == a:
                piece_t, piece = np.array([a]), np.concatenate([Ya, Za], axis=1)
            else:
                sol = _span_solve(backend, model, a, b, Ya, Za, P, start.batched, options, t_eval=grid)
                all_stats.append(sol.stats)
                setup_time += sol.setup_time
                piece_t, Yp, Zp = _outputs(sol, compiled)
                piece = np.concatenate([Yp, Zp], axis=1)
        else:
            if not closed:
                sol = _span_solve(backend, model, a, b, Ya, Za, P, start.batched, options, t_eval=None)
                all_stats.append(sol.stats)
                setup_time += sol.setup_time
            else:
                sol = last
            piece_t, Yp, Zp = _outputs(sol, compiled)
            piece = np.concatenate([Yp, Zp], axis=1)
            if not closed:
                piece_t, piece = piece_t[:-1], piece[:-1]
        if sol is not None and sol.status != "success":
            failing.append(f"on [{a:.6g}, {b:.6g}]: {sol.status}")
        if sol is not None and sol.dense is not None:
            dense[-1] = sol.dense
        times.append(piece_t)
        rows.append(piece)
    edges = [piece[0] for piece in pieces] + [pieces[-1][1]]
    if pieces[-1][4] is not None:  # a terminal event: the solve ends with the values after it
        times.append(np.array([pieces[-1][1]]))
        rows.append(np.concatenate([Y, Z], axis=1))
        edges.append(pieces[-1][1])
        dense.append(Held(pieces[-1][1], np.concatenate([Y, Z], axis=1)))
    t_out = np.concatenate(times)
    table = np.concatenate(rows, axis=0)
    out = {name: table[:, j][None, :].copy() for j, name in enumerate(names)}
    stats = merge_stats(all_stats)
    stats["events"] = count

    def by_name(rows) -> dict:
        table = np.asarray(rows, dtype=float).reshape(len(rows), len(names))
        return {v: table[:, j][None, :].copy() for j, v in enumerate(names)}

    events_out = {
        name: {
            "t": np.asarray(entry["t"], dtype=float)[None, :],
            "moved": np.asarray(entry["moved"], dtype=float)[None, :],
            "before": by_name(entry["before"]),
            "after": by_name(entry["after"]),
        }
        for name, entry in record.items()
    }
    return Solution(
        t=t_out,
        values=out,
        method=last.method,
        settings=settings_as_given(last, options),
        solve_time=time.perf_counter() - started - setup_time,  # (all the rest: trial solves, resets, outputs)
        stats=stats,
        compiled=for_method(compiled, backend),
        parameters=P,
        batched=start.batched,
        status="success" if not failing else "; ".join(failing),
        setup_time=setup_time,
        events=events_out,
        dense=joined_in_time(edges, dense),
    )


def _trial(backend, compiled, options, batched, P, which, when, a: float, tau: float, ya, za) -> tuple:
    """One trial solve of ``compiled`` over ``[a, tau]`` from ``(ya, za)``: ``(F, y (1, n), z (1, m), stats)``,
    ``F`` the event function ``which`` at its end.  A fixed ``h`` is kept (at most the span); a span shorter
    than a method's own grid resolves is one fixed step, its adaptive settings dropped.  Its warnings are
    not the solve's (its outputs are solved again), so they are not shown."""
    fields = {f.name for f in dataclasses.fields(options)}
    changes = {"t_eval": None}
    if "h" in fields and getattr(options, "h", None) is not None:
        changes["h"] = min(options.h, tau - a)
    elif "h" in fields and tau - a <= TINY_SPAN * max(1.0, abs(a)):
        changes |= {"h": tau - a} | {name: None for name in ("rtol", "atol", "h0") if name in fields}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sol = _span_solve(backend, compiled, a, tau, ya, za, P, batched, options, **changes)
    _, Ys, Zs = _outputs(sol, compiled)
    y, z = Ys[-1:], Zs[-1:]
    return float(when(np.array([tau]), y, z, P)[0, which]), y, z, sol.stats


def _clear_of_zero(backend, compiled, options, batched, P, which, when, a, b, ya, za, side, delta, event):
    """``(t, F, y (1, n), z (1, m))`` past ``a`` where the event function ``which``, at zero at ``a``, is on
    its ``side`` in the method's own solution: a look-ahead ``delta`` later, doubled while the method's
    error near zero hides the side (up to half the bracket).

    Raises
    ------
    ZenoError
        It is not on its side anywhere there: back across zero sooner than the method resolves.
    """
    step = delta
    while True:
        tau = min(a + step, 0.5 * (a + b))
        value, y, z, _ = _trial(backend, compiled, options, batched, P, which, when, a, tau, ya, za)
        if np.sign(value) == side:
            return tau, value, y, z
        if tau >= 0.5 * (a + b):
            raise ZenoError(
                f"event '{event.name}' at t = {a:.12g}: its function does not leave zero to the side the flow "
                f"takes within {tau - a:.3g} of its last crossing, at the method's accuracy (events closer together "
                "than it resolves: Zeno, or a state resting on its guard); make the event terminal=True to stop "
                "there, tighten the tolerances, or end t_span before it",
                a,
            )
        step *= 2.0


def _locate(backend, compiled, options, batched, P, which, when, a, b, Fa, Fb, ya, za):
    """The event ``which`` between outputs ``a`` and ``b`` (values ``Fa``, ``Fb`` of opposite sign or
    ``Fb`` 0): ``(t, y (1, n), z (1, m), the trial solves' stats)``, by the Illinois method on trial
    solves from ``a``."""
    stats = []
    tol = EVENT_TOL * max(1.0, abs(a), abs(b))

    def trial(tau):
        value, y, z, solved = _trial(backend, compiled, options, batched, P, which, when, a, tau, ya, za)
        stats.append(solved)
        return value, y, z

    if Fb == 0:
        _, y, z = trial(b)
        return b, y, z, stats
    lo, hi, flo, fhi = a, b, Fa, Fb
    best = None
    side = 0
    for _ in range(MAX_LOCATION_ITERATIONS):
        tau = hi - fhi * (hi - lo) / (fhi - flo) if fhi != flo else 0.5 * (lo + hi)
        if not lo < tau < hi:
            tau = 0.5 * (lo + hi)
        tau = max(tau, min(a + 1e-13 * max(1.0, abs(a)), 0.5 * (lo + hi)))  # (no trial span below ~1e-13)
        f, y, z = trial(tau)
        best = (tau, y, z)
        if f == 0 or hi - lo <= tol:
            return tau, y, z, stats
        if np.sign(f) == np.sign(flo):
            lo, flo = tau, f
            if side == -1:
                fhi *= 0.5  # (Illinois: halve the stale end's value)
            side = -1
        else:
            hi, fhi = tau, f
            if side == 1:
                flo *= 0.5
            side = 1
        if hi - lo <= tol:
            tau = hi  # (the event after the crossing: the function has changed sign there)
            f, y, z = trial(tau)
            return tau, y, z, stats
    raise EventLocationError(
        f"event {compiled.events[which].name!r} between t = {a:.10g} and {b:.10g}: not located to {tol:.1e} in "
        f"{MAX_LOCATION_ITERATIONS} trial solves (the bracket is [{lo:.15g}, {hi:.15g}], last trial "
        f"{best[0]:.15g}); the event function may be discontinuous there"
    )

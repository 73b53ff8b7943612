"""Declared events: impacts, resets and stops, located during the solve, in every method.

``m.event(name, when, direction=0, reset=None, terminal=False)`` declares an event at each zero
crossing of ``when`` (an expression of t, the variables and parameters): ``direction`` +1 for a
rising, -1 for a falling crossing, 0 for both.  At the event ``reset`` (state name -> expression
of the values just before; events at one instant all read those, and two that set one state to
different values raise :class:`~daemodel.errors.ResetConflictError`) sets states; the states are
then projected onto the constraints where the reset left them (least change, reported), the
algebraic variables are solved anew with the routine that initialises them at t0, and the
integration starts again.  ``terminal=True`` ends
the solve there.

How (:func:`solve_with_events`, for every method alike): integrate towards t1 on the method's own
outputs, evaluate every event function there, and take the first crossing (a method that can stop,
``backend.stops``, ends that solve where it finds the crossing: its steps up to there are the piece's
outputs, instead of a solve to t1 whose rest is discarded); locate it between the
two outputs that bracket it by the Illinois variant of regula falsi, each trial time a short solve
from the output before it (so the located state has the method's own accuracy, not an
interpolant's), to :func:`~daemodel.solving.branches.event_tol` in t and a tenth of the states' tolerance
(:mod:`daemodel.solving.locate`; one float64 cannot resolve is flagged); keep the outputs before it,
apply the reset, go on from there.  A function that crosses zero and comes back between two outputs changes no sign at
them: it is looked for on the dense output between them (:mod:`daemodel.solving.between`, also in
the blocks a stopping method shows its search), confirmed by a trial solve, and its crossing located
the same way; a search stopped for one its trial does not confirm goes on from there (at most
``max_events`` times).  An event function at zero where a piece starts (just fired, or where the
solve starts) takes the side the flow goes to (:mod:`daemodel.solving.branches`: one explicit
step), so a flight shorter than an output step is a crossing too.  At most ``max_events`` events a solve
(default :data:`DEFAULT_MAX_EVENTS`); events whose times converge stop earlier, at their estimated
accumulation point, and so does a reset that leaves its function on the guard
(:class:`~daemodel.errors.ZenoError`).

Switches on states and algebraic variables (found in :mod:`daemodel.compiling.switches`) are events
too (:func:`~daemodel.compiling.switches.with_state_events`: no reset, named after the switch), with
the switch locked to the branch the flow takes where each piece starts
(:func:`daemodel.compiling.switches.lock_branches`,
never the switch's value at zero), so that every piece is smooth; a switch where neither branch
goes on (a sliding mode) is refused (:class:`~daemodel.errors.SlidingModeError`); one whose function rests on
zero within the method's error keeps its branch where both agree (:mod:`daemodel.solving.resting`).

After the solve, crossings within the method's error (a function that crosses and comes back, or comes near zero,
within 1000 tolerances of it) stand only where the whole solve 100 times tighter confirms them; else the status
says they are undecided (:mod:`daemodel.solving.undecided`, ``stats["undecided_checks"]``).
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings

import numpy as np

from daemodel.compiling.batch_function import claim_generated, generating_seconds
from daemodel.compiling.switches import has_state_switches
from daemodel.errors import (
    ConvergenceError,
    EventLimitError,
    EventLocationError,
    EventResolutionWarning,
    StepLimitError,
    SwitchError,
    TimeResolutionError,
    ZenoError,
)
from daemodel.solving.between import (
    dense_crossing,
    earliest_tied,
)
from daemodel.solving.branches import (
    RESOLUTION_LOOKAHEAD,
    SHORTEST_TOLS,
    accumulation_point,
    check_accumulating,
    drift,
    event_tol,
    finite_functions,
    jumped,
    reset_keeps_motion,
    resolution,
    start_piece,
    time_text,
)
from daemodel.solving.crossings import crossing_stop, first_crossing, settled
from daemodel.solving.hidden import first_excursion
from daemodel.solving.locate import earlier_tied, locate, outputs, span_solve, trial_solve
from daemodel.solving.misses import CarriedErrors, status_of, tighter
from daemodel.solving.pieces import (
    breakpoints_between,
    join_samples,
    joined_breakpoints,
    merge_stats,
    onto_constraints,
)
from daemodel.solving.resets import apply_resets
from daemodel.solving.resting import account, gone, rest_or_raise, watch
from daemodel.solving.rounding import floor_at
from daemodel.solving.switches import for_method, settings_as_given
from daemodel.solving.undecided import audit

# Events one solve may handle, unless dm.solve(max_events=...) says otherwise.
DEFAULT_MAX_EVENTS = 1000
# Chattering: more than CHATTER_EVENTS events within CHATTER_SPAN of t_span's length end the solve
# (EventLimitError) before max_events does; a sliding mode makes thousands, each a few trial solves.
CHATTER_EVENTS, CHATTER_SPAN = 20, 1e-9
# Which way an event function at zero goes (after an event, or where it starts) is read off one explicit
# step this long: LOOKAHEAD_SPAN of t_span's length, and at least LOOKAHEAD_TOLS location tolerances (so
# that a located event's own error in t cannot decide the side).
LOOKAHEAD_SPAN, LOOKAHEAD_TOLS = 1e-9, 100
# A detection solve on locked branches that fails at a time is solved again to this fraction of the way
# there, where the crossing that its branch went past is looked for (_detect).
BEFORE_FAILURE = 0.99


def _functions(compiled):
    """Numeric event functions of ``compiled``: ``F(t, Y, Z, P) -> (B, E)`` and the resets, cached."""

    def build():
        numeric = compiled.numeric
        when = numeric.batch_function([e.when for e in compiled.events])
        resets = [numeric.batch_function([expr for _, expr in e.reset]) if e.reset else None for e in compiled.events]
        return when, resets

    return compiled.cached(("events", compiled.events), build)


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
        A batch without ``t_eval``: its samples' outputs would not share times (:func:`daemodel.solve` gives
        such a batch to :func:`~daemodel.solving.batches.solve_on_common_times`).
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


def _one_sample(backend, compiled, t_span, start, options, max_events: int, audited: bool = True):
    from daemodel.backends.grids import output_times
    from daemodel.compiling.initial_states import algebraic_values
    from daemodel.dense import Held, joined_in_time
    from daemodel.solution import Solution

    started = time.perf_counter()
    made = generating_seconds()  # (functions' code made at its first use in this call: setup too, not solve)
    t0, t1 = (float(v) for v in t_span)
    when, resets = _functions(compiled)
    events = compiled.events
    whens = tuple(event.when for event in events)  # (their drifts and resets read within their own rounding)
    P = np.asarray(start.p, dtype=float)
    Y, Z = np.asarray(start.y0, dtype=float), np.asarray(start.z0, dtype=float)
    user_grid = None if getattr(options, "t_eval", None) is None else output_times(options.t_eval, t_span, ())
    pieces, all_stats, record = [], [], {e.name: {"t": [], "before": [], "after": [], "moved": []} for e in events}
    t, count, setup_time, last = t0, 0, 0.0, None
    recent = []  # (the event times, to see chattering before max_events)
    history = {e: [] for e in range(len(events))}  # (each event's times, to see them accumulate)
    fired, crossing, preferred, exited, moved_off = [], {}, {}, set(), set()  # (what happened at t: start_piece)
    keeps_motion = {e for e, event in enumerate(events) if not event.strict and reset_keeps_motion(compiled, event)}
    lock = has_state_switches(compiled)
    failing = []  # (the pieces whose solve did not meet its accuracy, and events not located to it)
    location, spent = [], [0.0]  # (the trial solves' stats; the tolerance the excursions integrated through used)
    missed, checks = [], []  # (near misses within the method's error: misses.NearMiss; the tighter solves' stats)
    continued, carried = 0, {}  # (pieces that end where a search stopped for nothing, and the step they reached)
    keeps_dense = getattr(options, "dense_output", True)  # (the searches keep theirs: see between.dense_crossing)
    rests = {}  # (switches resting on zero within the method's error: resting.Rest by event)
    rested, left_rests = 0, 0  # (rests begun; rests left, each a piece that ends where its function leaves the band)
    carried_in = CarriedErrors()  # (each piece, to estimate the error it carries on: misses.CarriedErrors)

    def delta_at(time_: float) -> float:
        return max(LOOKAHEAD_SPAN * (t1 - t0), LOOKAHEAD_TOLS * event_tol(time_, t1 - t0))

    def shortest_at(time_: float) -> float:
        return min(delta_at(time_), max(LOOKAHEAD_SPAN * (t1 - t0), SHORTEST_TOLS * event_tol(time_, t1 - t0)))

    while True:
        # (switches on variables locked to the branch the flow takes from the piece's start: smooth until an event)
        before = generating_seconds()
        try:
            begin = start_piece(
                backend, compiled, when, t, Y, Z, P, fired, crossing, preferred, delta_at(t), lock, exited, moved_off,
                t1 - t, span=t1 - t0, shortest=shortest_at(t),
            )  # fmt: skip
        except ZenoError as error:  # (a ball at rest: where its bounces accumulate, if their times tell)
            limit = max((accumulation_point(history[e]) or -math.inf for e in fired), default=-math.inf)
            if limit > -math.inf:
                raise ZenoError(f"{error}; its events accumulate at t ≈ {time_text(limit)}", limit) from None
            raise
        setup_time += begin.setup_time
        claim_generated(before)  # (on start_piece's setup clock already)
        begin, rests, rest_sides = watch(begin, rests, when, t, Y, Z, P, fired)
        piece, piece_when = begin.model, begin.when
        spent_before = spent[0]
        if t == t0 and Z.shape[1] and any(e.strict for e, side in zip(events, begin.sides, strict=True) if side):
            Z = algebraic_values(for_method(piece, backend), t, Y, P, Z)  # (z0 on the branch taken, not at zero)
        with warnings.catch_warnings(record=True) as caught:  # (said only where the solve is the last piece's)
            warnings.simplefilter("always")
            clean = [t]  # (read between by the search's stop up to there, and nothing found)
            stop = crossing_stop(compiled, begin, P, options, spent, clean)  # (it ends at a crossing, not at t1)
            sol, failed = _detect(backend, piece, t, t1, Y, Z, P, start.batched, options, stop, carried, lock)
        carried = {}
        all_stats.append(sol.stats)
        setup_time += sol.setup_time
        last = sol
        T, Ys, Zs = outputs(sol, compiled)
        F = settled(piece_when(T, Ys, Zs, np.repeat(P, len(T), axis=0)), T, t, begin)
        first, which, hit, before_index = None, None, {}, None
        for e, event in enumerate(events):
            hits = first_crossing(F[:, e], event.direction, bool(begin.armed[e]), begin.sides[e])
            if len(hits):
                hit[e] = int(hits[0])
                if first is None or hits[0] < first:
                    first, which, before_index = int(hits[0]), e, int(hits[1])
        finite_functions(compiled, F, T, Ys, len(T) if first is None else first + 1)
        found = None  # (which, a, b, Fa, Fb, ya, za, the first trial, each fired event's side after it)
        if first is not None:
            tied = [e for e in hit if hit[e] == first]
            which = earliest_tied(sol, compiled, piece_when, P, tied, T[before_index], T[first], F[before_index], which)
            a, b, Fa, Fb = T[before_index], T[first], F[before_index, which], F[first, which]
            ya, za = Ys[before_index : before_index + 1], Zs[before_index : before_index + 1]
            if before_index == 0 and which in begin.at_zero and begin.sides[which]:
                # (at zero where the piece starts, going to its side: the bracket starts a look-ahead later, where
                # the method's own solution is on that side, clear of its error at the start)
                try:
                    a, Fa, ya, za = _clear_of_zero(
                        backend, piece, options, start.batched, P, which, piece_when, a, b, ya, za,
                        begin.sides[which], shortest_at(a), events[which],
                    )  # fmt: skip
                except ZenoError as error:  # (a continuous switch resting on zero: the piece again, watched)
                    if which in rests:
                        raise
                    rests[which] = rest_or_raise(
                        error, compiled, backend, piece, begin.sides[which], options, P, which, a, ya, za, t1,
                        ahead=0.5 * (a + b),
                    )  # fmt: skip
                    rested += 1
                    spent[0] = spent_before
                    continue
            guess = dense_crossing(sol, compiled, piece_when, which, P, a, b, Fa)
            sides_after = {e: int(np.sign(F[first, e])) or 1 for e in tied}
            found = (which, a, b, Fa, Fb, ya, za, guess, sides_after)
        # a function that crossed zero and came back between two outputs, before that crossing
        until = math.inf if found is None else (found[7] if found[7] is not None else found[2])
        shown = len(T) if first is None else first + 1
        failing += account(
            rests, rest_sides, compiled, backend, piece, options, P, T[:shown], Ys[:shown], Zs[:shown], F[:shown]
        )
        read = max(int(np.searchsorted(T, clean[0], side="right")) - 1, 0)  # (what the stop has not read between)
        hidden, trials = first_excursion(
            backend, piece, options, start.batched, P, compiled, piece_when, sol, T[read:shown], F[read:shown],
            Ys[read:], Zs[read:], begin, until, spent, missed, checks, carried_in,
        )  # fmt: skip
        all_stats += trials
        location += trials
        if hidden is not None:
            found, hit = hidden, {}
        if failed is not None and found is None:  # (no switch crossed before the failure: the model's own)
            raise failed
        left = None if failed is not None else gone(rests, rest_sides, F[:shown])
        ended = left is not None and bool(found is None or T[left] <= found[1])
        if ended:  # (a rest ends: on from there, watched anew)
            found, T, Ys, Zs = None, T[: left + 1], Ys[: left + 1], Zs[: left + 1]
        if found is None and T[-1] < t1 and sol.status == "success" and len(T) > 1:
            # (stopped at an excursion on the dense output that the method's own trial solve did not confirm, or
            # where a rest ends: on from there, with the step it had reached.  A rest ends once, and begins only
            # where a piece starts at zero, at t0 or after an event: max_events bounds them)
            left_rests += ended
            continued += not ended
            if continued > max_events:
                raise EventLimitError(
                    f"{continued} crossings of zero on the dense output that the method's own solution does not "
                    f"confirm, by t = {T[-1]:.10g} (max_events = {max_events}): the event functions graze zero "
                    "within the method's error that often; tighten the tolerances or raise max_events"
                )
            pieces.append((t, T[-1], Y, Z, "continued", piece, sol.dense if keeps_dense else None, sol))
            again = _again(backend, piece, start.batched, P, piece_when, t, Y, Z, T[-1], checks)
            carried_in.add(again)
            if getattr(options, "h", None) is None:
                carried = {"h0": float(T[-1] - T[-2])}
            t, Y, Z = float(T[-1]), Ys[-1:].copy(), Zs[-1:].copy()
            carried_in.restart(None, Y, Z)
            fired, crossing, preferred, exited, moved_off = [], {}, {}, set(), set()
            continue
        if found is None:
            for warning in caught:
                warnings.warn(warning.message, warning.category, stacklevel=4)
            pieces.append((t, t1, Y, Z, None, piece, sol.dense if keeps_dense else None, sol))
            break
        which, a, b, Fa, Fb, ya, za, guess, sides_after = found
        count += 1
        if count > max_events:
            raise EventLimitError(
                f"event '{events[which].name}' would be event number {count} by t = {b:.10g} (max_events = "
                f"{max_events}): events this close together are chattering (Zeno); raise max_events, or end t_span "
                "before it"
            )
        t_event, y_event, z_event, located, unresolved = locate(
            backend, piece, options, start.batched, P, which, piece_when, a, b, Fa, Fb, ya, za, guess, t1 - t0
        )
        all_stats += located
        location += located
        if hit:  # (an event tied with it that crossed before it: located too, the earlier of them fires)
            which, t_event, y_event, z_event, unresolved = earlier_tied(
                backend, piece, options, start.batched, P, piece_when, events, hit, first, T[before_index],
                F[before_index], Ys[before_index : before_index + 1], Zs[before_index : before_index + 1],
                (which, t_event, y_event, z_event, unresolved), location, all_stats, t1 - t0,
            )  # fmt: skip
        carried_in.add(_again(backend, piece, start.batched, P, piece_when, t, Y, Z, t_event, checks))
        if unresolved is not None:
            from daemodel.backends.base import caller_level

            failing.append(unresolved)
            warnings.warn(unresolved, EventResolutionWarning, stacklevel=caller_level())
        ends = t_event >= t1 - event_tol(t1, t1 - t0)  # (an event at t1: applied there, and the solve ends)
        t_event = t1 if ends else t_event
        recent.append(t_event)
        if len(recent) > CHATTER_EVENTS and recent[-1] - recent[-1 - CHATTER_EVENTS] <= CHATTER_SPAN * (t1 - t0):
            first_time = recent[-1 - CHATTER_EVENTS]
            raise ZenoError(
                f"event '{events[which].name}': {CHATTER_EVENTS} events between t = {first_time:.12g} and "
                f"{recent[-1]:.12g}: chattering (Zeno); end t_span before it, or make the event terminal=True",
                recent[-1],
            )
        pieces.append((t, t_event, Y, Z, (which, t_event), piece, sol.dense if keeps_dense else None, sol))
        # every event whose function changed sign (its way) between the bracket's start and the located
        # time fires there, in declaration order (identical or simultaneous events)
        F_event = piece_when(np.array([t_event]), y_event, z_event, P)[0]
        fired = [
            e
            for e, event in enumerate(events)
            if e == which
            or (
                e in hit
                and hit[e] == first
                and (
                    len(first_crossing(np.array([F[before_index, e], F_event[e]]), event.direction, True))
                    or F_event[e] == 0
                )
            )
        ]
        # (and a declared event whose function a switch firing here takes across zero by a jump: off zero after it)
        delta = delta_at(t_event)
        jumps = jumped(compiled, backend, piece, when, piece_when, t_event, y_event, z_event, P, delta, fired)
        fired = sorted(fired + jumps)
        for e in fired:
            history[e].append(t_event)
            check_accumulating(events[e], history[e], t0, t1)
        with_reset = [e for e in fired if resets[e] is not None]
        crossing = {}
        if with_reset:  # (how the functions moved just before the resets: a reset must send them back)
            # (from z solved at y_event, as after the reset: the method's z is off its constraints by its own
            # tolerance, 8e-14 for radau at rtol 1e-8, against a drift of 1e-9, and a reset that left the
            # motion as it was seemed to change it: ZenoError)
            z_start = (
                z_event
                if not z_event.shape[1]
                else algebraic_values(for_method(piece, backend), t_event, y_event, P, z_event)
            )
            changes = drift(compiled, backend, piece, t_event, y_event, z_start, P, when, delta_at(t_event),
                            exprs=whens)  # fmt: skip
            crossing = {e: changes[e] for e in with_reset}
        preferred = {e: sides_after.get(e, 1) for e in fired if events[e].strict and not events[e].integer}
        # (and each declared event that crossed zero here, from the bracket's start to its side after: the side it
        # crossed to, which a look-ahead that reads it back on the side it came from has passed its crossing back;
        # not a bounce's, whose reset sends it back)
        F_from = piece_when(np.array([a]), ya, za, P)[0]
        preferred |= {
            e: sides_after[e]
            for e in fired
            if e in keeps_motion and e in sides_after and sides_after[e] == -np.sign(F_from[e]) != 0
        }
        exited = {e for e in fired if e in begin.sliding}
        for e in exited:  # (it leaves the sliding motion to the side whose rate reached 0)
            up, down = begin.sliding[e](np.array([t_event]), y_event, z_event, P)[0]
            preferred[e] = 1 if abs(up) <= abs(down) else -1
        before = np.concatenate([y_event, z_event], axis=1)
        F_raw = when(np.array([t_event]), y_event, z_event, P)[0]
        Y = apply_resets(compiled, resets, with_reset, t_event, y_event, z_event, P)
        F_reset = when(np.array([t_event]), Y, z_event, P)[0]
        floor = np.maximum(floor_at(compiled, whens, t_event, y_event, z_event, P),
                           floor_at(compiled, whens, t_event, Y, z_event, P))  # fmt: skip
        moved_off = {e for e in with_reset if abs(F_reset[e] - F_raw[e]) > floor[e]} | set(jumps)
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
                after = start_piece(
                    backend, compiled, when, t_event, Y, z_event, P, fired, crossing, preferred, delta, lock, exited,
                    moved_off, t1 - t_event, span=t1 - t0, shortest=shortest_at(t_event),
                )  # fmt: skip
                setup_time += after.setup_time
                reduced = for_method(after.model, backend)
            Z = algebraic_values(reduced, t_event, Y, P, z_event)
            carried_in.restart(_after_event(compiled, resets, with_reset, t_event, P, reduced), Y, Z)
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
    # the outputs: each piece's detection solve's where the method stops at a crossing and chooses its steps (a
    # solve to the event makes the same steps, the same values, but for its last one or two, which it shortens to
    # end there): its steps before its end, or the user's times (t_eval) read off them where its dense output is
    # an evaluation (radau's polynomials, what t_eval evaluates); else each piece solved again to its end on the
    # user's times, or on its own (a fixed h: equal steps over the piece); a piece ending at an event leaves
    # its time to the next one, which starts with the values after it
    reuse = backend.stops and getattr(options, "h", None) is None
    names = (*compiled.state_names, *compiled.algebraic_names)
    times, rows = [], []
    dense = []  # each piece's dense output: its output solve's, else its detection solve's (that ran past b)
    marks = []  # (the time breakpoints each piece's detection solve crossed before its end)
    for a, b, Ya, Za, event, model, detection, found in pieces:
        closed, sol = event is None, None
        dense.append(detection)
        if found.breakpoints:
            marks.append(breakpoints_between(found.breakpoints, a, b, closed))
        if user_grid is not None:
            grid = user_grid[(user_grid >= a) & ((user_grid <= b) if closed else (user_grid < b))]
            if not len(grid):
                continue
            if len(grid) == 1 and grid[0] == a:
                piece_t, piece = np.array([a]), np.concatenate([Ya, Za], axis=1)
            elif reuse and found.dense is not None and not found.dense.solves_again:
                # (read off the detection solve's steps where that is an evaluation, as without t_eval: solved
                # again, each piece cost its steps twice)
                piece_t, piece = grid, found.columns_at(grid, names)
                if found.status != "success":
                    failing.append(f"on [{a:.6g}, {b:.6g}]: {found.status}")
            else:
                sol = span_solve(backend, model, a, b, Ya, Za, P, start.batched, options, t_eval=grid)
                all_stats.append(sol.stats)
                setup_time += sol.setup_time
                piece_t, Yp, Zp = outputs(sol, compiled)
                piece = np.concatenate([Yp, Zp], axis=1)
        else:
            if not (closed or reuse):
                sol = span_solve(backend, model, a, b, Ya, Za, P, start.batched, options, t_eval=None)
                all_stats.append(sol.stats)
                setup_time += sol.setup_time
            piece_t, Yp, Zp = outputs(found if sol is None else sol, compiled)
            piece = np.concatenate([Yp, Zp], axis=1)
            if not closed:
                before = piece_t < b
                piece_t, piece = piece_t[before], piece[before]
            if sol is None and found.status != "success":
                failing.append(f"on [{a:.6g}, {b:.6g}]: {found.status}")
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
    stats = merge_stats(all_stats + checks)
    stats["events"] = count
    # (the trial solves that located the events, and confirmed excursions: their steps are among stats["steps"])
    stats["location_trials"] = len(location)
    stats["location_steps"] = int(sum(trial.get("steps", 0) for trial in location))
    stats["searches_continued"] = continued  # (stopped at an excursion that its trial did not confirm)
    stats["rests"], stats["rests_left"] = rested, left_rests  # (switches that rested on zero; those that left it)
    stats["near_miss_checks"] = len(checks)  # (tighter solves, their steps among stats["steps"])
    failing += status_of(missed, last.method)

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
    setup_time += claim_generated(made)
    solution = Solution(
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
        breakpoints=joined_breakpoints(marks),
        dense=joined_in_time(edges, dense),
    )
    tight = tighter(options)
    if not audited or tight is None:  # (a tighter solve's own, or nothing tighter to check with)
        return solution
    # (crossings within the method's error, confirmed by the whole solve again TIGHTER times tighter or flagged;
    # its steps among stats["steps"], its time on the solve's clock)
    checked, audit_started, made_before = [], time.perf_counter(), generating_seconds()

    def again():
        with warnings.catch_warnings():  # (the check's own warnings are not the solve's: its status is read)
            warnings.simplefilter("ignore")
            checked.append(_one_sample(backend, compiled, t_span, start, tight, max_events, False))
        return checked[-1]

    flagged = audit(solution, compiled, when, options, P, again)
    stats["undecided_checks"] = len(checked)
    if checked:
        own = ("events", "location_trials", "location_steps", "searches_continued", "rests", "rests_left")
        stats = merge_stats([stats, {k: v for k, v in checked[0].stats.items() if k not in own}])
    status = "; ".join(([] if solution.status == "success" else [solution.status]) + flagged) or "success"
    # (code made for it, and the check's own setup, are setup)
    setup = claim_generated(made_before) + sum(check.setup_time for check in checked)
    spent = time.perf_counter() - audit_started - setup
    return dataclasses.replace(
        solution, status=status, stats=stats, solve_time=solution.solve_time + spent, setup_time=setup_time + setup
    )


def _detect(backend, piece, t: float, t1: float, Y, Z, P, batched, options, stop, carried: dict, lock: bool):
    """A piece's detection solve from ``t`` towards ``t1`` (with its dense output, where the location's first
    trial is read, whatever the caller keeps) and None.  Where its switches are locked and it fails at a
    time the method names (the ``t`` of :class:`~daemodel.errors.SolverError`), the solve again to
    :data:`BEFORE_FAILURE` of the way there, and the error, for the caller to raise unless a crossing comes
    before it: the branch continued past its switch can leave the model's domain (the wheelset's creep
    left unsaturated past its saturation failed IDAS's Newton 6 ms after it) in a method that does not
    stop at a crossing (``backend.stops``)."""

    def run(end: float):
        return span_solve(
            backend, piece, t, end, Y, Z, P, batched, options, stop=stop, t_eval=None, dense_output=True, **carried
        )

    try:
        return run(t1), None
    except (ConvergenceError, StepLimitError) as error:
        if not lock or error.t is None or not t < error.t < t1:
            raise
        try:
            return run(t + BEFORE_FAILURE * (error.t - t)), error
        except (ConvergenceError, StepLimitError):
            raise error from None


def _clear_of_zero(backend, compiled, options, batched, P, which, when, a, b, ya, za, side, delta, event):
    """``(t, F, y (1, n), z (1, m))`` past ``a`` where the event function ``which``, at zero at ``a``, is on
    its ``side`` in the method's own solution: a look-ahead ``delta`` later, doubled while the method's
    error near zero hides the side (up to half the bracket).

    Raises
    ------
    ZenoError
        It is not on its side anywhere there: back across zero sooner than the method resolves.
    TimeResolutionError
        It is not, and half the bracket is within ``RESOLUTION_LOOKAHEAD`` resolutions of t (float64's spacing).
    EventLocationError
        No float64 time lies between ``a`` and ``b`` to look at.
    """
    step = delta
    if not a < 0.5 * (a + b):  # (no float64 time to read it at: the trial would start and end at a)
        raise EventLocationError(
            f"event '{event.name}' at t = {a:.17g}: float64 holds no time between it and the next output t = "
            f"{b:.17g} (its spacing there is {math.ulp(a):.3g}), so the side its function goes to cannot be read; "
            "t's resolution at this |t| is too coarse for the span or for the event (located to a few spacings, which "
            "can leave its function on the wrong side of zero past the next output): start t_span nearer 0 (shift "
            "the model's time)",
            a,
        )
    while True:
        tau = min(a + step, 0.5 * (a + b))
        value, y, z, _ = trial_solve(backend, compiled, options, batched, P, which, when, a, tau, ya, za)
        if np.sign(value) == side:
            return tau, value, y, z
        if tau >= 0.5 * (a + b) and tau - a <= RESOLUTION_LOOKAHEAD * resolution(a):
            # (the event located to float64's spacing of t leaves its function off zero, on the other side, by its
            # rate times that: casadi-idas's first output after the ball's impact at t0 = 1e14 (located to 0.031)
            # lay two spacings on, the ball still below the floor, rising)
            raise TimeResolutionError(
                f"event '{event.name}' at t = {time_text(a)}: its function does not leave zero to the side the flow "
                f"takes within {tau - a:.3g} of its last crossing, {(tau - a) / math.ulp(abs(a)):.3g} float64 spacings "
                f"of t at |t| = {abs(a):.3g} (spacing {math.ulp(abs(a)):.3g}; the event is located to "
                f"{resolution(a):.3g}, which leaves its function off zero by its rate times that): a motion this short "
                "and a state resting on its guard (Zeno) look alike there; count time from near the start (t - t0 in "
                "the model, t_span from 0)",
                a,
            )
        if tau >= 0.5 * (a + b):
            raise ZenoError(
                f"event '{event.name}' at t = {a:.12g}: its function does not leave zero to the side the flow "
                f"takes within {tau - a:.3g} of its last crossing, at the method's accuracy (events closer together "
                "than it resolves: Zeno, or a state resting on its guard); make the event terminal=True to stop "
                "there, tighten the tolerances, or end t_span before it",
                a,
            )
        step *= 2.0


def _again(backend, piece, batched, P, when, a: float, ya, za, b: float, checks: list):
    """``solve(options, y0, z0) -> (y (1, n), z (1, m))``: the piece ``[a, b]`` from ``(y0, z0)`` (None: ``(ya,
    za)``) solved again with other options (:class:`~daemodel.solving.misses.CarriedErrors`), its stats added to
    ``checks``."""

    def solve(options, y0=None, z0=None):
        start = (ya, za) if y0 is None else (y0, z0)
        _, y, z, solved = trial_solve(backend, piece, options, batched, P, 0, when, a, b, *start)
        checks.append(solved)
        return y, z

    return solve


def _after_event(compiled, resets, with_reset: list, t_event: float, P, reduced):
    """``after(y, z) -> (y, z)``: what follows the event at ``t_event`` does to values at it: the resets
    ``with_reset``, the projection onto the constraints, and the algebraic variables solved on ``reduced``
    (:class:`~daemodel.solving.misses.CarriedErrors`, for a solve tighter than the method's)."""
    from daemodel.compiling.initial_states import algebraic_values

    def after(y, z):
        Y = apply_resets(compiled, resets, with_reset, t_event, y, z, P)
        Y = onto_constraints(dataclasses.replace(compiled, t0=float(t_event)), Y, P)
        return Y, algebraic_values(reduced, t_event, Y, P, z)

    return after

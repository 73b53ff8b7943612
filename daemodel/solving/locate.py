"""Locating one declared event between two outputs (:func:`locate`), for :mod:`daemodel.solving.events`:
trial solves of the method's own from the output before it (:func:`trial_solve`, each a :func:`span_solve`),
the Illinois variant of regula falsi on their event function values, to
:func:`~daemodel.solving.branches.event_tol` in t and until the states move across the bracket (their rates
times its width) by a share of their tolerance (:data:`LOCATE_SHARE`); an event that float64's spacing of
t does not resolve to that tolerance is flagged, never "success"."""

from __future__ import annotations

import dataclasses
import math
import warnings

import numpy as np

from daemodel.compiling.switches import has_time_switches
from daemodel.errors import EventLocationError
from daemodel.solving.branches import RESOLVE_ULPS, event_tol, resolution
from daemodel.solving.crossings import first_crossing
from daemodel.solving.pieces import segment_steps
from daemodel.solving.switches import for_method, solve_with_breakpoints

# Trial solves of the location of one event before EventLocationError; from BISECT_AFTER on, a bracket
# that two trials in a row did not halve from the same end is bisected (a root as flat as x^3's: the
# secant crept 1e-14 a trial from the end next to it, and 100 trials did not locate it).
MAX_LOCATION_ITERATIONS, BISECT_AFTER = 100, 24
# A located event's bracket is narrowed until the states move across it (their rates times its width) by at most
# this share of their tolerance (atol + rtol |y|), so that its time moves the states after it by less than that
# (at t0 = 1e6 the width in t alone left them 1356 rtol off).
LOCATE_SHARE = 0.1
# A trial solve of a method computing in float32 runs in float64: its event function's sign is float32's rounding
# within ~1e-7 of a crossing (x' = Piecewise((-1, x > 1), (-0.25, True)) hit x = 1.0 exactly over 6e-8 in t, and
# the search crept along that plateau: 32 trials for one event, 51 for 7 samples, against 3 in float64), while the
# side an event leaves its function on must be told there.  The pieces between events stay in float32.
TRIALS_DTYPE = {"float32": {"dtype": "float64"}}
# A trial solve this short (relative to max(1, |t|)) is one step, whatever the method's own grid.
TINY_SPAN = 1e-9
# The first trial of an event's location is where the dense output crosses (between.dense_crossing); the
# second is GUESS_WIDTH of the bracket past it.
GUESS_WIDTH = 1e-4


def span_solve(backend, compiled, a: float, b: float, Y, Z, P, batched: bool, options, stop=None, **changes):
    """One solve of ``compiled`` over [a, b] from the states ``Y``, ``Z`` (its time switches cut, as
    :func:`daemodel.solving.switches.solve_with_breakpoints` does).  ``stop``: a search's ``stop(names)``
    (:func:`~daemodel.solving.crossings.crossing_stop`; the backend's names of its states and algebraic
    variables) -> the backend's ``stop`` (:mod:`daemodel.backends.base`, rule 8); used where the backend takes it and
    no time switch cuts the span, else the solve goes on to ``b``."""
    from daemodel.compiling.initial_states import InitialStates

    model = dataclasses.replace(compiled, t0=float(a), y0=Y[0].copy(), z0=Z[0].copy())
    start = InitialStates(y0=Y, z0=Z, p=P, batched=batched)
    fields = {f.name for f in dataclasses.fields(options)}
    if "h" not in changes and getattr(options, "h", None) is not None:  # (a piece shorter than h: equal steps)
        changes["h"] = segment_steps(a, b, options.h)
    # (an option the method lacks is left out)
    options = dataclasses.replace(options, **{k: v for k, v in changes.items() if k in fields})
    if has_time_switches(model):
        return solve_with_breakpoints(backend, model, (float(a), float(b)), start, options)
    reduced = for_method(model, backend)
    if stop is not None and backend.stops:
        names = (reduced.state_names, reduced.algebraic_names)
        return backend.solve(reduced, (float(a), float(b)), start, options, stop=stop(names))
    return backend.solve(reduced, (float(a), float(b)), start, options)


def outputs(sol, compiled):
    """``(t, Y (T, n), Z (T, m))`` of a one-sample solution."""
    T = len(sol.t)
    Y = np.stack([np.asarray(sol.values[n])[0] for n in compiled.state_names], axis=-1).reshape(T, -1)
    Z = [np.asarray(sol.values[n])[0] for n in compiled.algebraic_names]
    Z = np.stack(Z, axis=-1).reshape(T, -1) if Z else np.zeros((T, 0))
    return np.asarray(sol.t, dtype=float), Y, Z


def trial_solve(backend, compiled, options, batched, P, which, when, a: float, tau: float, ya, za) -> tuple:
    """One trial solve of ``compiled`` over ``[a, tau]`` from ``(ya, za)``: ``(F, y (1, n), z (1, m), stats)``,
    ``F`` the event function ``which`` at its end.  A fixed ``h`` is kept (at most the span); a span shorter
    than a method's own grid resolves is one fixed step, its adaptive settings dropped.  Its warnings are
    not the solve's (its outputs are solved again), so they are not shown.  A method computing in float32 solves
    its trials in float64 (:data:`TRIALS_DTYPE`), from the float32 solve's output."""
    fields = {f.name for f in dataclasses.fields(options)}
    changes = {"t_eval": None} | TRIALS_DTYPE.get(getattr(options, "dtype", None), {})
    if "h" in fields and getattr(options, "h", None) is not None:
        changes["h"] = min(options.h, tau - a)
    elif "h" in fields and tau - a <= TINY_SPAN * max(1.0, abs(a)):
        changes |= {"h": tau - a} | {name: None for name in ("rtol", "atol", "h0") if name in fields}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        sol = span_solve(backend, compiled, a, tau, ya, za, P, batched, options, **changes)
    _, Ys, Zs = outputs(sol, compiled)
    y, z = Ys[-1:], Zs[-1:]
    return float(when(np.array([tau]), y, z, P)[0, which]), y, z, sol.stats


def states_tol(options) -> tuple[float, float] | None:
    """``(rtol, atol)`` the states are solved to: an adaptive method's own; a fixed step's ``estimate_bound``
    for both (its local error estimate's bound, in units of the solution's size ``1 + |y|``); else None."""
    if getattr(options, "h", None) is not None:
        bound = getattr(options, "estimate_bound", None)
        return (float(bound), float(bound)) if isinstance(bound, float | int) else None
    rtol, atol = getattr(options, "rtol", None), getattr(options, "atol", None)
    if not isinstance(rtol, float | int) or not isinstance(atol, float | int):
        return None
    return float(rtol), float(atol)


def locate(backend, compiled, options, batched, P, which, when, a, b, Fa, Fb, ya, za, guess=None, span=math.inf):
    """The event ``which`` between outputs ``a`` and ``b`` (values ``Fa``, ``Fb`` of opposite sign or
    ``Fb`` 0): ``(t, y (1, n), z (1, m), the trial solves' stats, None or the flag of an event not located
    to the states' tolerance)``, by the Illinois method on trial solves from ``a``, to
    :func:`~daemodel.solving.branches.event_tol` in t (``span``: t_span's length) and, for a method with a
    tolerance (:func:`states_tol`), until the states move by at most :data:`LOCATE_SHARE` of it across the
    bracket (their rates at its ends times its width: two trial solves' values differ by their own errors
    too, 1.1 atol for casadi-idas 2 float64 spacings apart on the wheelset); a bracket
    :func:`~daemodel.solving.branches.resolution` wide (float64 holds no finer time) across which they move
    by more than their tolerance is flagged: the event's time, and so the states after it, are off by more.
    A ``guess`` (:func:`~daemodel.solving.between.dense_crossing`'s) is the first trial, and the next one
    :data:`GUESS_WIDTH` of the bracket past it on the other side, so that the search starts from a bracket
    that narrow where the guess is as good as the dense output (about half the trials on the wheelset);
    else the search goes on from whichever bracket the trials leave."""
    stats = []
    tol, floor = event_tol(max(abs(a), abs(b)), span), resolution(max(abs(a), abs(b)))
    tolerance = states_tol(options)

    def trial(tau):
        value, y, z, solved = trial_solve(backend, compiled, options, batched, P, which, when, a, tau, ya, za)
        stats.append(solved)
        return value, y, z

    def apart() -> float:
        """How far the states move across the bracket, in their tolerances: the larger of their rates at
        its ends (where known) times its width (0 for a method without a tolerance, or rates not finite)."""
        if tolerance is None:
            return 0.0
        rtol, atol = tolerance
        rhs = compiled.numeric.batch_function(list(compiled.rhs))  # (made once: the numeric system keeps it)
        share = 0.0
        for t, (y, z) in ((lo, at_lo), (hi, at_hi)) if at_hi is not None else ((lo, at_lo),):
            rate = np.abs(rhs(t, y, z, P)) * (hi - lo) / (atol + rtol * np.abs(y))
            share = max(share, float(np.max(rate, initial=0.0)))
        return share if math.isfinite(share) else 0.0

    def settled() -> bool:
        return hi - lo <= floor or (hi - lo <= tol and apart() <= LOCATE_SHARE)

    def flag(t_event) -> str | None:
        share = apart()
        if share <= 1.0:  # (within the tolerance: a bracket narrower than float64 allows at t would not be)
            return None
        return (
            f"flagged: event {compiled.events[which].name!r} at t = {t_event:.17g} is located to {hi - lo:.3g} in t, "
            f"{RESOLVE_ULPS} float64 spacings there; the states move by {share:.3g} of their tolerance "
            f"(rtol {tolerance[0]:g}, atol {tolerance[1]:g}) across it, so the event's time and the states after it "
            f"are off by up to that much: float64 does not resolve t finely enough at |t| = {abs(t_event):.3g}; start "
            "t_span nearer 0 (shift the model's time), or loosen the tolerances"
        )

    if Fb == 0:
        _, y, z = trial(b)
        return b, y, z, stats, None
    lo, hi, flo, fhi = a, b, Fa, Fb
    at_lo = (ya, za)  # (the states at lo)
    best, at_hi = None, None  # (the trial's values at hi, where one set it)
    side, slow, last_side, zero = (
        0,
        0,
        0,
        None,
    )  # (slow: trials in a row that kept the same end and did not halve the bracket)
    width = GUESS_WIDTH * (b - a)
    for k in range(MAX_LOCATION_ITERATIONS):
        if guess is not None and k == 0:
            tau = guess
        elif guess is not None and k == 1:  # (the other side of the guess: the guess landed on lo's if side == -1)
            tau = guess + width if side == -1 else guess - width
        elif slow >= 2 and k >= BISECT_AFTER:  # (a flat root, x^3's: the secant creeps from one end; bisected)
            tau = 0.5 * (lo + hi)
        else:
            tau = hi - fhi * (hi - lo) / (fhi - flo) if fhi != flo else 0.5 * (lo + hi)
        if not lo < tau < hi:
            # the secant at an end (one whose value is near zero: a trial landed on the crossing): half the
            # tolerance inside it closes the bracket from the other side, where the midpoint's trials bisected
            # towards it (30 trials on an oscillator's crossing)
            tau = lo + 0.5 * tol if tau <= lo else hi - 0.5 * tol
        if not lo < tau < hi:  # (NaN, or a bracket within the tolerance)
            tau = 0.5 * (lo + hi)
        tau = max(tau, min(a + 1e-13 * max(1.0, abs(a)), 0.5 * (lo + hi)))  # (no trial span below ~1e-13)
        f, y, z = trial(tau)
        best = (tau, y, z)
        if settled():
            return tau, y, z, stats, flag(tau)
        before = hi - lo
        if f == 0 or np.sign(f) == np.sign(flo):
            # (a value exactly 0 has no side: the crossing is where the function reaches the other one, so a
            # function resting on zero over [1, 2] crosses at 2, not wherever a trial landed on it; the last
            # zero is the event where the other side is within the tolerance of it)
            lo, flo, at_lo = tau, f, (y, z)
            zero = (tau, y, z) if f == 0 else zero
            if side == -1:
                fhi *= 0.5  # (Illinois: halve the stale end's value)
            side = -1
        else:
            hi, fhi, at_hi = tau, f, (y, z)
            if side == 1:
                flo *= 0.5
            side = 1
        kept = side == last_side and hi - lo > 0.5 * before
        slow, last_side = (slow + 1 if kept or slow >= 2 else 0), side
        if settled():  # (the event after the crossing, where the function has changed sign: its trial's values)
            if zero is not None and hi - zero[0] <= tol:
                return (*zero, stats, flag(zero[0]))
            at_hi = at_hi if at_hi is not None else trial(hi)[1:]
            return hi, *at_hi, stats, flag(hi)
    raise EventLocationError(
        f"event {compiled.events[which].name!r} between t = {a:.10g} and {b:.10g}: not located to {tol:.1e} in "
        f"{MAX_LOCATION_ITERATIONS} trial solves (the bracket is [{lo:.15g}, {hi:.15g}], last trial "
        f"{best[0]:.15g}); the event function may be discontinuous there"
    )


def earlier_tied(
    backend, piece, options, batched, P, when, events, hit, first, a, Fa, ya, za, located, stats, more, span
):
    """``located`` (``(which, t, y, z, flag)``), or the event tied with it (``hit[e] == first``: crossing between
    the same two outputs) whose function crossed (its way) before ``t``, located from the output ``a`` (values
    ``Fa`` of every function, states ``ya``, ``za``) and earlier by more than the location's tolerance; again from
    there, until none is (crossings within twice the tolerance of ``t`` join it, as a flat root, tanh(y)^3, joins y's).
    The first declared of events crossing in one cell of the dense output was located, the
    others fired with it: x - 1 crossing 1e-5 (radau: 1e-3) before x - 1.00001, declared second, fired at 1.00001,
    a reset there 1e-5 late, "success", in every method.  The trial solves' stats are added to ``stats`` and
    ``more``."""
    which, t_event, y_event, z_event, flag = located
    for _ in range(len(events)):
        F_at = when(np.array([t_event]), y_event, z_event, P)[0]
        earlier = None
        for e in sorted(hit):
            if e == which or hit[e] != first:
                continue
            before = t_event - 2.0 * event_tol(t_event, span)  # (crossings within the tolerance of t join it)
            if not len(first_crossing(np.array([Fa[e], F_at[e]]), events[e].direction, True)) or not a < before:
                continue
            value, _, _, solved = trial_solve(backend, piece, options, batched, P, e, when, a, before, ya, za)
            stats.append(solved)
            more.append(solved)
            if not len(first_crossing(np.array([Fa[e], value]), events[e].direction, True)):
                continue
            found = locate(backend, piece, options, batched, P, e, when, a, before, Fa[e], value, ya, za, None, span)
            stats += found[3]
            more += found[3]
            if earlier is None or found[0] < earlier[1]:
                earlier = (e, *found[:3], found[4])
        if earlier is None:
            break
        which, t_event, y_event, z_event, flag = earlier
    return which, t_event, y_event, z_event, flag

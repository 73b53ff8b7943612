"""casadi-idas's event search: a solve that ends where the caller's ``stop`` says (rule 8 of
:mod:`daemodel.backends.base`), read at about one output per IDAS step.

casadi runs IDAS to a fixed list of output times and shows nothing between them: no step ends, no root
finding (casadi's own events are experimental: on 0.99 - x of an oscillator they fired once in 30 s, 6.7e-3
off zero) and no interpolant.  A search read at the 101 default outputs of a solve to t1 saw a switching
function at those outputs only: 14 of the 956 crossings of 0.99 - sin t over (0, 3000), 4.8 periods apart,
"success".  Here the search integrates in windows that double from :data:`FIRST_WINDOW` of the span (a
piece that ends at an event soon after its start costs a few short windows, not a solve to t1), each
solved again from the piece's start (no restart: the steps and values of one solve from there) on
normalised time (:func:`~.plumbing.normalised_dae`), with outputs only on its new part, :data:`OUTPUTS_PER_STEP`
or more per IDAS step there: a window whose IDAS took more steps than that is solved again on a finer grid
(IDAS interpolates at outputs: more of them leave its steps and values as they were, and cost nothing
measurable: 101 or 60,000 outputs over 40,826 steps, 0.08-0.11 s).  ``stop`` reads each window's new
outputs; where it returns True the search ends there.  IDAS starts again from the last output read only
where its steps to a window's first new output would pass half of ``max_num_steps`` (its limit per output
interval), or a window's new part would need more than :data:`MAX_POINTS` outputs.  A window whose IDAS
fails is cut to end just before the failure, and one that fails at its start is halved.

Measured (``benchmarks/idas_humps.json``): 956 of the 956 crossings, 8.5 s of CPU against 0.63 s for the 14.
The trial solves that locate each crossing now start from an output within about half a step of it, IDAS
started again from an interpolated value: the part of sin t above 0.99 at rtol 1e-10 integrates 1.10e-7 off
over (0, 100), 1.23 times the error of trial solves from outputs 1 s apart.
"""

from __future__ import annotations

import math
import re

import numpy as np
from daemodel.backends.casadi.plumbing import cached_integrator, consistent_start, scaled_dae
from daemodel.backends.checks import check_output_memory
from daemodel.backends.progress import captured_output

from daemodel.errors import DaemodelError, StepLimitError
from daemodel.executors import struck_limit

# The first window: this fraction of the span; each next one twice the last (up to the span's end).
FIRST_WINDOW = 1.0 / 1024
# Outputs per IDAS step, at least, in every window (on average over the window: the grid is uniform).
OUTPUTS_PER_STEP = 2
# A window's grid has a power of two of points, from MIN_POINTS to MAX_POINTS (one integrator each, kept with
# the model); a window whose steps need more than MAX_POINTS is halved instead.
MIN_POINTS, MAX_POINTS = 64, 2**14
# A window solved again (a finer grid, or halved) at most this many times: past it StepLimitError.  (Each redo
# doubles the points per step; 2^30 of them in a row would mean IDAS's steps shrank a billion times.)
MAX_REDOS = 30
# A window whose IDAS fails at its start is halved at most this many times; past it, IDAS's failure is raised.
# (The wheelset's failed from t = 0.7135690 with windows of 3.6e-4 and 7.2e-4, and went on with 1.8e-4, while
# IDACalcIC's own step was 0.001 of the window: plumbing.consistent_start.)
START_HALVINGS = 8
# IDAS prints the time of its failure to 6 digits (of normalised time here): a window cut short there ends this
# fraction of its length before it.
PRINTED_DIGITS = 2e-6


def _grid_size(steps: float) -> int:
    """Points of a window's grid for ``steps`` IDAS steps: a power of two, :data:`OUTPUTS_PER_STEP` a step."""
    wanted = max(MIN_POINTS, OUTPUTS_PER_STEP * steps)
    return min(MAX_POINTS, 2 ** math.ceil(math.log2(wanted)))


def real_times(printed: str, a: float, w: float) -> str:
    """IDAS's message on normalised time (``t = s``, ``h = ...``) with its times and steps on the real one."""
    printed = re.sub(r"t = ([-+0-9.eE]+)", lambda m: f"t = {a + w * float(m.group(1)):.17g}", printed)
    return re.sub(r"h = ([-+0-9.eE]+)", lambda m: f"h = {w * float(m.group(1)):.17g}", printed)


def search(compiled, t_span, y0, z0, p, settings: dict, step0, stop, explain, max_num_steps: int, slope):
    """``(times (T,), values (1, T, n+m), stats)`` of one sample from ``t_span[0]`` (its value first) until
    ``stop(times, Y, Z, None)`` returns True for a window's outputs, or to ``t_span[1]``.

    ``settings``: IDAS's (those of the whole solve, less ``step0``); ``step0``: the first step the solve
    would take from t0 (None: IDAS's choice); ``explain(error, printed, outputs)``: the exception for IDAS's
    failure (its message on the real time, the window's output times).

    Raises
    ------
    StepLimitError
        The windows' IDAS steps together past ``DEFAULT_OUTPUT_POINTS x max_num_steps`` (a solve to t1's
        limit over its default outputs), or a window solved again :data:`MAX_REDOS` times.
    """
    import casadi
    from daemodel.backends.grids import DEFAULT_OUTPUT_POINTS

    t0, t1 = float(t_span[0]), float(t_span[1])
    y, z, p = np.asarray(y0, dtype=float), np.asarray(z0, dtype=float), np.asarray(p, dtype=float)
    n = len(y)
    times, rows = [np.array([t0])], [np.concatenate([y, z])[None, :]]
    stats = {"search_windows": 0, "search_redos": 0, "search_restarts": 0}
    budget = DEFAULT_OUTPUT_POINTS * max_num_steps
    if stop(times[0], y[None, :], z[None, :], None):
        return times[0], rows[0][None], stats
    # IDAS runs from `a` (values y, z) to `end`, its outputs on (done, end]: read up to `done` already; `before`
    # its steps to `done`.  A window is solved from `a` again, twice as long (no restart: the values a solve
    # to t1 has), until its new part needs more than MAX_POINTS outputs: then IDAS starts again from `done`
    a, done, w, points, before, first = t0, t0, FIRST_WINDOW * (t1 - t0), MIN_POINTS, 0, step0
    while done < t1:
        end = min(a + w, t1)
        if t1 - end < 1e-12 * max(1.0, abs(t1)):  # (no sliver of a window left at t1)
            end = t1
        failed, halved = None, 0  # (IDAS's failure in this window, where it is cut short to end there)
        for _redo in range(MAX_REDOS + 1):
            span = end - a
            grid = (done - a) / span + (end - done) / span * (np.arange(1, points + 1) / points)
            grid[-1] = 1.0
            # (the outputs kept so far and this window's, refused before casadi allocates them: MemoryLimitError)
            check_output_memory("casadi-idas's event search", compiled, 1, sum(len(t) for t in times) + points)
            own = dict(settings)
            if first is not None and first / span < 1e-3 * grid[0]:  # (shorter than IDAS's own first guess)
                own["step0"] = 2.0 ** math.floor(math.log2(first / span))  # (a power of two: few integrators)
            own |= consistent_start(grid[0], own.get("step0"))  # (IDACalcIC's own step, on normalised time)
            integrator = cached_integrator(compiled, "idas", "normalised", 0.0, grid.tolist(), own)
            with captured_output() as printed:
                try:
                    try:
                        found = integrator(x0=y, z0=z, p=np.concatenate([p, [a, span]]))
                    except RuntimeError as error:  # (IDACalcIC failed: a one-off integrator given y' = f)
                        if "IDACalcIC" not in str(error) or struck_limit() is not None:
                            raise
                        stats["initial_slope_fallbacks"] = stats.get("initial_slope_fallbacks", 0) + 1
                        exact = {**own, "calc_ic": False, "init_xdot": (span * slope(a, y, z)).tolist()}
                        scaled = scaled_dae(compiled, "normalised")
                        integrator = casadi.integrator("idas", "idas", scaled, 0.0, grid.tolist(), exact)
                        found = integrator(x0=y, z0=z, p=np.concatenate([p, [a, span]]))
                except DaemodelError:  # (a time limit's signal, raised inside the call: not IDAS's failure)
                    raise
                except RuntimeError as error:
                    failure = struck_limit() or explain(
                        str(error), real_times(printed.getvalue(), a, span), a + span * grid
                    )
                else:
                    failure = None
            stats["search_redos"] += 1
            if failure is not None:
                # (IDAS failed at t: the locked branch may leave the model's domain just past a crossing of its
                # switch, the wheelset's 1.5e-6 after it; the window up to there shows the crossing, if any.
                # IDAS prints t with 6 digits, here of normalised time: the cut is that much before it)
                at = getattr(failure, "t", None)
                if at is None or isinstance(failure, StepLimitError) or struck_limit() is not None or at >= end:
                    raise failure from None
                cut = float(at) - PRINTED_DIGITS * span
                if cut > done:
                    failed, end = failure, cut
                    continue
                if done > t0:  # (failed before the part to read: the pieces go on from `done`, re-locked)
                    return np.concatenate(times), np.concatenate(rows)[None], stats
                # (failed at once: IDACalcIC's scale is the first output's distance; halved)
                halved += 1
                if halved > START_HALVINGS:
                    raise failure from None
                end = a + 0.5 * (end - a)
                continue
            steps = int(integrator.stats().get("nsteps", 0))
            _add(stats, integrator.stats())
            if stats.get("nsteps", 0) > budget:
                raise StepLimitError(
                    f"casadi-idas: the event search took {stats['nsteps']:,} IDAS steps by t = {end:.6g}, past "
                    f"{DEFAULT_OUTPUT_POINTS} x max_num_steps = {budget:,} (sample 0 of '{compiled.name}'); raise "
                    "max_num_steps or loosen rtol/atol, or shorten t_span",
                    end,
                )
            if OUTPUTS_PER_STEP * (steps - before) <= points:
                break
            if points < MAX_POINTS:
                points = _grid_size(steps - before)
            elif done > a:  # (IDAS starts again from the outputs read: a window from there)
                a, y, z, before, w = done, rows[-1][-1, :n].copy(), rows[-1][-1, n:].copy(), 0, end - done
                first = None
                stats["search_restarts"] += 1
                points = _grid_size(steps)
            else:
                end = a + 0.5 * (end - a)
        else:
            raise StepLimitError(
                f"casadi-idas: the event search's window from t = {done:.6g} was solved again {MAX_REDOS} times for "
                f"{OUTPUTS_PER_STEP} outputs a step (sample 0 of '{compiled.name}'): IDAS's steps there shrink "
                "without end; shorten t_span before it",
                done,
            )
        stats["search_redos"] -= 1  # (the window's last solve is no redo)
        stats["search_windows"] += 1
        X, Zs = np.asarray(found["xf"]).T.reshape(points, n), np.asarray(found["zf"]).T.reshape(points, -1)
        T = a + (end - a) * grid
        T[-1] = end
        times.append(T)
        rows.append(np.concatenate([X, Zs], axis=1))
        if stop(T, X, Zs, None):
            break
        if failed is not None:
            if done == t0:  # (no crossing before IDAS's failure in the solve's first window: the model's own)
                raise failed from None
            break  # (the pieces go on from the window's end, their switches locked again there)
        # (the next window twice as long from `a`, its new part's grid as fine as this one's steps asked for; or,
        # where IDAS's steps to its first new output would pass half of max_num_steps, its limit per output
        # interval, from `end` again: IDAS starts there)
        points = _grid_size(steps)
        if 2 * steps > max_num_steps:
            a, done, before, w = end, end, 0, end - a
            y, z, first = X[-1].copy(), Zs[-1].copy(), None
            stats["search_restarts"] += 1
        else:
            done, before, w = end, steps, 2.0 * (end - a)
    return np.concatenate(times), np.concatenate(rows)[None], stats


def _add(stats: dict, more: dict) -> None:
    """``stats`` with casadi's counts in ``more`` (``n...``) added, its other numbers the last window's."""
    for key, value in more.items():
        if not isinstance(value, (int, float)) or isinstance(value, bool):
            continue
        stats[key] = stats.get(key, 0) + value if key.startswith("n") else value

"""The first crossing hidden between a piece's outputs: an event function that left its side of zero and came back
between two outputs (:func:`daemodel.solving.between.excursions`), confirmed by a trial solve of the method's own,
and the near misses among them checked against the method's error (:mod:`daemodel.solving.misses`).  Used by
:mod:`daemodel.solving.events`, which locates what this finds."""

from __future__ import annotations

import dataclasses

import numpy as np

from daemodel.solving.between import (
    across,
    armed_outputs,
    dense_crossing,
    dense_states,
    excursions,
    inner_samples,
    on_dense,
)
from daemodel.solving.branches import EXCURSION_BUDGET, excursion_weight
from daemodel.solving.locate import trial_solve
from daemodel.solving.misses import NearMisses


def first_excursion(
    backend, piece, options, batched, P, compiled, when, sol, T, F, Ys, Zs, begin, until, spent, missed, checks, carried
):
    """``(crossing, the trial solves' stats)``: the first excursion (:func:`daemodel.solving.between.excursions`)
    before ``until`` that a trial solve of the method's own confirms (on the other side at its deepest point
    on the dense output), as ``(which, a, b, Fa, Fb, ya, za, the first trial, {which: its side after})``
    for :func:`~daemodel.solving.locate.locate`; None where there is none.  Its crossing is the first one its
    ``direction`` accepts: the one away from its side, else the one back to it.  A switch's excursion is integrated
    through where its ``branches.excursion_weight`` fits in what ``spent[0]`` leaves of ``EXCURSION_BUDGET``
    (adding it).
    A near miss (the method's own solution does not cross) within its error is added to ``missed``
    (:mod:`daemodel.solving.misses`), the stats of the tighter solves that checked them to ``checks``; ``carried``:
    the error the pieces before carry in (:class:`~daemodel.solving.misses.CarriedErrors`)."""
    stats = []
    if sol.dense is None:
        return None, stats

    def read(times):
        return on_dense(sol, compiled, when, P, times)

    def tight(opts, a, tau, ya, za, e):  # (a check's tighter solve: misses.NearMisses)
        value, y, z, solved = trial_solve(backend, piece, opts, batched, P, e, when, a, tau, ya, za)
        checks.append(solved)
        return value, y, z

    near = NearMisses(tight, when, P, options, T[0], Ys[:1], Zs[:1], carried)

    for x in excursions(read, T, F, armed_outputs(F, begin.armed, begin.sides), inner_samples(sol.dense)):
        if x.t >= until:
            if T[x.before] >= until:
                break
            # (its deepest point past the crossing found, in the interval that holds that crossing: it may have
            # left its side before it.  Min(0, 0.01 - (x - 1.02)^2) + Max(0, x - 1.01), x = t: the Max's crossing
            # at 1.01 was located, the Min's at 0.92 not (its deepest point, 1.02, lies past 1.01), and the piece
            # integrated Min's branch 0 over [0.92, 1.01]: 5.7e-4 off at rtol 1e-8, "success")
            if x.near is not None or not across(read, x, until):
                continue
            x = dataclasses.replace(x, t=until)  # (a point on its other side before the crossing found)
        i, e = x.before, x.event
        direction = compiled.events[e].direction
        away = direction == 0 or (direction > 0) == (x.side < 0)  # (its crossing away counts, else the one back)
        if not away and x.near is None and until < T[i + 1] and across(read, x, until):
            # (the crossing back lies past the crossing found, which comes first: the next piece, from there, starts
            # on this function's other side and sees it.  (x - 1)^2 - 0.0064 rising (direction +1) at 1.08 was
            # located before the crossing of Max(0, x - 1.01) at 1.01, which never fired: w 2.4e-3 off, "success")
            continue
        miss = None if x.near is None else near.check(x, compiled.events[e].name, Ys[i : i + 1], Zs[i : i + 1])
        if x.near is not None and miss is None:
            continue
        if compiled.events[e].strict:  # (a switch whose other branch changes less than the tolerance left)
            y, z = dense_states(sol, compiled, np.array([x.t]))
            weight = excursion_weight(compiled, piece, options, P, x.t, y, z, T[i + 1] - T[i])
            if spent[0] + weight <= EXCURSION_BUDGET:
                spent[0] += weight
                continue
        if miss is not None:
            missed.append(miss)
            continue
        ya, za = Ys[i : i + 1], Zs[i : i + 1]
        value, y, z, solved = trial_solve(backend, piece, options, batched, P, e, when, T[i], x.t, ya, za)
        stats.append(solved)
        if np.sign(value) != -x.side:  # (the method's own solution stays on its side: within its error of zero)
            continue
        if away:
            guess = dense_crossing(sol, compiled, when, e, P, T[i], x.t, F[i, e])
            return (e, T[i], x.t, F[i, e], value, ya, za, guess, {e: int(-x.side)}), stats
        guess = dense_crossing(sol, compiled, when, e, P, x.t, T[i + 1], value)
        return (e, x.t, T[i + 1], value, F[i + 1, e], y, z, guess, {e: int(x.side)}), stats
    return None, stats

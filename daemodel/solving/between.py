"""What the event functions do between a solve's outputs, read off its dense output.

:mod:`daemodel.solving.events` scans the event functions at a piece's outputs (each radau step, each
of IDAS's outputs) for a sign change.  Between two outputs it asks the dense output three things:

- where a crossing it found lies (:func:`dense_crossing`): its location's first trial;
- which of several crossings between the same two outputs comes first (:func:`dense_bracket`'s cells);
- whether a function left its side of zero and came back between two outputs, which changes no sign
  at them (:func:`excursions`).  Unseen, the piece (its switches locked to the branch it started on)
  integrated through the other branch's interval on the wrong one and said "success": the part of
  sin t above 0.99, integrated at rtol 1e-10 in radau steps of 0.57, saw 2 of its 4 crossings, the
  integral 1.9e-3 off; casadi-idas, one output a second, 14 of 32 (tests/solving/test_events_edges.py).

Excursions are looked for at samples: the outputs, and where the dense output is cheap to read
(radau's and collocation's polynomials, not a method started again: ``dense.solves_again``)
:data:`EXCURSION_POINTS` more inside each interval.  A sample on the other side than its interval's
two ends is one; so is a local extremum towards zero among the samples (one nearer zero than both
its neighbours, all three on one side), where :data:`EXCURSION_ROUNDS` rounds of
:data:`EXCURSION_GRID` points on the dense output, each about the last round's deepest, and the vertex of the
parabola through each round's deepest point and its neighbours, look for the other side.  The caller
confirms each with a trial solve of the method's own (an excursion inside
the dense output's error is none).  Where each look solves again, an extremum the probes find still on its
side is yielded too, as a near miss with its distance to zero (``Excursion.near``), for
:mod:`daemodel.solving.misses` to check against the method's error; so is, unprobed, an extremum whose
parabola stays short of :data:`HALFWAY` (at its vertex): casadi-idas's search reads about two samples an IDAS
step, which leave the parabola no way past halfway from a peak 10 tolerances from zero, and 2 of the 6
crossings of 0.999999 - sin(t + 1.96) at rtol 1e-7 were counted, "success".  No sampling sees everything: an
excursion both narrower than the samples' spacing and away from any extremum they show is not seen; one
deep enough to matter at the method's tolerance makes an extremum the samples show, unless the function is
that rough between two steps that each met the tolerance.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from daemodel.errors import ConvergenceError

# The first trial of an event's location is where the dense output crosses (dense_crossing): found on
# DENSE_ROUNDS grids of DENSE_POINTS intervals, each inside the last's bracketing interval, then a secant.
# The wheelset at rtol 1e-6: 12.8 trial solves an event without it (1,077 for 84 events), 5.9 with it (480
# for 82); an oscillator, 9.1 -> 4.
DENSE_ROUNDS, DENSE_POINTS = 2, 16
# Samples of the event functions inside each interval of outputs, where the dense output is cheap to read.
EXCURSION_POINTS = 4
# An extremum towards zero among the samples is zoomed into: EXCURSION_ROUNDS grids of EXCURSION_GRID
# intervals, each over the two intervals about the last grid's deepest point (each round 1/8 of the last).
EXCURSION_ROUNDS, EXCURSION_GRID = 3, 16
# An extremum among the samples is zoomed into only where the parabola through it and its neighbours reaches
# below HALFWAY of the nearest one's distance to zero: every extremum zoomed into cost the wheelset under
# casadi-idas (each look IDAS started again) 73 s instead of 21, and an oscillator's 955 peaks that never
# cross 0.9 s of radau's 1.3.
HALFWAY = 0.5
# Where each look solves again, an extremum is probed at most this many times, at the vertex of the parabola
# through the three points nearest zero (casadi-idas on an oscillator whose switch never crosses: 3 grids of
# 17 looks a peak made it 7 x slower).
EXCURSION_PROBES = 4


# (the mark of an extremum among samples that each solve again whose parabola stays on its side: excursions)
NEAR = "near"


def dense_states(sol, compiled, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(Y (K, n), Z (K, m))`` of ``compiled``'s variables on ``sol``'s dense output at ``times``."""
    U = sol.columns_at(times, (*compiled.state_names, *compiled.algebraic_names))
    return U[:, : len(compiled.state_names)], U[:, len(compiled.state_names) :]


def on_dense(sol, compiled, when, P, times: np.ndarray) -> np.ndarray:
    """The event functions ``when`` on ``sol``'s dense output at ``times``: (K, E)."""
    Y, Z = dense_states(sol, compiled, times)
    return when(times, Y, Z, np.repeat(P, len(times), axis=0))


def inner_samples(dense) -> int:
    """Samples :func:`excursions` reads inside each interval of outputs on ``dense``: none where reading
    it solves again (a method started again from an output), else :data:`EXCURSION_POINTS`."""
    return 0 if dense is None or getattr(dense, "solves_again", False) else EXCURSION_POINTS


def dense_bracket(sol, compiled, when, which, P, a: float, b: float, Fa: float) -> tuple | None:
    """``(lo, hi, F(lo), F(hi))``: the cell of :data:`DENSE_ROUNDS` rounds of :data:`DENSE_POINTS` points
    on ``sol``'s dense output, each within the last, where the event function ``which`` first leaves
    ``Fa``'s side between ``a`` and ``b``; None without a dense output or a sign change on it.  Events
    that cross at one instant share their cells, whatever their functions' slopes there."""
    if sol.dense is None or not (sol.t[0] <= a < b <= sol.t[-1]):
        return None
    lo, hi = a, b
    for _ in range(DENSE_ROUNDS):
        grid = np.linspace(lo, hi, DENSE_POINTS + 1)
        try:
            F = on_dense(sol, compiled, when, P, grid)[:, which]
        except ConvergenceError:  # (a method started again that fails there: no guess, the trial solves locate)
            return None
        other = np.flatnonzero((np.sign(F) != np.sign(Fa)) & (F != 0))
        if not len(other) or other[0] == 0:
            return None
        k = int(other[0])
        lo, hi, f_lo, f_hi = grid[k - 1], grid[k], F[k - 1], F[k]
    return lo, hi, f_lo, f_hi


def dense_crossing(sol, compiled, when, which, P, a: float, b: float, Fa: float) -> float | None:
    """Where the event function ``which`` first leaves ``Fa``'s side between the outputs ``a`` and ``b`` on
    ``sol``'s dense output (radau's collocation polynomials: between its outputs at the method's stage
    order), the first trial of the location; None without a dense output or a sign change on it.
    :func:`dense_bracket` narrows it, then a secant."""
    bracket = dense_bracket(sol, compiled, when, which, P, a, b, Fa)
    if bracket is None:
        return None
    lo, hi, f_lo, f_hi = bracket
    guess = lo - f_lo * (hi - lo) / (f_hi - f_lo) if f_hi != f_lo else 0.5 * (lo + hi)
    return float(guess) if a < guess < b else None


@dataclass(frozen=True)
class Excursion:
    """An event function on the other side of zero between two outputs on whose sides it agrees."""

    event: int  # which event function
    before: int  # the output before it
    t: float  # the deepest point found on the other side, on the dense output
    side: float  # the side it left (+1 or -1): its sign at the outputs about it
    # None: on the other side at t.  A distance: a near miss, found where each look solves again (the method's
    # own solution): the probes found no crossing, the function is this far from zero at t, its nearest point
    # (:mod:`daemodel.solving.misses` checks whether that is within the method's error)
    near: float | None = None


def excursions(read, T: np.ndarray, F: np.ndarray, checked: np.ndarray, inner: int) -> Iterator[Excursion]:
    """The excursions (see the module docstring) of the event functions between the outputs ``T`` (values
    ``F``, (len(T), E)), earliest sample first.  ``read(times) -> (K, E)``: the functions on the dense
    output (it may raise :class:`~daemodel.errors.ConvergenceError`: not seen there); ``inner``: samples
    read inside each interval (0 where reading solves again); ``checked[j, e]``: whether the scan reads
    the function ``e`` at output ``j`` (False where it is not yet armed).  Lazy: each is zoomed into as
    it is asked for, so that a caller that takes the first confirmed one pays for no other."""
    if len(T) < 2 or not checked.any():
        return
    T, F = np.asarray(T, dtype=float), np.asarray(F, dtype=float)
    owner = np.repeat(np.arange(len(T) - 1), inner + 1)  # (each sample's interval: an output, then those inside)
    times = (T[:-1, None] + np.diff(T)[:, None] * (np.arange(inner + 1) / (inner + 1))).ravel()
    G = np.repeat(F[:-1], inner + 1, axis=0)
    if inner:
        at = np.flatnonzero(np.arange(len(times)) % (inner + 1))
        try:
            G[at] = read(times[at])
        except ConvergenceError:
            return
    times, owner, G = np.append(times, T[-1]), np.append(owner, len(T) - 2), np.vstack([G, F[-1:]])
    # an interval is read where the scan reads both ends and they are on one side of zero
    side = np.sign(F[:-1]) * ((np.sign(F[:-1]) == np.sign(F[1:])) & checked[:-1] & checked[1:])
    sample_side = side[owner]
    found = []
    k = np.arange(1, len(times) - 1)
    for e in range(F.shape[1]):
        s, g = sample_side[:, e], G[:, e]
        other = np.flatnonzero((s != 0) & (np.sign(g) == -s))
        if len(other):
            found.append((int(other[0]), e, None))
        # local extrema towards zero, all three samples on their intervals' side
        deeper = (s[k] != 0) & (s[k - 1] == s[k]) & (s[k + 1] == s[k])
        deeper &= (np.sign(g[k - 1]) == s[k]) & (np.sign(g[k]) == s[k]) & (np.sign(g[k + 1]) == s[k])
        deeper &= (s[k] * g[k] < s[k] * g[k - 1]) & (s[k] * g[k] <= s[k] * g[k + 1])
        past = _past_halfway((times[k - 1], times[k], times[k + 1]), (g[k - 1], g[k], g[k + 1]), s[k], 1)[0]
        found += [(int(j), e, slice(j - 1, j + 2)) for j in k[deeper & past]]
        if not inner:  # (each look solves again: an extremum the parabola keeps on its side is a near miss there)
            found += [(int(j), e, NEAR) for j in k[deeper & ~past]]
        found += [(j, e, window) for j, window in _edge_extrema(times, s, g)]
    for j, e, window in sorted(found, key=lambda item: (times[item[0]], item[1])):
        s = float(sample_side[j, e])
        # (an extremum at the first or last sample, which has one neighbour here: its other lies in the
        # scan before or after, so only the interval inside this one is looked into)
        lo, hi = max(j - 1, 0), min(j + 1, len(times) - 1)
        if window is NEAR:  # (the parabola's vertex, unread: misses.NearMisses decides whether it is near zero)
            _, vertex, value = parabola(*times[j - 1 : j + 2].astype(float), *G[j - 1 : j + 2, e].astype(float))
            t = min(max(float(vertex), float(times[j - 1])), float(times[j + 1]))
            yield Excursion(e, int(np.searchsorted(T, t, side="right") - 1), t, s, near=abs(float(value)))
            continue
        if window is None:  # (a sample on the other side)
            t = float(times[j])
        elif inner:
            t = _zoom(read, e, s, float(times[lo]), float(times[hi]))
        else:  # (each look solves again: a few probes at the parabola's vertex, not grids)
            probed = _probe(read, e, s, times[window].astype(float), G[window, e].astype(float))
            if probed is None:
                continue
            t, value = probed
            if s * value >= 0:  # (no crossing: the nearest point the probes found, a near miss)
                yield Excursion(e, int(np.searchsorted(T, t, side="right") - 1), t, s, near=abs(value))
                continue
        if t is not None:
            yield Excursion(e, int(np.searchsorted(T, t, side="right") - 1), t, s)


def _edge_extrema(times: np.ndarray, s: np.ndarray, g: np.ndarray) -> list:
    """``[(j, window)]``: the first and last samples ``j`` (0, ``len(times) - 1``) where the event function's
    extremum towards zero lies between them and their one neighbour, each with the three samples at its end
    (``window``, a slice of ``times``): the sample nearer zero than that neighbour, the three on one side,
    and the parabola through them turning inside that end's interval past :data:`HALFWAY` to zero
    (:func:`_past_halfway`).  (The scan before or after reads the other side of an output: neither saw the
    hump of sin t above 0.99999 whose peak fell 0.01 after an output, at rtol 1e-11 with five stages.)"""
    out = []
    if len(times) < 3:
        return out
    for j, window, nearest in ((0, slice(0, 3), 0), (len(times) - 1, slice(len(times) - 3, None), 2)):
        near = j + 1 if j == 0 else j - 1  # (the end's one neighbour)
        side = s[j]
        if side == 0 or not (np.all(s[window] == side) and np.all(np.sign(g[window]) == side)):
            continue
        # (at the first sample a tie with its neighbour counts: the interior test takes only a tie on its right)
        if not (side * g[j] <= side * g[near] if j == 0 else side * g[j] < side * g[near]):
            continue
        past, vertex = _past_halfway(tuple(times[window]), tuple(g[window]), side, nearest)
        if past and min(times[j], times[near]) < vertex < max(times[j], times[near]):
            out.append((j, window))
    return out


def _past_halfway(t: tuple, g: tuple, side, nearest: int) -> tuple:
    """``(whether, the vertex's time)``: whether the parabola through the three samples ``(t[i], g[i])`` (each
    a float, or arrays of as many triples), all on ``side`` of zero, turns towards zero and reaches past
    :data:`HALFWAY` of the distance to zero of its sample ``nearest`` (0, 1 or 2: the one nearest zero).
    The one test of the extrema :func:`excursions` looks into, inside a scan and at its ends."""
    curve, vertex, value = parabola(*t, *g)
    return (side * curve > 0) & (side * value < HALFWAY * side * g[nearest]), vertex


def armed_outputs(F: np.ndarray, armed, sides) -> np.ndarray:
    """``[j, e]``: whether the scan of :mod:`daemodel.solving.events` reads the event function ``e`` at
    output ``j`` (values ``F``): one not ``armed`` (nor given its side) where the piece starts is read
    from the first two outputs in a row on one side of zero."""
    checked = np.ones(F.shape, dtype=bool)
    for e in range(F.shape[1]):
        if armed[e] or sides[e]:
            continue
        s = np.sign(F[:, e])
        same = np.flatnonzero((s[1:] == s[:-1]) & (s[1:] != 0))
        checked[: same[0] if len(same) else len(s), e] = False
    return checked


def joined_blocks(blocks: list):
    """The dense output of consecutive blocks of one solve: one block's own, or, of blocks of
    :class:`~daemodel.dense.CollocationPolynomials` (radau's), theirs with their steps one after another."""
    from daemodel.dense import CollocationPolynomials

    if len(blocks) == 1:
        return blocks[0]
    if not all(isinstance(b, CollocationPolynomials) for b in blocks):
        raise TypeError("joined_blocks: blocks of one solve's collocation polynomials only")  # (daemodel's own bug)
    return CollocationPolynomials.joined(blocks)


def block_excursion(dense, columns, when, P, n: int, T: np.ndarray, F: np.ndarray, armed: np.ndarray, counts) -> bool:
    """Whether a stopping method's block of outputs ``T`` (the output before it first; ``F`` the event
    functions there) shows an excursion of a function ``armed`` on its dense output ``dense`` (values in
    the method's order; ``columns`` reorders them to the model's, ``n`` states first) that
    ``counts(excursion, y (1, n), z (1, m), the step's length)`` accepts."""

    def states(at):
        V = dense(at)[0][:, columns]
        return V[:, :n], V[:, n:]

    def read(at):
        return when(at, *states(at), np.repeat(P, len(at), axis=0))

    checked = np.repeat(armed[None, :], len(T), axis=0)
    for x in excursions(read, T, F, checked, inner_samples(dense)):
        if x.near is None and counts(x, *states(np.array([x.t])), T[x.before + 1] - T[x.before]):
            return True
    return False


def parabola(t0, t1, t2, g0, g1, g2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(curvature, vertex time, vertex value)`` of the parabola through ``(t0, g0), (t1, g1), (t2, g2)``
    (arrays or floats); where it is a line, curvature 0 at ``(t1, g1)``."""
    slope = (g1 - g0) / (t1 - t0)
    curve = ((g2 - g1) / (t2 - t1) - slope) / (t2 - t0)
    with np.errstate(divide="ignore", invalid="ignore"):
        at = np.where(curve != 0, 0.5 * (t0 + t1) - 0.5 * slope / curve, t1)
    return curve, at, np.where(curve != 0, g0 + (at - t0) * slope + curve * (at - t0) * (at - t1), g1)


def _probe(read, e: int, side: float, t: np.ndarray, g: np.ndarray) -> tuple[float, float] | None:
    """``(t, F)``: where the event function ``e`` is on the other side than ``side``, looked for by successive
    parabolic interpolation from the three samples ``(t, g)`` about a local extremum towards zero: each of
    :data:`EXCURSION_PROBES` probes at the vertex of the parabola through the three nearest zero, on the
    dense output (``read``).  Where none is (or the vertex stops moving), the point read nearest zero, still on
    ``side``; None where the samples show no extremum towards zero or a read fails."""
    t, g = list(t), list(g)
    nearest = None  # (the point read nearest zero)
    for _ in range(EXCURSION_PROBES):
        curve, vertex, _ = parabola(*t, *g)
        if not side * curve > 0:  # (no extremum towards zero between them)
            return nearest
        at = min(max(float(vertex), t[0]), t[2])
        if min(abs(at - x) for x in t) <= 1e-6 * (t[2] - t[0]):  # (the vertex stopped moving)
            return nearest
        try:
            value = float(read(np.array([at]))[0, e])
        except ConvergenceError:  # (a method started again that fails there: not seen)
            return None
        if side * value < 0 or nearest is None or side * value < side * nearest[1]:
            nearest = (at, value)
        if side * value < 0:
            return nearest
        points = sorted(zip([*t, at], [*g, value], strict=True))
        k = min(range(1, 3), key=lambda i: side * points[i][1])  # (the nearest zero, with a neighbour each side)
        k = min(max(k, 1), 2)
        t, g = [p[0] for p in points[k - 1 : k + 2]], [p[1] for p in points[k - 1 : k + 2]]
    return nearest


def _zoom(read, e: int, side: float, lo: float, hi: float) -> float | None:
    """The deepest point on the other side than ``side`` of the event function ``e`` found by
    :data:`EXCURSION_ROUNDS` rounds of :data:`EXCURSION_GRID` points on the dense output (``read``) over
    ``[lo, hi]``, each about the last's deepest (or the vertex of the parabola through a round's deepest point
    and its neighbours, where that is on the other side); None where every point stays on ``side``."""
    for _ in range(EXCURSION_ROUNDS):
        grid = np.linspace(lo, hi, EXCURSION_GRID + 1)
        try:
            g = side * read(grid)[:, e]
        except ConvergenceError:  # (a method started again that fails there: not seen)
            return None
        k = int(np.argmin(g))
        if g[k] < 0:
            return float(grid[k])
        # (and the vertex of the parabola through the deepest point and its neighbours: an excursion narrower
        # than a grid's spacing about it.  (t - 1)^2 - 1e-8 below zero for 2e-4 about t = 1, between radau steps
        # of 0.4 at rtol 1e-12 (exact there: a parabola), was missed by the grids, and y' = 3 instead of 1 over it
        # left y 4e-4 off, "success")
        j = min(max(k, 1), EXCURSION_GRID - 1)
        curve, vertex, _ = parabola(*grid[j - 1 : j + 2], *g[j - 1 : j + 2])
        if curve > 0 and grid[j - 1] < vertex < grid[j + 1]:
            try:
                deepest = side * float(read(np.array([vertex]))[0, e])
            except ConvergenceError:
                return None
            if deepest < 0:
                return float(vertex)
        lo, hi = grid[max(k - 1, 0)], grid[min(k + 1, EXCURSION_GRID)]
    return None


def earliest_tied(sol, compiled, when, P, tied: list, a: float, b: float, Fa: np.ndarray, which: int) -> int:
    """Of the events ``tied`` whose first crossing lies between the same two outputs ``a`` and ``b``
    (``Fa``: every event function at ``a``), the one that crosses first on ``sol``'s dense output, in
    :func:`dense_bracket`'s cells (events that cross in one cell: the first declared, whose
    location the
    others join, so that a root as flat as tanh(y)^3's at y's is never the one located); ``which``, the
    first declared, where there is one or the dense output does not tell.  A step that holds two
    crossings once located the first declared one and fired the earlier with it, late (a state 0.0134
    off at rtol 1e-8, said "success": tests/solving/test_events.py)."""
    if len(tied) < 2:
        return which
    cells = {e: dense_bracket(sol, compiled, when, e, P, a, b, Fa[e]) for e in tied}
    known = {e: cell[1] for e, cell in cells.items() if cell is not None}
    return min(known, key=lambda e: (known[e], e)) if len(known) == len(tied) else which


def across(read, x, t: float) -> bool:
    """Whether the excursion ``x``'s function is on its other side at ``t`` on the dense output (``read``)."""
    try:
        value = read(np.array([t]))[0, x.event]
    except ConvergenceError:  # (not seen there)
        return False
    return bool(np.sign(value) == -x.side)

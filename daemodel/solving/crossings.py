"""Where an event function crosses zero: the scan of a piece's outputs for the first sign change its
way (:func:`first_crossing`, :class:`Crossings`, fed block by block), and the search's ``stop`` that
ends a stopping method's solve there, or at a crossing and crossing back inside a block
(:func:`crossing_stop`).  Used by :mod:`daemodel.solving.events`."""

from __future__ import annotations

import numpy as np

from daemodel.dense import CollocationPolynomials
from daemodel.solving.between import block_excursion, joined_blocks
from daemodel.solving.branches import EXCURSION_BUDGET, SHORTEST_TOLS, excursion_weight, resolution


def settled(F: np.ndarray, times: np.ndarray, start: float, begin) -> np.ndarray:
    """``F`` (T, E) with the functions of the declared events reset where a piece starts (``begin.reset``, each
    read back to its side by :func:`~daemodel.solving.branches.start_piece`) read as zero, no side, at the outputs
    within :data:`SHORTEST_TOLS` float64 resolutions of t after the piece's ``start`` (within the shortest
    look-ahead that side was read over): an event located to t's spacing leaves its function off zero by its rate
    times that.  The ball's impact at t0 = 1e12 (spacing 1.2e-4), located 2 spacings late, left h at -7.6e-4,
    still below the floor at casadi-idas's next outputs (1 spacing on, some at the same t): read as a fall
    through it with no time between to look at, an EventLocationError.  Past the window the function is on its
    side or crosses as any (where |t| < 1e3 the window is below 2e-12)."""
    if not begin.reset:
        return F
    near = np.asarray(times, dtype=float) - start <= SHORTEST_TOLS * resolution(start)
    if not near.any():
        return F
    F = np.array(F, dtype=float, copy=True)
    F[np.ix_(near, sorted(begin.reset))] = 0.0
    return F


def first_crossing(values: np.ndarray, direction: int, armed: bool, side: float = 0.0) -> np.ndarray:
    """``[j, i]``: the first output j where the function is on the other side of zero (in
    ``direction``) than at output i, the last before it off zero (values exactly 0 have no side: a
    function that stays on zero crosses nothing); empty where there is none.  ``armed`` False: not
    until it has left zero and stayed on one side; ``side`` (+1 or -1): the side the function
    starts on, whatever its first value (a switch just crossed)."""
    return Crossings(direction, armed, side).feed(values)


class Crossings:
    """:func:`first_crossing`'s scan, fed the outputs in blocks as a solve makes them: :meth:`feed` returns
    the first crossing ``[j, i]`` (output numbers from the first value fed) once a block holds it.
    The scan reads each value once, in order, so the crossing found is the one :func:`first_crossing`
    finds over all of them."""

    def __init__(self, direction: int, armed: bool, side: float = 0.0):
        self.direction, self.side = direction, side
        self.armed = armed or bool(side)
        self.current, self.at, self.count = side, 0, 0

    def feed(self, values: np.ndarray) -> np.ndarray:
        """The first crossing so far (see :func:`first_crossing`), after ``values`` (the next outputs')."""
        for value in np.sign(np.asarray(values, dtype=float)):
            j = self.count
            self.count += 1
            if j == 0:
                self.current = self.side if self.side else value
                continue
            if value == 0:
                continue
            if not self.armed:
                self.armed = value == self.current
                self.current, self.at = value, j
                continue
            if self.current != 0 and value != self.current:
                if self.direction == 0 or (self.direction > 0) == (value > self.current):
                    return np.array([j, self.at], dtype=int)
            self.current, self.at = value, j
        return np.zeros(0, dtype=int)


# The search reads between the outputs of a stopping method's blocks (between.block_excursion) once they hold
# this many steps together: a crossing and crossing back found up to that many steps late, for a fraction of
# the per-step cost (an oscillator of 4 states: 60 us a step read one by one, as much as the step itself).
EXCURSION_BATCH = 16


def crossing_stop(compiled, begin, P, options, spent: list, clean: list):
    """The search's ``stop`` for a search's solve: given the backend's names, a function of each block
    of outputs, True once an event function has crossed zero its way in the outputs so far (as
    :func:`first_crossing` finds it over all of them) or, on the block's dense output, left its side and come
    back (:func:`daemodel.solving.between.block_excursion`), so that the solve ends there, not at t1 (the
    wheelset's searches once solved the rest of t_span: 285,000 of the solve's 291,665 steps).  ``spent``:
    the tolerance the switches' excursions integrated through have used (``[float]``, added to);
    ``clean``: the time up to which the blocks were read between and held none (``[float]``, set)."""
    events, start = compiled.events, clean[0]
    wanted = (*compiled.state_names, *compiled.algebraic_names)
    n = len(compiled.state_names)
    armed = np.array([bool(begin.armed[k]) or bool(begin.sides[k]) for k in range(len(events))], dtype=bool)

    def counts(x, y, z, span) -> bool:  # (an excursion the search stops for; one it integrates through is spent)
        if not events[x.event].strict:
            return True
        weight = excursion_weight(compiled, begin.model, options, P, x.t, y, z, span)
        if spent[0] + weight > EXCURSION_BUDGET:
            return True
        spent[0] += weight
        return False

    def make(names):
        position = {v: k for k, v in enumerate((*names[0], *names[1]))}
        if any(v not in position for v in wanted):
            return lambda times, Y, Z, dense=None: False  # (outputs the search does not read as its own: no stop)
        columns = np.array([position[v] for v in wanted], dtype=int)
        scans = [Crossings(e.direction, bool(begin.armed[k]), begin.sides[k]) for k, e in enumerate(events)]
        last, pending = [], []  # (the output before the blocks not yet read between; those blocks)

        def stop(times, Y, Z, dense=None) -> bool:
            U = np.concatenate([Y, Z], axis=1)[:, columns]
            F = settled(begin.when(times, U[:, :n], U[:, n:], np.repeat(P, len(times), axis=0)), times, start, begin)
            if any(len(scan.feed(F[:, k])) for k, scan in enumerate(scans)):
                return True
            found = False
            if dense is not None and last and armed.any():
                pending.append((dense, times, F))
                batched = isinstance(dense, CollocationPolynomials)  # (read between in batches of steps)
                if not batched or sum(len(block[1]) for block in pending) >= EXCURSION_BATCH:
                    dense = joined_blocks([block[0] for block in pending])
                    T_block = np.concatenate([[last[0]], *(block[1] for block in pending)])
                    F_block = np.vstack([last[1], *(block[2] for block in pending)])
                    found = block_excursion(dense, columns, begin.when, P, n, T_block, F_block, armed, counts)
                    pending.clear()
                    if not found and armed.all():  # (read between up to there: the search after the solve need not)
                        clean[0] = float(T_block[-1])
            if not pending:
                last[:] = [times[-1], F[-1:]]
            return found

        return stop

    return make

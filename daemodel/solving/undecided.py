"""Crossings within the method's error: an event function whose extremum lies within the method's error of zero
crosses there twice or not at all, and the method's own solution decides which by its error.

:mod:`daemodel.solving.misses` checks the near misses that casadi-idas's probes find (the method's function comes
close without crossing).  The symmetric case went unchecked: a ball with air drag (h' = v, v' = -9.81 - 0.5 v|v|,
v -> -0.8 v at h = 0) and an event on h - L, L within 1e-6..1e-9 of its third apex (0.09496), at rtol = atol = 1e-6
recorded 7 crossings under casadi-idas and the reference method where the exact solution has 5 (L above the apex),
and radau 6 (one of the two about the apex) where it has 7, each "success" (tests/solving/test_undecided.py).

After the solve (:func:`audit`), each event without a reset is read at the method's outputs (and, where its dense
output is an evaluation, :data:`~daemodel.solving.between.EXCURSION_POINTS` points inside each interval): a run of
consecutive samples within :data:`~daemodel.solving.misses.NEAR_MISS_TOLS` tolerances of zero (in what a tolerance
of the variables moves the function: :func:`~daemodel.solving.misses.function_tolerance`) that holds a recorded
crossing is decided by the method only where it is one crossing from one side to the other.  Any other run (a hump
crossed twice, once, or more; one that reaches the end of the span; a hump not crossed whose samples come within the
band) is checked by the whole solve again :data:`~daemodel.solving.misses.TIGHTER` times tighter (once a solve,
whatever the runs): the run's crossings stand where that solve records as many in it and, at the run's extremum
(its sample furthest past zero, or the midpoint of two crossings), is past zero (or, with none, on its side) by more
than its own error (1/TIGHTER of the two solves' difference there) and tolerance.  Else the status says so, never
"success".  Events whose reset sets a state their function or its rate depends on (a bounce: h at zero, v -> -e v)
are not read: the reset sends their function back from zero by design.
Nor are the switches on variables but floor and ceiling (read as their argument's signed distance to the nearest
integer, which crosses zero where it reaches one): a continuous one (Max, Abs) that the method's error takes
across zero changes nothing beyond it (:mod:`daemodel.solving.resting` weighs its branches where it rests there),
and one that jumps (sign, Heaviside) is refused where it rests.  A floor of a state that decays onto an integer
(x = 2.5 e^-t, floor(x) 0 from t = log 2.5 on) recorded 15 crossings of 0 from t = 21.9 to 57.7 under casadi-idas at
rtol 1e-8 (its x within 1e-12 of zero, the exact 8e-10 to 2e-25 above it), "success".
"""

from __future__ import annotations

import numpy as np

from daemodel.errors import ModelError, SolverError, TimeLimitError
from daemodel.solving.between import inner_samples, parabola
from daemodel.solving.branches import reset_keeps_motion
from daemodel.solving.misses import NEAR_MISS_TOLS, TIGHTER


def tolerances(when, options, T: np.ndarray, V: np.ndarray, n: int, P: np.ndarray) -> np.ndarray:
    """(K, E): how far one tolerance of ``options`` moves each event function at the times ``T`` (K,) with
    variables ``V`` (K, n + m), as :func:`~daemodel.solving.misses.function_tolerance` at each (vectorised)."""
    step = options.atol + options.rtol * np.abs(V)
    alternate = 1 - 2 * (np.arange(V.shape[1]) % 2)
    K = len(T)
    W = np.concatenate([V, V + step, V + step * alternate])
    F = when(np.tile(T, 3), W[:, :n], W[:, n:], np.repeat(P, 3 * K, axis=0))
    return np.maximum(np.abs(F[K : 2 * K] - F[:K]), np.abs(F[2 * K :] - F[:K]))


def _samples(sol, names: tuple) -> tuple[np.ndarray, np.ndarray]:
    """``(T (K,), V (K, len(names)))``: ``sol``'s outputs, and inside each interval the dense output's points where
    reading it is an evaluation (not a method started again)."""
    T = np.asarray(sol.t, dtype=float).reshape(-1)
    V = np.stack([np.asarray(sol.values[v], dtype=float).reshape(-1) for v in names], axis=1)
    inner = inner_samples(sol.dense)
    gaps = np.diff(T)
    if not inner or not len(gaps) or not np.all(gaps > 0):
        return T, V
    inside = (T[:-1, None] + gaps[:, None] * (np.arange(1, inner + 1) / (inner + 1))).ravel()
    T_all = np.concatenate([T, inside])
    order = np.argsort(T_all, kind="stable")
    return T_all[order], np.concatenate([V, sol.columns_at(inside, names)])[order]


def _vertices(T: np.ndarray, F: np.ndarray, band: np.ndarray) -> np.ndarray:
    """The times, strictly between samples ``T`` (K,), of the vertices of the parabolas through three samples of a
    function ``F[:, j]`` (K, J) about a local extremum towards zero (all three on one side) that reach within
    ``band`` (K, J) of zero: a hump whose samples stay outside the band (radau's steps over an apex) is seen."""
    if len(T) < 3:
        return np.zeros(0)
    t0, t1, t2 = T[:-2, None], T[1:-1, None], T[2:, None]
    g0, g1, g2 = F[:-2], F[1:-1], F[2:]
    s = np.sign(g1)
    towards = (s != 0) & (np.sign(g0) == s) & (np.sign(g2) == s) & (s * g1 < s * g0) & (s * g1 <= s * g2)
    towards &= (t0 < t1) & (t1 < t2)  # (a crossing's sample beside an output at its time: no parabola)
    with np.errstate(divide="ignore", invalid="ignore"):
        _, vertex, value = parabola(t0, t1, t2, g0, g1, g2)
    near = towards & (np.abs(value) <= band[1:-1]) & (vertex > t0) & (vertex < t2) & (vertex != t1)
    return np.unique(np.broadcast_to(vertex, near.shape)[near])


def _runs(inside: np.ndarray) -> list[tuple[int, int]]:
    """``[(first, last)]``: the runs of consecutive True in ``inside``."""
    edges = np.diff(np.concatenate([[0], inside.astype(int), [0]]))
    return list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1, strict=True))


def audit(sol, compiled, when, options, P: np.ndarray, tighter_solve) -> list[str]:
    """The statuses of the runs of ``sol`` (the method's solution, its events recorded) whose crossings lie within
    the method's error and that a solve :data:`TIGHTER` times tighter does not confirm (see the module docstring).
    ``tighter_solve() -> Solution``: that solve, with its events (called at most once, where a run asks).  Empty
    for a method without rtol and atol."""
    if getattr(options, "rtol", None) is None or getattr(options, "atol", None) is None:
        return []
    which = [e for e, event in enumerate(compiled.events) if _read(compiled, event)]
    if not which or len(np.asarray(sol.t).reshape(-1)) < 2:
        return []
    names = (*compiled.state_names, *compiled.algebraic_names)
    n = len(compiled.state_names)
    base_T, base_V = _samples(sol, names)
    tight, statuses = [], []

    def values(solution, t: np.ndarray, e: int) -> np.ndarray:
        u = solution.columns_at(t, names)
        return when(t, u[:, :n], u[:, n:], np.repeat(P, len(t), axis=0))[:, e]

    for e in which:
        event = compiled.events[e]
        record = sol.events[event.name]
        crossed = np.asarray(record["t"], dtype=float).reshape(-1)
        T, V = _with_crossings(sol, names, base_T, base_V, crossed, record["before"])
        F = when(T, V[:, :n], V[:, n:], np.repeat(P, len(T), axis=0))
        band = NEAR_MISS_TOLS * tolerances(when, options, T, V, n, P)[:, e]
        F = F[:, e]
        near = F - np.round(F) if event.integer else F  # (a floor's argument: its distance to the nearest integer)
        vertices = _vertices(T, near[:, None], band[:, None])
        if len(vertices):  # (an extremum between samples that its parabola puts within the band: read there too)
            T, V = _merged(T, V, vertices, sol.columns_at(vertices, names))
            F = when(T, V[:, :n], V[:, n:], np.repeat(P, len(T), axis=0))
            band = NEAR_MISS_TOLS * tolerances(when, options, T, V, n, P)[:, e]
            F = F[:, e]
            near = F - np.round(F) if event.integer else F
        for first, last in _runs(np.abs(near) <= band):
            level = float(np.round(F[first])) if event.integer else 0.0  # (the integer it comes near)
            lo = T[first - 1] if first > 0 else -np.inf
            hi = T[last + 1] if last + 1 < len(T) else np.inf
            inner = crossed[(crossed > lo) & (crossed < hi)]
            left = F[first - 1] - level if first > 0 else 0.0
            right = F[last + 1] - level if last + 1 < len(T) else 0.0
            side = np.sign(left) or np.sign(right) or 1.0
            if len(inner) == 1 and left * right <= 0:
                continue  # (one crossing from one side to the other, or one at an end of the span: none read past it)
            if not len(inner) and left * right <= 0:  # (none recorded: only a hump with one side about it is checked)
                if not _hump_at_an_end(F[first : last + 1] - level, left, right, first == 0, last + 1 == len(T)):
                    continue
                side = np.sign(left) or np.sign(right) or np.sign(F[first] - level)
            if len(inner) == 1 and event.direction:  # (one way only: the other crossing may lie between the samples)
                halves = np.array([0.5 * (lo + inner[0]), 0.5 * (inner[0] + hi)])
                ends = values(sol, halves, e) - level
                if ends[0] * ends[1] < 0 and np.all(np.abs(ends) > np.maximum(band[first - 1], band[last + 1])):
                    continue  # (from one side to the other, each half-way out of the band: decided)
            # (the extremum: the sample furthest past zero, or the midpoint of two crossings, read on the dense output)
            middles = (0.5 * (inner[:-1] + inner[1:]))[:8]
            at = list(zip(T[first : last + 1], F[first : last + 1] - level, strict=True))
            at += list(zip(middles, values(sol, middles, e) - level, strict=True)) if len(middles) else []
            t_star, f_star = (float(v) for v in max(at, key=lambda point: -side * point[1]))
            scale = float(band[first + int(np.argmin(np.abs(T[first : last + 1] - t_star)))]) / NEAR_MISS_TOLS
            if not tight:
                try:
                    tight.append(tighter_solve())
                except TimeLimitError:
                    raise
                except (SolverError, ModelError) as error:
                    tight.append(error)
            checked = tight[0]
            where = (
                f"event '{event.name}' {_crossings(len(inner))} between t = {_time(lo, T[0])} and "
                f"{_time(hi, T[-1])}, where its function stays within {NEAR_MISS_TOLS} tolerances of "
                f"{'zero' if not event.integer else f'the integer {level:.0f}'} in {sol.method}'s solution "
                f"({f_star:.3g} at t = {t_star:.10g})"
            )
            if isinstance(checked, Exception) or checked.status != "success":
                why = checked if isinstance(checked, Exception) else checked.status
                statuses.append(
                    f"{where}, and a solve {TIGHTER} times tighter, to check it, failed ({why}): "
                    "whether it crosses there is not decided at the method's accuracy; tighten rtol/atol"
                )
                continue
            again = np.asarray(checked.events[event.name]["t"], dtype=float).reshape(-1)
            k = int(np.sum((again > lo) & (again < hi)))
            f_tight = float(values(checked, np.array([t_star]), e)[0]) - level
            error = max(abs(f_star - f_tight) / TIGHTER, scale / TIGHTER)
            past = -side * f_tight > error if len(inner) else side * f_tight > error
            if k == len(inner) and past:
                continue
            statuses.append(
                f"{where}, and a solve {TIGHTER} times tighter {_crossings(k, 'there')}, reaching {f_tight:.3g} "
                f"(its error {error:.3g}): whether it crosses there is not decided at the method's accuracy; tighten "
                "rtol/atol"
            )
    return statuses


def _hump_at_an_end(G: np.ndarray, left: float, right: float, at_start: bool, at_end: bool) -> bool:
    """Whether a run of samples ``G`` (an event function's values less its level) that holds no crossing and
    reaches an end of the span (``at_start``, ``at_end``; ``left``, ``right``: the samples beside it, 0 past an
    end) is a hump: on one side of zero at its ends, and nearer zero inside than at either.  Such a run was not
    read (its missing neighbour taken for 0): x = (t - 1)^2 - 1e-12, crossed at 1 -+ 1e-6, within 1000
    tolerances of zero over the whole span at rtol 1e-3, was counted 0 times by casadi-idas, "success"."""
    if not (at_start or at_end) or not len(G):
        return False
    a = G[0] if at_start else left
    b = G[-1] if at_end else right
    side = np.sign(a)
    if side == 0 or np.sign(b) != side or np.any(np.sign(G) != side):
        return False
    return bool(np.min(side * G) < min(side * a, side * b))


def _read(compiled, event) -> bool:
    """Whether :func:`audit` reads ``event``: a declared one whose reset (if any) sets no state its function or that
    function's rate depends on (a bounce's reset sends its function back from zero by design), or a floor or ceiling
    of a variable."""
    if event.strict:
        return event.integer
    return reset_keeps_motion(compiled, event)


def _merged(T: np.ndarray, V: np.ndarray, times: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The samples ``(T (K,), V (K, N))`` with ``(times, values)`` among them, in time order."""
    T_all = np.concatenate([T, times])
    order = np.argsort(T_all, kind="stable")
    return T_all[order], np.concatenate([V, values])[order]


def _with_crossings(sol, names: tuple, T: np.ndarray, V: np.ndarray, crossed: np.ndarray, before: dict) -> tuple:
    """The samples ``(T, V)`` with an event's recorded crossings ``crossed`` (the values just before each, by name in
    ``before``), and the dense output at the middle of two crossings with no sample between them: each crossing in
    the run of samples about it, and two crossings far apart (on a sparse t_eval) not taken for one run."""
    if not len(crossed):
        return T, V
    at = np.stack([np.asarray(before[v], dtype=float).reshape(-1) for v in names], axis=1)
    T, V = _merged(T, V, crossed, at)
    a, b = crossed[:-1], crossed[1:]
    empty = np.searchsorted(T, b, side="left") == np.searchsorted(T, a, side="right")
    middles = 0.5 * (a + b)[empty & (b > a)]
    return _merged(T, V, middles, sol.columns_at(middles, names)) if len(middles) else (T, V)


def _crossings(k: int, there: str = "") -> str:
    said = "crosses zero once" if k == 1 else f"crosses zero {k} times" if k else "does not cross zero"
    return f"{said} {there}".rstrip()


def _time(t: float, end: float) -> str:
    return f"{end:.10g}" if not np.isfinite(t) else f"{t:.10g}"

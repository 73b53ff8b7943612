"""Errors across events and breakpoints: each side compared on its own branch.

At an event (and at a time breakpoint, where algebraic values may jump) a solution has two values:
the left limit, ``events[name]["before"]``, and the right limit, ``events[name]["after"]``, which is
also its value at that time in ``t``.  Two solves locate the same event at instants that differ by
their accuracy (1e-12 apart at best); between the two instants one holds the value after the reset
and the other the value before it, O(1) apart however accurate both are (a bouncing ball's velocity:
8 m/s).  So :meth:`Solution.errors`, :meth:`Solution.error_report` and :func:`compare` measure:

* the variables at the solution's output times, leaving out those within the window of an instant of
  either side, ``[t - w, t + w]`` with ``w = TIME_MATCH_RTOL * max(span, 1)`` (an output time between
  two instants of the same event further apart than that is measured: one side is after its event
  and the other before, which is the solve's error in timing it);
* the instants themselves, per event name (and ``"time breakpoints"``): ``|t_a - t_b|`` of each
  pair, and the values before against the values before, after against after, each side's at its
  own instant.

A reference callable states its instants by an attribute ``events`` (and ``breakpoints``) laid out
as :attr:`Solution.events` (``Problem.exact_solution()`` does); without one, only the solution's
instants are left out, and there is nothing to pair them with.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from daemodel.errors import ComparisonError

# Times of two solutions count as the same when they differ by less than this, relative to
# the span: grids built as t0 + k*h in different orders differ in the last bits.
TIME_MATCH_RTOL = 1e-9

# The label of a solution's time breakpoints among its event names (which are identifiers).
BREAKPOINTS = "time breakpoints"


@dataclass(frozen=True)
class InstantErrors:
    """One event name's (or the breakpoints') instants on both sides, paired each with its nearest.

    Attributes
    ----------
    count : int
        The solution's instants (summed over the samples of a batch).
    reference_count : int or None
        The reference's inside the solution's span; None for a reference callable that states none.
    t : float
        Max ``|t_a - t_b|`` over the pairs; NaN without pairs.
    before, after : dict name -> float
        Max absolute error of each variable's values just before (just after) the instants, each side's
        at its own instant; NaN without pairs.
    """

    count: int
    reference_count: int | None
    t: float
    before: dict
    after: dict

    @property
    def values(self) -> float:
        """The largest error of the values on either side, over the variables."""
        every = [*self.before.values(), *self.after.values()]
        return float(max(every)) if every and not np.isnan(every).all() else float("nan")


@dataclass(frozen=True)
class ErrorReport:
    """What :meth:`Solution.error_report` measured.

    Attributes
    ----------
    variables : dict name -> {"max": float, "mean": float}
        At the output times outside the instants' windows (what :meth:`Solution.errors` returns).
    instants : dict label -> InstantErrors
        Per event name, and :data:`BREAKPOINTS`; empty where neither side has any.
    excluded : int
        Output values (times, summed over samples) left out of ``variables``.
    window : float
        ``w``, the margin around each instant (see the module docstring).
    """

    variables: dict
    instants: dict
    excluded: int
    window: float


def records_of(source, names, batch: int, side: str) -> dict | None:
    """``label -> (t (B, K), before name -> (B, K), after name -> (B, K))`` of a Solution or a
    reference callable; None for a callable that states no instants.

    Raises
    ------
    ComparisonError
        A callable's ``events``/``breakpoints`` not laid out as :attr:`Solution.events`, or with another
        number of samples than the solution.
    """
    known = any(  # (a Solution's are dicts, empty where it has none)
        getattr(source, key, None) is not None for key in ("events", "breakpoints")
    )
    if not known:
        return None
    events = getattr(source, "events", None) or {}
    breakpoints = getattr(source, "breakpoints", None) or {}
    if not isinstance(events, Mapping) or not isinstance(breakpoints, Mapping):
        raise ComparisonError(
            f"the {side}'s events/breakpoints must be dicts laid out as Solution.events (name -> "
            f"{{'t', 'before', 'after'}}); got {type(events).__name__}, {type(breakpoints).__name__}"
        )
    listed = [(str(name), record) for name, record in events.items()]
    if breakpoints:
        listed.append((BREAKPOINTS, breakpoints))
    out = {}
    for label, record in listed:
        out[label] = _record(record, names, batch, f"the {side}'s {label!r}")
    return out


def _record(record, names, batch: int, where: str) -> tuple:
    def rows(value, what: str) -> np.ndarray:
        try:
            array = np.asarray(value, dtype=float)
        except (TypeError, ValueError):
            array = None
        if array is None or array.ndim not in (1, 2):
            raise ComparisonError(f"{where}: {what} is not a (K,) or (B, K) array of numbers")
        array = array if array.ndim == 2 else array[None, :]
        if len(array) not in (1, batch):
            raise ComparisonError(f"{where}: {what} has {len(array)} rows; the solution has {batch} samples")
        return np.broadcast_to(array, (batch, array.shape[-1]))

    if not isinstance(record, Mapping) or not all(key in record for key in ("t", "before", "after")):
        raise ComparisonError(f"{where} must be a dict with 't', 'before' and 'after', as Solution.events holds")
    t = rows(record["t"], "'t'")
    sides = []
    for key in ("before", "after"):
        if not isinstance(record[key], Mapping):
            raise ComparisonError(f"{where}: {key!r} must be a dict name -> values")
        values = {}
        for name in names:
            if name in record[key]:
                values[name] = rows(record[key][name], f"{key!r} of {name!r}")
                if values[name].shape != t.shape:
                    raise ComparisonError(
                        f"{where}: {key!r} of {name!r} has shape {values[name].shape}, its times {t.shape}"
                    )
        sides.append(values)
    return t, sides[0], sides[1]


def measure(t: np.ndarray, own: dict, theirs: dict | None, names, batch: int) -> tuple[np.ndarray, dict, float]:
    """``(keep (B, T) bool, label -> InstantErrors, w)`` for output times ``t`` of a solution whose
    instants are ``own`` and a reference's ``theirs`` (None: it states none); see the module docstring."""

    span = float(t[-1] - t[0])
    w = TIME_MATCH_RTOL * max(abs(span), 1.0)
    keep = np.ones((batch, len(t)), dtype=bool)
    out = {}
    for label in dict.fromkeys([*own, *(theirs or {})]):
        mine = own.get(label)
        other = None if theirs is None else theirs.get(label)
        count, reference_count, dt = 0, (None if theirs is None else 0), []
        before = {name: [] for name in names}
        after = {name: [] for name in names}
        for b in range(batch):
            ta, pa = _inside(mine, b, t[0] - w, t[-1] + w)
            tb, pb = _inside(other, b, t[0] - w, t[-1] + w)
            count += len(ta)
            if reference_count is not None:
                reference_count += len(tb)
            i, j = _pairs(ta, tb)
            # (only each instant's own neighbourhood: an output time between two paired instants further apart
            # than the window sees one side after its event and the other before, an error of the solve's timing)
            for s in (*ta, *tb):
                keep[b] &= ~((t >= s - w) & (t <= s + w))
            if len(i):
                dt.append(np.abs(ta[i] - tb[j]))
                for side, found in ((before, 1), (after, 2)):
                    for name in names:
                        if name in pa[found] and name in pb[found]:
                            a = mine[found][name][b][pa[0][i]]
                            c = other[found][name][b][pb[0][j]]
                            side[name].append(np.abs(a - c))

        def worst(parts) -> float:
            return float(np.max(np.concatenate(parts))) if parts else float("nan")

        out[label] = InstantErrors(
            count=count,
            reference_count=reference_count,
            t=worst(dt),
            before={name: worst(v) for name, v in before.items() if v},
            after={name: worst(v) for name, v in after.items() if v},
        )
    return keep, out, w


def _pairs(ta: np.ndarray, tb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Indices ``(i, j)`` of the instants of two ascending lists that are each other's nearest: the same
    event on both sides (an instant one side lacks pairs with nothing, and shifts no other pair)."""
    if not len(ta) or not len(tb):
        return np.zeros(0, dtype=int), np.zeros(0, dtype=int)

    def nearest(x: np.ndarray, among: np.ndarray) -> np.ndarray:
        k = np.clip(np.searchsorted(among, x), 1, len(among) - 1) if len(among) > 1 else np.zeros(len(x), dtype=int)
        if len(among) > 1:
            k = np.where(np.abs(among[k - 1] - x) <= np.abs(among[k] - x), k - 1, k)
        return k

    j = nearest(ta, tb)
    i = np.flatnonzero(nearest(tb[j], ta) == np.arange(len(ta)))
    return i, j[i]


def _inside(record, b: int, lo: float, hi: float) -> tuple[np.ndarray, tuple]:
    """The finite instants of sample ``b`` of ``record`` within [lo, hi] (ascending), and
    ``(their indices, before, after)`` of the record (empty without one)."""
    if record is None:
        return np.zeros(0), (np.zeros(0, dtype=int), {}, {})
    t, before, after = record
    row = t[b]
    index = np.flatnonzero(np.isfinite(row) & (row >= lo) & (row <= hi))
    index = index[np.argsort(row[index], kind="stable")]
    return row[index], (index, before, after)

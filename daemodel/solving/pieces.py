"""Solves in pieces joined into one: the pieces' stats merged, samples solved in groups joined in sample
order, the fixed step of a piece, and the states carried across a switch put back onto the constraints.
Shared by the solves from breakpoint to breakpoint (:mod:`daemodel.solving.switches`) and from event to
event (:mod:`daemodel.solving.events`)."""

from __future__ import annotations

import math

import numpy as np

from daemodel.dense import joined_by_samples
from daemodel.errors import SwitchError
from daemodel.stats import padded_with_nan

# Stats summed over segments (counters); keys starting with "max"/ending "_max" take the largest,
# "min"/"_min" the smallest; any other key keeps the first segment's value (stages, engine, ...).
# (a batch's samples joined: its "location_trials", "searches_continued", "near_miss_checks" were the first's)
_COUNTERS = ("steps", "attempts", "rejected", "iterations", "evaluations", "decompositions", "failures",
             "refreshes", "retries", "runs", "setups", "calls", "events", "trials", "continued", "checks")  # fmt: skip


def merge_stats(all_stats: list) -> dict:
    """The stats of pieces solved one after another as one: counters summed, ``max``/``min`` entries
    the largest/smallest, figures per step or segment (lists, arrays) one piece's after another (an
    empty one adds nothing; rows of different widths padded with NaN), anything else the first's."""
    out = {}
    for key in dict.fromkeys(k for stats in all_stats for k in stats):
        values = [stats[key] for stats in all_stats if key in stats]
        if any(isinstance(v, np.ndarray) for v in values) and all(isinstance(v, list | np.ndarray) for v in values):
            # a piece's figures may be an empty list (no step) or rows of another width (the converted
            # stats of a Solution, daemodel.stats.as_arrays): join the non-empty ones as arrays
            values = [np.asarray(v) for v in values if len(v)] or [np.asarray(values[0])]
            values = _same_width(values)
        numeric = all(isinstance(v, int | float | np.integer | np.floating) and not isinstance(v, bool) for v in values)
        if numeric and (key.startswith("max") or key.endswith("_max")):
            out[key] = max(values)
        elif numeric and (key.startswith("min") or key.endswith("_min")):
            out[key] = min(values)
        elif numeric and any(word in key for word in _COUNTERS):
            out[key] = sum(values)
        elif all(isinstance(v, list) for v in values):
            out[key] = [x for v in values for x in v]
        elif all(isinstance(v, np.ndarray) and v.ndim >= 1 for v in values) and len({v.shape[1:] for v in values}) == 1:
            out[key] = np.concatenate(values)  # (per step or segment: the pieces' one after another)
        else:
            out[key] = values[0]
    return out


def _same_width(arrays: list) -> list:
    """2-D float or integer arrays of different widths padded with NaN to the widest (others as they are)."""
    if len(arrays) < 2 or any(a.ndim != 2 or a.dtype.kind not in "fiu" for a in arrays):
        return arrays
    return padded_with_nan(arrays)


def segment_steps(a: float, b: float, h: float) -> float:
    """The step of a fixed grid on [a, b]: equal steps, as few as keep each at most ``h``."""
    return (b - a) / max(1, math.ceil((b - a) / h * (1 - 1e-9)))


def onto_constraints(model, Y: np.ndarray, P: np.ndarray) -> np.ndarray:
    """The states ``Y`` (B, n) where they satisfy ``model``'s z-free constraint levels at its t0, else
    their least-change projection onto them (a switch inside a constraint moves its solution set).

    Raises
    ------
    SwitchError
        No state near a sample's satisfies them after the switch.
    """
    from daemodel.compiling.initial_states import constraint_checks, project_states, state_violations

    hidden = constraint_checks(model).hidden
    if not hidden or not state_violations(model, Y, P)[2].any():
        return Y
    projected = project_states(model, Y, P)
    residual, _, bad = state_violations(model, projected, P)
    if bad.any():
        sample, level = np.argwhere(bad)[0]
        name, label, _ = hidden[level]
        raise SwitchError(
            f"after the switch at t = {model.t0:.10g} no state near sample {sample}'s satisfies {label}: {name} = "
            f"{residual[sample, level]:.6g} after the projection; the switch leaves the constraints without a "
            "real solution there"
        )
    return projected


def _pad(records: list, B: int) -> dict:
    """``(sample indices, record)`` pairs of per-group records (``"t"``, ``"moved"``: (b, k); ``"before"``,
    ``"after"``: name -> (b, k)) as one record over all B samples, padded with NaN to the longest."""
    K = max(record["t"].shape[1] for _, record in records)
    out = {"t": np.full((B, K), np.nan), "moved": np.full((B, K), np.nan), "before": {}, "after": {}}
    for index, record in records:
        k = record["t"].shape[1]
        out["t"][index, :k] = record["t"]
        out["moved"][index, :k] = record["moved"]
        for side in ("before", "after"):
            for name, values in record[side].items():
                out[side].setdefault(name, np.full((B, K), np.nan))[index, :k] = values
    return out


def breakpoints_between(record: dict, a: float, b: float, closed: bool) -> dict:
    """The entries of a breakpoint record (``"t"``, ``"moved"``: (B, K); ``"before"``, ``"after"``: name ->
    (B, K)) at times in ``[a, b)``, ``[a, b]`` where ``closed`` (a piece of a solve with events)."""
    t = record["t"][0]
    keep = (t >= a) & ((t <= b) if closed else (t < b))
    return {
        "t": record["t"][:, keep],
        "moved": record["moved"][:, keep],
        **{side: {name: v[:, keep] for name, v in record[side].items()} for side in ("before", "after")},
    }


def joined_breakpoints(records: list) -> dict:
    """One breakpoint record of the pieces' ``records`` (as :func:`breakpoints_between` returns them, in
    time order); ``{}`` where there are none."""
    if not records:
        return {}

    def joined(get) -> np.ndarray:
        return np.concatenate([get(record) for record in records], axis=1)

    return {
        "t": joined(lambda r: r["t"]),
        "moved": joined(lambda r: r["moved"]),
        **{
            side: {name: joined(lambda r, n=name, s=side: r[s][n]) for name in records[0][side]}
            for side in ("before", "after")
        },
    }


def join_samples(parts: list, B: int, batched: bool):
    """One Solution of the groups' (``(sample indices, Solution)``): values and parameters in sample order,
    breakpoints and events padded with NaN to the longest.  Groups on other output times (a terminal event
    that ends some early, a batch without t_eval: :mod:`daemodel.solving.batches`) are joined on all their
    times, each group's values at the others' times from its dense output (:meth:`Solution.at`: radau's is
    what t_eval evaluates), NaN after its own end where that comes before the last."""
    from daemodel.solution import Solution

    first = parts[0][1]
    t = first.t
    ends = None
    if any(len(sol.t) != len(first.t) or not np.array_equal(sol.t, first.t) for _, sol in parts):
        # (a terminal event ends some samples early: each keeps its own end, NaN after it; the times are
        # all of theirs, each sample's values at the others' times from its dense output)
        t = np.unique(np.concatenate([sol.t for _, sol in parts]))
        last = max(sol.t[-1] for _, sol in parts)
        ends = [sol.t[-1] if sol.t[-1] < last else None for _, sol in parts]
    values = {name: np.full((B, len(t)), np.nan) for name in first.values}
    parameters = np.empty((B, first.parameters.shape[1]))
    for index, sol in parts:
        if ends is None:
            for name in values:
                values[name][index] = sol.values[name]
        else:
            own = np.isin(t, sol.t)
            between = ~own & (t <= sol.t[-1])
            found = sol.at(t[between]) if between.any() else {}
            for name in values:
                row = np.full((len(index), len(t)), np.nan)
                row[:, own] = np.asarray(sol.values[name]).reshape(len(index), -1)
                if between.any():
                    row[:, between] = np.asarray(found[name]).reshape(len(index), -1)
                values[name][index] = row
        parameters[index] = sol.parameters
    # (with events, a sample may end before any breakpoint: its entries NaN)
    marks = [(index, sol.breakpoints) for index, sol in parts if sol.breakpoints]
    breakpoints = _pad(marks, B) if marks else {}
    events = {name: _pad([(index, sol.events[name]) for index, sol in parts], B) for name in first.events}
    stats = merge_stats([sol.stats for _, sol in parts])  # (events: every group's, summed)
    stats["groups"] = len(parts)
    if isinstance(stats.get("batch"), int):  # (each group's solve had its own: the whole is B samples)
        stats["batch"] = B
    if ends is not None:  # (where each sample ended)
        stats["t_end"] = np.empty(B)
        for index, sol in parts:
            stats["t_end"][index] = sol.t[-1]
    failing = [f"samples {index.tolist()}: {sol.status}" for index, sol in parts if sol.status != "success"]
    return Solution(
        t=t,
        values=values,
        method=first.method,
        settings=first.settings,
        solve_time=sum(sol.solve_time for _, sol in parts),
        stats=stats,
        compiled=first.compiled,
        parameters=parameters,
        batched=batched,
        status="success" if not failing else "; ".join(failing),
        setup_time=sum(sol.setup_time for _, sol in parts),
        breakpoints=breakpoints,
        events=events,
        dense=joined_by_samples([(index, sol.dense) for index, sol in parts], B, ends),
    )

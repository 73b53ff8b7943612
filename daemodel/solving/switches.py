"""Switches: where a model's equations change branch, found in the compiled equations.

A switching function is what decides a branch: each relation of a ``Piecewise`` condition
(``lhs - rhs``), the argument of ``Heaviside``, ``sign`` and ``Abs``, the differences of the
arguments of ``Max`` and ``Min``, the argument of ``floor`` and ``ceiling`` (which switch where it
crosses an integer).  One that depends on ``t`` and parameters only switches at *time
breakpoints*, found before the solve (:func:`breakpoints`: in closed form where sympy solves the
equation, else by bracketing sign changes on a fine grid and bisecting); one that depends on a
state or algebraic variable is a *state event*, listed but not yet located.

Across a breakpoint no method keeps its order: a step whose stages straddle the switch sees two
different right-hand sides, and the step that ends at it evaluates its last stage (c_s = 1) on the
branch after it.  :func:`solve_with_breakpoints` therefore integrates from breakpoint to
breakpoint, each segment on a model whose time switches are fixed to the branch of the segment's
interior (:func:`branch_model`: the switch decided at the segment's midpoint), so that each side
is evaluated with its own branch, the left limit included; at each breakpoint the states carry
over and the algebraic variables are solved anew (the branch may move them).  Every method gets
this, fixed steps with the grid cut at the breakpoints (each segment split into equal steps no
longer than ``h``), so that order 2s-1 holds across them.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from dataclasses import dataclass

import numpy as np
import sympy as sp

from daemodel.dense import joined_by_samples, joined_in_time
from daemodel.errors import SwitchError

# Points of the grid on which a switching function's sign changes are bracketed (per segment of
# t_span); two roots closer than the grid's spacing may be missed if the function does not change
# sign between them (a tangency, where the branch does not change either).
ROOT_GRID = 4096
# Breakpoints closer than this (relative to the span) are one.
MERGE_TOL = 1e-12
# Relations whose switching function has more operations than this are not handed to sympy's
# solveset (it may take long on large expressions); they are found numerically.
CLOSED_FORM_MAX_OPS = 40
# Most breakpoints one solve may cut its span at (a switching function of t that oscillates
# fast, e.g. floor(1e6 t), would otherwise make millions of segments).
MAX_BREAKPOINTS = 10_000

_KINDS = {
    sp.Piecewise: "Piecewise",
    sp.Heaviside: "Heaviside",
    sp.sign: "sign",
    sp.Abs: "Abs",
    sp.Max: "Max",
    sp.Min: "Min",
    sp.floor: "floor",
    sp.ceiling: "ceiling",
}


@dataclass(frozen=True)
class Switch:
    """One switching function.

    Attributes
    ----------
    kind : str
        ``"Piecewise"``, ``"Heaviside"``, ``"sign"``, ``"Abs"``, ``"Max"``, ``"Min"``, ``"floor"``
        or ``"ceiling"``.
    function : sympy.Expr
        The switching function: the branch changes where it crosses 0 (``floor``/``ceiling``: an
        integer).
    equation : str
        Where it occurs (the ODE of a state, ``x'``, or the constraint's name).
    time_only : bool
        It depends on ``t`` (and parameters) only: a time breakpoint.
    """

    kind: str
    function: sp.Expr
    equation: str
    time_only: bool

    def describe(self) -> str:
        what = "time breakpoint" if self.time_only else "state event, located during the solve"
        crossing = "an integer" if self.kind in ("floor", "ceiling") else "0"
        return f"{self.kind} in {self.equation}: {self.function} crosses {crossing} ({what})"


def _switching_functions(node) -> list:
    """The switching functions of one switch node (see the module docstring)."""
    if isinstance(node, sp.Piecewise):
        out = []
        for _, condition in node.args:
            if condition in (sp.true, sp.false):
                continue
            for relation in sorted(condition.atoms(sp.core.relational.Relational), key=sp.default_sort_key):
                out.append(relation.lhs - relation.rhs)
        return out
    if isinstance(node, sp.Max | sp.Min):
        args = node.args
        return [args[i] - args[j] for i in range(len(args)) for j in range(i + 1, len(args))]
    return [node.args[0]]


def find_switches(compiled) -> tuple[Switch, ...]:
    """Every switching function of ``compiled``'s right-hand sides and constraints (each chain
    element), once per equation; cached on the compiled model."""
    key = ("switches",)
    if key in compiled._cache:
        return compiled._cache[key]
    time_symbols = {compiled.t, *compiled.parameters}
    equations = [(f"{name}'", (rhs,)) for name, rhs in zip(compiled.state_names, compiled.rhs, strict=True)]
    equations += [(c.name, c.chain) for c in compiled.constraints]
    found, seen = [], set()
    for label, exprs in equations:
        for expr in exprs:
            for node in sp.preorder_traversal(expr):
                kind = _KINDS.get(type(node))
                if kind is None:
                    continue
                for function in _switching_functions(node):
                    function = sp.sympify(function)
                    symbols = function.free_symbols
                    if compiled.t not in symbols and symbols <= time_symbols:
                        continue  # (constant in time: the branch never changes)
                    if (label, kind, function) in seen:
                        continue
                    seen.add((label, kind, function))
                    found.append(Switch(kind, function, label, symbols <= time_symbols))
    compiled._cache[key] = tuple(found)
    return compiled._cache[key]


def breakpoints(compiled, t_span, p: np.ndarray) -> np.ndarray:
    """The times in the open interval ``t_span`` where a time switch of ``compiled`` changes
    branch, for parameter values ``p`` (k,), sorted, near-equal ones merged.

    Raises
    ------
    SwitchError
        More than :data:`MAX_BREAKPOINTS` of them, naming the switch that makes most.
    """

    t0, t1 = (float(v) for v in t_span)
    switches = [s for s in find_switches(compiled) if s.time_only]
    if not switches:
        return np.zeros(0)
    values = dict(zip(compiled.parameters, (float(v) for v in p), strict=True))
    numeric = compiled.numeric
    times = []
    for switch in switches:
        found = _roots(switch, compiled.t, values, numeric, p, t0, t1)
        if len(found) > MAX_BREAKPOINTS:
            raise _too_many(switch, len(found), t0, t1)
        times += found
    if not times:
        return np.zeros(0)
    times = np.sort(np.asarray(times, dtype=float))
    tol = MERGE_TOL * max(1.0, abs(t1 - t0))
    merged = [times[0]]
    for value in times[1:]:
        if value - merged[-1] > tol:
            merged.append(value)
    out = np.asarray(merged)
    out = out[(out > t0 + tol) & (out < t1 - tol)]
    if len(out) > MAX_BREAKPOINTS:
        raise SwitchError(
            f"the time switches make {len(out)} breakpoints in t_span = ({t0:g}, {t1:g}), more than "
            f"{MAX_BREAKPOINTS}; smooth the switching functions, or shorten t_span"
        )
    return out


def _roots(switch: Switch, t, values: dict, numeric, p: np.ndarray, t0: float, t1: float) -> list:
    """Where ``switch`` changes branch in (t0, t1): closed form where sympy gives a finite set of
    real numbers, else bracketed on :data:`ROOT_GRID` points and bisected to rounding."""
    phi = switch.function.subs(values)
    integer = switch.kind in ("floor", "ceiling")
    if not integer and sp.count_ops(phi) <= CLOSED_FORM_MAX_OPS:
        try:
            solutions = sp.solveset(phi, t, sp.Interval.open(t0, t1))
        except (NotImplementedError, ValueError, TypeError):
            solutions = None
        if isinstance(solutions, sp.FiniteSet) and all(s.is_real for s in solutions):
            return [float(s) for s in solutions]
    evaluate = numeric.batch_function([switch.function])
    P = np.asarray(p, dtype=float)[None, :]
    n, m = len(numeric.y), len(numeric.z)

    def at(times):
        times = np.atleast_1d(np.asarray(times, dtype=float))
        return evaluate(times, np.zeros((len(times), n)), np.zeros((len(times), m)), np.repeat(P, len(times), axis=0))[
            :, 0
        ]

    grid = np.linspace(t0, t1, ROOT_GRID + 1)
    values_ = at(grid)
    if not np.isfinite(values_).all():
        bad = grid[~np.isfinite(values_)][0]
        raise SwitchError(
            f"{switch.kind} in {switch.equation}: its switching function {switch.function} is not finite at t = "
            f"{bad:.6g}; the breakpoints cannot be located"
        )
    level = np.floor(values_) if integer else np.sign(values_)
    brackets = np.flatnonzero(level[1:] != level[:-1])
    if integer:  # every integer crossed between two grid points: (bracket, integer)
        low, high = np.minimum(values_[:-1], values_[1:])[brackets], np.maximum(values_[:-1], values_[1:])[brackets]
        counts = (np.floor(high) - np.floor(low)).astype(np.int64)
        if counts.sum() > MAX_BREAKPOINTS:
            raise _too_many(switch, int(counts.sum()), t0, t1)
        which = np.repeat(brackets, counts)
        targets = np.concatenate([np.arange(np.floor(a) + 1, np.floor(b) + 1) for a, b in zip(low, high, strict=True)])
    else:
        if len(brackets) > MAX_BREAKPOINTS:
            raise _too_many(switch, len(brackets), t0, t1)
        which, targets = brackets, np.zeros(len(brackets))
    if not len(which):
        return []
    return _bisect(lambda s: at(s) - targets, grid[which], grid[which + 1]).tolist()


def _too_many(switch: Switch, count: int, t0: float, t1: float) -> SwitchError:
    return SwitchError(
        f"{switch.kind} in {switch.equation} switches {count} times in t_span = ({t0:g}, {t1:g}) (at most "
        f"{MAX_BREAKPOINTS} breakpoints a solve): {switch.function} changes branch too often to integrate from "
        "breakpoint to breakpoint; smooth it, or shorten t_span"
    )


def _bisect(g, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Roots of the vector function ``g`` (one entry per bracket), each in its [a, b] where g(a) and
    g(b) differ in sign or one is 0, all brackets halved together down to rounding."""
    a, b = a.astype(float).copy(), b.astype(float).copy()
    ga = g(a)
    exact_a = ga == 0
    gb = g(b)
    exact_b = gb == 0
    for _ in range(1100):  # (a float64 interval halves to adjacent floats in at most ~1100 passes)
        mid = 0.5 * (a + b)
        open_ = (mid > a) & (mid < b)
        if not open_.any():
            break
        gm = g(mid)
        left = (np.sign(gm) == np.sign(ga)) & open_
        a = np.where(left, mid, a)
        ga = np.where(left, gm, ga)
        b = np.where(open_ & ~left, mid, b)
    out = 0.5 * (a + b)
    return np.where(exact_a, a, np.where(exact_b, b, out))


def _time_only(expr, time_symbols) -> bool:
    return sp.sympify(expr).free_symbols <= time_symbols


def _fix(expr, at: dict, decide, sides: dict | None = None):
    """``expr`` with every switch whose switching functions ``decide`` accepts (a predicate on an
    expression) replaced by its branch at ``at`` (``{symbol: value}``).  ``sides`` (switching function
    -> +1 or -1) gives the branch of the functions that are at zero there: the side the solution goes
    to (never the switch's value at zero: ``Heaviside(0) = 1/2``, ``sign(0) = 0`` are no branch)."""
    sides = sides or {}
    if expr.is_Atom:
        return expr
    args = [_fix(a, at, decide, sides) if isinstance(a, sp.Basic) else a for a in expr.args]

    def value(function) -> float:
        side = sides.get(function)
        if side is None and -function in sides:
            side = -sides[-function]
        return float(side) if side else float(function.subs(at))

    if isinstance(expr, sp.Piecewise):
        kept = []
        for (piece, _), (_, condition) in zip(args, expr.args, strict=True):
            if condition == sp.true:
                if not kept:
                    return piece
                kept.append((piece, True))
                break
            if kept or not decide(condition):
                kept.append((piece, condition))
                continue
            relations = condition.atoms(sp.core.relational.Relational)
            truth = {r: type(r)(value(sp.sympify(r.lhs - r.rhs)), 0) for r in relations}
            if bool(condition.xreplace(truth)):
                return piece
        return sp.Piecewise(*kept) if kept else sp.nan
    if isinstance(expr, sp.Heaviside | sp.sign | sp.Abs | sp.floor | sp.ceiling | sp.DiracDelta):
        inner = args[0]
        if not decide(inner):
            return expr.func(*args)
        if isinstance(expr, sp.DiracDelta):
            return sp.S.Zero  # (0 inside a segment: the switch is at its ends)
        if isinstance(expr, sp.floor | sp.ceiling):
            number = float(inner.subs(at))
            side = sides.get(inner)
            if side:  # (at an integer k: floor is k going up, k - 1 going down)
                k = round(number)
                return sp.Integer(k if side > 0 else k - 1) + (1 if isinstance(expr, sp.ceiling) else 0)
            return sp.Integer(math.floor(number) if isinstance(expr, sp.floor) else math.ceil(number))
        number = value(inner)
        if isinstance(expr, sp.Heaviside):
            half = args[1] if len(args) > 1 else sp.S.Half
            return sp.S.One if number > 0 else (sp.S.Zero if number < 0 else half)
        if isinstance(expr, sp.sign):
            return sp.Integer(int(np.sign(number)))
        return inner if number >= 0 else -inner
    if isinstance(expr, sp.Max | sp.Min):
        if not all(decide(a) for a in args):
            return expr.func(*args)
        pick = 0
        for j in range(1, len(args)):
            difference = value(sp.sympify(args[pick] - args[j]))
            if (difference < 0) if isinstance(expr, sp.Max) else (difference > 0):
                pick = j
        return args[pick]
    return expr.func(*args)


def branch_model(compiled, tau: float, p: np.ndarray):
    """``compiled`` with its time switches fixed to their branch at ``t = tau`` (parameters ``p``):
    smooth on a segment between two breakpoints.  Models with the same branches are one (cached on
    ``compiled``, with their generated code)."""
    time_symbols = {compiled.t, *compiled.parameters}
    at = {compiled.t: sp.Float(tau), **dict(zip(compiled.parameters, (sp.Float(float(v)) for v in p), strict=True))}
    return _fixed(compiled, at, lambda e: _time_only(e, time_symbols), "branch")


def lock_branches(compiled, t: float, y: np.ndarray, z: np.ndarray, p: np.ndarray, sides: dict | None = None):
    """``compiled`` with its switches on states and algebraic variables fixed to their branch at
    ``(t, y, z)`` (time switches left to :func:`branch_model`): smooth until one of those switching
    functions crosses zero, which :mod:`daemodel.solving.events` locates and then locks again.
    ``sides`` (switching function -> +1 or -1): the branch of those at zero there (see :func:`_fix`).
    Cached."""
    sides = sides or {}
    switches = find_switches(compiled)
    functions = tuple(dict.fromkeys(switch.function for switch in switches))
    integer = {switch.function for switch in switches if switch.kind in ("floor", "ceiling")}
    numbers = compiled.numeric.batch_function(list(functions))(
        np.array([float(t)]), np.asarray(y, dtype=float)[None], np.asarray(z, dtype=float)[None], np.asarray(p)[None]
    )[0]
    # the branches as numbers (each function's sign, an integer part's floor and ceiling, or the side given):
    # the same branches are the same model, found without rewriting the equations (large models: seconds each)
    decided, signature = {}, []
    for function, number in zip(functions, numbers, strict=True):
        side = sides.get(function) or (-sides[-function] if -function in sides else None)
        if function in integer:
            signature.append((round(number), side) if side else (math.floor(number), math.ceil(number)))
            if side:
                decided[function] = side
        else:
            signature.append(side or int(np.sign(number)))
            if signature[-1]:
                decided[function] = signature[-1]
    key = ("locked-by", tuple(signature))
    if key not in compiled._cache:
        time_symbols = {compiled.t, *compiled.parameters}
        values = [
            (compiled.t, t),
            *zip(compiled.parameters, p, strict=True),
            *zip(compiled.states, y, strict=True),
            *zip(compiled.algebraics, z, strict=True),
        ]
        at = {symbol: sp.Float(float(value)) for symbol, value in values}
        compiled._cache[key] = _fixed(compiled, at, lambda e: not _time_only(e, time_symbols), "locked", decided)
    return compiled._cache[key]


def for_method(compiled, backend):
    """``compiled`` reduced to the highest index ``backend`` takes (itself where it takes it)."""
    return compiled.reduced(backend.max_index) if compiled.index > backend.max_index else compiled


def settings_as_given(sol, options) -> dict:
    """``sol``'s settings with ``t_eval`` and ``h`` as the user gave them (a piece's were its own)."""
    settings = dict(sol.settings)
    for key in ("t_eval", "h"):
        if key in settings:
            settings[key] = getattr(options, key)
    return settings


def has_state_switches(compiled) -> bool:
    return any(not s.time_only for s in find_switches(compiled))


def _fixed(compiled, at: dict, decide, kind: str, sides: dict | None = None):
    """``compiled`` with the switches ``decide`` accepts fixed at ``at`` (see :func:`_fix`), cached."""
    rhs = tuple(_fix(e, at, decide, sides) for e in compiled.rhs)
    constraints = tuple(
        dataclasses.replace(c, chain=tuple(_fix(e, at, decide, sides) for e in c.chain)) for c in compiled.constraints
    )
    key = (kind, rhs, tuple(c.chain for c in constraints))
    if key not in compiled._cache:
        compiled._cache[key] = dataclasses.replace(compiled, rhs=rhs, constraints=constraints, _cache={})
    return compiled._cache[key]


# Stats summed over segments (counters); keys starting with "max"/ending "_max" take the largest,
# "min"/"_min" the smallest; any other key keeps the first segment's value (stages, engine, ...).
_COUNTERS = ("steps", "attempts", "rejected", "iterations", "evaluations", "decompositions", "failures",
             "refreshes", "retries", "runs", "setups", "calls")  # fmt: skip


def _merge_stats(all_stats: list) -> dict:
    out = {}
    for key in dict.fromkeys(k for stats in all_stats for k in stats):
        values = [stats[key] for stats in all_stats if key in stats]
        numeric = all(isinstance(v, int | float | np.integer | np.floating) and not isinstance(v, bool) for v in values)
        if numeric and (key.startswith("max") or key.endswith("_max")):
            out[key] = max(values)
        elif numeric and (key.startswith("min") or key.endswith("_min")):
            out[key] = min(values)
        elif numeric and any(word in key for word in _COUNTERS):
            out[key] = sum(values)
        elif all(isinstance(v, list) for v in values):
            out[key] = [x for v in values for x in v]
        else:
            out[key] = values[0]
    return out


def _segment_steps(a: float, b: float, h: float) -> float:
    """The step of a fixed grid on [a, b]: equal steps, as few as keep each at most ``h``."""
    return (b - a) / max(1, math.ceil((b - a) / h * (1 - 1e-9)))


def solve_with_breakpoints(backend, compiled, t_span, start, options):
    """Solve from breakpoint to breakpoint (see the module docstring): each segment on
    :func:`branch_model` at its midpoint (reduced to the index ``backend`` takes), the states
    carried over (projected onto the constraints where a switch inside one moved them), the
    algebraic variables solved anew at each breakpoint; one :class:`~daemodel.solution.Solution`
    of them all, whose values at a breakpoint are those after it (:attr:`Solution.breakpoints`
    holds both sides).  Samples of a batch whose parameters move the breakpoints are solved in
    groups that share them, on the common output times ``t_eval``.  ``compiled`` is the model as
    compiled, before any reduction: a switch inside a constraint that the reduction differentiates
    away is still a breakpoint.

    Raises
    ------
    SwitchError
        The samples of a batch switch at different times and no ``t_eval`` gives them common
        output times.
    """
    from daemodel.compiling.initial_states import InitialStates

    P = np.asarray(start.p, dtype=float)
    groups: dict = {}
    for b in range(len(P)):
        times = breakpoints(compiled, t_span, P[b])
        key = next((k for k in groups if _same(k, times, t_span)), None)
        groups.setdefault(key if key is not None else tuple(times.tolist()), []).append(b)
    if len(groups) == 1:
        return _solve_segments(backend, compiled, t_span, start, options, np.asarray(next(iter(groups))))
    if getattr(options, "t_eval", None) is None:
        (first, one), (second, other) = list(groups.items())[:2]
        raise SwitchError(
            f"the samples of this batch switch at different times (sample {one[0]}: {_times(np.asarray(first))}; "
            f"sample {other[0]}: {_times(np.asarray(second))}): their parameters move the breakpoints, so their steps "
            "differ; pass t_eval to have them on common output times, or solve them one at a time"
        )
    parts = []
    for times, members in groups.items():
        index = np.asarray(members)
        sub = InitialStates(y0=start.y0[index], z0=start.z0[index], p=start.p[index], batched=True)
        parts.append((index, _solve_segments(backend, compiled, t_span, sub, options, np.asarray(times))))
    return _join_samples(parts, len(P), start.batched)


def _onto_constraints(model, Y: np.ndarray, P: np.ndarray) -> np.ndarray:
    """The states ``Y`` (B, n) where they satisfy ``model``'s z-free constraint levels at its t0, else
    their least-change projection onto them (a switch inside a constraint moves its solution set).

    Raises
    ------
    SwitchError
        No state near a sample's satisfies them after the switch.
    """
    from daemodel.compiling.initial_states import constraint_checks as _checks
    from daemodel.compiling.initial_states import project_states, state_violations

    hidden = _checks(model).hidden
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


def _same(key: tuple, times: np.ndarray, t_span) -> bool:
    tol = MERGE_TOL * max(1.0, t_span[1] - t_span[0])
    return len(key) == len(times) and bool(np.all(np.abs(np.asarray(key) - times) <= tol))


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


def _join_samples(parts: list, B: int, batched: bool):
    """One Solution of the groups' (``(sample indices, Solution)``, all on the same output times):
    values and parameters in sample order, breakpoints and events padded with NaN to the longest."""
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
    breakpoints = _pad([(index, sol.breakpoints) for index, sol in parts], B) if first.breakpoints else {}
    events = {name: _pad([(index, sol.events[name]) for index, sol in parts], B) for name in first.events}
    stats = _merge_stats([sol.stats for _, sol in parts])
    stats["groups"] = len(parts)
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


def _solve_segments(backend, compiled, t_span, start, options, times: np.ndarray):
    """The samples of ``start``, which share the breakpoints ``times``, from one to the next."""
    from daemodel.backends.grids import output_times
    from daemodel.compiling.initial_states import InitialStates, algebraic_values
    from daemodel.solution import Solution

    t0, t1 = t_span
    moved = []  # (B,) per breakpoint: how far the states were projected there
    solved = for_method(compiled, backend)
    P = np.asarray(start.p, dtype=float)
    edges = [t0, *times.tolist(), t1]
    user_grid = None if getattr(options, "t_eval", None) is None else output_times(options.t_eval, t_span, ())
    h = getattr(options, "h", None)
    Y, Z = np.asarray(start.y0, dtype=float), np.asarray(start.z0, dtype=float)
    names = (*compiled.state_names, *compiled.algebraic_names)
    parts, pre, post = [], [], []
    for k, (a, b) in enumerate(itertools.pairwise(edges)):
        last = k == len(edges) - 2
        whole = branch_model(compiled, 0.5 * (a + b), P[0])
        model = for_method(whole, backend)
        if k:  # the states carry over (projected where a switch moved the constraints); z follows the branch
            projected = _onto_constraints(dataclasses.replace(whole, t0=float(a)), Y, P)
            moved.append(np.max(np.abs(projected - Y), axis=1, initial=0.0))
            Y = projected
            Z = algebraic_values(model, a, Y, P, Z)
            post.append(np.concatenate([Y, Z], axis=1))
        model = dataclasses.replace(model, t0=float(a), y0=Y[0].copy(), z0=Z[0].copy())
        changes, unseen = {}, False
        if user_grid is not None:
            inside = user_grid[(user_grid >= a) & ((user_grid <= b) if last else (user_grid < b))]
            # (a last segment with no output time in it, a piece before an event: solved to b, b not shown)
            unseen = last and not len(inside)
            changes["t_eval"] = np.concatenate([inside, [b]]) if not last or unseen else inside
        if h is not None:
            changes["h"] = _segment_steps(a, b, h)
        segment_start = InitialStates(y0=Y, z0=Z, p=P, batched=start.batched)
        sol = backend.solve(model, (float(a), float(b)), segment_start, dataclasses.replace(options, **changes))
        end = np.stack([np.asarray(sol.values[name])[:, -1] for name in names], axis=-1)
        Y, Z = end[:, : len(compiled.states)].copy(), end[:, len(compiled.states) :].copy()
        keep = np.full(len(sol.t), not unseen)
        if not last:
            pre.append(end)
            keep[-1] = False  # (the breakpoint's values are the next segment's: after the switch)
        parts.append((sol, keep))
    t = np.concatenate([sol.t[keep] for sol, keep in parts])
    values = {
        name: np.concatenate([np.asarray(sol.values[name])[:, keep] for sol, keep in parts], axis=1)
        for name in parts[0][0].values
    }
    failing = [
        f"on [{a:.6g}, {b:.6g}]: {sol.status}"
        for (sol, _), (a, b) in zip(parts, itertools.pairwise(edges), strict=True)
        if sol.status != "success"
    ]
    stats = _merge_stats([sol.stats for sol, _ in parts])
    stats["segments"] = len(parts)
    settings = settings_as_given(parts[0][0], options)
    B = len(P)
    record = {
        "t": np.repeat(times[None, :], B, axis=0),
        "moved": np.stack(moved, axis=-1) if moved else np.zeros((B, 0)),
        "before": {
            name: np.stack([v[:, j] for v in pre], axis=-1) if pre else np.zeros((B, 0)) for j, name in enumerate(names)
        },
        "after": {
            name: np.stack([v[:, j] for v in post], axis=-1) if post else np.zeros((B, 0))
            for j, name in enumerate(names)
        },
    }
    return Solution(
        t=t,
        values=values,
        method=parts[0][0].method,
        settings=settings,
        solve_time=sum(sol.solve_time for sol, _ in parts),
        stats=stats,
        compiled=solved,
        parameters=parts[0][0].parameters,
        batched=parts[0][0].batched,
        status="success" if not failing else "; ".join(failing),
        setup_time=sum(sol.setup_time for sol, _ in parts),
        breakpoints=record,
        dense=joined_in_time(edges, [sol.dense for sol, _ in parts]),
    )


def _times(times: np.ndarray) -> str:
    shown = ", ".join(f"{v:.6g}" for v in times[:5])
    return f"[{shown}{', ...' if len(times) > 5 else ''}]" if len(times) else "none"


def has_time_switches(compiled) -> bool:
    return any(s.time_only for s in find_switches(compiled))

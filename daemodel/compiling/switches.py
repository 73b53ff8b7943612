"""Switches: where a model's equations change branch, found in the compiled equations.

A switching function is what decides a branch: each relation of a ``Piecewise`` condition
(``lhs - rhs``), the argument of ``Heaviside``, ``sign`` and ``Abs``, the differences of the
arguments of ``Max`` and ``Min``, the argument of ``floor`` and ``ceiling`` (which switch where it
crosses an integer).  One that depends on ``t`` and parameters only switches at *time
breakpoints*, found before the solve (:func:`breakpoints`: in closed form where sympy solves the
equation, else by bracketing sign changes on a fine grid and bisecting); one that depends on a
state or algebraic variable is a *state event*, listed but not yet located.

Segments are solved from breakpoint to breakpoint in :mod:`daemodel.solving.switches`; switches on
states become events (:func:`with_state_events`), located in :mod:`daemodel.solving.events`.
"""

from __future__ import annotations

import dataclasses
import math
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
import sympy as sp

from daemodel.declaring.events import Event
from daemodel.errors import SwitchError

# Points of the grid on which a switching function's sign changes are bracketed (per segment of
# t_span); two roots closer than the grid's spacing may be missed if the function does not change
# sign between them (a tangency, where the branch does not change either).
ROOT_GRID = 4096

# Breakpoints closer than this (relative to the span) are one, and within MERGE_ULPS float64 spacings of the
# span's ends (a root bisected to adjacent floats; as an event's bracket, branches.RESOLVE_ULPS, no time between).
MERGE_TOL, MERGE_ULPS = 1e-12, 2

# Relations whose switching function has more operations than this are not handed to sympy's
# solveset (it may take long on large expressions); they are found numerically.
CLOSED_FORM_MAX_OPS = 40

# Most breakpoints one solve may cut its span at (a switching function of t that oscillates
# fast, e.g. floor(1e6 t), would otherwise make millions of segments).
MAX_BREAKPOINTS = 10_000
# Breakpoints kept per model: those of this many spans and parameter values (the event pieces' spans: one each).
KEPT_SPANS = 64

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
            stack = [expr]
            while stack:  # (preorder, as sympy's preorder_traversal, without its generator's cost per node)
                node = stack.pop()
                stack.extend(reversed(node.args))
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
    branch, for parameter values ``p`` (k,), sorted, near-equal ones merged; read-only, kept with the
    model for the last :data:`KEPT_SPANS` spans and parameter values asked for (sympy's solveset took
    19-86 ms of every solve of a two-segment model, on its solve clock).

    Raises
    ------
    SwitchError
        More than :data:`MAX_BREAKPOINTS` of them, naming the switch that makes most.
    """
    key = (*(float(v) for v in t_span), np.asarray(p, dtype=float).tobytes())
    kept = compiled._cache.setdefault("breakpoints", OrderedDict())
    if key in kept:
        kept.move_to_end(key)
        return kept[key]
    times = _breakpoints(compiled, t_span, p)
    times.flags.writeable = False
    kept[key] = times
    if len(kept) > KEPT_SPANS:
        kept.popitem(last=False)
    return times


def _breakpoints(compiled, t_span, p: np.ndarray) -> np.ndarray:
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
    tol = merge_tol(t0, t1)
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


def merge_tol(t0: float, t1: float) -> float:
    """How close two breakpoints in ``(t0, t1)`` are one (and one is at an end): :data:`MERGE_TOL` of the span, at
    least :data:`MERGE_ULPS` float64 spacings of its ends; never an absolute 1e-12, which merged two steps of a rate
    5e-13 apart on a span of 3e-7 and left the state 1.25e-6 off (rtol 1e-10), "success", in every method."""
    return max(MERGE_TOL * abs(t1 - t0), MERGE_ULPS * math.ulp(max(abs(t0), abs(t1))))


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
    # (a node none of whose arguments changed is kept as it is: rebuilt, sympy evaluates it again, and Min
    # and Max compare their arguments pairwise; the wheelset's creep forces took 1-2 s per locked branch)
    unchanged = all(new is old for new, old in zip(args, expr.args, strict=True))

    def value(function, fixed) -> float:
        # (the side is looked up by the switching function as find_switches wrote it, of the node's arguments
        # as they stand in the equations: a switch inside it (Min(x**2, Max(-2, y))'s x**2 - Max(-2, y)) is
        # already fixed in ``args``, and x**2 - y is no key of ``sides``, so the comparison fell to its value
        # at zero, a rounding's sign, or a tie to the earlier argument: the branch before the crossing, kept
        # after it, "success"; its value where no side is given: ``fixed``'s, inner switches on their side)
        side = sides.get(function)
        if side is None and -function in sides:
            side = -sides[-function]
        if side:
            return float(side)
        number = fixed.subs(at)
        try:
            return float(number)
        except TypeError:  # (a complex number: sympy's sqrt of a negative; numpy's nan, which no comparison orders)
            where = ", ".join(f"{symbol} = {float(v):.6g}" for symbol, v in at.items())
            raise SwitchError(
                f"switching function {function} is {sp.N(number, 6)}, not a real number, at {where}, where the "
                "branch of its switch is chosen: write the switch's arguments so that they stay real there (a sqrt, "
                "log or power of a negative), or end t_span before it"
            ) from None

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
            differences = {r: sp.sympify(r.lhs - r.rhs) for r in relations}
            truth = {r: type(r)(value(d, _fix(d, at, decide, sides)), 0) for r, d in differences.items()}
            if bool(condition.xreplace(truth)):
                return piece
        return sp.Piecewise(*kept) if kept else sp.nan
    if isinstance(expr, sp.Heaviside | sp.sign | sp.Abs | sp.floor | sp.ceiling | sp.DiracDelta):
        inner, switching = args[0], expr.args[0]  # (fixed; as find_switches wrote it: the key of sides)
        if not decide(switching):
            return expr if unchanged else expr.func(*args)
        if isinstance(expr, sp.DiracDelta):
            return sp.S.Zero  # (0 inside a segment: the switch is at its ends)
        if isinstance(expr, sp.floor | sp.ceiling):
            number = float(inner.subs(at))
            side = sides.get(switching)
            if side:  # (at an integer k: floor is k going up, k - 1 going down)
                k = round(number)
                return sp.Integer(k if side > 0 else k - 1) + (1 if isinstance(expr, sp.ceiling) else 0)
            return sp.Integer(math.floor(number) if isinstance(expr, sp.floor) else math.ceil(number))
        number = value(switching, inner)
        if isinstance(expr, sp.Heaviside):
            half = args[1] if len(args) > 1 else sp.S.Half
            return sp.S.One if number > 0 else (sp.S.Zero if number < 0 else half)
        if isinstance(expr, sp.sign):
            return sp.Integer(int(np.sign(number)))
        return inner if number >= 0 else -inner
    if isinstance(expr, sp.Max | sp.Min):
        kept = _contenders(expr.args, args, decide, value, 1 if isinstance(expr, sp.Max) else -1)
        if len(kept) == len(args):
            return expr if unchanged else expr.func(*args)
        return kept[0] if len(kept) == 1 else expr.func(*kept)
    return expr if unchanged else expr.func(*args)


def _contenders(written, args, decide, value, way: int) -> list:
    """The arguments of a ``Max`` (``way`` = 1) or ``Min`` (-1) that may still be its value once the
    switching functions ``decide`` accepts (its arguments' differences, :func:`find_switches`) are
    fixed by ``value``: those that lose no decided comparison (a tie to the earlier argument).  Only
    the comparisons between them are left, all undecided: ``Min(1, x)`` is ``1`` or ``x`` on a piece
    of the state event ``1 - x`` (before, it was locked only where every argument, the constant too,
    was of the variables, and stayed a kink inside each piece); ``Max(x, sin(t), 0)`` keeps
    ``Max(sin(t), 0)`` where ``x`` is below both, for the time breakpoints to cut.  ``written``: the
    node's arguments as they stand in the equations, whose differences are the switching functions
    (decided, and looked up in the sides, as find_switches found them); ``args``: the same with the
    switches inside them fixed (valued, and returned)."""
    k = len(args)

    def compare(i: int, j: int) -> float:
        return way * value(sp.sympify(written[i] - written[j]), sp.sympify(args[i] - args[j]))

    out = set(range(k))
    for i in range(k):
        for j in range(i + 1, k):
            if not decide(sp.sympify(written[i] - written[j])):
                continue
            number = compare(i, j)  # (> 0: i wins, < 0: j wins, 0: a tie, to the earlier)
            out.discard(j if number >= 0 else i)
    if not out:  # (sides that contradict one another, a > b > c > a: the first one standing in turn)
        pick = 0
        for j in range(1, k):
            if compare(pick, j) < 0:
                pick = j
        return [args[pick]]
    return [args[i] for i in sorted(out)]


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
    decided, signature = _decisions(compiled, t, y, z, p, sides or {})
    key = ("locked-by", signature)
    if key not in compiled._cache:
        time_symbols = {compiled.t, *compiled.parameters}
        at = _point(compiled, t, y, z, p)
        compiled._cache[key] = _fixed(compiled, at, lambda e: not _time_only(e, time_symbols), "locked", decided)
    return compiled._cache[key]


def lock_functions(compiled, functions: tuple, t: float, y: np.ndarray, z: np.ndarray, p: np.ndarray, sides=None):
    """``functions`` (sympy expressions: the event functions) with the switches on variables inside them fixed
    to the branches :func:`lock_branches` gives the equations at the same point and ``sides``: a piece's own
    event functions, smooth on it.  ``-x + floor(x) + 0.5`` (the switching function of ``Max(x - floor(x),
    0.5)``) jumps from -0.5 to 0.5 where x reaches 1, a jump that is no crossing; read as it is on a piece
    whose floor is locked to 1 from a located x a rounding below 1, it was -0.5 there and +0.5 a step on, a
    crossing at the piece's start that never left zero to its side (ZenoError at t = 0.621 in every method).
    ``functions`` themselves where none holds such a switch.  Cached."""

    def nested() -> bool:
        return any(_KINDS.get(type(node)) for f in functions for node in sp.preorder_traversal(f) if not node.is_Atom)

    if not compiled.cached(("nested-switches", functions), nested):
        return functions
    decided, signature = _decisions(compiled, t, y, z, p, sides or {})
    key = ("locked-functions", functions, signature)
    if key not in compiled._cache:
        time_symbols = {compiled.t, *compiled.parameters}
        at = _point(compiled, t, y, z, p)
        compiled._cache[key] = tuple(_fix(f, at, lambda e: not _time_only(e, time_symbols), decided) for f in functions)
    return compiled._cache[key]


def _decisions(compiled, t: float, y: np.ndarray, z: np.ndarray, p: np.ndarray, sides: dict) -> tuple:
    """``(decided, signature)``: the side of each switching function on variables at ``(t, y, z)`` (``sides``
    where given, else its sign; an integer part's level), and the branches as numbers: the same branches are
    the same model, found without rewriting the equations (large models: seconds each)."""
    switches = find_switches(compiled)
    functions = tuple(dict.fromkeys(switch.function for switch in switches))
    integer = {switch.function for switch in switches if switch.kind in ("floor", "ceiling")}
    numbers = compiled.numeric.batch_function(list(functions))(
        np.array([float(t)]), np.asarray(y, dtype=float)[None], np.asarray(z, dtype=float)[None], np.asarray(p)[None]
    )[0]
    decided, signature = {}, []
    for function, number in zip(functions, numbers, strict=True):
        if not np.isfinite(number):  # (numpy's sign of a nan is nan: a bare "cannot convert float NaN to integer")
            switch = next(switch for switch in switches if switch.function == function)
            at = ", ".join(f"{n} = {v:.6g}" for n, v in zip(compiled.state_names, np.ravel(y), strict=True))
            raise SwitchError(
                f"{switch.kind} in {switch.equation}: its switching function {function} is {float(number)} at t = "
                f"{float(t):.12g} ({at}), so the branch cannot be chosen (a nan compares to nothing); write it "
                "without a sqrt, log or division that the solution takes out of its domain"
            )
        side = sides.get(function) or (-sides[-function] if -function in sides else None)
        if function in integer:
            signature.append((round(number), side) if side else (math.floor(number), math.ceil(number)))
            if side:
                decided[function] = side
        else:
            signature.append(side or int(np.sign(number)))
            if signature[-1]:
                decided[function] = signature[-1]
    return decided, tuple(signature)


def _point(compiled, t: float, y: np.ndarray, z: np.ndarray, p: np.ndarray) -> dict:
    """``{symbol: value}`` of t, the parameters and the variables at one point (sympy Floats)."""
    values = [
        (compiled.t, t),
        *zip(compiled.parameters, p, strict=True),
        *zip(compiled.states, y, strict=True),
        *zip(compiled.algebraics, z, strict=True),
    ]
    return {symbol: sp.Float(float(value)) for symbol, value in values}


def has_state_switches(compiled) -> bool:
    return any(not s.time_only for s in find_switches(compiled))


def has_time_switches(compiled) -> bool:
    return any(s.time_only for s in find_switches(compiled))


def _fixed(compiled, at: dict, decide, kind: str, sides: dict | None = None):
    """``compiled`` with the switches ``decide`` accepts fixed at ``at`` (see :func:`_fix`), cached."""
    rhs = tuple(_fix(e, at, decide, sides) for e in compiled.rhs)
    constraints = tuple(
        dataclasses.replace(c, chain=tuple(_fix(e, at, decide, sides) for e in c.chain)) for c in compiled.constraints
    )
    key = (kind, rhs, tuple(c.chain for c in constraints))
    return compiled.kept_copy(key, lambda: dataclasses.replace(compiled, rhs=rhs, constraints=constraints, _cache={}))


def with_state_events(compiled):
    """``compiled`` with an event at each of its switches on a state or algebraic variable
    (:func:`find_switches`; no reset, named after the switch; ``floor`` and
    ``ceiling`` at the integers below and above the function's value in each piece), so that no step
    straddles one; cached on ``compiled``."""

    def build():
        extra, names, functions = [], {e.name for e in compiled.events}, set()
        for switch in find_switches(compiled):
            if switch.time_only or switch.function in functions or -switch.function in functions:
                continue  # (one event a surface: an index-2 model repeats f's switches in its hidden constraints)
            functions.add(switch.function)
            name, k = f"{switch.kind} in {switch.equation}", 1
            while name in names:
                k += 1
                name = f"{switch.kind} in {switch.equation} ({k})"
            names.add(name)
            integer = switch.kind in ("floor", "ceiling")
            extra.append(Event(name, switch.function, 0, (), False, strict=True, integer=integer))
        return dataclasses.replace(compiled, events=(*compiled.events, *extra), _cache={}) if extra else None

    key = ("with-state-events",)
    if key not in compiled._cache:
        compiled._cache[key] = build()
    # (no switch on a variable: the model itself, also for a copy at other initial values that shares its cache)
    return compiled if compiled._cache[key] is None else compiled.rebased(compiled._cache[key])

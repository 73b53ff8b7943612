"""Model only what a scene needs: alias elimination and output-driven pruning.

* An *alias* constraint ``0 = a (x - v)`` (a a nonzero number, x algebraic, v = +-symbol)
  is removed together with x; x is substituted by v everywhere and stays readable as an
  alias (a named expression of the remaining variables).
* Pruning keeps the variables the requested outputs depend on through the coupled system.
  A differential variable depends on the variables of its right-hand side.  An algebraic
  variable depends on every variable of the constraints it is solved with: the connected
  block of constraints and algebraic variables linked through the determining equations,
  including all levels of each derivative chain (the hidden constraints restrict y).
"""

from __future__ import annotations

import heapq
from dataclasses import replace

import sympy as sp

from daemodel.compiling.structure import Differentiator, incidence
from daemodel.compiling.zero_test import (
    MODULUS,
    exact_value,
    is_zero,
    modular_value,
    numeric_point,
    numeric_value,
    point_value,
)


def find_alias(
    g: sp.Expr, algebraics, symbols, calculus: Differentiator | None = None
) -> tuple[sp.Symbol, sp.Expr] | None:
    """Return ``(x, v)`` when ``0 = g`` says ``x = v`` for an algebraic x and v = +-symbol.

    ``algebraics``: a list, or a dict of each algebraic variable's position (the first one in that
    order that ``g`` is an alias of wins); only those occurring in ``g`` are looked at, so that a
    scan of n constraints is O(n), not O(n^2)."""
    calculus = calculus or Differentiator()
    occurring = calculus.free_symbols(g)  # once, not once per algebraic variable
    position = algebraics if isinstance(algebraics, dict) else {x: i for i, x in enumerate(algebraics)}
    g_values = []  # [g's exact value at exact_value's point] once asked (None: not rational there)
    for x in sorted((s for s in occurring if s in position), key=position.__getitem__):
        a = calculus.diff(g, x)
        if not (a.is_number and a != 0):
            continue
        others = (occurring - {x}) & symbols
        if a.is_Rational and a.q % MODULUS and a.p % MODULUS:
            # v's exact value is -(g - a x) / a at the point of exact_value, and modulo a prime: a residue
            # that is neither s's nor -s's rules s out without building v (most constraints are no alias,
            # and building v cost most of the scan); _may_be decides on the candidates left
            g_values = g_values or [modular_value(g)]
            if g_values[0] is not None:
                coefficient = int(a.p) * pow(int(a.q), -1, MODULUS) % MODULUS
                value = -(g_values[0] - coefficient * modular_value(x)) * pow(coefficient, -1, MODULUS) % MODULUS
                if not any(value in (r, -r % MODULUS) for r in map(modular_value, others)):
                    continue
        v = -(g - a * x) / a
        # the zero test (no expansion where the values decide) only for the symbols v may be
        for s in _may_be(v, others):
            for candidate in (s, -s):
                if is_zero(v - candidate):
                    return x, candidate
    return None


def _may_be(v: sp.Expr, candidates) -> list:
    """The symbols s of ``candidates`` (in a fixed order) that ``v`` may be identically, up to sign.

    Others are ruled out where ``v`` has a value at the point of
    :func:`~daemodel.compiling.zero_test.exact_value` (exact) or at the first point of the numeric zero test
    (:func:`~daemodel.compiling.zero_test.numeric_value`, 40 digits) and ``|v|`` differs from ``|s|`` there.
    """
    candidates = sorted(candidates, key=lambda s: s.name)
    value = exact_value(v)
    if value is not None:
        return [s for s in candidates if abs(value) == point_value(s)]
    value = numeric_value(v)
    if value is None:
        return candidates
    return [s for s in candidates if abs(abs(value) - numeric_point(s, 0)) <= ALIAS_MATCH_RTOL * abs(value)]


# A value and a symbol's value at the numeric test's first point (40 digits) "match" within this:
# far above the round-off of an expression equal to the symbol, far below any other coincidence.
ALIAS_MATCH_RTOL = 1e-20


def eliminate_aliases(
    rhs: dict, constraints: list, algebraics: list, symbols: set, calculus: Differentiator | None = None
):
    """Remove alias constraints and their algebraic variables.

    Parameters
    ----------
    rhs : dict Symbol -> Expr
        Right-hand sides of the ODEs (rewritten in place).
    constraints : list of Equation
    algebraics : list of Symbol
    symbols : set of Symbol
        What an alias may stand for (states, algebraics, parameters, t).
    calculus : Differentiator, optional
        Shared derivatives and free symbols.

    Returns
    -------
    constraints, algebraics, aliases
        The remaining constraints (expressions substituted), the remaining algebraic
        variables, and ``[(name, expr, equation)]`` for every eliminated alias.
    """
    calculus = calculus or Differentiator()
    constraints, aliases = list(constraints), []
    # Every elimination restarts the scan from the first constraint.  A constraint found to be no
    # alias stays none until an elimination rewrites it (find_alias looks only at the algebraic
    # variables that occur in it), so the scan takes the first constraint not settled (a heap of
    # them): the same first alias as a full rescan, without re-examining every constraint after
    # every elimination.  Where each algebraic variable occurs (right-hand sides, constraints,
    # aliases) is kept as it changes, so an elimination rewrites only those: scanning every
    # equation per elimination made n aliases O(n^2) (64 s for 3,000, hours at 10^5).
    position = {x: i for i, x in enumerate(algebraics)}  # (the algebraic variables not eliminated yet)
    in_rhs: dict = {x: set() for x in position}  # x -> the states whose right-hand side holds it
    in_constraints: dict = {x: set() for x in position}  # x -> the constraints (positions) that hold it
    in_aliases: dict = {x: set() for x in position}  # x -> the aliases (positions) whose expression holds it

    def note(table: dict, expr: sp.Expr, key) -> None:
        for s in calculus.free_symbols(expr):
            if s in table:
                table[s].add(key)

    for y, f in rhs.items():
        note(in_rhs, f, y)
    for i, c in enumerate(constraints):
        note(in_constraints, c.expr, i)
    removed = [False] * len(constraints)
    unsettled = list(range(len(constraints)))  # (a heap: already in order)
    queued = [True] * len(constraints)
    while unsettled:
        k = heapq.heappop(unsettled)
        queued[k] = False
        if removed[k]:
            continue
        hit = find_alias(constraints[k].expr, position, symbols, calculus)
        if hit is None:
            continue
        x, v = hit
        removed[k] = True
        sub = {x: v}
        for y in in_rhs.pop(x):  # (each rewritten apart: the order changes nothing)
            rhs[y] = rhs[y].xreplace(sub)
            note(in_rhs, rhs[y], y)
        for i in in_constraints.pop(x):
            if removed[i]:
                continue
            constraints[i] = replace(constraints[i], expr=constraints[i].expr.xreplace(sub))
            note(in_constraints, constraints[i].expr, i)
            if not queued[i]:
                heapq.heappush(unsettled, i)
                queued[i] = True
        for i in in_aliases.pop(x):
            n, e, q = aliases[i]
            aliases[i] = (n, e.xreplace(sub), q)
            note(in_aliases, aliases[i][1], i)
        note(in_aliases, v, len(aliases))
        aliases.append((x.name, v, constraints[k]))
        del position[x]
    remaining = [c for c, gone in zip(constraints, removed, strict=True) if not gone]
    return remaining, [x for x in algebraics if x in position], aliases


def blocks(constraints, algebraics, calculus: Differentiator | None = None) -> list[tuple[list[int], list[int]]]:
    """Connected blocks ``(constraint indices, algebraic indices)`` of the determining equations."""
    rows = incidence(constraints, algebraics, calculus)
    parent = list(range(len(constraints) + len(algebraics)))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i, cols in enumerate(rows):
        for j in cols:
            parent[root(i)] = root(len(constraints) + j)
    groups: dict[int, tuple[list[int], list[int]]] = {}
    for i in range(len(constraints)):
        groups.setdefault(root(i), ([], []))[0].append(i)
    for j in range(len(algebraics)):
        groups.setdefault(root(len(constraints) + j), ([], []))[1].append(j)
    return list(groups.values())


def needed(
    outputs: list[str], rhs: dict, constraints, algebraics, aliases: dict, calculus: Differentiator | None = None
) -> set[str]:
    """Names of the variables the outputs depend on (closure through the coupled system)."""
    depends: dict[str, set[str]] = {y.name: {s.name for s in e.free_symbols} for y, e in rhs.items()}
    for rows, cols in blocks(constraints, algebraics, calculus):
        names = {s.name for i in rows for e in constraints[i].chain for s in e.free_symbols}
        names |= {algebraics[j].name for j in cols}
        for j in cols:
            depends[algebraics[j].name] = names
    for name, expr in aliases.items():
        depends[name] = {s.name for s in expr.free_symbols}
    keep: set[str] = set()
    todo = list(outputs)
    while todo:
        name = todo.pop()
        if name not in keep:
            keep.add(name)
            todo.extend(depends.get(name, ()))
    return keep

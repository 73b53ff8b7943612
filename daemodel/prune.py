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

from dataclasses import replace

import sympy as sp

from daemodel.structure import incidence


def find_alias(g: sp.Expr, algebraics, symbols) -> tuple[sp.Symbol, sp.Expr] | None:
    """Return ``(x, v)`` when ``0 = g`` says ``x = v`` for an algebraic x and v = +-symbol."""
    for x in algebraics:
        if x not in g.free_symbols:
            continue
        a = sp.diff(g, x)
        if not (a.is_number and a != 0):
            continue
        v = sp.expand(-(g - a * x) / a)
        bare = -v if v.could_extract_minus_sign() else v
        if isinstance(bare, sp.Symbol) and bare != x and bare in symbols:
            return x, v
    return None


def eliminate_aliases(rhs: dict, constraints: list, algebraics: list, symbols: set):
    """Remove alias constraints and their algebraic variables.

    Parameters
    ----------
    rhs : dict Symbol -> Expr
        Right-hand sides of the ODEs (rewritten in place).
    constraints : list of Equation
    algebraics : list of Symbol
    symbols : set of Symbol
        What an alias may stand for (states, algebraics, parameters, t).

    Returns
    -------
    constraints, algebraics, aliases
        The remaining constraints (expressions substituted), the remaining algebraic
        variables, and ``[(name, expr, equation)]`` for every eliminated alias.
    """
    constraints, algebraics, aliases = list(constraints), list(algebraics), []
    found = True
    while found:
        found = False
        for k, eq in enumerate(constraints):
            hit = find_alias(eq.expr, algebraics, symbols)
            if hit is None:
                continue
            x, v = hit
            sub = {x: v}
            for y in rhs:
                rhs[y] = rhs[y].xreplace(sub)
            constraints = [replace(c, expr=c.expr.xreplace(sub)) for c in constraints[:k] + constraints[k + 1 :]]
            aliases = [(n, e.xreplace(sub), q) for n, e, q in aliases] + [(x.name, v, eq)]
            algebraics.remove(x)
            found = True
            break
    return constraints, algebraics, aliases


def blocks(constraints, algebraics) -> list[tuple[list[int], list[int]]]:
    """Connected blocks ``(constraint indices, algebraic indices)`` of the determining equations."""
    rows = incidence(constraints, algebraics)
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


def needed(outputs: list[str], rhs: dict, constraints, algebraics, aliases: dict) -> set[str]:
    """Names of the variables the outputs depend on (closure through the coupled system)."""
    depends: dict[str, set[str]] = {y.name: {s.name for s in e.free_symbols} for y, e in rhs.items()}
    for rows, cols in blocks(constraints, algebraics):
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

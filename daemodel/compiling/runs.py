"""Runs of repeated equations: one template, its leaves at indices that advance by fixed strides.

A discretised PDE declares the same equation at every grid point with shifted indices: at 10^5
unknowns reaction-diffusion's ``f`` and ``g`` are two such templates (and two boundary rows).  casadi's
virtual machine evaluates them at ~1 ns an operation; the C compiler cannot take the 10^5 expressions
(minutes), but it takes a template once.  :func:`equation_runs` finds, among the rows of ``f`` and
``g``, runs of consecutive rows of one template (the same tree of operations and the same numbers, its
symbols in the same places) whose leaves sit at ``base + stride * k`` in ``t``, ``x``, ``z`` or ``p``
and whose output row is ``base + stride * k`` too; the rows in no run are "the rest".  A backend
compiles each template as a small casadi function, a loop over each run and the rest as one function
(``backends/radau/stencil.py``).

Each template is the first member's expression converted by :class:`.codegen.CasadiConverter` with
its symbols replaced by the template's inputs: every member gets the operations, in the same order,
that the whole model's conversion (:meth:`.compiled.CompiledDAE.casadi_dae`) gives it, so that the
values are the same bits (checked by ``tests/compiling/test_runs.py``).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import sympy as sp

from daemodel.compiling.codegen import CasadiConverter
from daemodel.declaring.stencils import paused_collection

# A run holds at least this many rows (shorter ones are left to the rest: each run is a loop of its own).
RUN_MIN = 16
# The most runs and rest rows the compiled functions take: beyond, the model is not a repeated stencil
# (its rest would be the 10^5-expression function that the compiler cannot take) and none is made.
RUNS_MAX, REST_MAX = 10_000, 2_000

# The inputs of the functions, in order: where a leaf is read from.
INPUTS = ("t", "x", "z", "p")


class Run(NamedTuple):
    """``count`` rows of output ``output`` (0: f, 1: g), the k-th at row ``out_base + out_stride * k``,
    of template ``template``; its j-th leaf read from input ``inputs[j]`` (an index of :data:`INPUTS`)
    at ``bases[j] + strides[j] * k``."""

    template: int
    count: int
    inputs: tuple
    bases: tuple
    strides: tuple
    output: int
    out_base: int
    out_stride: int


class EquationRuns(NamedTuple):
    """The runs of a model's ``f`` and ``g`` (:func:`equation_runs`).

    templates : list of casadi.Function, each of its leaves (scalars) to one scalar
    runs : list of :class:`Run`
    rest : casadi.Function of ``(t, x, z, p)`` to the rows in no run (f's first), or None where none
    rest_rows : ``(f rows, g rows)``, int arrays: where the rest's outputs go
    sizes : ``(n, m, P)``
    """

    templates: list
    runs: list
    rest: object
    rest_rows: tuple
    sizes: tuple

    def describe(self) -> str:
        """How many templates, runs and rest rows, in a few words (a solve's stats)."""
        rest = len(self.rest_rows[0]) + len(self.rest_rows[1])
        rows = sum(run.count for run in self.runs)
        return f"{len(self.templates)} templates, {len(self.runs)} runs of {rows} rows, {rest} rows apart"


# One object per leaf position of a key (equal to nothing else).
_LEAF = [object() for _ in range(64)]


def _shape(expr, where: dict, leaves: list, seen: dict, numbers: dict):
    """``expr``'s tree as nested tuples: nodes as (type, *args), symbols of ``where`` as their place among
    ``leaves`` (first occurrence first, appended to ``leaves``), numbers as (type, value, sign), anything
    else as itself.  ``numbers`` memoises by ``id`` (every expression is alive while the rows are read:
    sympy's hashes of numbers were half of the search's time at 10^5 unknowns); symbols are looked up by
    equality (a model's expressions may hold an equal symbol that is another object)."""
    args = expr._args
    if not args:
        if expr.is_Symbol:
            k = seen.get(expr)
            if k is None and expr in where:
                k = seen[expr] = len(leaves)
                leaves.append(expr)
            if k is not None:
                return _LEAF[k] if k < len(_LEAF) else ("leaf", k)
            return expr
        value = numbers.get(id(expr))
        if value is None:
            number = CasadiConverter._number(expr)  # (its type too: x**(1/2) is a square root, x**0.5 a power)
            value = numbers[id(expr)] = expr if number is None else (type(expr), number, bool(np.signbit(number)))
        return value
    if isinstance(expr, sp.Piecewise):  # (its (value, condition) pairs: their parts)
        return (sp.Piecewise, *[_shape(part, where, leaves, seen, numbers) for pair in args for part in pair])
    return (type(expr), *[_shape(a, where, leaves, seen, numbers) for a in args])


def _runs(members: list, leaves: list, where: dict) -> list:
    """The runs among a group's rows ``members`` (increasing, one output), ``leaves[k]`` each row's
    leaves: ``[(first, last, inputs, indices)]`` of the maximal runs of at least :data:`RUN_MIN` rows."""
    if len(members) < RUN_MIN:
        return []
    count = len(leaves[members[0]])
    places = np.array([[where[s] for s in leaves[k]] for k in members], dtype=np.int64)
    places = places.reshape(len(members), count, 2)
    inputs, indices = places[..., 0], np.concatenate([places[..., 1], np.array(members)[:, None]], axis=1)
    step = np.diff(indices, axis=0)  # (rows - 1, leaves + 1): from each row to the next
    joins = (inputs[1:] == inputs[:-1]).all(axis=1)  # (row k and k + 1 read the same inputs)
    same = np.concatenate([[False], (step[1:] == step[:-1]).all(axis=1)])  # (step k as step k - 1)
    breaks = np.flatnonzero(~(joins & same))
    found, first, M = [], 0, len(members)
    while first < M - 1:
        if not joins[first]:
            first += 1
            continue
        # (the run first..last takes step[first] from each row to the next: up to the next break after first)
        at = np.searchsorted(breaks, first + 1)
        last = int(breaks[at]) if at < len(breaks) else M - 1
        if last - first + 1 >= RUN_MIN:
            found.append((first, last, inputs[first], indices[first], step[first]))
        first = last + 1
    return found


def equation_runs(compiled) -> EquationRuns | None:
    """The runs of ``compiled``'s ``f`` and ``g`` and their rest (see the module docs), or None where
    they are not a repeated stencil: more than :data:`RUNS_MAX` runs or :data:`REST_MAX` rest rows."""
    import casadi

    n, m, P = len(compiled.states), len(compiled.algebraics), len(compiled.parameters)
    where = {compiled.t: (0, 0)}
    for kind, symbols in ((1, compiled.states), (2, compiled.algebraics), (3, compiled.parameters)):
        where.update((symbol, (kind, i)) for i, symbol in enumerate(symbols))
    outputs = compiled._outputs()
    rows = [*outputs["f"][0], *outputs["g"][0]]
    groups, leaves, numbers = {}, [], {}
    with paused_collection():  # (10^6 tuples made: full collections would walk every tree of the model)
        for row, expr in enumerate(rows):
            leaves.append([])
            key = (row >= n, _shape(expr, where, leaves[-1], {}, numbers))
            groups.setdefault(key, []).append(row)
    templates, runs, covered = [], [], np.zeros(n + m, dtype=bool)
    for members in groups.values():
        found = _runs(members, leaves, where)
        if not found:
            continue
        first = leaves[members[found[0][0]]]
        symbols = [casadi.SX.sym(f"a{j}") for j in range(len(first))]
        template = CasadiConverter(dict(zip(first, symbols, strict=True)))(rows[members[found[0][0]]])
        templates.append(casadi.Function(f"template{len(templates)}", symbols, [casadi.SX(template)]))
        for start, last, inputs, indices, step in found:
            output, row = int(members[start] >= n), members[start]
            base = row - n * output
            runs.append(Run(len(templates) - 1, last - start + 1, tuple(int(i) for i in inputs),
                            tuple(int(i) for i in indices[:-1]), tuple(int(i) for i in step[:-1]), output, base,
                            int(step[-1])))  # fmt: skip
            covered[members[start : last + 1]] = True
        if len(runs) > RUNS_MAX:
            return None
    apart = np.flatnonzero(~covered)
    if not runs or len(apart) > REST_MAX:
        return None
    rest = None
    if len(apart):
        dae = compiled.casadi_dae()
        both = casadi.vertcat(dae["ode"], dae["alg"])
        rest = casadi.Function("rest", [dae["t"], dae["x"], dae["z"], dae["p"]], [both[apart.tolist()]])
    return EquationRuns(templates, runs, rest, (apart[apart < n], apart[apart >= n] - n), (n, m, P))

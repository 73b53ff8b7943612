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

from daemodel.compiling.codegen import CasadiConverter, casadi_jacobian
from daemodel.declaring.stencils import paused_collection

# A run holds at least this many rows (shorter ones are left to the rest: each run is a loop of its own).
RUN_MIN = 16
# The most runs and rest rows the compiled functions take: beyond, the model is not a repeated stencil
# (its rest would be the 10^5-expression function that the compiler cannot take) and none is made.
RUNS_MAX, REST_MAX = 10_000, 2_000
# A template's partial derivatives by forward sweeps, one per leaf: the order of operations of the whole
# model's Jacobian where casadi colours it forward (a band: each row's nonzeros few; dense rows apart too).
# casadi chose reverse for a template, a single row: rows of products of 11 neighbours' sines then differed
# from the whole model's Jacobian by up to 7e-16 relative.  Where casadi colours the whole model backward (a
# row reads 60 unknowns) neither sweep gives its bits: the values agree to rounding (4e-16), not bit for bit.
FORWARD = {"allow_forward": True, "allow_reverse": False}

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
    derivatives : list of casadi.Function, each template's leaves to its nonzero partial derivatives (in its
        leaves' order: ``derivative_leaves``)
    derivative_leaves : list of int arrays, the leaves each template's partial derivatives are in
    rest_jacobian : casadi.Function of ``(t, x, z, p)`` to the nonzeros of the rest's Jacobian in ``(x, z)``
        (column-major), or None where there is no rest or its Jacobian has no nonzeros (rows of t and constants)
    rest_pattern : ``(rows, cols)`` of those nonzeros: rows among the rest's, columns among ``(x, z)``
    rest_leaves : int array (k, 2), the inputs the rest reads, each ``(input, index)`` (input 0-3: t, x, z, p),
        input by input, indices increasing: the inputs of ``rest``'s and ``rest_jacobian``'s inner functions
        (``rest_rows``, ``rest_jacobian_rows``), which a caller may call on them alone
    rest_inner : those inner functions, ``(rest_rows, rest_jacobian_rows)`` (None where their outer one is None):
        casadi drops a call whose outputs are all zeros (rows apart ``u' = 0``), and with it the function the outer
        one would have named
    """

    templates: list
    runs: list
    rest: object
    rest_rows: tuple
    sizes: tuple
    derivatives: list = ()
    derivative_leaves: list = ()
    rest_jacobian: object = None
    rest_pattern: tuple = (np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64))
    rest_leaves: np.ndarray = np.zeros((0, 2), dtype=np.int64)
    rest_inner: tuple = (None, None)

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
    derivatives, derivative_leaves = [], []
    for members in groups.values():
        found = _runs(members, leaves, where)
        if not found:
            continue
        first = leaves[members[found[0][0]]]
        symbols = [casadi.SX.sym(f"a{j}") for j in range(len(first))]
        template = casadi.SX(CasadiConverter(dict(zip(first, symbols, strict=True)))(rows[members[found[0][0]]]))
        templates.append(casadi.Function(f"template{len(templates)}", symbols, [template]))
        # (its partial derivatives: casadi's AD of the template's operations, those of each member's row)
        partials = casadi.jacobian(template, casadi.vertcat(*symbols), FORWARD) if symbols else casadi.SX(1, 0)
        derivative_leaves.append(np.asarray(partials.sparsity().get_col(), dtype=np.int64))
        derivatives.append(casadi.Function(f"derivative{len(derivatives)}", symbols, [partials.nz[:]]))
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
    rest = rest_jacobian = None
    rest_pattern, rest_leaves, rest_inner = (
        EquationRuns._field_defaults[name] for name in ("rest_pattern", "rest_leaves", "rest_inner")
    )
    if len(apart):
        rest, rest_jacobian, rest_pattern, rest_leaves, rest_inner = _rest_functions(compiled, [rows[i] for i in apart])
    return EquationRuns(templates, runs, rest, (apart[apart < n], apart[apart >= n] - n), (n, m, P), derivatives,
                        derivative_leaves, rest_jacobian, rest_pattern, rest_leaves, rest_inner)  # fmt: skip


def _rest_functions(compiled, rows: list):
    """The rest's function of ``(t, x, z, p)`` to ``rows`` (the rows in no run), its Jacobian's function to
    its nonzeros in ``(x, z)`` (None where it has none), their pattern, the inputs the rows read and the two
    functions' inner functions (:class:`EquationRuns`' rest_leaves, rest_inner): the rows alone converted (not the
    whole model), each on the symbols it reads, an MX function gathering those from the whole inputs (casadi's
    function of the whole inputs' symbols held them all: 11 MB at 10^5 unknowns for rows of two boundaries)."""
    import casadi

    read = set().union(*(row.free_symbols for row in rows))
    table, places, local, whole, gathered = {}, [], [], [], []
    for kind, column in zip(
        INPUTS, ((compiled.t,), compiled.states, compiled.algebraics, compiled.parameters), strict=True
    ):
        places.append([i for i, symbol in enumerate(column) if symbol in read])
        symbols = [casadi.SX.sym(f"{kind}{i}") for i in places[-1]]
        table.update(zip((column[i] for i in places[-1]), symbols, strict=True))
        local.append(casadi.vertcat(*symbols) if symbols else casadi.SX(0, 1))
        whole.append(casadi.MX.sym(kind, len(column)))
        gathered.append(whole[-1][places[-1]] if places[-1] else casadi.MX(0, 1))
    both = CasadiConverter(table).stack(rows)
    inner_rows = casadi.Function("rest_rows", local, [both])
    rest = casadi.Function("rest", whole, [inner_rows(*gathered)])
    partials = casadi_jacobian(both, casadi.vertcat(local[1], local[2]))
    inner = casadi.Function("rest_jacobian_rows", local, [partials.nz[:]])
    # (rows that read no unknown (u' = sin t, a constant): no nonzeros, and casadi drops a call of no outputs, which
    # then has no inner function to compile or count: None, as for no rest)
    rest_jacobian = casadi.Function("rest_jacobian", whole, [inner(*gathered)]) if partials.nnz() else None
    local_rows, local_cols = (np.asarray(part, dtype=np.int64) for part in partials.sparsity().get_triplet())
    columns = np.asarray([*places[1], *(len(compiled.states) + j for j in places[2])], dtype=np.int64)
    leaves = np.array([(kind, i) for kind, indices in enumerate(places) for i in indices], dtype=np.int64)
    inners = (inner_rows, inner if rest_jacobian is not None else None)
    return rest, rest_jacobian, (local_rows, columns[local_cols]), leaves.reshape(-1, 2), inners


def jacobian_layout(runs: EquationRuns) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """``(rows, cols, taken)``: the nonzeros of ``[f_y f_z; g_y g_z]`` in casadi's order (column by column,
    rows increasing: :meth:`.compiled.CompiledDAE.casadi_jacobian_pattern`'s), and where each is in the
    values the runs' derivatives write (template by template, its runs in order, row by row, then the rest's
    Jacobian), or None where two of them are one entry (a row whose leaves meet at one unknown)."""
    n, m, _ = runs.sizes
    D = n + m
    rows, cols, taken, offset = [], [], [], 0
    for k, partials in enumerate(runs.derivative_leaves):
        for run in (r for r in runs.runs if r.template == k):
            steps = np.arange(run.count, dtype=np.int64)
            for place, leaf in enumerate(partials):
                kind = run.inputs[leaf]
                if INPUTS[kind] in ("x", "z"):
                    rows.append(run.output * n + run.out_base + run.out_stride * steps)
                    cols.append((0 if INPUTS[kind] == "x" else n) + run.bases[leaf] + run.strides[leaf] * steps)
                    taken.append(offset + steps * len(partials) + place)
            offset += run.count * len(partials)
    apart = np.concatenate([runs.rest_rows[0], runs.rest_rows[1] + n]).astype(np.int64)
    rows.append(apart[runs.rest_pattern[0]])
    cols.append(runs.rest_pattern[1])
    taken.append(offset + np.arange(runs.rest_pattern[0].size, dtype=np.int64))
    rows, cols, taken = (np.concatenate(parts) for parts in (rows, cols, taken))
    order = np.argsort(cols * D + rows, kind="stable")
    keys = cols[order] * D + rows[order]
    if keys.size and (np.diff(keys) == 0).any():
        return None
    index = index_for(D)  # (as casadi_jacobian_pattern's)
    taken = taken[order]
    return rows[order].astype(index), cols[order].astype(index), taken.astype(index_for(taken.size))


def index_for(size: int):
    """int32 where indices below ``size`` fit, else int64."""
    return np.int32 if size <= np.iinfo(np.int32).max else np.int64


def model_runs(compiled) -> EquationRuns | None:
    """:func:`equation_runs` of ``compiled``, made once per model."""
    return compiled.cached("equation-runs", lambda: equation_runs(compiled))


def runs_jacobian_layout(compiled) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """:func:`jacobian_layout` of :func:`model_runs`, made once per model; None where the model is no
    repeated stencil or the layout is none."""

    def build():
        runs = model_runs(compiled)
        return None if runs is None else jacobian_layout(runs)

    return compiled.cached("equation-runs-jacobian-layout", build)

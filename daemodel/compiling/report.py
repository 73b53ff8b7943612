"""The compiled model's report (:meth:`CompiledDAE.report`): variables, equations, the index of each
constraint, switches, events, initialisation and pruning, as text.

A model of 10^5 unknowns made a report of 10^5 equations (38.5 s at 10^5 unknowns, 17.7 MB: sympy
prints each equation, its terms sorted), which no one reads.  By default each run of more than
:data:`SUMMARY_ROWS` entries of a section (the elements of one array, ``c[0]`` to ``c[99999]``, or
consecutive scalar names, ``c_1`` to ``c_99999``) shows its first :data:`HEAD_ROWS` entries, one line
that says how many are left out and how to see them, and its last entry; only what is shown is
printed.  ``full=True`` lists every entry, as before.
"""

from __future__ import annotations

import itertools

from daemodel.compiling.structure import ITERATION_MATRIX
from daemodel.declaring.arrays import split_element

# A run of more than this many entries (an array's elements, or consecutive scalars) is summarised:
# models of up to 50 variables of a kind (the IVP test set's: at most 27 unknowns, but Fekete's 160)
# read as before.
SUMMARY_ROWS = 50
# Entries shown at the start of a summarised run (and its last one after the summary line).
HEAD_ROWS = 3
FULL_HINT = "report(full=True) lists every one"


def report(compiled, full: bool = False) -> str:
    """The report of ``compiled`` (see the module docstring): every entry with ``full``, else each
    long run of a section summarised."""
    c = compiled
    kind = {0: "ODE", 1: "index-1 DAE", 2: "index-2 DAE", 3: "index-3 DAE"}[c.index]
    lines = [f"Model '{c.name}': {kind} (semi-explicit), t0 = {c.t0:g}"]
    if c.reduced_from:
        lines[0] += f", reduced from index {c.reduced_from}"

    def state(i: int) -> list[str]:
        name = c.states[i].name
        return [f"  #{c.ode_numbers[i]:<3d} {name}' = {c.rhs[i]}", f"        {name}(t0) = {c.y0[i]:.16g}"]

    def algebraic(i: int) -> list[str]:
        owner = c.constraints[c.determined_by[i]]
        how = {
            1: owner.name,
            2: f"hidden constraint {owner.level_name(1)}",
            3: f"hidden constraint {owner.level_name(2)}",
        }
        return [f"  {c.algebraics[i].name}(t0) = {c.z0[i]:.16g}   (consistent: from {how[owner.index]} = 0)"]

    def parameter(i: int) -> list[str]:
        return [f"  {c.parameters[i].name} = {c.parameter_values[i]:.16g}"]

    def constraint(i: int) -> list[str]:
        k = c.constraints[i]
        out = [
            f"  #{k.number:<3d} {k.name}: 0 = {k.expr}",
            f"        index {k.index}: determines the algebraic variables through {ITERATION_MATRIX[k.index]}",
        ]
        return out + [f"        {k.level_name(j)} = {k.chain[j]}" for j in range(1, k.index)]

    def alias(i: int) -> list[str]:
        name, expr, label = c.aliases[i]
        return [f"  {name} = {expr}   (from {label})"]

    lines.append(f"Differential variables ({len(c.states)}):")
    lines += listing(c.state_names, state, full)
    lines.append(f"Algebraic variables ({len(c.algebraics)}):")
    lines += listing(c.algebraic_names, algebraic, full)
    if c.parameters:
        lines.append(f"Parameters ({len(c.parameters)}):")
        lines += listing(c.parameter_names, parameter, full)
    lines.append(f"Constraints ({len(c.constraints)}):")
    lines += listing([k.name for k in c.constraints], constraint, full)
    if c.aliases:
        lines.append(f"Aliases eliminated ({len(c.aliases)}):")
        lines += listing([name for name, _, _ in c.aliases], alias, full)
    if c.invariants:
        lines.append("Invariants (drift): " + names_line(c.invariant_names, full))
    from daemodel.compiling.switches import find_switches

    switches = find_switches(c)
    if switches:
        lines.append(f"Switches ({len(switches)}):")
        lines += listing([s.equation for s in switches], lambda i: [f"  {switches[i].describe()}"], full)
    if c.events:
        lines.append(f"Events ({len(c.events)}):")
        state_names = c.state_names
        lines += listing([e.name for e in c.events], lambda i: [f"  {c.events[i].describe(state_names)}"], full)
    lines.append("Initialisation: " + ("; ".join(c.notes) if c.notes else "given values are consistent"))
    dropped = {k: v for k, v in c.dropped.items() if v}
    if dropped:
        lines.append("Pruned (not needed by the requested outputs):")
        lines += [f"  {kind}: {names_line(names, full)}" for kind, names in dropped.items()]
    else:
        lines.append("Pruned: nothing (every variable is needed)")
    return "\n".join(lines)


def runs(names) -> list[tuple[int, int]]:
    """``(start, stop)`` of each run of ``names``: consecutive elements of one array (``u[0]``, ``u[1]``,
    ...), or consecutive names of no array."""
    out, start = [], 0
    for _, group in itertools.groupby(names, key=_array_of):
        stop = start + sum(1 for _ in group)
        out.append((start, stop))
        start = stop
    return out


def _array_of(name: str) -> str | None:
    """The array whose element ``name`` is (``"u"`` for ``u[3]``, ``u'`` included), else None."""
    parts = split_element(name.rstrip("'")) if "[" in name else None
    return None if parts is None else parts[0]


def listing(names, entry, full: bool) -> list[str]:
    """The lines of ``entry(i)`` for each entry ``i`` of a section whose entries are named ``names``:
    every one with ``full``, else each run longer than :data:`SUMMARY_ROWS` as its first
    :data:`HEAD_ROWS`, a line counting those left out, and its last."""
    lines = []
    for start, stop in runs(names):
        if full or stop - start <= SUMMARY_ROWS:
            shown = range(start, stop)
        else:
            shown = [*range(start, start + HEAD_ROWS), None, stop - 1]
        for i in shown:
            if i is None:
                left = stop - 1 - (start + HEAD_ROWS)
                first, last = names[start + HEAD_ROWS], names[stop - 2]
                lines.append(f"  ... {left:,} more, {first} to {last} ({FULL_HINT})")
            else:
                lines += entry(i)
    return lines


def names_line(names, full: bool) -> str:
    """``names`` joined by commas, each run longer than :data:`SUMMARY_ROWS` shortened as :func:`listing`
    shortens it."""
    parts = []
    for start, stop in runs(names):
        if full or stop - start <= SUMMARY_ROWS:
            parts += names[start:stop]
        else:
            left = stop - 1 - (start + HEAD_ROWS)
            parts += [*names[start : start + HEAD_ROWS], f"... {left:,} more ...", names[stop - 1]]
    shortened = not full and len(parts) < len(names)
    return ", ".join(parts) + (f" ({FULL_HINT})" if shortened else "")

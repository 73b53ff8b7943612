"""Drawing a :class:`~daemodel.solution.Solution`: the solution the method computed, not its output grid.

Each variable is drawn against t:

* from the method's dense output (:attr:`Solution.dense`, evaluated by :meth:`Solution.at` at the
  method's own accuracy) on :data:`DRAWN_POINTS` times across the span and the output times, so that
  a bouncing ball's flights are parabolas, not chords between a few output points; without a dense
  output (a method that keeps none, a loaded file without one), the output points with markers,
  joined by straight segments;
* broken at every event and time breakpoint: each piece runs up to its own end value (the left
  limit, the value before the reset) and the next starts from the value after it (the right limit),
  so that no line joins the two sides of a jump;
* with the instants marked as ticks on the time axis, one colour and one legend entry per event name
  (and one for the time breakpoints).

:func:`plot_solution` draws a whole figure (:meth:`Solution.plot`); :func:`draw_variable` and
:func:`mark_instants` draw one panel, for any figure that shows solutions.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from itertools import pairwise

import numpy as np

from daemodel.declaring.arrays import element_name, element_names, split_element
from daemodel.errors import OmittedPanelsWarning, ResourceLimitError
from daemodel.files import save_figure
from daemodel.instants import BREAKPOINTS

# Samples drawn by Solution.plot for a batch; more lines only hide each other.
PLOTTED_SAMPLES = 20
# Panels Solution.plot() draws without names=: four rows of three stay readable on a screen or a
# page; a 62-variable model drew 62 panels of a few pixels each.
PLOTTED_PANELS = 12

# Times across the span on which a dense output is drawn (with the output times): a figure is about
# 1000 pixels wide, so a curve drawn on twice that shows no chord; a flight of the bouncing ball
# (g = 9.81) on a span of 2.5 is drawn to g (2.5 / 2000)^2 / 8 = 2e-6 at its apex.
DRAWN_POINTS = 2001
# Colours of the instants' ticks, one per event name: the solution is C0 and a reference C3.
INSTANT_COLORS = ("C1", "C2", "C4", "C5", "C6", "C8", "C9", "C7")


@dataclass(frozen=True)
class Instant:
    """One event or time breakpoint of one sample: its time, its label, each variable's value on each side."""

    t: float
    label: str
    before: dict
    after: dict


def instants_of(records: dict, sample: int, names, span: tuple) -> list[Instant]:
    """The instants of one sample, in time order, from records laid out as :attr:`Solution.events`
    (label -> ``"t"`` (B, K), ``"before"`` and ``"after"`` name -> (B, K)); NaN padding and instants
    outside ``span`` are left out, and a variable a record lacks is NaN on both sides."""
    out = []
    for label, record in records.items():
        times = np.asarray(record["t"], dtype=float)
        row = min(sample, len(times) - 1)
        for j, t in enumerate(times[row]):
            if not (span[0] < t <= span[1]):  # (NaN: a batch's padding)
                continue
            sides = {}
            for side in ("before", "after"):
                values = record[side]
                sides[side] = {
                    name: float(np.asarray(values[name], dtype=float)[row, j]) if name in values else np.nan
                    for name in names
                }
            out.append(Instant(float(t), label, sides["before"], sides["after"]))
    return sorted(out, key=lambda instant: instant.t)


def solution_records(solution) -> dict:
    """The solution's breakpoints (as :data:`BREAKPOINTS`) and events, label -> record, with the values
    of the eliminated aliases on each side computed from those of the states and algebraic variables."""
    records = ({BREAKPOINTS: solution.breakpoints} if solution.breakpoints else {}) | dict(solution.events)
    c = solution.compiled
    if not c.aliases:
        return records
    aliases = c.numeric.batch_function([e for _, e, _ in c.aliases])
    out = {}
    for label, record in records.items():
        times = np.asarray(record["t"], dtype=float)
        B, K = times.shape
        full = {"t": times}
        for side in ("before", "after"):
            values = dict(record[side])
            if K and not set(c.alias_names) <= set(values):
                with np.errstate(invalid="ignore"):  # (NaN padding)
                    found = aliases(
                        times.reshape(B * K),
                        rows(values, c.state_names, B * K),
                        rows(values, c.algebraic_names, B * K),
                        np.repeat(solution.parameters, K, axis=0),
                    )
                values |= {name: found[:, i].reshape(B, K) for i, name in enumerate(c.alias_names)}
            full[side] = values
        out[label] = full
    return out


def rows(values: dict, names, count: int) -> np.ndarray:
    """The values of ``names`` as ``(count, len(names))`` rows (each value of shape (B, K), B*K = count)."""
    if not names:
        return np.zeros((count, 0))
    return np.stack([np.asarray(values[n], dtype=float).reshape(count) for n in names], axis=-1)


def broken_curve(grid: np.ndarray, values: np.ndarray, instants: list[Instant], name: str) -> tuple:
    """``(t, y)`` to draw: ``values`` (on ``grid``, ascending, from the span's start to its end) cut at
    each instant, each piece ending at the instant's value before it and the next starting at its value
    after it, the pieces joined by NaN (a break in the line)."""
    edges = [(grid[0], None), *((i.t, i) for i in instants), (grid[-1], None)]
    t_out, y_out = [], []
    for (start, opening), (end, closing) in pairwise(edges):
        first, last = opening is None, closing is None
        if end <= start and (first or last):
            continue  # an instant at the span's end: nothing after it
        inside = (grid > start) & (grid < end)
        t_piece = [start, *grid[inside], end]
        y_piece = [
            values[0] if first else opening.after[name],
            *values[inside],
            values[-1] if last else closing.before[name],
        ]
        if t_out:
            t_out.append(np.nan)
            y_out.append(np.nan)
        t_out += t_piece
        y_out += y_piece
    return np.asarray(t_out, dtype=float), np.asarray(y_out, dtype=float)


@dataclass(frozen=True)
class Drawn:
    """What a figure draws of a solution: the times, each variable's values there (B, K), and whether
    they come from the dense output (a fine grid) or are the output points."""

    grid: np.ndarray
    values: dict
    dense: bool


def drawn_values(solution, names) -> Drawn:
    """The values to draw: the dense output on :data:`DRAWN_POINTS` times and the output times, or the
    output points where the solution has no dense output (or a batch too large to evaluate it for)."""
    t = solution.t
    if solution.dense is not None:
        grid = np.union1d(np.linspace(t[0], t[-1], DRAWN_POINTS), t)
        try:
            found = solution.at(grid)
        except ResourceLimitError:
            found = None  # a batch whose dense values at every time would not fit: its output points
        if found is not None:
            values = {name: np.asarray(found[name]).reshape(solution.batch_size, len(grid)) for name in names}
            return Drawn(grid, values, True)
    return Drawn(t, {name: solution.values[name] for name in names}, False)


def draw_variable(ax, solution, name: str, drawn: Drawn | None = None, samples=None, **style) -> list:
    """Draw one variable of ``solution`` on ``ax``, each sample's line broken at its own events and
    breakpoints (see the module docs); returns the lines (``gid`` ``"solution"``).

    Parameters
    ----------
    drawn : Drawn, optional
        The values from :func:`drawn_values` (computed here for ``name`` when not given).
    samples : int, optional
        How many samples of a batch to draw; default up to :data:`~daemodel.plotting.PLOTTED_SAMPLES`.
    style
        Passed to ``ax.plot`` (colour, line width, ...).
    """
    drawn = drawn_values(solution, [name]) if drawn is None else drawn
    shown = min(solution.batch_size, PLOTTED_SAMPLES if samples is None else samples)
    records = solution_records(solution)
    span = (float(solution.t[0]), float(solution.t[-1]))
    style = {"color": "C0", "lw": 1.2 if shown == 1 else 0.7, "alpha": 1 if shown == 1 else 0.6} | style
    if not drawn.dense:
        style = {"marker": "o", "markersize": 2.5 if shown == 1 else 1.5} | style
    lines = []
    for b in range(shown):
        t, y = broken_curve(drawn.grid, drawn.values[name][b], instants_of(records, b, [name], span), name)
        lines += ax.plot(t, y, **({"gid": "solution"} | style))
    return lines


def draw_reference(ax, reference, name: str, grid: np.ndarray, span: tuple) -> list:
    """Draw a reference dashed on ``ax``: a :class:`Solution` (its first sample, from its own dense
    output), or a callable ``t -> dict name -> values`` evaluated on ``grid`` and broken at the instants
    it states by attributes ``events`` and ``breakpoints`` laid out as :attr:`Solution.events` (as
    :meth:`Problem.exact_solution` does); nothing where it has no values for ``name``."""
    style = {"linestyle": "--", "color": "C3", "lw": 1, "label": "reference", "gid": "reference"}
    if not callable(reference):  # a Solution
        if name not in reference.names:
            return []
        return draw_variable(ax, reference, name, samples=1, **style)
    values = reference(grid)
    if name not in values:
        return []
    records = dict(getattr(reference, "events", None) or {})
    breakpoints = getattr(reference, "breakpoints", None)
    if breakpoints:
        records[BREAKPOINTS] = breakpoints
    y = np.broadcast_to(np.asarray(values[name], dtype=float), grid.shape)
    t, y = broken_curve(grid, y, instants_of(records, 0, [name], span), name)
    return ax.plot(t, y, **style)


def mark_instants(ax, solution, samples=None) -> list:
    """Ticks on the time axis of ``ax`` at the events and breakpoints of the drawn samples, one colour and
    one label per event name (``gid`` ``"instant"``); returns the marks."""
    from matplotlib.transforms import blended_transform_factory

    shown = min(solution.batch_size, PLOTTED_SAMPLES if samples is None else samples)
    span = (float(solution.t[0]), float(solution.t[-1]))
    on_axis = blended_transform_factory(ax.transData, ax.transAxes)
    marks = []
    records = ({BREAKPOINTS: solution.breakpoints} if solution.breakpoints else {}) | dict(solution.events)
    for i, (label, record) in enumerate(records.items()):
        times = np.asarray(record["t"], dtype=float)[:shown].ravel()
        times = np.unique(times[(times > span[0]) & (times <= span[1])])
        if not len(times):
            continue
        marks += ax.plot(
            times,
            np.zeros_like(times),
            linestyle="none",
            marker="|",
            markersize=9,
            markeredgewidth=1.2,
            color=INSTANT_COLORS[i % len(INSTANT_COLORS)],
            transform=on_axis,
            clip_on=False,
            label=label,
            gid="instant",
        )
    return marks


def element_names_of(solution, names) -> list:
    """``names`` with each array's name (``"u"``, declared by ``m.states("u", 100)``) spread over its
    elements, in numpy's order, and an element written with spaces (``"T[3, 4]"``) as declared."""
    arrays, out = solution.compiled.arrays, []
    for name in names:
        parts = split_element(name) if isinstance(name, str) else None
        if isinstance(name, str) and name in arrays:
            out += element_names(name, arrays[name])
        elif parts is not None and parts[0] in arrays:
            out.append(element_name(*parts, arrays[parts[0]], "plot(names=...)"))
        else:
            out.append(name)
    return out


def plot_solution(solution, path=None, names=None, reference=None):
    """:meth:`Solution.plot`: each variable against t, one panel each; a batch shows up to
    :data:`~daemodel.plotting.PLOTTED_SAMPLES` samples (see the module docs for what is drawn).

    Parameters
    ----------
    path : str or Path, optional
        Write the figure there (PNG, PDF, ... by suffix).
    names : iterable of str, optional
        Variables to draw, all of them (an array's name: each of its elements).  Default: the
        states, then the algebraic variables, at most :data:`~daemodel.plotting.PLOTTED_PANELS` of
        them; where more were left out, the figure's title says how many and an
        :class:`~daemodel.errors.OmittedPanelsWarning` names them.
    reference : callable or Solution, optional
        Drawn dashed on top (first sample only for a batch), see :func:`draw_reference`.

    Returns
    -------
    matplotlib.figure.Figure
    """
    from matplotlib.figure import Figure

    compiled = solution.compiled
    omitted = []
    if names is None:
        every = [*compiled.state_names, *compiled.algebraic_names]
        names, omitted = every[:PLOTTED_PANELS], every[PLOTTED_PANELS:]
    else:
        names = element_names_of(solution, names)
    if omitted:
        listed = ", ".join(omitted[:PLOTTED_PANELS]) + (", ..." if len(omitted) > PLOTTED_PANELS else "")
        warnings.warn(
            f"plot() drew {len(names)} of the {len(names) + len(omitted)} variables of '{compiled.name}' and "
            f"left out {len(omitted)} ({listed}); choose them with names=[...]",
            OmittedPanelsWarning,
            stacklevel=3,  # (the caller of Solution.plot)
        )
    for name in names:
        solution[name]  # raises for unknown names before drawing anything
    drawn = drawn_values(solution, names)
    span = (float(solution.t[0]), float(solution.t[-1]))
    reference_grid = drawn.grid if drawn.dense else np.union1d(np.linspace(*span, DRAWN_POINTS), solution.t)
    columns = min(3, len(names))
    rows = -(-len(names) // columns)
    fig = Figure(figsize=(4.2 * columns, 2.8 * rows), layout="constrained")
    axes = fig.subplots(rows, columns, squeeze=False, sharex=True)
    shown = min(solution.batch_size, PLOTTED_SAMPLES)
    legend = {}
    for ax, name in zip(axes.flat, names, strict=False):
        draw_variable(ax, solution, name, drawn)
        if reference is not None:
            for line in draw_reference(ax, reference, name, reference_grid, span):
                legend.setdefault(line.get_label(), line)
        for mark in mark_instants(ax, solution):
            legend.setdefault(mark.get_label(), mark)
        ax.set_title(name)
        ax.grid(alpha=0.3)
    for ax in axes.flat[len(names) :]:
        ax.set_visible(False)
    # the lowest visible panel of each column carries the time axis (sharex hides the others'
    # tick labels, and the last row may be partly empty)
    for column in range(columns):
        lowest = max(row for row in range(rows) if row * columns + column < len(names))
        axes[lowest, column].tick_params(labelbottom=True)
        axes[lowest, column].set_xlabel("t")
    if legend:  # one legend for the panels, below them, where it hides no data
        handles, labels = list(legend.values()), list(legend)
        fig.legend(handles, labels, loc="outside lower center", ncols=min(len(labels), 4), fontsize=8)
    batch = f", {shown} of {solution.batch_size} samples" if solution.batched else ""
    points = "" if drawn.dense else ", drawn through its output points"
    left_out = f"\n{len(names)} of {len(names) + len(omitted)} variables; names=[...] chooses" if omitted else ""
    fig.suptitle(f"{compiled.name}: {solution.method}{batch}{points}{left_out}")
    if path is not None:
        save_figure(fig, path, "plot path", dpi=120)
    return fig

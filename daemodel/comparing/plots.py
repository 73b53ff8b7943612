"""The work-precision plot of a :class:`~daemodel.comparing.tables.Comparison`: max absolute error
against time, log-log, one curve per method through its sweep."""

from __future__ import annotations

import math

import numpy as np

from daemodel.errors import ComparisonError
from daemodel.files import save_figure

# What Comparison.plot can put on its time axis: the solve time, or setup plus solve.
CLOCKS = ("solve", "total")
# Below this many decades a log axis is labelled at 1, 2 and 5 times powers of ten (a power alone
# may not fall inside it); above, at powers of ten only, at most LOG_LABELS of them.
LABEL_125_DECADES = 2.0
LOG_LABELS = 7


def work_precision(comparison, path=None, clock: str = "solve"):
    """Work-precision plot: max absolute error against time, log-log, one curve per method
    through its sweep; differential and algebraic variables in separate panels.

    ``clock="solve"`` (default) draws :attr:`~daemodel.comparing.tables.Run.solve_time`, each method's median setup time
    noted in the legend; ``clock="total"`` draws setup plus solve.  The legend names each
    curve's sweep from its cheapest setting to its most accurate (``h=0.1 -> 0.0125``), so
    no label sits on the data, where the curves of methods with equal settings would make
    them collide.  A setting that failed is an ``x`` on the top edge at the time it took to
    fail, and the legend counts the failures.

    Returns
    -------
    matplotlib.figure.Figure
    """
    from matplotlib.figure import Figure
    from matplotlib.transforms import blended_transform_factory

    if clock not in CLOCKS:
        raise ComparisonError(f"clock must be one of {', '.join(map(repr, CLOCKS))}; got {clock!r}")
    groups = [("differential variables", comparison.states)]
    if comparison.algebraics:
        groups.append(("algebraic variables", comparison.algebraics))
    fig = Figure(figsize=(6.2 * len(groups), 4.6), layout="constrained")
    axes = fig.subplots(1, len(groups), squeeze=False)[0]
    methods = list(dict.fromkeys(run.method for run in comparison.runs))
    for ax, (title, names) in zip(axes, groups, strict=True):
        top_edge = blended_transform_factory(ax.transData, ax.transAxes)
        all_times, all_errors = [], []
        for i, method in enumerate(methods):
            runs = [r for r in comparison.runs if r.method == method and r.failure is None]
            failed = [r for r in comparison.runs if r.method == method and r.failure is not None]
            label = method + (f": {_sweep_range(runs)}" if runs else "")
            if runs and clock == "solve":
                label += f" (setup {_seconds(float(np.median([r.setup_time for r in runs])))})"
            if failed:
                label += f", {len(failed)} of {len(failed) + len(runs)} failed"
            times = [r.solve_time + (r.setup_time if clock == "total" else 0.0) for r in runs]
            errors = [max(max(r.errors[n]["max"] for n in names), 1e-17) for r in runs]
            ax.loglog(times, errors, "o-", color=f"C{i}", label=label)
            shown = [r for r in failed if math.isfinite(r.solve_time) and r.solve_time > 0]
            if shown:  # at the time it took to fail, on the top edge: no error to place it by
                ax.plot([r.solve_time for r in shown], [0.98] * len(shown), "x", color=f"C{i}", transform=top_edge)
            all_times += [t for t in times if math.isfinite(t) and t > 0] + [r.solve_time for r in shown]
            all_errors += [e for e in errors if math.isfinite(e)]
        if all_times:
            readable_log_axis(ax.xaxis, min(all_times), max(all_times))
        if all_errors:
            readable_log_axis(ax.yaxis, min(all_errors), max(all_errors))
        ax.set_xlabel("solve time [s]" if clock == "solve" else "setup + solve time [s]")
        listed = ", ".join(names) if len(names) <= 6 else f"{names[0]} ... {names[-1]}, {len(names)} variables"
        ax.set_ylabel(f"max absolute error ({listed})")
        ax.set_title(title)
        ax.grid(which="both", alpha=0.25)
    # one legend for the panels, below them, where it hides no data
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncols=min(len(labels), 2), fontsize=8)
    t0, t1 = comparison.t_span
    fig.suptitle(f"{comparison.model} on [{t0:g}, {t1:g}]: error against {comparison.reference}")
    if path is not None:
        save_figure(fig, path, "plot path", dpi=130)
    return fig


def readable_log_axis(axis, low: float, high: float) -> None:
    """Label a log ``axis`` holding data from ``low`` to ``high`` (> 0) so that no two labels overlap:
    at 1, 2 and 5 times powers of ten below :data:`LABEL_125_DECADES` decades (the limits widened to
    the 1-2-5 values around the data, so at least two labels show), at powers of ten (at most
    :data:`LOG_LABELS`) above; minor ticks unlabelled.  Matplotlib's default labels the minor ticks
    of a narrow log axis, "3x10^-3" beside "4x10^-3", which overlap."""
    from matplotlib.ticker import FixedLocator, FuncFormatter, LogLocator, NullFormatter

    low, high = float(low), float(high)
    if not (0 < low <= high and math.isfinite(high)):
        return
    if high == low:
        low, high = low / 1.5, high * 1.5
    set_limits = axis.axes.set_xlim if axis is axis.axes.xaxis else axis.axes.set_ylim
    if math.log10(high / low) < LABEL_125_DECADES:
        first, last = math.floor(math.log10(low)) - 1, math.ceil(math.log10(high)) + 1
        candidates = [m * 10.0**k for k in range(first, last + 1) for m in (1, 2, 5)]
        below = max(c for c in candidates if c <= low * (1 + 1e-12))
        above = min(c for c in candidates if c >= high * (1 - 1e-12))
        axis.set_major_locator(FixedLocator([c for c in candidates if below <= c <= above]))
        set_limits(below, above)
    else:
        axis.set_major_locator(LogLocator(base=10.0, numticks=LOG_LABELS))
    axis.set_major_formatter(FuncFormatter(_power_label))
    axis.set_minor_formatter(NullFormatter())


def _power_label(value: float, _position=None) -> str:
    """``2e-3`` as "2x10^-3" in mathtext, ``1e-3`` as "10^-3"."""
    if not value > 0:
        return ""
    exponent = math.floor(math.log10(value) + 1e-9)
    mantissa = round(value / 10.0**exponent, 6)
    if mantissa == 1:
        return f"$10^{{{exponent}}}$"
    return f"${mantissa:g}\\times10^{{{exponent}}}$"


def _sweep_range(runs) -> str:
    """``"h=0.1 -> 0.0125"``: a sweep's first and last setting, the name said once where both share it."""
    first, last = (runs[0].short or runs[0].settings), (runs[-1].short or runs[-1].settings)
    if len(runs) == 1 or first == last:
        return first
    head, _, _ = first.partition("=")
    if "," not in first and last.startswith(head + "="):
        last = last[len(head) + 1 :]
    return f"{first} -> {last}"


def _seconds(value: float) -> str:
    """A duration for a legend: ``"0.81 ms"``, ``"795 ms"``, ``"1.24 s"``."""
    return f"{value * 1e3:.3g} ms" if value < 1 else f"{value:.3g} s"

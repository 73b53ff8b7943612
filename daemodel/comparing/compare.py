"""Every method on one model: time against error, as a table and a work-precision plot.

>>> result = dm.compare(model, (0.0, 1.0), methods=["radau", "casadi-idas", "pinn"])
>>> print(result.table())
>>> result.save("results/")            # <model>.json, <model>.csv, <model>_work_precision.png

Each method is solved over a sweep of its accuracy setting (its backend's
``work_precision``: step sizes h for the fixed-step methods, tolerances for the adaptive
ones), and every solution is measured against one reference: the model's exact solution
when given, else ``method="reference"`` (scipy at rtol = atol = 1e-12) on the same times.

Clocks: every method reports the same two (:attr:`Solution.solve_time`, producing the values from
a ready method; :attr:`Solution.setup_time`, getting ready: code generation, integrator
construction, training).  The table shows both; the plot draws the solve time by default (the
setup noted in the legend) or their sum (``clock="total"``).

User mistakes (an unknown method or option, a setting its method refuses, a grid too large
to solve, a reference that raises or is not finite) are refused before the first solve; a
method that fails at a setting is recorded as a failed run, shown as such in the table.
"""

from __future__ import annotations

import csv
import dataclasses
import math
import time
import traceback
import warnings
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from daemodel.backends import REFERENCE, get_backend
from daemodel.backends import methods as registered_methods
from daemodel.backends.grids import SWEEP_FIRST_STEPS, fixed_grid
from daemodel.backends.torch_setup import torch_device
from daemodel.errors import (
    ComparisonError,
    ModelError,
    ResourceLimitError,
    SolverError,
)
from daemodel.files import (
    atomic_write,
    file_name,
    read_json,
    readable_path,
    save_figure,
    writable_directory,
    writable_file,
    write_json,
)

# Sweep points per method when compare() is not told otherwise.
DEFAULT_POINTS = 4
# The table's words for why a PINN's certificate failed at a step (keys: NEWTON_FAILED,
# ESTIMATE_FAILED, NO_DIGIT of backends/pinn/certificate.py, which imports torch).
CERTIFICATE_FAILURES = {
    "newton": "failed (Newton from the networks)",
    "estimate": "failed (no Radau error estimate)",
    "digit": "failed (Radau's step has no correct digit)",
}
# Most sweep points: a fixed-step sweep halves h from span/steps at each point, so point 12 is
# already span/(2,048 steps) (20,480 steps per solve at the default steps = 10), and each
# further point doubles the time.
MAX_POINTS = 12
# Most fixed-grid steps one compared setting may take, refused before any solve: radau's
# default max_steps, five times the finest default sweep point.
MAX_SWEEP_STEPS = 100_000
# Times across t_span on which a reference callable is checked before the first solve.
REFERENCE_CHECK_POINTS = 11
# What Comparison.plot can put on its time axis: the solve time, or setup plus solve.
CLOCKS = ("solve", "total")


@dataclass(frozen=True)
class Run:
    """One solve of one method at one setting.

    Attributes
    ----------
    method : str
    settings : str
        The options that were swept, e.g. ``"h=0.05"`` or ``"rtol=1e-06, atol=1e-08"``.
    solve_time : float
        :attr:`Solution.solve_time` in seconds; for a failed run, the time until it failed.
    setup_time : float
        :attr:`Solution.setup_time` in seconds (training for ``pinn``); NaN for a failed run (null in
        the JSON).
    errors : dict name -> {"max": float, "mean": float}
        Absolute errors against the reference over the output times, except those within the window
        of an event or breakpoint (:mod:`daemodel.instants`; ``excluded`` counts them).
    drift : dict constraint -> float
        Max ``|g|`` of each original constraint along the solution.
    failure : str or None
        The error message when the method failed at this setting (then no errors).
    short : str
        The part of ``settings`` that changes along the method's sweep (plot labels).
    messages : tuple of str
        The warnings the solve raised (``"Category: text"``, each once), kept here instead of
        printed above the table; casadi's own printed output is caught by its backend and,
        when it explains a failure, quoted in ``failure``.
    status : str
        :attr:`Solution.status` ("success", or why not: a PINN answer that is not certified starts
        with "flagged").
    certificate : dict
        A PINN run's certificate where the ratio of the two is largest: ``distance`` (from the
        Radau solution at the same h) and ``radau_error`` (what it is compared with: Radau's own
        error there, or the rounding floor); empty otherwise.
    step : tuple
        ``(stages, h)`` of a fixed-step run (radau, casadi-collocation, pinn), else empty: runs on
        the same grid, whose times the table compares.
    instants : dict label -> dict
        Per event name (and ``"time breakpoints"``): ``count`` and ``reference_count`` (None where the
        reference states no instants), ``t`` (max ``|t_a - t_b|`` of the paired instants), ``before``
        and ``after`` (max error over the variables of the values just before and just after them,
        each side at its own instant); empty for a model without either.
    excluded : int
        Output values left out of ``errors`` for lying within the window of an instant.
    """

    method: str
    settings: str
    solve_time: float
    setup_time: float
    errors: dict
    drift: dict
    failure: str | None = None
    short: str = ""
    messages: tuple = ()
    status: str = "success"
    certificate: dict = dataclasses.field(default_factory=dict)
    step: tuple = ()
    instants: dict = dataclasses.field(default_factory=dict)
    excluded: int = 0


@dataclass(frozen=True)
class Comparison:
    """The runs of :func:`compare` on one model.

    Attributes
    ----------
    model : str
    t_span : (float, float)
    reference : str
        What the errors are measured against.
    states, algebraics : tuple of str
    runs : tuple of Run
    """

    model: str
    t_span: tuple
    reference: str
    states: tuple
    algebraics: tuple
    runs: tuple

    @property
    def names(self) -> tuple:
        return (*self.states, *self.algebraics)

    def records(self) -> list[dict]:
        """One flat dict per run: method, settings, solve_time, setup_time, ``<var>_max``, ``<var>_mean``,
        ``drift_<constraint>``, for a model with events or breakpoints ``<event>_count``,
        ``<event>_reference_count``, ``<event>_t``, ``<event>_before``, ``<event>_after`` and ``excluded``
        (:attr:`Run.instants`), failure, status, ..."""
        out = []
        drift_names = sorted({k for r in self.runs for k in r.drift})
        labels = list(dict.fromkeys(k for r in self.runs for k in r.instants))
        for run in self.runs:
            row = {
                "method": run.method,
                "settings": run.settings,
                "solve_time": run.solve_time,
                "setup_time": run.setup_time,
            }
            for name in self.names:
                error = run.errors.get(name, {})
                row[f"{name}_max"], row[f"{name}_mean"] = error.get("max"), error.get("mean")
            row.update({f"drift_{k}": run.drift.get(k) for k in drift_names})
            for label in labels:
                instant = run.instants.get(label, {})
                stem = label.replace(" ", "_")
                for key in ("count", "reference_count", "t", "before", "after"):
                    row[f"{stem}_{key}"] = instant.get(key)
            if labels:
                row["excluded"] = run.excluded
            row["failure"] = run.failure
            row["status"] = run.status
            row["certified_distance"] = run.certificate.get("distance")
            row["certificate_radau_error"] = run.certificate.get("radau_error")
            row["messages"] = " | ".join(run.messages) or None
            out.append(row)
        return out

    def table(self, detail: bool = False) -> str:
        """A text table: method, settings, solve and setup times, errors, constraint drift.

        By default the errors are grouped: the max absolute error over the differential variables
        and over the algebraic ones, each with the variable that reached it, so that the table
        stays about 110 characters wide whatever the model's size (125 with the event columns of a model
        with events or breakpoints).  ``detail=True`` gives a
        ``max (mean)`` column per variable instead (also in :meth:`to_csv`).
        """
        width = {"method": max(8, *(len(r.method) for r in self.runs)) + 2, "settings": 0}
        width["settings"] = max(10, *(len(r.settings) for r in self.runs)) + 2
        head = f"{'method':<{width['method']}}{'settings':<{width['settings']}}{'solve [s]':>10}{'setup [s]':>10}"
        groups = [("differential", self.states)] + ([("algebraic", self.algebraics)] if self.algebraics else [])
        if detail:
            head += "".join(f"{name + ' max (mean)':>20}" for name in self.names)
        else:
            # each cell: the error in 9 characters, then the variable in parentheses
            name_width = max(len(name) for name in self.names)
            cell = max(12 + name_width, *(len(title) + 6 for title, _ in groups))
            head += "".join(f"{title + ' max':>{cell}}" for title, _ in groups)
        head += f"{'drift':>10}"
        instants = any(r.instants for r in self.runs)
        if instants:
            head += f"{'event t':>10}{'event y':>10}{'excluded':>9}"
        lines = [
            f"{self.model} on [{self.t_span[0]:g}, {self.t_span[1]:g}]: absolute errors against {self.reference}",
            head,
            "-" * len(head),
        ]
        for run in self.runs:
            line = f"{run.method:<{width['method']}}{run.settings:<{width['settings']}}"
            if run.failure is not None:
                lines.append(line + f"{'-':>10}{'-':>10}  failed: {run.failure}")
                continue
            line += f"{run.solve_time:>10.3g}{run.setup_time:>10.3g}"
            if detail:
                for name in self.names:
                    error = run.errors[name]
                    line += f"{error['max']:>11.1e} ({error['mean']:.0e})"
            else:
                for _, names in groups:
                    worst = max(names, key=lambda name: run.errors[name]["max"])
                    line += f"{run.errors[worst]['max']:>{cell - name_width - 3}.1e} ({worst:<{name_width}})"
            line += f"{max(run.drift.values()):>10.1e}" if run.drift else f"{'-':>10}"
            if instants:
                line += _instant_cells(run)
            if run.certificate and run.certificate.get("failure"):
                line += f"  cert: {CERTIFICATE_FAILURES.get(run.certificate['failure'], run.certificate['failure'])}"
            elif run.certificate:
                verdict = "<=" if run.certificate["distance"] <= run.certificate["radau_error"] else "> "
                line += f"  cert {run.certificate['distance']:.0e} {verdict} {run.certificate['radau_error']:.0e}"
            if run.status != "success":  # (a certified PINN is flagged where radau's own estimate is)
                line += f"  {run.status.split(':')[0]}"
            lines.append(line)
        lines += self._certificate_notes()
        if instants:
            lines += self._instant_notes()
        for method in self.failed_methods:
            count = sum(r.method == method for r in self.runs)
            lines.append(f"{method} failed at every setting ({count} of {count}): no errors to compare, no curve")
        warned = [r for r in self.runs if r.messages]
        if warned:
            lines.append(
                f"{len(warned)} run(s) raised warnings ({', '.join(f'{r.method} {r.short}' for r in warned)}): "
                "see 'messages' in the JSON and CSV"
            )
        return "\n".join(lines)

    def _instant_notes(self) -> list[str]:
        """What the event columns mean, and each run whose instants the reference does not match."""
        labels = list(dict.fromkeys(k for r in self.runs for k in r.instants))
        notes = [
            f"event t, event y: at the instants of {', '.join(labels)}, each paired with the nearest of the "
            "reference's, max |t - t_ref| and the max error of the values just before and just after (each side at "
            "its own instant); excluded: output values within 1e-9 of the span of either side's instant, left out of "
            "the variables' errors (one side may hold the value after a reset, the other the value before)"
        ]
        for run in self.runs:
            for label, instant in run.instants.items():
                theirs = instant.get("reference_count")
                if theirs is None:
                    notes.append(
                        f"{run.method} {run.settings}: {instant['count']} {label} instants; the reference states none, "
                        "so they are left out and not compared"
                    )
                elif theirs != instant["count"]:
                    notes.append(
                        f"{run.method} {run.settings}: {instant['count']} {label} instants, the reference "
                        f"{theirs}: the unpaired ones are left out and not compared"
                    )
        return notes

    def _certificate_notes(self) -> list[str]:
        """What the certificate column means, and each PINN run's time against radau's at the same
        setting: its training against radau's solve, and setup + solve of each (training,
        evaluation and certificate against radau's engine setup and solve)."""
        certified = [r for r in self.runs if r.certificate]
        if not certified:
            return []
        notes = [
            "cert: the PINN's certified distance from the Radau solution at the same stages and h, against Radau's "
            "own error or the rounding floor, where their ratio is worst; success needs distance <= that, and "
            "radau's own local error estimate at the same stages and h within estimate_bound, else 'flagged'"
        ]
        radau = {r.step: r for r in self.runs if r.method == "radau" and r.failure is None and r.step}
        for run in certified:
            twin = radau.get(run.step)
            if twin is not None:
                training = run.setup_time / max(twin.solve_time, 1e-12)  # a PINN's setup is its training
                total = (run.solve_time + run.setup_time) / max(twin.solve_time + twin.setup_time, 1e-12)
                notes.append(
                    f"{run.method} {run.settings}: training {training:.3g}x radau's solve, setup + solve "
                    f"{total:.3g}x radau's, at the same stages and h"
                )
        return notes

    @property
    def failed_methods(self) -> tuple:
        """The methods that failed at every setting of their sweep."""
        methods = dict.fromkeys(r.method for r in self.runs)
        return tuple(m for m in methods if all(r.failure is not None for r in self.runs if r.method == m))

    @classmethod
    def load(cls, path) -> Comparison:
        """A Comparison from the JSON :meth:`to_json` wrote, e.g. to redraw its plot without
        solving again; a failed run's null setup time is NaN again.

        Raises
        ------
        ComparisonError
            When the file is not such a JSON (naming the file and what is missing).
        """
        path = readable_path(path, "Comparison.load: path", ComparisonError)
        if not path.exists():
            raise ComparisonError(f"no comparison file at {path}")
        payload = read_json(path, ComparisonError, "a comparison saved by Comparison.to_json")
        _check_payload(path, payload)
        try:
            runs = tuple(
                Run(
                    method=r["method"],
                    settings=r["settings"],
                    solve_time=math.nan if r["solve_time"] is None else r["solve_time"],
                    setup_time=math.nan if r["setup_time"] is None else r["setup_time"],
                    errors={
                        name: {key: math.nan if value is None else value for key, value in error.items()}
                        for name, error in r["errors"].items()
                    },
                    drift={name: math.nan if value is None else value for name, value in r["drift"].items()},
                    failure=r.get("failure"),
                    short=r.get("short", ""),
                    messages=tuple(r.get("messages", ())),
                    status=r.get("status", "success"),
                    certificate={
                        key: math.nan if value is None else value for key, value in r.get("certificate", {}).items()
                    },
                    step=tuple(r.get("step", ())),
                    instants={
                        label: {
                            key: math.nan if value is None and key != "reference_count" else value
                            for key, value in instant.items()
                        }
                        for label, instant in r.get("instants", {}).items()
                    },
                    excluded=r.get("excluded", 0),
                )
                for r in payload["runs"]
            )
            return cls(
                model=file_name(payload["model"], f"{path}: field 'model'", ComparisonError),
                t_span=tuple(payload["t_span"]),
                reference=payload["reference"],
                states=tuple(payload["states"]),
                algebraics=tuple(payload["algebraics"]),
                runs=runs,
            )
        except (ValueError, KeyError, TypeError, AttributeError) as error:
            if isinstance(error, ComparisonError):
                raise
            raise ComparisonError(
                f"{path} is not a comparison saved by Comparison.to_json: {type(error).__name__}: {error}"
            ) from None

    def to_json(self, path) -> Path:
        """Write the comparison as JSON (atomically; a failed run's NaN times as null); read it back
        with :meth:`load`."""
        path = writable_file(path, "path")
        payload = {
            "model": self.model,
            "t_span": list(self.t_span),
            "reference": self.reference,
            "states": list(self.states),
            "algebraics": list(self.algebraics),
            "runs": [dataclasses.asdict(run) for run in self.runs],
        }
        # a failed run's wall time is NaN, which JSON lacks: null, as strict parsers expect
        return write_json(path, _nan_to_none(payload))

    def to_csv(self, path) -> Path:
        """Write :meth:`records` as CSV (atomically), one row per run."""
        path = writable_file(path, "path")
        rows = self.records()

        def write(handle):
            writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)

        return atomic_write(path, write, text=True)

    def plot(self, path=None, clock: str = "solve"):
        """Work-precision plot: max absolute error against time, log-log, one curve per method
        through its sweep; differential and algebraic variables in separate panels.

        ``clock="solve"`` (default) draws :attr:`Run.solve_time`, each method's median setup time
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
        groups = [("differential variables", self.states)]
        if self.algebraics:
            groups.append(("algebraic variables", self.algebraics))
        fig = Figure(figsize=(6.2 * len(groups), 4.6), layout="constrained")
        axes = fig.subplots(1, len(groups), squeeze=False)[0]
        methods = list(dict.fromkeys(run.method for run in self.runs))
        for ax, (title, names) in zip(axes, groups, strict=True):
            top_edge = blended_transform_factory(ax.transData, ax.transAxes)
            for i, method in enumerate(methods):
                runs = [r for r in self.runs if r.method == method and r.failure is None]
                failed = [r for r in self.runs if r.method == method and r.failure is not None]
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
            ax.set_xlabel("solve time [s]" if clock == "solve" else "setup + solve time [s]")
            listed = ", ".join(names) if len(names) <= 6 else f"{names[0]} ... {names[-1]}, {len(names)} variables"
            ax.set_ylabel(f"max absolute error ({listed})")
            ax.set_title(title)
            ax.grid(which="both", alpha=0.25)
        # one legend for the panels, below them, where it hides no data
        handles, labels = axes[0].get_legend_handles_labels()
        fig.legend(handles, labels, loc="outside lower center", ncols=min(len(labels), 2), fontsize=8)
        fig.suptitle(f"{self.model} on [{self.t_span[0]:g}, {self.t_span[1]:g}]: error against {self.reference}")
        if path is not None:
            save_figure(fig, path, "plot path", dpi=130)
        return fig

    def save(self, directory) -> list[Path]:
        """Write ``<model>.json``, ``<model>.csv`` and ``<model>_work_precision.png`` into ``directory``."""
        directory = writable_directory(directory, "save directory")
        stem = directory / file_name(self.model, "the comparison's model name", ComparisonError)
        png = Path(f"{stem}_work_precision.png")
        self.plot(png)
        return [self.to_json(f"{stem}.json"), self.to_csv(f"{stem}.csv"), png]


def _check_payload(path, payload) -> None:
    """Every field of a saved comparison with its type, before anything is built from it: a
    ComparisonError names the first that is not what :meth:`Comparison.to_json` writes."""

    def bad(field: str, expected: str):
        raise ComparisonError(f"{path}: field {field!r} is not {expected}: the file is damaged or was edited")

    def number(value, field: str, none: bool = True):
        if (value is None and none) or (isinstance(value, int | float) and not isinstance(value, bool)):
            return
        bad(field, "a number" + (" or null" if none else ""))

    def strings(value, field: str):
        if not isinstance(value, list) or not all(isinstance(item, str) for item in value):
            bad(field, "a list of strings")

    if not isinstance(payload, dict):
        bad("(top level)", "an object")
    for key in ("model", "t_span", "reference", "states", "algebraics", "runs"):
        if key not in payload:
            return  # named by the KeyError below, as before
    span = payload["t_span"]
    if not isinstance(span, list) or len(span) != 2:
        bad("t_span", "a pair of numbers")
    for value in span:
        number(value, "t_span", none=False)
    if not all(math.isfinite(v) for v in span) or not span[0] < span[1]:
        bad("t_span", "a finite, increasing pair")
    if not isinstance(payload["reference"], str):
        bad("reference", "a string")
    strings(payload["states"], "states")
    strings(payload["algebraics"], "algebraics")
    if not payload["states"]:
        bad("states", "a non-empty list")
    names = [*payload["states"], *payload["algebraics"]]
    if not isinstance(payload["runs"], list):
        bad("runs", "a list")
    for k, run in enumerate(payload["runs"]):
        where = f"runs[{k}]"
        if not isinstance(run, dict):
            bad(where, "an object")
        for key in ("method", "settings", "short", "status"):
            if not isinstance(run.get(key, ""), str):
                bad(f"{where}.{key}", "a string")
        for key in ("solve_time", "setup_time"):
            number(run.get(key), f"{where}.{key}")
        if run.get("failure") is not None and not isinstance(run["failure"], str):
            bad(f"{where}.failure", "a string or null")
        strings(run.get("messages", []), f"{where}.messages")
        errors = run.get("errors", {})
        if not isinstance(errors, dict) or (run.get("failure") is None and set(errors) != set(names)):
            bad(f"{where}.errors", "an entry for every variable of states and algebraics")
        for name, error in errors.items():
            if not isinstance(error, dict) or set(error) != {"max", "mean"}:
                bad(f"{where}.errors.{name}", "an object of max and mean")
            number(error["max"], f"{where}.errors.{name}.max")
            number(error["mean"], f"{where}.errors.{name}.mean")
        for key in ("drift", "certificate"):
            table = run.get(key, {})
            if not isinstance(table, dict):
                bad(f"{where}.{key}", "an object")
            for name, value in table.items():
                number(value, f"{where}.{key}.{name}")
        instants = run.get("instants", {})
        if not isinstance(instants, dict):
            bad(f"{where}.instants", "an object")
        for label, instant in instants.items():
            if not isinstance(instant, dict) or set(instant) != {"count", "reference_count", "t", "before", "after"}:
                bad(f"{where}.instants.{label}", "an object of count, reference_count, t, before and after")
            for key in ("count", "reference_count", "t", "before", "after"):
                number(instant[key], f"{where}.instants.{label}.{key}", none=key != "count")
        number(run.get("excluded", 0), f"{where}.excluded", none=False)
        step = run.get("step", [])
        if not isinstance(step, list) or len(step) not in (0, 2):
            bad(f"{where}.step", "empty or a pair (stages, h)")
        for value in step:
            number(value, f"{where}.step", none=False)


def _sweep_range(runs) -> str:
    """``"h=0.1 -> 0.0125"``: a sweep's first and last setting, the name said once where both share it."""
    first, last = (runs[0].short or runs[0].settings), (runs[-1].short or runs[-1].settings)
    if len(runs) == 1 or first == last:
        return first
    head, _, _ = first.partition("=")
    if "," not in first and last.startswith(head + "="):
        last = last[len(head) + 1 :]
    return f"{first} -> {last}"


def compare(
    model,
    t_span,
    methods=None,
    *,
    reference=None,
    sweep: dict | None = None,
    points: int = DEFAULT_POINTS,
    steps: int = SWEEP_FIRST_STEPS,
    progress: bool | None = None,
) -> Comparison:
    """Solve ``model`` with each method over a sweep of its accuracy setting and measure every
    solution against one reference.

    User mistakes are refused before the first solve (see :func:`plan_comparison`); a method
    that fails at a setting (a :class:`SolverError`) is recorded as a failed run and the sweep
    goes on.  A :class:`ModelError` that only a solve reveals is raised, never recorded: it is
    a mistake to fix, not a point of the work-precision curve.

    Parameters
    ----------
    model : Model or CompiledDAE
    t_span : (float, float)
    methods : iterable of str, optional
        Registered method names; default every method except ``"reference"``.
    reference : callable, optional
        ``reference(t) -> dict name -> values``, e.g. ``Problem.exact_solution()``: for times
        ``t`` of shape (T,), finite values of shape (T,) for every state and algebraic
        variable.  Default: ``method="reference"`` (scipy, rtol = atol = 1e-12) solved on each
        run's times.
    sweep : dict method -> list of option dicts, optional
        Settings to solve a method with instead of its default sweep, e.g.
        ``{"radau": [{"stages": 5, "h": 0.1}, {"stages": 5, "h": 0.05}]}``.
    points : int
        Length of the default sweeps, 1 to :data:`MAX_POINTS`.
    steps : int
        Steps over ``t_span`` of the fixed-step methods' coarsest default setting (``h = span /
        steps``, then halved at each point).  The default 10 suits a smooth solution on the
        span; an oscillation or a fast transient needs more (each problem in
        :data:`daemodel.problems.PROBLEMS` carries its own ``compare_steps``).
    progress : bool, optional
        Show a progress bar (default: when stderr is a terminal).

    Returns
    -------
    Comparison

    Raises
    ------
    ModelError
        Before any solve: an unknown method or option, an unusable setting, a grid of more
        than :data:`MAX_SWEEP_STEPS` steps, ``points`` out of range, an inconsistent initial
        state, or a reference that raises or returns missing, misshapen or non-finite values
        (:class:`ComparisonError`, naming the variable and the time).
    SolverError
        Only when the default reference solve itself fails.
    """
    return plan_comparison(model, t_span, methods, reference=reference, sweep=sweep, points=points, steps=steps).run(
        progress
    )


@dataclass(frozen=True)
class ComparisonPlan:
    """A checked :func:`compare`: the model, the interval, the settings to solve and the reference.

    Made by :func:`plan_comparison`, which refuses every user mistake it can find before a
    solve; :meth:`run` then solves.  ``daemodel compare`` plans every target before solving any.

    Attributes
    ----------
    compiled : CompiledDAE
    t_span : (float, float)
    settings : tuple of (method, options, settings label, short label)
    reference : CheckedReference or None
    """

    compiled: object
    t_span: tuple
    settings: tuple
    reference: CheckedReference | None

    def run(self, progress: bool | None = None) -> Comparison:
        """Solve every setting; a :class:`SolverError` at one is recorded as a failed run."""
        from daemodel.backends.progress import show_progress
        from daemodel.solving.solver import solve

        compiled, t_span = self.compiled, self.t_span
        references = {}

        def measure(solution):
            if self.reference is not None:
                return solution.error_report(self.reference)
            key = tuple(solution.t)
            if key not in references:
                references[key] = solve(compiled, t_span, method=REFERENCE, t_eval=solution.t)
            return solution.error_report(references[key])

        bar = None
        if show_progress(progress):
            from daemodel.backends.progress import progress_bar

            bar = progress_bar(len(self.settings), f"compare {compiled.name}", "solve")
        runs = []
        try:
            for method, options, label, short in self.settings:
                if bar is not None:
                    bar.set_postfix_str(f"{method} {label}")
                began = time.perf_counter()
                with warnings.catch_warnings(record=True) as caught:
                    warnings.simplefilter("always")
                    try:
                        solution = solve(compiled, t_span, method=method, **options)
                    except SolverError as error:
                        solution, failure = None, str(error)
                        failed_after = time.perf_counter() - began
                messages = tuple(dict.fromkeys(f"{w.category.__name__}: {w.message}" for w in caught))
                if solution is None:
                    runs.append(
                        Run(
                            method,
                            label,
                            failed_after,
                            math.nan,
                            {},
                            {},
                            failure=failure,
                            short=short,
                            messages=messages,
                            status="failed",
                        )
                    )
                else:
                    report = measure(solution)
                    runs.append(
                        Run(
                            method,
                            label,
                            solution.solve_time,
                            solution.setup_time,
                            report.variables,
                            solution.drift(),
                            short=short,
                            messages=messages,
                            status=solution.status,
                            certificate=_certificate_digest(solution),
                            step=_step(solution),
                            instants={name: _instant_digest(i) for name, i in report.instants.items()},
                            excluded=report.excluded,
                        )
                    )
                if bar is not None:
                    bar.update(1)
        finally:
            if bar is not None:
                bar.close()
        if self.reference is not None:
            described = "the exact solution"
        else:
            backend = get_backend(REFERENCE)
            described = backend.describe(backend.Options())
        return Comparison(
            model=compiled.name,
            t_span=t_span,
            reference=described,
            states=tuple(compiled.state_names),
            algebraics=tuple(compiled.algebraic_names),
            runs=tuple(runs),
        )


def plan_comparison(
    model,
    t_span,
    methods=None,
    *,
    reference=None,
    sweep: dict | None = None,
    points: int = DEFAULT_POINTS,
    steps: int = SWEEP_FIRST_STEPS,
) -> ComparisonPlan:
    """Check everything :func:`compare` is given, without solving; the arguments are compare's.

    Refuses, each with a :class:`ModelError` naming the culprit: an unknown method, a sweep
    for a method not compared, ``points`` outside 1 to :data:`MAX_POINTS`, a setting its
    method rejects (with the method, the setting and how far the default sweep is usable), a
    fixed grid of more than :data:`MAX_SWEEP_STEPS` steps, an inconsistent initial state, and
    a reference that fails on :data:`REFERENCE_CHECK_POINTS` times across ``t_span``.
    """
    from daemodel.compiling.compiler import as_compiled
    from daemodel.compiling.initial_states import initial_states
    from daemodel.solving.solver import check_span

    compiled = as_compiled(model, "compare()")
    t_span = check_span(t_span, compiled)
    methods = [m for m in registered_methods() if m != REFERENCE] if methods is None else list(methods)
    if not methods:
        raise ComparisonError("compare() needs at least one method")
    backends = {method: get_backend(method) for method in methods}  # unknown names raise here
    sweep = dict(sweep or {})
    stray = sorted(set(sweep) - set(methods))
    if stray:
        raise ComparisonError(f"sweep names {', '.join(stray)}, which is not among the methods {', '.join(methods)}")
    check_points(points, steps)
    if reference is not None and not callable(reference):
        raise ComparisonError(
            f"reference must be a callable t -> dict of values (an exact solution); got {type(reference).__name__}"
        )
    settings = []
    for method in methods:
        given = method in sweep
        options_list = sweep[method] if given else backends[method].work_precision(t_span, points, steps)
        if (
            not isinstance(options_list, list | tuple)
            or not options_list
            or not all(isinstance(s, dict) for s in options_list)
        ):
            raise ComparisonError(f"sweep[{method!r}] must be a non-empty list of option dicts; got {options_list!r}")
        labels = sweep_labels(list(options_list))
        for i, (options, (label, short)) in enumerate(zip(options_list, labels, strict=True)):
            context = f"{method} at {label} (setting {i + 1} of {len(options_list)})"
            if given:
                fix = f"; fix sweep[{method!r}]"
            elif i > 0:
                fix = f"; {method}'s default sweep is usable up to points = {i}"
            else:
                fix = ""
            _check_setting(backends[method], options, t_span, context, fix)
            settings.append((method, options, label, short))
    initial_states(compiled)  # an inconsistent initial state would fail every solve: refuse it now
    checked = None
    if reference is not None:
        checked = CheckedReference(reference, compiled, t_span)
        checked(np.linspace(*t_span, REFERENCE_CHECK_POINTS))
    return ComparisonPlan(compiled=compiled, t_span=t_span, settings=tuple(settings), reference=checked)


def check_points(points, steps: int = SWEEP_FIRST_STEPS) -> int:
    """``points`` if it is an integer from 1 to :data:`MAX_POINTS`, and ``steps`` a positive
    integer, else :class:`ComparisonError`."""
    if isinstance(points, bool) or not isinstance(points, int) or points < 1:
        raise ComparisonError(f"points must be a positive integer; got {points!r}")
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise ComparisonError(f"steps must be a positive integer (the coarsest fixed-step grid); got {steps!r}")
    if points > MAX_POINTS:
        finest = steps * 2 ** (MAX_POINTS - 1)
        raise ComparisonError(
            f"points = {points} is more than {MAX_POINTS}: a fixed-step sweep halves h from span/{steps} "
            f"at each point, so point {MAX_POINTS} already takes {finest:,} steps per solve and every further point "
            f"doubles that; take points <= {MAX_POINTS}, or give sweep= with the settings you need"
        )
    return points


def _check_setting(backend, options: dict, t_span, context: str, fix: str) -> None:
    """Raise the :class:`ModelError` that solving ``options`` would raise, before any solve,
    with ``context`` (method and setting) in front and ``fix`` behind its message."""
    from daemodel.solving.solver import check_options

    try:
        check_options(backend, options)
        flat = _flatten(options)
        if flat.get("device") is not None:  # a CUDA device torch cannot see
            torch_device(flat["device"])
        h = flat.get("h")
        if h is not None:  # a fixed grid: checked by Options as a positive number
            span = t_span[1] - t_span[0]
            if span / h > MAX_SWEEP_STEPS:
                raise ResourceLimitError(
                    f"h = {h:g} makes {math.ceil(span / h):,} steps over t_span = ({t_span[0]:g}, {t_span[1]:g}), "
                    f"more than the {MAX_SWEEP_STEPS:,} a compared setting may take; "
                    f"take h >= {span / MAX_SWEEP_STEPS:g}"
                )
            fixed_grid(t_span, h)  # h larger than the interval
    except ModelError as error:
        raise type(error)(f"{context}: {error}{fix}") from None


@dataclass(frozen=True, eq=False)
class CheckedReference:
    """A reference callable whose every answer is checked before an error is measured with it.

    ``reference(t)`` must return a mapping with a finite float array of shape (T,) (or (B, T))
    for every state and algebraic variable of ``compiled``; anything else, and any exception
    it raises, is a :class:`ComparisonError` naming the variable, the time and the fix.
    Variables it gives beyond those (aliases) are checked too when the model has them; other
    keys are ignored.
    """

    function: object
    compiled: object
    t_span: tuple

    @property
    def events(self):
        """The reference's own ``events`` (laid out as :attr:`Solution.events`), or None."""
        return getattr(self.function, "events", None)

    @property
    def breakpoints(self):
        """The reference's own ``breakpoints`` (laid out as :attr:`Solution.breakpoints`), or None."""
        return getattr(self.function, "breakpoints", None)

    def __call__(self, t) -> dict:
        t = np.asarray(t, dtype=float)
        where = f"on {t.size} times from {t[0]:g} to {t[-1]:g}"
        try:
            values = self.function(t)
        except Exception as error:  # the user's code: any exception is a message, not a traceback
            raise ComparisonError(
                f"the reference, called {where}, raised {exception_summary(error, depth=1)}; reference(t) must "
                "take an array of times and return a dict name -> array of values"
            ) from error
        if not isinstance(values, Mapping):
            raise ComparisonError(
                f"the reference returned {type(values).__name__} {where}; it must return a dict name -> array of values"
            )
        c = self.compiled
        required = (*c.state_names, *c.algebraic_names)
        missing = [n for n in required if n not in values]
        if missing:
            raise ComparisonError(
                f"the reference gives no values for {', '.join(missing)}; it gives "
                f"{', '.join(map(str, values)) or 'none'}, and must give every state and algebraic variable of "
                f"'{c.name}': {', '.join(required)}"
            )
        out = {}
        for name in (*required, *(n for n in c.alias_names if n in values)):
            out[name] = self._check(name, values[name], t)
        return out

    def _check(self, name: str, value, t: np.ndarray) -> np.ndarray:
        try:
            array = np.asarray(value)
            if array.dtype.kind == "O":  # e.g. a list of sympy numbers
                array = array.astype(float)
        except (TypeError, ValueError):
            array = None
        if array is None or array.dtype.kind not in "iuf":  # text numpy would parse, complex, bool
            found = f"dtype {array.dtype}" if array is not None else type(value).__name__
            raise ComparisonError(
                f"the reference's values for '{name}' are not real numbers ({found}); return a float array per variable"
            )
        array = array.astype(float, copy=False)
        if array.ndim not in (1, 2) or array.shape[-1] != t.size:
            raise ComparisonError(
                f"the reference's values for '{name}' have shape {array.shape}; expected ({t.size},), one value per "
                f"time of the t it was called with (or (B, {t.size}) for a batch)"
            )
        finite = np.isfinite(array)
        if not finite.all():
            bad = ~finite.reshape(-1, t.size)
            first = int(np.argmax(bad.any(axis=0)))
            value = array.reshape(-1, t.size)[:, first][bad[:, first]][0]
            raise ComparisonError(
                f"the reference's value for '{name}' is {value} at t = {t[first]:g} ({int(bad.sum())} of {array.size} "
                f"values not finite); a reference must be finite on t_span = ({self.t_span[0]:g}, "
                f"{self.t_span[1]:g}): fix it, or give none to measure against method='reference'"
            )
        return array


def exception_summary(error: BaseException, *, depth: int | None = None, filename=None) -> str:
    """``"ZeroDivisionError: division by zero (line 7 of model.py)"``: one line for an
    exception raised by user code, with the line where known.

    Parameters
    ----------
    depth : int, optional
        The line is that of traceback entry ``depth`` (1: the function called inside the ``try``).
    filename : str or Path, optional
        The line is that of the innermost traceback entry in this file (named even when no
        entry is in it).
    """
    if isinstance(error, SyntaxError) and error.lineno is not None:
        return f"{type(error).__name__}: {error.msg} (line {error.lineno} of {error.filename})"
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    text = f"{type(error).__name__}: {lines[0]}" if lines else type(error).__name__
    frames = traceback.extract_tb(error.__traceback__)
    if filename is not None:
        target = Path(filename).resolve()
        frame = next((f for f in reversed(frames) if Path(f.filename).resolve() == target), None)
        return f"{text} (line {frame.lineno} of {filename})" if frame is not None else f"{text} (in {filename})"
    if depth is not None and len(frames) > depth:
        return f"{text} (line {frames[depth].lineno} of {frames[depth].filename})"
    return text


def _step(solution) -> tuple:
    """``(stages, h)`` of a fixed-step Solution, else ()."""
    settings = solution.settings if isinstance(solution.settings, dict) else {}
    if settings.get("h") is None or settings.get("stages") is None:
        return ()
    return (int(settings["stages"]), float(settings["h"]))


def _instant_digest(instant) -> dict:
    """A :class:`~daemodel.instants.InstantErrors` as :attr:`Run.instants` keeps it: the values'
    errors as the max over the variables on each side."""

    def worst(errors: dict) -> float:
        return float(max(errors.values())) if errors else math.nan

    return {
        "count": instant.count,
        "reference_count": instant.reference_count,
        "t": instant.t,
        "before": worst(instant.before),
        "after": worst(instant.after),
    }


def _instant_cells(run) -> str:
    """The table's event t, event y and excluded cells of a run ("-" where nothing was paired)."""

    def cell(values) -> str:
        values = [v for v in values if v is not None and not math.isnan(v)]
        return f"{max(values):>10.1e}" if values else f"{'-':>10}"

    dt = cell([i["t"] for i in run.instants.values()])
    dy = cell([v for i in run.instants.values() for v in (i["before"], i["after"])])
    return f"{dt}{dy}{run.excluded:>9d}"


def _certificate_digest(solution) -> dict:
    """A PINN Solution's certificate where distance / bound is largest (over variables, times and
    samples): the certified distance and what it is compared with; empty for other methods."""
    certificate = solution.stats.get("certificate") if isinstance(solution.stats, dict) else None
    if not certificate:
        return {}
    digest = {"distance": certificate["worst"]["distance"], "radau_error": certificate["worst"]["bound"]}
    if certificate.get("failure"):
        digest["failure"] = certificate["failure"]
    return digest


def _nan_to_none(value):
    """``value`` with every non-finite float (in dicts and lists) replaced by None."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _nan_to_none(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_nan_to_none(v) for v in value]
    return value


def sweep_labels(sweep: list[dict]) -> list[tuple[str, str]]:
    """``(settings, short)`` text for each option dict of one method's sweep: ``settings``
    names every option (a config dataclass by its fields that differ from its defaults or
    along the sweep), ``short`` only what changes along the sweep (for the plot)."""
    flat = [_flatten(options) for options in sweep]
    keys = list(dict.fromkeys(k for f in flat for k in f))
    varying = [k for k in keys if len({repr(f.get(k)) for f in flat}) > 1]
    out = []
    for options, f in zip(sweep, flat, strict=True):
        named = [k for k in keys if k in f and (k in options or k in varying or f[k] != _default(options, k))]
        full = ", ".join(_show(k, f[k]) for k in named) or "defaults"
        short = ", ".join(_show(k, f[k]) for k in varying if k in f) or full
        out.append((full, short))
    return out


def _flatten(options: dict) -> dict:
    """Options with any config dataclass replaced by its fields."""
    flat = {}
    for key, value in options.items():
        if dataclasses.is_dataclass(value):
            flat.update({f.name: getattr(value, f.name) for f in dataclasses.fields(value)})
        else:
            flat[key] = value
    return flat


def _default(options: dict, key: str):
    for value in options.values():
        if dataclasses.is_dataclass(value) and key in {f.name for f in dataclasses.fields(value)}:
            return getattr(type(value)(), key)
    return None


def _show(key: str, value) -> str:
    return f"{key}={value:g}" if isinstance(value, float) else f"{key}={value}"


def _seconds(value: float) -> str:
    """A duration for a legend: ``"0.81 ms"``, ``"795 ms"``, ``"1.24 s"``."""
    return f"{value * 1e3:.3g} ms" if value < 1 else f"{value:.3g} s"

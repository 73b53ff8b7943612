"""The result of :func:`~daemodel.compare`: its runs, as a text table, CSV and JSON (and back).

The work-precision plot is drawn by :mod:`daemodel.comparing.plots`; the sweep that makes the runs is
:mod:`daemodel.comparing.compare`'s.
"""

from __future__ import annotations

import csv
import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

from daemodel.errors import ComparisonError
from daemodel.files import (
    atomic_write,
    file_name,
    read_json,
    readable_path,
    writable_directory,
    writable_file,
    write_json,
)

# The table's words for why a PINN's certificate failed at a step (keys: NEWTON_FAILED,
# ESTIMATE_FAILED, NO_DIGIT of backends/pinn/certificate.py, which imports torch).
CERTIFICATE_FAILURES = {
    "newton": "failed (Newton from the networks)",
    "estimate": "failed (no Radau error estimate)",
    "digit": "failed (Radau's step has no correct digit)",
}


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
    """The runs of :func:`~daemodel.comparing.compare.compare` on one model.

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
        """The work-precision plot (:func:`daemodel.comparing.plots.work_precision`): max absolute error
        against the solve time (``clock="solve"``) or setup plus solve (``clock="total"``), log-log, one
        curve per method through its sweep; written to ``path`` when given.

        Returns
        -------
        matplotlib.figure.Figure
        """
        from daemodel.comparing.plots import work_precision

        return work_precision(self, path, clock)

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


def _instant_cells(run) -> str:
    """The table's event t, event y and excluded cells of a run ("-" where nothing was paired)."""

    def cell(values) -> str:
        values = [v for v in values if v is not None and not math.isnan(v)]
        return f"{max(values):>10.1e}" if values else f"{'-':>10}"

    dt = cell([i["t"] for i in run.instants.values()])
    dy = cell([v for i in run.instants.values() for v in (i["before"], i["after"])])
    return f"{dt}{dy}{run.excluded:>9d}"


def _nan_to_none(value):
    """``value`` with every non-finite float (in dicts and lists) replaced by None."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _nan_to_none(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_nan_to_none(v) for v in value]
    return value

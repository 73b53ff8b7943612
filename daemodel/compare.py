"""Every method on one model: wall time against error, as a table and a work-precision plot.

>>> result = dm.compare(model, (0.0, 1.0), methods=["radau", "casadi-idas", "pinn"])
>>> print(result.table())
>>> result.save("results/")            # <model>.json, <model>.csv, <model>_work_precision.png

Each method is solved over a sweep of its accuracy setting (its backend's
``work_precision``: step sizes h for the fixed-step methods, tolerances for the adaptive
ones), and every solution is measured against one reference: the model's exact solution
when given, else ``method="reference"`` (scipy at rtol = atol = 1e-12) on the same times.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path

from daemodel.backends import get_backend
from daemodel.backends import methods as registered_methods
from daemodel.errors import ComparisonError, SolverError

# Sweep points per method when compare() is not told otherwise.
DEFAULT_POINTS = 4


@dataclass(frozen=True)
class Run:
    """One solve of one method at one setting.

    Attributes
    ----------
    method : str
    settings : str
        The options that were swept, e.g. ``"h=0.05"`` or ``"rtol=1e-06, atol=1e-08"``.
    wall_time : float
        The method's own solve time in seconds (training included for ``pinn``; NaN when it failed).
    errors : dict name -> {"max": float, "mean": float}
        Absolute errors against the reference over every output time.
    drift : dict constraint -> float
        Max ``|g|`` of each original constraint along the solution.
    failure : str or None
        The error message when the method failed at this setting (then no errors).
    short : str
        The part of ``settings`` that changes along the method's sweep (plot labels).
    """

    method: str
    settings: str
    wall_time: float
    errors: dict
    drift: dict
    failure: str | None = None
    short: str = ""


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
        """One flat dict per run: method, settings, wall_time, ``<var>_max``, ``<var>_mean``,
        ``drift_<constraint>``, failure."""
        out = []
        drift_names = sorted({k for r in self.runs for k in r.drift})
        for run in self.runs:
            row = {"method": run.method, "settings": run.settings, "wall_time": run.wall_time}
            for name in self.names:
                error = run.errors.get(name, {})
                row[f"{name}_max"], row[f"{name}_mean"] = error.get("max"), error.get("mean")
            row.update({f"drift_{k}": run.drift.get(k) for k in drift_names})
            row["failure"] = run.failure
            out.append(row)
        return out

    def table(self) -> str:
        """A text table: method, settings, wall time, ``max (mean)`` error per variable, drift."""
        width = {"method": max(8, *(len(r.method) for r in self.runs)) + 2, "settings": 0}
        width["settings"] = max(10, *(len(r.settings) for r in self.runs)) + 2
        head = f"{'method':<{width['method']}}{'settings':<{width['settings']}}{'time [s]':>10}"
        head += "".join(f"{name + ' max (mean)':>20}" for name in self.names) + f"{'drift':>10}"
        lines = [
            f"{self.model} on [{self.t_span[0]:g}, {self.t_span[1]:g}]: absolute errors against {self.reference}",
            head,
            "-" * len(head),
        ]
        for run in self.runs:
            line = f"{run.method:<{width['method']}}{run.settings:<{width['settings']}}"
            if run.failure is not None:
                lines.append(line + f"{run.wall_time:>10.3f}  failed: {run.failure}")
                continue
            line += f"{run.wall_time:>10.3f}"
            for name in self.names:
                error = run.errors[name]
                line += f"{error['max']:>11.1e} ({error['mean']:.0e})"
            line += f"{max(run.drift.values(), default=math.nan):>10.1e}"
            lines.append(line)
        return "\n".join(lines)

    def to_json(self, path) -> Path:
        path = Path(path)
        payload = {
            "model": self.model,
            "t_span": list(self.t_span),
            "reference": self.reference,
            "states": list(self.states),
            "algebraics": list(self.algebraics),
            "runs": [dataclasses.asdict(run) for run in self.runs],
        }
        path.write_text(json.dumps(payload, indent=2) + "\n")
        return path

    def to_csv(self, path) -> Path:
        path = Path(path)
        rows = self.records()
        with path.open("w", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
        return path

    def plot(self, path=None):
        """Work-precision plot: max absolute error against wall time, log-log, one curve per
        method through its sweep; differential and algebraic variables in separate panels.

        Returns
        -------
        matplotlib.figure.Figure
        """
        from matplotlib.figure import Figure

        groups = [("differential variables", self.states)]
        if self.algebraics:
            groups.append(("algebraic variables", self.algebraics))
        fig = Figure(figsize=(6.2 * len(groups), 4.6), layout="constrained")
        axes = fig.subplots(1, len(groups), squeeze=False)[0]
        methods = list(dict.fromkeys(run.method for run in self.runs))
        for ax, (title, names) in zip(axes, groups, strict=True):
            for i, method in enumerate(methods):
                runs = [r for r in self.runs if r.method == method and r.failure is None]
                if not runs:
                    continue
                times = [r.wall_time for r in runs]
                errors = [max(max(r.errors[n]["max"] for n in names), 1e-17) for r in runs]
                ax.loglog(times, errors, "o-", color=f"C{i}", label=method)
                for x, y, run in zip(times, errors, runs, strict=True):
                    ax.annotate(
                        run.short or run.settings, (x, y), textcoords="offset points", xytext=(4, 3), fontsize=6.5
                    )
            ax.set_xlabel("wall time [s]")
            ax.set_ylabel(f"max absolute error ({', '.join(names)})")
            ax.set_title(title)
            ax.grid(which="both", alpha=0.25)
            ax.legend(fontsize=8)
        fig.suptitle(
            f"{self.model} on [{self.t_span[0]:g}, {self.t_span[1]:g}]: error against {self.reference} vs wall time"
        )
        if path is not None:
            fig.savefig(path, dpi=130)
        return fig

    def save(self, directory) -> list[Path]:
        """Write ``<model>.json``, ``<model>.csv`` and ``<model>_work_precision.png`` into ``directory``."""
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        stem = directory / self.model
        png = Path(f"{stem}_work_precision.png")
        self.plot(png)
        return [self.to_json(f"{stem}.json"), self.to_csv(f"{stem}.csv"), png]


def compare(
    model,
    t_span,
    methods=None,
    *,
    reference=None,
    sweep: dict | None = None,
    points: int = DEFAULT_POINTS,
    progress: bool | None = None,
) -> Comparison:
    """Solve ``model`` with each method over a sweep of its accuracy setting and measure every
    solution against one reference.

    Parameters
    ----------
    model : Model or CompiledDAE
    t_span : (float, float)
    methods : iterable of str, optional
        Registered method names; default every method except ``"reference"``.
    reference : callable, optional
        ``reference(t) -> dict name -> values``, e.g. ``Problem.exact_solution()``.  Default:
        ``method="reference"`` (scipy, rtol = atol = 1e-12) solved on each run's times.
    sweep : dict method -> list of option dicts, optional
        Settings to solve a method with instead of its default sweep, e.g.
        ``{"radau": [{"stages": 5, "h": 0.1}, {"stages": 5, "h": 0.05}]}``.
    points : int
        Length of the default sweeps.
    progress : bool, optional
        Show a progress bar (default: when stderr is a terminal).

    Returns
    -------
    Comparison
    """
    from daemodel.backends.base import show_progress
    from daemodel.solver import as_compiled, check_span, solve

    compiled = as_compiled(model, "compare()")
    t_span = check_span(t_span, compiled)
    methods = [m for m in registered_methods() if m != "reference"] if methods is None else list(methods)
    if not methods:
        raise ComparisonError("compare() needs at least one method")
    backends = {method: get_backend(method) for method in methods}  # unknown names raise here
    sweep = dict(sweep or {})
    stray = sorted(set(sweep) - set(methods))
    if stray:
        raise ComparisonError(f"sweep names {', '.join(stray)}, which is not among the methods {', '.join(methods)}")
    if isinstance(points, bool) or not isinstance(points, int) or points < 1:
        raise ComparisonError(f"points must be a positive integer; got {points!r}")
    if reference is not None and not callable(reference):
        raise ComparisonError(
            f"reference must be a callable t -> dict of values (an exact solution); got {type(reference).__name__}"
        )
    plan = []
    for method in methods:
        settings = sweep.get(method, backends[method].work_precision(t_span, points))
        if not isinstance(settings, list | tuple) or not settings or not all(isinstance(s, dict) for s in settings):
            raise ComparisonError(f"sweep[{method!r}] must be a non-empty list of option dicts; got {settings!r}")
        labels = sweep_labels(list(settings))
        plan += [(method, options, *label) for options, label in zip(settings, labels, strict=True)]

    references = {}

    def measure(solution):
        if reference is not None:
            return solution.errors(reference)
        key = tuple(solution.t)
        if key not in references:
            references[key] = solve(compiled, t_span, method="reference", t_eval=solution.t)
        return solution.errors(references[key])

    bar = None
    if show_progress(progress):
        from tqdm.auto import tqdm

        bar = tqdm(total=len(plan), desc=f"compare {compiled.name}", unit="solve", leave=False)
    runs = []
    try:
        for method, options, label, short in plan:
            if bar is not None:
                bar.set_postfix_str(f"{method} {label}")
            try:
                solution = solve(compiled, t_span, method=method, **options)
            except SolverError as error:
                runs.append(Run(method, label, math.nan, {}, {}, failure=str(error), short=short))
            else:
                runs.append(Run(method, label, solution.wall_time, measure(solution), solution.drift(), short=short))
            if bar is not None:
                bar.update(1)
    finally:
        if bar is not None:
            bar.close()
    described = "the exact solution" if reference is not None else "method='reference' (scipy, rtol = atol = 1e-12)"
    return Comparison(
        model=compiled.name,
        t_span=t_span,
        reference=described,
        states=tuple(compiled.state_names),
        algebraics=tuple(compiled.algebraic_names),
        runs=tuple(runs),
    )


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

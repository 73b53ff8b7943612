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

This module plans and runs the sweep; the pieces it uses each have their own:
:mod:`~daemodel.comparing.sweeps` (the settings: defaults, bounds, labels),
:mod:`~daemodel.comparing.references` (a reference callable, checked),
:mod:`~daemodel.comparing.tables` (the :class:`Comparison`: table, CSV, JSON) and
:mod:`~daemodel.comparing.plots` (its work-precision plot).
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass

import numpy as np

from daemodel.backends import REFERENCE, backends_for, get_backend
from daemodel.backends.grids import SWEEP_FIRST_STEPS
from daemodel.comparing.references import REFERENCE_CHECK_POINTS, CheckedReference
from daemodel.comparing.sweeps import DEFAULT_POINTS, check_points, check_setting, sweep_labels
from daemodel.comparing.tables import Comparison, Run
from daemodel.errors import ComparisonError, SolverError, TimeLimitError


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
        Method names (built in, registered or installed: ``dm.methods()``); default every method except
        ``"reference"``.
    reference : callable, optional
        ``reference(t) -> dict name -> values``, e.g. ``Problem.exact_solution()``: for times
        ``t`` of shape (T,), finite values of shape (T,) for every state and algebraic
        variable.  Default: ``method="reference"`` (scipy, rtol = atol = 1e-12) solved on each
        run's times.
    sweep : dict method -> list of option dicts, optional
        Settings to solve a method with instead of its default sweep, e.g.
        ``{"radau": [{"stages": 5, "h": 0.1}, {"stages": 5, "h": 0.05}]}``.
    points : int
        Length of the default sweeps, 1 to :data:`~daemodel.comparing.sweeps.MAX_POINTS`.
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
        than :data:`~daemodel.comparing.sweeps.MAX_SWEEP_STEPS` steps, ``points`` out of range, an inconsistent initial
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
        from daemodel.solving.solver import prepare, solve

        compiled, t_span = self.compiled, self.t_span
        prepare(compiled, dict.fromkeys(method for method, *_ in self.settings))  # (no method pays for the others)
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
                    except TimeLimitError:  # (the caller's time is up: not this method's failure)
                        raise
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
    for a method not compared, ``points`` outside 1 to :data:`~daemodel.comparing.sweeps.MAX_POINTS`, a setting its
    method rejects (with the method, the setting and how far the default sweep is usable), a
    fixed grid of more than :data:`~daemodel.comparing.sweeps.MAX_SWEEP_STEPS` steps, an inconsistent initial state, and
    a reference that fails on :data:`~daemodel.comparing.references.REFERENCE_CHECK_POINTS` times across ``t_span``.
    """
    from daemodel.compiling.compiler import as_compiled
    from daemodel.compiling.initial_states import initial_states
    from daemodel.solving.solver import check_span

    compiled = as_compiled(model, "compare()")
    t_span = check_span(t_span, compiled)
    backends = backends_for(None if methods is None else list(methods), "compare()")  # (unknown names raise here)
    methods = list(backends)
    if not methods:
        raise ComparisonError("compare() needs at least one method")
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
            check_setting(backends[method], options, t_span, context, fix)
            settings.append((method, options, label, short))
    initial_states(compiled)  # an inconsistent initial state would fail every solve: refuse it now
    checked = None
    if reference is not None:
        checked = CheckedReference(reference, compiled, t_span)
        checked(np.linspace(*t_span, REFERENCE_CHECK_POINTS))
    return ComparisonPlan(compiled=compiled, t_span=t_span, settings=tuple(settings), reference=checked)


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

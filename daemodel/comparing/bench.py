"""Every method on suites of problems: significant correct digits at the end against time, run by
run into an output folder that a rerun resumes, then one report.

>>> result = dm.bench(["testset", "paper"], out="bench/")     # bench/report.html, results.json, .csv
>>> print(result.table())

For each problem and each method, a sweep of the method's accuracy setting (:func:`default_sweep`):
rtol = atol = 1e-3 ... 1e-11 for a method with tolerances, its own step sizes (halved from the
problem's coarsest) for a fixed-step method, its defaults otherwise.  Each run is read as the Test
Set reads it: scd = -log10 of the largest relative error at the end (:func:`~daemodel.comparing.suites.scd`),
with its setup, solve and wall (= setup + solve) times and its step counts.  A run is
``"success"`` (within the accuracy its method states), ``"flagged"`` (the Solution's status says
why not), ``"failed"`` (the named error's class and message; a run past ``time_limit`` is a
:class:`~daemodel.errors.TimeLimitError`) or ``"skipped"`` (a setting its method refuses or that is
beyond the method's ``bench_max_steps``: the reason is kept).

Each run is written to ``out/runs/`` as it finishes (:mod:`daemodel.files`: atomic, inside ``out``);
a rerun loads what is there and solves only the rest.  Runs go one after another here, on
``workers`` processes of this machine, or on Ray (``executor="ray"``).

This module plans and runs; :mod:`~daemodel.comparing.suites` says what the problems are and reads
scd, :mod:`~daemodel.comparing.bench_files` stores the runs and :mod:`~daemodel.comparing.bench_report`
writes the report.
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from dataclasses import dataclass

from daemodel.comparing.suites import BenchProblem, resolve, scd
from daemodel.errors import BenchError, DaemodelError, InvalidOptionError, ModelError, TimeLimitError

# The tolerances rtol = atol a method with tolerances is swept over (the Test Set's range).
DEFAULT_TOLERANCES = (1e-3, 1e-5, 1e-7, 1e-9, 1e-11)
# Step sizes a fixed-step method is swept over: span / steps, halved this many times less one.
DEFAULT_FIXED_POINTS = 3
# Seconds one run may take before it is stopped and recorded as a TimeLimitError: far above a
# Test Set run's usual second; the wheelset's tight settings came near it (casadi-idas at rtol = 1e-11:
# 39 s in benchmarks/bench_testset_paper.json; radau at 1e-9 took 100 s on a shared core in an earlier
# measurement, 5.6 s there), which keeps `daemodel bench testset paper` near ten minutes.
DEFAULT_TIME_LIMIT = 60.0
# Where the runs' end values come from when a problem has neither published values nor a closed form.
REFERENCE_METHOD_NOTE = "scipy (method='reference', rtol = atol = 1e-12)"
EXECUTORS = ("local", "processes", "ray")
# Compiled models of this process, by target: a worker compiles each problem once for all its runs.
_COMPILED: dict = {}


@dataclass(frozen=True)
class Setting:
    """One run to make: a problem, a method, its options and their labels."""

    problem: BenchProblem
    method: str
    index: int
    options: dict
    settings: str
    short: str


@dataclass(frozen=True)
class BenchResult:
    """What :func:`bench` ran: the problems, the methods, every run's record and the files written.

    Attributes
    ----------
    problems : tuple of BenchProblem
    methods : tuple of str
    records : tuple of dict
        One per run (see :mod:`~daemodel.comparing.bench_files` for the fields).
    paths : tuple of Path
        ``report.html``, ``results.json``, ``results.csv``.
    computed : int
        Runs solved by this call (the others were loaded from ``out``).
    elapsed : float
        Seconds this call took, from the first check to the last file.
    """

    problems: tuple
    methods: tuple
    records: tuple
    paths: tuple
    computed: int
    elapsed: float

    def summary(self) -> list[dict]:
        """Per method: problems solved, time to 6 / 8 / 10 scd, failures by error
        (:func:`~daemodel.comparing.bench_report.summary`)."""
        from daemodel.comparing.bench_report import summary

        return summary(self.records, self.methods, self.problems)

    def table(self) -> str:
        """The summary as text."""
        from daemodel.comparing.bench_report import summary_text

        return summary_text(self.summary(), len(self.problems))


def bench(
    suites_or_files,
    methods=None,
    out="bench",
    *,
    workers: int = 1,
    executor: str | None = None,
    address: str | None = None,
    tolerances=DEFAULT_TOLERANCES,
    points: int = DEFAULT_FIXED_POINTS,
    sweep: dict | None = None,
    time_limit: float | None = DEFAULT_TIME_LIMIT,
    threads: int = 1,
    progress: bool | None = None,
) -> BenchResult:
    """Run every method on every problem of ``suites_or_files`` over a sweep of its accuracy setting;
    write the runs and the report into ``out``.

    Parameters
    ----------
    suites_or_files : str or iterable of str
        Suite names (``"testset"``, ``"paper"``) and model files (``.py``, as ``daemodel compare`` reads them).
    methods : iterable of str, optional
        Registered method names (:func:`daemodel.backends.methods`); default every one but ``"reference"``.
    out : str or Path
        The output folder (created): ``runs/`` (one JSON file per run), ``references/``,
        ``report.html``, ``results.json``, ``results.csv``.  Runs already there are not solved again.
    workers : int
        Processes to run on (``executor="processes"``, the default when ``workers > 1``), or the CPUs
        of a local Ray cluster (``executor="ray"``).
    executor : {"local", "processes", "ray"}, optional
        Where runs go: here one after another (default for ``workers=1``), on ``workers`` processes
        of this machine, or as Ray tasks (``address``: an existing cluster).
    tolerances : sequence of float
        rtol = atol of the methods with tolerances, loosest first.
    points : int
        Step sizes of the fixed-step methods (span / steps, halved ``points - 1`` times; steps is
        the problem's ``compare_steps``).
    sweep : dict method -> list of option dicts, optional
        Settings to run a method with instead of its default sweep, on every problem.
    time_limit : float or None
        Seconds one run may take; past it, the run stops and is recorded as a TimeLimitError.
    threads : int
        Torch threads per run (fixed, for comparable timings).
    progress : bool, optional
        A progress bar with the current problem and method (default: when stderr is a terminal).

    Returns
    -------
    BenchResult

    Raises
    ------
    BenchError
        Before any solve: an unknown suite, a bad option, a setting in ``sweep`` its method refuses;
        a run file in ``out`` that is not one (naming the file and the field).
    UnknownMethodError
        An unknown method.
    """
    from daemodel.backends import backends_for
    from daemodel.comparing.bench_files import load_runs, reference_values, write_run
    from daemodel.comparing.bench_report import write_report
    from daemodel.files import writable_directory

    began = time.perf_counter()
    executor = _check_options(workers, executor, address, tolerances, points, time_limit, threads)
    problems = resolve(suites_or_files)
    backends = backends_for(None if methods is None else list(methods), "bench")  # (unknown names raise here)
    methods = list(backends)
    if not methods:
        raise BenchError("bench needs at least one method")
    stray = sorted(set(sweep or {}) - set(methods))
    if stray:
        raise BenchError(f"sweep names {', '.join(stray)}, which is not among the methods {', '.join(methods)}")
    out = writable_directory(out, "out")
    problems = [
        p
        if p.reference
        else dataclasses.replace(p, reference=reference_values(out, p), reference_source=REFERENCE_METHOD_NOTE)
        for p in problems
    ]
    plan, skipped = [], []
    for problem in problems:
        for method in methods:
            runs, refused = plan_settings(problem, method, backends[method], tolerances, points, sweep)
            plan += runs
            skipped += refused
    done = load_runs(out, plan + [s for s, _ in skipped])
    for setting, reason in skipped:
        if setting_key(setting) not in done:
            done[setting_key(setting)] = write_run(out, skipped_record(setting, reason))
    todo = [s for s in plan if setting_key(s) not in done]
    _run(todo, out, executor, workers, address, time_limit, threads, progress, done)
    records = tuple(done[setting_key(s)] for s in plan + [s for s, _ in skipped])
    records = tuple(sorted(records, key=lambda r: (r["problem"], r["method"], r["index"])))
    paths = write_report(out, problems, methods, records)
    return BenchResult(tuple(problems), tuple(methods), records, tuple(paths), len(todo), time.perf_counter() - began)


def _check_options(workers, executor, address, tolerances, points, time_limit, threads) -> str:
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise InvalidOptionError(f"workers must be a positive integer; got {workers!r}")
    if executor is None:
        executor = "local" if workers == 1 else "processes"
    if executor not in EXECUTORS:
        raise InvalidOptionError(f"executor must be one of {', '.join(EXECUTORS)}; got {executor!r}")
    if executor == "local" and workers != 1:
        raise InvalidOptionError(
            f"executor='local' runs one run at a time; workers={workers} needs 'processes' or 'ray'"
        )
    if address is not None and executor != "ray":
        raise InvalidOptionError("address names a Ray cluster: pass executor='ray' with it")
    try:
        tolerances = [float(t) for t in tolerances]
    except (TypeError, ValueError):
        raise InvalidOptionError(f"tolerances must be a sequence of numbers; got {tolerances!r}") from None
    if not tolerances or not all(0 < t < 1 for t in tolerances):
        raise InvalidOptionError(f"tolerances must be numbers between 0 and 1, at least one; got {tolerances!r}")
    if isinstance(points, bool) or not isinstance(points, int) or not 1 <= points <= 12:
        raise InvalidOptionError(f"points must be an integer from 1 to 12; got {points!r}")
    if time_limit is not None and (
        isinstance(time_limit, bool) or not isinstance(time_limit, int | float) or not time_limit > 0
    ):
        raise InvalidOptionError(f"time_limit must be a positive number of seconds or None; got {time_limit!r}")
    if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
        raise InvalidOptionError(f"threads must be a positive integer; got {threads!r}")
    return executor


def default_sweep(backend, problem: BenchProblem, tolerances, points: int) -> list[dict]:
    """A method's settings on ``problem``: rtol = atol over ``tolerances`` when its options have both
    (adaptive steps), else its own ``work_precision`` with ``points`` settings from the problem's
    coarsest fixed step (one run with its defaults for a method without an accuracy setting)."""
    fields = {f.name for f in dataclasses.fields(backend.Options)}
    if {"rtol", "atol"} <= fields:
        return [{"rtol": float(t), "atol": float(t)} for t in tolerances]
    return list(backend.work_precision(problem.t_span, points, problem.steps))


def plan_settings(problem, method, backend, tolerances, points, sweep) -> tuple[list, list]:
    """``(runs, skipped)`` of one method on one problem: the settings to solve, and those refused
    before any solve with the reason (a default setting its method refuses, or a fixed grid longer
    than the method's ``bench_max_steps``).  A setting the user gave in ``sweep`` that its method
    refuses is a :class:`BenchError`."""
    from daemodel.comparing.sweeps import check_setting, sweep_labels

    given = sweep is not None and method in sweep
    options_list = sweep[method] if given else default_sweep(backend, problem, tolerances, points)
    if (
        not isinstance(options_list, list | tuple)
        or not options_list
        or not all(isinstance(s, dict) for s in options_list)
    ):
        raise BenchError(f"sweep[{method!r}] must be a non-empty list of option dicts; got {options_list!r}")
    runs, skipped = [], []
    span = problem.t_span[1] - problem.t_span[0]
    for i, (options, (label, short)) in enumerate(zip(options_list, sweep_labels(list(options_list)), strict=True)):
        setting = Setting(problem, method, i, dict(options), label, short)
        limit = backend.bench_max_steps
        h = options.get("h")
        if limit is not None and isinstance(h, int | float) and h > 0 and span / h > limit:
            skipped.append(
                (setting, f"h = {h:g} makes {math.ceil(span / h):,} steps over [{problem.t_span[0]:g}, "
                 f"{problem.t_span[1]:g}], more than {method}'s bench_max_steps = {limit:,}")
            )  # fmt: skip
            continue
        try:
            check_setting(backend, options, problem.t_span, f"{problem.name}: {method} at {label}", "")
        except ModelError as error:
            if given:
                raise BenchError(f"{error}; fix sweep[{method!r}]") from None
            skipped.append((setting, f"{type(error).__name__}: {error}"))
            continue
        runs.append(setting)
    return runs, skipped


def setting_key(setting: Setting) -> str:
    """The run's file name stem in ``out/runs`` (:func:`~daemodel.comparing.bench_files.run_key`)."""
    from daemodel.comparing.bench_files import run_key

    return run_key(setting.problem.name, setting.method, setting.index)


def skipped_record(setting: Setting, reason: str) -> dict:
    """The record of a setting refused before any solve."""
    record = _record(setting)
    record.update(status="skipped", reason=reason)
    return record


def _record(setting: Setting) -> dict:
    return {
        "problem": setting.problem.name,
        "method": setting.method,
        "index": setting.index,
        "settings": setting.settings,
        "short": setting.short,
        "status": "",
        "scd": None,
        "scd_component": None,
        "setup_time": None,
        "solve_time": None,
        "wall_time": None,
        "error_class": None,
        "error": None,
        "flag": None,
        "reason": None,
        "messages": [],
        "stats": {},
    }


def run_setting(shared, setting: Setting, time_limit: float | None, threads: int) -> dict:
    """Solve one setting and read its scd: the record :func:`bench` stores (``shared`` is unused:
    :func:`daemodel.executors.run_tasks` passes every task one shared object)."""
    import torch

    from daemodel.compiling.compiler import as_compiled
    from daemodel.executors import time_limit as limited
    from daemodel.solving.solver import solve

    torch.set_num_threads(threads)
    problem, record = setting.problem, _record(setting)
    if problem.target not in _COMPILED:
        _COMPILED[problem.target] = as_compiled(problem.model(), "bench")
    compiled = _COMPILED[problem.target]
    message = (
        f"{problem.name}: {setting.method} at {setting.settings} ran past the time limit of {time_limit:g} s and was "
        "stopped; give bench a longer time_limit (--time-limit) or leave this setting out"
        if time_limit is not None
        else ""
    )
    began = time.perf_counter()
    limit = limited(time_limit, message)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            with limit:
                solution = solve(compiled, problem.t_span, method=setting.method, **setting.options)
        except Exception as error:  # any method's failure, a plugged-in one's too: recorded, by its class
            failed_after = time.perf_counter() - began
            name, text = type(error).__name__, str(error)
            if not isinstance(error, DaemodelError):
                text = f"(not a daemodel error) {text}"
            if limit.expired and not isinstance(error, TimeLimitError):
                # the limit struck inside a method that reports a callback's exception as its own failure
                name, text = TimeLimitError.__name__, f"{message} (it surfaced in {setting.method} as {name}: {text})"
            record.update(status="failed", error_class=name, error=text, solve_time=failed_after)
            solution = None
    record["messages"] = list(dict.fromkeys(f"{w.category.__name__}: {w.message}" for w in caught))
    if solution is not None and limit.expired:
        # the limit struck, and the method went on: code that treats any RuntimeError as a failure of its
        # own (a plugged-in method's; radau's factorisations did, before they let daemodel errors through)
        # took it for one, so the run finished, past its limit
        record.update(
            status="failed", error_class=TimeLimitError.__name__, solve_time=time.perf_counter() - began,
            error=f"{message} (the method caught it and finished after {time.perf_counter() - began:.3g} s)",
        )  # fmt: skip
        return record
    if solution is None:
        return record
    end = {name: float(solution[name][..., -1].reshape(-1)[0]) for name in (problem.scd_names or problem.reference)}
    digits, where = scd(end, problem.reference, problem.scd_names)
    record.update(
        scd=digits if math.isfinite(digits) else None,
        scd_component=where,
        setup_time=float(solution.setup_time),
        solve_time=float(solution.solve_time),
        wall_time=float(solution.setup_time) + float(solution.solve_time),
        stats={
            k: v
            for k, v in (solution.stats if isinstance(solution.stats, dict) else {}).items()
            if isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
        },
    )
    if solution.status == "success" and math.isfinite(digits):
        record["status"] = "success"
    else:
        record.update(status="flagged", flag=solution.status if solution.status != "success" else "no finite scd")
    return record


def _run(todo, out, executor, workers, address, time_limit, threads, progress, done) -> None:
    """Solve ``todo``, each record written to ``out/runs`` and added to ``done`` as it finishes."""
    from daemodel.backends.progress import progress_bar, show_progress
    from daemodel.comparing.bench_files import write_run
    from daemodel.executors import run_processes, run_tasks

    bar = progress_bar(len(todo), "bench", "run") if todo and show_progress(progress) else None

    def finished(i, record):
        done[setting_key(todo[i])] = write_run(out, record)
        if bar is not None:
            bar.set_postfix_str(f"{record['problem']} {record['method']} {record['settings']}")
            bar.update(1)

    try:
        if executor == "local":
            for i, setting in enumerate(todo):
                if bar is not None:
                    bar.set_postfix_str(f"{setting.problem.name} {setting.method} {setting.settings}")
                finished(i, run_setting(None, setting, time_limit, threads))
        elif executor == "processes":
            tasks = [(None, s, time_limit, threads) for s in todo]
            run_processes(run_setting, tasks, workers=workers, label="bench", on_result=finished)
        else:
            tasks = [(s, time_limit, threads) for s in todo]
            run_tasks(
                run_setting,
                None,
                tasks,
                executor="ray",
                workers=workers if address is None else None,
                address=address,
                label="bench",
                on_result=finished,
                task_timeout=None,  # each run keeps its own time_limit
            )
    finally:
        if bar is not None:
            bar.close()

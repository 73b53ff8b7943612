"""Ensembles: a large batch of initial states and parameter sets, solved chunk by chunk, in this
process or as Ray tasks (:mod:`daemodel.executors`), with each sample's failure recorded instead
of ending the run.

A chunk is one batched call of the method (radau's vectorised Newton over the chunk).  A chunk
that fails is split in halves until the failing samples stand alone; they are recorded by
index in ``stats["failures"]`` and left out of the returned Solution, whose values stay finite.
What the chunks give back is joined in :mod:`daemodel.solving.ensemble_results`; an ensemble
written to a directory is laid out, resumed and read back in :mod:`daemodel.solving.ensemble_files`.
"""

from __future__ import annotations

import dataclasses
import math
import sys
import time
from dataclasses import dataclass

import numpy as np

from daemodel.errors import (
    ConvergenceError,
    InconsistentAlgebraicValueError,
    InconsistentInitialStateError,
    InitialisationError,
    InvalidOptionError,
    SolverError,
    TimeLimitError,
)
from daemodel.executors import (
    DEFAULT_TASK_TIMEOUT,
    EXECUTORS,
    check_executor,
    check_timeout,
    refuse_engine,
    run_tasks,
    struck_limit,
)
from daemodel.files import DirectoryLock, check_memory, writable_directory
from daemodel.solution import Solution
from daemodel.solving.ensemble_files import (
    EnsembleFiles,
    inputs_digest,
    resume,
    run_fingerprint,
    write_chunk,
    write_manifest,
)
from daemodel.solving.ensemble_results import Failure, assemble, joined_switches, merged

# Samples per chunk by default: big enough that radau's per-step Python overhead is shared,
# small enough that a chunk's arrays stay modest (10^4 pendulum samples over 20 steps: ~10 MB).
DEFAULT_CHUNK = 10_000
# Failed samples an ensemble records before it stops.  A chunk is bisected down to its failing
# samples, so one whose every sample fails (an option that fails them all, such as a max_steps
# too small) costs about log2(chunk) times its own solve plus a solve per sample: the bound ends
# that after this many, with an error that names the first.
DEFAULT_MAX_FAILURES = 1000
# Failures of a single sample: what its own states or the method's iteration caused.  Any other
# error (a wrong option, a model error) would fail every sample and ends the ensemble at once.
SAMPLE_FAILURES = (SolverError, InitialisationError, InconsistentInitialStateError, InconsistentAlgebraicValueError)


def ensemble(
    model,
    t_span,
    *,
    y0=None,
    z0=None,
    parameters=None,
    method: str = "radau",
    executor: str = "local",
    chunk: int = DEFAULT_CHUNK,
    workers: int | None = None,
    address: str | None = None,
    progress: bool = False,
    write_to=None,
    max_failures: int | None = DEFAULT_MAX_FAILURES,
    task_timeout: float | None = DEFAULT_TASK_TIMEOUT,
    **options,
) -> Solution | EnsembleFiles:
    """Solve a large batch in chunks: ``executor="local"`` one chunk after another in this process
    (no Ray, no worker processes), ``executor="ray"`` one Ray task per chunk.

    Parameters
    ----------
    model : Model or CompiledDAE
    t_span, y0, z0, parameters, method, **options
        As in :func:`daemodel.solve`; the batch is split into chunks of ``chunk`` samples, each
        solved by one :func:`daemodel.solve` call.  ``engine=`` is the method's (radau's
        ``"torch"`` or ``"casadi"``), passed to every chunk's solve.
    executor : {"local", "ray"}
        Where the chunks run (:mod:`daemodel.executors`).  Spelled ``engine=`` before: ``engine="local"``
        or ``"ray"`` raises an :class:`InvalidOptionError` that names the new spelling.
    chunk : int
        Samples per task.  On a CPU about 10^4 (smaller arrays stay in cache); on a GPU the
        largest that fits its memory (10^5 pendulum states on an H100: one call 0.33 s, chunks
        of 10^4 1.19 s).
    workers : int, optional
        Ray only, when this call starts Ray: the CPUs of the local cluster it starts (default:
        all).  Each task takes one CPU and runs torch on one thread.
    address : str, optional
        Ray only: the cluster to connect to (``"auto"``, ``"ray://host:10001"``); default: the
        running one, else a new local one.
    progress : bool
        One line per finished chunk on stderr.
    max_failures : int or None
        Failed samples to record before the ensemble stops with a :class:`ConvergenceError`
        that names the first (default 1000; None: no bound).
    task_timeout : float or None
        Ray only: seconds a chunk's task may run before it is stopped with a
        :class:`TimeLimitError` (default one hour; None: no limit).
    write_to : str or Path, optional
        A directory (created if missing) to write each chunk's values to as the chunk finishes,
        one :meth:`Solution.save` file per chunk, with a manifest ``ensemble.json``, instead of
        keeping them in memory: for batches whose values do not fit.  The call then returns an
        :class:`EnsembleFiles`, which reads them back a chunk at a time.  The directory is
        locked while the call runs (a second writer is refused).  The same call on a directory
        that an interrupted run left **resumes**: the chunks there are checked against this
        call's model, inputs, method and settings and kept, and only the others are solved; a
        chunk of any other run is refused by name.  On a finished directory of the same call it
        returns the files without solving.

    Notes
    -----
    Adaptive radau with no ``t_eval`` reports a batch on the steps it took together: an ensemble
    of more than one sample needs ``t_eval`` then, so that every chunk, and each half of a chunk
    split around a failing sample, gives its values on the same times.

    Returns
    -------
    Solution
        The samples that were solved, in batch order, batched.  ``stats["samples"]`` holds their
        indices in the ensemble, ``stats["failures"]`` a :class:`Failure` per sample that was
        not (the status says how many), ``stats["chunks"]`` each chunk's seconds and size;
        ``events`` and ``breakpoints`` as a batched solve's ((B, K), NaN-padded).
        With ``write_to``, an :class:`EnsembleFiles` instead.

    Raises
    ------
    ResourceLimitError
        In memory, before any chunk, when the outputs (samples x the output times that ``t_eval``
        or a fixed ``h`` gives x variables) exceed :func:`daemodel.files.memory_limit`.
    InvalidOptionError
        ``engine="local"`` or ``"ray"`` (now ``executor=``), or an option that the method or
        the executor refuses, named before any chunk runs.
    InvalidOptionError, SolutionFileError
        With ``write_to``: a directory of another run (other inputs, model, events, parameter
        values, method or settings).
    """
    from daemodel.backends import get_backend
    from daemodel.compiling.compiler import as_compiled
    from daemodel.compiling.initial_states import columns as columns_of
    from daemodel.solving.solver import check_options, check_span

    if isinstance(options.get("engine"), str) and options["engine"] in EXECUTORS:
        refuse_engine("ensemble()", options)  # the old spelling of executor=; any other engine= is the method's
    check_executor(executor, workers, address, options.get("device", "cpu"))
    check_timeout(task_timeout)
    backend = get_backend(method)
    if "dense_output" in {f.name for f in dataclasses.fields(backend.Options)} and "dense_output" not in options:
        # an ensemble keeps its chunks' values, not their dense outputs: none is built (radau's takes s + 1
        # times the memory of the values)
        options = {**options, "dense_output": False}
    checked = check_options(backend, options)  # a misspelt option is named before any chunk runs
    if isinstance(chunk, bool) or not isinstance(chunk, int | np.integer) or chunk < 1:
        raise InvalidOptionError(f"chunk must be a positive integer (samples per task); got {chunk!r}")
    chunk = int(chunk)
    if max_failures is not None and (
        isinstance(max_failures, bool) or not isinstance(max_failures, int | np.integer) or max_failures < 0
    ):
        raise InvalidOptionError(f"max_failures must be a non-negative integer or None; got {max_failures!r}")
    compiled = as_compiled(model, "ensemble()")
    t_span = check_span(t_span, compiled)
    columns = {
        "y0": columns_of(compiled, y0, compiled.state_names, compiled.y0, "y0"),
        "parameters": columns_of(
            compiled, parameters, compiled.parameter_names, compiled.parameter_values, "parameters"
        ),
    }
    if z0 is not None:
        columns["z0"] = columns_of(compiled, z0, compiled.algebraic_names, compiled.z0, "z0")
    sizes = {name: size for name, (size, _) in columns.items() if size is not None}
    if len(set(sizes.values())) > 1:
        raise InvalidOptionError(
            "y0, z0 and parameters make batches of different sizes: "
            + ", ".join(f"{name}: {size}" for name, size in sizes.items())
        )
    total = next(iter(sizes.values()), 1)
    if total > 1 and backend.times_follow_samples(checked):
        raise InvalidOptionError(
            f"ensemble: {method} with adaptive steps and no t_eval reports each batch on the steps it took, so the "
            "chunks (and the halves of a chunk split around a failing sample) would come back on different times; "
            "give t_eval=[...] (the collocation polynomials give the values there)"
        )
    times = _output_times_at_least(checked, t_span)
    if write_to is None and times:  # refused before any chunk: outputs that cannot fit are known from the options
        variables = len(compiled.states) + len(compiled.algebraics) + len(compiled.aliases)
        check_memory(
            f"ensemble of {total} samples kept in memory",
            {f"outputs of at least {times} times x {variables} variables": total * times * variables * 8},
        )
    arrays = {name: np.broadcast_to(array, (total, array.shape[1])) for name, (_, array) in columns.items()}
    pieces = [(start, min(start + chunk, total)) for start in range(0, total, chunk)]
    work = [
        (start, {name: np.ascontiguousarray(array[start:stop]) for name, array in arrays.items()})
        for start, stop in pieces
    ]
    plan = _Plan(
        compiled,
        t_span,
        method,
        options,
        total,
        chunk,
        executor,
        workers,
        address,
        progress,
        max_failures,
        task_timeout,
    )
    if write_to is None:
        return _run(plan, work)
    directory = writable_directory(write_to, "write_to")  # made once the inputs are known good
    with DirectoryLock(directory, "write_to"):
        digests = {start: inputs_digest(batch) for start, batch in work}
        run = run_fingerprint(compiled, t_span, method, options, chunk, total, digests)
        done = resume(directory, compiled, run, digests, {start: len(batch["y0"]) for start, batch in work})
        if isinstance(done, EnsembleFiles):
            return done
        began = time.perf_counter()
        earlier = [failure for result in done.values() for failure in result["failures"]]
        results = _run(plan, [item for item in work if item[0] not in done], (directory, run, digests), earlier)
        # the run's wall time: this call's, plus the seconds of the chunks an earlier call left
        seconds = time.perf_counter() - began + sum(result["seconds"] for result in done.values())
        results = sorted([*done.values(), *results], key=lambda result: result["offset"])
        write_manifest(directory, compiled, results, total, seconds, executor, chunk, run)
        return EnsembleFiles.load(directory, compiled)


def _output_times_at_least(options, t_span) -> int | None:
    """The fewest output times a solve with ``options`` (a method's Options) reports: its ``t_eval``'s
    distinct times, else the grid of a fixed step ``h`` (events add times); None where the options
    do not tell (then the first chunk does)."""
    given = {f.name: getattr(options, f.name) for f in dataclasses.fields(options)}
    t_eval, h = given.get("t_eval"), given.get("h")
    if t_eval is not None:
        try:
            return len(np.unique(np.asarray(t_eval, dtype=float)))
        except (TypeError, ValueError):  # (the method names what is wrong with it)
            return None
    if isinstance(h, int | float) and not isinstance(h, bool) and h > 0:
        return math.ceil(min((t_span[1] - t_span[0]) / h * (1 - 1e-9), 2**53)) + 1  # (steps of h, rounded up)
    return None


@dataclass(frozen=True)
class _Plan:
    """One ensemble call's settings, as given."""

    compiled: object
    t_span: tuple
    method: str
    options: dict
    total: int
    chunk: int
    executor: str
    workers: int | None
    address: str | None
    progress: bool
    max_failures: int | None
    task_timeout: float | None


def _run(plan: _Plan, work: list, files: tuple | None = None, earlier: tuple = ()):
    """Solve ``work``'s chunks: each result written to ``files`` = (directory, run, digests) as it
    finishes (the results, without values, are returned), or kept and assembled into one Solution."""
    began = time.perf_counter()
    finished, failed, sized = [], list(earlier), []  # a resumed run's failures count towards max_failures

    def report(_, result) -> None:
        finished.append(result["size"])
        failed.extend(result["failures"])
        if result.get("stopped") or (plan.max_failures is not None and len(failed) > plan.max_failures):
            _too_many_failures(failed, plan.max_failures)
        if files is None and "values" in result and not sized:  # the first values tell the output's size
            sized.append(True)
            width = sum(value.shape[1] for value in result["values"].values())  # times x variables
            check_memory(f"ensemble of {plan.total} samples kept in memory", {"outputs": plan.total * width * 8})
        if files is not None:
            write_chunk(files, plan.compiled, result)
        elif plan.executor == "ray" and "values" in result:
            # arrays from Ray are views into its object store, which they would keep pinned
            result["values"] = {name: np.array(value) for name, value in result["values"].items()}
            result["parameters"] = np.array(result["parameters"])
            result["switches"] = joined_switches([result["switches"]]) | {"rows": result["switches"]["rows"]}
        if plan.progress:
            print(
                f"ensemble: {len(finished)}/{len(work)} chunks, {sum(finished)} samples, "
                f"{time.perf_counter() - began:.1f} s",
                file=sys.stderr,
                flush=True,
            )

    results = run_tasks(
        solve_chunk,
        (plan.compiled, plan.t_span, plan.method, plan.options, plan.max_failures),
        work,
        executor=plan.executor,
        workers=plan.workers,
        address=plan.address,
        label="ensemble",
        on_result=report,
        task_timeout=plan.task_timeout,
    )
    if files is not None:
        return results
    return assemble(plan.compiled, results, plan.total, time.perf_counter() - began, plan.executor, plan.chunk)


def solve_chunk(shared: tuple, offset: int, batch: dict) -> dict:
    """One chunk: its samples' values, or, for a chunk that fails, its halves' (down to single
    samples, whose failures are recorded).  ``shared`` is (compiled, t_span, method, options,
    max_failures); a chunk that finds more than max_failures failures stops there, and its
    result says ``"stopped"``.  Plain data in and out: it runs in a Ray worker."""
    *problem, max_failures = shared
    began = time.perf_counter()
    found: list = []
    try:
        return _solve_part(problem, offset, batch, found, max_failures)
    except _TooManyFailures:
        seconds = time.perf_counter() - began
        return {"offset": offset, "size": len(batch["y0"]), "seconds": seconds, "failures": found, "stopped": True}


class _TooManyFailures(Exception):
    """A chunk's bisection found more failures than max_failures (internal: ends the chunk)."""


def _solve_part(problem: list, offset: int, batch: dict, found: list, max_failures: int | None) -> dict:
    from daemodel.solving.solver import solve

    compiled, t_span, method, options = problem
    size = len(batch["y0"])
    began = time.perf_counter()
    try:
        solution = solve(compiled, t_span, method=method, **batch, **options)
    except SAMPLE_FAILURES as error:
        if isinstance(error, TimeLimitError):  # the task's time is up: no half of it may run on
            raise
        if struck_limit() is not None:  # (it struck inside a call that reported it as its own failure)
            raise struck_limit() from error
        if size == 1:
            failure = Failure(index=offset, error=type(error).__name__, message=str(error))
            found.append(failure)
            if max_failures is not None and len(found) > max_failures:
                raise _TooManyFailures from None
            return {"offset": offset, "size": 1, "seconds": time.perf_counter() - began, "failures": [failure]}
        half = size // 2
        parts = [
            _solve_part(problem, offset + lo, {k: v[lo:hi] for k, v in batch.items()}, found, max_failures)
            for lo, hi in ((0, half), (half, size))
        ]
        return merged(parts, offset, size, time.perf_counter() - began)
    values = {name: np.asarray(value).reshape(size, -1) for name, value in solution.values.items()}
    return {
        "offset": offset,
        "size": size,
        "seconds": time.perf_counter() - began,
        "failures": [],
        "indices": np.arange(offset, offset + size),
        "values": values,
        "parameters": np.asarray(solution.parameters).reshape(size, -1),
        "switches": {"events": solution.events, "breakpoints": solution.breakpoints, "rows": size},
        # the solved system travels as its index, not pickled back: the driver holds the model
        "meta": {key: getattr(solution, key) for key in ("t", "method", "settings", "status")},
        "index": solution.compiled.index,
    }


def _too_many_failures(failed: list, max_failures: int) -> None:
    """Stop the ensemble: more than ``max_failures`` samples failed (``failed``, so far)."""
    first = min(failed, key=lambda f: f.index)
    raise ConvergenceError(
        f"ensemble: more than max_failures={max_failures} samples failed ({len(failed)} found, first: sample "
        f"{first.index}, {first.error}: {first.message}); the ensemble stopped, with samples left unsolved. "
        "If many samples are expected to fail, raise max_failures (None: no bound); else fix what fails them"
    )

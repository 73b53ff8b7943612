"""Ensembles: a large batch of initial states and parameter sets, solved chunk by chunk, in this
process or as Ray tasks, with each sample's failure recorded instead of ending the run.

A chunk is one batched call of the method (radau's vectorised Newton over the chunk).  A chunk
that fails is split in halves until the failing samples stand alone; they are recorded by
index in ``stats["failures"]`` and left out of the returned Solution, whose values stay finite.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import re
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from daemodel.errors import (
    InconsistentAlgebraicValueError,
    InconsistentInitialStateError,
    InitialisationError,
    InvalidOptionError,
    SolutionFileError,
    SolverError,
    TimeLimitError,
)
from daemodel.executors import DEFAULT_TASK_TIMEOUT, check_executor, check_timeout, run_tasks
from daemodel.files import (
    DirectoryLock,
    check_memory,
    is_plain_file,
    open_inside,
    read_arrays,
    read_json,
    readable_path,
    writable_directory,
    write_json,
)
from daemodel.solution import Solution
from daemodel.solution_files import SOLUTION_ARRAYS, declared, matching_system, read

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
# What ensemble(write_to=...) writes: a manifest and one Solution.save file per chunk with values.
# Each chunk records the run's fingerprint (model, t_span, method, settings, chunking) and a hash
# of its own samples' inputs, so that a resumed run takes only its own chunks and a loader
# refuses a chunk copied from another run.
ENSEMBLE_FORMAT = "daemodel-ensemble/3"
# Formats this version refuses by name: /1 carried no fingerprints, /2 none of events or parameter values.
OLDER_ENSEMBLE_FORMATS = {
    "daemodel-ensemble/1": "whose chunks carry no fingerprints",
    "daemodel-ensemble/2": "whose fingerprints ignore events and parameter values",
}
MANIFEST = "ensemble.json"
CHUNK_FILE = "chunk-{offset:012d}.npz"
CHUNK_NAME = re.compile(r"chunk-(\d{12})\.npz")
# What an interrupted atomic write leaves: a temporary file, never complete, removed on resume.
PARTIAL_NAME = re.compile(r"\.(chunk-\d{12}\.npz|ensemble\.json)\..+\.partial")
MANIFEST_KEYS = (
    "model",
    "fingerprint",
    "fingerprints",
    "declared",
    "run",
    "total",
    "chunk",
    "engine",
    "seconds",
    "status",
    "failures",
    "files",
)


@dataclass(frozen=True)
class Failure:
    """One sample the method could not solve.

    Attributes
    ----------
    index : int
        The sample's position in the ensemble's batch.
    error : str
        The exception's class name (see :mod:`daemodel.errors`).
    message : str
        The method's message from solving this sample alone: where it says "sample 0", that is
        this sample (``index`` in the ensemble).
    """

    index: int
    error: str
    message: str


def ensemble(
    model,
    t_span,
    *,
    y0=None,
    z0=None,
    parameters=None,
    method: str = "radau",
    engine: str = "local",
    chunk: int = DEFAULT_CHUNK,
    workers: int | None = None,
    address: str | None = None,
    progress: bool = False,
    write_to=None,
    max_failures: int | None = DEFAULT_MAX_FAILURES,
    task_timeout: float | None = DEFAULT_TASK_TIMEOUT,
    **options,
) -> Solution | EnsembleFiles:
    """Solve a large batch in chunks: ``engine="local"`` one chunk after another in this process
    (no Ray, no worker processes), ``engine="ray"`` one Ray task per chunk.

    Parameters
    ----------
    model : Model or CompiledDAE
    t_span, y0, z0, parameters, method, **options
        As in :func:`daemodel.solve`; the batch is split into chunks of ``chunk`` samples, each
        solved by one :func:`daemodel.solve` call.
    engine : {"local", "ray"}
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
    InvalidOptionError, SolutionFileError
        With ``write_to``: a directory of another run (other inputs, model, events, parameter
        values, method or settings).
    """
    from daemodel.backends import get_backend
    from daemodel.compiling.compiler import as_compiled
    from daemodel.compiling.initial_states import _columns
    from daemodel.solving.solver import check_options, check_span

    check_executor(engine, workers, address, options.get("device", "cpu"))
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
        "y0": _columns(compiled, y0, compiled.state_names, compiled.y0, "y0"),
        "parameters": _columns(compiled, parameters, compiled.parameter_names, compiled.parameter_values, "parameters"),
    }
    if z0 is not None:
        columns["z0"] = _columns(compiled, z0, compiled.algebraic_names, compiled.z0, "z0")
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
        compiled, t_span, method, options, total, chunk, engine, workers, address, progress, max_failures, task_timeout
    )
    if write_to is None:
        return _run(plan, work)
    directory = writable_directory(write_to, "write_to")  # made once the inputs are known good
    with DirectoryLock(directory, "write_to"):
        digests = {start: _inputs_digest(batch) for start, batch in work}
        run = _run_fingerprint(compiled, t_span, method, options, chunk, total, digests)
        done = _resume(directory, compiled, run, digests, {start: len(batch["y0"]) for start, batch in work})
        if isinstance(done, EnsembleFiles):
            return done
        began = time.perf_counter()
        earlier = [failure for result in done.values() for failure in result["failures"]]
        results = _run(plan, [item for item in work if item[0] not in done], (directory, run, digests), earlier)
        # the run's wall time: this call's, plus the seconds of the chunks an earlier call left
        seconds = time.perf_counter() - began + sum(result["seconds"] for result in done.values())
        results = sorted([*done.values(), *results], key=lambda result: result["offset"])
        _write_manifest(directory, compiled, results, total, seconds, engine, chunk, run)
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
    engine: str
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
            _write_chunk(files, plan.compiled, result)
        elif plan.engine == "ray" and "values" in result:
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
        engine=plan.engine,
        workers=plan.workers,
        address=plan.address,
        label="ensemble",
        on_result=report,
        task_timeout=plan.task_timeout,
    )
    if files is not None:
        return results
    return _assemble(plan.compiled, results, plan.total, time.perf_counter() - began, plan.engine, plan.chunk)


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
        return _merge(parts, offset, size, time.perf_counter() - began)
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


def _merge(parts: list, offset: int, size: int, seconds: float) -> dict:
    solved = [part for part in parts if "values" in part]
    merged = {
        "offset": offset,
        "size": size,
        "seconds": seconds,
        "failures": [failure for part in parts for failure in part["failures"]],
    }
    if solved:
        merged["indices"] = np.concatenate([part["indices"] for part in solved])
        merged["values"] = {
            name: np.concatenate([part["values"][name] for part in solved]) for name in solved[0]["values"]
        }
        merged["parameters"] = np.concatenate([part["parameters"] for part in solved])
        merged["switches"] = joined_switches([part["switches"] for part in solved]) | {"rows": len(merged["indices"])}
        merged["meta"], merged["index"] = solved[0]["meta"], solved[0]["index"]
    return merged


def _assemble(compiled, results: list, total: int, seconds: float, engine: str, chunk: int) -> Solution:
    failures = _failures(results, total)
    solved = [result for result in results if "values" in result]
    values = {name: np.concatenate([result["values"][name] for result in solved]) for name in solved[0]["values"]}
    stats = {
        "engine": engine,
        "chunk": chunk,
        "samples": np.concatenate([result["indices"] for result in solved]),
        "failures": failures,
        "chunks": [
            {key: r[key] for key in ("offset", "size", "seconds")} | {"status": r["meta"]["status"]} for r in solved
        ],
        "peak_memory_mb": [r["peak_memory_mb"] for r in results if "peak_memory_mb" in r],
    }
    meta = solved[0]["meta"]
    return Solution(
        values=values,
        parameters=np.concatenate([result["parameters"] for result in solved]),
        **joined_switches([result["switches"] for result in solved]),
        solve_time=seconds,
        stats=stats,
        batched=True,
        compiled=_system(compiled, solved[0]["index"]),
        **{**meta, "status": _status([(r["offset"], r["meta"]["status"]) for r in solved], failures, total)},
    )


def _joined_records(records: list) -> dict:
    """Breakpoint or event records of consecutive rows (``"t"``, ``"moved"`` (b, K), ``"before"``,
    ``"after"`` name -> (b, K)) as one, each padded with NaN to the most switches any row had."""
    K = max(record["t"].shape[1] for record in records)

    def joined(tables: list) -> np.ndarray:
        padded = [
            np.pad(np.asarray(x, dtype=float), ((0, 0), (0, K - x.shape[1])), constant_values=np.nan) for x in tables
        ]
        return np.concatenate(padded)

    out = {key: joined([record[key] for record in records]) for key in ("t", "moved")}
    for side in ("before", "after"):
        out[side] = {name: joined([record[side][name] for record in records]) for name in records[0][side]}
    return out


def joined_switches(parts: list) -> dict:
    """The ``{"events": ..., "breakpoints": ...}`` of solutions of consecutive rows (chunks, halves of
    a chunk; ``"rows"`` each) as those of one Solution: the layout of a batched solve's, NaN-padded."""
    names = list(dict.fromkeys(name for part in parts for name in part["events"]))
    variables = next((list(r["before"]) for p in parts for r in [p["breakpoints"], *p["events"].values()] if r), [])

    def record(found: dict | None, rows: int) -> dict:  # (a part without this switch: none of its rows had one)
        if found:
            return found
        none = np.zeros((rows, 0))
        return {
            "t": none,
            "moved": none,
            "before": dict.fromkeys(variables, none),
            "after": dict.fromkeys(variables, none),
        }

    out = {
        "events": {
            name: _joined_records([record(part["events"].get(name), part["rows"]) for part in parts]) for name in names
        },
        "breakpoints": {},
    }
    if any(part["breakpoints"] for part in parts):
        out["breakpoints"] = _joined_records([record(part["breakpoints"], part["rows"]) for part in parts])
    return out


def switch_rows(switches: dict, rows) -> dict:
    """``{"events": ..., "breakpoints": ...}`` of the rows ``rows`` (a mask or indices)."""

    def take(record: dict) -> dict:
        out = {key: np.asarray(record[key])[rows] for key in ("t", "moved")}
        out |= {side: {name: np.asarray(v)[rows] for name, v in record[side].items()} for side in ("before", "after")}
        return out

    return {
        "events": {name: take(record) for name, record in switches["events"].items()},
        "breakpoints": take(switches["breakpoints"]) if switches["breakpoints"] else {},
    }


def _system(compiled, index: int):
    """The system a method solved: the model, or its reduction to ``index``."""
    return compiled if compiled.index <= index else compiled.reduced(index)


def _failures(results: list, total: int) -> list:
    """Every failure by index; a ConvergenceError naming the first when no sample was solved."""
    from daemodel.errors import ConvergenceError

    failures = sorted((failure for result in results for failure in result["failures"]), key=lambda f: f.index)
    if len(failures) == total:
        first = failures[0]
        raise ConvergenceError(
            f"ensemble: every one of the {total} samples failed; sample {first.index}: {first.error}: {first.message}"
        )
    return failures


def _too_many_failures(failed: list, max_failures: int) -> None:
    from daemodel.errors import ConvergenceError

    first = min(failed, key=lambda f: f.index)
    raise ConvergenceError(
        f"ensemble: more than max_failures={max_failures} samples failed ({len(failed)} found, first: sample "
        f"{first.index}, {first.error}: {first.message}); the ensemble stopped, with samples left unsolved. "
        "If many samples are expected to fail, raise max_failures (None: no bound); else fix what fails them"
    )


def _status(statuses: list, failures: list, total: int) -> str:
    """The chunks' status when they agree, else each distinct one with the chunks that gave it
    (a fixed-budget PINN states its own residual per chunk); then the failures' count."""
    distinct: dict = {}
    for offset, status in statuses:
        distinct.setdefault(status, []).append(offset)
    if len(distinct) == 1:
        status = statuses[0][1]
    else:
        status = "the chunks' statuses differ: " + "; ".join(
            f"{text!r} (chunks from sample {', '.join(map(str, offsets[:3]))}{', ...' if len(offsets) > 3 else ''})"
            for text, offsets in distinct.items()
        )
    if not failures:
        return status
    shown = f"{len(failures)} of {total} samples failed and are left out (stats['failures'], first: sample "
    return f"{status}; {shown}{failures[0].index}, {failures[0].error})"


# ---- chunks written to files ----------------------------------------------------------------------
class EnsembleFiles:
    """An ensemble written chunk by chunk to a directory by ``ensemble(..., write_to=...)``.

    Iterate over it for one :class:`Solution` per chunk file (its ``stats["samples"]`` are the
    samples' indices in the ensemble), or gather chosen samples with :meth:`solution`: either
    way only one chunk's values are read at a time.

    Attributes
    ----------
    directory : Path
    total : int
        Samples in the ensemble, solved or not.
    failures : list of Failure
        The samples that were not solved, by index.
    status, engine, chunk, seconds
        As the in-memory ensemble's ``status`` and ``stats``; ``seconds`` is the whole run.

    Examples
    --------
    >>> files = dm.ensemble(model, (0, 1), y0=states, h=0.05, write_to="runs/sweep")
    >>> peak = max(part["y1"].max() for part in files)   # one chunk in memory at a time
    >>> files.solution([0, 17, 99_999])["y1"]     # three samples, read from their chunks
    >>> files = dm.EnsembleFiles.load("runs/sweep", model)   # later, in another process
    """

    def __init__(self, directory: Path, compiled, manifest: dict):
        self.directory, self.compiled, self._manifest = directory, compiled, manifest
        self.total, self.run = int(manifest["total"]), manifest["run"]
        self.failures = [Failure(**failure) for failure in manifest["failures"]]
        self.status, self.engine = manifest["status"], manifest["engine"]
        self.chunk, self.seconds = int(manifest["chunk"]), float(manifest["seconds"])

    @classmethod
    def load(cls, directory, model) -> EnsembleFiles:
        """The ensemble written to ``directory`` for ``model`` (a Model or CompiledDAE with the
        same equations and names).

        Raises
        ------
        SolutionFileError
            No manifest there, not a daemodel ensemble, a field that is damaged (named), a chunk
            file missing or not a plain file, or another model.
        """
        from daemodel.compiling.compiler import as_compiled

        directory = readable_path(directory, "EnsembleFiles.load: directory", SolutionFileError, "directory")
        path = directory / MANIFEST
        if not path.exists():
            raise SolutionFileError(f"no ensemble at {directory}: {MANIFEST} is missing")
        manifest = read_json(path, SolutionFileError, "a daemodel ensemble manifest", follow=False)
        if isinstance(manifest, dict) and manifest.get("format") in OLDER_ENSEMBLE_FORMATS:
            raise SolutionFileError(
                f"{path} is a daemodel ensemble of format {manifest['format']!r}, "
                f"{OLDER_ENSEMBLE_FORMATS[manifest['format']]}; this version reads {ENSEMBLE_FORMAT!r}: solve the "
                "ensemble again into a new directory"
            )
        if not isinstance(manifest, dict) or manifest.get("format") != ENSEMBLE_FORMAT:
            raise SolutionFileError(f"{path} is not a daemodel ensemble manifest (expected format {ENSEMBLE_FORMAT!r})")
        lacking = [key for key in MANIFEST_KEYS if key not in manifest]
        if lacking:
            raise SolutionFileError(f"{path} is damaged: it lacks {', '.join(lacking)}")
        _check_manifest(path, manifest)
        compiled = as_compiled(model, "EnsembleFiles.load()")
        matching_system(compiled, manifest, directory, "an ensemble")
        missing = [entry["file"] for entry in manifest["files"] if not is_plain_file(directory / entry["file"])]
        if missing:
            raise SolutionFileError(
                f"{directory}: {len(missing)} of the ensemble's {len(manifest['files'])} chunk files are missing "
                f"(first: {missing[0]})"
            )
        return cls(directory, compiled, manifest)

    def __len__(self) -> int:
        """Chunk files (a chunk whose every sample failed has none)."""
        return len(self._manifest["files"])

    @property
    def solved(self) -> int:
        """Samples with values."""
        return sum(entry["solved"] for entry in self._manifest["files"])

    def __iter__(self):
        for entry in self._manifest["files"]:
            yield self._read(entry)

    def _read(self, entry: dict) -> Solution:
        part = _read_chunk(self.directory, entry["file"], self.compiled)
        samples = part.stats["samples"]
        if part.stats.get("run") != self.run or part.stats.get("inputs") != entry["inputs"]:
            raise SolutionFileError(
                f"{self.directory / entry['file']} is a chunk of another ensemble run (other samples, model, method "
                "or settings) than this manifest's: it was copied or left there; the ensemble is damaged"
            )
        if (
            len(samples) != entry["solved"]
            or (samples < entry["offset"]).any()
            or (samples >= entry["offset"] + entry["size"]).any()
        ):
            raise SolutionFileError(
                f"{self.directory / entry['file']} holds {len(samples)} samples, not the {entry['solved']} of samples "
                f"{entry['offset']} to {entry['offset'] + entry['size'] - 1} that the manifest lists"
            )
        return part

    def solution(self, samples=None) -> Solution:
        """The values of ``samples`` (indices in the ensemble, in the order given; default: every
        solved sample, which must then fit in memory), as one batched Solution.

        Raises
        ------
        InvalidOptionError
            An index outside the ensemble, or of a sample that failed (named, with its error).
        """
        rows = self.solved if samples is None else np.size(samples)
        if self._manifest["files"]:
            first_file = self._manifest["files"][0]["file"]
            with open_inside(self.directory, first_file, "files[0].file", SolutionFileError) as handle:
                where = self.directory / first_file
                shapes = read_arrays(handle, where, SOLUTION_ARRAYS, SolutionFileError, data=False, others=True)
            _, times, variables = shapes["values"]
            check_memory(
                f"EnsembleFiles.solution of {rows} samples of {times} times and {variables} variables",
                {"values": rows * times * variables * 8},
            )
        wanted = self._wanted(samples)
        kept, first = [], None  # per chunk read: the wanted rows only, so one chunk is whole at a time
        for entry in self._manifest["files"]:
            inside = wanted[(wanted >= entry["offset"]) & (wanted < entry["offset"] + entry["size"])]
            if len(inside):
                part = self._read(entry)
                rows = np.isin(part.stats["samples"], inside)
                kept.append(
                    (
                        part.stats["samples"][rows],
                        {name: part.values[name][rows].copy() for name in self._names(part)},
                        part.parameters[rows].copy(),
                        switch_rows({"events": part.events, "breakpoints": part.breakpoints}, rows)
                        | {"rows": int(rows.sum())},
                    )
                )
                first = first or {key: getattr(part, key) for key in ("t", "method", "settings", "compiled")}
                del part
        got = np.concatenate([indices for indices, *_ in kept]) if kept else np.zeros(0, np.int64)
        absent = np.setdiff1d(wanted, got)
        if len(absent):
            raise SolutionFileError(
                f"{self.directory}: sample {absent[0]} is in no chunk file although the manifest does not list it as "
                "failed: the ensemble is damaged"
            )
        order = np.argsort(got, kind="stable")
        take = order[np.searchsorted(got, wanted, sorter=order)]
        names = kept[0][1].keys()
        return Solution(
            values={name: np.concatenate([values[name] for _, values, *_ in kept])[take] for name in names},
            solve_time=self.seconds,
            stats={"samples": wanted, "engine": self.engine, "chunk": self.chunk},
            parameters=np.concatenate([parameters for _, _, parameters, _ in kept])[take],
            **switch_rows(joined_switches([switches for *_, switches in kept]), take),
            batched=True,
            status=self.status,
            **first,
        )

    @staticmethod
    def _names(part: Solution) -> tuple:
        return (*part.compiled.state_names, *part.compiled.algebraic_names)

    def _wanted(self, samples) -> np.ndarray:
        failed = {failure.index: failure for failure in self.failures}
        if samples is None:
            return np.setdiff1d(np.arange(self.total, dtype=np.int64), np.fromiter(failed, np.int64, len(failed)))
        wanted = np.atleast_1d(np.asarray(samples))
        if wanted.ndim != 1 or not len(wanted) or not np.issubdtype(wanted.dtype, np.integer):
            raise InvalidOptionError(f"samples must be a non-empty list of sample indices; got {samples!r}")
        outside = wanted[(wanted < 0) | (wanted >= self.total)]
        if len(outside):
            raise InvalidOptionError(f"sample {outside[0]} is not in the ensemble of {self.total} samples")
        lost = [failed[i] for i in wanted.tolist() if i in failed]
        if lost:
            raise InvalidOptionError(
                f"sample {lost[0].index} failed ({lost[0].error}: {lost[0].message}) and has no values; "
                f"{len(self.failures)} samples failed (EnsembleFiles.failures)"
            )
        return wanted.astype(np.int64)

    def __repr__(self) -> str:
        return (
            f"EnsembleFiles('{self.directory}', {self.solved} of {self.total} samples in {len(self)} chunk files, "
            f"status={self.status!r})"
        )


def _run_fingerprint(compiled, t_span, method: str, options: dict, chunk: int, total: int, digests: dict) -> str:
    """What makes two ensemble calls the same run: the model (its equations, events and parameter
    values), the span, the method, its settings, the chunking and every chunk's inputs (``digests``,
    offset -> hash): a finished directory run again with other inputs is another run."""
    text = json.dumps(
        [
            ENSEMBLE_FORMAT,
            compiled.fingerprint(),
            list(t_span),
            method,
            sorted(options.items()),
            chunk,
            total,
            sorted(digests.items()),
        ],
        default=lambda value: np.asarray(value).tolist() if isinstance(value, np.ndarray | np.generic) else repr(value),
    )
    return hashlib.sha256(text.encode()).hexdigest()


def _inputs_digest(batch: dict) -> str:
    """A hash of one chunk's inputs (y0, z0, parameters), by name."""
    digest = hashlib.sha256()
    for name in sorted(batch):
        digest.update(name.encode() + np.ascontiguousarray(batch[name], dtype=np.float64).tobytes())
    return digest.hexdigest()


def _read_chunk(directory: Path, name: str, compiled) -> Solution:
    """A chunk file (its name checked, read without following a link) as a Solution."""
    with open_inside(directory, name, "chunk file", SolutionFileError) as handle:
        part = read(handle, directory / name, compiled)
    samples = part.stats.get("samples")
    if (
        not isinstance(samples, np.ndarray)
        or samples.dtype.kind not in "iu"
        or samples.shape != (part.batch_size,)
        or (samples < 0).any()
        or len(np.unique(samples)) != len(samples)
    ):
        raise SolutionFileError(
            f"{directory / name}: field 'stats.samples' is not {part.batch_size} distinct sample indices, one a row"
        )
    part.stats["samples"] = np.asarray(samples, dtype=np.int64)
    try:
        part.stats["failures"] = [Failure(**failure) for failure in part.stats.get("failures", [])]
    except TypeError:
        raise SolutionFileError(f"{directory / name}: field 'stats.failures' is damaged") from None
    return part


def _resume(directory: Path, compiled, run: str, digests: dict, sizes: dict):
    """What an earlier run of the same call left in ``directory``: the finished ensemble's
    :class:`EnsembleFiles`, or the chunks already written (by offset, as results without values);
    anything of another run is refused by name.  Temporary files of interrupted writes are removed."""
    names = sorted(entry.name for entry in directory.iterdir())
    for name in names:
        if PARTIAL_NAME.fullmatch(name):
            (directory / name).unlink(missing_ok=True)
    if MANIFEST in names:
        files = EnsembleFiles.load(directory, compiled)
        if files.run != run:
            raise InvalidOptionError(
                f"write_to {directory} holds a finished ensemble of other samples, model, method or settings; give "
                "another directory, or remove its files"
            )
        return files
    done = {}
    for name in names:
        if not name.startswith("chunk-"):
            continue
        match = CHUNK_NAME.fullmatch(name)
        offset = int(match[1]) if match else None
        if offset not in sizes or not is_plain_file(directory / name):
            raise InvalidOptionError(
                f"write_to {directory}: {name} is not one of this ensemble's chunk files (chunk-<first sample>.npz "
                "for its chunking, a plain file); give another directory, or remove it"
            )
        part = _read_chunk(directory, name, compiled)
        if part.stats.get("run") != run or part.stats.get("inputs") != digests[offset]:
            raise InvalidOptionError(
                f"write_to {directory}: {name} is not a chunk of this ensemble (another run's samples, model, method, "
                "settings or chunking); give another directory, or remove that file to solve its samples again"
            )
        done[offset] = {
            "offset": offset,
            "size": sizes[offset],
            "seconds": part.solve_time,
            "failures": part.stats["failures"],
            "file": name,
            "solved": len(part.stats["samples"]),
            "meta": {"status": part.status},
            "index": part.compiled.index,
            "inputs": digests[offset],
        }
    return done


def _write_chunk(files: tuple, compiled, result: dict) -> None:
    """Write a finished chunk's values and drop them from ``result``, which keeps its bookkeeping."""
    if "values" not in result:
        return
    directory, run, digests = files
    meta = result["meta"]
    part = Solution(
        compiled=_system(compiled, result["index"]),
        values=result.pop("values"),
        parameters=result.pop("parameters"),
        **{key: value for key, value in result.pop("switches").items() if key != "rows"},
        solve_time=result["seconds"],
        stats={
            "samples": result["indices"],
            "failures": [dataclasses.asdict(f) for f in result["failures"]],
            "run": run,
            "inputs": digests[result["offset"]],
        },
        batched=True,
        **meta,
    )
    result["file"] = CHUNK_FILE.format(offset=result["offset"])
    result["solved"] = len(result.pop("indices"))
    result["inputs"] = digests[result["offset"]]
    part.save(directory / result["file"])


def _write_manifest(directory: Path, compiled, results: list, total, seconds, engine, chunk, run: str) -> None:
    failures = _failures(results, total)
    written = [result for result in results if "file" in result]
    solved = _system(compiled, written[0]["index"])  # a reduction, for index 3
    manifest = {
        "format": ENSEMBLE_FORMAT,
        "model": compiled.name,
        "fingerprint": solved.fingerprint(),
        "fingerprints": solved.fingerprints(),
        "declared": declared(solved),
        "run": run,
        "total": total,
        "chunk": chunk,
        "engine": engine,
        "seconds": seconds,
        "status": _status([(r["offset"], r["meta"]["status"]) for r in written], failures, total),
        "failures": [dataclasses.asdict(failure) for failure in failures],
        "files": [
            {key: result[key] for key in ("file", "offset", "size", "solved", "seconds", "inputs")}
            | {"status": result["meta"]["status"], "peak_memory_mb": result.get("peak_memory_mb")}
            for result in written
        ],
    }
    write_json(directory / MANIFEST, manifest)


def _check_manifest(path: Path, manifest: dict) -> None:
    """Every field of a manifest that sizes or names something, checked before anything is read
    or allocated by it: whole numbers in range, chunk names that are the names of their offsets
    (no path), chunks in order inside the ensemble, and samples that add up to its total."""

    def bad(field: str, why: str):
        raise SolutionFileError(f"{path}: field {field!r} {why}: the manifest is damaged or was edited")

    def whole(value, field: str, low: int, high: float = float("inf")) -> int:
        if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
            bad(field, f"is {value!r}, not a whole number from {low} to {high:g}")
        return value

    total = whole(manifest["total"], "total", 1)
    whole(manifest["chunk"], "chunk", 1)
    for key in ("run", "status", "engine", "model", "fingerprint"):
        if not isinstance(manifest[key], str):
            bad(key, "is not a string")
    for key in ("fingerprints", "declared"):
        if not isinstance(manifest[key], dict):
            bad(key, "is not an object")
    if isinstance(manifest["seconds"], bool) or not isinstance(manifest["seconds"], int | float):
        bad("seconds", f"is {manifest['seconds']!r}, not a number")
    if not isinstance(manifest["files"], list) or not isinstance(manifest["failures"], list):
        bad("files" if not isinstance(manifest["files"], list) else "failures", "is not a list")
    end, solved = 0, 0
    for k, entry in enumerate(manifest["files"]):
        if not isinstance(entry, dict) or not {"file", "offset", "size", "solved", "inputs"} <= set(entry):
            bad(f"files[{k}]", "lacks file, offset, size, solved or inputs")
        offset = whole(entry["offset"], f"files[{k}].offset", end, total - 1)
        size = whole(entry["size"], f"files[{k}].size", 1, total - offset)
        solved += whole(entry["solved"], f"files[{k}].solved", 1, size)
        if entry["file"] != CHUNK_FILE.format(offset=offset):
            bad(f"files[{k}].file", f"is {entry['file']!r}, not the name of the chunk at sample {offset}")
        end = offset + size
    seen = set()
    for k, failure in enumerate(manifest["failures"]):
        if not isinstance(failure, dict) or set(failure) != {"index", "error", "message"}:
            bad(f"failures[{k}]", "is not an index, an error and a message")
        if not isinstance(failure["error"], str) or not isinstance(failure["message"], str):
            bad(f"failures[{k}]", "has an error or a message that is not a string")
        seen.add(whole(failure["index"], f"failures[{k}].index", 0, total - 1))
    if len(seen) != len(manifest["failures"]) or solved + len(seen) != total:
        bad("total", f"is {total}, but the chunks hold {solved} solved samples and {len(seen)} distinct failures")
    # every sample lies in one chunk as solved or failed, or outside every chunk as failed
    failed = np.sort(np.fromiter(seen, np.int64, len(seen)))
    inside = 0
    for k, entry in enumerate(manifest["files"]):
        lo, hi = np.searchsorted(failed, [entry["offset"], entry["offset"] + entry["size"]])
        inside += hi - lo
        if entry["solved"] + (hi - lo) != entry["size"]:
            bad(f"files[{k}].solved", f"is {entry['solved']}, but {hi - lo} of the chunk's {entry['size']} failed")
    covered = sum(entry["size"] for entry in manifest["files"])
    if len(seen) - inside != total - covered:
        bad("failures", f"leave {total - covered - (len(seen) - inside)} samples outside every chunk unaccounted for")

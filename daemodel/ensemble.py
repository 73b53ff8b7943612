"""Ensembles: a large batch of initial states and parameter sets, solved chunk by chunk, in this
process or as Ray tasks, with each sample's failure recorded instead of ending the run.

A chunk is one batched call of the method (radau's vectorised Newton over the chunk).  A chunk
that fails is split in halves until the failing samples stand alone; they are recorded by
index in ``stats["failures"]`` and left out of the returned Solution, whose values stay finite.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import numpy as np

from daemodel.errors import (
    InconsistentAlgebraicValueError,
    InconsistentInitialStateError,
    InitialisationError,
    InvalidOptionError,
    SolverError,
)
from daemodel.solution import Solution

ENGINES = ("local", "ray")
# Samples per chunk by default: big enough that radau's per-step Python overhead is shared,
# small enough that a chunk's arrays stay modest (10^4 pendulum samples over 20 steps: ~10 MB).
DEFAULT_CHUNK = 10_000
# Failures of a single sample: what its own states or the method's iteration caused.  Any other
# error (a wrong option, a model error) would fail every sample and ends the ensemble at once.
SAMPLE_FAILURES = (SolverError, InitialisationError, InconsistentInitialStateError, InconsistentAlgebraicValueError)


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
    **options,
) -> Solution:
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
        Samples per task.
    workers : int, optional
        Ray only, when this call starts Ray: the CPUs of the local cluster it starts (default:
        all).  Each task takes one CPU and runs torch on one thread.
    address : str, optional
        Ray only: the cluster to connect to (``"auto"``, ``"ray://host:10001"``); default: the
        running one, else a new local one.
    progress : bool
        One line per finished chunk on stderr.

    Returns
    -------
    Solution
        The samples that were solved, in batch order, batched.  ``stats["samples"]`` holds their
        indices in the ensemble, ``stats["failures"]`` a :class:`Failure` per sample that was
        not (the status says how many), ``stats["chunks"]`` each chunk's seconds and size.
    """
    from daemodel.initial_states import _columns
    from daemodel.model import Model

    if engine not in ENGINES:
        raise InvalidOptionError(f"engine must be one of {', '.join(ENGINES)}; got {engine!r}")
    if isinstance(chunk, bool) or not isinstance(chunk, int | np.integer) or chunk < 1:
        raise InvalidOptionError(f"chunk must be a positive integer (samples per task); got {chunk!r}")
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 1):
        raise InvalidOptionError(f"workers must be a positive integer; got {workers!r}")
    if engine == "local" and (workers is not None or address is not None):
        raise InvalidOptionError("workers and address are Ray's: pass engine='ray' with them")
    compiled = model.compile() if isinstance(model, Model) else model
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
    arrays = {name: np.broadcast_to(array, (total, array.shape[1])) for name, (_, array) in columns.items()}
    pieces = [(start, min(start + chunk, total)) for start in range(0, total, chunk)]
    work = [
        (start, {name: np.ascontiguousarray(array[start:stop]) for name, array in arrays.items()})
        for start, stop in pieces
    ]
    began = time.perf_counter()
    if engine == "local":
        results = []
        for start, batch in work:
            results.append(solve_chunk(compiled, t_span, method, options, start, batch))
            _report(progress, results, len(work), began)
    else:
        results = _run_on_ray(compiled, t_span, method, options, work, workers, address, progress, began)
    return _assemble(results, total, time.perf_counter() - began, engine, chunk)


def solve_chunk(compiled, t_span, method: str, options: dict, offset: int, batch: dict) -> dict:
    """One chunk: its samples' values, or, for a chunk that fails, its halves' (down to single
    samples, whose failures are recorded).  Plain data in and out: it runs in a Ray worker."""
    from daemodel.solver import solve

    size = len(batch["y0"])
    began = time.perf_counter()
    try:
        solution = solve(compiled, t_span, method=method, **batch, **options)
    except SAMPLE_FAILURES as error:
        if size == 1:
            failure = Failure(index=offset, error=type(error).__name__, message=str(error))
            return {"offset": offset, "size": 1, "seconds": time.perf_counter() - began, "failures": [failure]}
        half = size // 2
        parts = [
            solve_chunk(compiled, t_span, method, options, offset + lo, {k: v[lo:hi] for k, v in batch.items()})
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
        "solution": _shell(solution),
    }


def _shell(solution: Solution) -> Solution:
    """The solution without its values: what the assembled Solution takes its settings from."""
    return dataclasses.replace(solution, values={}, parameters=np.zeros((0, 0)))


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
        merged["solution"] = solved[0]["solution"]
    return merged


def _run_on_ray(compiled, t_span, method, options, work, workers, address, progress, began) -> list:
    try:
        import ray
    except ImportError:
        raise InvalidOptionError(
            "engine='ray' needs Ray, which is not installed: pip install 'daemodel[ray]' (or pip install ray)"
        ) from None
    if not ray.is_initialized():
        ray.init(address=address, num_cpus=workers if address is None else None, log_to_driver=False)
    elif address is not None or workers is not None:
        raise InvalidOptionError("Ray is already running in this process: leave out address and workers")
    task = ray.remote(num_cpus=1)(_ray_chunk)
    shared = ray.put(compiled)  # pickled once; workers regenerate its code, without sympy's analysis
    pending = [task.remote(shared, t_span, method, options, start, batch) for start, batch in work]
    results = []
    while pending:
        done, pending = ray.wait(pending, num_returns=1)
        results.append(ray.get(done[0]))
        _report(progress, results, len(work), began)
    return sorted(results, key=lambda result: result["offset"])


def _ray_chunk(compiled, t_span, method, options, offset, batch):
    """A Ray task: one chunk on one thread (Ray gives the task one CPU)."""
    import resource

    import torch

    torch.set_num_threads(1)
    result = solve_chunk(compiled, t_span, method, options, offset, batch)
    result["peak_memory_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return result


def _report(progress: bool, results: list, chunks: int, began: float) -> None:
    if progress:
        import sys

        samples = sum(result["size"] for result in results)
        print(
            f"ensemble: {len(results)}/{chunks} chunks, {samples} samples, {time.perf_counter() - began:.1f} s",
            file=sys.stderr,
            flush=True,
        )


def _assemble(results: list, total: int, seconds: float, engine: str, chunk: int) -> Solution:
    from daemodel.errors import ConvergenceError

    failures = sorted((failure for result in results for failure in result["failures"]), key=lambda f: f.index)
    solved = [result for result in results if "values" in result]
    if not solved:
        first = failures[0]
        raise ConvergenceError(
            f"ensemble: every one of the {total} samples failed; sample {first.index}: {first.error}: {first.message}"
        )
    shell = solved[0]["solution"]
    values = {name: np.concatenate([result["values"][name] for result in solved]) for name in solved[0]["values"]}
    stats = {
        "engine": engine,
        "chunk": chunk,
        "samples": np.concatenate([result["indices"] for result in solved]),
        "failures": failures,
        "chunks": [{"offset": r["offset"], "size": r["size"], "seconds": r["seconds"]} for r in results],
        "peak_memory_mb": [r["peak_memory_mb"] for r in results if "peak_memory_mb" in r],
    }
    status = shell.status
    if failures:
        shown = f"{len(failures)} of {total} samples failed and are left out (stats['failures'], first: sample "
        status = f"{status}; {shown}{failures[0].index}, {failures[0].error})"
    return dataclasses.replace(
        shell,
        values=values,
        parameters=np.concatenate([result["parameters"] for result in solved]),
        solve_time=seconds,
        setup_time=0.0,
        stats=stats,
        batched=True,
        status=status,
    )

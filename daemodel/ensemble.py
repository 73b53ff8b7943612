"""Ensembles: a large batch of initial states and parameter sets, solved chunk by chunk, in this
process or as Ray tasks, with each sample's failure recorded instead of ending the run.

A chunk is one batched call of the method (radau's vectorised Newton over the chunk).  A chunk
that fails is split in halves until the failing samples stand alone; they are recorded by
index in ``stats["failures"]`` and left out of the returned Solution, whose values stay finite.
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from daemodel.engine import check_engine, run_tasks
from daemodel.errors import (
    InconsistentAlgebraicValueError,
    InconsistentInitialStateError,
    InitialisationError,
    InvalidOptionError,
    SolutionFileError,
    SolverError,
)
from daemodel.files import writable_directory
from daemodel.solution import Solution

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
ENSEMBLE_FORMAT = "daemodel-ensemble/1"
MANIFEST = "ensemble.json"
CHUNK_FILE = "chunk-{offset:012d}.npz"
MANIFEST_KEYS = ("model", "fingerprint", "total", "chunk", "engine", "seconds", "status", "failures", "files")


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
    write_to : str or Path, optional
        A directory (created if missing; it must hold no earlier ensemble) to write each
        chunk's values to as the chunk finishes, one :meth:`Solution.save` file per chunk, with
        a manifest ``ensemble.json``, instead of keeping them in memory: for batches whose values
        do not fit.  The call then returns an :class:`EnsembleFiles`, which reads them back a
        chunk at a time.

    Returns
    -------
    Solution
        The samples that were solved, in batch order, batched.  ``stats["samples"]`` holds their
        indices in the ensemble, ``stats["failures"]`` a :class:`Failure` per sample that was
        not (the status says how many), ``stats["chunks"]`` each chunk's seconds and size.
        With ``write_to``, an :class:`EnsembleFiles` instead.
    """
    from daemodel.initial_states import _columns
    from daemodel.model import Model

    check_engine(engine, workers, address, options.get("device", "cpu"))
    if isinstance(chunk, bool) or not isinstance(chunk, int | np.integer) or chunk < 1:
        raise InvalidOptionError(f"chunk must be a positive integer (samples per task); got {chunk!r}")
    chunk = int(chunk)
    if max_failures is not None and (
        isinstance(max_failures, bool) or not isinstance(max_failures, int | np.integer) or max_failures < 0
    ):
        raise InvalidOptionError(f"max_failures must be a non-negative integer or None; got {max_failures!r}")
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
    directory = None if write_to is None else _empty_directory(write_to)  # made once the inputs are known good
    arrays = {name: np.broadcast_to(array, (total, array.shape[1])) for name, (_, array) in columns.items()}
    pieces = [(start, min(start + chunk, total)) for start in range(0, total, chunk)]
    work = [
        (start, {name: np.ascontiguousarray(array[start:stop]) for name, array in arrays.items()})
        for start, stop in pieces
    ]
    began = time.perf_counter()
    finished, failed = [], []

    def report(_, result) -> None:
        finished.append(result["size"])
        failed.extend(result["failures"])
        if result.get("stopped") or (max_failures is not None and len(failed) > max_failures):
            _too_many_failures(failed, max_failures)
        if directory is not None:
            _write_chunk(directory, compiled, result)
        elif engine == "ray" and "values" in result:
            # arrays from Ray are views into its object store, which they would keep pinned
            result["values"] = {name: np.array(value) for name, value in result["values"].items()}
            result["parameters"] = np.array(result["parameters"])
        if progress:
            print(
                f"ensemble: {len(finished)}/{len(work)} chunks, {sum(finished)} samples, "
                f"{time.perf_counter() - began:.1f} s",
                file=sys.stderr,
                flush=True,
            )

    results = run_tasks(
        solve_chunk,
        (compiled, t_span, method, options, max_failures),
        work,
        engine=engine,
        workers=workers,
        address=address,
        label="ensemble",
        on_result=report,
    )
    if directory is not None:
        _write_manifest(directory, compiled, results, total, time.perf_counter() - began, engine, chunk)
        return EnsembleFiles.load(directory, compiled)
    return _assemble(compiled, results, total, time.perf_counter() - began, engine, chunk)


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
    from daemodel.solver import solve

    compiled, t_span, method, options = problem
    size = len(batch["y0"])
    began = time.perf_counter()
    try:
        solution = solve(compiled, t_span, method=method, **batch, **options)
    except SAMPLE_FAILURES as error:
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
        solve_time=seconds,
        stats=stats,
        batched=True,
        compiled=_system(compiled, solved[0]["index"]),
        **{**meta, "status": _status([(r["offset"], r["meta"]["status"]) for r in solved], failures, total)},
    )


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
        self.total = int(manifest["total"])
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
            No manifest there, not a daemodel ensemble, a chunk file missing, or another model.
        """
        from daemodel.solver import as_compiled

        directory = Path(directory).expanduser()
        path = directory / MANIFEST
        if not path.is_file():
            raise SolutionFileError(f"no ensemble at {directory}: {MANIFEST} is missing")
        try:
            manifest = json.loads(path.read_text())
        except (OSError, ValueError) as error:
            raise SolutionFileError(f"{path} is not a daemodel ensemble manifest ({type(error).__name__})") from None
        if not isinstance(manifest, dict) or manifest.get("format") != ENSEMBLE_FORMAT:
            raise SolutionFileError(f"{path} is not a daemodel ensemble manifest (expected format {ENSEMBLE_FORMAT!r})")
        lacking = [key for key in MANIFEST_KEYS if key not in manifest]
        if lacking:
            raise SolutionFileError(f"{path} is damaged: it lacks {', '.join(lacking)}")
        compiled = as_compiled(model, "EnsembleFiles.load()")
        candidates = [compiled] + [compiled.reduced(k) for k in (2, 1) if compiled.index > k]
        if not any(c.fingerprint() == manifest["fingerprint"] for c in candidates):
            raise SolutionFileError(
                f"{directory} holds an ensemble of model '{manifest['model']}' with other equations or names than "
                f"'{compiled.name}'; load it with the model that was solved"
            )
        missing = [entry["file"] for entry in manifest["files"] if not (directory / entry["file"]).is_file()]
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
        part = Solution.load(self.directory / entry["file"], self.compiled)
        part.stats["samples"] = np.asarray(part.stats["samples"], dtype=np.int64)
        part.stats["failures"] = [Failure(**failure) for failure in part.stats["failures"]]
        return part

    def solution(self, samples=None) -> Solution:
        """The values of ``samples`` (indices in the ensemble, in the order given; default: every
        solved sample, which must then fit in memory), as one batched Solution.

        Raises
        ------
        InvalidOptionError
            An index outside the ensemble, or of a sample that failed (named, with its error).
        """
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
                    )
                )
                first = first or {key: getattr(part, key) for key in ("t", "method", "settings", "compiled")}
                del part
        got = np.concatenate([indices for indices, _, _ in kept])
        order = np.argsort(got, kind="stable")
        take = order[np.searchsorted(got, wanted, sorter=order)]
        names = kept[0][1].keys()
        return Solution(
            values={name: np.concatenate([values[name] for _, values, _ in kept])[take] for name in names},
            solve_time=self.seconds,
            stats={"samples": wanted, "engine": self.engine, "chunk": self.chunk},
            parameters=np.concatenate([parameters for _, _, parameters in kept])[take],
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
            return np.array([i for i in range(self.total) if i not in failed], dtype=np.int64)
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


def _empty_directory(path) -> Path:
    directory = writable_directory(path, "write_to")
    earlier = [p.name for p in directory.iterdir() if p.name == MANIFEST or p.name.startswith("chunk-")]
    if earlier:
        raise InvalidOptionError(
            f"write_to {directory} holds an earlier ensemble ({sorted(earlier)[0]}, ...); give an empty directory "
            "or remove its files"
        )
    return directory


def _write_chunk(directory: Path, compiled, result: dict) -> None:
    """Write a finished chunk's values and drop them from ``result``, which keeps its bookkeeping."""
    if "values" not in result:
        return
    meta = result["meta"]
    part = Solution(
        compiled=_system(compiled, result["index"]),
        values=result.pop("values"),
        parameters=result.pop("parameters"),
        solve_time=result["seconds"],
        stats={"samples": result["indices"], "failures": [dataclasses.asdict(f) for f in result["failures"]]},
        batched=True,
        **meta,
    )
    result["file"] = CHUNK_FILE.format(offset=result["offset"])
    result["solved"] = len(result.pop("indices"))
    part.save(directory / result["file"])


def _write_manifest(directory: Path, compiled, results: list, total: int, seconds: float, engine, chunk) -> None:
    failures = _failures(results, total)
    written = [result for result in results if "file" in result]
    manifest = {
        "format": ENSEMBLE_FORMAT,
        "model": compiled.name,
        "fingerprint": _system(compiled, written[0]["index"]).fingerprint(),  # a reduction, for index 3
        "total": total,
        "chunk": chunk,
        "engine": engine,
        "seconds": seconds,
        "status": _status([(r["offset"], r["meta"]["status"]) for r in written], failures, total),
        "failures": [dataclasses.asdict(failure) for failure in failures],
        "files": [
            {key: result[key] for key in ("file", "offset", "size", "solved", "seconds")}
            | {"status": result["meta"]["status"], "peak_memory_mb": result.get("peak_memory_mb")}
            for result in written
        ],
    }
    (directory / MANIFEST).write_text(json.dumps(manifest, indent=1))

"""An ensemble on disk, as ``ensemble(..., write_to=...)`` writes it: the directory's layout (a
manifest and one :meth:`Solution.save` file per chunk with values), the run's fingerprint that
resumes it, the manifest's checks, and :class:`EnsembleFiles`, which reads it back a chunk at a
time.  Files are written and read through :mod:`daemodel.files` (atomic writes, names and paths
checked, sizes checked before allocation)."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import re
from pathlib import Path

import numpy as np

from daemodel.errors import InvalidOptionError, SolutionFileError
from daemodel.files import (
    check_memory,
    is_plain_file,
    open_inside,
    read_arrays,
    read_json,
    readable_path,
    write_json,
)
from daemodel.solution import Solution
from daemodel.solution_files import SOLUTION_ARRAYS, declared, matching_system, read
from daemodel.solving.ensemble_results import (
    Failure,
    all_failures,
    common_times,
    ensemble_status,
    joined_switches,
    solved_system,
    switch_rows,
)

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
    "engine",  # the executor, "local" or "ray": this format's name for it (read as EnsembleFiles.executor)
    "seconds",
    "status",
    "failures",
    "files",
)


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
    status, executor, chunk, seconds
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
        self.status, self.executor = manifest["status"], manifest["engine"]
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
                kept[-1] += (part.t,)
                first = first or {key: getattr(part, key) for key in ("method", "settings", "compiled")}
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
        t, onto = common_times([times for *_, times in kept])  # (chunks whose samples end at terminal events)
        return Solution(
            t=t,
            values={
                name: np.concatenate([at(values[name]) for (_, values, *_), at in zip(kept, onto, strict=True)])[take]
                for name in names
            },
            solve_time=self.seconds,
            stats={"samples": wanted, "executor": self.executor, "chunk": self.chunk},
            parameters=np.concatenate([parameters for _, _, parameters, *_ in kept])[take],
            **switch_rows(joined_switches([switches for _, _, _, switches, _ in kept]), take),
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


def run_fingerprint(compiled, t_span, method: str, options: dict, chunk: int, total: int, digests: dict) -> str:
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


def inputs_digest(batch: dict) -> str:
    """A hash of one chunk's inputs (y0, z0, parameters), by name."""
    digest = hashlib.sha256()
    for name in sorted(batch):
        digest.update(name.encode() + np.ascontiguousarray(batch[name], dtype=np.float64).tobytes())
    return digest.hexdigest()


def _read_chunk(directory: Path, name: str, compiled) -> Solution:
    """A chunk file (its name checked, read without following a link) as a Solution."""
    with open_inside(directory, name, "chunk file", SolutionFileError) as handle:
        part = read(handle, directory / name, compiled, Solution)
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


def resume(directory: Path, compiled, run: str, digests: dict, sizes: dict):
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


def write_chunk(files: tuple, compiled, result: dict) -> None:
    """Write a finished chunk's values and drop them from ``result``, which keeps its bookkeeping."""
    if "values" not in result:
        return
    directory, run, digests = files
    meta = result["meta"]
    part = Solution(
        compiled=solved_system(compiled, result["index"]),
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


def write_manifest(directory: Path, compiled, results: list, total, seconds, executor, chunk, run: str) -> None:
    """The manifest of a finished run (every chunk's result in ``results``, written or failed),
    written last: a directory with a manifest is a finished ensemble."""
    failures = all_failures(results, total)
    written = [result for result in results if "file" in result]
    solved = solved_system(compiled, written[0]["index"])  # a reduction, for index 3
    manifest = {
        "format": ENSEMBLE_FORMAT,
        "model": compiled.name,
        "fingerprint": solved.fingerprint(),
        "fingerprints": solved.fingerprints(),
        "declared": declared(solved),
        "run": run,
        "total": total,
        "chunk": chunk,
        "engine": executor,
        "seconds": seconds,
        "status": ensemble_status([(r["offset"], r["meta"]["status"]) for r in written], failures, total),
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

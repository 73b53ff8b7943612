"""A benchmark's output folder: one JSON file per run in ``runs/``, the computed end values in
``references/``; written atomically inside the folder (:mod:`daemodel.files`), read back after
checking each file's size and every field (JSON, never pickle).

A run file holds one record of :func:`daemodel.comparing.bench.bench`::

    problem, method, settings, short : str      index : int
    status : "success" | "flagged" | "failed" | "skipped"
    scd : float or null (significant correct digits at the end), scd_component : str or null
    setup_time, solve_time, wall_time : float or null (seconds; a failed run's solve_time: until it failed)
    error_class, error : str or null (a failed run's exception)
    flag : str or null (a flagged run's status), reason : str or null (why a setting was skipped)
    messages : list of str (the warnings of the solve), stats : dict name -> number
"""

from __future__ import annotations

import math
import os
from pathlib import Path

from daemodel.errors import BenchError
from daemodel.files import file_name, read_json, write_json

RUNS, REFERENCES = "runs", "references"
FORMAT, REFERENCE_FORMAT, VERSION = "daemodel-bench-run", "daemodel-bench-reference", 1
# Largest run file read back: a record is a few kB (its messages and stats); anything larger is not one.
RUN_FILE_BYTES = 1 << 20
STATUSES = ("success", "flagged", "failed", "skipped")
_TEXT = ("problem", "method", "settings", "short", "status")
_NUMBERS = ("scd", "setup_time", "solve_time", "wall_time")
_OPTIONAL_TEXT = ("scd_component", "error_class", "error", "flag", "reason")


def run_key(problem: str, method: str, index: int) -> str:
    """A run's file name stem in ``out/runs``: problem, method and the setting's place in its sweep."""
    return f"{problem}.{method}.{index:02d}"


def run_path(out: Path, key: str) -> Path:
    """The file of the run ``key`` (problem.method.index) in ``out/runs``."""
    return Path(out) / RUNS / file_name(f"{key}.json", "run file", BenchError)


def write_run(out: Path, record: dict) -> dict:
    """``record`` written atomically to its file in ``out/runs`` (created); returns it."""
    key = run_key(record["problem"], record["method"], record["index"])
    path = run_path(out, key)
    path.parent.mkdir(exist_ok=True)
    write_json(path, {"format": FORMAT, "version": VERSION, **record})
    return record


def load_runs(out: Path, settings) -> dict:
    """The stored records of ``settings`` (key -> record): those whose file exists and holds the same
    problem, method and settings (a file for other settings is left to be solved again and replaced).

    Raises
    ------
    BenchError
        A run file that is too large, not JSON or not a run record: the message names the file and the field.
    """
    done = {}
    for setting in settings:
        key = run_key(setting.problem.name, setting.method, setting.index)
        path = run_path(out, key)
        if not os.path.lexists(path):
            continue
        record = read_run(path)
        if (record["problem"], record["method"], record["index"], record["settings"]) == (
            setting.problem.name,
            setting.method,
            setting.index,
            setting.settings,
        ):
            done[key] = record
    return done


def read_run(path: Path) -> dict:
    """One run file's record, every field checked (see the module docs); else a :class:`BenchError`
    naming the file and the field."""
    size = os.lstat(path).st_size
    if size > RUN_FILE_BYTES:
        raise BenchError(f"{path} is {size:,} bytes, more than a bench run file holds ({RUN_FILE_BYTES:,}); remove it")
    try:
        value = read_json(path, BenchError, "a daemodel bench run file", follow=False)
    except BenchError as error:  # (cut short, or not JSON: the fix is the same as for a wrong field)
        raise BenchError(f"{error}. Remove the file to run it again") from None
    if not isinstance(value, dict):
        raise BenchError(
            f"{path} is not a daemodel bench run file: it holds a {type(value).__name__}, not an object. Remove the "
            "file to run it again"
        )

    def bad(field: str, expected: str):
        shown = repr(value.get(field))[:60]
        return BenchError(f"{path}: field {field!r} must be {expected}; found {shown}. Remove the file to run it again")

    if value.get("format") != FORMAT:
        raise bad("format", repr(FORMAT))
    if value.get("version") != VERSION:
        raise bad("version", str(VERSION))
    for field in _TEXT:
        if not isinstance(value.get(field), str):
            raise bad(field, "a string")
    if value["status"] not in STATUSES:
        raise bad("status", " or ".join(STATUSES))
    index = value.get("index")
    if isinstance(index, bool) or not isinstance(index, int) or index < 0:
        raise bad("index", "a non-negative integer")
    for field in _NUMBERS:
        number = value.get(field)
        if number is not None and (isinstance(number, bool) or not isinstance(number, int | float)):
            raise bad(field, "a number or null")
    for field in _OPTIONAL_TEXT:
        if value.get(field) is not None and not isinstance(value[field], str):
            raise bad(field, "a string or null")
    messages = value.get("messages")
    if not isinstance(messages, list) or not all(isinstance(m, str) for m in messages):
        raise bad("messages", "a list of strings")
    stats = value.get("stats")
    if not isinstance(stats, dict) or not all(
        isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) for v in stats.values()
    ):
        raise bad("stats", "an object of numbers")
    return {k: v for k, v in value.items() if k not in ("format", "version")}


def reference_values(out: Path, problem) -> dict:
    """A problem's values at its end from a tight scipy solve (``method="reference"``, rtol = atol =
    1e-12), kept in ``out/references`` and read from there while the target and interval match."""
    from daemodel.compiling.compiler import as_compiled
    from daemodel.solving.solver import solve

    path = Path(out) / REFERENCES / file_name(f"{problem.name}.json", "reference file", BenchError)
    if os.path.lexists(path):
        value = read_json(path, BenchError, "a daemodel bench reference file", follow=False)
        if not isinstance(value, dict) or value.get("format") != REFERENCE_FORMAT:
            raise BenchError(
                f"{path}: field 'format' must be {REFERENCE_FORMAT!r}; remove the file to compute it again"
            )
        values = value.get("values")
        if not isinstance(values, dict) or not all(
            isinstance(v, int | float) and not isinstance(v, bool) for v in values.values()
        ):
            raise BenchError(
                f"{path}: field 'values' must be an object of numbers; remove the file to compute it again"
            )
        if value.get("target") == problem.target and value.get("t_span") == list(problem.t_span):
            return values
    t0, t1 = problem.t_span
    solution = solve(as_compiled(problem.model(), "bench"), problem.t_span, method="reference", t_eval=[t0, t1])
    values = {name: float(solution[name][-1]) for name in solution.names}
    path.parent.mkdir(exist_ok=True)
    write_json(
        path,
        {"format": REFERENCE_FORMAT, "target": problem.target, "t_span": list(problem.t_span), "values": values},
    )
    return values

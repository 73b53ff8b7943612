"""What an ensemble's chunks give back, and how it is joined: the samples that failed, the rows of
events and breakpoints of consecutive chunks, the status, one batched Solution.

A chunk's result is plain data (it comes back from a Ray worker): ``"offset"``, ``"size"``,
``"seconds"``, ``"failures"`` (:class:`Failure` each) and, where some sample was solved,
``"indices"``, ``"values"`` (name -> (rows, times)), ``"parameters"``, ``"switches"``, ``"meta"``
(the Solution's t, method, settings, status) and ``"index"`` (of the system the method solved).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from daemodel.errors import ConvergenceError
from daemodel.solution import Solution


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


def common_times(times: list) -> tuple:
    """``(t, takes)``: the output times that parts of an ensemble (``times``: each part's, increasing) can
    share, and for each part a function ``values (rows, its times) -> (rows, len(t))``.  Parts differ where
    a terminal event ended their samples (each part's times are t_eval and its own samples' ends): a time is
    kept where every part has a value of its own there or has ended before it (NaN: its samples ended), so
    that no value moves to another time; a sample's end that another part, still running, has no value at
    is left out (its values after the event are in the event's record)."""
    if all(len(t) == len(times[0]) and np.array_equal(t, times[0]) for t in times):
        return times[0], [lambda values: values] * len(times)
    union = np.unique(np.concatenate(times))
    t = union[np.all([np.isin(union, own) | (union > own[-1]) for own in times], axis=0)]

    def take(own):
        inside = t <= own[-1]
        at = np.searchsorted(own, t[inside])

        def taken(values):
            out = np.full((len(values), len(t)), np.nan)
            out[:, inside] = np.asarray(values, dtype=float)[:, at]
            return out

        return taken

    return t, [take(np.asarray(own)) for own in times]


def merged(parts: list, offset: int, size: int, seconds: float) -> dict:
    """The results of consecutive parts of one chunk (its halves, split around a failing sample)
    as the result of the chunk of ``size`` samples from ``offset``."""
    solved = [part for part in parts if "values" in part]
    merged = {
        "offset": offset,
        "size": size,
        "seconds": seconds,
        "failures": [failure for part in parts for failure in part["failures"]],
    }
    if solved:
        t, takes = common_times([part["meta"]["t"] for part in solved])
        merged["indices"] = np.concatenate([part["indices"] for part in solved])
        merged["values"] = {
            name: np.concatenate([take(part["values"][name]) for part, take in zip(solved, takes, strict=True)])
            for name in solved[0]["values"]
        }
        merged["parameters"] = np.concatenate([part["parameters"] for part in solved])
        merged["switches"] = joined_switches([part["switches"] for part in solved]) | {"rows": len(merged["indices"])}
        merged["meta"], merged["index"] = solved[0]["meta"] | {"t": t}, solved[0]["index"]
    return merged


def assemble(compiled, results: list, total: int, seconds: float, executor: str, chunk: int) -> Solution:
    """Every chunk's result as one batched Solution of the solved samples, in batch order (the
    statuses, failures and chunk records in its stats); a ConvergenceError when none was solved."""
    failures = all_failures(results, total)
    solved = [result for result in results if "values" in result]
    t, takes = common_times([result["meta"]["t"] for result in solved])
    values = {
        name: np.concatenate([take(result["values"][name]) for result, take in zip(solved, takes, strict=True)])
        for name in solved[0]["values"]
    }
    stats = {
        "executor": executor,
        "chunk": chunk,
        "samples": np.concatenate([result["indices"] for result in solved]),
        "failures": failures,
        "chunks": [
            {key: r[key] for key in ("offset", "size", "seconds")} | {"status": r["meta"]["status"]} for r in solved
        ],
        "peak_memory_mb": [r["peak_memory_mb"] for r in results if "peak_memory_mb" in r],
    }
    meta = solved[0]["meta"] | {"t": t}
    return Solution(
        values=values,
        parameters=np.concatenate([result["parameters"] for result in solved]),
        **joined_switches([result["switches"] for result in solved]),
        solve_time=seconds,
        stats=stats,
        batched=True,
        compiled=solved_system(compiled, solved[0]["index"]),
        **{**meta, "status": ensemble_status([(r["offset"], r["meta"]["status"]) for r in solved], failures, total)},
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


def solved_system(compiled, index: int):
    """The system a method solved: the model, or its reduction to ``index``."""
    return compiled if compiled.index <= index else compiled.reduced(index)


def all_failures(results: list, total: int) -> list:
    """Every failure by index; a ConvergenceError naming the first when no sample was solved."""
    failures = sorted((failure for result in results for failure in result["failures"]), key=lambda f: f.index)
    if len(failures) == total:
        first = failures[0]
        raise ConvergenceError(
            f"ensemble: every one of the {total} samples failed; sample {first.index}: {first.error}: {first.message}"
        )
    return failures


def ensemble_status(statuses: list, failures: list, total: int) -> str:
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

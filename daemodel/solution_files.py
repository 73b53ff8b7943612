"""The solution file: what :meth:`Solution.save` writes (numpy's ``.npz``, no pickled objects) and
:meth:`Solution.load` reads back, every field checked and sizes checked before anything is allocated,
and the model's fingerprints that a loaded file must match."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from daemodel.dense import dense_from_stored, stored_dense
from daemodel.errors import SolutionFileError
from daemodel.files import (
    STORED_KINDS,
    STORED_NAME,
    atomic_write,
    memory_limit,
    parse_json,
    read_arrays,
    restored,
    stored,
    writable_file,
)
from daemodel.messages import listed, quoted

# What Solution.save writes and Solution.load reads.
SOLUTION_FORMAT = "daemodel-solution/2"

OLDER_SOLUTION_FORMATS = ("daemodel-solution/1",)

# Its arrays (dtype kinds, axes): times (T,), values (B, T, variables), parameters (B, k), and
# the JSON of everything else, whose arrays (stats, events, breakpoints, the dense output) are the
# members it lists in "arrays" (:func:`daemodel.files.stored`); and the fields of that JSON with their types.
SOLUTION_ARRAYS = {"t": ("f", 1), "values": ("f", 3), "parameters": ("f", 2), "meta": ("U", 0)}

SOLUTION_META = {
    "format": str,
    "model": str,
    "fingerprint": str,
    "fingerprints": dict,
    "declared": dict,
    "names": list,
    "method": str,
    "settings": dict,
    "solve_time": (int, float),
    "setup_time": (int, float),
    "stats": dict,
    "status": str,
    "batched": bool,
    "breakpoints": dict,
    "events": dict,
    "arrays": dict,
}


def declared(compiled) -> dict:
    """What a solution's fingerprints cover, in words, for a loader's message: the events and the
    parameter values."""
    return {
        "events": [event.describe(compiled.state_names) for event in compiled.events],
        "parameter values": {
            name: float(v) for name, v in zip(compiled.parameter_names, compiled.parameter_values, strict=True)
        },
    }


def matching_system(compiled, meta: dict, path: Path, what: str = "a solution", solved=None):
    """The system among ``compiled`` and its reductions whose fingerprints are those ``meta`` stored
    (``"fingerprint"``, ``"fingerprints"``, ``"declared"``, ``"model"``), else a :class:`SolutionFileError`
    saying that ``path`` holds ``what`` of another model and what differs: the equations, or the
    events (both listed), or the parameter values (each changed one named).  ``solved`` (B, k): the
    parameter values the stored result was solved at, which the model's may equal instead of the
    declared ones it was compiled with (a solve with ``parameters=``).  A solve locates each switch on a
    variable as an event of its own (:func:`~daemodel.compiling.switches.with_state_events`), which its
    result lists: the model with those events is a candidate too."""
    from daemodel.compiling.switches import with_state_events

    located = with_state_events(compiled)
    systems = [compiled] if located is compiled else [compiled, located]
    candidates = [c for system in systems for c in [system] + [system.reduced(k) for k in (2, 1) if system.index > k]]
    parts = meta["fingerprints"]
    for candidate in candidates:
        if candidate.fingerprint() == meta["fingerprint"] and candidate.fingerprints() == parts:
            return candidate
    values = np.asarray(compiled.parameter_values, dtype=float)
    if solved is not None and np.shape(solved)[1:] == values.shape and len(solved) and np.all(solved == values):
        for candidate in candidates:
            mine = candidate.fingerprints()
            if all(mine[field] == parts.get(field) for field in mine if field != "parameter values"):
                return candidate
    differing = min(
        ([field for field, value in c.fingerprints().items() if parts.get(field) != value] for c in candidates),
        key=len,
    )
    if not differing or "equations" in differing:
        raise SolutionFileError(
            f"{path} holds {what} of model {meta['model']!r} with other equations or names than '{compiled.name}'; "
            "load it with the model that was solved"
        )
    mine, theirs = declared(compiled), meta["declared"] if isinstance(meta["declared"], dict) else {}
    details = []
    if "events" in differing:
        details.append(f"its events {theirs.get('events', '?')}, the model's {mine['events']}")
    if "parameter values" in differing:
        saved, now = theirs.get("parameter values") or {}, mine["parameter values"]
        changed = [f"{n} = {saved.get(n, '?')!r}, the model's {v!r}" for n, v in now.items() if saved.get(n) != v]
        details.append("its " + ("; ".join(changed) if changed else f"parameter values {saved}"))
    raise SolutionFileError(
        f"{path} holds {what} of model {meta['model']!r} whose {' and '.join(differing)} differ from those of "
        f"'{compiled.name}' ({'; '.join(details)}): load it with the model that was solved"
    )


def _switch_record(record, B: int, names: list, path: Path, field: str) -> dict:
    """A breakpoint or event record read back, checked: ``"t"`` and ``"moved"`` (B, K), ``"before"`` and
    ``"after"`` each variable's (B, K)."""

    def table(value, where: str, K: int | None) -> np.ndarray:
        if not isinstance(value, np.ndarray) or value.dtype.kind != "f" or value.ndim != 2 or len(value) != B:
            raise SolutionFileError(f"{path}: field '{where}' is not a float array of {B} rows: it is damaged")
        if K is not None and value.shape[1] != K:
            raise SolutionFileError(f"{path}: field '{where}' has {value.shape[1]} columns, not {K}: it is damaged")
        return value

    if not isinstance(record, dict) or set(record) != {"t", "moved", "before", "after"}:
        raise SolutionFileError(
            f"{path}: field '{field}' is not times, moves and values before and after: it is damaged"
        )
    t = table(record["t"], f"{field}.t", None)
    out = {"t": t, "moved": table(record["moved"], f"{field}.moved", t.shape[1])}
    for side in ("before", "after"):
        if not isinstance(record[side], dict) or sorted(record[side]) != sorted(names):
            raise SolutionFileError(f"{path}: field '{field}.{side}' does not hold the variables {listed(names)}")
        out[side] = {name: table(record[side][name], f"{field}.{side}.{name}", t.shape[1]) for name in names}
    return out


# The switch kinds whose events a solve names "<kind> in <equation>" (daemodel.solving.events).
_SWITCH_KINDS = ("Piecewise", "Heaviside", "sign", "Abs", "Max", "Min", "floor", "ceiling")

# A stored dense output must give the stored values at the output times to this, relative to their size.
DENSE_CHECK_RTOL = 1e-4


def _check_instants(model, t: np.ndarray, breakpoints: dict, events: dict, path: Path) -> None:
    """Refuse a file whose events are not the model's, or whose instants are not times of its span in order
    (NaN only as the padding after a sample's last)."""
    declared = [e.name for e in model.events]
    missing = [name for name in declared if name not in events]
    if model.events and missing:
        raise SolutionFileError(f"{path}: field 'events' lacks the model's event(s) {missing}: it is damaged")
    foreign = [n for n in events if n not in declared and not any(n.startswith(f"{k} in ") for k in _SWITCH_KINDS)]
    if foreign:
        raise SolutionFileError(f"{path}: field 'events' holds {foreign}, which the model does not declare")
    tol = 1e-9 * max(1.0, float(t[-1] - t[0]))
    records = ([("breakpoints", breakpoints)] if breakpoints else []) + [(f"events.{n}", r) for n, r in events.items()]
    for where, record in records:
        for row in record["t"]:
            known = ~np.isnan(row)
            seen = row[known]
            if (
                np.isinf(row).any()
                or (known[1:] & ~known[:-1]).any()
                or (np.diff(seen) < 0).any()
                or (len(seen) and (seen[0] < t[0] - tol or seen[-1] > t[-1] + tol))
            ):
                raise SolutionFileError(
                    f"{path}: field '{where}.t' is not a sequence of times in [{t[0]:g}, {t[-1]:g}] in order: it is "
                    "damaged"
                )


def _check_dense(dense, t: np.ndarray, values: np.ndarray, path: Path, n: int) -> None:
    """Refuse a stored dense output that does not give the stored values at the output times (the ``n``
    states' alone where the algebraic variables are solved from them: ``resolves_algebraic``)."""
    try:
        found = np.asarray(dense(t), dtype=float)
        if dense.resolves_algebraic:
            found, values = found[..., :n], values[..., :n]
    except (ValueError, IndexError, TypeError, FloatingPointError) as error:
        raise SolutionFileError(f"{path}: field 'dense' cannot be evaluated at the output times: {error}") from None
    both = np.isfinite(values)
    if found.shape != values.shape or not (np.isfinite(found) == both).all():
        raise SolutionFileError(f"{path}: field 'dense' does not cover the output times: it is damaged")
    scale = 1.0 + np.abs(values[both]).max(initial=0.0)
    if (np.abs(found[both] - values[both]) > DENSE_CHECK_RTOL * scale).any():
        raise SolutionFileError(f"{path}: field 'dense' does not give the stored values at the output times: it is "
                                "damaged")  # fmt: skip


def write(sol, path) -> Path:
    """Write ``sol`` to ``path`` (see :meth:`Solution.save`)."""
    path = writable_file(path, "path")
    c = sol.compiled
    names = [*c.state_names, *c.algebraic_names]
    arrays: dict = {}
    meta = {
        "format": SOLUTION_FORMAT,
        "model": c.name,
        "fingerprint": c.fingerprint(),
        "fingerprints": c.fingerprints(),
        "declared": declared(c),
        "names": names,
        "method": sol.method,
        "settings": stored(sol.settings, arrays),
        "solve_time": sol.solve_time,
        "setup_time": sol.setup_time,
        "stats": stored(sol.stats, arrays),
        "status": sol.status,
        "batched": sol.batched,
        "breakpoints": stored(sol.breakpoints, arrays),
        "events": stored(sol.events, arrays),
        "dense": stored(stored_dense(sol.dense), arrays),
        "arrays": {name: array.ndim for name, array in arrays.items()},
    }
    arrays |= {
        "t": sol.t,
        "values": np.stack([sol.values[n] for n in names], axis=-1),
        "parameters": sol.parameters,
        "meta": np.array(json.dumps(meta, allow_nan=False)),
    }
    return atomic_write(path, lambda handle: np.savez(handle, **arrays))


def read(handle, path: Path, model, cls):
    """The solution in the open file ``handle`` (``path`` for messages), every field checked."""
    from daemodel.compiling.compiler import as_compiled

    limit = memory_limit()
    first = read_arrays(
        handle, path, {"meta": ("U", 0)}, SolutionFileError, limit, "daemodel solution file", others=True
    )
    meta = parse_json(str(first["meta"]), path, SolutionFileError, "a daemodel solution file")
    if isinstance(meta, dict) and meta.get("format") in OLDER_SOLUTION_FORMATS:
        raise SolutionFileError(
            f"{path} is a daemodel solution file of format {meta['format']!r}, which kept no events, breakpoints "
            f"or dense output; this version reads {SOLUTION_FORMAT!r}: solve and save it again"
        )
    if not isinstance(meta, dict) or meta.get("format") != SOLUTION_FORMAT:
        raise SolutionFileError(f"{path} is not a daemodel solution file (expected format {SOLUTION_FORMAT!r})")
    for key, kind in SOLUTION_META.items():
        if key not in meta:
            raise SolutionFileError(f"{path} lacks the field {key!r}: it is damaged")
        if not isinstance(meta[key], kind) or (kind is not bool and isinstance(meta[key], bool)):
            expected = "a number" if isinstance(kind, tuple) else f"a {kind.__name__}"
            raise SolutionFileError(f"{path}: field {key!r} is a {type(meta[key]).__name__}, not {expected}")
    if "dense" not in meta or not isinstance(meta["dense"], dict | None):
        raise SolutionFileError(f"{path}: field 'dense' is missing or not an object: it is damaged")
    declared = meta["arrays"]
    bad = [
        k for k, v in declared.items() if not STORED_NAME.fullmatch(k) or isinstance(v, bool) or v not in range(1, 33)
    ]
    if bad:
        raise SolutionFileError(f"{path}: field 'arrays' lists {bad[0]!r}, which is no array daemodel writes")
    expected = SOLUTION_ARRAYS | {name: (STORED_KINDS, ndim) for name, ndim in declared.items()}
    arrays = read_arrays(handle, path, expected, SolutionFileError, limit, "daemodel solution file")
    compiled = as_compiled(model, "Solution.load()")
    match = matching_system(compiled, meta, path, solved=arrays["parameters"])
    names = [*match.state_names, *match.algebraic_names]
    if meta["names"] != names:
        raise SolutionFileError(
            f"{path}: field 'names' is {quoted(meta['names'], 200)}; the model's variables are {listed(names)}"
        )
    t, values, parameters = arrays["t"], arrays["values"], arrays["parameters"]
    if not len(t) or not np.isfinite(t).all() or (np.diff(t) <= 0).any():
        raise SolutionFileError(f"{path}: field 't' is not a non-empty, finite, increasing sequence of times")
    B = len(parameters)
    if parameters.shape[1:] != (len(match.parameter_names),) or not np.isfinite(parameters).all():
        raise SolutionFileError(
            f"{path}: field 'parameters' has shape {parameters.shape} or non-finite values; the model has "
            f"{len(match.parameter_names)} parameters"
        )
    if values.shape != (B, len(t), len(names)) or (not meta["batched"] and B != 1):
        raise SolutionFileError(
            f"{path}: field 'values' has shape {values.shape}; {B} sample{'s' * (B != 1)}, {len(t)} times and "
            f"{len(names)} variables make {(B, len(t), len(names))}"
            + ("" if meta["batched"] or B == 1 else " (and an unbatched solution has one sample)")
        )

    def field(key):
        return restored(meta[key], arrays, path, SolutionFileError, key)

    breakpoints = field("breakpoints")
    if breakpoints:
        breakpoints = _switch_record(breakpoints, B, names, path, "breakpoints")
    events = {
        name: _switch_record(record, B, names, path, f"events.{name}") for name, record in field("events").items()
    }
    _check_instants(match, t, breakpoints, events, path)
    dense = None
    if meta["dense"] is not None:
        try:
            dense = dense_from_stored(field("dense"), B, len(names))
        except ValueError as error:
            raise SolutionFileError(f"{path}: field 'dense' is damaged: {error}") from None
        _check_dense(dense, t, values, path, len(match.states))
    return cls(
        t=t,
        values={name: np.ascontiguousarray(values[..., i]) for i, name in enumerate(names)},
        method=meta["method"],
        settings=field("settings"),
        solve_time=meta["solve_time"],
        setup_time=meta["setup_time"],
        stats=field("stats"),
        compiled=match,
        parameters=parameters,
        batched=meta["batched"],
        status=meta["status"],
        breakpoints=breakpoints,
        events=events,
        dense=dense,
    )

"""A solution's counters (``Solution.stats``): figures per step, segment or sample as numpy arrays,
printed as a summary."""

from __future__ import annotations

import numpy as np

# Items of a list that a printed stats dict shows before it says how many more there are.
SHOWN_ITEMS = 6

# Values that :func:`as_arrays` returns as they are (a solution's stats are mostly these).
PLAIN = frozenset({int, float, str, bool, type(None)})

# Entries a printed stats dict shows, one a line, before it says how many more there are (with the
# braces: at most 40 lines whatever the batch).
SHOWN_ENTRIES = 36


class Stats(dict):
    """A solution's counters (``Solution.stats``): a plain dict whose figures per step, segment or
    sample are numpy arrays (lists of numbers, nested ones included, become arrays; ragged ones are
    padded with NaN), and whose ``repr`` is a summary, one entry a line and at most 40 lines, so that
    printing the stats of a batch of 10^3 samples is a screen, not megabytes: an array shows its
    shape, dtype, range and median, a long list its first items and its length."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        for key, value in self.items():
            if type(value) not in PLAIN:  # (most entries: as_arrays keeps them as they are)
                self[key] = as_arrays(value)

    def extended(self, **entries) -> Stats:
        """A copy with ``entries`` added (converted as the constructor converts), its own entries taken as
        they are (converted already: the solve's clock, which adds two entries to every solution, paid
        for a second pass over all of them)."""
        out = Stats()
        dict.update(out, self)
        for key, value in entries.items():
            out[key] = as_arrays(value)
        return out

    def __repr__(self) -> str:
        items = [f"{key!r}: {_summary(value)}" for key, value in self.items()]
        if len(items) > SHOWN_ENTRIES:
            items = [*items[: SHOWN_ENTRIES - 1], f"... ({len(items) - SHOWN_ENTRIES + 1} more entries)"]
        if sum(len(item) + 2 for item in items) <= 100:
            return "{" + ", ".join(items) + "}"
        return "{" + ",\n ".join(items) + "}"

    __str__ = __repr__

    def to_dict(self) -> dict:
        """The stats as plain Python values for ``json.dumps`` (strict JSON included): arrays as nested
        lists, numpy scalars as Python numbers, NaN and infinities as None."""
        return {str(key): plain(value) for key, value in self.items()}


def plain(value):
    """``value`` with numpy arrays and scalars as Python lists and numbers, non-finite floats as None."""
    if isinstance(value, np.ndarray | np.generic):
        value = value.tolist()
    if isinstance(value, dict):
        return {str(key): plain(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [plain(item) for item in value]
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value


def as_arrays(value):
    """``value`` with its lists of numbers (nested ones too, ragged ones padded with NaN) as numpy
    arrays, inside dicts too; other values as they are."""
    if isinstance(value, dict):
        return {key: as_arrays(item) for key, item in value.items()}
    if not isinstance(value, list | tuple) or not value:
        return value
    items = [as_arrays(item) for item in value]
    if all(_is_number(item) for item in items):
        return np.asarray(items)
    if all(isinstance(item, np.ndarray) and item.dtype.kind in "fiu" for item in items):
        if len({item.shape for item in items}) == 1:
            return np.stack(items)
        if all(item.ndim == 1 for item in items):
            return np.stack(padded_with_nan(items))
    return type(value)(items) if isinstance(value, list) else tuple(items)


def padded_with_nan(arrays: list) -> list:
    """Numeric arrays of one number of axes, as floats, their last axis padded with NaN to the widest."""
    width = max(a.shape[-1] for a in arrays)
    pad = [(0, 0)] * (arrays[0].ndim - 1)
    return [np.pad(a.astype(float), [*pad, (0, width - a.shape[-1])], constant_values=np.nan) for a in arrays]


def _is_number(value) -> bool:
    return isinstance(value, int | float | np.integer | np.floating) and not isinstance(value, bool | np.bool_)


def _summary(value) -> str:
    if isinstance(value, np.ndarray):
        if value.size <= SHOWN_ITEMS:
            return repr(value.tolist())
        if value.dtype.kind in "fiu":
            finite = value[np.isfinite(value)] if value.dtype.kind == "f" else value
            span = (
                f" from {finite.min():.4g} to {finite.max():.4g}, median {np.median(finite):.4g}" if finite.size else ""
            )
            return f"<array {value.shape} {value.dtype}{span}>"
        if value.dtype.kind == "b":
            return f"<array {value.shape} bool, {int(value.sum())} true>"
        return f"<array {value.shape} {value.dtype}>"
    if isinstance(value, np.generic):
        return repr(value.item())  # (3, not np.int64(3))
    if isinstance(value, dict):
        text = "{" + ", ".join(f"{k!r}: {_summary(v)}" for k, v in value.items()) + "}"
        return text if len(text) <= 300 else text[:290] + f"... ({len(value)} entries)}}"
    if isinstance(value, list | tuple) and len(value) > SHOWN_ITEMS:
        shown = ", ".join(_summary(v) for v in value[:SHOWN_ITEMS])
        return f"[{shown}, ... ({len(value)} items)]"
    if isinstance(value, list | tuple):
        return ("[{}]" if isinstance(value, list) else "({})").format(", ".join(_summary(v) for v in value))
    return repr(value)

"""The settings a comparison sweeps: their number, their bounds, their labels, each checked before any solve.

Each method is solved over a sweep of its accuracy setting: its backend's ``work_precision`` (step
sizes h for the fixed-step methods, tolerances for the adaptive ones), or the settings the user gives.
"""

from __future__ import annotations

import dataclasses
import math

from daemodel.backends.grids import SWEEP_FIRST_STEPS, fixed_grid
from daemodel.backends.torch_setup import torch_device
from daemodel.errors import ComparisonError, ModelError, ResourceLimitError

# Sweep points per method when compare() is not told otherwise.
DEFAULT_POINTS = 4
# Most sweep points: a fixed-step sweep halves h from span/steps at each point, so point 12 is
# already span/(2,048 steps) (20,480 steps per solve at the default steps = 10), and each
# further point doubles the time.
MAX_POINTS = 12
# Most fixed-grid steps one compared setting may take, refused before any solve: radau's
# default max_steps, five times the finest default sweep point.
MAX_SWEEP_STEPS = 100_000


def check_points(points, steps: int = SWEEP_FIRST_STEPS) -> int:
    """``points`` if it is an integer from 1 to :data:`MAX_POINTS`, and ``steps`` a positive
    integer, else :class:`ComparisonError`."""
    if isinstance(points, bool) or not isinstance(points, int) or points < 1:
        raise ComparisonError(f"points must be a positive integer; got {points!r}")
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise ComparisonError(f"steps must be a positive integer (the coarsest fixed-step grid); got {steps!r}")
    if points > MAX_POINTS:
        finest = steps * 2 ** (MAX_POINTS - 1)
        raise ComparisonError(
            f"points = {points} is more than {MAX_POINTS}: a fixed-step sweep halves h from span/{steps} "
            f"at each point, so point {MAX_POINTS} already takes {finest:,} steps per solve and every further point "
            f"doubles that; take points <= {MAX_POINTS}, or give sweep= with the settings you need"
        )
    return points


def check_setting(backend, options: dict, t_span, context: str, fix: str) -> None:
    """Raise the :class:`ModelError` that solving ``options`` would raise, before any solve,
    with ``context`` (method and setting) in front and ``fix`` behind its message."""
    from daemodel.solving.solver import check_options

    try:
        check_options(backend, options)
        flat = _flatten(options)
        if flat.get("device") is not None:  # a CUDA device torch cannot see
            torch_device(flat["device"])
        h = flat.get("h")
        if h is not None:  # a fixed grid: checked by Options as a positive number
            span = t_span[1] - t_span[0]
            if span / h > MAX_SWEEP_STEPS:
                raise ResourceLimitError(
                    f"h = {h:g} makes {math.ceil(span / h):,} steps over t_span = ({t_span[0]:g}, {t_span[1]:g}), "
                    f"more than the {MAX_SWEEP_STEPS:,} a compared setting may take; "
                    f"take h >= {span / MAX_SWEEP_STEPS:g}"
                )
            fixed_grid(t_span, h)  # h larger than the interval
    except ModelError as error:
        raise type(error)(f"{context}: {error}{fix}") from None


def sweep_labels(sweep: list[dict]) -> list[tuple[str, str]]:
    """``(settings, short)`` text for each option dict of one method's sweep: ``settings``
    names every option (a config dataclass by its fields that differ from its defaults or
    along the sweep), ``short`` only what changes along the sweep (for the plot)."""
    flat = [_flatten(options) for options in sweep]
    keys = list(dict.fromkeys(k for f in flat for k in f))
    varying = [k for k in keys if len({repr(f.get(k)) for f in flat}) > 1]
    out = []
    for options, f in zip(sweep, flat, strict=True):
        named = [k for k in keys if k in f and (k in options or k in varying or f[k] != _default(options, k))]
        full = ", ".join(_show(k, f[k]) for k in named) or "defaults"
        short = ", ".join(_show(k, f[k]) for k in varying if k in f) or full
        out.append((full, short))
    return out


def _flatten(options: dict) -> dict:
    """Options with any config dataclass replaced by its fields."""
    flat = {}
    for key, value in options.items():
        if dataclasses.is_dataclass(value):
            flat.update({f.name: getattr(value, f.name) for f in dataclasses.fields(value)})
        else:
            flat[key] = value
    return flat


def _default(options: dict, key: str):
    for value in options.values():
        if dataclasses.is_dataclass(value) and key in {f.name for f in dataclasses.fields(value)}:
            return getattr(type(value)(), key)
    return None


def _show(key: str, value) -> str:
    return f"{key}={value:g}" if isinstance(value, float) else f"{key}={value}"

"""Time grids shared by the methods: fixed-step grids, output times, work-precision sweeps."""

from __future__ import annotations

import math

import numpy as np

from daemodel.errors import ResourceLimitError, StepSizeError, TimeSpanError

# Number of output times a method with its own step selection reports when t_eval is not given.
DEFAULT_OUTPUT_POINTS = 101


# Work-precision sweeps (daemodel.compare): fixed-step methods take h = span / (10 * 2^k),
# tolerance-driven ones rtol = 10^-(4 + 2k), k = 0, 1, ...: coarse enough to be cheap at
# k = 0, and four points reach the float64 floor of a fifth-order method on a unit interval.
SWEEP_FIRST_STEPS = 10


SWEEP_FIRST_DIGITS = 4


# Stages of the fixed-step sweeps: the paper's v = 3 (order 5), where the PINN was measured.
SWEEP_STAGES = 3


# Most steps of a fixed grid, whatever the method: its times alone take 80 MB, and at the ~0.1 ms
# that the cheapest step of any backend costs, 10^7 steps are > 15 minutes: past this, h is a typo.
MAX_GRID_POINTS = 10**7


# A grid step must exceed this many ulps of the largest |t|, or t0 + k h repeats times.
MIN_STEP_ULPS = 16


def halving_steps(t_span, points: int, steps: int = SWEEP_FIRST_STEPS) -> list[float]:
    """Step sizes of a work-precision sweep: span / steps, span / (2 steps), ..."""
    return [(t_span[1] - t_span[0]) / (steps * 2**k) for k in range(points)]


def fixed_step_sweep(t_span, points: int, steps: int = SWEEP_FIRST_STEPS) -> list[dict]:
    """``stages``/``h`` options of a fixed-step method's work-precision sweep."""
    return [{"stages": SWEEP_STAGES, "h": h} for h in halving_steps(t_span, points, steps)]


def tolerance_sweep(points: int) -> list[dict]:
    """``rtol``/``atol`` options of an adaptive method's sweep: rtol = atol = 1e-4, 1e-6, ..."""
    return [{"rtol": tol, "atol": tol} for tol in (10.0 ** -(SWEEP_FIRST_DIGITS + 2 * k) for k in range(points))]


def grid_steps(t_span, h: float, *, max_steps: int | None = None) -> int:
    """Steps of the grid :func:`fixed_grid` builds, checked before anything is allocated.

    Raises :class:`StepSizeError` when ``h`` exceeds the interval or is below the float
    resolution of t there, and :class:`ResourceLimitError` when the grid needs more than
    ``max_steps`` (the caller's own budget, when given) or :data:`MAX_GRID_POINTS` steps.
    """
    t0, t1 = t_span
    span = t1 - t0
    if h > span * (1 + 1e-12):
        raise StepSizeError(
            f"h = {h:g} is larger than the interval t_span = ({t0:g}, {t1:g}) of length {span:g}; take h <= {span:g}"
        )
    steps = span / h  # a float: it may exceed any int a grid could hold
    for limit, name in ((max_steps, "max_steps"), (MAX_GRID_POINTS, "MAX_GRID_POINTS")):
        if limit is not None and not steps <= limit * (1 + 1e-9):
            why = "raise max_steps or" if name == "max_steps" else "a fixed grid holds at most that many steps:"
            raise ResourceLimitError(
                f"h = {h:g} over t_span = ({t0:g}, {t1:g}) needs {steps:.4g} steps, more than {name} = {limit:,}; "
                f"{why} take h >= {span / limit:.3g}"
            )
    resolution = MIN_STEP_ULPS * float(np.spacing(max(abs(t0), abs(t1))))
    # (one step, t0 to t1, repeats no time: an event's trial solve 1.7e-6 past an output at t = 1e9 is one, and
    # was refused for an h below 16 spacings that the user never gave)
    if h < resolution and steps > 1 + 1e-9:
        raise StepSizeError(
            f"h = {h:g} is below the float64 resolution of t on t_span = ({t0:.15g}, {t1:.15g}) "
            f"({MIN_STEP_ULPS} ulps = {resolution:.3g}): the grid's times would repeat; take h >= {resolution:.3g}"
        )
    return round(steps) if abs(steps - round(steps)) <= 1e-9 * max(1.0, steps) else math.ceil(steps)


def fixed_grid(t_span, h: float, *, max_steps: int | None = None) -> np.ndarray:
    """``t0, t0 + h, ..., t1``: the last step is shortened unless span/h is an integer (to 1e-9).

    The step count is checked first (:func:`grid_steps`): against ``max_steps`` when given, and
    always against :data:`MAX_GRID_POINTS`, so an impossible grid is refused before it is allocated.
    """
    t0, t1 = t_span
    count = grid_steps(t_span, h, max_steps=max_steps)
    grid = t0 + h * np.arange(count + 1)
    grid[-1] = t1
    return grid


def default_times(t_span) -> np.ndarray:
    """The :data:`DEFAULT_OUTPUT_POINTS` output times of a method that chooses its own steps, each float64 time once:
    over a span of a few float64 spacings of t (a trial solve of an event's location at t = 1e13, 0.02 long,
    11 spacings there) linspace's times round onto one another and onto t0, and casadi-idas, given a first output
    at t0, started IDACalcIC with a step of 0 and never returned."""
    return np.unique(np.linspace(*t_span, DEFAULT_OUTPUT_POINTS))


def output_times(t_eval, t_span, default) -> np.ndarray:
    """Validated output times: sorted, finite, inside ``t_span``; ``default`` when None."""
    if t_eval is None:
        return np.asarray(default, dtype=float)
    times = numeric_times(t_eval)
    t0, t1 = t_span
    slack = 1e-12 * max(1.0, abs(t0), abs(t1))
    if times.size == 0:
        raise TimeSpanError(f"t_eval must hold at least one finite time; got {t_eval!r}")
    # (array methods and one comparison of neighbours, not np.all/np.any over np.diff: twice per solve)
    if not np.isfinite(times).all():
        raise TimeSpanError(f"t_eval must hold finite times only; got {t_eval!r}")
    if (times[1:] <= times[:-1]).any():
        raise TimeSpanError("t_eval must be strictly increasing")
    if times[0] < t0 - slack or times[-1] > t1 + slack:
        raise TimeSpanError(f"t_eval runs from {times[0]:g} to {times[-1]:g}, outside t_span = ({t0:g}, {t1:g})")
    # (clipped only where an end lies outside, by its slack: np.clip's Python wrapper cost a few us twice a solve)
    if not (times[0] < t0 or times[-1] > t1):
        return times
    clipped = np.clip(times, t0, t1)
    if (clipped[1:] <= clipped[:-1]).any():  # (two times within the slack outside one end: both at that end)
        raise TimeSpanError(
            f"t_eval holds two times that lie outside t_span = ({t0!r}, {t1!r}) by less than its slack ({slack:.3g}) "
            "and so are the same time at its end; keep one of them"
        )
    return clipped


def numeric_times(t_eval) -> np.ndarray:
    """``t_eval`` as a flat float array; :class:`TimeSpanError` unless it holds real numbers only."""
    try:
        array = np.asarray(t_eval)
        if array.dtype.kind == "O":  # e.g. a list mixing Python, numpy and sympy numbers
            array = array.astype(float)
    except (TypeError, ValueError):
        array = None
    if array is None or array.dtype.kind not in "iuf":
        kind = "no array" if array is None else f"dtype {array.dtype}"
        raise TimeSpanError(f"t_eval must be a sequence of real numbers; got {t_eval!r} ({kind})")
    return array.astype(float).reshape(-1)

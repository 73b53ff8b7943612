"""The backend contract, and checks that several methods' options share.

A backend is a final subclass of :class:`AbstractBackend`:

1. ``name`` is the string users pass as ``solve(method=...)``; ``Options`` is a frozen,
   keyword-only dataclass whose fields are the method's options, validated in
   ``__post_init__``; ``max_index`` is the highest index the method solves directly
   (``solve`` reduces a model of higher index before calling it).
2. ``solve(compiled, t_span, start, options)`` integrates every sample of ``start`` over
   ``t_span = (t0, t1)``, ``t0 < t1``, and returns a :class:`~daemodel.solution.Solution`
   with values for every state and algebraic variable, its wall time and its stats.
3. It never returns non-finite values and never warns-then-returns: a failure raises a
   :class:`~daemodel.errors.SolverError` (:class:`~daemodel.errors.ConvergenceError`,
   :class:`~daemodel.errors.LocalErrorBoundError`, :class:`~daemodel.errors.StepLimitError`)
   naming the time, the step, the sample and the fix.
4. Every loop has a user-settable bound, and a request that cannot fit (a grid of more than
   :data:`MAX_GRID_POINTS` steps, see :func:`grid_steps`) is refused before anything is allocated.
"""

from __future__ import annotations

import math
import sys
import time
from abc import ABC, abstractmethod
from contextlib import contextmanager
from typing import ClassVar

import numpy as np

from daemodel.errors import InvalidOptionError, ResourceLimitError, StepSizeError, TimeSpanError
from daemodel.reals import real

# Number of output times a method with its own step selection reports when t_eval is not given.
DEFAULT_OUTPUT_POINTS = 101
# Work-precision sweeps (daemodel.compare): fixed-step methods take h = span / (10 * 2^k),
# tolerance-driven ones rtol = 10^-(4 + 2k), k = 0, 1, ...: coarse enough to be cheap at
# k = 0, and four points reach the float64 floor of a fifth-order method on a unit interval.
SWEEP_FIRST_STEPS = 10
SWEEP_FIRST_DIGITS = 4
# Stages of the fixed-step sweeps: the paper's v = 3 (order 5), where the PINN was measured.
SWEEP_STAGES = 3
# Fixed-step methods (radau, casadi-collocation): a step whose estimated local error exceeds this
# fraction of its variable's scale 1 + max|u| keeps no correct digit.  Measured: smooth problems
# (pendulum, Hessenberg, an RLC circuit, s = 1..5, h = 0.1..0.0125) stay below 0.035; steps across
# a pole that land on a finite root measure 0.2 and more (a wrong root is wrong by O(1) times the
# scale, so the 1e3 first proposed would catch almost none of them).
LOCAL_ERROR_BOUND = 0.1
# Fixed steps: a run whose largest local error estimate, in the same units, exceeds this is flagged
# (status "flagged: ..." naming the step, and a LocalErrorWarning), not "success": the default asks
# for about three correct digits of every step relative to the solution's size; ``estimate_bound``
# sets it per solve.
DEFAULT_ESTIMATE_BOUND = 1e-3
# Step loops give up early when the last PROGRESS_WINDOW steps project more than PROJECTION_FACTOR
# times the steps left in the budget: an endless t_span or a chattering switch fails in a second
# instead of spending the whole budget.  The projection lets h keep growing as it did over the
# window (a stiff transient's slow start is not judged at its pace), and a collapsing h (below
# COLLAPSE_FACTOR of the window's start: a blow-up) is left to the step-size failure that names it.
PROGRESS_WINDOW, PROJECTION_FACTOR, COLLAPSE_FACTOR = 100, 10, 0.1
# Windows in a row that must each project past the budget before a loop gives up early.
HOPELESS_WINDOWS = 2
# Meaningful relative tolerances: below ~50 eps of float64 no integrator can deliver (IDAS and
# RADAU5 stall there, and an adaptive solve runs until the step underflows); at or above 0.1 not
# even one digit is asked for.
RTOL_RANGE = (1e-14, 0.1)
# Most steps of a fixed grid, whatever the method: its times alone take 80 MB, and at the ~0.1 ms
# that the cheapest step of any backend costs, 10^7 steps are > 15 minutes: past this, h is a typo.
MAX_GRID_POINTS = 10**7
# A grid step must exceed this many ulps of the largest |t|, or t0 + k h repeats times.
MIN_STEP_ULPS = 16


def estimate_status(method: str, worst: float, bound: float, where: str) -> str:
    """ "success" where a fixed-step run's largest local error estimate ``worst`` is within ``bound``;
    else a "flagged: ..." status naming the step (``where``), with a :class:`LocalErrorWarning`."""
    import warnings

    from daemodel.errors import LocalErrorWarning

    if worst <= bound:
        return "success"
    status = (
        f"flagged: {method}'s local error estimate reaches {worst:.3g} of the solution's size at {where}, beyond "
        f"estimate_bound = {bound:g}: the values there keep fewer digits than the bound asks; take a smaller h, "
        "or the adaptive mode (rtol=...)"
    )
    warnings.warn(status, LocalErrorWarning, stacklevel=caller_level())
    return status


def caller_level() -> int:
    """The ``stacklevel`` that points a warning at the first frame outside daemodel (the user's call),
    judged by module name (an installed copy's paths say nothing about the repository's layout)."""
    import sys

    frame, level = sys._getframe(1), 1
    while frame is not None and frame.f_globals.get("__name__", "").split(".")[0] == "daemodel":
        frame, level = frame.f_back, level + 1
    return level


def make_solution(
    backend,
    compiled,
    start,
    options,
    times,
    values,
    solve_time: float,
    stats: dict,
    settings=None,
    status="success",
    setup_time: float = 0.0,
    dense=None,
):
    """The :class:`Solution` of a backend: ``values`` has shape (B, T, n+m) in state then algebraic order.

    ``backend`` is the backend or its method name (a trained surrogate answers as ``"pinn"``
    without one).  ``solve_time`` and ``setup_time`` are :attr:`Solution.solve_time` and
    :attr:`Solution.setup_time`; ``settings`` defaults to the options' fields (less ``t_eval``; a
    function, such as radau's ``start_guess``, by its name, not copied); ``status`` is
    :attr:`Solution.status`; ``dense`` is :attr:`Solution.dense` (:mod:`daemodel.dense`).

    Raises
    ------
    BranchError
        When the algebraic variables leave their branch of roots between two output times
        (:func:`daemodel.initial_states.check_branch`).
    """
    from dataclasses import asdict, fields, is_dataclass

    from daemodel.initial_states import check_branch
    from daemodel.solution import Solution

    check_branch(backend if isinstance(backend, str) else backend.name, compiled, times, values, start.p)
    if settings is None:
        settings = {}
        for field in fields(options):
            value = getattr(options, field.name)
            if field.name == "t_eval":
                continue
            if is_dataclass(value):
                value = asdict(value)
            elif callable(value):
                value = getattr(value, "__qualname__", type(value).__name__)
            settings[field.name] = value

    names = (*compiled.state_names, *compiled.algebraic_names)
    return Solution(
        t=np.asarray(times, dtype=float),
        values={name: np.ascontiguousarray(values[..., i]) for i, name in enumerate(names)},
        method=backend if isinstance(backend, str) else backend.name,
        settings=settings,
        solve_time=solve_time,
        setup_time=setup_time,
        stats=stats,
        compiled=compiled,
        parameters=start.p,
        batched=start.batched,
        status=status,
        dense=dense,
    )


class AbstractBackend(ABC):
    """A solution method: ``solve(compiled, t_span, start, options) -> Solution``."""

    name: ClassVar[str]
    Options: ClassVar[type]
    max_index: ClassVar[int]

    @abstractmethod
    def solve(self, compiled, t_span: tuple[float, float], start, options):
        """Integrate every sample of ``start`` (:class:`InitialStates`) over ``t_span``."""

    def describe(self, options) -> str:
        """The method and the settings that matter for its accuracy, for a label (e.g. a reference's)."""
        return self.name

    def times_follow_samples(self, options) -> bool:
        """Whether the output times depend on the samples solved together (adaptive steps with no
        ``t_eval``): the samples of separate calls, such as an ensemble's chunks, then come back
        on different times."""
        return False

    def work_precision(self, t_span: tuple[float, float], points: int, steps: int = SWEEP_FIRST_STEPS) -> list[dict]:
        """``points`` sets of options, from cheap to accurate, that :func:`daemodel.compare`
        sweeps; a method without an accuracy setting is solved once with its defaults.  A
        fixed-step method's coarsest setting takes ``steps`` steps over ``t_span``; others
        ignore it."""
        return [{}]


class ProgressWatch:
    """Whether a step loop can still reach ``t1`` within its budget, judged window by window.

    ``start`` is ``(t, count, h, extra)`` where the current window began (``extra``: whatever
    the caller wants back for its message, e.g. its accepted steps then).
    """

    def __init__(self, t: float, h: float, extra=None):
        self.start = (t, 0, h, extra)
        self.strikes = 0  # windows in a row that projected past the budget

    def hopeless(self, count: int, t: float, h: float, t1: float, budget: int, extra=None) -> float | None:
        """Call once per step; ``count`` steps (or attempts) so far.  Returns the projected number of
        further steps when :data:`HOPELESS_WINDOWS` windows in a row project past
        :data:`PROJECTION_FACTOR` times the budget left, else None (starting a new window when one
        is complete)."""
        t_w, count_w, h_w, _ = self.start
        steps = count - count_w
        if steps < PROGRESS_WINDOW or count >= budget:  # the budget's own error speaks at the end
            return None
        covered, left, growth = t - t_w, t1 - t, h / h_w
        if covered <= 0:
            needed = math.inf
        elif growth > 1:  # windows covering covered * growth^k: a geometric series up to t1
            needed = steps * math.log1p(left * (growth - 1) / covered) / math.log(growth)
        else:
            needed = steps * left / covered
        hopeless = growth >= COLLAPSE_FACTOR and needed > PROJECTION_FACTOR * (budget - count)
        self.strikes = self.strikes + 1 if hopeless else 0
        if self.strikes >= HOPELESS_WINDOWS:
            return needed
        self.start = (t, count, h, extra)
        return None


# Seconds between progress lines when stderr is not a terminal (a log file, CI): a terminal
# redraws one line in place, a log would keep every redraw.
LOG_PROGRESS_SECONDS = 5.0


@contextmanager
def captured_output():
    """Collect what casadi prints during a call instead of showing it (yields the text).

    casadi's Python module sends its C++ output streams to ``sys.stdout``/``sys.stderr``, so
    redirecting those catches IDAS's messages, the root finder's dumps and the inputs a failing
    call prints of every function it was nested in (the tests check the file descriptors too,
    with ``capfd``).
    """
    import contextlib
    import io

    text = io.StringIO()
    with contextlib.redirect_stdout(text), contextlib.redirect_stderr(text):
        yield text


def stderr_is_terminal() -> bool:
    return bool(getattr(sys.stderr, "isatty", lambda: False)())


def show_progress(progress: bool | None) -> bool:
    """``progress`` as given, or whether stderr is a terminal."""
    if progress is None:
        return stderr_is_terminal()
    return bool(progress)


def progress_bar(total: int, desc: str, unit: str):
    """A tqdm bar on stderr: redrawn in place on a terminal, a line every
    :data:`LOG_PROGRESS_SECONDS` at most elsewhere."""
    from tqdm.auto import tqdm

    interval = 0.1 if stderr_is_terminal() else LOG_PROGRESS_SECONDS
    return tqdm(total=total, desc=desc, unit=unit, leave=False, mininterval=interval, file=sys.stderr)


def halving_steps(t_span, points: int, steps: int = SWEEP_FIRST_STEPS) -> list[float]:
    """Step sizes of a work-precision sweep: span / steps, span / (2 steps), ..."""
    return [(t_span[1] - t_span[0]) / (steps * 2**k) for k in range(points)]


def fixed_step_sweep(t_span, points: int, steps: int = SWEEP_FIRST_STEPS) -> list[dict]:
    """``stages``/``h`` options of a fixed-step method's work-precision sweep."""
    return [{"stages": SWEEP_STAGES, "h": h} for h in halving_steps(t_span, points, steps)]


def tolerance_sweep(points: int) -> list[dict]:
    """``rtol``/``atol`` options of an adaptive method's sweep: rtol = atol = 1e-4, 1e-6, ..."""
    return [{"rtol": tol, "atol": tol} for tol in (10.0 ** -(SWEEP_FIRST_DIGITS + 2 * k) for k in range(points))]


def check_number(name: str, value, *, positive: bool = True, integer: bool = False, allow_none: bool = False):
    """``value`` as a Python float (int with ``integer=True``) or None, else :class:`InvalidOptionError`.

    Any real number is accepted: Python, numpy (``np.float32(0.05)``) or sympy (``sp.Rational(1, 20)``)
    (see :func:`daemodel.reals.real`); options store the returned value.
    """
    if value is None and allow_none:
        return None
    number = real(value, name, integer=integer, error=InvalidOptionError)
    if positive and number <= 0:
        raise InvalidOptionError(f"{name} must be positive; got {value!r}")
    return number


def set_number(options, name: str, **check) -> None:
    """:func:`check_number` on the option ``name`` of a frozen options dataclass, which then holds the
    returned Python number (casadi, torch and JSON take it as it is)."""
    object.__setattr__(options, name, check_number(name, getattr(options, name), **check))


def set_tolerances(options, **check) -> None:
    """:func:`check_tolerances` on ``options.rtol`` and ``options.atol``, stored as floats."""
    rtol, atol = check_tolerances(options.rtol, options.atol, **check)
    object.__setattr__(options, "rtol", rtol)
    object.__setattr__(options, "atol", atol)


def check_tolerances(rtol, atol, *, minimum_rtol: float = RTOL_RANGE[0]) -> tuple[float, float]:
    """``(rtol, atol)`` as floats; :class:`InvalidOptionError` unless ``rtol`` lies in :data:`RTOL_RANGE`
    and ``atol`` is positive."""
    rtol = check_number("rtol", rtol)
    atol = check_number("atol", atol)
    low, high = minimum_rtol, RTOL_RANGE[1]
    if not low <= rtol <= high:
        raise InvalidOptionError(
            f"rtol = {rtol:g} is outside the meaningful range [{low:g}, {high:g}]: "
            + (
                "float64 cannot deliver more digits; use rtol >= " + f"{low:g}"
                if rtol < low
                else "that asks for no correct digit; use rtol <= " + f"{high:g}"
            )
        )
    return rtol, atol


def check_stages(stages) -> None:
    if isinstance(stages, bool) or not isinstance(stages, int) or not 1 <= stages <= 7:
        raise InvalidOptionError(f"stages must be an integer from 1 to 7 (Radau IIA of order 2s-1); got {stages!r}")


def check_dtype(dtype) -> str:
    """Normalise ``"float64"``, ``"float32"`` or a torch dtype to its name."""
    name = str(dtype).removeprefix("torch.")
    if name not in ("float64", "float32"):
        raise InvalidOptionError(f"dtype must be 'float64' (default) or 'float32'; got {dtype!r}")
    return name


# torch work (samples x unknowns per operation) below which intra-op threads cost more than they
# give: measured on 2 cores, batched radau on 100 pendulums takes 0.064 s on 1 thread and 0.117 s
# on 2, while 10,000 take 1.37 s and 1.07 s, and 50,000 7.4 s and 4.2 s.
SMALL_TORCH_WORK = 20_000


def check_threads(threads) -> None:
    """``threads`` is None or a positive integer, else :class:`InvalidOptionError`."""
    if threads is not None and (isinstance(threads, bool) or not isinstance(threads, int) or threads < 1):
        raise InvalidOptionError(f"threads must be a positive integer or None (chosen by the work); got {threads!r}")


@contextmanager
def torch_threads(threads: int | None, work: int):
    """torch's intra-op threads for one computation, the caller's setting restored after it.

    ``threads`` None: one thread when ``work`` (samples x unknowns per operation) is below
    :data:`SMALL_TORCH_WORK`, where more only add synchronisation, and torch's own setting (the
    caller's ``torch.set_num_threads``) otherwise.
    """
    import torch

    wanted = threads if threads is not None else (1 if work < SMALL_TORCH_WORK else None)
    before = torch.get_num_threads()
    if wanted is not None and wanted != before:
        torch.set_num_threads(wanted)
    try:
        yield
    finally:
        if torch.get_num_threads() != before:
            torch.set_num_threads(before)


# (device, dtype) pairs on which torch has run its first operations in this process (see warm_up_torch).
_TORCH_WARM: set[tuple[str, str]] = set()


def warm_up_torch(device="cpu", dtype: str = "float64") -> float:
    """Import torch and run its first operations on ``device`` in ``dtype``, once per process; the
    seconds this call took (0.0 when already warm).

    torch's first use in a process costs 1-4 s (the import, then the first matrix product and LU,
    which load their kernels and LAPACK; a CUDA device's context on top).  A backend that uses torch
    calls this inside its timed setup, so that the cost lands on the setup clock of the solve that
    pays it instead of on no clock (the solve after it would look 100 times faster).
    """
    key = (str(device), str(dtype))
    if key in _TORCH_WARM:
        return 0.0
    began = time.perf_counter()
    import torch

    a = torch.eye(4, dtype=getattr(torch, dtype), device=torch_device(device)) + 1.0  # a named error for a bad device
    factors = torch.linalg.lu_factor(a)
    torch.linalg.lu_solve(*factors, a @ a)
    if a.device.type == "cuda":
        torch.cuda.synchronize(a.device)
    _TORCH_WARM.add(key)
    return time.perf_counter() - began


def torch_device(name):
    """``torch.device(name)`` for a device daemodel's torch solvers can use here: the CPU or a visible CUDA device.

    Raises :class:`InvalidOptionError` naming the device and the valid choices for anything else
    (not a device name, ``"meta"``, ``"mps"``, a CUDA device torch cannot see).
    """
    import torch

    choices = device_choices()
    if isinstance(name, torch.device):
        device = name
    elif isinstance(name, str):
        try:
            device = torch.device(name)
        except (RuntimeError, ValueError):
            raise InvalidOptionError(
                f"device = {name!r} names no torch device; the choices here are {choices}"
            ) from None
    else:
        raise InvalidOptionError(f"device must be a string such as 'cpu'; got {name!r}; the choices here are {choices}")
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise InvalidOptionError(f"device = {name!r} but torch sees no CUDA device; use device='cpu'")
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise InvalidOptionError(
                f"device = {name!r} but torch sees {torch.cuda.device_count()} CUDA device(s); the choices here "
                f"are {choices}"
            )
    elif device.type != "cpu":
        raise InvalidOptionError(
            f"device = {name!r}: daemodel's torch solvers run on the CPU or a CUDA device, not on "
            f"{device.type!r} (float64, LU factorisation); the choices here are {choices}"
        )
    return device


def device_choices() -> str:
    """The devices :func:`torch_device` accepts on this machine, as a readable list."""
    import torch

    names = ["'cpu'"]
    if torch.cuda.is_available():
        count = torch.cuda.device_count()
        names += ["'cuda'", "'cuda:0'" if count == 1 else f"'cuda:0' to 'cuda:{count - 1}'"]
    return ", ".join(names)


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
    if h < resolution:
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


def check_output_memory(method: str, compiled, samples: int, points: int, extra: int = 0) -> None:
    """Refuse, before allocating, a solve whose outputs (``samples`` x ``points`` x variables
    float64) and ``extra`` bytes exceed the memory limit (:func:`daemodel.files.check_memory`)."""
    from daemodel.files import check_memory

    D = len(compiled.states) + len(compiled.algebraics)
    parts = {"outputs": samples * points * D * 8} | ({"working set": extra} if extra else {})
    check_memory(f"{method} on {samples} sample(s) of {D} unknowns", parts)


def output_times(t_eval, t_span, default) -> np.ndarray:
    """Validated output times: sorted, finite, inside ``t_span``; ``default`` when None."""
    if t_eval is None:
        return np.asarray(default, dtype=float)
    times = numeric_times(t_eval)
    t0, t1 = t_span
    slack = 1e-12 * max(1.0, abs(t0), abs(t1))
    if times.size == 0:
        raise TimeSpanError(f"t_eval must hold at least one finite time; got {t_eval!r}")
    if not np.all(np.isfinite(times)):
        raise TimeSpanError(f"t_eval must hold finite times only; got {t_eval!r}")
    if np.any(np.diff(times) <= 0):
        raise TimeSpanError("t_eval must be strictly increasing")
    if times[0] < t0 - slack or times[-1] > t1 + slack:
        raise TimeSpanError(f"t_eval runs from {times[0]:g} to {times[-1]:g}, outside t_span = ({t0:g}, {t1:g})")
    return np.clip(times, t0, t1)


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

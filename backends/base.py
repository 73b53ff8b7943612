"""The backend contract: what a method is, and the Solution it returns.

What several methods share besides lives apart: :mod:`.checks` (their options' checks),
:mod:`.grids` (time grids, output times, sweeps), :mod:`.progress` (progress bars, step loops that
cannot finish, casadi's output) and :mod:`.torch_setup` (devices, threads, torch's warm-up).

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
   :data:`~.grids.MAX_GRID_POINTS` steps, see :func:`~.grids.grid_steps`) is refused before anything is allocated.
5. A backend whose ``stops`` is True also takes ``solve(..., stop=...)``: a function
   ``stop(times (k,), Y (k, n), Z (k, m)) -> bool`` of one sample's outputs, called on each block of
   them in order as the integration makes them (the start value first); where it returns True the
   integration ends after that block, and the Solution holds the outputs up to it (those of a solve to
   t1 up to there, the same values).  The event search (:mod:`daemodel.solving.events`) stops where
   an event function has crossed zero, instead of solving on to t1 and discarding the rest.
"""

from __future__ import annotations

import sys
import time
from abc import ABC, abstractmethod
from typing import ClassVar

import numpy as np
from daemodel.backends.grids import SWEEP_FIRST_STEPS

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
        (:func:`daemodel.compiling.initial_states.check_branch`).
    """
    from dataclasses import asdict, fields, is_dataclass

    from daemodel.compiling.initial_states import check_branch
    from daemodel.solution import Solution

    began = time.perf_counter()  # (the check is part of the solve: on its clock)
    check_branch(backend if isinstance(backend, str) else backend.name, compiled, times, values, start.p)
    checked = time.perf_counter() - began
    solve_time += checked
    stats = {**stats, "branch_check_seconds": checked}
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
    # solve() takes stop=... (rule 5 of the module docstring)
    stops: ClassVar[bool] = False
    # Most fixed steps over t_span one setting of a benchmark sweep (dm.bench) gives this method
    # (None: no limit beyond the sweep's own); a longer grid is skipped with the reason in the report.
    bench_max_steps: ClassVar[int | None] = None

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

"""The backend contract: what a method is, and the Solution it returns.

What several methods share besides lives apart: :mod:`.checks` (their options' checks),
:mod:`.grids` (time grids, output times, sweeps), :mod:`.progress` (progress bars, step loops that
cannot finish, casadi's output) and :mod:`.torch_setup` (devices, threads, torch's warm-up).  The
same contract holds for a method plugged in from outside (:mod:`.registry`; docs/methods.md#writing-a-method
walks through one).

A backend is a final subclass of :class:`AbstractBackend`:

1. ``name`` is the string users pass as ``solve(method=...)`` (the name it is registered under);
   ``Options`` is a frozen, keyword-only dataclass whose fields are the method's options, with
   defaults, validated in ``__post_init__`` (a value it cannot use:
   :class:`~daemodel.errors.InvalidOptionError` naming the option, the value and the range; an
   unknown keyword is refused by ``solve`` before, with :class:`~daemodel.errors.UnknownOptionError`
   listing the fields); ``max_index`` is the highest index the method solves directly
   (``solve`` reduces a model of higher index before calling it).
2. ``solve(compiled, t_span, start, options)`` integrates every sample of ``start`` (an
   :class:`~daemodel.compiling.initial_states.InitialStates`: consistent ``y0`` (B, n), ``z0`` (B, m),
   parameters ``p`` (B, k)) over ``t_span = (t0, t1)``, ``t0 < t1``, checked, and returns a
   :class:`~daemodel.solution.Solution` (made by :func:`make_solution`) with values for every state and
   algebraic variable at its output times (``t_eval`` where the method has that option: checked by
   :func:`~.grids.output_times`), its clocks and its stats.  ``compiled`` (a
   :class:`~daemodel.compiling.compiled.CompiledDAE`, index at most ``max_index``) gives the model's
   functions: ``compiled.torch_functions()`` (batched ``f``, ``g`` and their Jacobian),
   ``compiled.numeric``, ``compiled.casadi_dae()``.
3. Status: ``"success"`` only when the values are within the accuracy the method states (adaptive
   steps: their tolerance; fixed steps: the embedded estimate within its bound; a trained network:
   its error estimate within its bound); otherwise ``"flagged: ..."`` with the estimate, what it was
   compared with and the fix, and a warning the user cannot miss (:func:`estimate_status`).
4. It never returns non-finite values and never warns-then-returns: a failure raises a
   :class:`~daemodel.errors.SolverError` (:class:`~daemodel.errors.ConvergenceError`,
   :class:`~daemodel.errors.LocalErrorBoundError`, :class:`~daemodel.errors.StepLimitError`)
   naming the time, the step, the sample and the fix.
5. Every loop has a user-settable bound, and a request that cannot fit (a grid of more than
   :data:`~.grids.MAX_GRID_POINTS` steps, see :func:`~.grids.grid_steps`) is refused before anything is allocated;
   a model too large for the method at any setting is refused by :meth:`AbstractBackend.check_size`,
   which ``solve`` calls before the work that grows with the model (finding its switches, setup).
6. Clocks: ``setup_time`` is getting ready (generating or compiling code, building an integrator,
   training a network), ``solve_time`` is producing the values from the ready method, checks of
   the result included (:func:`make_solution` adds the branch check to it); nothing the method does
   runs outside them.  ``solve`` adds what it did before and after (compiling the model, initial
   states, joining pieces) to them, so that for every method setup + solve is the call's wall time.
7. Pieces: a model with switches or events is solved piece by piece (from breakpoint to
   breakpoint, from event to event, and short trial solves that locate an event), each a call of
   ``solve`` from the states where the last ended.  A method that cannot be called on pieces (one
   trained over the whole span per call) sets ``solves_pieces = False``; ``solve`` then refuses such
   models with :class:`~daemodel.errors.UnsupportedModelError` naming the method and the switch or event.
8. A backend whose ``stops`` is True also takes ``solve(..., stop=...)``: a function
   ``stop(times (k,), Y (k, n), Z (k, m), dense) -> bool`` of one sample's outputs, called on each block
   of them in order as the integration makes them (the start value first), ``dense`` the block's dense
   output from the output before it where the method has one (else None); where it returns True the
   integration ends after that block, and the Solution holds the outputs up to it (those of a solve to
   t1 up to there, the same values).  The event search (:mod:`daemodel.solving.events`) stops where
   an event function has crossed zero, instead of solving on to t1 and discarding the rest.
9. :meth:`AbstractBackend.work_precision` gives :func:`daemodel.compare` its default sweep (cheap to
   accurate); :meth:`AbstractBackend.describe` a label.
"""

from __future__ import annotations

import dataclasses
import functools
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


# Settings that make_solution keeps as they are (neither a dataclass nor a function).
PLAIN_SETTINGS = frozenset({bool, int, float, str})


@functools.cache
def option_names(options: type) -> tuple[str, ...]:
    """The fields of an options class that :func:`make_solution` keeps as its settings (all but
    ``t_eval``), found once per class."""
    return tuple(field.name for field in dataclasses.fields(options) if field.name != "t_eval")


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
    branch_signs=None,
):
    """The :class:`Solution` of a backend: ``values`` has shape (B, T, n+m) in state then algebraic order.

    ``backend`` is the backend or its method name (a trained surrogate answers as ``"pinn"``
    without one).  ``solve_time`` and ``setup_time`` are :attr:`Solution.solve_time` and
    :attr:`Solution.setup_time`; ``settings`` defaults to the options' fields (less ``t_eval``; a
    function, such as radau's ``start_guess``, by its name, not copied); ``status`` is
    :attr:`Solution.status`; ``dense`` is :attr:`Solution.dense` (:mod:`daemodel.dense`); ``branch_signs``
    (B, T), where the method knows ``sign(det H_z)`` at its outputs (NaN where not), spares the branch check
    their evaluation (:func:`daemodel.compiling.initial_states.check_branch`'s ``signs``).

    Raises
    ------
    BranchError
        When the algebraic variables leave their branch of roots between two output times
        (:func:`daemodel.compiling.initial_states.check_branch`).
    """
    from dataclasses import asdict, is_dataclass

    from daemodel.compiling.batch_function import claim_generated, generating_seconds
    from daemodel.compiling.initial_states import check_branch
    from daemodel.solution import Columns, Solution

    began, made = time.perf_counter(), generating_seconds()  # (the check is part of the solve: on its clock)
    name = backend if isinstance(backend, str) else backend.name
    check_branch(name, compiled, times, values, start.p, branch_signs)
    generated = claim_generated(made)  # (but its code, made at its first use (a piece's model), is setup)
    checked = time.perf_counter() - began - generated
    solve_time, setup_time = solve_time + checked, setup_time + generated
    stats = {**stats, "branch_check_seconds": checked}
    if generated:  # (in the setup: the figures add up to the clocks)
        stats["branch_check_code_seconds"] = generated
    if settings is None:
        settings = {}
        for name in option_names(type(options)):
            value = getattr(options, name)
            if value is not None and type(value) not in PLAIN_SETTINGS:  # (most are: one test, not two)
                if is_dataclass(value):
                    value = asdict(value)
                elif callable(value):
                    value = getattr(value, "__qualname__", type(value).__name__)
            settings[name] = value

    names = (*compiled.state_names, *compiled.algebraic_names)
    # (one copy with the variables first: each variable's (B, T) values are a contiguous view of it, where a
    # copy per variable took 140 ms at 10^5 unknowns)
    values = np.asarray(values)
    columns = np.ascontiguousarray(values.transpose(values.ndim - 1, *range(values.ndim - 1)))  # (np.moveaxis)
    columns.flags.writeable = False
    return Solution(
        t=np.asarray(times, dtype=float),
        values=Columns(names, columns),  # (each name's view made when read: 10^4 views were 1.5 MB)
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
    # solve() takes stop=... (rule 8 of the module docstring)
    stops: ClassVar[bool] = False
    # solve() may be called on pieces of the span (rule 7): models with switches and events are solved
    solves_pieces: ClassVar[bool] = True
    # Most fixed steps over t_span one setting of a benchmark sweep (dm.bench) gives this method
    # (None: no limit beyond the sweep's own); a longer grid is skipped with the reason in the report.
    bench_max_steps: ClassVar[int | None] = None

    @abstractmethod
    def solve(self, compiled, t_span: tuple[float, float], start, options):
        """Integrate every sample of ``start`` (:class:`InitialStates`) over ``t_span``."""

    def check_size(self, compiled, t_span: tuple[float, float], start, options) -> None:
        """Refuse, with a named error, a model this method cannot hold at its size, before any work
        that grows with it: :func:`daemodel.solve` calls it once the initial values are read
        (``start``, :class:`InitialStates`), before the switches are found and the method is set
        up.  ``compiled`` is the model as given (reduction keeps its variables).  Default: nothing."""
        return None  # (a method without a size limit: the work that grows with the model is its own)

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

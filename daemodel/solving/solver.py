"""``solve``: one entry point for every method."""

from __future__ import annotations

import dataclasses
import math
import time

from daemodel.backends import get_backend
from daemodel.compiling.algebraic import prepare as prepare_algebraic
from daemodel.compiling.compiler import as_compiled
from daemodel.compiling.initial_states import branch_check_functions, initial_states
from daemodel.compiling.switches import (
    branch_model,
    breakpoints,
    find_switches,
    has_time_switches,
    lock_branches,
    with_state_events,
)
from daemodel.errors import (
    InvalidOptionError,
    InvalidValueError,
    SensitivityError,
    TimeSpanError,
    UnknownOptionError,
    UnsupportedModelError,
)
from daemodel.messages import quoted
from daemodel.reals import is_real, real
from daemodel.solution import Solution
from daemodel.solving.batches import solve_on_common_times
from daemodel.solving.events import DEFAULT_MAX_EVENTS, solve_with_events
from daemodel.solving.resolution import flag_time_rounding
from daemodel.solving.switches import for_method, solve_with_breakpoints


def solve(
    model,
    t_span,
    *,
    method: str = "radau",
    y0=None,
    z0=None,
    parameters=None,
    max_events: int = DEFAULT_MAX_EVENTS,
    sensitivities=None,
    **options,
) -> Solution:
    """Solve a DAE over ``t_span`` with one method, for one initial state or a batch.

    Parameters
    ----------
    model : Model or CompiledDAE
        A Model is compiled first (all outputs).
    t_span : (float, float)
        ``(t0, t1)`` with ``t0 < t1``; ``t0`` is the time of the model's initial values.
    method : str
        A method's name: ``"radau"``, ``"casadi-collocation"``, ``"casadi-idas"``,
        ``"reference"``, ``"pinn"``, or one registered or installed from outside (``dm.methods()``
        lists them; :mod:`daemodel.backends.registry`).
    y0 : dict name -> float or array (B,), or array (n,) or (B, n), optional
        Initial states; states not named keep the model's values.  An array or a dict of
        arrays makes a batch: the solution's values get a leading axis of size B.
    z0 : same as y0, for the algebraic variables, optional
        Newton's starting values (and a claim checked against the consistent values).
    parameters : dict name -> float or array (B,), or array (k,) or (B, k), optional
    max_events : int
        Most events (``Model.event``) one solve handles (:class:`EventLimitError` beyond: chattering).
    sensitivities : list of str, optional
        Parameters and states to differentiate the solution by (``"radau"``): the exact derivatives
        of its discrete solution at the output times, algebraic variables included, read with
        ``sol.sensitivity(output, name)`` (:mod:`daemodel.sensitivities`).  A state's
        initial value moves with the others held where the constraints allow; a parameter moves the
        initial states the least that keeps them consistent.
    **options
        The method's options (e.g. ``stages=3, h=0.05`` or ``rtol=1e-8`` for ``"radau"``,
        ``config=dm.PINNConfig(...)`` for ``"pinn"``);
        an option the method does not have is an error that lists the ones it has.

    Returns
    -------
    Solution

    Examples
    --------
    >>> sol = dm.solve(model, (0.0, 1.0), method="radau", stages=3, h=0.05)
    >>> sol["y5"], sol.errors(exact), sol.drift()
    """
    started = time.perf_counter()
    dispatched = []  # when the work went to a method: the time before it (compile, checks) is setup
    sol = _solve(model, t_span, method, y0, z0, parameters, max_events, sensitivities, options, dispatched)
    sol = flag_time_rounding(sol)  # (every method: where t's float64 spacing is too coarse for the tolerance)
    return within_clocks(sol, started, dispatched[0] if dispatched else started)


def system_for(model, backend):
    """The system ``backend`` solves of ``model`` (reduced to its highest index), with its branch check's
    functions made: work a solve keeps with the compiled model, done before any method's clock."""
    compiled = for_method(model, backend)
    if compiled.algebraics:
        # (the check runs after the integration: made in the setup, numpy's code too, which evaluates the check
        # of more than a few output times; a locked piece's, made at its first check, is often only ever
        # evaluated at a trial solve's two ends, on casadi)
        branch_check_functions(compiled)[2].numpy()
        # (and, at index 2 or more, those that solve the algebraic variables from the states at the outputs)
        prepare_algebraic(compiled)
    return compiled


def prepare(model, methods) -> None:
    """Make now, on no method's clock, the work that every solve of ``model`` shares and keeps with the
    compiled model: the system each of ``methods`` solves (an index reduction), its branch check's
    functions, the initial-value checks and the switches.  :func:`daemodel.compare` calls it first,
    so that the first method it times does not pay for the others (the pendulum's first radau solve
    had 231 ms of such work in its setup, the next ones 0.2 ms)."""
    model = as_compiled(model)
    initial_states(model)
    with_state_events(model)
    for method in methods:
        system_for(model, get_backend(method))


def within_clocks(sol: Solution, started: float, dispatched: float) -> Solution:
    """``sol`` with every second since ``started`` on its clocks, so that its setup plus its solve time
    is the call's wall time: the time until the work ``dispatched`` to a method (compiling the model,
    checking options, initial states, switches) added to ``setup_time``, what the methods' own clocks
    did not count after it (joining pieces, checks) to ``solve_time``; each also in the stats
    (``preparation_seconds``, ``completion_seconds``), so that a method's own figures add up to them."""
    wall = time.perf_counter() - started
    before = dispatched - started
    after = max(0.0, wall - before - sol.setup_time - sol.solve_time)
    stats = sol.stats.extended(preparation_seconds=before, completion_seconds=after)
    return dataclasses.replace(sol, setup_time=sol.setup_time + before, solve_time=sol.solve_time + after, stats=stats)


def _solve(model, t_span, method, y0, z0, parameters, max_events, sensitivities, options, dispatched) -> Solution:
    """:func:`solve`'s work; ``dispatched`` gets the time at which it goes to a method."""
    backend = get_backend(method)
    opts = check_options(backend, options)
    if isinstance(max_events, bool) or not isinstance(max_events, int) or max_events < 0:
        raise InvalidOptionError(f"max_events must be a non-negative integer; got {max_events!r}")

    model = as_compiled(model)
    if sensitivities is not None:
        check_sensitivities(model, backend, opts, sensitivities)
    t_span = check_span(t_span, model)
    start = initial_states(model, y0=y0, z0=z0, parameters=parameters)
    backend.check_size(model, t_span, start, opts)  # (the PINN at 10^5 unknowns: refused in 0.2 s, not 10)
    if sensitivities is not None and find_switches(model):
        dispatched.append(time.perf_counter())
        return _on_fixed_branches(backend, model, t_span, start, opts, sensitivities)
    compiled = system_for(model, backend)
    located = with_state_events(model)  # (declared events, and one at each switch on a variable)
    # (a batch's samples have their own event times: they share outputs on t_eval only; without it a batch's
    # events and switches on variables are located in each sample, the batch's outputs all their output times
    # (.batches), a method without t_eval too: it stepped across the switches, x' = -Min(1, x) 2.7 tolerances off
    # at rtol 1e-10, "success", and a declared event was told to "pass t_eval", an option it does not have)
    batch_alone = len(start.p) > 1 and getattr(opts, "t_eval", None) is None
    # (float32 too: stepped across, x' = Piecewise((-1, x > 1), (-0.25, True)) from 7 x0 in [1.2, 2.8] at rtol 1e-5
    # ended 3,700 tolerances off, "success"; located in float32, within 0.02 of them: tests/solving/test_batches.py)
    time_switches = has_time_switches(model)
    if not backend.solves_pieces and (located.events or time_switches):
        raise unsupported(backend, model)
    if located.events and batch_alone:
        dispatched.append(time.perf_counter())
        return solve_on_common_times(backend, located, t_span, start, opts, max_events)
    if located.events:  # (located, reset and restarted from, in every method)
        dispatched.append(time.perf_counter())
        return solve_with_events(backend, located, t_span, start, opts, max_events)
    dispatched.append(time.perf_counter())
    if time_switches:  # (from breakpoint to breakpoint, each side on its own branch)
        return solve_with_breakpoints(backend, model, t_span, start, opts)
    sol = backend.solve(compiled, t_span, start, opts)
    return sol if sensitivities is None else with_sensitivities(sol, model, sensitivities)


def unsupported(backend, model) -> UnsupportedModelError:
    """The error for a method that is not called on pieces (``solves_pieces = False``) given ``model``,
    which has events or switches: naming the first of them."""
    if model.events:
        what = f"the event {model.events[0].name!r}"
    else:
        what = f"a switch ({find_switches(model)[0].describe()})"
    return UnsupportedModelError(
        f"method {backend.name!r} solves the whole span at once (solves_pieces = False), but model '{model.name}' "
        f"has {what}, across which daemodel solves piece by piece: use a method that solves pieces, e.g. 'radau'"
    )


def check_sensitivities(model, backend, opts, names) -> None:
    """Refuse, before solving, what :func:`with_sensitivities` cannot differentiate."""
    from daemodel.sensitivities import directions

    directions(model, names)
    if backend.name != "radau":
        raise SensitivityError(
            f"sensitivities are the derivatives of radau's discrete solution (its stage equations); method "
            f"{backend.name!r} has none: solve with method='radau'"
        )
    if not opts.dense_output:
        raise SensitivityError("sensitivities need the record of radau's steps: drop dense_output=False")
    if getattr(opts, "dtype", "float64") != "float64":
        raise SensitivityError(
            f"sensitivities are computed in float64 only (their linear systems are those of the steps); got "
            f"dtype={opts.dtype!r}: drop it, or solve in float64"
        )
    if model.events:
        raise SensitivityError(
            f"sensitivities: model '{model.name}' has events, across which the derivatives of the solution jump; "
            "daemodel does not differentiate through them yet: solve the span between two of them"
        )


def _on_fixed_branches(backend, model, t_span, start, opts, names) -> Solution:
    """The solve and its sensitivities for a model whose switches keep their branch over ``t_span``:
    on that branch the model is smooth and its solution is the model's, so are their derivatives (a
    parameter that moves a switch outside the span moves it nowhere near, to first order).  Refused
    where a time switch changes branch inside the span, the samples of a batch start on different
    branches, a switch on the variables is at zero at t0, or one crosses during the solve (checked at
    every step's nodes): across a switch the derivatives jump."""
    import numpy as np

    def refuse(what: str) -> SensitivityError:
        return SensitivityError(
            f"sensitivities: model '{model.name}' {what}, across which the derivatives of the solution jump; "
            "daemodel does not differentiate through switches yet: solve the span between two of them"
        )

    t0, t1 = (float(v) for v in t_span)
    P, Y0, Z0 = (np.asarray(a, dtype=float) for a in (start.p, start.y0, start.z0))
    on_states = [s for s in find_switches(model) if not s.time_only]
    values = model.numeric.batch_function([s.function for s in on_states]) if on_states else None
    branches = {}
    for b in range(len(P)):
        inside = breakpoints(model, t_span, P[b])
        if len(inside):
            raise refuse(f"has a time switch that changes branch at t = {inside[0]:.6g}, inside t_span")
        if on_states:
            at_t0 = values(np.array([t0]), Y0[b : b + 1], Z0[b : b + 1], P[b : b + 1])[0]
            for switch, value in zip(on_states, at_t0, strict=True):
                integer = switch.kind in ("floor", "ceiling")
                if (value == round(value)) if integer else value == 0:
                    raise refuse(f"starts on the switch {switch.describe()!r} (sample {b})")
        smooth = lock_branches(branch_model(model, 0.5 * (t0 + t1), P[b]), t0, Y0[b], Z0[b], P[b])
        branches.setdefault((smooth.rhs, tuple(c.chain for c in smooth.constraints)), (b, smooth))
    if len(branches) > 1:
        (first, _), (second, _) = list(branches.values())[:2]
        raise refuse(f"starts on other branches of its switches in samples {first} and {second}")
    ((_, smooth),) = branches.values()
    sol = backend.solve(for_method(smooth, backend), t_span, start, opts)
    if on_states:
        dense = sol.dense
        B, S, K, D = dense.nodes.shape
        n = len(sol.compiled.states)
        times = (dense.starts[:, None] + dense.lengths[:, None] * np.r_[0.0, dense.c][None, :]).ravel()
        U = dense.nodes.reshape(B, S * K, D).astype(float)
        F = values(
            np.tile(times, B), U[..., :n].reshape(-1, n), U[..., n:].reshape(B * S * K, -1), np.repeat(P, S * K, 0)
        )
        F = F.reshape(B, S * K, len(on_states))
        for q, switch in enumerate(on_states):
            side = np.floor(F[..., q]) if switch.kind in ("floor", "ceiling") else np.sign(F[..., q])
            moved = side != side[:, :1]
            if moved.any():
                b, k = np.argwhere(moved)[0]
                raise refuse(
                    f"crosses its switch {switch.describe()!r} between t = {times[k - 1]:.6g} and {times[k]:.6g} "
                    f"(sample {b})"
                )
    return with_sensitivities(sol, smooth, names)


def with_sensitivities(sol, model, names) -> Solution:
    """``sol`` with its forward sensitivities: generating their numeric Jacobians (once per model)
    added to ``setup_time``, the pass itself to ``solve_time``."""
    from daemodel.sensitivities import forward, prepare

    started = time.perf_counter()
    prepare(sol.compiled)
    prepared = time.perf_counter()
    where, values = forward(sol, names, model=model)
    seconds = time.perf_counter() - prepared
    return dataclasses.replace(
        sol,
        sensitivities={name: values[..., q] for q, name in enumerate(where.names)},
        setup_time=sol.setup_time + prepared - started,
        solve_time=sol.solve_time + seconds,
        stats={**sol.stats, "sensitivity_seconds": seconds},
    )


def check_options(backend, options: dict):
    """``backend.Options(**options)``, an unknown name being an :class:`UnknownOptionError` that
    lists the method's options (not the dataclass's TypeError)."""
    fields = {f.name for f in dataclasses.fields(backend.Options)}
    unknown = sorted(set(options) - fields)
    if unknown:
        raise UnknownOptionError(
            f"method {backend.name!r} has no option {', '.join(repr(u) for u in unknown)}; "
            f"its options are {', '.join(sorted(fields))}"
        )
    return backend.Options(**options)


def _pair(value):
    """``(float, float)`` from two real numbers (Python, numpy or sympy; no strings, no booleans), else None."""
    try:
        items = list(value)
    except TypeError:
        return None
    if len(items) != 2 or not all(is_real(v) for v in items):
        return None
    try:
        return real(items[0], "t0", finite=False), real(items[1], "t1", finite=False)
    except InvalidValueError:  # a sympy symbol: no number
        return None


def check_span(t_span, compiled) -> tuple[float, float]:
    """``(t0, t1)`` as floats, finite, increasing, starting at the model's initial time."""
    pair = None if isinstance(t_span, str | bytes | dict) else _pair(t_span)
    if pair is None:
        raise TimeSpanError(f"t_span must be a pair (t0, t1) of numbers; got {quoted(t_span, 60)}")
    t0, t1 = pair
    if not (math.isfinite(t0) and math.isfinite(t1)):
        raise TimeSpanError(f"t_span must be finite; got ({t0}, {t1})")
    if t1 <= t0:
        raise TimeSpanError(
            f"t_span = ({t0:g}, {t1:g}) is {'empty' if t1 == t0 else 'reversed'}; daemodel integrates "
            "forward in time: give t0 < t1"
        )
    if abs(t0 - compiled.t0) > 1e-12 * max(1.0, abs(t0)):
        raise TimeSpanError(
            f"t_span starts at {t0:g} but the initial values of '{compiled.name}' hold at t0 = {compiled.t0:g}; "
            f"start t_span there or declare m.initial(t={t0:g}, ...)"
        )
    return t0, t1

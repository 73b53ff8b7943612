"""A batch without ``t_eval`` whose model has events (``m.event``) or switches on its variables (``Max``,
``Min``, ``Piecewise`` of the states): its events and switches located in each sample, as one sample alone or
a batch on ``t_eval`` has them (a batch with events was refused: "pass t_eval").

A batch's samples cross their switches at times of their own, and share output times only where the user
gives them (``t_eval``).  Without it the batch stepped across its switches instead of locating them, its
steps' error estimate blind to the kink: x' = -Min(1, x) from x0 = 1.5, 2, 2.3 over [0, 3] at the default
tolerance ended up to 7.8e-8 off (one at a time: 8e-12), "success".  Now each sample is solved alone with
its switches located, and the batch is solved again on the output times of all of them (each sample's own
steps and switch instants, so that every sample's kink is an output time), as a batch on ``t_eval`` is.
That is about twice the work of the samples solved one at a time (``stats["samples_alone_steps"]`` counts
the first pass's steps): 50 samples of that model 2.4 s where stepping across took 0.9 s and t_eval
(31 times) 0.9 s (benchmarks/batch_switches.json, minima of 3 passes).
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np


def solve_on_common_times(backend, located, t_span, start, options, max_events: int):
    """:func:`~daemodel.solving.events.solve_with_events` of a batch without ``t_eval`` (``options`` with a
    ``t_eval`` field): each sample alone, then all on the union of their output times (module docstring).

    Raises
    ------
    ResourceLimitError
        The outputs on the union of the samples' times (samples x times x variables) exceed the memory limit:
        pass t_eval.
    """
    from daemodel.backends.checks import check_output_memory
    from daemodel.compiling.initial_states import InitialStates
    from daemodel.solving.events import solve_with_events

    times, steps = [], 0
    for b in range(len(start.p)):
        one = InitialStates(y0=start.y0[b : b + 1], z0=start.z0[b : b + 1], p=start.p[b : b + 1], batched=True)
        with warnings.catch_warnings():  # (the solve on the common times says them again)
            warnings.simplefilter("ignore")
            alone = solve_with_events(backend, located, t_span, one, options, max_events)
        times.append(np.asarray(alone.t))
        steps += int(alone.stats.get("steps", 0))
    grid = np.unique(np.concatenate(times))
    check_output_memory(backend.name, located, len(start.p), len(grid))
    sol = solve_with_events(backend, located, t_span, start, dataclasses.replace(options, t_eval=grid), max_events)
    # (the samples alone, which chose the times, apart from the solve on them: stats["steps"] is that solve's)
    return dataclasses.replace(sol, stats=sol.stats.extended(samples_alone_steps=steps))

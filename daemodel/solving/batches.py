"""A batch without ``t_eval`` whose model has events (``m.event``) or switches on its variables (``Max``,
``Min``, ``Piecewise`` of the states): each sample's events and switches located, as one sample alone or a
batch on ``t_eval`` has them.

A batch's samples cross their switches and fire their events at times of their own, and share output times
only where the user gives them (``t_eval``).  Without it the batch stepped across its switches instead of
locating them, its steps' error estimate blind to the kink: x' = -Min(1, x) from x0 = 1.5, 2, 2.3 over [0, 3]
at the default tolerance ended up to 7.8e-8 off (one at a time: 8e-12), "success"; and a batch with declared
events was refused.  Now each sample is solved alone with its events and switches located, and the batch's
output times are all of theirs (each sample's own steps and event instants, so that every sample's kink is an
output time).  Each sample's values at the others' times are read off its dense output where reading it is an
evaluation (radau's, casadi-collocation's collocation polynomials): the values ``t_eval`` gives, for radau the
same evaluation of the same steps.  Where it is not (a method started again from an output: casadi-idas, the
reference; ``dense_output=False``), the samples are solved again on those times, as a batch on ``t_eval`` is:
about twice the work (``stats["samples_alone_steps"]`` counts the first pass's steps, ``samples_alone_setup`` and
``samples_alone_solve`` its seconds, on the call's clocks too; where nothing is solved
again it is ``stats["steps"]``); a method without ``t_eval`` (plugged in) whose samples' times differ cannot be
read there: :class:`~daemodel.errors.SwitchError` (it stepped across a batch's switches: x' = -Min(1, x) 2.7
tolerances off at rtol 1e-10, "success").  A terminal event ends its sample's values there (NaN after it,
``stats["t_end"]``).  50 samples of x' = -Min(1, x) over (0, 3) at the default tolerance: 823 steps and 0.53 s
where the samples alone and again on the union took 1,214 and 1.10 s, the same values (minima of 3 interleaved
passes on a shared machine: benchmarks/batch_switches.json).
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np


def solve_on_common_times(backend, located, t_span, start, options, max_events: int):
    """:func:`~daemodel.solving.events.solve_with_events` of a batch without ``t_eval`` (``options`` with a
    ``t_eval`` field): each sample alone, joined on the union of their output times (module docstring).

    Raises
    ------
    ResourceLimitError
        The outputs on the union of the samples' times (samples x times x variables) exceed the memory limit:
        pass t_eval.
    SwitchError
        A method without ``t_eval`` whose samples' outputs do not share times, and cannot be read between them.
    """
    from daemodel.backends.checks import check_output_memory
    from daemodel.compiling.initial_states import InitialStates
    from daemodel.errors import SwitchError
    from daemodel.solving.events import solve_with_events
    from daemodel.solving.pieces import join_samples

    parts, steps = [], 0
    with warnings.catch_warnings(record=True) as caught:  # (said once, below: by the solve that is kept)
        warnings.simplefilter("always")
        for b in range(len(start.p)):
            one = InitialStates(y0=start.y0[b : b + 1], z0=start.z0[b : b + 1], p=start.p[b : b + 1], batched=True)
            alone = solve_with_events(backend, located, t_span, one, options, max_events)
            parts.append((np.array([b]), alone))
            steps += int(alone.stats.get("steps", 0))
    grid = np.unique(np.concatenate([np.asarray(sol.t) for _, sol in parts]))
    check_output_memory(backend.name, located, len(start.p), len(grid))
    if all(sol.dense is not None and not sol.dense.solves_again for _, sol in parts):
        for warning in caught:
            warnings.warn(warning.message, warning.category, stacklevel=4)
        sol = join_samples(parts, len(start.p), start.batched)
        return dataclasses.replace(sol, stats=sol.stats.extended(samples_alone_steps=steps))
    if "t_eval" not in {f.name for f in dataclasses.fields(options)}:
        if any(len(sol.t) != len(grid) for _, sol in parts):
            raise SwitchError(
                f"a batch of {len(start.p)} samples with events or switches on its variables: each sample's are "
                f"located alone, but their outputs do not share times, and method {backend.name!r} has no t_eval "
                "and no dense output to give each one's values at the others': solve the samples one at a time"
            )
        return join_samples(parts, len(start.p), start.batched)
    sol = solve_with_events(backend, located, t_span, start, dataclasses.replace(options, t_eval=grid), max_events)
    # (the samples alone, which chose the times, apart from the solve on them: stats["steps"] is that solve's; their
    # clocks added to its, so that the code they made at its first use is setup: it was on neither, and the call's
    # wall time left to within_clocks put it on the solve's, 0.3 s made slower of casadi-idas's events' code)
    setup, solve = sum(one.setup_time for _, one in parts), sum(one.solve_time for _, one in parts)
    stats = sol.stats.extended(samples_alone_steps=steps, samples_alone_setup=setup, samples_alone_solve=solve)
    return dataclasses.replace(sol, setup_time=sol.setup_time + setup, solve_time=sol.solve_time + solve, stats=stats)

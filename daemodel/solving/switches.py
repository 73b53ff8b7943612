"""Solving from one time breakpoint to the next.

Across a breakpoint no method keeps its order: a step whose stages straddle the switch sees two
different right-hand sides, and the step that ends at it evaluates its last stage (c_s = 1) on the
branch after it.  :func:`solve_with_breakpoints` therefore integrates from breakpoint to
breakpoint, each segment on a model whose time switches are fixed to the branch of the segment's
interior (:func:`daemodel.compiling.switches.branch_model`: the switch decided at the segment's
midpoint), so that each side is evaluated with its own branch, the left limit included; at each
breakpoint the states carry over and the algebraic variables are solved anew (the branch may move
them).  Every method gets this, fixed steps with the grid cut at the breakpoints (each segment split
into equal steps no longer than ``h``), so that order 2s-1 holds across them.  The switches
themselves are found and classified in :mod:`daemodel.compiling.switches`.
"""

from __future__ import annotations

import dataclasses
import itertools
import time

import numpy as np

from daemodel.compiling.batch_function import claim_generated, generating_seconds
from daemodel.compiling.switches import branch_model, breakpoints, merge_tol
from daemodel.dense import joined_in_time
from daemodel.errors import SwitchError
from daemodel.solving.pieces import join_samples, merge_stats, onto_constraints, segment_steps


def for_method(compiled, backend):
    """``compiled`` reduced to the highest index ``backend`` takes (itself where it takes it)."""
    return compiled.reduced(backend.max_index) if compiled.index > backend.max_index else compiled


def settings_as_given(sol, options) -> dict:
    """``sol``'s settings with ``t_eval`` and ``h`` as the user gave them (a piece's were its own)."""
    settings = dict(sol.settings)
    for key in ("t_eval", "h"):
        if key in settings:
            settings[key] = getattr(options, key)
    return settings


def solve_with_breakpoints(backend, compiled, t_span, start, options):
    """Solve from breakpoint to breakpoint (see the module docstring): each segment on
    :func:`branch_model` at its midpoint (reduced to the index ``backend`` takes), the states
    carried over (projected onto the constraints where a switch inside one moved them), the
    algebraic variables solved anew at each breakpoint; one :class:`~daemodel.solution.Solution`
    of them all, whose values at a breakpoint are those after it (:attr:`Solution.breakpoints`
    holds both sides).  Samples of a batch whose parameters move the breakpoints are solved in
    groups that share them, on the common output times ``t_eval``.  ``compiled`` is the model as
    compiled, before any reduction: a switch inside a constraint that the reduction differentiates
    away is still a breakpoint.

    Raises
    ------
    SwitchError
        The samples of a batch switch at different times and no ``t_eval`` gives them common
        output times.
    """
    from daemodel.compiling.initial_states import InitialStates

    P = np.asarray(start.p, dtype=float)
    groups: dict = {}
    began = time.perf_counter()  # (finding the breakpoints, kept with the model: setup, as the model's code is)
    for b in range(len(P)):
        times = breakpoints(compiled, t_span, P[b])
        key = next((k for k in groups if _same(k, times, t_span)), None)
        groups.setdefault(key if key is not None else tuple(times.tolist()), []).append(b)
    found = time.perf_counter() - began
    if len(groups) == 1:
        sol = _solve_segments(backend, compiled, t_span, start, options, np.asarray(next(iter(groups))))
        return dataclasses.replace(sol, setup_time=sol.setup_time + found)
    if getattr(options, "t_eval", None) is None:
        (first, one), (second, other) = list(groups.items())[:2]
        raise SwitchError(
            f"the samples of this batch switch at different times (sample {one[0]}: {_times(np.asarray(first))}; "
            f"sample {other[0]}: {_times(np.asarray(second))}): their parameters move the breakpoints, so their steps "
            "differ; pass t_eval to have them on common output times, or solve them one at a time"
        )
    parts = []
    for times, members in groups.items():
        index = np.asarray(members)
        sub = InitialStates(y0=start.y0[index], z0=start.z0[index], p=start.p[index], batched=True)
        parts.append((index, _solve_segments(backend, compiled, t_span, sub, options, np.asarray(times))))
    sol = join_samples(parts, len(P), start.batched)
    return dataclasses.replace(sol, setup_time=sol.setup_time + found)


def _same(key: tuple, times: np.ndarray, t_span) -> bool:
    tol = merge_tol(*(float(v) for v in t_span))
    return len(key) == len(times) and bool(np.all(np.abs(np.asarray(key) - times) <= tol))


def _solve_segments(backend, compiled, t_span, start, options, times: np.ndarray):
    """The samples of ``start``, which share the breakpoints ``times``, from one to the next."""
    from daemodel.backends.grids import output_times
    from daemodel.compiling.initial_states import InitialStates, algebraic_values
    from daemodel.solution import Solution

    t0, t1 = t_span
    made = generating_seconds()  # (code made at its first use, each segment's branch check: setup, not solve)
    moved = []  # (B,) per breakpoint: how far the states were projected there
    solved = for_method(compiled, backend)
    P = np.asarray(start.p, dtype=float)
    edges = [t0, *times.tolist(), t1]
    user_grid = None if getattr(options, "t_eval", None) is None else output_times(options.t_eval, t_span, ())
    h = getattr(options, "h", None)
    Y, Z = np.asarray(start.y0, dtype=float), np.asarray(start.z0, dtype=float)
    names = (*compiled.state_names, *compiled.algebraic_names)
    parts, pre, post = [], [], []
    for k, (a, b) in enumerate(itertools.pairwise(edges)):
        last = k == len(edges) - 2
        whole = branch_model(compiled, 0.5 * (a + b), P[0])
        model = for_method(whole, backend)
        if k:  # the states carry over (projected where a switch moved the constraints); z follows the branch
            projected = onto_constraints(dataclasses.replace(whole, t0=float(a)), Y, P)
            moved.append(np.max(np.abs(projected - Y), axis=1, initial=0.0))
            Y = projected
            Z = algebraic_values(model, a, Y, P, Z)
            post.append(np.concatenate([Y, Z], axis=1))
        model = dataclasses.replace(model, t0=float(a), y0=Y[0].copy(), z0=Z[0].copy())
        changes, unseen = {}, False
        if user_grid is not None:
            inside = user_grid[(user_grid >= a) & ((user_grid <= b) if last else (user_grid < b))]
            # (a last segment with no output time in it, a piece before an event: solved to b, b not shown)
            unseen = last and not len(inside)
            changes["t_eval"] = np.concatenate([inside, [b]]) if not last or unseen else inside
        if h is not None:
            changes["h"] = segment_steps(a, b, h)
        segment_start = InitialStates(y0=Y, z0=Z, p=P, batched=start.batched)
        sol = backend.solve(model, (float(a), float(b)), segment_start, dataclasses.replace(options, **changes))
        end = np.stack([np.asarray(sol.values[name])[:, -1] for name in names], axis=-1)
        Y, Z = end[:, : len(compiled.states)].copy(), end[:, len(compiled.states) :].copy()
        keep = np.full(len(sol.t), not unseen)
        if not last:
            pre.append(end)
            keep[-1] = False  # (the breakpoint's values are the next segment's: after the switch)
        parts.append((sol, keep))
    t = np.concatenate([sol.t[keep] for sol, keep in parts])
    values = {
        name: np.concatenate([np.asarray(sol.values[name])[:, keep] for sol, keep in parts], axis=1)
        for name in parts[0][0].values
    }
    failing = [
        f"on [{a:.6g}, {b:.6g}]: {sol.status}"
        for (sol, _), (a, b) in zip(parts, itertools.pairwise(edges), strict=True)
        if sol.status != "success"
    ]
    stats = merge_stats([sol.stats for sol, _ in parts])
    stats["segments"] = len(parts)
    settings = settings_as_given(parts[0][0], options)
    B = len(P)
    record = {
        "t": np.repeat(times[None, :], B, axis=0),
        "moved": np.stack(moved, axis=-1) if moved else np.zeros((B, 0)),
        "before": {
            name: np.stack([v[:, j] for v in pre], axis=-1) if pre else np.zeros((B, 0)) for j, name in enumerate(names)
        },
        "after": {
            name: np.stack([v[:, j] for v in post], axis=-1) if post else np.zeros((B, 0))
            for j, name in enumerate(names)
        },
    }
    return Solution(
        t=t,
        values=values,
        method=parts[0][0].method,
        settings=settings,
        solve_time=sum(sol.solve_time for sol, _ in parts),
        stats=stats,
        compiled=solved,
        parameters=parts[0][0].parameters,
        batched=parts[0][0].batched,
        status="success" if not failing else "; ".join(failing),
        setup_time=sum(sol.setup_time for sol, _ in parts) + claim_generated(made),
        breakpoints=record,
        dense=joined_in_time(edges, [sol.dense for sol, _ in parts]),
    )


def _times(times: np.ndarray) -> str:
    shown = ", ".join(f"{v:.6g}" for v in times[:5])
    return f"[{shown}{', ...' if len(times) > 5 else ''}]" if len(times) else "none"

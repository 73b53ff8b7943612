"""Adaptive steps' outputs of the algebraic variables of a system of index 2 (or 3, reduced): solved again
from the returned states (:mod:`daemodel.compiling.algebraic`), the collocation's distance from them
reported as the estimate of the collocation's error.

Adaptive steps weigh an index-2 variable's error estimate by h, as RADAU5 does (its stage values are
of order s where the states' step ends are of order 2s - 1), so its collocation values at the outputs
were several tolerances off while the status said success.  Weighing it unscaled instead would cost
steps of order s for every variable; solving it from the states costs one batched Newton solve of
small systems at the outputs (linear in z in mechanics: one step, a casadi function made in the setup,
:class:`~daemodel.compiling.algebraic.AffineStep`).  Fixed steps keep the collocation
solution (what ``h`` asks for, and what the Radau-PINN's certificate measures against): their
estimate already reads an index-2 variable unweighted (:meth:`.error.ErrorEstimate.check_fixed`).
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
from daemodel.backends.base import caller_level

from daemodel.compiling.algebraic import algebraic_from_states, resolves_algebraic
from daemodel.compiling.algebraic import prepare as prepare_algebraic
from daemodel.compiling.batch_function import claim_generated, generating_seconds
from daemodel.errors import LocalErrorWarning


def resolved_outputs(options, compiled) -> bool:
    """Whether a solve of ``compiled`` with ``options`` solves its algebraic variables from the states at its
    outputs (adaptive steps on a system with some of index 2 or more), and its dense output between them."""
    return options.adaptive and resolves_algebraic(compiled)


def prepare_outputs(options, compiled) -> None:
    """In a solve's setup: make what the solve at the outputs evaluates (:func:`daemodel.compiling.algebraic.prepare`,
    once per model; the numpy code only where there is no affine step), where the solve resolves them.  solve()
    prepared its model, but the pieces between breakpoints and events are models of their own, whose affine step
    (0.1-1.6 s for chains of 20 to 199 pendulums) was made at their first solve at the outputs, on the solve clock.
    Claimed here (counted in this setup, not again by a caller that moves code made at first use into its own)."""
    if resolved_outputs(options, compiled):
        made = generating_seconds()
        prepare_algebraic(compiled, numpy=False)
        claim_generated(made)


def marked(dense, resolved: bool):
    """The dense output ``dense`` (None, or the steps' collocation polynomials), marked where ``resolved`` so
    that :meth:`~daemodel.solution.Solution.at` solves the algebraic variables from its states between the
    outputs too (``resolves_algebraic``)."""
    return dataclasses.replace(dense, resolves_algebraic=True) if resolved and dense is not None else dense


def resolve_outputs(method: str, compiled, start, options, times, values, stats):
    """``(values, flag, signs)``: ``values`` (B, T, n+m) of an adaptive solve with the algebraic variables
    solved from the states at every output where the system has some of index 2 or more (else as
    given), None, or a "flagged: ..." status naming the first output where Newton failed (its
    collocation values kept, their error not estimated), and ``sign(det H_z)`` (B, T) at the outputs
    where the solve read it (:class:`~daemodel.compiling.algebraic.Resolved`; the branch check's, NaN where
    not known) or None.

    Where they were solved again, adds to ``stats``: ``algebraic_resolved`` (True),
    ``algebraic_correction``, the largest ``|z_collocation - z| / (atol + rtol |z|)`` over the outputs
    (the collocation values' error, estimated) and ``algebraic_correction_at`` (the variable, time and
    sample where it is).
    """
    if not resolved_outputs(options, compiled):
        return values, None, None
    n = len(compiled.states)
    values = np.array(values, dtype=float)  # (a copy: the stepper's arrays stay its own)
    times = np.asarray(times, dtype=float)
    collocation = values[..., n:].copy()
    found = algebraic_from_states(compiled, times, values[..., :n], collocation, start.p)
    values[..., n:] = found.z
    change = np.abs(collocation - found.z) / (options.atol + options.rtol * np.abs(found.z))
    converged = found.converged.all()
    change = change if converged else np.where(found.converged[..., None], change, 0.0)
    stats["algebraic_resolved"] = True
    stats["algebraic_correction"] = float(change.max(initial=0.0))
    if change.size:
        sample, k, j = np.unravel_index(int(np.argmax(change)), change.shape)
        where = f"'{compiled.algebraic_names[j]}' at t = {times[k]:.6g}"
        stats["algebraic_correction_at"] = where + (f", sample {sample}" if change.shape[0] > 1 else "")
    if converged:
        return values, None, found.signs
    sample, k = np.argwhere(~found.converged)[0]
    count = int((~found.converged).sum())
    flag = (
        f"flagged: {method}: the algebraic variables could not be solved from the states at t = {times[k]:.6g}"
        + (f" (sample {sample})" if found.converged.shape[0] > 1 else "")
        + f" and {count - 1} more output(s): their values there are the collocation's, whose error (index 2: of "
        "order s, weighed by h in the step control) may exceed rtol and atol; compare with a tighter rtol"
    )
    warnings.warn(flag, LocalErrorWarning, stacklevel=caller_level())
    return values, flag, found.signs

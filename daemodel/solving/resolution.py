"""Whether float64 resolves t finely enough for the solution's tolerance, for every method.

A method evaluates f and g at times t + c h, which float64 rounds to the spacing of t there: at t = 1e13
that is 2e-3 (at 1e9, 1.2e-7).  Where f depends on t itself, each stage then sees f a little off, by up
to |df/dt| times half that spacing, and no error estimate can see it (the stages are solved exactly for
that rounded f).  Over the span the states can move by up to

    E = sum over output intervals of (t_(k+1) - t_k) |df/dt| spacing(t) / 2

(y' = cos(t) from t0 = 1e13 over 2: E = 2e-3; radau at rtol 1e-8 ended 1.7e-5 off, IDAS 1.7e-5, the PINN at
h = 0.1 2.5e-4, each "success" before).  ``df/dt`` is read off f at the middle of each output interval,
a few spacings either side, with the states held (the methods that choose steps, radau and IDAS, now
step by what t's spacing makes of them: a model that does not name t is not moved by it).  Where E exceeds
the tolerance (``atol + rtol max|u|``; without ``rtol``, what a fixed step's or the PINN's own local error
estimates add up to: :func:`tolerance`) the solution is flagged with
:class:`~daemodel.errors.TimeResolutionWarning`, never "success"; the fix is to count time from near the
start (``t - t0`` in the model).

The algebraic variables move with t where the equations that determine them name it (to first order,
:func:`_held_roots`), and f with them; at the output times themselves t is exact (a step ends where t + h
rounds, and the methods' outputs are read there).  What this does not see: the
growth of an error by the flow after it arises (the bound adds the errors as they arise), and a span near
t = 0 (:data:`SPAN_RATIO`).
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np

from daemodel.errors import TimeResolutionWarning

# t's rounding is judged where |t| exceeds this many times the span: nearer 0, t's spacing is float64's
# resolution of the span itself (t's relative rounding over [0, t1]), which no choice of time's origin improves;
# and a model's first check reads every right-hand side for t (0.1 s at 10^4 equations, then kept).
SPAN_RATIO = 1.0
# df/dt is read in this many intervals at least (outputs far apart are cut into pieces).
MIN_INTERVALS = 64
# df/dt is read over this many spacings of t either side of an interval's middle (fewer where the interval
# is shorter): enough that the difference is not f's own rounding, few enough to stay local.
SPACINGS = 16
# A fixed step's and the PINN's tolerance where they keep no estimate (backends.base.DEFAULT_ESTIMATE_BOUND).
DEFAULT_BOUND = 1e-3
# A fixed step's tolerance, in units of 1 + max|u|, is at least this (its estimates at rounding are not its
# accuracy: y' = t is exact for radau, its estimates 1e-17).
FIXED_FLOOR = 1e-12


def explicit_time(compiled) -> bool:
    """Whether the right-hand sides of ``compiled``, or the equations that determine its algebraic variables,
    name t (made once per model)."""

    def build():
        exprs = (*compiled.rhs, *(c.determining for c in compiled.constraints))
        return any(compiled.t in e.free_symbols for e in exprs)

    return compiled.cached("names-t", build)


def rounding_bound(sol, compiled):
    """``(E, tol, time)``: the bound E (B, n) on what t's rounding moved each state by (module docstring), the
    tolerance (B, n) it is held to, and the time of each one's largest contribution (B, n); None where
    t is not large against the span (:data:`SPAN_RATIO`), the model does not name t or there is no interval."""
    t = np.asarray(sol.t, dtype=float)
    if len(t) < 2 or max(abs(t[0]), abs(t[-1])) <= SPAN_RATIO * (t[-1] - t[0]):
        return None
    if not explicit_time(compiled):
        return None
    n, names = len(compiled.states), (*compiled.state_names, *compiled.algebraic_names)
    B = np.asarray(sol.parameters).shape[0]
    U = np.stack([np.asarray(sol.values[name], dtype=float).reshape(B, len(t)) for name in names], axis=-1)
    keep = t[1:] > t[:-1]  # (an event's instant is two outputs at one time)
    if not keep.any():
        return None
    # each interval cut into `pieces` (at least MIN_INTERVALS in all: t_eval=[t0, t1] would read df/dt once),
    # the values between its ends linear (f's t alone moves: the states only place the reading)
    pieces = -(-MIN_INTERVALS // int(keep.sum()))
    w = (np.arange(pieces) + 0.5) / pieces  # (the pieces' middles, as fractions of their interval)
    ends = t[:-1][keep][:, None] + np.diff(t)[keep][:, None] * np.arange(pieces + 1) / pieces
    a, b = ends[:, :-1].ravel(), np.maximum(ends[:, 1:], ends[:, :-1]).ravel()
    left, right = U[:, :-1][:, keep], U[:, 1:][:, keep]  # (B, k, D)
    middle = (left[:, :, None] * (1 - w)[None, None, :, None] + right[:, :, None] * w[None, None, :, None]).reshape(
        B, len(a), -1
    )
    h, K = b - a, len(a)
    dtype = np.float32 if sol.settings.get("dtype") == "float32" else np.float64
    spacing = np.spacing(np.maximum(np.abs(a), np.abs(b)).astype(dtype)).astype(float)
    width = np.maximum(np.minimum(SPACINGS * spacing, 0.25 * h), spacing)
    before, after = np.tile(a + 0.5 * h - width, B), np.tile(a + 0.5 * h + width, B)
    P = np.repeat(np.asarray(sol.parameters, dtype=float), K, axis=0)
    Y, Z = middle[..., :n].reshape(B * K, n), middle[..., n:].reshape(B * K, -1)
    with np.errstate(all="ignore"):
        Z_before, Z_after = _held_roots(compiled, before, after, Y, Z, P)
        rhs = compiled.numeric.batch_function(list(compiled.rhs))
        change = rhs(after, Y, Z_after, P) - rhs(before, Y, Z_before, P)
        rate = np.abs(change).reshape(B, K, n) / (after - before).reshape(B, K, 1)
        moved = np.nan_to_num(h[None, :, None] * rate * (0.5 * spacing)[None, :, None], nan=0.0)
    size = np.nanmax(np.abs(U[..., :n]), axis=1, initial=0.0)
    return moved.sum(axis=1), tolerance(sol, size, int(keep.sum())), a[np.argmax(moved, axis=1)]


def _held_roots(compiled, before, after, Y, Z, P):
    """The algebraic variables at the times ``before`` and ``after`` with the states held: Z moved by the
    equations that determine it, ``H(t, y, z) = 0``, to first order (one Newton step from Z at each time:
    ``-H_z^-1 H``, the same matrix); Z itself where none names t."""
    if not compiled.algebraics or not any(compiled.t in c.determining.free_symbols for c in compiled.constraints):
        return Z, Z
    from daemodel.compiling.linear import SparseStack, least_squares

    numeric = compiled.numeric
    determining = [c.determining for c in compiled.constraints]
    H, Hz = numeric.batch_function(determining), numeric.newton_jacobian(determining, compiled.algebraics)
    J = Hz(0.5 * (before + after), Y, Z, P)
    shifts = []
    for when in (before, after):
        residual = -H(when, Y, Z, P)
        shifts.append(Z + (J.solve(residual) if isinstance(J, SparseStack) else least_squares(J, residual)))
    return tuple(shifts)


def tolerance(sol, size, intervals: int):
    """What ``sol`` holds its states (B, n) to: ``atol + rtol max|u|`` (``size``: max|u|); without rtol (a
    fixed step, the PINN) what its own local error estimates add up to over its steps, in units of
    ``1 + max|u|`` and at least :data:`FIXED_FLOOR` of it (the bound on the estimate, ``estimate_bound``,
    where a method keeps no estimate)."""
    settings, stats = sol.settings, sol.stats
    rtol, atol = settings.get("rtol"), settings.get("atol")
    if rtol is not None and atol is not None:
        return float(atol) + float(rtol) * size
    estimate = stats.get("max_local_error_estimate")
    if estimate is None:  # (the PINN keeps radau's estimate at its h with its certificate)
        estimate = (stats.get("certificate") or {}).get("max_local_error_estimate")
    if estimate is None or not np.isfinite(estimate):
        return float(settings.get("estimate_bound") or DEFAULT_BOUND) * (1.0 + size)
    steps = stats.get("steps") or intervals
    return max(float(estimate) * steps, FIXED_FLOOR) * (1.0 + size)


def flag_time_rounding(sol, compiled=None):
    """``sol``, flagged (status ``"flagged: ..."`` and a :class:`~daemodel.errors.TimeResolutionWarning`)
    where t's rounding may have moved a state by more than its tolerance (:func:`rounding_bound`)."""
    compiled = sol.compiled if compiled is None else compiled
    found = rounding_bound(sol, compiled)
    if found is None:
        return sol
    E, tol, where = found
    ratio = E / tol
    if not (ratio.max(initial=0.0) > 1.0):
        return sol
    sample, k = np.unravel_index(int(np.argmax(ratio)), ratio.shape)
    at = float(where[sample, k])
    spacing = float(np.spacing(abs(at)))
    message = (
        f"flagged: t's float64 spacing ({spacing:.3g} near t = {at:.6g}) may move '{compiled.state_names[k]}' by "
        f"up to {E[sample, k]:.3g} (|df/dt| over the span times half that spacing), {ratio[sample, k]:.3g} times "
        f"its tolerance {tol[sample, k]:.3g}" + (f" (sample {sample})" if ratio.shape[0] > 1 else "") + ": count "
        "time from near the start (t - t0 in the model) or loosen the tolerance"
    )
    from daemodel.backends.base import caller_level

    warnings.warn(message, TimeResolutionWarning, stacklevel=caller_level())
    status = message if sol.status == "success" else f"{sol.status}; {message}"
    return dataclasses.replace(sol, status=status)

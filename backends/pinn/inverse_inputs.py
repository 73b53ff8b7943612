"""The inputs of the PINN's inverse mode (:mod:`.inverse`), checked before any training: the data
times and values, the fitted parameters with their start values and bounds (:class:`Transform`
keeps every value inside its bounds), and the constraints that a fitted parameter may not enter.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from daemodel.errors import FittedConstraintError, InvalidOptionError, ShapeError, TimeSpanError


@dataclass(frozen=True)
class Transform:
    """Each fitted parameter ``p = low + (high - low) sigmoid(q)`` (two finite bounds), ``low +
    exp(q)`` or ``high - exp(q)`` (one), or ``q`` (none): any q keeps p inside its bounds."""

    low: np.ndarray
    high: np.ndarray

    def to_parameters(self, q):
        finite_low = torch.as_tensor(np.isfinite(self.low))
        finite_high = torch.as_tensor(np.isfinite(self.high))
        # infinite bounds replaced by 0 in the branches that do not use them: torch.where's
        # unused branch still takes part in the gradient (0 * inf is NaN)
        low = torch.as_tensor(np.where(np.isfinite(self.low), self.low, 0.0), dtype=q.dtype)
        high = torch.as_tensor(np.where(np.isfinite(self.high), self.high, 0.0), dtype=q.dtype)
        return torch.where(
            finite_low & finite_high,
            low + (high - low) * torch.sigmoid(q),
            torch.where(finite_low, low + torch.exp(q), torch.where(finite_high, high - torch.exp(q), q)),
        )

    def to_q(self, p: np.ndarray) -> np.ndarray:
        low, high, p = self.low, self.high, np.asarray(p, dtype=float)
        q = p.copy()
        with np.errstate(divide="ignore", invalid="ignore"):
            both = np.isfinite(low) & np.isfinite(high)
            q = np.where(both, np.log((p - low) / (high - p)), q)
            q = np.where(np.isfinite(low) & ~np.isfinite(high), np.log(p - low), q)
            q = np.where(~np.isfinite(low) & np.isfinite(high), np.log(high - p), q)
        return q


def check_inputs(compiled, t_span, times, data, names, start, bounds):
    """The inputs of :func:`~daemodel.backends.pinn.inverse.fit_inverse`, checked, each mistake a
    named error.  Returns arrays: times (T,), the output columns (indices into states then algebraics), the
    data (T, outputs) with NaN where missing, the fitted parameters' indices, start, low, high."""
    variables = (*compiled.state_names, *compiled.algebraic_names)
    t0, t1 = (float(t) for t in t_span)
    times = np.asarray(times, dtype=float)
    if times.ndim != 1 or times.size == 0:
        raise ShapeError(f"times must be a 1-d array of at least one time; got shape {times.shape}")
    if not np.all(np.isfinite(times)) or np.any(np.diff(times) < 0):
        raise TimeSpanError("times must be finite and sorted ascending")
    if times[0] < t0 or times[-1] > t1:
        raise TimeSpanError(
            f"times run from {times[0]:g} to {times[-1]:g}, outside t_span ({t0:g}, {t1:g}): fit over a t_span "
            "that holds every data time"
        )
    if not isinstance(data, dict) or not data:
        raise ShapeError("data must be a dict output name -> array of values at times (NaN where missing)")
    unknown = [name for name in data if name not in variables]
    if unknown:
        raise ShapeError(
            f"data names {', '.join(map(repr, unknown))}, not a variable of model '{compiled.name}' "
            f"(its variables: {', '.join(variables)})"
        )
    columns = [variables.index(name) for name in data]
    values = []
    for name in data:
        column = np.asarray(data[name], dtype=float)
        if column.shape != times.shape:
            raise ShapeError(f"data['{name}'] has shape {column.shape}; times has {times.shape}: one value per time")
        if np.isinf(column).any():
            raise ShapeError(f"data['{name}'] holds an infinite value; mark a missing one with NaN")
        values.append(column)
    values = np.stack(values, axis=1)
    if not np.isfinite(values).any():
        raise ShapeError("data holds no finite value (every entry is NaN): nothing to fit")
    names = tuple(names)
    missing = [name for name in names if name not in compiled.parameter_names]
    if missing or not names or len(set(names)) != len(names):
        raise ShapeError(
            f"names must be distinct parameters of model '{compiled.name}' ({', '.join(compiled.parameter_names)}); "
            f"got {names}"
        )
    k = len(names)
    start = np.asarray(start, dtype=float).reshape(-1)
    low, high = (np.broadcast_to(np.asarray(b, dtype=float), (k,)).copy() for b in bounds)
    if start.shape != (k,) or not np.all(np.isfinite(start)):
        raise ShapeError(f"start must hold {k} finite values, one per name in {names}; got {start}")
    outside = [i for i in range(k) if not low[i] < start[i] < high[i]]
    if outside:
        i = outside[0]
        raise InvalidOptionError(
            f"the start value of '{names[i]}', {start[i]:g}, is not strictly inside its bounds ({low[i]:g}, "
            f"{high[i]:g}): the fit moves each parameter inside its bounds only; start inside them"
        )
    indices = np.array([compiled.parameter_names.index(name) for name in names])
    return times, columns, values, indices, start, low, high


def check_constraints(compiled, names):
    """Refuse a z-free constraint level (an index-2 constraint, or an index-3 one's position and
    velocity levels) that depends on a fitted parameter: the given initial states satisfy it at
    the start value only, so every other value would start inconsistently (the fit does not move
    y0).  A constraint that holds z (index 1) is fine: z0 follows the parameters."""
    from daemodel.compiling.init import hidden_constraints

    fitted = {symbol for symbol in compiled.parameters if str(symbol) in names}
    for _, label, expr in hidden_constraints(compiled.constraints):
        used = sorted(str(s) for s in expr.free_symbols & fitted)
        if used:
            raise FittedConstraintError(
                f"{label} involves the fitted parameter{'s' if len(used) > 1 else ''} {', '.join(map(repr, used))} "
                "and no algebraic variable: the initial states satisfy it at the start value only, and the fit "
                "does not move them; fit a model whose initial states follow the parameter (declare it in the "
                "initial values), or fix the parameter"
            )

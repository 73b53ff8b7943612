"""A surrogate's training states: drawn from a box of initial states (and parameter values),
projected onto the constraints, with their consistent algebraic values (``Surrogate.train``)."""

from __future__ import annotations

import numpy as np

from daemodel.errors import InconsistentInitialStateError, InvalidOptionError, ShapeError, UnknownSymbolError


def draw_training_states(model, compiled, box: dict, parameter_box: dict, samples: int, seed: int) -> tuple:
    """``samples`` consistent initial states drawn from a box (a Sobol sequence scrambled with
    ``seed``), for ``Surrogate.train``.

    Parameters
    ----------
    model : Model or CompiledDAE
        As the user declared it (checked against the box before any index reduction).
    compiled : CompiledDAE
        The model the networks solve (:func:`~daemodel.backends.pinn.segments.resolve_model`'s).
    box, parameter_box : dict name -> (low, high)
        The ranges of the initial states and of the parameters that become network inputs.
    samples, seed : int

    Returns
    -------
    (y (B, n), z (B, m), p (B, k), inputs)
        The states projected onto the constraints, their algebraic values, the parameters, and
        the names of the parameters that are network inputs.
    """
    from scipy.stats import qmc

    from daemodel.compiling.compiler import as_compiled
    from daemodel.compiling.initial_states import algebraic_values, project_states

    ranges = _ranges(box, compiled.state_names, "box", "state") + _ranges(
        parameter_box, compiled.parameter_names, "parameter_box", "parameter"
    )
    if not ranges:
        raise InvalidOptionError("box names no state: give box={'y1': (low, high), ...}")
    unit = qmc.Sobol(len(ranges), scramble=True, seed=seed).random(samples)
    y = np.tile(np.asarray(compiled.y0, dtype=float), (samples, 1))
    p = np.tile(np.asarray(compiled.parameter_values, dtype=float), (samples, 1))
    for column, (kind, index, low, high) in enumerate(ranges):
        target = y if kind == "state" else p
        target[:, index] = low + (high - low) * unit[:, column]
    _refuse_inconsistent_box(as_compiled(model, "Surrogate.train()"), y, p, box)  # (before any reduction)
    y = project_states(compiled, y, p)
    z = algebraic_values(compiled, compiled.t0, y, p, np.tile(np.asarray(compiled.z0, dtype=float), (samples, 1)))
    inputs = tuple(name for name in compiled.parameter_names if name in parameter_box)
    return y, z, p, inputs


def _refuse_inconsistent_box(compiled, drawn: np.ndarray, p: np.ndarray, box: dict) -> None:
    """Refuse a box none of whose drawn states the constraints admit (pendulum ``y1`` in [2, 3]: no
    point of it is on the circle), naming the box and the constraint, before training on states
    outside it: the least-change projection of every drawn state leaves the box.

    ``compiled`` is the model as declared (an index-3 model's reduction keeps its position level as an
    invariant only); ``drawn`` (B, n) the states drawn in the box.
    """
    from daemodel.compiling.initial_states import constraint_checks, project_states, state_violations

    hidden = constraint_checks(compiled).hidden
    if not hidden:
        return
    y = project_states(compiled, drawn, p)
    names = compiled.state_names
    index = np.array([names.index(k) for k in box])
    low, high = (np.array([box[k][j] for k in box], dtype=float) for j in (0, 1))
    slack = 1e-9 * np.maximum(1.0, np.maximum(abs(low), abs(high)))  # (a projection onto a face of the box)
    if ((y[:, index] >= low - slack) & (y[:, index] <= high + slack)).all(axis=1).any():
        return
    residual, _, bad = state_violations(compiled, drawn, p)
    level = int(np.argmax(bad[0])) if bad[0].any() else int(np.argmax(np.abs(residual[0])))
    name, label, _ = hidden[level]
    given = ", ".join(f"{k} in [{lo:g}, {hi:g}]" for k, (lo, hi) in box.items())
    j = int(np.argmax(np.maximum(low - y[0, index], y[0, index] - high)))
    moved = f"{names[index[j]]} = {drawn[0, index[j]]:.6g} -> {y[0, index[j]]:.6g}"
    raise InconsistentInitialStateError(
        f"Surrogate.train(): no state drawn in the box ({given}) satisfies {label} inside it: each of the "
        f"{len(drawn)} leaves the box on its least-change projection ({name} = {residual[0, level]:.6g} at the "
        f"first, whose projection moves {moved}); choose ranges the constraints allow, or name in the box the "
        "states the constraints determine too"
    )


def _ranges(box, names, argument: str, kind: str) -> list:
    if not isinstance(box, dict):
        raise ShapeError(f"{argument} must be a dict {kind} name -> (low, high); got {type(box).__name__}")
    out = []
    for name, bounds in box.items():
        if name not in names:
            raise UnknownSymbolError(
                f"{argument} names '{name}', which is not a {kind}; the {kind}s are {', '.join(names)}"
            )
        try:
            low, high = (float(v) for v in bounds)
        except (TypeError, ValueError):
            raise ShapeError(f"{argument}['{name}'] must be a pair (low, high); got {bounds!r}") from None
        if not (np.isfinite(low) and np.isfinite(high) and low < high):
            raise InvalidOptionError(f"{argument}['{name}'] = ({low:g}, {high:g}) must be finite with low < high")
        out.append((kind, names.index(name), low, high))
    return out

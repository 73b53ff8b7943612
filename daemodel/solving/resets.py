"""The states after the events that fire at one instant: each reset an expression of the values just
before the instant (``Model.event``), whatever the others set; two that set one state to different values
(:class:`~daemodel.errors.ResetConflictError`) and a value that is not finite
(:class:`~daemodel.errors.InvalidValueError`) are refused.  Used by :mod:`daemodel.solving.events`."""

from __future__ import annotations

import numpy as np

from daemodel.errors import InvalidValueError, ResetConflictError
from daemodel.solving.rounding import floor_at


def apply_resets(compiled, resets, fired: list, t: float, y, z, P) -> np.ndarray:
    """The states (1, n) after the resets of the events ``fired`` at ``t`` (``resets``: each event's numeric
    reset, ``F(t, Y, Z, P) -> (1, k)``, or None), each an expression of the values just before (``y`` (1, n),
    ``z`` (1, m)), whatever the others set.

    Raises
    ------
    ResetConflictError
        Two of them set one state to values further apart than rounding.
    InvalidValueError
        One sets a state to a value that is not finite.
    """
    events = compiled.events
    Y, setter, rounds = y.copy(), {}, {}  # (state -> the event that set it, the rounding of the value it set)
    for e in fired:
        new = resets[e](t, y, z, P)
        # (each value within the rounding of its own expression's terms, not of an absolute 1: resets to 1e-15 and
        # 2e-15 of a state in units of 1e-14 conflict)
        floor = floor_at(compiled, tuple(expr for _, expr in events[e].reset), t, y, z, P)
        for k, (index, _) in enumerate(events[e].reset):
            value, was = float(new[0, k]), float(Y[0, index])
            if index in setter and abs(value - was) > max(floor[k], rounds[index]):
                raise ResetConflictError(
                    f"events '{events[setter[index]].name}' and '{events[e].name}' fire together at t = {t:.12g} and "
                    f"reset '{compiled.state_names[index]}' to different values ({was:.12g} and {value:.12g}): which "
                    "one holds is not defined (each reset reads the values just before); reset that state in one "
                    "of them, or give them guards that differ"
                )
            setter[index], rounds[index] = e, floor[k]
            Y[:, index] = new[:, k]
    for index in (i for i in setter if not np.isfinite(Y[0, i])):
        name, state = events[setter[index]].name, compiled.state_names[index]
        expr = dict(events[setter[index]].reset)[index]
        before = ", ".join(f"{n} = {v:.6g}" for n, v in zip(compiled.state_names, y[0], strict=True))
        raise InvalidValueError(
            f"event '{name}' at t = {t:.12g}: its reset sets '{state}' to {float(Y[0, index])} ({expr} at {before}); "
            "a reset must give finite values: keep it inside its expression's domain there"
        )
    return Y

"""What user code hands a comparison, checked: a reference callable's every answer, and an exception
raised by user code (a reference, a model file) summarised in one line with its place."""

from __future__ import annotations

import traceback
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from daemodel.errors import ComparisonError

# Times across t_span on which a reference callable is checked before the first solve.
REFERENCE_CHECK_POINTS = 11


@dataclass(frozen=True, eq=False)
class CheckedReference:
    """A reference callable whose every answer is checked before an error is measured with it.

    ``reference(t)`` must return a mapping with a finite float array of shape (T,) (or (B, T))
    for every state and algebraic variable of ``compiled``; anything else, and any exception
    it raises, is a :class:`ComparisonError` naming the variable, the time and the fix.
    Variables it gives beyond those (aliases) are checked too when the model has them; other
    keys are ignored.
    """

    function: object
    compiled: object
    t_span: tuple

    @property
    def events(self):
        """The reference's own ``events`` (laid out as :attr:`Solution.events`), or None."""
        return getattr(self.function, "events", None)

    @property
    def breakpoints(self):
        """The reference's own ``breakpoints`` (laid out as :attr:`Solution.breakpoints`), or None."""
        return getattr(self.function, "breakpoints", None)

    def __call__(self, t) -> dict:
        t = np.asarray(t, dtype=float)
        where = f"on {t.size} times from {t[0]:g} to {t[-1]:g}"
        try:
            values = self.function(t)
        except Exception as error:  # the user's code: any exception is a message, not a traceback
            raise ComparisonError(
                f"the reference, called {where}, raised {exception_summary(error, depth=1)}; reference(t) must "
                "take an array of times and return a dict name -> array of values"
            ) from error
        if not isinstance(values, Mapping):
            raise ComparisonError(
                f"the reference returned {type(values).__name__} {where}; it must return a dict name -> array of values"
            )
        c = self.compiled
        required = (*c.state_names, *c.algebraic_names)
        missing = [n for n in required if n not in values]
        if missing:
            raise ComparisonError(
                f"the reference gives no values for {', '.join(missing)}; it gives "
                f"{', '.join(map(str, values)) or 'none'}, and must give every state and algebraic variable of "
                f"'{c.name}': {', '.join(required)}"
            )
        out = {}
        for name in (*required, *(n for n in c.alias_names if n in values)):
            out[name] = self._check(name, values[name], t)
        return out

    def _check(self, name: str, value, t: np.ndarray) -> np.ndarray:
        try:
            array = np.asarray(value)
            if array.dtype.kind == "O":  # e.g. a list of sympy numbers
                array = array.astype(float)
        except (TypeError, ValueError):
            array = None
        if array is None or array.dtype.kind not in "iuf":  # text numpy would parse, complex, bool
            found = f"dtype {array.dtype}" if array is not None else type(value).__name__
            raise ComparisonError(
                f"the reference's values for '{name}' are not real numbers ({found}); return a float array per variable"
            )
        array = array.astype(float, copy=False)
        if array.ndim not in (1, 2) or array.shape[-1] != t.size:
            raise ComparisonError(
                f"the reference's values for '{name}' have shape {array.shape}; expected ({t.size},), one value per "
                f"time of the t it was called with (or (B, {t.size}) for a batch)"
            )
        finite = np.isfinite(array)
        if not finite.all():
            bad = ~finite.reshape(-1, t.size)
            first = int(np.argmax(bad.any(axis=0)))
            value = array.reshape(-1, t.size)[:, first][bad[:, first]][0]
            raise ComparisonError(
                f"the reference's value for '{name}' is {value} at t = {t[first]:g} ({int(bad.sum())} of {array.size} "
                f"values not finite); a reference must be finite on t_span = ({self.t_span[0]:g}, "
                f"{self.t_span[1]:g}): fix it, or give none to measure against method='reference'"
            )
        return array


def exception_summary(error: BaseException, *, depth: int | None = None, filename=None) -> str:
    """``"ZeroDivisionError: division by zero (line 7 of model.py)"``: one line for an
    exception raised by user code, with the line where known.

    Parameters
    ----------
    depth : int, optional
        The line is that of traceback entry ``depth`` (1: the function called inside the ``try``).
    filename : str or Path, optional
        The line is that of the innermost traceback entry in this file (named even when no
        entry is in it).
    """
    if isinstance(error, SyntaxError) and error.lineno is not None:
        return f"{type(error).__name__}: {error.msg} (line {error.lineno} of {error.filename})"
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    text = f"{type(error).__name__}: {lines[0]}" if lines else type(error).__name__
    frames = traceback.extract_tb(error.__traceback__)
    if filename is not None:
        target = Path(filename).resolve()
        frame = next((f for f in reversed(frames) if Path(f.filename).resolve() == target), None)
        return f"{text} (line {frame.lineno} of {filename})" if frame is not None else f"{text} (in {filename})"
    if depth is not None and len(frames) > depth:
        return f"{text} (line {frames[depth].lineno} of {frames[depth].filename})"
    return text

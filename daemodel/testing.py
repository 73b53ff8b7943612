"""Assertions for users' tests: two solutions (or a solution and an exact one) agree.

>>> from daemodel.testing import assert_solutions_close
>>> assert_solutions_close(dm.solve(m, span, method="pinn"), dm.solve(m, span, method="radau"), atol=1e-8)
"""

from __future__ import annotations

import numpy as np

from daemodel.errors import ComparisonError
from daemodel.solution import Solution


def assert_solutions_close(actual, desired, *, atol: float = 0.0, rtol: float = 1e-7, names=None) -> None:
    """Assert ``|actual - desired| <= atol + rtol * |desired|`` for every variable and time.

    Parameters
    ----------
    actual : Solution
    desired : Solution or callable
        A Solution on the same times (and batch size), or ``desired(t) -> dict name -> values``
        such as ``Problem.exact_solution()``.
    atol, rtol : float
        As in ``numpy.testing.assert_allclose`` (same defaults).
    names : iterable of str, optional
        Variables to compare; default every variable of ``actual`` that ``desired`` has.

    Raises
    ------
    AssertionError
        Naming the first variable that differs, the time (and sample) of its largest violation,
        both values there, and how many values of that variable are out of tolerance.
    """
    if not isinstance(actual, Solution):
        raise TypeError(f"actual must be a Solution; got {type(actual).__name__}")
    if not (isinstance(desired, Solution) or callable(desired)):
        raise TypeError(f"desired must be a Solution or a callable t -> dict of values; got {type(desired).__name__}")
    try:
        wanted, reference = actual._aligned_reference(desired, names)
    except ComparisonError as error:  # other times, or variables one side lacks
        raise AssertionError(str(error)) from None
    if isinstance(desired, Solution) and desired.batch_size != actual.batch_size:
        raise AssertionError(f"the solutions have different batch sizes: {actual.batch_size} and {desired.batch_size}")
    label = f"desired ({desired.method})" if isinstance(desired, Solution) else "desired"
    for name in wanted:
        a = actual.values[name]  # (B, T)
        b = np.broadcast_to(np.asarray(reference[name], dtype=float), a.shape)
        bound = atol + rtol * np.abs(b)
        excess = np.abs(a - b) - bound
        bad = ~(excess <= 0)  # NaN counts as a violation
        if bad.any():
            worst = np.where(np.isnan(excess), np.inf, excess)
            sample, k = np.unravel_index(int(np.argmax(worst)), a.shape)
            where = f"t = {actual.t[k]:.6g}" + (f", sample {sample}" if actual.batched else "")
            x, y = float(a[sample, k]), float(b[sample, k])
            raise AssertionError(
                f"{name} differs at {where}: actual ({actual.method}) {x!r}, {label} {y!r} "
                f"(|difference| {abs(x - y):.3g} > atol + rtol*|desired| = {bound[sample, k]:.3g}); "
                f"{int(bad.sum())} of {a.size} values of {name} are out of tolerance"
            )

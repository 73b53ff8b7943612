"""Near misses (daemodel/solving/misses.py): an extremum of an event function that the method's own solution
leaves within its error of zero, checked by a solve 100 times tighter."""

import math

import numpy as np
import pytest
from daemodel.backends.casadi.idas import IDASOptions

from daemodel import errors as E
from daemodel.solving.between import Excursion, excursions
from daemodel.solving.misses import NEAR_MISS_TOLS, TIGHTER, NearMiss, NearMisses, function_tolerance, status_of


def _miss(near: float, t: float = 1.0) -> Excursion:
    return Excursion(event=0, before=0, t=t, side=1.0, near=near)


def _when(t, Y, Z, P):
    """The event function 0.999999 - s, s the first state: (K, 1)."""
    return (0.999999 - Y[:, :1]).reshape(-1, 1)


ONE, NONE, P = np.ones((1, 2)), np.zeros((1, 0)), np.zeros((1, 0))


def _near(trial, rtol=1e-7):
    return NearMisses(trial, _when, P, IDASOptions(rtol=rtol, atol=rtol), 0.0, ONE, NONE)


def _solver(value):
    """A trial ``(options, a, tau, ya, za, which) -> (F, y, z)`` returning ``value`` (or raising it), and its calls."""
    calls = []

    def trial(options, a, tau, ya, za, which):
        calls.append((options.rtol, options.atol, a, tau))
        if isinstance(value, Exception):
            raise value
        return value, ya, za

    return trial, calls


def test_a_near_miss_that_a_tighter_solve_crosses_is_flagged_with_both_values():
    trial, calls = _solver(-9.6e-7)
    near = _near(trial)
    miss = near.check(_miss(1.1e-6, t=5.5), "hump", ONE, NONE)
    assert miss == NearMiss("hump", 5.5, 1.1e-6, -9.6e-7)
    assert calls == [(1e-7 / TIGHTER, 1e-7 / TIGHTER, 0.0, 5.5)]
    assert miss.status("casadi-idas") == (
        "event 'hump' near t = 5.5: its function stays 1.1e-06 from zero in casadi-idas's solution, where a solve "
        "100 times tighter crosses to -9.6e-07: a crossing within the method's error, not located; tighten rtol/atol"
    )
    # (the next check goes on from there: one tighter solve of the piece)
    near.check(_miss(2e-6, t=8.0), "hump", ONE, NONE)
    assert calls[-1][2:] == (5.5, 8.0)


def test_a_near_miss_whose_tighter_solve_fails_is_flagged():
    trial, _ = _solver(E.StepLimitError("max_num_steps"))
    miss = _near(trial).check(_miss(1e-6), "hump", ONE, NONE)
    assert miss.tight is None
    assert status_of([miss, NearMiss("hump", 2.5, 1e-6, -1e-6)], "casadi-idas") == [
        "event 'hump' near t = 1: its function stays 1e-06 from zero in casadi-idas's solution, where a solve 100 "
        "times tighter, to check it, failed: a crossing within the method's error, not located; tighten rtol/atol "
        "(and 1 more, the last near t = 2.5)"
    ]


def test_a_time_limit_that_strikes_in_the_check_is_not_its_failure():
    trial, _ = _solver(E.TimeLimitError("the task's time limit of 1 s ran out"))
    with pytest.raises(E.TimeLimitError, match="time limit of 1 s"):
        _near(trial).check(_miss(1e-6), "hump", ONE, NONE)


@pytest.mark.parametrize(
    ("near", "tight", "rtol", "solves"),
    [
        (1.1e-6, 1e-7, 1e-7, 1),  # (the tighter solve stays on the side too: a near miss, no crossing)
        (1.1e-6, -5e-9, 1e-7, 1),  # (across by less than its own error, a hundredth of the solves' difference)
        (1e-8, -1.5e-9, 1e-7, 1),  # (across by less than the tighter solve's tolerance, 2e-9: rounding)
        (NEAR_MISS_TOLS * 2e-7 * 1.01, -1.0, 1e-7, 0),  # (past NEAR_MISS_TOLS tolerances: not checked)
        (1e-15, -1.0, 1e-14, 0),  # (an rtol at its floor: nothing tighter to check with)
    ],
)
def test_what_is_not_a_near_miss(near, tight, rtol, solves):
    trial, calls = _solver(tight)
    assert _near(trial, rtol).check(_miss(near), "hump", ONE, NONE) is None and len(calls) == solves


def test_a_function_tolerance_is_how_far_one_tolerance_of_the_variables_moves_it():
    # s1 - s2 at (1, 3): moving both up cancels; every other one down moves it by both tolerances
    options = IDASOptions(rtol=1e-6, atol=1e-8)
    y = np.array([[1.0, 3.0]])

    def when(t, Y, Z, P):
        return (Y[:, :1] - Y[:, 1:2]).reshape(-1, 1)

    assert abs(function_tolerance(when, options, 0, 0.0, y, NONE, P) - (2e-8 + 4e-6)) < 1e-15
    assert abs(function_tolerance(_when, options, 0, 0.0, y, NONE, P) - (1e-8 + 1e-6)) < 1e-15


def test_the_probes_report_the_point_nearest_zero_where_no_crossing_is():
    # each look solves again (no inner samples): a hump of 1 - sin t that stays 1e-6 above zero is a near miss at
    # its peak, found by the probes to the dense output's accuracy
    c, peak = 1.000001, math.pi / 2

    def read(t):
        return (c - np.sin(np.asarray(t, dtype=float)))[:, None]

    T = np.array([peak - 0.23, peak - 0.03, peak + 0.17])
    F = read(T)
    found = list(excursions(read, T, F, np.ones(F.shape, dtype=bool), 0))
    assert len(found) == 1 and found[0].side == 1.0
    assert abs(found[0].t - peak) < 1e-4 and abs(found[0].near - 1e-6) < 1e-9

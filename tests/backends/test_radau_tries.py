"""An attempt's tries written once (backends/radau/tries.py): on Python values (the general path and
the compiled attempt) and on casadi symbols (the compiled run's graph) the same tries in the same order.

A side whose tries' outcomes are set by the test (one written over the namespace, so that both
namespaces run the same side) shows which tries ran: each try's evaluations count says which
matrices and which guess it ran on.
"""

import itertools

import casadi
import pytest
from daemodel.backends.radau import formulas
from daemodel.backends.radau.formulas import CASADI, SCALAR
from daemodel.backends.radau.tries import AbstractTriesSide, attempt_tries

CONVERGED, NON_FINITE, DIVERGING = formulas.CONVERGED, formulas.NON_FINITE, formulas.DIVERGING


class SetSide(AbstractTriesSide):
    """matrices = (fresh, usable, then the test's settings: whether a refresh's factors serve, whether
    the stages' check finds a sign change, each try's outcome), guess 0 (extrapolated) or 1 (the
    start value); a result = (outcome, evaluations), the evaluations 1 + 10 guess + 100 fresh (which
    try it was).  (On casadi symbols a branch reads nothing but its operands: the settings travel
    with the matrices.)"""

    def __init__(self, xp, kept):
        self.xp, self.kept_jacobian = xp, kept

    def kept(self):
        return self.kept_jacobian

    def attempt(self, matrices, guess):
        fresh, _, _, _, first, again, start = matrices
        outcome = self.xp.where(guess > 0, start, self.xp.where(fresh > 0, again, first))
        return outcome, 1 + 10 * guess + 100 * fresh

    def failed(self, result):
        return result[0] != CONVERGED

    def non_finite(self, result):
        return result[0] == NON_FINITE

    def evaluations(self, result):
        return result[1]

    def refresh(self, matrices):
        return (1 + 0 * matrices[0], matrices[2], *matrices[2:])

    def usable(self, matrices):
        return matrices[1] > 0

    def check_stages(self, matrices):
        return matrices[3]


FIELDS = ("stale", "usable", "retries", "evaluations", "newton_failed", "stage_flip")


def _tries(xp, outcomes, usable_after, flip, kept, extrapolated):
    zero = 0 * outcomes[0]
    matrices = (zero, 1 + zero, usable_after, flip, *outcomes)
    tries = attempt_tries(xp, SetSide(xp, kept), matrices, zero, 1 + zero, extrapolated)
    return [tries.result[0], *(getattr(tries, name) for name in FIELDS)]


COMBINATIONS = list(
    itertools.product((CONVERGED, DIVERGING), (CONVERGED, DIVERGING, NON_FINITE), (CONVERGED, DIVERGING, NON_FINITE),
                      (0.0, 1.0), (0.0, 1.0), (False, True), (False, True))
)  # fmt: skip


def test_the_tries_are_the_same_on_python_values_and_on_casadi_symbols():
    names = ("first", "fresh", "start", "usable_after", "flip", "kept", "extrapolated")
    x = {name: casadi.MX.sym(name) for name in names}
    symbols = _tries(CASADI, (x["first"], x["fresh"], x["start"]), *(x[name] for name in names[3:]))
    function = casadi.Function("tries", list(x.values()), symbols)
    for first, fresh, start, usable_after, flip, kept, extrapolated in COMBINATIONS:
        outcomes = (float(first), float(fresh), float(start))
        python = _tries(SCALAR, outcomes, usable_after, flip, kept, extrapolated)
        compiled = [float(value) for value in function(*outcomes, usable_after, flip, kept, extrapolated)]
        assert compiled == [float(value) for value in python], (first, fresh, start, usable_after, flip, kept)


@pytest.mark.parametrize(
    ("outcomes", "usable_after", "kept", "extrapolated", "expected"),
    [
        # converged at once: one try
        ((CONVERGED, DIVERGING, DIVERGING), 1.0, True, True, (CONVERGED, False, 0, 1, False)),
        # a kept Jacobian failed: again on a fresh one, which converges
        ((DIVERGING, CONVERGED, DIVERGING), 1.0, True, True, (CONVERGED, True, 1, 1 + 101, False)),
        # ... which fails too: from the start value, on the fresh one
        ((DIVERGING, DIVERGING, CONVERGED), 1.0, True, True, (CONVERGED, True, 2, 1 + 101 + 111, False)),
        # a fresh Jacobian (not kept) and the start value as the guess: one try, then the check
        ((DIVERGING, CONVERGED, CONVERGED), 1.0, False, False, (DIVERGING, False, 1, 1, True)),
        # the fresh factors cannot serve: no more tries, no check (the general path takes the attempt)
        ((DIVERGING, CONVERGED, CONVERGED), 0.0, True, True, (DIVERGING, True, 1, 1, False)),
        # every try failed, the last on non-finite values: a Newton failure as on the general path (h
        # shrinks), and the check (Akzo Nobel at rtol 1e-4: no longer handed to the general path)
        ((DIVERGING, DIVERGING, NON_FINITE), 1.0, True, True, (NON_FINITE, True, 3, 1 + 101 + 111, True)),
    ],
)
def test_the_tries_in_the_general_paths_order(outcomes, usable_after, kept, extrapolated, expected):
    outcome, stale, retries, evaluations, newton_failed = expected
    found = _tries(SCALAR, tuple(map(float, outcomes)), usable_after, 1.0, kept, extrapolated)
    assert found[0] == outcome and found[1] == stale and found[3] == retries and found[4] == evaluations
    assert found[5] == newton_failed and found[6] == (1.0 if newton_failed else False)


def test_an_overflowing_residual_fails_its_attempt_without_numpy_warnings():
    """The ring modulator at rtol 1e-8: 45 attempts' Newton iterations overflow (the diodes' exp) and
    are retried shorter; numpy's "invalid value encountered in matmul" about each reached the user
    as a RuntimeWarning from a run that succeeds."""
    import warnings

    import daemodel as dm
    from daemodel.problems import PROBLEMS

    ring = PROBLEMS["ring-modulator"]
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        sol = dm.solve(ring.model().compile(), ring.t_span, rtol=1e-8, atol=1e-8)
    assert sol.status == "success" and sol.stats["newton_failures"] > 0

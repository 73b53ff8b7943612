"""The simplified Newton iteration's state machine written once (backends/radau/iteration.py): the
general path runs it on arrays, the compiled attempt on casadi SX (compiled.newton_tests); fed the same
increment norms, both end with the same outcome, iterations, contraction, rate and evaluations."""

import math

import numpy as np
import pytest
from daemodel.backends.radau import formulas
from daemodel.backends.radau.compiled import NEWTON_AFTER, NEWTON_BEFORE, newton_tests
from daemodel.backends.radau.formulas import ArrayOps
from daemodel.backends.radau.iteration import newton_pass, newton_start

TOL = 1e-3
# (the increment norms of the passes that take one, the start rate eta, the iterations allowed):
# the outcome, the iterations k and the residual evaluations
CASES = {
    "converged-1-confirmed": (([0.5, 2e-4], 1e-3, 7), formulas.CONVERGED, 1, 2),  # iteration, check
    "converged-3": (([1e-1, 1e-2, 1e-4], 0.5, 7), formulas.CONVERGED, 3, 4),  # + f at the final stages
    "converged-7": (([0.3**j for j in range(7)], 0.5, 10), formulas.CONVERGED, 7, 8),
    "refuted-check": (([0.5, 2e-3], 1e-3, 7), formulas.CONVERGED, 2, 4),  # 1, the check counted 2, f
    "diverging": (([1e-1, 1.5e-1], 0.5, 7), formulas.DIVERGING, 2, 2),
    "slow": (([1.0, 0.9], 0.5, 7), formulas.SLOW, 2, 2),
    "non-finite": (([1e-1, math.nan], 0.5, 7), formulas.NON_FINITE, 2, 2),
    "non-finite-check": (([0.5, math.nan], 1e-3, 7), formulas.NON_FINITE, 2, 3),  # a NaN confirms nothing
    "iteration-limit": (([1.0, 0.05, 0.01], 0.5, 3), formulas.NOT_CONVERGED, 3, 3),
    "one-iteration-allowed": (([0.5], 1e-3, 1), formulas.CONVERGED, 1, 2),  # no check: f at once
}


def _on_arrays(norms, eta, iterations, trust_last_rate=True):
    """The passes on numpy arrays of one sample, as Newton.simplified runs them (no norm where only f is needed)."""
    ops, left = ArrayOps(np), iter(norms)
    state = newton_start(np.array([eta]), np.zeros(1), np.ones(1, dtype=bool))
    with np.errstate(all="raise"):  # (no test past a failure: no rate at theta 1)
        while state.active:
            norm = None if state.mode == formulas.EVALUATE else np.array([next(left)])
            state = newton_pass(ops, state, norm, TOL, iterations, trust_last_rate=trust_last_rate).state
    assert next(left, None) is None  # every norm read
    return state.outcome, state.k, float(state.theta[0]), float(state.eta[0]), state.evaluations


def _on_casadi(norms, eta, iterations):
    """The passes through the compiled step's SX function, evaluated numerically; where it only evaluates
    f the increment is computed all the same (NaN here: it must not count)."""
    function, left = newton_tests(iterations), iter(norms)
    state = {name: 0.0 for name in NEWTON_BEFORE.names}
    state.update(eta=eta, active=1.0)
    while state["active"]:
        norm = math.nan if state["mode"] == formulas.EVALUATE else next(left)
        before = NEWTON_BEFORE.pack(**{name: state[name] for name in NEWTON_BEFORE.names[1:-1]}, norm=norm, tol=TOL)
        state = NEWTON_AFTER.read(np.asarray(function(before=before)["after"]).ravel())
    assert next(left, None) is None
    return int(state["outcome"]), int(state["k"]), float(state["theta"]), float(state["eta"]), int(state["evaluations"])


@pytest.mark.parametrize("case", CASES)
def test_the_pass_ends_the_same_on_arrays_and_on_casadi_symbols(case):
    (norms, eta, iterations), outcome, k, evaluations = CASES[case]
    arrays = _on_arrays(norms, eta, iterations)
    assert arrays[0] == outcome and arrays[1] == k and arrays[4] == evaluations
    assert _on_casadi(norms, eta, iterations) == arrays  # theta and eta bit for bit


def test_theta_and_eta_written_out():
    # three iterations: the first reads the start rate, the second and third contract at 1e-2 / 1e-1, 1e-4 / 1e-2
    _, _, theta, eta, _ = _on_arrays([1e-1, 1e-2, 1e-4], 0.5, 7)
    assert theta == 1e-4 / 1e-2 and eta == (1e-4 / 1e-2) / (1 - 1e-4 / 1e-2)
    assert _on_casadi([1e-1, 1e-2, 1e-4], 0.5, 7)[2:4] == (theta, eta)
    # a refuted check: its increment (2e-3 > tol) is the second iteration's, against the first's 0.5
    outcome, k, theta, eta, evaluations = _on_arrays([0.5, 2e-3], 1e-3, 7)
    assert (outcome, k, evaluations) == (formulas.CONVERGED, 2, 4)
    assert theta == 2e-3 / 0.5 and eta == (2e-3 / 0.5) / (1 - 2e-3 / 0.5)


def test_without_the_last_rate_a_convergence_ends_the_iteration():
    """The fixed grid: no check and no evaluation after the convergence (f at the last iterate serves)."""
    outcome, k, _, _, evaluations = _on_arrays([1e-1, 1e-2, 1e-4], 1.0, 7, trust_last_rate=False)
    assert (outcome, k, evaluations) == (formulas.CONVERGED, 3, 3)


def test_a_check_moves_only_the_samples_it_refutes():
    ops = ArrayOps(np)
    state = newton_start(np.full(3, 1e-3), np.zeros(3), np.ones(3, dtype=bool))
    state = newton_pass(ops, state, np.array([0.5, 0.2, 0.4]), TOL, 7).state  # every sample converged at k = 1
    assert state.mode == formulas.CHECK and state.active and not state.iterating.any()
    found = newton_pass(ops, state, np.array([1e-4, 5e-3, 2e-4]), TOL, 7)
    assert found.iterate and list(found.moved) == [False, True, False]
    after = found.state
    np.testing.assert_array_equal(after.theta, [0.0, 5e-3 / 0.2, 0.0])  # only the refuted sample's moves
    assert (after.k, after.evaluations, after.mode, after.outcome) == (2, 3, formulas.EVALUATE, formulas.CONVERGED)

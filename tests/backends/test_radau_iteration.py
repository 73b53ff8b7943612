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


def test_five_stages_and_more_take_radau5s_geometric_contraction():
    """From the third iteration on, RADAU5's sqrt(q_k q_(k-1)) of the last two ratios (formulas.mean_contraction)
    for s >= 5 (formulas.GEOMETRIC_CONTRACTION_STAGES), the same on arrays and casadi symbols; s = 3 keeps q_k."""
    ops = ArrayOps(np)
    norms = [1e-1, 1e-2, 1e-4]  # ratios 1e-1, then 1e-2: the mean 10^-1.5
    mean = ((1e-4 / 1e-2) * (1e-2 / 1e-1)) ** 0.5
    for stages, theta in ((3, 1e-4 / 1e-2), (5, mean), (7, mean)):
        geometric = formulas.geometric_contraction(stages)
        state = newton_start(np.array([0.5]), np.zeros(1), np.ones(1, dtype=bool))
        function = newton_tests(7, geometric)
        scalars = {name: 0.0 for name in NEWTON_BEFORE.names}
        scalars.update(eta=0.5, active=1.0)
        for norm in norms:
            state = newton_pass(ops, state, np.array([norm]), TOL, 7, geometric=geometric).state
            before = NEWTON_BEFORE.pack(
                **{name: scalars[name] for name in NEWTON_BEFORE.names[1:-1]}, norm=norm, tol=TOL
            )
            scalars = NEWTON_AFTER.read(np.asarray(function(before=before)["after"]).ravel())
        assert float(state.theta[0]) == theta and float(state.eta[0]) == theta / (1 - theta)
        assert (scalars["theta"], scalars["eta"]) == (float(state.theta[0]), float(state.eta[0]))
    # a mean below the divergence bound where the last ratio alone (1.1) is above it: the iteration goes on
    for geometric, outcome in ((True, formulas.CONVERGED), (False, formulas.DIVERGING)):
        state = newton_start(np.array([0.5]), np.zeros(1), np.ones(1, dtype=bool))
        for norm in (1.0, 0.1, 0.11):
            state = newton_pass(ops, state, np.array([norm]), TOL, 7, geometric=geometric).state
        assert state.outcome == outcome and state.active == geometric
    assert float(state.theta[0]) == pytest.approx(1.1)  # (the last ratio alone)

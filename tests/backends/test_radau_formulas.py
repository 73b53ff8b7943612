"""radau's formulas written once (backends/radau/formulas.py): the Python path evaluates them on floats
and arrays, the compiled step and run on casadi symbols; both must give the same numbers, bit for
bit where the compiled run is held to the controller's steps, and RADAU5's values."""

import math

import casadi
import numpy as np
import pytest
from daemodel.backends.radau import formulas
from daemodel.backends.radau.compiled import Layout
from daemodel.backends.radau.formulas import CASADI, SCALAR, ArrayOps

# (h, err, Newton's iterations k, last accepted (h, err), rejected_last, jac_kept, predictive)
CASES = [
    (0.1, 0.5, 3, (0.0, 0.0), False, True, True),  # no accepted step yet: the quotient alone
    (0.1, 0.5, 3, (0.08, 0.7), False, True, True),  # Gustafsson's prediction
    (0.1, 1e-14, 1, (0.1, 1e-3), False, False, True),  # the growth bound
    (0.1, 0.999, 7, (0.2, 0.01), True, True, True),  # after a rejection h does not grow
    (0.1, 0.2, 2, (0.1, 0.3), False, True, False),
    (0.1, 0.05, 2, (0.1, 0.05), False, True, True),  # within the band: h stays
    (2.5e-7, 3.0, 4, (3e-7, 0.9), False, True, True),  # rejected
    (0.1, math.inf, 7, (0.1, 0.5), False, True, True),  # Newton failed
]


def _controller(xp, h, err, k, last, rejected_last, jac_kept, predictive, failed, t=0.3, t0=0.0, t1=1.0):
    s, iterations, keep = 3, 7, (1.0, 1.2)
    err = formulas.finite_or_inf(xp, err)
    quot = formulas.error_quotient(xp, err, k, s, iterations)
    new_h, (h_acc, err_acc) = formulas.next_step(xp, h, err, quot, s, last, predictive, rejected_last, keep, jac_kept)
    t_next = formulas.step_end(xp, t, h, t1)
    return [
        quot,
        formulas.accepted(xp, failed, err),
        formulas.rejected_step(xp, h, quot, failed),
        new_h,
        h_acc,
        err_acc,
        formulas.step_length(xp, h, t, t1),
        formulas.underflow(xp, h, t),
        t_next,
        formulas.finished(xp, t_next, t0, t1),
    ]


@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("failed", [False, True])
def test_the_controller_gives_the_same_bits_on_floats_and_on_casadi_symbols(case, failed):
    h, err, k, last, rejected_last, jac_kept, predictive = case
    floats = _controller(SCALAR, h, err, k, last, rejected_last, jac_kept, predictive, failed)
    names = ("h", "err", "k", "h_acc", "err_acc", "rejected_last", "jac_kept", "predictive", "failed")
    x = {name: casadi.SX.sym(name) for name in names}
    symbols = _controller(
        CASADI, x["h"], x["err"], x["k"], (x["h_acc"], x["err_acc"]), x["rejected_last"], x["jac_kept"],
        x["predictive"], x["failed"],
    )  # fmt: skip
    function = casadi.Function("controller", list(x.values()), symbols)
    values = (h, err, k, *last, rejected_last, jac_kept, predictive, failed)
    compiled = [float(out) for out in function(*map(float, values))]
    assert compiled == [float(value) for value in floats]


def test_radau5s_step_size_formulas():
    """Hairer & Wanner IV.8 (RADAU5): fac = min(0.9, 0.9 (2 nit + 1) / (2 nit + k)), quot = fac err^(-1/4) at
    s = 3, bounded to [0.2, 8]; Gustafsson's h_new = 0.9 h (h / h_acc) (err_acc / err^2)^(1/4) h."""
    quot = formulas.error_quotient(SCALAR, 0.5, 3, 3, 7)
    assert quot == pytest.approx(min(0.9, 0.9 * 15 / 17) * 0.5**-0.25, rel=1e-15)
    new_h, accepted = formulas.next_step(SCALAR, 0.1, 0.5, quot, 3, (0.08, 0.7), True, False, (1.0, 1.2), True)
    predicted = 0.9 * (0.1 / 0.08) * (0.7 / 0.25) ** 0.25
    assert new_h == pytest.approx(0.1 * min(quot, predicted), rel=1e-15) and accepted == (0.1, 0.5)
    assert formulas.next_step(SCALAR, 0.1, 1e-20, 1e5, 3, (0.0, 0.0), True, False, (1.0, 1.2), False)[0] == 0.8
    assert formulas.rejected_step(SCALAR, 0.1, 1e-3, False) == pytest.approx(0.02)  # at least 0.2
    assert formulas.rejected_step(SCALAR, 0.1, 0.95, False) == pytest.approx(0.09)  # at most 0.9
    assert formulas.rejected_step(SCALAR, 0.1, 0.95, True) == 0.05  # Newton failed: halved
    assert formulas.step_length(SCALAR, 0.5, 0.6, 1.0) == pytest.approx(0.4)
    assert formulas.step_length(SCALAR, 0.4 * (1 - 1e-12), 0.6, 1.0) == 1.0 - 0.6  # stretched to the end


def test_the_error_norm_and_newtons_tests_on_arrays_and_casadi_symbols():
    rng = np.random.default_rng(3)
    D = 5
    err, scale, refiltered = rng.standard_normal(D), 0.1 + rng.random(D), 1e-3 * rng.standard_normal(D)
    arrays = ArrayOps(np)
    e, w, r = casadi.SX.sym("e", D), casadi.SX.sym("w", D), casadi.SX.sym("r", D)
    for first in (False, True):
        expected = formulas.error_norm(arrays, err[None], scale[None], first, lambda: refiltered[None])
        norm = casadi.Function("norm", [e, w, r], [formulas.error_norm(CASADI, e, w, first, lambda: r)])
        np.testing.assert_allclose(float(norm(err, scale, refiltered)), expected[0], rtol=1e-15)
        independent = np.sqrt(np.mean(((refiltered if first else err) / scale) ** 2))
        assert expected[0] == pytest.approx(independent, rel=1e-14)
    weights = formulas.index_weights(arrays, 0.01, 2, np.array([0.0, 1.0, 2.0]))
    np.testing.assert_array_equal(weights, [1.0, 1.0, 1.0, 0.01, 0.01**2])
    h = casadi.SX.sym("h")
    symbolic = casadi.Function("w", [h], [formulas.index_weights(CASADI, h, 2, np.array([0.0, 1.0, 2.0]))])
    np.testing.assert_array_equal(np.asarray(symbolic(0.01)).ravel(), weights)

    norm, previous, tol = 2e-4, 1e-3, 5e-6
    theta = formulas.contraction(arrays, np.array([norm]), np.array([previous]))
    assert theta[0] == 0.2 and not formulas.diverging(theta[0]) and formulas.diverging(0.99)
    assert formulas.rate(0.2) == pytest.approx(0.25)
    assert not formulas.converged(0.25, norm, tol) and formulas.converged(0.25, norm, 5e-5)
    assert formulas.too_slow(0.25, norm, 0.2, 1, tol) and not formulas.too_slow(0.25, norm, 0.2, 2, tol)
    assert formulas.start_rate(arrays, np.array([0.0]), 1e-16)[0] == pytest.approx(1e-16**0.8)
    x = casadi.SX.sym("x", 2)
    symbolic = casadi.Function("theta", [x], [formulas.contraction(CASADI, x[0], x[1])])
    assert float(symbolic([norm, previous])) == theta[0] and float(symbolic([norm, 0.0])) == norm / 1e-300


def test_layouts_name_every_part_once():
    layout = Layout("t", "h", ("u", 3), "code", ("p", 2))
    assert layout.size == 8 and layout["h"] == 1 and layout["u"] == slice(2, 5) and layout["p"] == slice(6, 8)
    vector = np.arange(8.0)
    parts = layout.read(vector)
    assert parts["code"] == 5.0 and list(parts["u"]) == [2.0, 3.0, 4.0]
    assert layout.pack(**parts)[2] is parts["u"]
    with pytest.raises(KeyError, match=r"expected the parts \['t', 'h', 'u', 'code', 'p'\]; got \['h', 't'\]"):
        layout.pack(t=0.0, h=1.0)


# (norm, previous, theta, eta, first, left, tol): Newton's outcome, the samples still iterating
NEWTON_CASES = [
    ((math.nan, 1e-3, 0.0, 0.5, False, 3, 1e-2), formulas.NON_FINITE, True),
    ((1e-4, 0.0, 0.0, 0.01, True, 6, 1e-2), formulas.CONVERGED, False),  # the first: the last step's rate
    ((1e-3, 1e-3, 0.1, 0.5, False, 3, 1e-6), formulas.DIVERGING, True),  # theta 1: no rate computed
    ((2e-4, 1e-3, 0.1, 0.5, False, 1, 5e-6), formulas.SLOW, True),  # 0.25 2e-4 0.2 > 5e-6
    ((2e-4, 1e-3, 0.1, 0.5, False, 2, 5e-6), formulas.CONVERGED, True),  # 0.25 2e-4 0.04 < 5e-6: on
    ((2e-4, 1e-3, 0.1, 0.5, False, 0, 5e-6), formulas.NOT_CONVERGED, True),
    ((2e-4, 1e-3, 0.1, 0.5, False, 0, 5e-5), formulas.CONVERGED, False),  # 0.25 2e-4 <= 5e-5
]


@pytest.mark.parametrize(("case", "outcome", "running"), NEWTON_CASES)
def test_newtons_tests_in_their_order_on_arrays_and_on_casadi_symbols(case, outcome, running):
    norm, previous, theta, eta, first, left, tol = case
    arrays = ArrayOps(np)
    with np.errstate(all="raise"):  # (a test past a failure, such as the rate at theta 1, would warn)
        found = formulas.newton_iteration(
            arrays, np.array([norm]), None if first else np.array([previous]), np.array([theta]), np.array([eta]),
            np.array([True]), first, left, tol,
        )  # fmt: skip
    assert found.outcome == outcome and found.running == running
    names = ("norm", "previous", "theta", "eta", "first", "left", "tol")
    x = {name: casadi.SX.sym(name) for name in names}
    tests = formulas.newton_iteration(CASADI, *(x[name] for name in names[:4]), 1, *(x[name] for name in names[4:]))
    function = casadi.Function("tests", list(x.values()), [tests.outcome, tests.theta, tests.eta, tests.active])
    symbolic = [float(value) for value in function(norm, previous, theta, eta, first, left, tol)]
    assert symbolic[0] == outcome and symbolic[3] == (running if outcome == formulas.CONVERGED else 1.0)
    if outcome != formulas.NON_FINITE:  # (the same contraction and rate, bit for bit)
        assert symbolic[1] == found.theta[0] and symbolic[2] == found.eta[0]
    if not first and outcome != formulas.NON_FINITE:
        assert found.theta[0] == norm / previous


def test_newtons_tests_move_only_the_samples_still_iterating():
    arrays = ArrayOps(np)
    norm, previous = np.array([1e-9, 1e-4, 5e-5]), np.array([1e-3, 1e-3, 1e-3])
    active = np.array([True, True, False])  # the third converged before: its theta and eta stay
    found = formulas.newton_iteration(arrays, norm, previous, np.full(3, 0.3), np.full(3, 0.5), active, False, 4, 1e-6)
    np.testing.assert_array_equal(found.theta, [1e-6, 0.1, 0.3])
    np.testing.assert_array_equal(found.eta, [1e-6 / (1 - 1e-6), 0.1 / 0.9, 0.5])
    assert list(found.active) == [False, True, False] and found.outcome == formulas.CONVERGED


def test_a_casadi_branch_runs_the_branch_taken_and_passes_the_rest_through():
    a, b = casadi.MX.sym("a"), casadi.MX.sym("b", 2)
    out, kept = CASADI.branch("b", a > 0, lambda a, b: (a * 2, b), lambda a, b: (a + 1, b), a, b)
    assert kept is b  # (both branches pass it through: no copy through the switch)
    function = casadi.Function("f", [a, b], [out])
    assert float(function(3.0, [0.0, 0.0])) == 6.0 and float(function(-3.0, [0.0, 0.0])) == -2.0
    assert SCALAR.branch("b", 3.0 > 0, lambda a: a * 2, lambda a: a + 1, 3.0) == 6.0


@pytest.mark.parametrize(
    ("k", "iterations", "then"), [(1, 7, formulas.CHECK), (2, 7, formulas.EVALUATE), (1, 1, formulas.EVALUATE)]
)
def test_a_convergence_at_the_first_iteration_is_checked_where_another_is_allowed(k, iterations, then):
    assert formulas.after_convergence(SCALAR, k, iterations) == then
    x = casadi.SX.sym("k")
    assert float(casadi.Function("then", [x], [formulas.after_convergence(CASADI, x, iterations)])(k)) == then
    assert formulas.confirmed(1e-7, 1e-6) and not formulas.confirmed(math.nan, 1e-6)

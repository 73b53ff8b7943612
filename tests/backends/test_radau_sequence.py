"""RADAU5's attempt sequence written once (backends/radau/sequence.py): the Python controller calls it on
floats, the compiled run's head and tail (backends/radau/loop.py) are the same functions on casadi SX
symbols; both must give the same numbers, bit for bit, and RADAU5's."""

import math

import pytest
from daemodel.backends.radau import formulas, loop, sequence
from daemodel.backends.radau.formulas import SCALAR

S, ITERATIONS = 3, 7
SETTINGS = dict(
    t0=0.0, t1=1.0, limit=32.0, newton_tol=0.03, rtol=1e-6, atol=1e-6, reuse_theta=0.1, keep_low=1.0,
    keep_high=1.2, predictive=1.0, trusted=0.2,
)  # fmt: skip
CARRIED = dict(
    t=0.3, h=0.1, h_old=0.08, eta=0.02, first=0.0, rejected_last=0.0, h_acc=0.08, err_acc=0.7, jac_kept=1.0,
    t_jac=0.2, factors_h=0.1, det_sign=1.0, t_det=0.2, attempts=3.0, active=1.0, code=0.0,
)  # fmt: skip
ATTEMPT = dict(
    stale=0.0, singular=0.0, sign=1.0, retry_sign=1.0, outcome=0.0, iterations=3.0, theta=0.05, eta=0.03,
    error_norm=0.5, evaluations=4.0, retries=0.0, newton_failed=0.0, stage_flip=0.0,
)  # fmt: skip

# (what the case is, the carried scalars, the settings and the attempt that differ from the above)
CASES = [
    ("accepted", {}, {}, {}),
    ("rejected", {}, {}, {"error_norm": 3.0}),
    ("failed Newton", {}, {}, {"newton_failed": 1.0, "outcome": 3.0, "error_norm": math.inf}),
    ("non-finite", {}, {}, {"outcome": 1.0, "error_norm": math.nan}),
    ("error NaN", {}, {}, {"error_norm": math.nan}),
    (
        "first step",
        {"first": 1.0, "h_old": 0.0, "h_acc": 0.0, "err_acc": 0.0, "jac_kept": 0.0, "factors_h": 0.0},
        {},
        {},
    ),
    ("after a rejection", {"rejected_last": 1.0, "factors_h": 0.0}, {}, {"error_norm": 0.01}),
    # (before the first accepted step, no estimate of a step beyond the probe's is refiltered: after one, any)
    (
        "first step beyond the probe's",
        {"first": 1.0, "h_old": 0.0, "h_acc": 0.0, "err_acc": 0.0, "jac_kept": 0.0, "factors_h": 0.0},
        {"trusted": 0.05},
        {},
    ),
    ("rejected beyond the probe's", {"rejected_last": 1.0, "h_acc": 0.0, "err_acc": 0.0}, {"trusted": 0.05}, {}),
    ("rejected beyond the probe's, a step accepted", {"rejected_last": 1.0}, {"trusted": 0.05}, {}),
    ("Gustafsson off", {}, {"predictive": 0.0}, {"error_norm": 0.2}),
    ("Gustafsson binding", {"err_acc": 0.05}, {}, {}),
    ("keep band", {}, {"keep_high": 1.5}, {"error_norm": 0.1}),
    ("keep band, Jacobian dropped", {}, {"keep_high": 1.5}, {"error_norm": 0.1, "theta": 0.5}),
    # (factors of the last step's h, which t's rounding moved: they serve; beyond that rounding: factored)
    ("factors within rounding", {"factors_h": (0.2 + 0.1) - 0.2}, {}, {}),
    ("factors beyond rounding", {"factors_h": 0.1 * (1 + 1e-12)}, {}, {}),
    ("growth bound", {}, {}, {"error_norm": 1e-14, "iterations": 1.0}),
    ("end of interval", {"t": 0.95}, {}, {}),
    ("stretched to the end", {"t": 1.0 - 0.1 - 1e-12}, {}, {}),
    ("h underflows", {"h": 1e-15, "t": 0.5}, {}, {}),
    ("rejected h underflows", {"h": 2e-14, "t": 0.5}, {}, {"error_norm": 1e6}),
    ("budget spent", {"attempts": 32.0}, {}, {}),
    ("stale Jacobian, sign flip", {}, {}, {"stale": 1.0, "retry_sign": -1.0}),
    ("refreshed, sign flip", {"jac_kept": 0.0, "det_sign": -1.0}, {}, {}),
    ("stages flip", {}, {}, {"newton_failed": 1.0, "stage_flip": 1.0, "outcome": 2.0}),
]


def _on_floats(carried, settings, attempt):
    """The sequence on Python floats: the head, then the tail of the attempt."""
    head = sequence.before_attempt(SCALAR, carried, settings)
    head.update(sequence.run_head(SCALAR, carried, settings, head["h"]))
    attempt = dict(attempt, **{name: head[name] for name in ("h", "limited", "underflow", "refreshed", "factored")})
    attempt["jac_kept"] = formulas.jacobian_kept(SCALAR, attempt["theta"], settings["reuse_theta"])
    after, decisions = sequence.after_attempt(SCALAR, carried, settings, attempt, S, ITERATIONS)
    scalars, ran, taken, record = sequence.run_tail(SCALAR, carried, settings, attempt, after, decisions)
    return head, after, decisions, scalars, ran, taken, record


def _case(carried, settings, attempt):
    return {**CARRIED, **carried}, {**SETTINGS, **settings}, {**ATTEMPT, **attempt}


def _same(a, b) -> bool:
    """The same float, bit for bit (NaN as NaN)."""
    a, b = float(a), float(b)
    return (math.isnan(a) and math.isnan(b)) or (a == b and math.copysign(1, a) == math.copysign(1, b))


@pytest.mark.parametrize(("name", "carried", "settings", "attempt"), CASES, ids=[case[0] for case in CASES])
def test_the_sequence_gives_the_same_bits_on_floats_and_in_the_compiled_run(name, carried, settings, attempt):
    carried, settings, attempt = _case(carried, settings, attempt)
    head, _, _, scalars, ran, taken, record = _on_floats(carried, settings, attempt)
    compiled_head = loop.head_function()(
        scalars=sequence.SCALARS.pack(**carried), settings=sequence.SETTINGS.pack(**settings)
    )
    for key in sequence.HEAD:
        assert _same(head[key], compiled_head[key]), key
    attempt = dict(attempt, **{key: float(compiled_head[key]) for key in ATTEMPT_FROM_HEAD})
    tail = loop.tail_function(S, ITERATIONS)(
        scalars=sequence.SCALARS.pack(**carried),
        settings=sequence.SETTINGS.pack(**settings),
        attempt=sequence.ATTEMPT.pack(**attempt),
    )
    after = [float(x) for x in tail["after"].full().ravel()]
    for key, value in zip(sequence.SCALARS.names, after, strict=True):
        assert _same(scalars[key], value), key
    assert _same(ran, tail["ran"]) and _same(taken, tail["taken"])
    for key, value in zip(sequence.RECORD, tail["record"].full().ravel(), strict=True):
        assert _same(record[key], value), key


ATTEMPT_FROM_HEAD = ("h", "limited", "underflow", "refreshed", "factored")


def test_the_cases_reach_every_decision():
    """The grid above covers acceptance, rejection, a failed Newton, Gustafsson's prediction binding,
    the keep band, the end of the interval, both underflows and every hand-back."""
    seen = {}
    for name, *parts in CASES:
        head, after, decisions, scalars, ran, taken, _ = _on_floats(*_case(*parts))
        seen[name] = (head, after, decisions, scalars, bool(ran), bool(taken))
    assert seen["accepted"][5] and not seen["rejected"][5] and seen["rejected"][4]
    assert seen["failed Newton"][4] and seen["failed Newton"][1]["first"]  # (the next step does not grow h)
    assert seen["first step"][0]["first"] and seen["after a rejection"][0]["first"] and not seen["accepted"][0]["first"]
    assert not seen["first step beyond the probe's"][0]["first"] and not seen["rejected beyond the probe's"][0]["first"]
    assert seen["rejected beyond the probe's, a step accepted"][0]["first"]
    assert seen["h underflows"][0]["underflow"] and not seen["h underflows"][4]
    assert seen["rejected h underflows"][2]["shrunk_away"] and not seen["rejected h underflows"][4]
    assert seen["end of interval"][3]["active"] == 0 and seen["end of interval"][3]["code"] == sequence.FINISHED
    stretched = seen["stretched to the end"]
    assert stretched[0]["h"] == 1.0 - (1.0 - 0.1 - 1e-12) and stretched[3]["active"] == 0 and stretched[3]["t"] == 1.0
    assert seen["budget spent"][3]["code"] == sequence.LIMIT and not seen["budget spent"][4]
    for handed in ("non-finite", "stale Jacobian, sign flip", "refreshed, sign flip", "stages flip"):
        assert not seen[handed][4] and seen[handed][3]["code"] == sequence.HANDBACK, handed
    # (the band keeps the step taken: 0.1 from t = 0.3 as t's float64 spacing makes it, formulas.step_length)
    kept = seen["keep band"][0]["h"]
    assert kept == (0.3 + 0.1) - 0.3 and seen["keep band"][1]["h"] == kept
    assert seen["keep band, Jacobian dropped"][1]["h"] != kept


def test_factors_serve_a_step_within_the_rounding_of_t_plus_h():
    """The step from t = 0.3 is 0.1 as t's float64 spacing makes it: the factors of the last step's 0.1 (from
    t = 0.2, another rounding) serve it and keep their own h; factors 1e-12 off, or none, are factored anew,
    and then carry the step's h."""
    h = (0.3 + 0.1) - 0.3
    for factors_h, factored in (((0.2 + 0.1) - 0.2, False), (0.1, False), (0.1 * (1 + 1e-12), True), (0.0, True)):
        carried, settings, attempt = _case({"factors_h": factors_h}, {}, {})
        head, _, _, scalars, ran, taken, _ = _on_floats(carried, settings, attempt)
        assert head["h"] == h and bool(head["factored"]) == factored, factors_h
        assert ran and taken and scalars["factors_h"] == (h if factored else factors_h), factors_h
    # (the bound: 64 eps (|t| + |h|), 0.4 here)
    assert not formulas.factors_serve(SCALAR, h, h + 70 * 2.0**-52 * 0.4, 0.3)
    assert formulas.factors_serve(SCALAR, h, h + 58 * 2.0**-52 * 0.4, 0.3)


# RADAU5's formulas written out (Hairer & Wanner IV.8; s = 3, Newton's most 7 iterations, k = 3 of them)
FAC = min(0.9, 0.9 * (2 * 7 + 1) / (2 * 7 + 3))


def _after(carried, settings, attempt):
    carried, settings, attempt = _case(carried, settings, attempt)
    attempt = dict(attempt, h=carried["h"], jac_kept=attempt["theta"] <= settings["reuse_theta"])
    return sequence.after_attempt(SCALAR, carried, settings, attempt, S, ITERATIONS)


def test_an_accepted_step_takes_radau5s_next_h():
    """err = 0.5, no accepted step before: h_new = h fac err^(-1/4), fac = 0.9 (2 7 + 1) / (2 7 + 3)."""
    after, decisions = _after({"h_acc": 0.0, "err_acc": 0.0}, {}, {"error_norm": 0.5})
    assert decisions["accepted"] and decisions["t_next"] == 0.3 + 0.1
    assert after["h"] == pytest.approx(0.1 * FAC * 0.5 ** (-1 / 4), rel=1e-15)
    assert (after["h_acc"], after["err_acc"]) == (0.1, 0.5)
    assert after["t"] == decisions["t_next"] and not after["first"] and not after["rejected_last"]


def test_gustafssons_prediction_takes_the_smaller_h():
    """The last accepted step (0.08, 0.05): h_new = h 0.9 (h / h_acc) (err_acc / err^2)^(1/4), below the
    quotient's; off, the quotient's."""
    after, _ = _after({"err_acc": 0.05}, {}, {"error_norm": 0.5})
    predicted = 0.9 * (0.1 / 0.08) * (0.05 / 0.5**2) ** (1 / 4)
    assert predicted < FAC * 0.5 ** (-1 / 4)
    assert after["h"] == pytest.approx(0.1 * predicted, rel=1e-15)
    off, _ = _after({"err_acc": 0.05}, {"predictive": 0.0}, {"error_norm": 0.5})
    assert off["h"] == pytest.approx(0.1 * FAC * 0.5 ** (-1 / 4), rel=1e-15)


def test_a_rejected_step_shrinks_h_and_a_failed_newton_halves_it():
    """err = 3: h_new = h max(0.2, min(fac err^(-1/4), 0.9)); a failed Newton: h / 2, and the next
    accepted step does not grow h (first)."""
    after, decisions = _after({}, {}, {"error_norm": 3.0})
    assert not decisions["accepted"] and after["t"] == 0.3 and after["rejected_last"]
    assert after["h"] == pytest.approx(0.1 * FAC * 3.0 ** (-1 / 4), rel=1e-15)
    assert (after["h_acc"], after["err_acc"]) == (0.08, 0.7)  # (unchanged)
    failed, decisions = _after({}, {}, {"error_norm": math.inf, "newton_failed": True})
    assert decisions["err"] == math.inf and failed["h"] == 0.05 and failed["first"]


def test_the_statistics_of_records():
    """Three attempts: one accepted, one rejected, one failed in Newton (its stages' Jacobian counted)."""
    sums = dict(ran=3, accepted=1, t=0.0, h=0.0, t_next=0.0, iterations=9, evaluations=14, refreshed=1, factored=1)
    sums.update(retries=2, newton_failed=1)
    stats = dict.fromkeys(sequence.statistics(sums), 0)
    sequence.add_statistics(stats, sums, shifts=2)
    assert stats == dict(
        attempts=3, rejected_steps=1, newton_failures=1, newton_iterations=9, residual_evaluations=14,
        jacobian_evaluations=2, compiled_retries=2, lu_decompositions=4,
    )  # fmt: skip
    own = dict.fromkeys(sequence.CONTROLLER_STATISTICS, 0)
    for accepted, failed in ((True, False), (False, False), (False, True)):
        sequence.add_attempt(own, accepted, failed)
    assert own == {name: stats[name] for name in sequence.CONTROLLER_STATISTICS}

"""Errors across events: a batch's samples paired each with its own impacts, and every refusal of a
reference's stated events."""

import numpy as np
import pytest

import daemodel as dm
from daemodel.errors import ComparisonError
from daemodel.problems import BOUNCING_BALL

EXACT = BOUNCING_BALL.exact_solution()


@pytest.fixture(scope="module")
def ball():
    return dm.solve(BOUNCING_BALL.model(), (0.0, 3.0), method="radau", h=0.01)


def test_a_batch_pairs_each_samples_own_instants():
    """g = 9.81 bounces 6 times on [0, 3], g = 5 three times: each sample's impacts are paired with
    its own in the reference (NaN-padded records), none across samples."""
    t = np.linspace(0.0, 3.0, 61)
    g = {"g": np.array([9.81, 5.0])}
    sol = dm.solve(BOUNCING_BALL.model(), (0.0, 3.0), method="radau", h=0.01, parameters=g, t_eval=t)
    reference = dm.solve(BOUNCING_BALL.model(), (0.0, 3.0), method="reference", parameters=g, t_eval=t)
    assert np.isfinite(sol.events["floor"]["t"]).sum(axis=1).tolist() == [6, 3]
    report = sol.error_report(reference)
    floor = report.instants["floor"]
    assert (floor.count, floor.reference_count) == (9, 9)
    assert floor.t < 1e-11 and floor.values < 1e-10
    assert max(e["max"] for e in report.variables.values()) < 1e-10
    assert report.excluded == 0  # no output time within 1e-9 of an impact on this grid


def test_an_instant_only_one_side_has_is_left_out_with_its_window(ball):
    """A reference that states one impact fewer (the first): the others pair each with its nearest, the
    unpaired impact's output time is left out all the same, and the counts say so."""
    fewer = dict(EXACT.events["floor"])
    fewer["t"] = EXACT.events["floor"]["t"][:, 1:]
    fewer["before"] = {k: v[:, 1:] for k, v in EXACT.events["floor"]["before"].items()}
    fewer["after"] = {k: v[:, 1:] for k, v in EXACT.events["floor"]["after"].items()}

    def reference(t):
        return EXACT(t)

    reference.events = {"floor": fewer}
    report = ball.error_report(reference)
    floor = report.instants["floor"]
    assert (floor.count, floor.reference_count, report.excluded) == (6, 5, 6)
    # the other five paired each with its own (not shifted by one): at the solve's accuracy
    assert floor.t < 1e-12 and floor.values < 1e-13


@pytest.mark.parametrize(
    "events, message",
    [
        ([1, 2], r"the reference's events/breakpoints must be dicts laid out as Solution.events"),
        ({"floor": {"t": [0.45]}}, r"the reference's 'floor' must be a dict with 't', 'before' and 'after'"),
        ({"floor": {"t": "soon", "before": {}, "after": {}}}, r"'floor': 't' is not a \(K,\) or \(B, K\) array"),
        (
            {"floor": {"t": np.zeros((3, 1)), "before": {}, "after": {}}},
            r"'floor': 't' has 3 rows; the solution has 1 samples",
        ),
        ({"floor": {"t": [0.45], "before": [0.0], "after": {}}}, r"'floor': 'before' must be a dict name -> values"),
        (
            {"floor": {"t": [0.45], "before": {"v": [1.0, 2.0]}, "after": {}}},
            r"'floor': 'before' of 'v' has shape \(1, 2\), its times \(1, 1\)",
        ),
    ],
)
def test_a_references_events_not_laid_out_as_a_solutions_are_refused(ball, events, message):
    def reference(t):
        return EXACT(t)

    reference.events = events
    with pytest.raises(ComparisonError, match=message):
        ball.errors(reference)

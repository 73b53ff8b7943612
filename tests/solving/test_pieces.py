"""merge_stats: the stats of pieces solved one after another (events, breakpoints) as one, on the
stats a Solution holds (daemodel.stats.Stats: its lists of numbers are arrays)."""

import numpy as np

from daemodel.solving.pieces import merge_stats
from daemodel.stats import Stats


def test_counters_sum_and_extremes_take_the_largest_and_smallest():
    merged = merge_stats(
        [Stats({"steps": 3, "h_max": 0.5, "h_min": 0.1}), Stats({"steps": 4, "h_max": 0.2, "h_min": 0.01})]
    )
    assert merged == {"steps": 7, "h_max": 0.5, "h_min": 0.01}


def test_a_piece_without_steps_neither_hides_nor_replaces_the_others_figures():
    for pieces in ([[1.0, 2.0], []], [[], [1.0, 2.0]], [[], [1.0], [], [2.0]]):
        merged = merge_stats([Stats({"local_error_estimates": p}) for p in pieces])
        np.testing.assert_array_equal(merged["local_error_estimates"], [1.0, 2.0])


def test_integer_and_float_figures_join_in_order():
    merged = merge_stats([Stats({"local_error_estimates": [1, 2]}), Stats({"local_error_estimates": [0.5]})])
    np.testing.assert_array_equal(merged["local_error_estimates"], [1.0, 2.0, 0.5])


def test_rows_of_different_widths_are_padded_with_nan_not_dropped():
    merged = merge_stats([Stats({"per_stage": [[1, 2]]}), Stats({"per_stage": [[0.5, 1, 3]]})])
    np.testing.assert_array_equal(merged["per_stage"], [[1.0, 2.0, np.nan], [0.5, 1.0, 3.0]])


def test_lists_of_other_things_still_concatenate():
    merged = merge_stats([Stats({"integrator": ["LSODA"]}), Stats({"integrator": ["Radau"]})])
    assert merged == {"integrator": ["LSODA", "Radau"]}


def test_a_batch_solved_in_groups_counts_every_samples_events_and_all_its_samples():
    """A batch with events is solved sample by sample (groups) and joined: its stats said the first
    group's ``events`` and ``batch`` (1 and 1 for three balls that bounce 1, 2 and 3 times)."""
    import daemodel as dm

    m = dm.Model("ball")
    h, v = m.states("h v")
    m.ode(h, v)
    m.ode(v, -9.81)
    m.initial(h=1.0, v=0.0)
    m.event("floor", "h", direction=-1, reset={"v": "-0.8*v"})
    heights = [3.0, 1.0, 0.5]  # first bounces at sqrt(2 h / g): 0.78, 0.45, 0.32; the next 1.6 sqrt(2 h / g) later
    alone = [dm.solve(m, (0.0, 1.3), y0={"h": h0, "v": 0.0}, rtol=1e-8).stats["events"] for h0 in heights]
    assert alone == [1, 2, 3]
    batch = dm.solve(m, (0.0, 1.3), y0={"h": heights, "v": [0.0] * 3}, t_eval=[0.0, 0.5, 1.3], rtol=1e-8)
    assert batch.stats["groups"] == 3 and batch.stats["batch"] == 3 and batch.stats["events"] == 6


def test_a_batch_solved_in_groups_counts_every_samples_location_trials():
    """A batch with switches, its samples solved alone and joined: its ``location_trials`` (and
    ``searches_continued``, ``near_miss_checks``) were the first sample's (4 for 20 samples in float32:
    tests/solving/test_batches.py read it as the batch's), now every sample's, as ``location_steps`` was."""
    import daemodel as dm

    m = dm.Model("min")
    m.states("x")
    m.ode("x", "-Min(1, x)")
    m.initial(x=2.0)
    x0 = [1.2, 2.0, 2.8]
    alone = []
    for value in x0:
        m.initial(x=value)
        alone.append(dm.solve(m, (0.0, 3.0)).stats)
    for options in ({}, {"t_eval": np.linspace(0.0, 3.0, 7)}):
        batch = dm.solve(m, (0.0, 3.0), y0={"x": x0}, **options).stats
        for key in ("location_trials", "location_steps", "searches_continued", "near_miss_checks"):
            assert batch[key] == sum(stats[key] for stats in alone), key
        assert batch["location_trials"] >= len(x0)  # (at least one trial each)

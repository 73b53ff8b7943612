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

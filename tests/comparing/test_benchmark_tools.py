"""The benchmarks' own arithmetic: how a time at equal error is read off a work-precision sweep."""

import importlib.util
import math
import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks"


def _benchmark(name: str):
    """The benchmark script ``benchmarks/<name>.py`` as a module (its folder on sys.path meanwhile)."""
    sys.path.insert(0, str(BENCHMARKS))
    try:
        spec = importlib.util.spec_from_file_location(name, BENCHMARKS / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        yield module
    finally:
        sys.path.remove(str(BENCHMARKS))


@pytest.fixture(scope="module")
def adaptive_precision():
    yield from _benchmark("adaptive_precision")


def test_time_at_error_interpolates_in_log_log(adaptive_precision):
    time_at_error = adaptive_precision.time_at_error
    # time = error^(-1/2) on three points: exact in log-log, whatever the order of the points
    points = [(1e-8, 1e4), (1e-4, 1e2), (1e-6, 1e3)]
    seconds, relation = time_at_error(points, 1e-7)
    assert relation == "=" and seconds == pytest.approx(10**3.5, rel=1e-12)
    assert time_at_error(points, 1e-6) == (pytest.approx(1e3), "=")


def test_time_at_error_uses_the_monotone_envelope_and_never_extrapolates(adaptive_precision):
    time_at_error = adaptive_precision.time_at_error
    # (1e-5, 50 s) costs more than the more accurate (1e-6, 20 s): it is off the envelope, and 1e-5
    # is read between (1e-6, 20) and (1e-4, 10), half-way in log: 20 * (10 / 20)^(1/2)
    points = [(1e-4, 10.0), (1e-5, 50.0), (1e-6, 20.0), (1e-8, 40.0)]
    seconds, relation = time_at_error(points, 1e-5)
    assert relation == "=" and seconds == pytest.approx(10 * math.sqrt(2), rel=1e-12)
    assert time_at_error(points, 1e-9) == (40.0, ">")  # beyond the most accurate point: a lower bound
    assert time_at_error(points, 1e-3) == (10.0, "<")  # looser than every point: an upper bound
    assert time_at_error([(math.nan, 1.0), (0.0, 2.0)], 1e-6) == (None, "")
    assert time_at_error(points, -1.0) == (None, "")


@pytest.fixture(scope="module")
def radau_idas():
    yield from _benchmark("radau_idas")


def test_peak_relative_error_scales_each_variable_by_its_own_peak(radau_idas):
    error = radau_idas.peak_relative_error
    reference = {"big": [0.0, 100.0, -200.0], "small": [1e-5, -4e-5, 0.0], "zero": [0.0, 0.0, 0.0]}
    values = {"big": [0.0, 101.0, -200.0], "small": [1e-5, -3e-5, 0.0], "zero": [0.0, 1e-9, 0.0]}
    # big: 1 / 200 = 5e-3; small: 1e-5 / 4e-5 = 0.25 (an absolute error 1e5 times smaller counts more)
    assert error(values, reference, ["big"]) == (pytest.approx(5e-3, rel=1e-12), "big")
    assert error(values, reference, ["big", "small"]) == (pytest.approx(0.25, rel=1e-12), "small")
    # a reference that is zero throughout is measured absolutely, not divided by zero
    assert error(values, reference, ["zero"]) == (pytest.approx(1e-9, rel=1e-12), "zero")
    assert error(values, reference, []) == (None, None)
    assert error({**values, "big": [math.nan, 0.0, 0.0]}, reference, ["big", "small"])[1] == "big"  # NaN: the worst
    with pytest.raises(ValueError, match=r"'big': values have shape \(2,\), the reference \(3,\)"):
        error({"big": [0.0, 1.0]}, reference, ["big"])


def test_worst_ratio_keeps_the_bounds_relation(radau_idas):
    worst, meets = radau_idas.worst_ratio, radau_idas.meets
    assert worst([]) is None and meets(None, 1.0) is None
    exact = worst([{"ratio": 0.8, "relation": "="}, {"ratio": 0.5, "relation": "<"}])
    assert exact == {"ratio": 0.8, "relation": "=", "points": 2} and meets(exact, 1.0) is True
    # the largest value an upper bound: the worst is at most it
    upper = worst([{"ratio": 0.8, "relation": "="}, {"ratio": 1.5, "relation": "<"}])
    assert upper["ratio"] == 1.5 and upper["relation"] == "<"
    assert meets(upper, 2.0) is True and meets(upper, 1.0) is None
    # a lower bound anywhere: the worst is at least the largest exact or lower-bound value
    lower = worst([{"ratio": 1.5, "relation": "="}, {"ratio": 0.9, "relation": ">"}, {"ratio": 3.0, "relation": "<"}])
    assert lower["ratio"] == 1.5 and lower["relation"] == ">"
    assert meets(lower, 1.0) is False and meets(lower, 2.0) is None


@pytest.fixture(scope="module")
def bench_tables():
    yield from _benchmark("bench_tables")


def test_bench_tables_read_the_most_digits_and_one_tolerance_off_the_runs(bench_tables):
    def run(problem, method, status, scd, solve, error_class=None, component="y"):
        return {"problem": problem, "method": method, "status": status, "scd": scd, "solve_time": solve,
                "error_class": error_class, "scd_component": component, "flag": None, "reason": None}  # fmt: skip

    results = {
        "problems": [{"name": "a"}, {"name": "b"}],
        "methods": ["radau", "pinn"],
        "runs": [
            run("a", "radau", "success", 6.0, 0.002), run("a", "radau", "success", 9.25, 0.004),
            run("a", "radau", "flagged", 12.0, 0.001), run("a", "pinn", "failed", None, 60.0, "TimeLimitError"),
            run("a", "pinn", "failed", None, 61.0, "TimeLimitError"), run("b", "radau", "success", 3.0, 2.5),
            run("b", "pinn", "skipped", None, None),
        ],
    }  # fmt: skip
    assert bench_tables.most_digits(results) == [
        "| problem | radau | pinn |",
        "|---|---:|---:|",
        "| a | 9.2 (4 ms) | none: 2 TimeLimitError |",
        "| b | 3.0 (2.5 s) | none: skipped |",
    ]
    one = {**results, "runs": [results["runs"][1], results["runs"][3], results["runs"][5]]}
    assert bench_tables.at_one_tolerance(one)[2:] == [
        "| a | 9.2 (y, 4 ms) | failed: TimeLimitError |",
        "| b | 3.0 (y, 2.5 s) |  |",
    ]


def test_bench_tables_ties_unrun_methods_bars_and_more_than_one_tolerance(bench_tables):
    """Of tied digits the fastest run (as the report's table against radau; it took the first in the
    file), 'none: no run' for a method with no run on a problem (it printed 'none: '), a '|' in a
    settings string escaped (it split the row), and --at-one-tolerance refuses a results.json with two
    runs of a method on a problem (it printed the last one read)."""

    def run(problem, method, scd, solve, settings="s"):
        return {"problem": problem, "method": method, "status": "success", "scd": scd, "solve_time": solve,
                "error_class": None, "scd_component": "y", "flag": None, "reason": None,
                "settings": settings}  # fmt: skip

    results = {
        "problems": [{"name": "a"}, {"name": "b"}],
        "methods": ["radau", "pinn"],
        "runs": [run("a", "radau", 9.0, 0.004), run("a", "radau", 9.0, 0.001), run("a", "pinn", 5.0, 0.2)],
    }
    assert bench_tables.most_digits(results)[2:] == [
        "| a | 9.0 (1 ms) | 5.0 (200 ms) |",
        "| b | none: no run | none: no run |",
    ]
    with pytest.raises(SystemExit, match=r"^radau has more than one run on a \(s\): --at-one-tolerance reads"):
        bench_tables.at_one_tolerance(results)
    hostile = {"problem": "a", "method": "pinn", "none": None, "scd": 5.0, "settings": "h=0.1 | <b>",
               "wall": 1.0, "solve": 0.1, "radau_scd": 6.0, "radau_solve": 0.01, "wall_ratio": 100.0,
               "solve_ratio": 10.0}  # fmt: skip
    table = bench_tables.against_radau_table({"against_radau": [hostile]})
    mine = "5.0 scd at h=0.1 \\| <b>: 1 s setup + solve, 100 ms solve"
    assert table[2] == f"| a | pinn | {mine} | 6.0 scd in 10 ms | 100x (10x solve) |"

"""The benchmarks' own arithmetic: how a time at equal error is read off a work-precision sweep."""

import importlib.util
import math
import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parent.parent / "benchmarks"


@pytest.fixture(scope="module")
def adaptive_precision():
    sys.path.insert(0, str(BENCHMARKS))
    try:
        spec = importlib.util.spec_from_file_location("adaptive_precision", BENCHMARKS / "adaptive_precision.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        yield module
    finally:
        sys.path.remove(str(BENCHMARKS))


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

"""daemodel.testing.assert_solutions_close: passes when close, and its messages name the
variable, the time, the sample and both values."""

import re

import numpy as np
import pytest

import daemodel as dm
from daemodel.problems import HESSENBERG
from daemodel.testing import assert_solutions_close

EXACT = HESSENBERG.exact_solution()


@pytest.fixture(scope="module")
def compiled():
    return HESSENBERG.model().compile()


@pytest.fixture(scope="module")
def radau(compiled):
    return dm.solve(compiled, (0.0, 0.5), method="radau", stages=3, h=0.05)


def test_close_solutions_pass_and_the_tolerance_is_respected(compiled, radau):
    collocation = dm.solve(compiled, (0.0, 0.5), method="casadi-collocation", stages=3, h=0.05)
    assert_solutions_close(collocation, radau, atol=1e-10, rtol=0)
    assert_solutions_close(radau, EXACT, atol=1e-7, rtol=0)  # the s = 3 error is 2e-8 here
    with pytest.raises(AssertionError):
        assert_solutions_close(radau, EXACT, atol=1e-10, rtol=0)


def test_message_names_variable_time_and_both_values(compiled, radau):
    shifted = dm.solve(compiled, (0.0, 0.5), method="radau", stages=3, h=0.05, y0={"y2": 1.001, "y4": 1.001})
    with pytest.raises(AssertionError) as info:
        assert_solutions_close(shifted, radau, atol=1e-6)
    message = str(info.value)
    # y1 is the first variable; its largest difference is at the end of the interval
    assert message.startswith("y1 differs at t = 0.5: actual (radau) 2.7") and ", desired (radau) 2.71828" in message
    assert "values of y1 are out of tolerance" in message
    expected = re.escape("y2 differs at t = 0: actual (radau) 1.001, desired 1.0 (|difference| 0.001 > atol + rtol*")
    with pytest.raises(AssertionError, match=expected):
        assert_solutions_close(shifted, EXACT, atol=1e-6, names=["y2"])


def test_batch_names_the_sample_and_nan_is_a_violation(compiled):
    y0 = np.array([[1.0, 1.0, 1.0, 1.0], [1.0, 1.01, 1.0, 1.01]])
    batch = dm.solve(compiled, (0.0, 0.2), method="radau", stages=3, h=0.05, y0=y0)
    with pytest.raises(AssertionError, match=r"^y1 differs at t = 0\.2, sample 1: actual \(radau\) "):
        assert_solutions_close(batch, EXACT, atol=1e-6)
    nan_exact = lambda t: {**EXACT(t), "y3": np.full_like(t, np.nan)}  # noqa: E731
    with pytest.raises(AssertionError, match=r"^y3 differs at t = 0, sample 0: actual \(radau\) 1\.0, desired nan"):
        assert_solutions_close(batch, nan_exact, atol=1.0, names=["y3"])


def test_mismatched_inputs_are_named(compiled, radau):
    other = dm.solve(compiled, (0.0, 0.5), method="radau", stages=3, h=0.1, dense_output=False)
    times = r"the reference \(radau\) has 6 times from 0 to 0\.5, this solution \(radau\) 11 from 0 to 0\.5"
    with pytest.raises(AssertionError, match=times):
        assert_solutions_close(radau, other)
    batch = dm.solve(compiled, (0.0, 0.5), method="radau", stages=3, h=0.05, y0=np.ones((2, 4)))
    with pytest.raises(AssertionError, match="different batch sizes: 1 and 2"):
        assert_solutions_close(radau, batch)
    with pytest.raises(AssertionError, match=r"cannot compare \['y9'\]"):
        assert_solutions_close(radau, EXACT, names=["y9"])
    with pytest.raises(TypeError, match="actual must be a Solution; got ndarray"):
        assert_solutions_close(np.zeros(3), radau)
    with pytest.raises(TypeError, match="desired must be a Solution or a callable"):
        assert_solutions_close(radau, 3.0)

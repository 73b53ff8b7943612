"""Solution (daemodel/solution.py): what its methods refuse, by name."""

import numpy as np
import pytest
import sympy as sp

import daemodel as dm
from daemodel import errors as E
from daemodel.problems import DECAY


@pytest.fixture(scope="module")
def decay():
    return dm.solve(DECAY.model(), (0.0, 1.0), h=0.1, stages=3)


def test_at_refuses_times_that_are_not_numbers(decay):
    """Before: "0.5" was parsed as 0.5 and True taken as t = 1."""
    with pytest.raises(E.InvalidValueError, match=r"at\(\): times must be real numbers; got the string '0.5'"):
        decay.at("0.5")
    with pytest.raises(E.InvalidValueError, match=r"at\(\): times must be real numbers; got booleans, the first True"):
        decay.at(True)
    with pytest.raises(E.InvalidValueError, match=r"got complex numbers \(the imaginary part would be dropped\)"):
        decay.at([0.5 + 0.1j])
    with pytest.raises(E.InvalidValueError, match=r"at\(\): times\[1\] must be a real number; got None"):
        decay.at([0.5, None])
    # numbers of every kind are times
    exact = decay.at(0.5)["y"]
    for t in (np.float32(0.5), sp.Rational(1, 2), [sp.S.Half], np.array([0.5])):
        assert np.atleast_1d(decay.at(t)["y"]) == pytest.approx(np.atleast_1d(exact), rel=1e-12)


def test_gradient_data_must_be_real_measurements():
    sol = dm.solve(DECAY.model(), (0.0, 1.0), h=0.1, stages=3, sensitivities=["k"])
    good = sol["y"] + 0.01
    with pytest.raises(E.DataError, match=r"gradient: the data for 'y' must be real numbers; got strings"):
        sol.gradient({"y": [str(v) for v in good]}, ["k"])
    with pytest.raises(E.DataError, match=r"the data for 'y' must be real numbers; got complex numbers"):
        sol.gradient({"y": good + 1e-3j}, ["k"])
    with pytest.raises(E.DataError, match=r"the data for 'y' are NaN everywhere: a series with no measurement"):
        sol.gradient({"y": np.full_like(good, np.nan)}, ["k"])  # (before: 0.0)
    assert sol.gradient({"y": good}, ["k"])["k"] != 0.0

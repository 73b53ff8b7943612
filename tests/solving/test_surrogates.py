"""Surrogate.solve (daemodel/solving/surrogates.py): what ends it."""

import numpy as np
import pytest


def test_a_time_limit_ends_a_surrogate_solve_instead_of_splitting_its_samples():
    """Surrogate.solve halves a part whose radau fails down to the samples that fail alone, then
    solves those again from their own start: a time limit was such a failure."""
    from types import SimpleNamespace

    from daemodel.errors import TimeLimitError
    from daemodel.solving.surrogates import Surrogate

    calls = []

    def struck(*_):
        calls.append(1)
        raise TimeLimitError("stop here")

    stub = SimpleNamespace(grid=np.linspace(0.0, 1.0, 3), compiled=SimpleNamespace(states=["y"], algebraics=[]))
    stub._radau = struck
    with pytest.raises(TimeLimitError, match=r"^stop here$"):
        Surrogate._collocation(stub, None, np.arange(8))
    assert calls == [1]

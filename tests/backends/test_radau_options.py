"""radau's options (backends/radau/options.py): adaptive steps with two stages are refused on systems of
index 2 and 3, and still run on index 1, and on a fixed grid."""

import numpy as np
import pytest
from daemodel.backends.radau.options import MIN_ADAPTIVE_STAGES_INDEX2

import daemodel as dm
from daemodel import errors as E
from daemodel.problems import CAR_AXIS, PENDULUM, SQUEEZER


def test_two_stages_are_refused_adaptive_steps_on_index_2_and_3():
    """The squeezer with two stages ended 1,000-1,600 rtol off in its velocities at rtol 1e-3 to 1e-9 and
    said success: on index 2 (and 3, solved as its index-2 reduction) adaptive steps need three stages;
    the refusal names the system, why, and what to give, for the default tolerances too."""
    assert MIN_ADAPTIVE_STAGES_INDEX2 == 3
    for problem, shown in ((SQUEEZER, "index-2 system of 'squeezer'"), (CAR_AXIS, "index-2 system of 'car-axis'")):
        compiled = problem.model().compile()
        with pytest.raises(E.InvalidOptionError, match=f"stages = 2 cannot take adaptive steps on the {shown}"):
            dm.solve(compiled, problem.t_span, rtol=1e-5, atol=1e-5, stages=2)
    pendulum = PENDULUM.model().compile()
    with pytest.raises(E.InvalidOptionError, match=r"give stages >= 3 \(or leave stages out\), or h=\.\.\. for a"):
        dm.solve(pendulum, (0.0, 1.0), stages=2)  # the default tolerances are adaptive too
    with pytest.raises(E.InvalidOptionError, match=r"an index-3 model is solved as its index-2 reduction"):
        dm.solve(CAR_AXIS.model().compile(), (0.0, 0.1), rtol=1e-4, stages=2)


def test_two_stages_still_run_fixed_steps_on_index_2_and_adaptive_ones_on_index_1():
    """The refusal is no wider than the measurement: a fixed grid of two stages on the pendulum (index 2)
    keeps |y| = 1 (the rod) to 1e-6, and adaptive two-stage steps on an index-1 system meet its
    closed form ``y = e^-t``, ``z = y^2``."""
    fixed = dm.solve(PENDULUM.model().compile(), (0.0, 1.0), stages=2, h=0.01)
    assert fixed.status == "success"
    radius = np.hypot(np.ravel(fixed["y1"]), np.ravel(fixed["y2"]))
    assert np.max(np.abs(radius - 1.0)) < 1e-6
    m = dm.Model("index1")
    (y,) = m.states("y")
    (z,) = m.algebraics("z")
    m.ode(y, -z / y)
    m.constraint(z - y**2, name="square")
    m.initial(y=1.0)
    sol = dm.solve(m.compile(), (0.0, 1.0), rtol=1e-6, atol=1e-6, stages=2)
    assert sol.status == "success"
    t = np.asarray(sol.t, dtype=float)
    assert np.max(np.abs(np.ravel(sol["y"]) - np.exp(-t))) < 1e-4
    assert np.max(np.abs(np.ravel(sol["z"]) - np.exp(-2 * t))) < 1e-4

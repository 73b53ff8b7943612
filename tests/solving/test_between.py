"""What the event functions do between a solve's outputs (daemodel/solving/between.py): an excursion narrower than
the zoom's grids, against the exact crossings."""

import math

import numpy as np
import pytest

import daemodel as dm

# radau's default on casadi's virtual machine, but in the tests marked machine_code (tests/conftest.py)
pytestmark = pytest.mark.virtual_machine


@pytest.mark.parametrize("depth", [1e-8, 1e-10])
@pytest.mark.parametrize("rtol", [1e-12, 1e-10])
def test_a_switch_excursion_narrower_than_the_zoom_s_grid_is_seen(depth, rtol):
    # x = (t - 1)^2 - depth is below zero for 2 sqrt(depth) (2e-4, 2e-5) about t = 1; radau integrates it exactly
    # in steps of ~0.4, and the zoom's grids (last spacing 1.6e-4) missed it: y' = 3 instead of 1 over it was
    # never taken, y 4e-4 and 4e-5 off at rtol 1e-12 (4e8 and 4e7 tolerances), "success"
    m = dm.Model("narrow_excursion")
    m.states("x y")
    m.ode("x", "2*(t - 1)")
    m.ode("y", "Piecewise((1, x > 0), (3, True))")
    m.initial(x=1.0 - depth, y=0.0)
    sol = dm.solve(m, (0.0, 2.0), method="radau", rtol=rtol, atol=rtol)
    half = math.sqrt(depth)
    assert sol.status == "success"
    np.testing.assert_allclose(sol.events["Piecewise in y'"]["t"].ravel(), [1 - half, 1 + half], atol=1e-8)
    assert abs(sol["y"][-1] - (2.0 + 4.0 * half)) < 1e3 * rtol

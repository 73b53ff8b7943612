"""Numerical stability on hard cases; each test prints the numbers it measured."""

import numpy as np
import pytest

import daemodel as dm
from daemodel import errors as E
from daemodel.problems import PENDULUM, PENDULUM_INDEX3, ROBERTSON


def robertson() -> dm.Model:
    return ROBERTSON.model()


def test_robertson_stiff_to_1e5_adaptive():
    times = np.concatenate([[0.0], np.logspace(-5, 5, 21)])
    sol = dm.solve(robertson(), (0.0, 1e5), rtol=1e-6, atol=1e-10, t_eval=times)
    ref = dm.solve(
        robertson(), (0.0, 1e5), method="reference", integrator="Radau", rtol=1e-10, atol=1e-14, t_eval=times
    )
    # error in units of the requested tolerance rtol |y| + atol
    relative = {n: np.max(np.abs(sol[n] - ref[n]) / (1e-6 * np.abs(ref[n]) + 1e-10)) for n in ("y1", "y2", "y3")}
    print(
        f"Robertson to 1e5: steps {sol.stats['steps']}, rejected {sol.stats['rejected_steps']}, "
        f"errors in units of the tolerance {relative}, mass drift {sol.drift()['mass']:.1e}"
    )
    assert max(relative.values()) < 20
    assert sol.stats["steps"] < 300  # a stiff solver: an explicit method would need ~1e8 steps
    assert sol.drift()["mass"] < 1e-12


@pytest.mark.parametrize("stages", [3, 5, 7])
def test_robertson_loose_tolerance_with_many_stages(stages):
    """At rtol = atol = 1e-4, y2 (~1e-5) is below the tolerance and the polynomial extrapolated from
    the last step makes a poor Newton start for s = 5 and 7 (contraction ~1e3 at h ~ 0.01): Newton
    restarts from the step's start value instead of shrinking h (before: > 300 attempts by t = 0.2)."""
    times = np.concatenate([[0.0], np.logspace(-5, np.log10(40), 11)])
    sol = dm.solve(robertson(), (0.0, 40.0), stages=stages, rtol=1e-4, atol=1e-4, t_eval=times, max_steps=300)
    ref = dm.solve(
        robertson(), (0.0, 40.0), method="reference", integrator="Radau", rtol=1e-10, atol=1e-14, t_eval=times
    )
    relative = {n: np.max(np.abs(sol[n] - ref[n]) / (1e-4 * np.abs(ref[n]) + 1e-4)) for n in ("y1", "y2", "y3")}
    print(f"Robertson s = {stages} at 1e-4: {sol.stats['attempts']} attempts, errors in tolerance units {relative}")
    assert sol.stats["attempts"] < 40
    assert max(relative.values()) < 1


def test_index3_pendulum_is_reduced_to_index2():
    c = PENDULUM_INDEX3.model().compile()
    assert c.index == 3
    sol = dm.solve(c, (0.0, 1.0), stages=3, h=0.01)
    assert sol.compiled.index == 2 and sol.compiled.reduced_from == 3
    ref = dm.solve(c, (0.0, 1.0), method="reference", t_eval=sol.t)
    errors = sol.errors(ref)
    drift = sol.drift()
    print(f"index-3 pendulum via index 2, h=0.01: errors {errors}, drift {drift}")
    assert max(e["max"] for e in errors.values()) < 1e-6
    assert drift["rod'"] < 1e-12  # enforced at every stage
    assert drift["rod"] < 1e-10  # position level: drifts, but only at the discretisation error


def test_pendulum_long_time_drift():
    c = PENDULUM.model().compile()
    sol = dm.solve(c, (0.0, 100.0), stages=3, h=0.05)
    energy = 0.5 * (sol["y3"] ** 2 + sol["y4"] ** 2) + sol["y2"]  # m = lam = 1
    radius = sol["y1"] ** 2 + sol["y2"] ** 2
    energy_drift = np.max(np.abs(energy - energy[0]))
    radius_drift = np.max(np.abs(radius - radius[0]))
    print(
        f"pendulum on [0, 100], s=3, h=0.05: velocity constraint {sol.drift()['velocity']:.1e}, "
        f"energy drift {energy_drift:.1e}, radius drift {radius_drift:.1e}"
    )
    assert sol.drift()["velocity"] < 1e-13
    assert energy_drift < 1e-6 and radius_drift < 1e-6
    assert np.all(np.isfinite(sol["y5"]))


def test_float32_error_is_reported_and_never_silent():
    c = PENDULUM.model().compile()
    ref = dm.solve(c, (0.0, 1.0), method="reference", t_eval=np.linspace(0, 1, 21))
    f64 = dm.solve(c, (0.0, 1.0), stages=3, h=0.05)
    f32 = dm.solve(c, (0.0, 1.0), stages=3, h=0.05, dtype="float32")
    e64, e32 = (max(e["max"] for e in s.errors(ref).values()) for s in (f64, f32))
    print(f"pendulum s=3 h=0.05: float64 max error {e64:.1e}, float32 {e32:.1e}")
    assert f32.stats["dtype"] == "float32" and f64.stats["dtype"] == "float64"
    assert e64 < 2e-5 and e32 < 1e-3
    with pytest.raises(E.InvalidOptionError, match="below what float32 can deliver"):
        dm.solve(c, (0.0, 1.0), rtol=1e-8, dtype="float32")
    with pytest.raises(E.InvalidOptionError, match="below 10 eps of float32"):
        dm.solve(c, (0.0, 1.0), h=0.05, newton_tol=1e-10, dtype="float32")

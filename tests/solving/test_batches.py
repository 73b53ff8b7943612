"""A batch without t_eval whose model switches on its states (daemodel/solving/batches.py): each sample's
switch located, as one sample alone or a batch on t_eval has it.  Before: x' = -Min(1, x) from x0 = 1.2, 2,
2.8 stepped across the switch at x = 1 and ended up to 9.2e-7 off at the default tolerance (3 rtol of
x(3) = 0.30), "success" (one at a time, or on t_eval: 7e-12)."""

import math

import numpy as np

import daemodel as dm

X0 = np.array([1.2, 2.0, 2.8])


def _exact(x0, t):
    """x = x0 - t until x = 1 (t = x0 - 1), then x = exp(-(t - (x0 - 1)))."""
    switch = x0 - 1.0
    return x0 - t if t <= switch else math.exp(-(t - switch))


def _model():
    m = dm.Model("min")
    m.states("x")
    m.ode("x", "-Min(1, x)")
    m.initial(x=2.0)
    return m


def test_a_batch_without_t_eval_locates_each_samples_switch():
    sol = dm.solve(_model(), (0.0, 3.0), y0={"x": X0})
    assert sol.status == "success" and sol["x"].shape == (len(X0), len(sol.t))
    for b, x0 in enumerate(X0):
        exact = np.array([_exact(x0, t) for t in sol.t])
        assert np.all(np.abs(sol["x"][b] - exact) <= 1e-8 + 1e-6 * np.abs(exact))  # (the default tolerance)
        assert abs(sol["x"][b][-1] - exact[-1]) <= 1e-10  # (was 9.2e-7 at t = 3; located: 7e-12)
        assert np.abs(sol.t - (x0 - 1.0)).min() <= 1e-10  # (each sample's switch is an output time)
    assert sol.stats["events"] == len(X0)


def test_a_batch_without_t_eval_agrees_with_its_samples_alone():
    sol = dm.solve(_model(), (0.0, 3.0), y0={"x": X0}, rtol=1e-9, atol=1e-9)
    for b, x0 in enumerate(X0):
        m = _model()
        m.initial(x=float(x0))
        alone = dm.solve(m, (0.0, 3.0), rtol=1e-9, atol=1e-9)
        shared = np.isin(sol.t, alone.t)
        assert shared.sum() == len(alone.t)  # (the batch's times hold every sample's own)
        np.testing.assert_allclose(sol["x"][b][shared], alone["x"], rtol=0, atol=1e-11)
        assert abs(alone["x"][-1] - _exact(x0, 3.0)) <= 1e-9

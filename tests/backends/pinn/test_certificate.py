"""The certificate's copy of radau's own fixed-step error estimate (backends/pinn/certificate.py):
on the PINN's steps it is the estimate radau computes on its own, step for step."""

import numpy as np
import pytest
from daemodel.backends.base import DEFAULT_ESTIMATE_BOUND

import daemodel as dm
from daemodel.problems import HESSENBERG, PENDULUM, PENDULUM_INDEX3


@pytest.mark.parametrize(("problem", "h"), [(HESSENBERG, 0.05), (PENDULUM, 0.1), (PENDULUM_INDEX3, 0.05)])
def test_the_certificates_estimate_is_radaus_own(problem, h):
    """Per step, the largest estimate (in units of 1 + max|u| so far) equals radau's to 1e-6
    (radau with a fresh Jacobian every step, as the certificate takes it at each step's start), and
    so does the largest index-weighted one, which LOCAL_ERROR_BOUND bounds."""
    c = problem.model().compile()
    radau = dm.solve(c, (0.0, 1.0), method="radau", h=h, stages=3, reuse_jacobian=False)
    pinn = dm.solve(c, (0.0, 1.0), method="pinn", h=h, stages=3)
    summary = pinn.stats["certificate"]
    assert summary["max_local_error_estimate"] == pytest.approx(max(radau.stats["local_error_estimates"]), rel=1e-6)
    assert summary["max_weighted_local_error_estimate"] == pytest.approx(
        radau.stats["max_local_error_estimate"], rel=1e-6
    )


def test_the_estimate_per_step_and_where_it_is_beyond_the_bound():
    """certify's Certificate.estimate, step by step, against radau's per-step list; beyond_bound()
    names no step on a smooth problem."""
    from daemodel.backends.pinn.certificate import certify
    from daemodel.backends.pinn.config import PINNConfig
    from daemodel.backends.pinn.segments import train_segments

    from daemodel.compiling.initial_states import initial_states
    from daemodel.solving.surrogates import Surrogate

    c = HESSENBERG.model().compile()
    config = PINNConfig(h=0.1)
    grid = np.linspace(0.0, 1.0, 11)
    start = initial_states(c)
    networks, stats = train_segments(c, config, grid, start.y0, start.z0, start.p, [], False, "pinn")
    surrogate = Surrogate(c, config, grid, networks, (), stats)
    values, predictions = surrogate.trajectory(start, stages=True)
    certificate = certify(c, config, grid, surrogate.networks, (), values, start.p, predictions=predictions)
    radau = dm.solve(c, (0.0, 1.0), method="radau", h=0.1, stages=3, reuse_jacobian=False)
    assert certificate.estimate.shape == (1, 10, 5)
    assert np.allclose(certificate.estimate[0].max(axis=1), radau.stats["local_error_estimates"], rtol=1e-6, atol=0)
    assert certificate.beyond_bound() is None


def test_radau_and_the_certificate_judge_the_estimate_through_one_function(monkeypatch):
    """radau's fixed step and the certificate's copy of its estimate both go through
    fixed_step_units (the refilter and where it may lower the estimate written once): on y' = -1e6 (y - cos t)
    from 0.95 at h = 0.01, where the first step is refiltered (its unfiltered estimate 2.6e-2), the
    calls of each give the same estimates per step (rows), to 1e-6, and the same status."""
    from daemodel.backends.radau import error

    calls, original = [], error.fixed_step_units

    def spy(*args):
        calls.append(original(*args))
        return calls[-1]

    monkeypatch.setattr(error, "fixed_step_units", spy)
    m = dm.Model("stiff")
    m.states("y")
    m.ode("y", "-1e6*(y - cos(t))")
    m.initial(y=0.95)
    radau = dm.solve(m, (0.0, 0.04), method="radau", h=0.01, reuse_jacobian=False)
    per_step = np.concatenate(calls)[:, 0]
    assert len(calls) == 4 and np.allclose(per_step, radau.stats["local_error_estimates"], rtol=1e-12)
    calls.clear()
    pinn = dm.solve(m, (0.0, 0.04), method="pinn", h=0.01)
    rows = np.concatenate(calls)[:, 0]  # (segment k of the one sample: row k)
    assert rows.shape == (4,) and np.allclose(rows, per_step, rtol=1e-6, atol=0)
    assert per_step.max() < DEFAULT_ESTIMATE_BOUND < 2.6e-2  # (refiltered: within the bound)
    assert radau.status == pinn.status == "success"

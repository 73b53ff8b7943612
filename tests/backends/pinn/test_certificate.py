"""The certificate's copy of radau's own fixed-step error estimate (backends/pinn/certificate.py):
on the PINN's steps it is the estimate radau computes on its own, step for step."""

import numpy as np
import pytest

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

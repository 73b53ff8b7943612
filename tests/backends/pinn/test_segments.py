"""Segments of the Radau-PINN (backends/pinn/segments.py): the grid of a span shorter than
``config.h``, and the memory check before any network is built."""

import numpy as np
import pytest

import daemodel as dm
from daemodel.errors import ResourceLimitError
from daemodel.problems import PENDULUM


def test_a_span_shorter_than_h_is_one_segment():
    from daemodel.backends.pinn.segments import segment_grid

    assert np.array_equal(segment_grid((0.45, 0.451), 0.05), [0.45, 0.451])
    assert np.allclose(segment_grid((0.0, 0.12), 0.05), [0.0, 0.05, 0.1, 0.12])
    with pytest.raises(dm.errors.StepSizeError, match="larger than the interval"):
        segment_grid((0.45, 0.451), 0.05, strict=True)


def test_the_parameter_count_before_building_is_the_networks_own():
    import torch
    from daemodel.backends.pinn.network import RadauNetwork, parameter_count_of

    for settings in ({}, {"width": 7, "depth": 3}, {"architecture": "shared", "stages": 2}):
        config = dm.PINNConfig(**settings)
        for copies in (1, 3):
            net = RadauNetwork(6, 4, 1, config, torch.Generator().manual_seed(0), copies=copies)
            assert parameter_count_of(6, 4, 1, config, copies) == net.parameter_count()


def test_a_width_of_a_million_is_refused_before_allocating(monkeypatch):
    """Before: torch's allocator failed for 48 TB ('DefaultCPUAllocator: can't allocate memory')."""
    monkeypatch.setenv("DAEMODEL_MEMORY_LIMIT", "8G")
    c = PENDULUM.model().compile()
    with pytest.raises(
        ResourceLimitError,
        match=r"pinn: networks of width = 1000000 and depth = 2 for 1 sample\(s\) of 5 unknowns would need "
        r"9\.83e\+05 GiB to train \(the networks of 20 segment\(s\) 8\.94e\+05 GiB, training's working copies "
        r"8\.94e\+04 GiB\), more than the 8 GiB allowed \(set DAEMODEL_MEMORY_LIMIT, e\.g\. '64G', to change "
        r"it\); take a smaller width or depth \(PINNConfig's defaults: width = 20, depth = 2\)",
    ):
        dm.solve(c, (0.0, 1.0), method="pinn", config=dm.PINNConfig(width=10**6))
    with pytest.raises(ResourceLimitError, match=r"width = 200 and depth = 100000 .* take a smaller width or depth"):
        dm.solve(c, (0.0, 1.0), method="pinn", config=dm.PINNConfig(width=200, depth=10**5))


def test_many_training_inputs_are_refused_for_lms_gram_matrices(monkeypatch):
    """64 training inputs per segment at width 1000: LM's Gram matrices of the hidden layers, 6 x
    (64 x 1000)^2 doubles, 4 copies (before: torch's allocator failed at 49 GB)."""
    monkeypatch.setenv("DAEMODEL_MEMORY_LIMIT", "8G")
    c = PENDULUM.model().compile()
    config = dm.PINNConfig(width=1000, samples=64, radius=0.01)
    fix = r"LM's Gram matrices 732 GiB.* take a smaller width or depth or fewer samples"
    with pytest.raises(ResourceLimitError, match=fix):
        dm.solve(c, (0.0, 1.0), method="pinn", config=config)


def test_the_estimate_is_of_the_measured_size():
    """The pendulum, width 1000, one segment: the estimate is 3 x the parameters (measured: peak
    resident memory 143 MB above the start for 46.7 MB of parameters), and samples = 8 adds the
    Gram matrices (measured 10.4 GB in all)."""
    from daemodel.backends.pinn.segments import network_memory

    c = PENDULUM.model().compile()
    parts = network_memory(c, dm.PINNConfig(width=1000), 4, 1, 1)
    assert sum(parts.values()) == 3 * 6_120_030 * 8
    parts = network_memory(c, dm.PINNConfig(width=1000, samples=8, radius=0.01), 4, 1, 1)
    assert 10.4e9 <= sum(parts.values()) <= 1.3 * 10.4e9

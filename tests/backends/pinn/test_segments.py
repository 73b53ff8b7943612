"""Segments of the Radau-PINN (backends/pinn/segments.py): the grid of a span shorter than
``config.h``, and the memory check before any network is built."""

import itertools

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
    from daemodel.backends.pinn.network import output_layout, output_sizes

    for n, m, s, architecture in itertools.product((0, 1, 5), (0, 1, 3), (1, 3), ("per-variable", "shared")):
        sizes, _ = output_layout(n, m, s, architecture)
        assert output_sizes(n, m, s, architecture) == (len(sizes), max(sizes, default=0))


def test_a_width_of_a_million_is_refused_before_allocating(monkeypatch):
    """Before: torch's allocator failed for 48 TB ('DefaultCPUAllocator: can't allocate memory')."""
    monkeypatch.setenv("DAEMODEL_MEMORY_LIMIT", "8G")
    c = PENDULUM.model().compile()
    with pytest.raises(
        ResourceLimitError,
        match=r"pinn: networks of width = 1000000 and depth = 2 for 1 sample\(s\) of 5 unknowns would need "
        r"at least 1\.34e\+05 GiB to train \(the networks of 1 segment\(s\) 4\.47e\+04 GiB, training's working "
        r"copies 8\.94e\+04 GiB, the Radau stage system, dense 5\.01e-05 GiB\), more than the 8 GiB allowed \(set "
        r"DAEMODEL_MEMORY_LIMIT, e\.g\. '64G', to change "
        r"it\); take a smaller width or depth \(PINNConfig's defaults: width = 20, depth = 2\)",
    ):  # (refused before the default h's pre-solve, on one segment: at least)
        dm.solve(c, (0.0, 1.0), method="pinn", config=dm.PINNConfig(width=10**6))
    # the check on the grid's segments (the same, after the pre-solve, where one segment fits)
    from daemodel.backends.pinn.segments import check_network_memory

    with pytest.raises(
        ResourceLimitError,
        match=r"pinn: networks of width = 1000000 and depth = 2 for 1 sample\(s\) of 5 unknowns would need "
        r"9\.83e\+05 GiB to train \(the networks of 20 segment\(s\) 8\.94e\+05 GiB, training's working copies "
        r"8\.94e\+04 GiB, the Radau stage system, dense 5\.01e-05 GiB\), more than the 8 GiB allowed \(set "
        r"DAEMODEL_MEMORY_LIMIT, e\.g\. '64G', to change "
        r"it\); take a smaller width or depth \(PINNConfig's defaults: width = 20, depth = 2\)",
    ):
        check_network_memory(c, dm.PINNConfig(width=10**6), 4, 1, 20)
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
    assert sum(size for name, size in parts.items() if "stage system" not in name) == 3 * 6_120_030 * 8
    # (the pendulum: D = 5, m = 1, s = 3: 54 KB)
    assert parts["the Radau stage system, dense"] == 16 * (4 * 5 + 1) * (4 * 5) * 8
    parts = network_memory(c, dm.PINNConfig(width=1000, samples=8, radius=0.01), 4, 1, 1)
    assert 10.4e9 <= sum(parts.values()) <= 1.3 * 10.4e9


def test_a_model_too_large_for_the_pinns_dense_stage_system_is_refused_before_allocating(monkeypatch):
    """The PINN's Levenberg-Marquardt solves the Radau stage system densely: ((s+1) D + m) x (s+1) D per
    input, 16 copies (measured at 400 and 800 unknowns: 1.5 GB at 800; 10^4 unknowns would need 200 GB).
    A model whose stage system does not fit is refused naming its size, the limit and radau."""
    monkeypatch.setenv("DAEMODEL_MEMORY_LIMIT", "1G")
    m = decay_chain(600)
    with pytest.raises(
        ResourceLimitError,
        match=r"pinn: a model of 600 unknowns is too large for the PINN: its Levenberg-Marquardt solves the Radau "
        r"stage system of 3 stages densely, which would need at least 1\.18 GiB to train \(.*the Radau stage system, "
        r"dense 0\.687 GiB\), more than the 1 GiB allowed .*solve it with method='radau' \(sparse\), or take fewer "
        r"stages",
    ):
        dm.solve(m.compile(), (0.0, 0.1), method="pinn", h=0.05)


def test_a_model_too_large_for_the_pinn_is_refused_before_the_pre_solve_and_the_switches(monkeypatch):
    """At 10^5 unknowns the refusal came after the default h's pre-solve (a radau solve) and the search
    for switches: 10.3 s beyond the compile; now before both (0.19 s: benchmarks/refusal_and_report.json)."""
    import daemodel.backends.pinn.segments as segments

    import daemodel.solving.solver as solver

    def never(*_, **__):
        raise AssertionError("ran before the refusal")

    monkeypatch.setattr(segments, "default_segments", never)
    monkeypatch.setattr(solver, "with_state_events", never)
    monkeypatch.setattr(solver, "system_for", never)
    monkeypatch.setenv("DAEMODEL_MEMORY_LIMIT", "1G")
    with pytest.raises(ResourceLimitError, match=r"a model of 600 unknowns is too large for the PINN: .* at least"):
        dm.solve(decay_chain(600).compile(), (0.0, 1.0), method="pinn")


def test_a_stage_system_beyond_the_limit_is_named_even_where_the_networks_are_larger(monkeypatch):
    """At 10^5 unknowns, 17 segments' networks (3.9e4 GiB) outweighed the stage system (2.15e4 GiB),
    and the message said to take a smaller width or depth, which cannot make the model fit."""
    from daemodel.backends.pinn.segments import check_network_memory

    monkeypatch.setenv("DAEMODEL_MEMORY_LIMIT", "0.5G")
    c = decay_chain(600).compile()
    with pytest.raises(
        ResourceLimitError,
        match=r"a model of 600 unknowns is too large for the PINN: .* which would need 4\.28 GiB .*the networks of "
        r"20 segment\(s\) 3\.27 GiB.*dense 0\.687 GiB\), .* solve it with method='radau'",
    ):
        check_network_memory(c, dm.PINNConfig(), 600, 1, 20)


def test_the_stage_system_estimate_counts_every_sample_of_a_batch(monkeypatch):
    """Independent networks for a batch: the loss's Jacobian holds every sample's stage system at
    once, (B, R, U) (seen: (6, 21, 20) for the pendulum and 6 samples), not one network's."""
    from daemodel.backends.pinn.segments import network_memory

    c = PENDULUM.model().compile()
    one = 16 * (4 * 5 + 1) * (4 * 5) * 8
    assert network_memory(c, dm.PINNConfig(), 4, 6, 1)["the Radau stage system, dense"] == 6 * one
    shared = dm.PINNConfig(batch="shared", samples=8, radius=0.01)
    assert network_memory(c, shared, 4, 6, 1)["the Radau stage system, dense"] == 48 * one
    monkeypatch.setenv("DAEMODEL_MEMORY_LIMIT", "1G")
    m = decay_chain(100)  # (one input: 16 x 400 x 400 doubles, 20 MB)
    with pytest.raises(
        ResourceLimitError,
        match=r"pinn: a model of 100 unknowns with 64 training inputs is too large for the PINN: .* densely for "
        r"every input at once, which would need at least 2\.16 GiB .*the Radau stage system, dense 1\.22 GiB\), more "
        r"than the 1 GiB allowed .*or take fewer stages or fewer samples",
    ):
        dm.solve(m.compile(), (0.0, 0.1), method="pinn", h=0.05, y0={"x0": np.linspace(0.5, 1.5, 64)})


def decay_chain(n: int) -> dm.Model:
    """``x_i' = -x_i`` for n states, all from 1."""
    m = dm.Model("chain")
    xs = m.states([f"x{i}" for i in range(n)])
    for x in xs:
        m.ode(x, -x)
    m.initial(**{x.name: 1.0 for x in xs})
    return m


def test_a_time_limit_in_the_default_h_pre_solve_is_not_called_a_failed_pre_solve(monkeypatch):
    """The default h's pre-solve turned any SolverError into "the default h comes from ..., which failed
    (...); give the segment length": a time limit that struck there said so too."""
    from daemodel.backends.pinn.segments import default_segments
    from daemodel.backends.radau.backend import RadauBackend

    from daemodel.compiling.initial_states import initial_states
    from daemodel.errors import TimeLimitError

    def struck(*_, **__):
        raise TimeLimitError("stop here")

    monkeypatch.setattr(RadauBackend, "solve", struck)
    compiled = PENDULUM.model().compile()
    with pytest.raises(TimeLimitError, match=r"^stop here$"):
        default_segments(compiled, (0.0, 1.0), initial_states(compiled), 200)


def test_a_batchs_default_h_is_its_trajectories_not_their_count_divided():
    """radau steps a batch's samples together (one h), so its steps are the batch's; they were divided
    by the samples, as scipy's per-sample sums were: 4 pendulums trained 4 segments where one trains
    18, and 100 would have trained one."""
    from daemodel.backends.pinn.segments import default_segments

    from daemodel.compiling.initial_states import initial_states

    compiled = PENDULUM.model().compile()
    one, steps, _ = default_segments(compiled, (0.0, 1.0), initial_states(compiled), 200)
    four, batch_steps, _ = default_segments(
        compiled, (0.0, 1.0), initial_states(compiled, y0=np.repeat(np.asarray(compiled.y0)[None], 4, axis=0)), 200
    )
    assert one == steps and four == batch_steps
    assert 0.7 * one <= four <= 1.3 * one

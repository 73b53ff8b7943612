"""radau's records of the accepted steps and the outputs at t_eval filled as the steps come
(backends/radau/records.py)."""

import gc
import sys
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from daemodel.backends.radau.backend import RadauBackend
from daemodel.backends.radau.options import RadauOptions

import daemodel as dm
from daemodel.compiling.initial_states import InitialStates
from daemodel.problems import PENDULUM

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import scaling_models

TIMES = np.linspace(0.0, 1.0, 11)


def traced_solve(compiled, **options) -> tuple:
    """``(traced peak during dm.solve over what was traced before it, the Solution)``."""
    gc.collect()
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        sol = dm.solve(compiled, (0.0, 1.0), method="radau", t_eval=TIMES, **options)
        return tracemalloc.get_traced_memory()[1] - before, sol
    finally:
        tracemalloc.stop()


def test_the_outputs_at_t_eval_keep_no_step_to_the_end():
    """With t_eval and dense_output=False the values at t_eval are read off each block of steps as it is
    accepted: the same values, bit for bit, as the dense output's (dense_output=True), and a solve of six
    times the steps peaks no higher (before: every step's nodes were kept to the solve's end, here 48 KB a
    step of 1,000 unknowns at s = 5: 16 more steps, 1.1 MB more)."""
    compiled = scaling_models.DECLARATIONS["stencils"](500).compile()
    traced_solve(compiled, stages=5, dense_output=False)  # (the model's first-solve pieces made)
    loose_peak, loose = traced_solve(compiled, rtol=1e-3, atol=1e-3, stages=5, dense_output=False)
    tight_peak, tight = traced_solve(compiled, rtol=1e-9, atol=1e-9, stages=5, dense_output=False)
    assert loose.status == tight.status == "success"
    assert tight.stats["steps"] >= loose.stats["steps"] + 10
    step_nodes = (5 + 1) * 1000 * 8
    assert tight_peak - loose_peak < 2 * step_nodes, (tight_peak, loose_peak)
    for rtol, sol in ((1e-3, loose), (1e-9, tight)):
        dense = dm.solve(compiled, (0.0, 1.0), method="radau", t_eval=TIMES, rtol=rtol, atol=rtol, stages=5)
        np.testing.assert_array_equal(sol.t, dense.t)
        for name in ("c[0]", "c[250]", "w[499]"):
            np.testing.assert_array_equal(sol[name], dense[name])


@pytest.mark.parametrize("jit", [False, "auto"])
def test_the_outputs_at_t_eval_with_a_stop_are_the_dense_outputs_up_to_it(jit):
    """A caller's stop (the backend contract's rule 8) with t_eval and dense_output=False: every block is shown
    with its polynomials (their nodes kept until then), and the outputs up to where it ended are those of
    the solve to t1 with the dense output, bit for bit (the compiled run's blocks of steps with jit)."""
    compiled = PENDULUM.model().compile()
    start = InitialStates(y0=compiled.y0[None], z0=compiled.z0[None], p=compiled.parameter_values[None], batched=False)
    t_eval = np.linspace(0.0, 3.0, 61)
    options = dict(rtol=1e-8, atol=1e-8, jit=jit, t_eval=t_eval)
    whole = RadauBackend().solve(compiled, (0.0, 3.0), start, RadauOptions(**options, dense_output=True))
    shown = []

    def stop(times, Y, Z, dense):
        if shown:
            assert np.allclose(dense(times)[0], np.hstack([Y, Z]), atol=1e-12)  # (the block's own polynomials)
        shown.append(times[-1])
        return bool((Y[:, 3] < 0).any())

    stopped = RadauBackend().solve(compiled, (0.0, 3.0), start, RadauOptions(**options, dense_output=False), stop=stop)
    k = len(stopped.t)
    assert 1 < k < len(t_eval) and stopped.t[-1] <= shown[-1] < 3.0
    np.testing.assert_array_equal(stopped.t, whole.t[:k])
    for name in ("y1", "y4", "y5"):
        np.testing.assert_array_equal(stopped[name], whole[name][:k])

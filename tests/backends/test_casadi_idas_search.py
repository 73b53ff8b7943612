"""casadi-idas's event search (backends/casadi/idas_search.py): windows read at about one output per IDAS
step, bounded, each failure named."""

import math

import numpy as np
import pytest
from daemodel.backends.casadi import idas_search

import daemodel as dm
from daemodel import errors as E


def _hump_event(c: float = 0.99):
    """s = sin t; a declared event on c - s counted in n (two crossings a hump, 2 acos(c) apart)."""
    m = dm.Model("humps")
    m.states("s c n")
    m.ode("s", "c")
    m.ode("c", "-s")
    m.ode("n", "0")
    m.initial(s=0.0, c=1.0, n=0.0)
    m.event("hump", f"{c} - s", reset={"n": "n + 1"})
    return m


def _hump_times(c: float, t1: float) -> np.ndarray:
    k = 2.0 * math.pi * np.arange(int(t1 / (2.0 * math.pi)) + 2)
    times = np.sort(np.concatenate([math.pi / 2 - math.acos(c) + k, math.pi / 2 + math.acos(c) + k]))
    return times[times < t1]


def test_humps_narrower_than_a_default_output_spacing_are_each_located():
    # 0.999 - sin t: humps 0.089 wide, 2 pi apart, over (0, 400): a solve to t1 read at its 101 default outputs
    # (4 s apart) saw none of the 128 crossings, "success"
    t1, rtol = 400.0, 1e-8
    sol = dm.solve(_hump_event(0.999), (0.0, t1), method="casadi-idas", rtol=rtol, atol=rtol, t_eval=[0.0, t1])
    found, exact = sol.events["hump"]["t"][0], _hump_times(0.999, t1)
    assert sol.status == "success" and len(found) == len(exact) == 128 and sol["n"][-1] == 128
    # (IDAS's own phase error over 400 s, 1e-5 at most, over the crossing's slope sqrt(1 - c^2))
    assert np.abs(found - exact).max() < 1e-3


def test_the_search_reads_at_least_one_output_a_step():
    # the detection solve's outputs, per IDAS step, in every window: a piece without events, one search to t1
    from daemodel.backends.casadi.idas import IDASBackend, IDASOptions

    from daemodel.compiling.initial_states import InitialStates

    compiled = _hump_event().compile()
    seen = []

    def stop(times, Y, Z, dense):
        seen.append(np.asarray(times, dtype=float).copy())
        return False

    start = InitialStates(y0=np.array([[0.0, 1.0, 0.0]]), z0=np.zeros((1, 0)), p=np.zeros((1, 0)), batched=False)
    sol = IDASBackend().solve(compiled, (0.0, 100.0), start, IDASOptions(rtol=1e-8, atol=1e-8), stop=stop)
    outputs = sum(len(t) for t in seen)
    assert sol.t[-1] == 100.0 and outputs == len(sol.t)
    assert outputs >= idas_search.OUTPUTS_PER_STEP * sol.stats["nsteps"] / 2  # (redone windows' steps counted too)
    assert np.all(np.diff(sol.t) > 0)


def test_the_search_s_steps_are_bounded_by_max_num_steps():
    with pytest.raises(
        E.StepLimitError,
        match=r"casadi-idas: the event search took [0-9,]+ IDAS steps by t = [0-9.]+, past 101 x max_num_steps = "
        r"20,200 \(sample 0 of 'humps'\); raise max_num_steps or loosen rtol/atol, or shorten t_span",
    ):
        # (2 - sin t never crosses: one piece, one search over all of (0, 3000), 40,000 IDAS steps)
        dm.solve(_hump_event(2.0), (0.0, 3000.0), method="casadi-idas", rtol=1e-7, atol=1e-7, max_num_steps=200)


def test_a_window_solved_again_without_end_is_refused(monkeypatch):
    monkeypatch.setattr(idas_search, "MAX_REDOS", 0)
    monkeypatch.setattr(idas_search, "MAX_POINTS", idas_search.MIN_POINTS)
    with pytest.raises(
        E.StepLimitError,
        match=r"casadi-idas: the event search's window from t = 0 was solved again 0 times for 2 outputs a step "
        r"\(sample 0 of 'humps'\): IDAS's steps there shrink without end; shorten t_span before it",
    ):
        dm.solve(_hump_event(), (0.0, 3000.0), method="casadi-idas", rtol=1e-10, atol=1e-10)


def test_the_search_s_outputs_are_refused_past_the_memory_limit(monkeypatch):
    # two outputs or more an IDAS step, all kept: refused before casadi allocates them, not a machine out of memory
    monkeypatch.setenv("DAEMODEL_MEMORY_LIMIT", "200K")
    with pytest.raises(
        E.ResourceLimitError,
        match=r"casadi-idas's event search on 1 sample\(s\) of 3 unknowns would need [0-9.]+ GiB \(outputs",
    ):
        dm.solve(_hump_event(2.0), (0.0, 3000.0), method="casadi-idas", rtol=1e-7, atol=1e-7)


def test_the_search_falls_back_to_the_exact_slope_where_idacalcic_fails(monkeypatch):
    # w = log y, w(0) = 0: IDACalcIC's line search fails at atol 1e-10 with its step 0.001 of the last output
    # (casadi's first_time left as it is; the solve to t1 falls back to y' = f); the search's windows raised
    # ConvergenceError (IDA_LINESEARCH_FAIL) before they did the same
    import sympy as sp

    monkeypatch.setattr(idas_search, "consistent_start", lambda first_output, step0: {"calc_ic": True})

    m = dm.Model("logarithm")
    (y,) = m.states("y")
    (w,) = m.algebraics("w")
    m.ode(y, -1)
    m.constraint(w - sp.log(y), name="log")
    m.initial(y=1.0)
    m.event("third", "w + 1")
    sol = dm.solve(m, (0.0, 0.9), method="casadi-idas")
    assert sol.stats["initial_slope_fallbacks"] >= 1
    assert sol.status == "success" and abs(sol.events["third"]["t"][0, 0] - (1.0 - math.exp(-1.0))) < 1e-8
    np.testing.assert_allclose(sol["w"], np.log(1.0 - sol.t), atol=1e-7)

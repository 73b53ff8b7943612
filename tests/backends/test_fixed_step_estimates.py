"""Fixed steps are honest: every step's local error estimate is reported, and a run beyond
``estimate_bound`` comes back flagged (status and a warning naming the step), for radau and for
casadi's collocation alike; casadi's integrators are built once per model, times and settings."""

import numpy as np
import pytest
from daemodel.backends.base import DEFAULT_ESTIMATE_BOUND

import daemodel as dm
from daemodel import errors as E
from daemodel.problems import PENDULUM


def _kink() -> dm.Model:
    """x' = 1 before t = 0.52 and -1 after (to 1e-4: tanh), x = min(t, 1.04 - t): a kink between grid
    points.  (A smooth function, which no solve stops at; a Piecewise would be a switch, which the
    grid is cut at or an event located at: tests/solving/test_switches.py, tests/solving/test_events.py.)"""
    m = dm.Model("kink")
    m.states("x")
    m.ode("x", "tanh(10000*(0.52 - t))")
    m.initial(x=0.0)
    return m


@pytest.mark.parametrize("method", ["radau", "casadi-collocation"])
def test_a_step_across_a_kink_is_flagged_with_its_estimate(method):
    with pytest.warns(E.LocalErrorWarning) as caught:
        sol = dm.solve(_kink(), (0.0, 1.0), h=0.05, method=method)
    assert sol.status == str(caught[0].message) and caught[0].filename == __file__  # points at the user's line
    assert sol.status.startswith(f"flagged: {method}'s local error estimate reaches 0.0") and sol.status.endswith(
        "of the solution's size at step 11 from t = 0.5 (h = 0.05), in 'x', beyond estimate_bound = 0.001: "
        "the values there keep fewer digits than the bound asks; take a smaller h, or the adaptive mode (rtol=...)"
    )
    estimates = np.asarray(sol.stats["local_error_estimates"])
    assert estimates.shape == (20,) and int(np.argmax(estimates)) == 10  # step 11, the one across t = 0.52
    exact = np.minimum(sol.t, 1.04 - sol.t)
    error = np.abs(sol["x"] - exact).max()
    assert DEFAULT_ESTIMATE_BOUND < error < 10 * estimates.max()  # the estimate's size, and truly beyond the bound
    assert dm.solve(_kink(), (0.0, 1.0), h=0.05, method=method, estimate_bound=0.1).status == "success"


@pytest.mark.parametrize("method", ["radau", "casadi-collocation"])
def test_a_smooth_run_within_the_bound_is_success(method, recwarn):
    sol = dm.solve(PENDULUM.model(), (0.0, 1.0), h=0.01, method=method)
    assert sol.status == "success" and not [w for w in recwarn if w.category is E.LocalErrorWarning]
    assert 0 < max(sol.stats["local_error_estimates"]) <= DEFAULT_ESTIMATE_BOUND
    assert len(sol.stats["local_error_estimates"]) == 100


def test_a_stiff_mode_is_filtered_before_it_is_judged(recwarn):
    """y' = -1e6 (y - cos t): the unfiltered estimate of the first step from y0 = 0.95 is 2.6e-2 (the
    stiff mode's transient), the true error 1.5e-5; refiltered (Hairer-Wanner) it is below the bound."""
    m = dm.Model("stiff")
    m.states("y")
    m.ode("y", "-1e6*(y - cos(t))")
    m.initial(y=0.95)
    sol = dm.solve(m, (0.0, 1.0), h=0.01)
    assert sol.status == "success", sol.status
    reference = dm.solve(m, (0.0, 1.0), rtol=1e-10, atol=1e-12, t_eval=sol.t)
    assert np.abs(sol["y"] - reference["y"]).max() < DEFAULT_ESTIMATE_BOUND


def test_estimate_bound_errors():
    with pytest.raises(E.InvalidOptionError, match=r"estimate_bound bounds a fixed step's local error estimate"):
        dm.solve(PENDULUM.model(), (0.0, 1.0), estimate_bound=1e-3)
    for method in ("radau", "casadi-collocation"):
        with pytest.raises(E.InvalidOptionError, match=r"estimate_bound must be positive; got -1"):
            dm.solve(PENDULUM.model(), (0.0, 1.0), h=0.1, method=method, estimate_bound=-1)


def test_integrators_kept_are_bounded(monkeypatch):
    from daemodel.backends.casadi import plumbing

    monkeypatch.setattr(plumbing, "KEPT_INTEGRATORS", 2)
    compiled = PENDULUM.model().compile()
    for t1 in (0.5, 0.75, 1.0):
        dm.solve(compiled, (0.0, t1), method="casadi-idas", rtol=1e-6)
    kept = compiled.reduced(1).cached("casadi-integrators", dict)  # (IDAS solves the index-1 reduction)
    assert [key[3][-1] for key in kept] == [0.75, 1.0]  # the two most recent t_spans (key: plugin, scale, t0, times)


def test_kept_integrators_name_their_time_scale():
    # (the caller's tag, where the dae's parameter count told them apart: a model with one more parameter than
    # another's shifted dae would have shared its integrators)
    from daemodel.backends.casadi import plumbing

    compiled = PENDULUM.model().compile()
    dm.solve(compiled, (0.0, 1.0), method="casadi-idas", rtol=1e-6)  # (on the time since t0)
    dm.solve(compiled, (0.0, 1e-7), method="casadi-idas", rtol=1e-6)  # (shorter than SHORT_SPAN: normalised)
    dm.solve(compiled, (0.0, 1.0), method="casadi-collocation", h=0.1)
    kept = [*compiled.reduced(1).cached("casadi-integrators", dict), *compiled.cached("casadi-integrators", dict)]
    assert {key[:2] for key in kept} == {("idas", "shifted"), ("idas", "normalised"), ("collocation", "own")}
    with pytest.raises(ValueError, match=r"unknown time scale 'since'; the scales are own, shifted, normalised"):
        plumbing.scaled_dae(compiled.reduced(1), "since")


def test_threads_keep_their_own_integrators():
    """A solve reads its integrator's statistics after its calls: threads solving one model with the
    same settings (different parameters) share no integrator, and each reports its own solve's."""
    import threading

    compiled = PENDULUM.model().compile()
    lams = (0.5, 1.0, 2.0, 4.0)  # 146, 173, 211 and 190 IDAS steps at rtol 1e-8

    def solve(lam):
        return dm.solve(compiled, (0.0, 1.0), method="casadi-idas", rtol=1e-8, parameters={"lam": lam}).stats

    alone = {lam: solve(lam)["nsteps"] for lam in lams}
    together, barrier = {lam: [] for lam in lams}, threading.Barrier(len(lams))

    def repeat(lam):
        barrier.wait()
        for _ in range(20):
            together[lam].append(solve(lam)["nsteps"])

    threads = [threading.Thread(target=repeat, args=(lam,)) for lam in lams]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    for lam in lams:
        assert set(together[lam]) == {alone[lam]}, lam
    kept = compiled.reduced(1).cached("casadi-integrators", dict)
    assert len({key[-1] for key in kept}) == len(lams) + 1  # the main thread's and each thread's


@pytest.mark.parametrize(("method", "options"), [("casadi-idas", {"rtol": 1e-6}), ("casadi-collocation", {"h": 0.1})])
def test_casadi_integrators_are_built_once_per_model_and_settings(monkeypatch, method, options):
    import casadi

    built = []
    original = casadi.integrator

    def counting(*args, **kwargs):
        built.append(args[0])  # the integrator's name
        return original(*args, **kwargs)

    monkeypatch.setattr(casadi, "integrator", counting)
    compiled = PENDULUM.model().compile()
    first = dm.solve(compiled, (0.0, 1.0), method=method, **options)
    again = dm.solve(compiled, (0.0, 1.0), method=method, **options)
    assert np.array_equal(first["y1"], again["y1"])
    name = "idas" if method == "casadi-idas" else "collocation"
    assert built.count(name) == 1 and len(built) == (1 if method == "casadi-idas" else 2)  # (+ the estimate's)
    dm.solve(compiled, (0.0, 1.0), method=method, **{k: v / 2 for k, v in options.items()})  # other settings
    assert built.count(name) == 2

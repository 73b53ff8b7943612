"""Forward sensitivities and the discrete adjoint of radau (daemodel/sensitivities.py, issue 29).

The references are independent of the code under test: central finite differences of solves at
perturbed parameters and initial states (made consistent by ``compiled.consistent``), for adaptive
runs on the steps the run took, re-solved by full Newton on the stage equations in torch
(:func:`daemodel.collocation.collocation_step`); and closed forms where one exists.
"""

import numpy as np
import pytest
import sympy as sp
import torch

import daemodel as dm
from daemodel import errors as E
from daemodel.collocation import collocation_step
from daemodel.compiling.algebraic import algebraic_from_states
from daemodel.problems import AKZO_NOBEL, DECAY, PENDULUM_INDEX3
from daemodel.sensitivities import directions, initial_sensitivities
from daemodel.tableau import radau_iia

FD_RTOL = 1e-6  # the bound: sensitivities against central differences


def _decay():
    """DECAY: y' = -k y, 0 = z - c y^2 (index 1), k = 1.5, c = 0.7, y0 = 1: dy/dk = -t exp(-k t),
    dy/dy0 = exp(-k t), dz/dk = 2 c y dy/dk, dz/dc = y^2."""
    return DECAY.model().compile()


def _relative(a, b):
    return float(np.max(np.abs(a - b)) / np.max(np.abs(b)))


def _on_steps(compiled, dense, parameters, y0):
    """The Radau solution on the steps of ``dense`` (a run's record), by full Newton from scratch:
    the step end values (S + 1, n + m), the start first."""
    tf = compiled.torch_functions()
    s = len(dense.c)
    tableau = radau_iia(s)
    A, c = (torch.tensor(np.array(x, dtype=float)) for x in (tableau.A, tableau.c))
    start = dm.solve(
        compiled,
        (compiled.t0, compiled.t0 + dense.lengths[0]),
        h=dense.lengths[0],
        stages=s,
        parameters=parameters,
        y0=y0,
    )
    n = len(compiled.states)
    u = np.array([start.values[name][0, 0] for name in (*compiled.state_names, *compiled.algebraic_names)])
    out = [u]
    p = torch.tensor(
        np.array(
            [parameters.get(k, v) for k, v in zip(compiled.parameter_names, compiled.parameter_values, strict=True)]
        )
    )
    for t, h in zip(dense.starts, dense.lengths, strict=True):
        y = torch.tensor(u[:n])
        Y, Z = y.repeat(s, 1), torch.tensor(u[n:]).repeat(s, 1)
        step = collocation_step(tf, A, c, float(t), float(h), y, Y, Z, p, max_iterations=50, tol=1e-15)
        assert bool(step.converged)
        u = torch.cat([step.Y[-1], step.Z[-1]]).numpy()
        out.append(u)
    out = np.array(out)
    if dense.resolves_algebraic:  # (adaptive steps on index 2: radau returns z solved from its states)
        times = np.concatenate([[compiled.t0], dense.starts + dense.lengths])
        found = algebraic_from_states(compiled, times, out[None, :, :n], out[None, :, n:], p.numpy()[None])
        assert found.converged.all()
        out[:, n:] = found.z[0]
    return out


def _perturbed(compiled, name, value, delta):
    """``(parameters, y0)`` with ``name`` moved by ``delta``, the initial states made consistent."""
    base_p = dict(zip(compiled.parameter_names, compiled.parameter_values, strict=True))
    y0 = dict(zip(compiled.state_names, compiled.y0, strict=True))
    if name in base_p:
        parameters = {**base_p, name: value + delta}
        return parameters, compiled.consistent(y0=y0, parameters=parameters)
    return base_p, compiled.consistent(y0={**y0, name: value + delta}, fix=[name])


@pytest.mark.filterwarnings(
    "ignore::daemodel.errors.LocalErrorWarning"
)  # (one stage at h = 0.1: flagged, as it should)
@pytest.mark.parametrize("stages", [1, 3])
def test_the_decay_sensitivities_converge_to_the_closed_form_at_order_2s_minus_1(stages):
    compiled = _decay()
    errors, hs = [], [0.1, 0.05, 0.025]
    for h in hs:
        sol = dm.solve(compiled, (0.0, 2.0), h=h, stages=stages, sensitivities=["k", "y", "c"])
        t = sol.t
        y = np.exp(-1.5 * t)
        exact_k = -t * y
        errors.append(
            max(
                np.abs(sol.sensitivity("y", "k") - exact_k).max(),
                np.abs(sol.sensitivity("y", "y") - y).max(),
                np.abs(sol.sensitivity("z", "k") - 2 * 0.7 * y * exact_k).max(),
                np.abs(sol.sensitivity("z", "c") - y**2).max(),
            )
        )
    order = np.polyfit(np.log(hs), np.log(errors), 1)[0]
    assert abs(order - (2 * stages - 1)) < 0.3, (errors, order)


@pytest.mark.parametrize("mode", ["fixed", "adaptive", "adaptive, jit"])
def test_pendulum_index3_sensitivities_match_central_differences(mode):
    compiled = PENDULUM_INDEX3.model().compile()
    options = dict(h=0.05, stages=3, newton_tol=1e-14) if mode == "fixed" else dict(rtol=1e-6, jit="jit" in mode)
    names = ["m", "lam", "y2", "y3"]
    sol = dm.solve(compiled, (0.0, 1.0), sensitivities=names, **options)
    values = dict(zip(compiled.parameter_names, compiled.parameter_values, strict=True))
    values.update(zip(compiled.state_names, compiled.y0, strict=True))
    outputs = (*compiled.state_names, *compiled.algebraic_names)
    for name in names:
        delta = 1e-5 * max(1.0, abs(values[name]))
        ends = []
        for sign in (1, -1):
            parameters, y0 = _perturbed(compiled, name, values[name], sign * delta)
            if mode == "fixed":
                run = dm.solve(compiled, (0.0, 1.0), parameters=parameters, y0=y0, **options)
                ends.append(np.stack([run[o] for o in outputs], axis=-1))
            else:  # on the steps the run took
                ends.append(_on_steps(sol.compiled, sol.dense, parameters, y0))
        fd = (ends[0] - ends[1]) / (2 * delta)
        ours = np.stack([sol.sensitivity(o, name) for o in outputs], axis=-1)
        for j, o in enumerate(outputs):
            assert _relative(ours[:, j], fd[:, j]) <= FD_RTOL, (name, o, _relative(ours[:, j], fd[:, j]))
        if name == "y2":  # the rod's length holds to first order: y1 dy1 + y2 dy2 = 0 at t0
            assert abs(ours[0, 0] * sol["y1"][0] + ours[0, 1] * sol["y2"][0]) < 1e-14


@pytest.mark.parametrize("mode", ["fixed", "adaptive"])
def test_akzo_nobel_sensitivities_match_central_differences(mode):
    compiled = AKZO_NOBEL.model().compile()
    span = (0.0, 20.0)
    options = dict(h=0.5, stages=3, newton_tol=1e-14) if mode == "fixed" else dict(rtol=1e-6)
    names = ["k1", "k2", "klA", "Ks", "y1", "y4"]
    sol = dm.solve(compiled, span, sensitivities=names, **options)
    values = dict(zip(compiled.parameter_names, compiled.parameter_values, strict=True))
    values.update(zip(compiled.state_names, compiled.y0, strict=True))
    outputs = (*compiled.state_names, *compiled.algebraic_names)
    for name in names:
        delta = 1e-5 * max(abs(values[name]), 1e-2)
        ends = []
        for sign in (1, -1):
            parameters, y0 = _perturbed(compiled, name, values[name], sign * delta)
            if mode == "fixed":
                run = dm.solve(compiled, span, parameters=parameters, y0=y0, **options)
                ends.append(np.stack([run[o] for o in outputs], axis=-1))
            else:
                ends.append(_on_steps(sol.compiled, sol.dense, parameters, y0))
        fd = (ends[0] - ends[1]) / (2 * delta)
        ours = np.stack([sol.sensitivity(o, name) for o in outputs], axis=-1)
        for j, o in enumerate(outputs):
            if np.abs(fd[:, j]).max() > 1e-12:  # (y3, y5 do not depend on y4's start at t0)
                assert _relative(ours[:, j], fd[:, j]) <= FD_RTOL, (name, o, _relative(ours[:, j], fd[:, j]))


def _misfit_data(sol, seed=0):
    rng = np.random.default_rng(seed)
    return {name: sol[name] * (1 + 0.02 * rng.standard_normal(sol[name].shape)) for name in ("y1", "y2", "y5")}


@pytest.mark.parametrize("options", [dict(h=0.05, stages=3), dict(rtol=1e-6, t_eval=np.linspace(0, 1, 7))])
def test_the_adjoint_gradient_is_the_forward_one(options):
    compiled = PENDULUM_INDEX3.model().compile()
    names = ["m", "lam", "y2", "y3"]
    sol = dm.solve(compiled, (0.0, 1.0), sensitivities=names, **options)
    data = _misfit_data(sol)
    data["y2"][2] = np.nan  # missing: no share
    gradient = sol.gradient(data, names)
    for name in names:
        forward = sum(np.nansum(2 * (sol[o] - data[o]) * sol.sensitivity(o, name)) for o in data)
        assert abs(gradient[name] - forward) <= 1e-8 * abs(forward), name
    expression = sol.gradient("y1**2 + t*y5 + lam*y4", names)
    for name in names:
        forward = np.sum(2 * sol["y1"] * sol.sensitivity("y1", name) + sol.t * sol.sensitivity("y5", name))
        forward += np.sum(sol.sensitivity("y4", name)) + (np.sum(sol["y4"]) if name == "lam" else 0.0)
        assert abs(expression[name] - forward) <= 1e-8 * abs(forward), name
    symbolic = sol.gradient(
        sp.Symbol("y1") ** 2 + sp.Symbol("t") * sp.Symbol("y5") + sp.Symbol("lam") * sp.Symbol("y4"), names
    )
    assert symbolic == pytest.approx(expression, rel=1e-14)


def test_an_alias_output_is_differentiated_through_its_expression():
    m = dm.Model("aliased")
    m.states("y")
    m.algebraics(["w", "u"])
    m.parameter("k", 0.5)
    m.ode("y", "-u*w")
    m.constraint("w - y")  # aliases, eliminated: w = y, u = k
    m.constraint("u - k")
    m.initial(y=2.0)
    compiled = m.compile()
    assert set(compiled.alias_names) == {"w", "u"}
    sol = dm.solve(compiled, (0.0, 1.0), h=0.01, stages=3, sensitivities=["k"])
    t = sol.t
    assert np.abs(sol.sensitivity("w", "k") - (-t * 2.0 * np.exp(-0.5 * t))).max() < 1e-9
    assert np.array_equal(sol.sensitivity("u", "k"), np.ones_like(t))
    data = {"w": sol["w"] + 0.1, "u": sol["u"] - 0.2}
    forward = np.sum(2 * (sol["w"] - data["w"]) * sol.sensitivity("w", "k")) + np.sum(2 * (sol["u"] - data["u"]))
    assert sol.gradient(data, ["k"])["k"] == pytest.approx(forward, rel=1e-10)
    product = np.sum(sol["w"] + 0.5 * sol.sensitivity("w", "k"))  # d(u w)/dk with u = k
    assert sol.gradient("u*w", ["k"])["k"] == pytest.approx(product, rel=1e-10)


def test_a_batch_has_each_samples_own_sensitivities():
    compiled = AKZO_NOBEL.model().compile()
    k1 = np.array([18.7, 20.0])
    batch = dm.solve(compiled, (0.0, 5.0), h=0.25, stages=3, parameters={"k1": k1}, sensitivities=["k1", "klA"])
    assert batch.sensitivity("y1", "k1").shape == batch["y1"].shape == (2, 21)
    for b, value in enumerate(k1):
        one = dm.solve(compiled, (0.0, 5.0), h=0.25, stages=3, parameters={"k1": value}, sensitivities=["k1", "klA"])
        for name in ("k1", "klA"):
            for o in ("y1", "y6"):
                assert np.allclose(batch.sensitivity(o, name)[b], one.sensitivity(o, name), rtol=1e-9, atol=1e-15)
    gradient = batch.gradient("y1", ["k1"])["k1"]
    assert gradient.shape == (2,)
    assert np.allclose(gradient, batch.sensitivity("y1", "k1").sum(axis=1), rtol=1e-10)


def test_initial_sensitivities_keep_the_constraints_and_match_consistent():
    compiled = PENDULUM_INDEX3.model().compile()
    y0, z0 = compiled.y0[None].copy(), compiled.z0[None].copy()
    y0[0] = [0.6, -0.8, 0.8, 0.6]  # on the rod, velocity tangent
    z0 = dm.solve(compiled, (0, 0.01), h=0.01, y0=y0[0]).values["y5"][:, :1]
    where = directions(compiled, ["y1", "y3", "m"])
    dy, _ = initial_sensitivities(compiled, 0.0, y0, z0, compiled.parameter_values[None], where)
    delta = 1e-6
    for q, name in enumerate(("y1", "y3")):
        names = compiled.state_names
        up = compiled.consistent(
            y0={**dict(zip(names, y0[0], strict=True)), name: y0[0][names.index(name)] + delta}, fix=[name]
        )
        down = compiled.consistent(
            y0={**dict(zip(names, y0[0], strict=True)), name: y0[0][names.index(name)] - delta}, fix=[name]
        )
        fd = (np.array([up[k] for k in names]) - np.array([down[k] for k in names])) / (2 * delta)
        assert np.allclose(dy[0, :, q], fd, atol=1e-8), (name, dy[0, :, q], fd)
    assert np.allclose(dy[0, :, 2], 0.0)  # the mass moves no initial state: the rod does not hold it


def test_sensitivity_errors_name_the_culprit(tmp_path):
    compiled = PENDULUM_INDEX3.model().compile()
    with pytest.raises(
        E.UnknownSymbolError, match=r"'g' is neither a parameter nor a state of model 'pendulum-index3'"
    ):
        dm.solve(compiled, (0, 1), h=0.1, sensitivities=["g"])
    with pytest.raises(E.SensitivityError, match=r"'y5' is an algebraic variable: its initial value is not free"):
        dm.solve(compiled, (0, 1), h=0.1, sensitivities=["y5"])
    with pytest.raises(E.SensitivityError, match=r"names 'm' more than once"):
        dm.solve(compiled, (0, 1), h=0.1, sensitivities=["m", "m"])
    with pytest.raises(E.SensitivityError, match="name at least one parameter or state"):
        dm.solve(compiled, (0, 1), h=0.1, sensitivities=[])
    with pytest.raises(E.SensitivityError, match=r"must be names \(strings\)"):
        dm.solve(compiled, (0, 1), h=0.1, sensitivities=[1.0])
    with pytest.raises(E.SensitivityError, match=r"method 'casadi-idas' has none: solve with method='radau'"):
        dm.solve(compiled, (0, 1), method="casadi-idas", sensitivities=["m"])
    with pytest.raises(E.SensitivityError, match="drop dense_output=False"):
        dm.solve(compiled, (0, 1), h=0.1, dense_output=False, sensitivities=["m"])
    sol = dm.solve(compiled, (0, 1), h=0.1, sensitivities=["m"])
    with pytest.raises(E.SensitivityError, match=r"no sensitivities with respect to 'lam'; it has them for \['m'\]"):
        sol.sensitivity("y1", "lam")
    with pytest.raises(E.UnknownSymbolError, match="the solution has no variable 'q'"):
        sol.sensitivity("q", "m")
    with pytest.raises(E.SensitivityError, match="solve with sensitivities"):
        dm.solve(compiled, (0, 1), h=0.1).sensitivity("y1", "m")
    with pytest.raises(E.UnknownSymbolError, match="the data name 'q'"):
        sol.gradient({"q": sol["y1"]}, ["m"])
    with pytest.raises(E.ShapeError, match=r"the data for 'y1' have shape \(3,\)"):
        sol.gradient({"y1": np.zeros(3)}, ["m"])
    with pytest.raises(E.UnknownSymbolError, match=r"the objective names \['q'\]"):
        sol.gradient(sp.Symbol("q"), ["m"])
    canary = tmp_path / "canary"
    evil = sp.Function(f"(lambda *a: open({str(canary)!r}, 'w') or 1.0)")
    with pytest.raises(E.ExpressionParseError, match="only supported functions may be called"):
        sol.gradient(evil(sp.Integer(1)) * sp.Symbol("y1"), ["m"])
    assert not canary.exists()
    with pytest.raises(E.SensitivityError, match="got int"):
        sol.gradient(3, ["m"])
    idas = dm.solve(compiled, (0, 1), method="casadi-idas")
    with pytest.raises(E.SensitivityError, match="this solution is 'casadi-idas''s"):
        idas.gradient("y1", ["m"])
    with pytest.raises(E.SensitivityError, match="keeps no record of its steps"):
        dm.solve(compiled, (0, 1), h=0.1, dense_output=False).gradient("y1", ["m"])


def test_a_state_the_constraints_fix_is_refused():
    m = dm.Model("held")
    m.states(["x", "y"])
    m.algebraics("z")
    m.ode("x", "z")
    m.ode("y", "-y")
    m.constraint("x - 1")  # index 2: x stays at 1, whatever y does
    m.initial(x=1.0, y=2.0)
    compiled = m.compile()
    with pytest.raises(E.SensitivityError, match=r"the constraints fix 'x' given the other states \(x - 1 = 0"):
        dm.solve(compiled, (0, 1), h=0.1, sensitivities=["x"])
    sol = dm.solve(compiled, (0, 1), h=0.1, sensitivities=["y"])
    pendulum = PENDULUM_INDEX3.model().compile()  # at (1, 0) the rod fixes y1: y2 cannot absorb it to first order
    with pytest.raises(E.SensitivityError, match=r"the constraints fix 'y1' given the other states \(y1\*\*2"):
        dm.solve(pendulum, (0, 1), h=0.1, sensitivities=["y1"])
    assert np.allclose(sol.sensitivity("y", "y"), np.exp(-sol.t), rtol=1e-6)
    assert np.allclose(sol.sensitivity("x", "y"), 0.0)


def test_events_and_switches_are_refused():
    m = dm.Model("bouncing")
    m.states(["x", "v"])
    m.ode("x", "v")
    m.ode("v", "-9.81")
    m.initial(x=1.0, v=0.0)
    m.event("floor", "x", direction=-1, reset={"v": "-0.9*v"})
    with pytest.raises(E.SensitivityError, match="has events, across which the derivatives of the solution jump"):
        dm.solve(m, (0, 1), h=0.1, sensitivities=["x"])


def _decay_with_switches():
    """x' = -k x, with a pulse from t = a (5: outside [0, 1]) and a source above x = 2 (never reached from 1)."""
    m = dm.Model("late")
    m.states("x")
    m.parameter("k", 1.5)
    m.parameter("a", 5.0)
    m.ode("x", "-k*x + Piecewise((1, t > a), (0, True)) + Heaviside(x - 2)")
    m.initial(x=1.0)
    return m


def test_switches_outside_the_span_keep_their_sensitivities():
    """Before: refused as a model with switches. On [0, 1] neither switch changes branch: x = exp(-k t),
    dx/dk = -t exp(-k t), dx/dx0 = exp(-k t), and dx/da = 0 (the pulse stays beyond the span)."""
    sol = dm.solve(_decay_with_switches(), (0.0, 1.0), rtol=1e-10, atol=1e-10, sensitivities=["k", "a", "x"])
    t = sol.t
    np.testing.assert_allclose(sol.sensitivity("x", "k"), -t * np.exp(-1.5 * t), rtol=0, atol=1e-12)
    np.testing.assert_allclose(sol.sensitivity("x", "x"), np.exp(-1.5 * t), rtol=0, atol=1e-12)
    assert np.abs(sol.sensitivity("x", "a")).max() == 0.0
    batch = dm.solve(_decay_with_switches(), (0.0, 1.0), h=0.05, parameters={"k": [1.0, 2.0]}, sensitivities=["k"])
    np.testing.assert_allclose(batch.sensitivity("x", "k")[1], -batch.t * np.exp(-2.0 * batch.t), atol=1e-9)


def test_switches_inside_the_span_are_refused_by_name():
    with pytest.raises(E.SensitivityError, match=r"time switch that changes branch at t = 5, inside t_span"):
        dm.solve(_decay_with_switches(), (0.0, 6.0), rtol=1e-8, sensitivities=["k"])
    with pytest.raises(E.SensitivityError, match=r"crosses its switch .*x - 2 crosses 0.* between t = "):
        dm.solve(_decay_with_switches(), (0.0, 1.0), rtol=1e-8, y0={"x": 4.0}, sensitivities=["k"])
    with pytest.raises(E.SensitivityError, match=r"starts on the switch .*x - 2 crosses 0"):
        dm.solve(_decay_with_switches(), (0.0, 1.0), rtol=1e-8, y0={"x": 2.0}, sensitivities=["k"])
    with pytest.raises(E.SensitivityError, match=r"other branches of its switches in samples 0 and 1"):
        dm.solve(_decay_with_switches(), (0.0, 1.0), h=0.1, y0={"x": [1.0, 3.0]}, sensitivities=["k"])


def test_sensitivities_refuse_float32():
    with pytest.raises(E.SensitivityError, match=r"float64 only .* got dtype='float32'"):
        dm.solve(DECAY.model(), (0.0, 1.0), h=0.1, dtype="float32", sensitivities=["k"])


def test_outputs_that_start_after_t0_have_the_same_sensitivities():
    compiled = _decay()
    late = dm.solve(compiled, (0.0, 2.0), h=0.05, stages=3, t_eval=[0.5, 1.0, 2.0], sensitivities=["k", "y"])
    full = dm.solve(compiled, (0.0, 2.0), h=0.05, stages=3, sensitivities=["k", "y"])
    rows = [10, 20, 40]
    for name in ("k", "y"):
        assert np.allclose(late.sensitivity("y", name), full.sensitivity("y", name)[rows], rtol=1e-12)
    gradient = late.gradient("y", ["k"])["k"]
    assert gradient == pytest.approx(full.sensitivity("y", "k")[rows].sum(), rel=1e-12)


def test_blocks_of_one_step_give_the_same_derivatives(monkeypatch):
    """The passes build, use and drop a block of steps at a time (the adjoint backwards, carrying the
    state's cotangent across blocks): blocks of a single step must change nothing."""
    from daemodel import sensitivities

    compiled = AKZO_NOBEL.model().compile()
    names = ["k1", "klA", "y1"]
    whole = dm.solve(compiled, (0.0, 20.0), rtol=1e-6, t_eval=np.linspace(0, 20, 9), sensitivities=names)
    data = {"y1": whole["y1"] * 1.01, "y6": whole["y6"] * 0.99}
    gradient = whole.gradient(data, names)
    monkeypatch.setattr(sensitivities, "BLOCK_BYTES", 1)
    single = dm.solve(compiled, (0.0, 20.0), rtol=1e-6, t_eval=np.linspace(0, 20, 9), sensitivities=names)
    assert sensitivities.StepSystems(compiled, single.dense, single.parameters).block == 1
    for name in names:
        for output in ("y1", "y6"):
            assert np.allclose(single.sensitivity(output, name), whole.sensitivity(output, name), rtol=1e-12, atol=0)
    assert single.gradient(data, names) == pytest.approx(gradient, rel=1e-12)


def test_sensitivities_beyond_the_dense_limit_are_refused_before_the_solve(monkeypatch):
    import daemodel.files

    compiled = DECAY.model().compile()  # (2 unknowns)
    monkeypatch.setattr(daemodel.files, "DENSE_MAX_ORDER", 5)
    sol = dm.solve(compiled, (0.0, 0.1), h=0.05, stages=2, sensitivities=["k"])  # (stages: 4 x 4 systems)
    assert np.isfinite(sol.sensitivity("y", "k")).all()
    with pytest.raises(
        E.ResourceLimitError,
        match=r"sensitivities of 'decay' \(2 unknowns, 3 stage\(s\)\) works on dense 6 x 6 matrices .* above its "
        r"limit of 5 x 5: differentiate a smaller model",
    ):
        dm.solve(compiled, (0.0, 0.1), h=0.05, stages=3, sensitivities=["k"])
    monkeypatch.setattr(daemodel.files, "DENSE_MAX_ORDER", 1)
    with pytest.raises(E.ResourceLimitError, match=r"sensitivities of 'decay' \(2 unknowns, 1 stage\(s\)\)"):
        dm.solve(compiled, (0.0, 0.1), h=0.05, stages=3, sensitivities=["k"])  # (refused before solving)


@pytest.mark.parametrize(("rhs", "k"), [("-Abs(k)*x", 2.0), ("-Abs(k)*x", -2.0), ("-sign(k)*k*x", 2.0)])
def test_sensitivities_through_abs_and_sign_of_a_parameter(rhs, k):
    """x' = -|k| x: x(1) = exp(-|k|), dx(1)/dk = -sign(k) exp(-|k|).  sympy's derivative of Abs(k) for a symbol
    not declared real holds Derivative(im(k), k), sign(k)'s Derivative(sign(k), k): no printer prints them, and
    the solve raised sympy's PrintMethodNotImplementedError."""
    m = dm.Model("absk")
    m.states("x")
    m.parameter("k", k)
    m.ode("x", rhs)
    m.initial(x=1.0)
    sol = dm.solve(m, (0.0, 1.0), method="radau", rtol=1e-10, atol=1e-10, sensitivities=["k"])
    assert sol.status == "success"
    assert abs(sol["x"][-1] - np.exp(-abs(k))) < 1e-9
    assert abs(np.ravel(sol.sensitivities["k"])[-1] + np.sign(k) * np.exp(-abs(k))) < 1e-8

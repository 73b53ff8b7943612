"""Dense output (daemodel/dense.py): Solution.at evaluates the method's own continuous solution,
radau's and the Radau-PINN's collocation polynomials, at the method's accuracy (issue 28, item 1)."""

import math

import numpy as np
import pytest

import daemodel as dm
from daemodel import errors as E
from daemodel.problems import AKZO_NOBEL, HESSENBERG, PENDULUM

# radau's default on casadi's virtual machine, but in the tests marked machine_code (tests/conftest.py)
pytestmark = pytest.mark.virtual_machine

EXACT = HESSENBERG.exact_solution()


def _slope(hs, errors) -> float:
    return float(np.polyfit(np.log(hs), np.log(errors), 1)[0])


def _largest(values, reference, names) -> float:
    return max(float(np.abs(np.asarray(values[n]) - np.asarray(reference[n])).max()) for n in names)


@pytest.mark.filterwarnings("ignore::daemodel.errors.LocalErrorWarning")
@pytest.mark.parametrize("stages", [2, 3])
def test_between_the_steps_the_polynomial_converges_at_order_s_plus_1(stages):
    """Inside each step (theta = 0.37) the collocation polynomial's error against the exact solution
    falls as h^(s+1) (the stage order plus one: min(s+1, 2s-1) at s = 2, 3), for the states and for
    the index-2 algebraic variable alike, measured."""
    c = HESSENBERG.model().compile()
    hs, y_errors, z_errors = [0.05, 0.025, 0.0125], [], []
    for h in hs:
        sol = dm.solve(c, (0.0, 1.0), h=h, stages=stages)
        inside = (np.arange(round(1 / h)) + 0.37) * h
        values, exact = sol.at(inside), EXACT(inside)
        y_errors.append(_largest(values, exact, c.state_names))
        z_errors.append(_largest(values, exact, c.algebraic_names))
    print(f"s = {stages}: y {y_errors}, z {z_errors}")
    assert abs(_slope(hs, y_errors) - (stages + 1)) < 0.3
    assert abs(_slope(hs, z_errors) - (stages + 1)) < 0.3


@pytest.mark.parametrize(
    ("problem", "options", "outputs"),
    [
        (PENDULUM, {"h": 0.05, "stages": 3}, 5),  # the case: 1170x farther than t_eval before
        (PENDULUM, {"h": 0.05, "stages": 3}, 11),
        (AKZO_NOBEL, {"rtol": 1e-6, "atol": 1e-6}, 5),  # adaptive: 8e5x before
        (AKZO_NOBEL, {"rtol": 1e-6, "atol": 1e-6, "jit": True}, 5),
    ],
)
def test_at_is_what_t_eval_gives(problem, options, outputs):
    """at() between sparse outputs gives the values solve(..., t_eval=those times) gives (the same
    polynomials, the same steps), so its error against a tight reference is t_eval's (ratio 1, where
    the Hermite interpolant of the outputs was 27-8e5x farther, measured here too)."""
    c = problem.model().compile()
    t0, t1 = problem.t_span
    grid = np.linspace(t0, t1, outputs)
    between = np.linspace(t0, t1, 41)[1:-1]
    between = between[~np.isin(between, grid)]
    sparse = dm.solve(c, problem.t_span, t_eval=grid, **options)
    direct = dm.solve(c, problem.t_span, t_eval=between, **options)
    names = [*c.state_names, *c.algebraic_names]
    values = sparse.at(between)
    assert _largest(values, direct, names) <= 1e-14 * max(1.0, _largest(direct, dict.fromkeys(names, 0.0), names))
    reference = dm.solve(c, problem.t_span, t_eval=between, rtol=1e-12, atol=1e-12)
    error, direct_error = _largest(values, reference, names), _largest(direct, reference, names)
    assert error <= 2 * direct_error
    hermite = dm.solve(c, problem.t_span, t_eval=grid, dense_output=False, **options).at(between)
    states = c.state_names  # (what the outputs alone give: 38-1400x farther on the states)
    assert _largest(hermite, reference, states) > 20 * _largest(direct, reference, states)
    np.testing.assert_array_equal(sparse.at(grid)["y1"], sparse["y1"])  # (the outputs themselves)


def test_a_batch_and_the_default_grid():
    """A batch keeps its axis; without t_eval (outputs on the step grid) the same polynomials."""
    c = HESSENBERG.model().compile()
    batch = dm.solve(c, (0.0, 1.0), h=0.05, y0={"y1": [1.0, 1.0]}, stages=3)
    single = dm.solve(c, (0.0, 1.0), h=0.05, stages=3, t_eval=[0.0125, 0.5, 0.9875])
    values = batch.at([0.0125, 0.5, 0.9875])
    assert {name: v.shape for name, v in values.items()} == {n: (2, 3) for n in batch.names}
    for name in batch.names:
        np.testing.assert_allclose(values[name], np.broadcast_to(single[name], (2, 3)), rtol=1e-13, atol=1e-15)


def _switched():
    m = dm.Model("switched")
    m.states("x")
    m.ode("x", "-x + Piecewise((0, t < 0.37), (1, True))")
    m.initial(x=0.0)
    return m


def test_across_a_breakpoint_each_side_its_own_polynomial():
    """Segments: at() between outputs that enclose the breakpoint gives each side's own solution (the
    Hermite interpolant across it was refused); on the breakpoint, the value after it."""
    sol = dm.solve(_switched(), (0.0, 1.0), stages=3, h=0.02, t_eval=[0.0, 0.5, 1.0])
    times = np.array([0.2, 0.36, 0.37, 0.38, 0.45])
    exact = np.where(times < 0.37, 0.0, 1.0 - np.exp(-(times - 0.37)))
    np.testing.assert_allclose(sol.at(times)["x"], exact, rtol=0, atol=1e-9)


def test_groups_of_samples_that_switch_at_different_times():
    a = np.array([0.3, 0.4, 0.3])
    m = dm.Model("moving")
    m.states("x")
    m.parameter("a", 0.3)
    m.ode("x", "-x + Piecewise((0, t < a), (1, True))")
    m.initial(x=0.0)
    batch = dm.solve(m, (0.0, 1.0), stages=3, h=0.05, t_eval=[0.0, 0.5, 1.0], parameters={"a": a})
    times = np.array([0.25, 0.35, 0.45])
    exact = np.where(times[None] < a[:, None], 0.0, 1.0 - np.exp(-(times[None] - a[:, None])))
    np.testing.assert_allclose(batch.at(times)["x"], exact, rtol=0, atol=1e-9)


def test_a_terminal_event_ends_with_the_values_after_it():
    m = dm.Model("ball")
    m.states("h v")
    m.ode("h", "v")
    m.ode("v", "-9.81")
    m.initial(h=1.0, v=0.0)
    m.event("floor", "h", direction=-1, reset={"v": "-0.8*v"}, terminal=True)
    sol = dm.solve(m, (0.0, 1.0), rtol=1e-10, atol=1e-10)
    impact = math.sqrt(2 / 9.81)
    assert sol.t[-1] == sol.events["floor"]["t"][0, 0]
    values = sol.at([0.3, sol.t[-1]])
    assert abs(values["h"][0] - (1 - 0.5 * 9.81 * 0.09)) < 1e-9
    assert values["v"][1] == sol["v"][-1] > 0 and abs(values["v"][1] - 0.8 * 9.81 * impact) < 1e-8


def test_the_option_is_checked_and_named_in_the_memory_message():
    c = HESSENBERG.model().compile()
    with pytest.raises(E.InvalidOptionError, match=r"dense_output must be True or False; got 'yes'"):
        dm.solve(c, (0.0, 1.0), h=0.05, dense_output="yes")
    assert dm.solve(c, (0.0, 1.0), h=0.05, dense_output=False).dense is None


def test_the_memory_check_counts_the_polynomials(monkeypatch):
    """10^4 steps: 1.6 MB with each step's stages, 0.4 MB of step ends, 1 MB allowed."""
    monkeypatch.setenv("DAEMODEL_MEMORY_LIMIT", "1M")
    c = HESSENBERG.model().compile()
    with pytest.raises(
        E.ResourceLimitError,
        match=r"outputs with the dense output \(dense_output=False keeps the step ends only\) 0\.00149 GiB",
    ):
        dm.solve(c, (0.0, 1.0), h=1e-4, stages=3)
    assert dm.solve(c, (0.0, 1.0), h=1e-4, stages=3, dense_output=False).dense is None


def test_casadi_collocation_finds_its_polynomials_again(monkeypatch):
    """casadi-collocation's stages, solved again from each step's ends, give radau's polynomials (the
    same equations at the same h) to the root finders' tolerance; a step whose stages do not end at its
    own end value is named."""
    from daemodel.backends.casadi import collocation as backend

    c = HESSENBERG.model().compile()
    inside = (np.arange(20) + 0.37) * 0.05
    collocation = dm.solve(c, (0.0, 1.0), method="casadi-collocation", h=0.05, stages=3)
    radau = dm.solve(c, (0.0, 1.0), method="radau", h=0.05, stages=3)
    names = [*c.state_names, *c.algebraic_names]
    assert _largest(collocation.at(inside), radau.at(inside), names) < 1e-10
    assert radau.dense.description == "each step's collocation polynomial (degree 3)"
    assert collocation.dense.description == "each step's collocation polynomial (degree 3), its stages solved again"
    np.testing.assert_allclose(collocation.at(collocation.t)["y5"], collocation["y5"], rtol=0, atol=1e-10)
    monkeypatch.setattr(backend, "DENSE_END_MATCH", -1.0)
    fresh = dm.solve(c, (0.0, 1.0), method="casadi-collocation", h=0.05, stages=3)
    with pytest.raises(
        E.ConvergenceError,
        match=r"casadi-collocation's dense output: the stage equations of the step from t = 0\.3 \(h = 0\.05\) "
        r"solved again from its ends give an end value .* away from the step's own",
    ):
        fresh.at([0.32])


@pytest.mark.parametrize("method", ["casadi-idas", "reference"])
@pytest.mark.parametrize("problem", [PENDULUM, AKZO_NOBEL])
def test_restarts_from_the_output_before(problem, method):
    """casadi-idas and the reference between sparse outputs: the method started again from the output
    before each time, with the solve's tolerances (the reference with the integrator it ended with:
    Radau on stiff akzo-nobel); within 2x of t_eval's error against a tight reference (IDAS 1.5x and
    1.01x, the reference 1.0x and 0.11x measured), where the outputs' Hermite interpolant was
    100-1e5x farther."""
    c = problem.model().compile()
    t0, t1 = problem.t_span
    grid = np.linspace(t0, t1, 5)
    between = np.linspace(t0, t1, 41)[1:-1]
    between = between[~np.isin(between, grid)]
    options = {"method": method, "rtol": 1e-6, "atol": 1e-6}
    sparse = dm.solve(c, problem.t_span, t_eval=grid, **options)
    direct = dm.solve(c, problem.t_span, t_eval=between, **options)
    reference = dm.solve(c, problem.t_span, t_eval=between, rtol=1e-12, atol=1e-12)
    names = [*c.state_names, *c.algebraic_names]
    assert _largest(sparse.at(between), reference, names) <= 2 * _largest(direct, reference, names)
    np.testing.assert_array_equal(sparse.at(grid)["y1"], sparse["y1"])  # (the outputs themselves)
    assert sparse.dense.description.endswith("started again from the output before each time")


def test_a_failing_idas_restart_is_named():
    c = PENDULUM.model().compile()
    sol = dm.solve(c, (0.0, 1.0), method="casadi-idas", t_eval=[0.0, 0.5, 1.0])

    def failing(**inputs):
        raise RuntimeError("Error in Function::call for 'idas' [IdasInterface] at .../idas_interface.cpp")

    object.__setattr__(sol.dense, "integrator", lambda: type("Broken", (), {"map": lambda self, k: failing})())
    with pytest.raises(
        E.ConvergenceError,
        match=r"casadi-idas's dense output: IDAS started again from the outputs before t = 0\.2, 0\.7 failed "
        r"\(Error in Function::call for 'idas'.*\); ask for those times with t_eval instead",
    ):
        sol.at([0.2, 0.5, 0.7])


def _switch_in_time():
    m = dm.Model("sw")
    m.states("x y")
    m.algebraics("z")
    m.ode("x", "-x + z + Piecewise((0, t < 0.37), (1, True))")
    m.ode("y", "z")
    m.constraint("z - sin(x) - y")
    m.initial(x=1.0, y=0.0)
    return m


def _pendulum_at_a_wall():
    m = dm.Model("wall")
    m.states("x y u v")
    m.algebraics("lam")
    m.ode("x", "u")
    m.ode("y", "v")
    m.ode("u", "-lam*x")
    m.ode("v", "-lam*y - 9.81")
    m.constraint("x**2 + y**2 - 1", name="rod")
    m.initial(x=0.8, y=-0.6, u=0.0, v=0.0)
    m.event("wall", "x + 0.5", direction=-1, reset={"u": "-0.8*u", "v": "-0.8*v"})
    return m


@pytest.mark.parametrize("method", ["reference", "casadi-idas", "radau"])
def test_restarts_across_a_breakpoint_and_an_event(method):
    """Pieces after a breakpoint or an event hold outputs that leave their start out (the first) and
    end before the event (the last): each restarts from its own start and runs on past its last
    output.  The reference gave the next output's value, and an IndexError, before."""
    options = {"method": method, "rtol": 1e-10, "atol": 1e-10}
    switched = dm.solve(_switch_in_time(), (0.0, 1.0), t_eval=[0.0, 0.5, 1.0], **options)
    direct = dm.solve(_switch_in_time(), (0.0, 1.0), t_eval=[0.37, 0.45], **options)
    assert _largest(switched.at([0.37, 0.45]), direct, ["x", "y", "z"]) < 1e-8
    times = np.array([0.8, 0.99, 2.2, 2.3])  # (the wall at t = 0.729 and 2.243)
    wall = dm.solve(_pendulum_at_a_wall(), (0.0, 3.0), t_eval=np.linspace(0.0, 3.0, 4), **options)
    direct = dm.solve(_pendulum_at_a_wall(), (0.0, 3.0), t_eval=times, **options)
    assert _largest(wall.at(times), direct, ["x", "y", "u", "v"]) < 1e-6


@pytest.mark.parametrize("engine", ["torch", "casadi"])
def test_the_step_ends_alone_keep_no_stages(engine, monkeypatch):
    """dense_output=False keeps one value a step: a copy of the end, not a view that keeps the stages
    (s times the memory the check counts)."""
    from daemodel.backends.radau import step

    kept, integrate = [], step.Stepper.integrate

    def recording(self, t_span, *stop):
        out = integrate(self, t_span, *stop)
        kept.append(self.records)
        return out

    monkeypatch.setattr(step.Stepper, "integrate", recording)
    dm.solve(HESSENBERG.model().compile(), (0.0, 1.0), h=0.05, stages=3, engine=engine, dense_output=False)
    for block in kept[0].values[1:]:
        if engine == "torch":
            assert block.untyped_storage().nbytes() == block.numel() * block.element_size()
        else:
            assert block.base is None or block.base.size == block.size


@pytest.mark.parametrize("engine", ["casadi", "torch"])
def test_each_steps_points_read_apart_give_the_gathered_values_bit_for_bit(engine, monkeypatch):
    """Large steps' nodes are read step by step (dense.collocation_values, from NODES_PER_STEP_LOOP
    entries a step: no gathered copy of every point's nodes); forced here on Hessenberg with several
    outputs per step and steps without any: the same values bit for bit as the gathered product, and
    within the solve's tolerance of the exact solution."""
    from daemodel import dense

    c = HESSENBERG.model().compile()
    t_eval = np.r_[np.linspace(0.0, 0.3, 13), 0.71, 1.0]  # (several points in a step, steps without one)
    options = {"rtol": 1e-8, "atol": 1e-8, "engine": engine}
    gathered = dm.solve(c, (0.0, 1.0), t_eval=t_eval, **options)
    monkeypatch.setattr(dense, "NODES_PER_STEP_LOOP", 1)
    apart = dm.solve(c, (0.0, 1.0), t_eval=t_eval, **options)
    assert apart.status == gathered.status == "success" and apart.stats["steps"] < len(t_eval)
    names = [*c.state_names, *c.algebraic_names]
    for name in names:
        np.testing.assert_array_equal(apart[name], gathered[name])
    assert _largest(apart, EXACT(t_eval), names) < 1e-7  # (1.0e-8 casadi, 3.7e-9 torch at rtol 1e-8)


@pytest.mark.parametrize("loop", [False, True])
def test_values_written_in_their_place_are_the_joined_values_bit_for_bit(loop, monkeypatch):
    """collocation_values(out=) (the dense output's values at t_eval written in place, a batch's out not contiguous)
    gives the values of out=None bit for bit, in both ways (gathered, step by step); the nodes of a run of steps are
    a view of the block (records.block_nodes), other steps a copy, the same values, and the nodes are not written."""
    from daemodel.backends.radau.records import block_nodes

    from daemodel import dense

    monkeypatch.setattr(dense, "NODES_PER_STEP_LOOP", 1 if loop else 10**9)
    rng = np.random.default_rng(3)
    nodes = rng.standard_normal((3, 7, 4, 50))
    kept = nodes.copy()
    owner = np.sort(rng.integers(0, 7, 40))
    weights = rng.standard_normal((40, 4))
    nodes_of = lambda k: block_nodes(nodes, k, np.asarray)  # noqa: E731
    joined = dense.collocation_values(weights, owner, nodes_of, np, np.asarray)
    out = rng.standard_normal((3, 45, 50))
    before = out[:, :5].copy()
    dense.collocation_values(weights, owner, nodes_of, np, np.asarray, out=out[:, 5:])
    np.testing.assert_array_equal(out[:, 5:], joined)
    np.testing.assert_array_equal(out[:, :5], before)
    np.testing.assert_array_equal(nodes, kept)
    run, apart = block_nodes(nodes, np.array([2, 3, 4]), np.asarray), block_nodes(nodes, np.array([1, 4]), np.asarray)
    assert np.shares_memory(run, nodes) and not np.shares_memory(apart, nodes)
    np.testing.assert_array_equal(run, nodes[:, 2:5])
    np.testing.assert_array_equal(apart, nodes[:, [1, 4]])
    shuffled = block_nodes(nodes, np.array([1, 3, 2, 4]), np.asarray)  # (the span of a run, not one: gathered)
    assert not np.shares_memory(shuffled, nodes)
    np.testing.assert_array_equal(shuffled, nodes[:, [1, 3, 2, 4]])

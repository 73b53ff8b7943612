"""The Radau-PINN's inverse mode: estimates against the truth and against an independent classical
fit (radau at the same h), its certificate against an independent radau solve at the estimates,
the initial algebraic values following a fitted parameter, and every error message."""

import re
import warnings

import numpy as np
import pytest
import scipy.optimize
from daemodel.backends.pinn import inverse
from daemodel.backends.pinn.inverse import fit_inverse

import daemodel as dm
from daemodel.compiling.initial_states import initial_states
from daemodel.errors import FittedConstraintError, InvalidOptionError, ShapeError, TimeSpanError, TrainingError
from daemodel.problems import PENDULUM

SPAN = (0.0, 1.0)
TRUE = {"k": 1.5, "c": 2.0}
CONFIG = dm.PINNConfig(h=0.1, stages=3)


@pytest.fixture(scope="module")
def decay():
    """y' = -k y, 0 = z - c y^2 (index 1: z0 = c y0^2 moves with c)."""
    m = dm.Model("decay")
    (y,) = m.states("y")
    (z,) = m.algebraics("z")
    k, c = m.parameter("k", TRUE["k"]), m.parameter("c", TRUE["c"])
    m.ode(y, -k * y)
    m.constraint(z - c * y**2, name="square")
    m.initial(y=1.0)
    return m.compile()


def observations(compiled, times, noise=0.0, seed=0, parameters=None):
    """Values of y and z at ``times`` from radau at rtol 1e-10, with relative Gaussian noise."""
    sol = dm.solve(compiled, SPAN, method="radau", rtol=1e-10, atol=1e-12, parameters=parameters)
    values = sol.at(times)
    rng = np.random.default_rng(seed)
    return {name: np.asarray(values[name]).reshape(-1) * (1 + noise * rng.standard_normal(len(times))) for name in "yz"}


def fit(compiled, times, data, start=(3.0, 1.0), config=CONFIG, **options):
    bounds = (np.zeros(2), np.full(2, np.inf))
    state = initial_states(compiled)
    return fit_inverse(compiled, SPAN, times, data, ("k", "c"), np.array(start), bounds, state, config, **options)


TIMES = np.linspace(0.02, 1.0, 50)


def test_noise_free_data_recover_the_parameters(decay):
    result = fit(decay, TIMES, observations(decay, TIMES))
    # measured 6.9e-8 and 1.2e-6 from the truth: radau's own error at h = 0.1 (at h = 0.05: 2.7e-10
    # and 5.7e-8; the classical fit at the same h agrees, see the next test)
    assert result.converged and result.solution.status == "success"
    assert abs(result.parameters[0] - TRUE["k"]) < 3e-7
    assert abs(result.parameters[1] - TRUE["c"]) < 5e-6
    assert result.loss["max_residual"] <= CONFIG.tol
    assert result.solution.method == "pinn"
    # the solution holds the grid and the data times, and z0 followed c: c y0^2
    assert np.all(np.isin(TIMES, result.solution.t)) and np.all(np.isin(np.linspace(0, 1, 11), result.solution.t))
    assert result.solution["z"][0] == pytest.approx(result.parameters[1], rel=1e-12)


def classical_fit(compiled, times, data, start):
    """The same least-squares problem solved classically: radau at the fit's h and stages, by
    scipy (its own finite-difference Jacobian), each output scaled by its data's spread."""
    spread = {name: np.std(values) for name, values in data.items()}

    def misfit(theta):
        sol = dm.solve(
            compiled,
            SPAN,
            method="radau",
            h=CONFIG.h,
            stages=CONFIG.stages,
            parameters=dict(zip("kc", theta, strict=True)),
        )
        values = sol.at(times)
        return np.concatenate([(np.asarray(values[n]).reshape(-1) - data[n]) / spread[n] for n in data])

    return scipy.optimize.least_squares(misfit, start, xtol=1e-14, ftol=1e-14, gtol=1e-14).x


def test_noisy_data_give_the_classical_estimate_at_the_same_h(decay):
    data = observations(decay, TIMES, noise=0.01, seed=1)
    result = fit(decay, TIMES, data)
    # 1 % noise: measured 1.3e-3 and 8.7e-4 from the truth
    assert abs(result.parameters[0] - TRUE["k"]) < 0.01
    assert abs(result.parameters[1] - TRUE["c"]) < 0.01
    # the networks sit on radau's solution, so the estimate is the classical one at the same h
    # (measured 6e-11 apart)
    reference = classical_fit(decay, TIMES, data, [1.4, 2.1])
    assert np.allclose(result.parameters, reference, rtol=1e-8, atol=0)


def test_certificate_is_the_distance_to_radau_at_the_estimates(decay):
    data = observations(decay, TIMES, noise=0.01, seed=2)
    result = fit(decay, TIMES, data)
    grid = np.linspace(0, 1, 11)
    estimates = dict(zip(result.names, result.parameters, strict=True))
    radau = dm.solve(decay, SPAN, method="radau", h=CONFIG.h, stages=CONFIG.stages, parameters=estimates)
    rows = np.searchsorted(result.solution.t, grid)
    actual = np.stack([np.abs(result.solution[n][rows] - radau[n]) for n in "yz"], axis=-1)  # (T, 2)
    certified = np.maximum(result.certificate.distance[0], result.certificate.floor[0])
    assert result.certificate.certified.all() and result.solution.status == "success"
    assert np.all(actual <= certified)
    assert certified.max() < 1e-12
    # at the start values radau is far away: the certificate is at the estimates, not there
    away = dm.solve(decay, SPAN, method="radau", h=CONFIG.h, stages=CONFIG.stages, parameters={"k": 3.0, "c": 1.0})
    assert np.abs(result.solution["y"][rows] - away["y"]).max() > 1e3 * certified.max()


def test_sparse_data_still_recover_the_parameters(decay):
    times = np.linspace(0.2, 1.0, 5)
    result = fit(decay, times, observations(decay, times))
    # measured 1.5e-8 and 7e-11 from the truth
    assert np.allclose(result.parameters, [TRUE["k"], TRUE["c"]], rtol=0, atol=1e-7)


def test_missing_values_are_left_out(decay):
    data = observations(decay, TIMES)
    data["z"][::2] = np.nan  # half of z unobserved
    result = fit(decay, TIMES, data)
    assert result.loss["data_points"] == 75
    # within radau's own error at h = 0.1, as with every datum (measured 1e-8 and 1.0e-6)
    assert abs(result.parameters[0] - TRUE["k"]) < 3e-7
    assert abs(result.parameters[1] - TRUE["c"]) < 5e-6


def test_the_iteration_cap_flags_the_answer(decay):
    result = fit(decay, TIMES, observations(decay, TIMES), max_iterations=1)
    assert not result.converged and result.iterations == 1
    assert result.solution.status.startswith("flagged: the joint training did not converge")
    assert "max_iterations" in result.solution.status


def test_bounds_hold_the_estimate(decay):
    # the truth k = 1.5 lies outside (2, 4): the estimate stays inside
    bounds = (np.array([2.0, 0.0]), np.array([4.0, np.inf]))
    state = initial_states(decay)
    data = observations(decay, TIMES)
    result = fit_inverse(decay, SPAN, TIMES, data, ("k", "c"), np.array([3.0, 1.0]), bounds, state, CONFIG)
    assert 2.0 < result.parameters[0] < 2.01


@pytest.mark.slow
def test_pendulum_masses_and_forces_from_positions():
    """Index 2, two parameters: m and lam from y1 and y2 (measured 3e-7 from the truth, 10 s)."""
    compiled = PENDULUM.model().compile()
    sol = dm.solve(compiled, SPAN, method="radau", rtol=1e-10, atol=1e-12)
    values = sol.at(TIMES)
    data = {n: np.asarray(values[n]).reshape(-1) for n in ("y1", "y2")}
    bounds = (np.array([0.0, -np.inf]), np.full(2, np.inf))
    state = initial_states(compiled)
    config = dm.PINNConfig(h=0.05, stages=3)
    result = fit_inverse(compiled, SPAN, TIMES, data, ("m", "lam"), np.array([1.5, 0.5]), bounds, state, config)
    assert result.solution.status == "success"
    assert np.allclose(result.parameters, [1.0, 1.0], rtol=0, atol=2e-6)


# ---- errors -------------------------------------------------------------------------------------
def test_a_fitted_parameter_in_a_z_free_constraint_is_refused():
    m = dm.Model("held")
    (y,) = m.states("y")
    (z,) = m.algebraics("z")
    a = m.parameter("a", 1.0)
    m.ode(y, z)
    m.constraint(y - a, name="level")  # index 2: y0 = a holds at a = 1 only
    m.initial(y=1.0)
    compiled = m.compile()
    state = initial_states(compiled)
    with pytest.raises(FittedConstraintError, match=r"'level'.*involves the fitted parameter 'a' and no algebraic"):
        fit_inverse(compiled, SPAN, TIMES, {"y": np.ones(50)}, ("a",), [1.0], ([0.0], [2.0]), state, CONFIG)


@pytest.mark.parametrize(
    ("change", "error", "match"),
    [
        ({"times": TIMES[::-1]}, TimeSpanError, "times must be finite and sorted ascending"),
        ({"times": TIMES + 0.5}, TimeSpanError, r"times run from 0.52 to 1.5, outside t_span \(0, 1\)"),
        ({"times": np.zeros((2, 2))}, ShapeError, r"times must be a 1-d array of at least one time; got shape"),
        ({"data": {"w": np.ones(50)}}, ShapeError, r"data names 'w', not a variable of model 'decay'"),
        ({"data": []}, ShapeError, "data must be a dict output name"),
        ({"data": {"y": np.ones(49)}}, ShapeError, r"data\['y'\] has shape \(49,\); times has \(50,\)"),
        ({"data": {"y": np.full(50, np.inf)}}, ShapeError, r"data\['y'\] holds an infinite value; mark a missing one"),
        ({"data": {"y": np.full(50, np.nan)}}, ShapeError, "data holds no finite value"),
        ({"names": ("k", "q")}, ShapeError, r"names must be distinct parameters of model 'decay' \(k, c\)"),
        ({"start": [1.0]}, ShapeError, r"start must hold 2 finite values, one per name"),
        ({"start": [-1.0, 1.0]}, InvalidOptionError, r"start value of 'k', -1, is not strictly inside its bounds"),
        ({"config": dm.PINNConfig(dtype="float32")}, InvalidOptionError, "the inverse mode runs in float64 on the CPU"),
        ({"max_iterations": 0}, InvalidOptionError, "max_iterations must be a positive integer; got 0"),
    ],
)
def test_input_errors(decay, change, error, match):
    arguments = {
        "times": TIMES,
        "data": {"y": np.ones(50)},
        "names": ("k", "c"),
        "start": [3.0, 1.0],
        "config": CONFIG,
        "max_iterations": None,
    }
    arguments.update(change)
    state = initial_states(decay)
    bounds = (np.zeros(2), np.full(2, np.inf))
    if len(arguments["names"]) != 2:
        bounds = (np.zeros(len(arguments["names"])), np.full(len(arguments["names"]), np.inf))
    with pytest.raises(error, match=match):
        fit_inverse(
            decay,
            SPAN,
            arguments["times"],
            arguments["data"],
            arguments["names"],
            arguments["start"],
            bounds,
            state,
            arguments["config"],
            max_iterations=arguments["max_iterations"],
        )


def test_a_batch_of_states_is_refused(decay):
    state = initial_states(decay, y0={"y": [1.0, 2.0]})
    bounds = (np.zeros(2), np.full(2, np.inf))
    with pytest.raises(ShapeError, match="fit_inverse fits one trajectory; state holds 2 samples"):
        fit_inverse(decay, SPAN, TIMES, {"y": np.ones(50)}, ("k", "c"), [3.0, 1.0], bounds, state, CONFIG)


def test_networks_off_the_radau_solution_at_the_start_are_a_training_error(decay, monkeypatch):
    # a tol below rounding and no rounding floor: Newton on the networks cannot meet it
    monkeypatch.setattr(inverse, "STAGNATION_SIZE", 0.0)
    config = dm.PINNConfig(h=0.1, stages=3, tol=1e-30)
    keep = r"trained at the start values keep a Radau residual of .* above tol = 1e-30"
    with pytest.raises(TrainingError, match=keep):
        fit(decay, TIMES, observations(decay, TIMES), config=config)


def test_a_fit_is_flagged_where_radaus_estimate_at_its_h_is():
    """The stiff CSTR's feed rate from exact concentrations at h = 1: radau at that h is flagged by
    its own estimate (0.07 of the size of r at step 3), and so is the fit, whose networks are
    certified close to radau; before, it said "success"."""
    from pinn_hard_models import cstr

    c = cstr().compile()
    t = np.arange(1.0, 10.5, 1.0)
    reference = dm.solve(c, (0.0, 10.0), method="radau", rtol=1e-10, atol=1e-10)
    data = {"C": np.asarray(reference.at(t)["C"]).ravel()}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = dm.fit(c, t, data, {"F": (0.5, 1.0, 2.0)}, method="pinn", config=dm.PINNConfig(h=1.0))
    assert re.match(
        r"flagged: radau's local error estimate at the same h and stages, on the PINN's steps, reaches [0-9.]+ of "
        r"the solution's size at step 3 from t = 2 \(h = 1\), in 'r', beyond estimate_bound = 0\.001",
        result.status,
    ), result.status

"""Every error a solve can raise for bad input or a failing solver, with its message."""

import numpy as np
import pytest
import sympy as sp

import daemodel as dm
from daemodel import errors as E
from daemodel.problems import HESSENBERG, PENDULUM


@pytest.fixture(scope="module")
def pendulum():
    return PENDULUM.model().compile()


@pytest.mark.parametrize(
    ("t_span", "match"),
    [
        ((1.0, 0.0), r"t_span = \(1, 0\) is reversed"),
        ((0.0, 0.0), r"t_span = \(0, 0\) is empty"),
        ((0.0, float("inf")), "t_span must be finite"),
        ("ab", "must be a pair"),
        ((0.5, 1.0), "initial values of 'pendulum' hold at t0 = 0"),
    ],
)
def test_bad_time_spans(pendulum, t_span, match):
    with pytest.raises(E.TimeSpanError, match=match):
        dm.solve(pendulum, t_span, h=0.1)


def test_bad_t_eval(pendulum):
    with pytest.raises(E.TimeSpanError, match="outside t_span"):
        dm.solve(pendulum, (0.0, 1.0), h=0.1, t_eval=[0.5, 2.0])
    with pytest.raises(E.TimeSpanError, match="strictly increasing"):
        dm.solve(pendulum, (0.0, 1.0), method="reference", t_eval=[0.5, 0.2])
    # (two times below t0 within its slack were both clipped to t0: casadi-idas's first output at t0, and IDACalcIC,
    # given a step of 0, never returned)
    with pytest.raises(
        E.TimeSpanError, match=r"t_eval holds two times that lie outside t_span = \(0\.0, 1\.0\) by less"
    ):
        dm.solve(pendulum, (0.0, 1.0), method="casadi-idas", t_eval=[-1e-13, -5e-14, 0.5])


def test_step_sizes(pendulum):
    with pytest.raises(E.StepSizeError, match=r"h = 2 is larger than the interval .* take h <= 1"):
        dm.solve(pendulum, (0.0, 1.0), h=2.0)
    with pytest.raises(E.StepSizeError, match="larger than the interval"):
        dm.solve(pendulum, (0.0, 1.0), method="casadi-collocation", h=1.5)
    with pytest.raises(E.InvalidOptionError, match="h must be positive"):
        dm.solve(pendulum, (0.0, 1.0), h=-0.1)
    with pytest.raises(E.InvalidOptionError, match="give one or the other"):
        dm.solve(pendulum, (0.0, 1.0), h=0.1, rtol=1e-6)


def test_unknown_method_lists_the_known_ones(pendulum):
    with pytest.raises(E.UnknownMethodError, match="unknown method 'rk4'; the methods are radau, casadi-collocation"):
        dm.solve(pendulum, (0.0, 1.0), method="rk4")
    assert dm.methods() == ("radau", "casadi-collocation", "casadi-idas", "reference", "pinn")


def test_unknown_option_lists_the_method_options(pendulum):
    with pytest.raises(E.UnknownOptionError, match=r"method 'radau' has no option 'stage'; its options are .*stages"):
        dm.solve(pendulum, (0.0, 1.0), stage=3)
    with pytest.raises(E.UnknownOptionError, match="'casadi-idas' has no option 'h'"):
        dm.solve(pendulum, (0.0, 1.0), method="casadi-idas", h=0.1)


@pytest.mark.parametrize(
    ("kwargs", "error", "match"),
    [
        ({"stages": 0}, E.InvalidOptionError, "stages must be an integer from 1 to 7"),
        ({"stages": 2.5}, E.InvalidOptionError, "stages must be an integer"),
        ({"dtype": "float16"}, E.InvalidOptionError, "dtype must be 'float64'"),
        ({"max_newton_iterations": 0}, E.InvalidOptionError, "max_newton_iterations must be positive"),
        ({"reuse_jacobian": "yes"}, E.InvalidOptionError, "reuse_jacobian must be True or False"),
        ({"device": "cuda:7", "h": 0.1}, E.InvalidOptionError, "torch sees no CUDA device"),
    ],
)
def test_invalid_radau_options(pendulum, kwargs, error, match):
    import torch

    if "device" in kwargs and torch.cuda.is_available():
        pytest.skip("a CUDA device is present")
    with pytest.raises(error, match=match):
        dm.solve(pendulum, (0.0, 1.0), **kwargs)


def test_invalid_options_of_other_methods(pendulum):
    with pytest.raises(E.InvalidOptionError, match="integrator must be one of DOP853"):
        dm.solve(pendulum, (0.0, 1.0), method="reference", integrator="Euler")
    with pytest.raises(E.InvalidOptionError, match="rtol must be positive"):
        dm.solve(pendulum, (0.0, 1.0), method="casadi-idas", rtol=0.0)


def test_batch_shapes(pendulum):
    with pytest.raises(E.ShapeError, match=r"y0 must have shape \(4,\) or \(batch, 4\) .*got shape \(3, 5\)"):
        dm.solve(pendulum, (0.0, 1.0), h=0.1, y0=np.zeros((3, 5)))
    with pytest.raises(E.ShapeError, match="the arrays have different lengths y1: 3, y2: 2"):
        dm.solve(pendulum, (0.0, 1.0), h=0.1, y0={"y1": [1, 0, 1], "y2": [0, 1]})
    with pytest.raises(E.ShapeError, match="the batch sizes differ: y0 has 2 samples, parameters has 3"):
        dm.solve(pendulum, (0.0, 1.0), h=0.1, y0={"y1": [1.0, 1.0]}, parameters={"m": [1.0, 2.0, 3.0]})
    with pytest.raises(E.UnknownSymbolError, match="y0 names 'q', which is not among"):
        dm.solve(pendulum, (0.0, 1.0), h=0.1, y0={"q": 1.0})
    with pytest.raises(E.InvalidValueError, match="y1 of sample 1 is nan"):
        dm.solve(pendulum, (0.0, 1.0), h=0.1, y0={"y1": [1.0, np.nan]})


def test_inconsistent_batch_names_the_samples(pendulum):
    y0 = {"y1": [1.0, 0.6, 1.0], "y2": [0.0, -0.8, 0.0], "y3": [0.0, 0.5, 0.0], "y4": [1.0, 0.0, 1.0]}
    with pytest.raises(E.InconsistentInitialStateError, match=r"samples 1 violate .* sample 1: .*velocity"):
        dm.solve(pendulum, (0.0, 1.0), h=0.1, y0=y0)
    with pytest.raises(E.InconsistentAlgebraicValueError, match="z0: y5 = 3 of sample 0 disagrees"):
        dm.solve(pendulum, (0.0, 1.0), h=0.1, z0={"y5": 3.0})


def test_max_newton_iterations_bounds_the_damped_fallback_too():
    """One iteration cannot converge a step, so every step falls back to damped Newton, which may
    take 5 x max_newton_iterations: it reaches the same collocation solution."""
    c = HESSENBERG.model().compile()
    capped = dm.solve(c, (0.0, 1.0), h=0.1, max_newton_iterations=1)
    assert capped.stats["damped_newton_attempts"] == 10 and capped.stats["max_newton_iterations"] <= 5
    free = dm.solve(c, (0.0, 1.0), h=0.1)
    assert free.stats["damped_newton_attempts"] == 0
    assert np.max(np.abs(capped["y1"] - free["y1"])) < 1e-13


@pytest.mark.parametrize("engine", ["casadi", "torch"])
def test_a_failed_damped_newton_says_why_after_the_undamped_reason(engine):
    """y' = y^2 from y(0) = 1 has no Radau IIA stage solution for h = 2 (it blows up at t = 1):
    the undamped iterations diverge, and no damped step from the start value decreases the increment."""
    m = dm.Model("blowup")
    (y,) = m.states("y")
    m.ode(y, y**2)
    m.initial(y=1.0)
    with pytest.raises(
        E.ConvergenceError,
        match=r"Newton failed in step 1 from t = 0 with h = 2 \(diverging \(contraction [0-9.]+\); damped Newton: "
        r"no damped step down to 0\.00098 of the increment decreases it \(increment [0-9.e+]+, tolerance 2\.2e-15\), "
        r"sample 0\); take a smaller h",
    ):
        dm.solve(m, (0.0, 4.0), h=2.0, engine=engine)


def test_z_undetermined_along_a_fixed_step_run_is_named():
    """0 = (0.5 - y) z - 1 stops determining z as y reaches 0.5: a fixed step says so, instead of
    a Newton failure after a restart (the restart from the step's start value is only for a guess
    at which f or g is not finite)."""
    m = dm.Model("flip")
    (y,) = m.states("y")
    (z,) = m.algebraics("z")
    m.ode(y, 1 + 0 * z)
    m.constraint((0.5 - y) * z - 1, name="c")
    m.initial(y=0.0)
    for h, where in ((0.03, "t = 0.48 and 0.51"), (0.13, "t = 0.26 and 0.52")):
        with pytest.raises(
            E.ConvergenceError,
            match=rf"the constraints \('c'\) stop determining the algebraic variables between {where}",
        ):
            dm.solve(m, (0.0, 1.0), h=h)


def test_blow_up_raises_instead_of_returning_nan():
    m = dm.Model("blowup")
    (y,) = m.states("y")
    m.ode(y, y**2)  # y = 1/(1 - t): infinite at t = 1
    m.initial(y=1.0)
    with pytest.raises(E.ConvergenceError, match=r"radau: .*t = 0\.9"):
        dm.solve(m, (0.0, 2.0), h=0.1)
    with pytest.raises(E.ConvergenceError, match=r"step size underflow at t = 1 \(h = .*\); the solution may blow up"):
        dm.solve(m, (0.0, 2.0), rtol=1e-6)


def test_max_steps(pendulum):
    with pytest.raises(E.StepLimitError, match="max_steps = 3 reached at t = "):
        dm.solve(pendulum, (0.0, 1.0), rtol=1e-8, max_steps=3)


def test_solution_errors(pendulum):
    sol = dm.solve(pendulum, (0.0, 1.0), h=0.1)
    with pytest.raises(E.UnknownSymbolError, match="the solution has no variable 'y9'"):
        sol["y9"]
    other = dm.solve(pendulum, (0.0, 1.0), method="reference")  # 101 times: its dense output answers at sol.t
    direct = dm.solve(pendulum, (0.0, 1.0), method="reference", t_eval=sol.t)
    for name, error in sol.errors(other).items():
        assert error["max"] == pytest.approx(sol.errors(direct)[name]["max"], rel=1e-3, abs=1e-11)
    plain = dm.solve(pendulum, (0.0, 1.0), h=0.05, dense_output=False)
    with pytest.raises(
        E.ComparisonError,
        match=r"the reference \(radau\) has 21 times from 0 to 1, this solution \(radau\) 11 from 0 to 1; solve the "
        r"reference with t_eval=sol\.t",
    ):
        sol.errors(plain)
    short = dm.solve(pendulum, (0.0, 0.5), h=0.05)
    with pytest.raises(E.ComparisonError, match=r"11 from 0 to 1, beyond the span of its dense output; solve the"):
        sol.errors(short)
    with pytest.raises(E.ComparisonError, match="cannot compare"):
        sol.errors(lambda t: {"q": t})
    with pytest.raises(E.ComparisonError, match="needs a Solution or a callable"):
        sol.errors(3.0)
    with pytest.raises(E.ModelError, match="needs a Model or a CompiledDAE"):
        dm.solve("pendulum", (0.0, 1.0))


def test_a_singular_newton_matrix_names_its_cause():
    """A fixed step whose Newton matrix is singular says why: a Jacobian that is not finite (sqrt(x)
    at x = 0, where f is finite), or a step size that puts an eigenvalue of the Jacobian on the
    method's real shift gamma / h."""
    from daemodel.backends.radau import embedded_weights
    from daemodel.backends.radau.transform import StageTransform

    from daemodel.tableau import radau_iia

    root = dm.Model("root")
    x, y = root.states("x y")
    root.ode(x, 1 + 0 * y)
    root.ode(y, sp.sqrt(x))
    root.initial(x=0.0, y=0.0)
    for engine in ("casadi", "torch"):
        with pytest.raises(
            E.ConvergenceError,
            match=r"singular for sample 0 at t = 0 with h = 0\.1: the Jacobian of f and g is not finite there "
            r"\(d\(y'\)/d\(x\) = (inf|nan) for sample 0: f or g is not differentiable at this state, e\.g\. sqrt\(x\) "
            r"at x = 0, or the state left their domain",
        ):
            dm.solve(root, (0.0, 1.0), stages=3, h=0.1, engine=engine)
    tableau = radau_iia(3)
    blocks = StageTransform.of(tableau.A, embedded_weights(tableau)[0]).blocks
    gamma = next(lam.real for _, lam in blocks if lam.imag == 0)
    m = dm.Model("resonant")
    (y,) = m.states("y")
    m.parameter("a", gamma / 0.1)  # y' = a y with a h = gamma: sigma - a = 0 exactly
    m.ode(y, "a*y")
    m.initial(y=1.0)
    with pytest.raises(E.ConvergenceError, match=r"an eigenvalue of the Jacobian times h meets one of the method"):
        dm.solve(m, (0.0, 0.2), stages=3, h=0.1)

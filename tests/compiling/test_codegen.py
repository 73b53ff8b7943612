"""Generated torch and casadi functions agree with sympy; batching, autograd, dtypes, errors."""

import linecache
import math

import casadi
import numpy as np
import pytest
import sympy as sp
import torch

import daemodel as dm
from daemodel import errors as E
from daemodel.problems import HESSENBERG, PENDULUM


def zoo() -> dm.Model:
    """Every supported function at least once."""
    m = dm.Model("zoo")
    a, b = m.states("a b")
    (z,) = m.algebraics("z")
    mu = m.parameter("mu", 0.7)
    t = m.t
    m.ode(
        a,
        sp.sin(a) * sp.cos(b)
        + sp.tan(a / 3)
        + sp.exp(-(a**2))
        + sp.log(1 + b**2)
        + sp.sqrt(2 + a)
        + sp.Abs(a - b)
        + sp.sign(a)
        + sp.atan2(a, b + 3)
        + 1 / sp.sqrt(3 + b**2)
        + sp.sin(1)
        + mu * z,
    )
    m.ode(
        b,
        "asin(a/4) + acos(b/4) + atan(a) + sinh(a/2) + cosh(b/3) + tanh(a) + asinh(b) + acosh(2 + a^2)"
        " + atanh(a/5) + erf(b) + Max(a, b, 0.3) + Min(a, b) + Piecewise((a**2, a > b), (b, True))"
        " + pi*t + (2 + a**2)**(1/3) + 2**a + ln(3) + abs(b)",
    )
    m.constraint(z - a * b - sp.cos(t), name="law")
    m.initial(a=0.3, b=-0.2)
    return m


def random_points(c, count, seed=0):
    rng = np.random.default_rng(seed)
    n, m_, k = len(c.states), len(c.algebraics), len(c.parameters)
    t = rng.uniform(0, 1, count)
    y = rng.uniform(-1.5, 1.5, (count, n))
    z = rng.uniform(-1.5, 1.5, (count, m_))
    p = rng.uniform(0.5, 2.0, (count, k))
    return t, y, z, p


def sympy_values(c, exprs, t, y, z, p):
    subs = {
        c.t: t,
        **dict(zip(c.states, y, strict=True)),
        **dict(zip(c.algebraics, z, strict=True)),
        **dict(zip(c.parameters, p, strict=True)),
    }
    return np.array([float(sp.N(e.subs(subs), 30)) for e in exprs])


@pytest.mark.parametrize("model", [zoo, HESSENBERG.model, PENDULUM.model], ids=["zoo", "hessenberg", "pendulum"])
def test_torch_casadi_sympy_agree(model):
    c = model().compile()
    tf = c.torch_functions()
    dae = c.casadi_dae()
    F = casadi.Function("F", [dae["t"], dae["x"], dae["z"], dae["p"]], [dae["ode"], dae["alg"]])
    t, y, z, p = random_points(c, 12)
    as_t = [torch.tensor(v, dtype=torch.float64) for v in (t, y, z, p)]
    f_torch, g_torch = tf.f(*as_t).numpy(), tf.g(*as_t).numpy()
    for i in range(len(t)):
        f_ref = sympy_values(c, c.rhs, t[i], y[i], z[i], p[i])
        g_ref = sympy_values(c, c.g, t[i], y[i], z[i], p[i])
        f_ca, g_ca = (np.array(v).ravel() for v in F(t[i], y[i], z[i], p[i]))
        np.testing.assert_allclose(f_torch[i], f_ref, rtol=1e-13, atol=1e-14)
        np.testing.assert_allclose(g_torch[i], g_ref, rtol=1e-13, atol=1e-14)
        np.testing.assert_allclose(f_ca, f_ref, rtol=1e-13, atol=1e-14)
        np.testing.assert_allclose(g_ca, g_ref, rtol=1e-13, atol=1e-14)


@pytest.mark.parametrize("batch", [(), (5,), (2, 3, 4)])
def test_any_leading_batch_shape(batch):
    c = PENDULUM.model().compile()
    tf = c.torch_functions()
    y = torch.randn(*batch, 4, dtype=torch.float64)
    z = torch.randn(*batch, 1, dtype=torch.float64)
    t = torch.rand(batch, dtype=torch.float64)
    f, g = tf.f(t, y, z), tf.g(t, y, z)
    assert f.shape == (*batch, 4) and g.shape == (*batch, 1)
    flat = tf.f(t.reshape(-1), y.reshape(-1, 4), z.reshape(-1, 1))
    torch.testing.assert_close(f.reshape(-1, 4), flat, rtol=0, atol=0)


def test_parameters_broadcast_over_samples_and_stages():
    c = PENDULUM.model().compile()
    tf = c.torch_functions()
    y = torch.randn(6, 3, 4, dtype=torch.float64)  # [samples, stages, n]
    z = torch.randn(6, 3, 1, dtype=torch.float64)
    p_shared = torch.tensor([2.0, 0.5], dtype=torch.float64)  # (k,)
    p_each = p_shared.expand(6, 1, 2)  # per sample
    f_shared, f_each = tf.f(0.0, y, z, p_shared), tf.f(0.0, y, z, p_each)
    torch.testing.assert_close(f_shared, f_each, rtol=0, atol=0)
    # y4' = (-y2 y5 - lam) / m with m = 2, lam = 0.5
    torch.testing.assert_close(f_shared[..., 3], (-y[..., 1] * z[..., 0] - 0.5) / 2.0)
    # default parameters are the model's values (m = lam = 1)
    torch.testing.assert_close(tf.f(0.0, y, z)[..., 3], -y[..., 1] * z[..., 0] - 1.0)
    assert tf.parameters.tolist() == [1.0, 1.0] and c.parameter_names == ("m", "lam")


def test_autograd_through_generated_functions():
    c = zoo().compile()
    tf = c.torch_functions()
    t, y, z, p = random_points(c, 4, seed=1)
    y = torch.tensor(y, requires_grad=True)
    z = torch.tensor(z, requires_grad=True)
    assert torch.autograd.gradcheck(lambda y, z: tf.f(torch.tensor(t), y, z, torch.tensor(p)), (y, z))
    assert torch.autograd.gradcheck(lambda y, z: tf.g(torch.tensor(t), y, z, torch.tensor(p)), (y, z))


def test_dtype_device_and_cache():
    c = HESSENBERG.model().compile()
    tf32 = c.torch_functions(dtype=torch.float32, device="cpu")
    y, z = torch.ones(2, 4), torch.ones(2, 1)
    assert tf32.f(0.0, y, z).dtype == torch.float32 and tf32.dtype == torch.float32
    assert c.torch_functions(dtype=torch.float32) is tf32
    assert c.torch_functions().dtype == torch.float64


def test_constant_rows_are_broadcast():
    m = dm.Model("constants")
    y1, y2 = m.states("y1 y2")
    m.ode(y1, 0)
    m.ode(y2, sp.Rational(1, 3))
    m.initial(y1=0.0, y2=0.0)
    tf = m.compile().torch_functions()
    out = tf.f(
        torch.zeros(5, dtype=torch.float64),
        torch.zeros(5, 2, dtype=torch.float64),
        torch.zeros(5, 0, dtype=torch.float64),
    )
    torch.testing.assert_close(out, torch.tensor([[0.0, 1 / 3]] * 5, dtype=torch.float64), rtol=0, atol=0)


def test_reserved_names_are_renamed():
    m = dm.Model("reserved")
    y, p, torch_ = m.states("y p torch")
    (z,) = m.algebraics("z")
    m.ode(y, -z)
    m.ode(p, y * torch_)
    m.ode(torch_, 1)
    m.constraint(z - y - p**2, name="law")
    m.initial(y=1.0, p=2.0, torch=3.0)
    c = m.compile()
    tf = c.torch_functions()
    assert "y_ = y[..., 0]" in tf.source["f"] and "torch_ = y[..., 2]" in tf.source["f"]
    out = tf.f(0.0, torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64), torch.tensor([5.0], dtype=torch.float64))
    assert out.tolist() == [-5.0, 3.0, 1.0]


def test_array_elements_become_identifiers_in_generated_source_and_casadi():
    """u[0] is no Python name: the torch source and casadi's symbols name it u_0 (and a scalar u_0
    declared after it u_0_), and no bracket of a user's name reaches generated code."""
    m = dm.Model("elements")
    u = m.states("u", 2)
    (u_0,) = m.states("u_0")
    T = m.algebraics("T", (1, 2))
    m.ode(u, [-u[1] * T[0, 0], u_0 - T[0, 1] + u[0]])
    m.ode(u_0, -u_0)
    m.constraint(T[0] - 2 * u + T[0] ** 3, name="law")
    m.initial(u=[1.0, 2.0], u_0=3.0)
    c = m.compile()
    tf = c.torch_functions()
    assert "u_0 = y[..., 0]" in tf.source["f"] and "u_0_ = y[..., 2]" in tf.source["f"]
    assert "T_0_1 = z[..., 1]" in tf.source["f"]
    for source in tf.source.values():
        body = source.replace("y[..., ", "").replace("z[..., ", "").replace("p[..., ", "")
        assert not any(f"{name}[" in body for name in ("u", "T")), source
    y, z = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64), torch.tensor([5.0, 7.0], dtype=torch.float64)
    assert tf.f(0.0, y, z).tolist() == [-10.0, 3.0 - 7.0 + 1.0, -3.0]
    dae = c.casadi_dae()
    assert [dae["x"][i].name() for i in range(3)] == ["u_0", "u_1", "u_0_"]
    assert [dae["z"][i].name() for i in range(2)] == ["T_0_0", "T_0_1"]
    ode = casadi.Function("f", [dae["x"], dae["z"], dae["p"], dae["t"]], [dae["ode"]])
    assert np.array(ode([1.0, 2.0, 3.0], [5.0, 7.0], [], 0.0)).ravel().tolist() == [-10.0, -3.0, -3.0]


def test_source_is_readable_and_registered():
    c = HESSENBERG.model().compile()
    tf = c.torch_functions()
    src = tf.source["f"]
    assert "_c0 = " in src and "# f[0]: ODE #1" in src  # common subexpressions, equation numbers
    # no user text besides validated identifiers: the model's name appears nowhere
    assert all("hessenberg" not in text for text in tf.source.values())
    filename = tf.f.__code__.co_filename
    assert linecache.getline(filename, 1) == "_layout_f = None\n"  # f has no constant entries
    assert linecache.getline(filename, 2).startswith("def f(t, y, z, p=None):")


def test_shape_errors_name_expected_and_actual():
    tf = HESSENBERG.model().compile().torch_functions()
    with pytest.raises(E.ShapeError, match=r"model 'hessenberg': y must have shape \(\.\.\., 4\); got \(2, 3\)"):
        tf.f(0.0, torch.ones(2, 3, dtype=torch.float64), torch.ones(2, 1, dtype=torch.float64))
    with pytest.raises(E.ShapeError, match=r"z must have shape \(\.\.\., 1\); got \(2, 2\)"):
        tf.g(0.0, torch.ones(2, 4, dtype=torch.float64), torch.ones(2, 2, dtype=torch.float64))
    with pytest.raises(E.ShapeError, match=r"p must have shape \(\.\.\., 0\); got \(1,\)"):
        tf.g(
            0.0,
            torch.ones(4, dtype=torch.float64),
            torch.ones(1, dtype=torch.float64),
            torch.ones(1, dtype=torch.float64),
        )


def test_unsupported_function_after_reduction_names_the_derived_constraint():
    # d/dt Max(y, 0) contains Heaviside, which no emitter supports
    m = dm.Model("kink")
    (y,) = m.states("y")
    (z,) = m.algebraics("z")
    m.ode(y, z)
    m.constraint(sp.Max(y, 0) - m.t - 1, name="kink")
    m.initial(y=1.0)
    c = m.compile()
    with pytest.raises(
        E.UnsupportedFunctionError, match=r"model 'kink', g: kink' \(#2, index 1\): function 'Heaviside'"
    ):
        c.reduced(index=1).torch_functions()


def test_casadi_idas_on_index1_reduction_matches_exact_solution():
    # An independent check of the casadi emitter: IDAS integrates the index-1 reduction.
    c = HESSENBERG.model().compile().reduced(index=1)
    dae = c.casadi_dae()
    assert set(dae) == {"x", "z", "p", "t", "ode", "alg"}
    grid = [0.25, 0.5]
    F = casadi.integrator("F", "idas", dae, 0.0, grid, {"abstol": 1e-12, "reltol": 1e-12})
    out = F(x0=c.y0, z0=c.z0, p=c.parameter_values)
    exact = HESSENBERG.exact_solution()(np.array(grid))
    xf, zf = np.array(out["xf"]), np.array(out["zf"])
    for i, name in enumerate(c.state_names):
        np.testing.assert_allclose(xf[i], exact[name], rtol=1e-8)
    np.testing.assert_allclose(zf[0], exact["y5"], rtol=1e-7)


def test_the_casadi_dae_is_made_once_per_model(monkeypatch):
    """casadi-idas converted the sympy system to casadi on every call (1-7 ms of its setup): the DAE is
    kept with the compiled model; each call returns its own dict."""
    from daemodel.compiling import compiled as compiled_module

    c = PENDULUM.model().compile()
    first = c.casadi_dae()
    first["ode"] = None  # (a caller's dict: the kept one is untouched)
    made = []

    class Counting(compiled_module.CasadiConverter):
        def __init__(self, *args, **kwargs):
            made.append(1)
            super().__init__(*args, **kwargs)

    monkeypatch.setattr(compiled_module, "CasadiConverter", Counting)
    again = c.casadi_dae()
    assert made == [] and again["ode"] is not None and again["alg"] is c.casadi_dae()["alg"]
    c.reduced(1).casadi_dae()  # (another system: converted)
    assert made == [1]


def _one_at_a_time_and_stacked(compiled, monkeypatch):
    """casadi's ode/alg function of ``compiled`` converted one expression at a time and stacked by
    structure (daemodel.compiling.codegen.VECTOR_GROUP), each on a fresh conversion."""
    from daemodel.compiling import codegen

    functions = []
    for group in (10**9, 2):
        monkeypatch.setattr(codegen, "VECTOR_GROUP", group)
        compiled._cache.pop("casadi_dae", None)
        dae = compiled.casadi_dae()
        functions.append(casadi.Function("f", [dae["t"], dae["x"], dae["z"], dae["p"]], [dae["ode"], dae["alg"]]))
    return functions


@pytest.mark.parametrize("size", [12, 40])
def test_expressions_of_one_structure_are_converted_together_to_the_same_bits(monkeypatch, size):
    """A line of cells with every kind of node (functions, Max, Piecewise with relations and logic,
    powers, a root, a shared subexpression, numbers that differ per cell): stacked by structure, the
    casadi functions give the one-at-a-time conversion's values bit for bit, with no more operations."""
    m = dm.Model("cells")
    u, w = m.states("u", size), m.algebraics("w", size)
    k = m.parameter("k", 0.7)
    shared = sp.sin(k * m.t)  # (in every equation: made once)
    for i in range(size):
        left, right = u[i - 1] if i else u[size - 1], u[(i + 1) % size]
        switch = sp.Piecewise(
            (left - u[i], (u[i] > 0.5) & (w[i] < 2)), (sp.Max(u[i], right) ** 2, u[i] < -1), (0, True)
        )
        m.ode(u[i], (i + 1) * (left - 2 * u[i] + right) - sp.exp(-u[i]) * shared + switch / (3 + i % 3))
        m.constraint(w[i] - sp.sqrt(1 + u[i] ** 2) - sp.Rational(1, i + 2) * sp.cos(u[i]) ** 3, name=f"c{i}")
    m.initial(**{f"u[{i}]": 0.1 * i - 0.4 for i in range(size)})
    compiled = m.compile()
    one, stacked = _one_at_a_time_and_stacked(compiled, monkeypatch)
    assert stacked.n_instructions() <= one.n_instructions()
    rng = np.random.default_rng(size)
    for _ in range(20):
        args = (rng.uniform(0, 3), rng.uniform(-2, 2, size), rng.uniform(0, 3, size), rng.uniform(0, 1, 1))
        for a, b in zip(one(*args), stacked(*args), strict=True):
            assert np.array_equal(np.asarray(a), np.asarray(b)), (a, b)


def test_the_library_models_convert_to_the_same_bits_stacked(monkeypatch):
    from daemodel.problems import PROBLEMS

    for name in ("wheelset", "squeezer", "car-axis"):
        compiled = PROBLEMS[name].model().compile()
        one, stacked = _one_at_a_time_and_stacked(compiled, monkeypatch)
        assert stacked.n_instructions() <= one.n_instructions(), name
        args = [np.linspace(0.3, 0.9, max(f.numel(), 1))[: f.numel()] for f in one.mx_in()]
        for a, b in zip(one(*args), stacked(*args), strict=True):
            assert np.array_equal(np.asarray(a), np.asarray(b), equal_nan=True), name


def _nan_in_max_or_min() -> dm.Model:
    """a' = Max(a, sqrt(b)) and b' = Min(sqrt(a), b): a nan where a or b is negative, in either argument.

    casadi's fmax and fmin return the other argument where one is nan, and torch.where(a >= b, a, b) returns b
    where a is nan: both gave a number (1, 0.5, ...) where sympy and numpy give nan."""
    m = dm.Model("nanargs")
    a, b = m.states("a b")
    m.ode(a, sp.Max(a, sp.sqrt(b)))
    m.ode(b, sp.Min(sp.sqrt(a), b))
    m.initial(a=1.0, b=1.0)
    return m


def _nan_in_a_piecewise_condition() -> dm.Model:
    """a' = Piecewise((1, sqrt(b) > 0), (2, True)), b' = Piecewise((a, sqrt(a) < 1 and b > 0), (-a, True)).

    nan > 0 is False in numpy, torch and casadi alike: the first took the otherwise branch, 2, where b < 0
    (sympy's own value there is no number either); the second's condition is an And of two comparisons."""
    m = dm.Model("nanpiece")
    a, b = m.states("a b")
    m.ode(a, sp.Piecewise((1, sp.sqrt(b) > 0), (2, True)))
    m.ode(b, sp.Piecewise((a, sp.And(sp.sqrt(a) < 1, b > 0)), (-a, True)))
    m.initial(a=1.0, b=1.0)
    return m


INF, NAN = math.inf, math.nan


@pytest.mark.parametrize(
    ("model", "points", "expected"),
    [
        (
            _nan_in_max_or_min,
            [(-1.0, 4.0), (4.0, -1.0), (NAN, 1.0), (1.0, NAN), (4.0, 1.0), (0.25, 4.0), (INF, 4.0)],
            [(2.0, NAN), (NAN, -1.0), (NAN, NAN), (NAN, NAN), (4.0, 1.0), (2.0, 0.5), (INF, 4.0)],
        ),
        (
            _nan_in_a_piecewise_condition,
            [(0.25, 4.0), (4.0, -1.0), (-1.0, 4.0), (NAN, 1.0), (0.25, -1.0), (INF, 0.0), (0.25, 0.0)],
            [(1.0, 0.25), (NAN, -4.0), (1.0, NAN), (1.0, NAN), (NAN, -0.25), (2.0, -INF), (2.0, -0.25)],
        ),
    ],
    ids=["max-or-min", "piecewise"],
)
def test_a_nan_through_a_max_or_a_piecewise_gives_the_same_values_in_every_emitter(model, points, expected):
    # a nan in a Max's or Min's argument, or in a Piecewise's condition, is a nan in numpy, torch and casadi;
    # finite and infinite values as before
    c = model().compile()
    tf, dae = c.torch_functions(), c.casadi_dae()
    F = casadi.Function("F", [dae["t"], dae["x"], dae["z"], dae["p"]], [dae["ode"]])
    Y = np.array(points)
    with np.errstate(invalid="ignore"):
        f_numpy = c.numeric.batch_function(list(c.rhs))(np.zeros(len(Y)), Y, np.zeros((len(Y), 0)), np.zeros((1, 0)))
    f_torch = tf.f(torch.zeros(len(Y), dtype=torch.float64), torch.tensor(Y), torch.zeros(len(Y), 0)).numpy()
    f_casadi = np.array([np.array(F(0.0, y, [], [])).ravel() for y in Y])
    for name, f in [("numpy", f_numpy), ("torch", f_torch), ("casadi", f_casadi)]:
        np.testing.assert_array_equal(f, np.array(expected), err_msg=name)


@pytest.mark.parametrize(
    ("method", "options"),
    [
        ("radau", {"engine": "casadi"}),
        ("radau", {"engine": "casadi", "jit": False}),
        ("radau", {"h": 0.1, "stages": 3}),
        ("casadi-idas", {}),
        ("casadi-collocation", {}),
        ("reference", {}),
    ],
)
def test_a_max_of_a_nan_in_the_equations_fails_as_the_nan_does(method, options):
    # u' = Max(0, sqrt(c - 2)) x at c = 1: the parameters' Max is no switch (it is in no piece's events), and
    # fmax(0, nan) = 0 gave u = 0 with "success" in radau's casadi engine (adaptive and fixed steps) and casadi-idas;
    # now each method raises what it raises for u' = sqrt(c - 2) x
    def model(rate: str) -> dm.Model:
        m = dm.Model("maxnan")
        m.states("x u")
        m.parameter("c", 1.0)
        m.ode("x", "-x")
        m.ode("u", rate)
        m.initial(x=1.0, u=0.0)
        return m

    with pytest.raises(E.SolverError) as plain:
        dm.solve(model("sqrt(c - 2)*x"), (0.0, 1.0), method=method, **options)
    with pytest.raises(type(plain.value)):
        dm.solve(model("Max(0, sqrt(c - 2))*x"), (0.0, 1.0), method=method, **options)


def _arrow(K):
    """K concentrations, each reading a mean of them all (a dense column), and the mean's constraint (a
    dense row): the Jacobian is an arrow."""
    m = dm.Model("arrow")
    c, w = m.states("c", K), m.algebraics("w", K)
    (mean,) = m.algebraics("mean")
    C = dm.stencil(np.array([0, *c, 0], dtype=object))
    m.ode(c, 0.1 * (C[:-2] - 2 * C[1:-1] + C[2:]) * (K + 1) ** 2 - dm.stencil(w) - mean)
    m.constraint(dm.stencil(w) - dm.stencil(c) ** 2 / (1 + dm.stencil(c)), name="rate")
    m.constraint(mean - sp.Add(*c) / K, name="mean")
    m.initial(c=np.sin(np.pi * np.arange(1, K + 1) / (K + 1)))
    return m.compile()


@pytest.mark.parametrize("K", [10, 200])
def test_casadi_jacobian_with_dense_rows_apart_is_casadis(K):
    from daemodel.compiling.codegen import casadi_jacobian

    dae = _arrow(K).casadi_dae()
    expr, variables = casadi.vertcat(dae["ode"], dae["alg"]), casadi.vertcat(dae["x"], dae["z"])
    ours, theirs = casadi_jacobian(expr, variables), casadi.jacobian(expr, variables)
    assert ours.sparsity() == theirs.sparsity()
    point = np.random.default_rng(K).uniform(0.1, 1.0, variables.numel())
    values = [casadi.Function("J", [variables], [J])(point).full() for J in (ours, theirs)]
    np.testing.assert_array_equal(values[0], values[1])


@pytest.mark.parametrize("jit", [False, "auto"])
def test_radau_differentiates_an_arrows_dense_row_apart(monkeypatch, jit):
    """casadi colours an arrow's Jacobian with one colour per unknown (O(D^2): 8.3 s at 4,001 unknowns);
    radau's Jacobian takes its dense row apart, so no differentiation sees the dense row and the dense
    column at once (jit="auto" above 200 unknowns: a stencil's templates, one row each, and the mean's row)."""
    seen, jacobian = [], casadi.jacobian
    monkeypatch.setattr(casadi, "jacobian", lambda e, v, *rest: seen.append(e.numel()) or jacobian(e, v, *rest))
    K = 100
    sol = dm.solve(_arrow(K), (0.0, 0.01), rtol=1e-6, atol=1e-8, jit=jit)
    assert sol.status == "success"
    assert 2 * K + 1 not in seen and 1 in seen
    assert K * 2 in seen if jit is False else (max(seen) < K and sol.stats["stencil"].startswith("machine code"))
    np.testing.assert_allclose(sol["mean"][-1], np.mean(sol["c"][:, -1]), rtol=1e-12)


@pytest.mark.parametrize(
    ("method", "options"),
    [
        ("radau", {"engine": "casadi"}),
        ("radau", {"h": 0.1, "stages": 3}),
        ("casadi-idas", {}),
        ("reference", {}),
    ],
)
def test_a_piecewise_on_a_nan_in_the_equations_fails_as_the_nan_does(method, options):
    # u' = Piecewise((1, sqrt(c - 2) > 0), (0, True)) x at c = 1: the parameters' switch has no breakpoint
    # (sqrt(-1) has no root) and its condition on the nan was False: u = 0 with "success" in every method; now each
    # raises what it raises for u' = sqrt(c - 2) x
    def model(rate: str) -> dm.Model:
        m = dm.Model("piecenan")
        m.states("x u")
        m.parameter("c", 1.0)
        m.ode("x", "-x")
        m.ode("u", rate)
        m.initial(x=1.0, u=0.0)
        return m

    with pytest.raises(E.SolverError) as plain:
        dm.solve(model("sqrt(c - 2)*x"), (0.0, 1.0), method=method, **options)
    with pytest.raises(type(plain.value)):
        dm.solve(model("Piecewise((1, sqrt(c - 2) > 0), (0, True))*x"), (0.0, 1.0), method=method, **options)


@pytest.mark.parametrize("method", ["radau", "casadi-idas", "reference"])
def test_a_switch_on_the_states_that_is_nan_where_its_branch_is_chosen_is_named(method):
    # u' = Piecewise((1, sqrt(x - 2) > 0), (0, True)) from x = 1: numpy's sign of the nan, cast to int, raised a
    # bare ValueError "cannot convert float NaN to integer" (switches._decisions) in every method
    m = dm.Model("piecestate")
    m.states("x u")
    m.ode("x", "-x")
    m.ode("u", "Piecewise((1, sqrt(x - 2) > 0), (0, True))")
    m.initial(x=1.0, u=0.0)
    message = (
        r"Piecewise in u': its switching function sqrt\(x - 2\) is nan at t = 0 \(x = 1, u = 0\), so the branch "
        r"cannot be chosen \(a nan compares to nothing\); write it without a sqrt, log or division"
    )
    with pytest.raises(E.SwitchError, match=message):
        dm.solve(m, (0.0, 1.0), method=method)

"""Runs of repeated equations (daemodel/compiling/runs.py): each run's template, evaluated on its rows'
leaves, gives the model's own f and g bit for bit; rows of another structure, other numbers or leaves
that do not advance by fixed strides are left to the rest, never put in a run."""

import casadi
import numpy as np
import pytest
import sympy as sp

import daemodel as dm
from daemodel.compiling import runs as runs_module
from daemodel.compiling.runs import INPUTS, RUN_MIN, equation_runs
from daemodel.problems.families import reaction_diffusion


def plain_values(compiled, args):
    """The model's own f and g (its casadi_dae, as the residual reads them) at ``args`` = (t, x, z, p)."""
    dae = compiled.casadi_dae()
    plain = casadi.Function("plain", [dae["t"], dae["x"], dae["z"], dae["p"]], [dae["ode"], dae["alg"]])
    return [np.asarray(v).ravel() for v in plain(*args)]


def run_values(found, args):
    """f and g rebuilt from the runs (each template mapped over its rows' leaves) and the rest."""
    n, m, _ = found.sizes
    out = [np.full(n, np.nan), np.full(m, np.nan)]
    for run in found.runs:
        template = found.templates[run.template]
        k = np.arange(run.count)
        leaves = [np.asarray(args[i], dtype=float).ravel()[b + s * k] for i, b, s in zip(run.inputs, run.bases,
                  run.strides, strict=True)]  # fmt: skip
        values = np.asarray(template.map(run.count).call([v[None, :] for v in leaves])[0]).ravel()
        out[run.output][run.out_base + run.out_stride * k] = values
    if found.rest is not None:
        rest = np.asarray(found.rest(*args)).ravel()
        f_rows, g_rows = found.rest_rows
        out[0][f_rows], out[1][g_rows] = rest[: len(f_rows)], rest[len(f_rows) :]
    return out


def random_args(compiled, seed=3):
    rng = np.random.default_rng(seed)
    n, m = len(compiled.states), len(compiled.algebraics)
    return [0.37, rng.uniform(-0.5, 2.0, n), rng.uniform(-0.5, 2.0, m), np.asarray(compiled.parameter_values)]


def test_the_family_is_two_templates_whose_runs_give_f_and_g_bit_for_bit():
    compiled = reaction_diffusion(300).compile()  # 600 unknowns, names c_1 .. c_300
    found = equation_runs(compiled)
    assert found is not None and len(found.templates) == 2
    n, m, _ = found.sizes
    rows = sum(run.count for run in found.runs)
    rest = len(found.rest_rows[0]) + len(found.rest_rows[1])
    assert rows + rest == n + m and rest < 40 and all(run.count >= RUN_MIN for run in found.runs)
    assert found.describe() == f"2 templates, {len(found.runs)} runs of {rows} rows, {rest} rows apart"
    for run in found.runs:  # (each leaf from the grid's states or algebraic variables, or the parameter D)
        assert {INPUTS[i] for i in run.inputs} <= {"x", "z", "p"}
    args = random_args(compiled)
    for got, want in zip(run_values(found, args), plain_values(compiled, args), strict=True):
        np.testing.assert_array_equal(got, want)


def scrambled_grid(K: int, seed: int = 0) -> dm.Model:
    """The family's equations with each cell's neighbours at random places: one template, leaves that do
    not advance by fixed strides (a run would read the wrong neighbours)."""
    rng = np.random.default_rng(seed)
    m = dm.Model(f"scrambled{K}")
    c, w = m.states("c", K), m.algebraics("w", K)
    left, right = rng.permutation(K), rng.permutation(K)
    for k in range(K):
        m.ode(c[k], (c[left[k]] - 2 * c[k] + c[right[k]]) * 7 - w[k])
        m.constraint(w[k] - c[k] ** 2 / (1 + c[k]), name=f"rate{k}")
    m.initial(c=np.linspace(0.1, 0.9, K))
    return m


def test_leaves_at_no_fixed_stride_are_left_to_the_rest_and_the_values_stay():
    compiled = scrambled_grid(300).compile()
    found = equation_runs(compiled)
    assert found is not None  # (g is a stencil: its rows make runs)
    f_rows = sum(run.count for run in found.runs if run.output == 0)
    assert f_rows < 300 // 4  # (f's rows: runs only where the permutations happen to advance by a stride)
    args = random_args(compiled)
    for got, want in zip(run_values(found, args), plain_values(compiled, args), strict=True):
        np.testing.assert_array_equal(got, want)


def test_rows_of_other_numbers_or_a_square_root_are_not_one_template():
    """x**(1/2) is a square root and x**0.5 a power (the key keeps the number's type), and a coefficient
    that changes from row to row is part of the template (a run would give every row the first's)."""
    K = 64
    m = dm.Model("coefficients")
    c, w = m.states("c", K), m.algebraics("w", K)
    for k in range(K):
        root = sp.sqrt(1 + c[k] ** 2) if k % 2 else (1 + c[k] ** 2) ** sp.Float(0.5)
        m.ode(c[k], -sp.Rational(k + 1, 7) * c[k] + w[k])
        m.constraint(w[k] - root, name=f"root{k}")
    m.initial(c=np.linspace(0.1, 0.9, K))
    compiled = m.compile()
    found = equation_runs(compiled)  # (g's rows of each kind sit at stride 2: a template and a run each)
    assert len(found.templates) == 2 and all(run.output == 1 and run.out_stride == 2 for run in found.runs)
    args = random_args(compiled)
    for got, want in zip(run_values(found, args), plain_values(compiled, args), strict=True):
        np.testing.assert_array_equal(got, want)


def test_a_model_of_distinct_equations_has_no_runs():
    """All-pairs equations (no two rows of one structure) are not a repeated stencil: None."""
    K = 40
    m = dm.Model("distinct")
    c = m.states("c", K)
    for k in range(K):
        m.ode(c[k], -sp.Add(*[c[j] ** (j % 3 + 1) for j in range(k + 1)]))
    m.initial(c=np.linspace(0.1, 0.9, K))
    assert equation_runs(m.compile()) is None


def test_too_many_rest_rows_is_not_a_repeated_stencil(monkeypatch):
    compiled = reaction_diffusion(300).compile()
    found = equation_runs(compiled)
    rest = len(found.rest_rows[0]) + len(found.rest_rows[1])
    monkeypatch.setattr(runs_module, "REST_MAX", rest - 1)
    assert equation_runs(compiled) is None
    monkeypatch.setattr(runs_module, "REST_MAX", rest)
    monkeypatch.setattr(runs_module, "RUNS_MAX", 0)
    assert equation_runs(compiled) is None


@pytest.mark.parametrize("declaration", ["loop", "stencils"])
def test_the_declarations_of_the_grid_give_the_same_runs_values(declaration):
    """The family declared by a loop of scalar names and by dm.stencil (benchmarks' scaling_models): runs
    that give its f and g bit for bit."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
    import scaling_models

    compiled = scaling_models.DECLARATIONS[declaration](150).compile()
    found = equation_runs(compiled)
    assert found is not None and sum(run.count for run in found.runs) > 250
    args = random_args(compiled, seed=11)
    for got, want in zip(run_values(found, args), plain_values(compiled, args), strict=True):
        np.testing.assert_array_equal(got, want)


def test_rows_of_a_constant_and_of_time_make_runs_too():
    """Rows without a leaf (v' = 1) and leaves of t (a source sin(t)): an ODE without algebraic variables."""
    compiled = heat_with_source().compile()
    found = equation_runs(compiled)
    assert any(len(found.templates[run.template].sx_in()) == 0 for run in found.runs)
    assert any("t" in {INPUTS[i] for i in run.inputs} for run in found.runs)
    args = random_args(compiled)
    for got, want in zip(run_values(found, args), plain_values(compiled, args), strict=True):
        np.testing.assert_array_equal(got, want)


def jacobian_of_runs(found, layout, args):
    """The Jacobian's nonzeros rebuilt from the runs: each template's derivatives mapped over its rows' leaves
    (the order the stencil's C writes them), the rest's Jacobian after them, then taken at ``layout[2]``."""
    values = []
    for k, derivative in enumerate(found.derivatives):
        for run in (r for r in found.runs if r.template == k):
            steps = np.arange(run.count)
            leaves = [np.asarray(args[i], dtype=float).ravel()[b + s * steps] for i, b, s in zip(run.inputs,
                      run.bases, run.strides, strict=True)]  # fmt: skip
            if len(found.derivative_leaves[k]):
                mapped = derivative.map(run.count).call([v[None, :] for v in leaves])[0]
                values.append(np.asarray(mapped).T.ravel())  # (row by row, each row's partials together)
    if found.rest_jacobian is not None:
        values.append(np.asarray(found.rest_jacobian(*args)).ravel())
    return np.concatenate(values)[layout[2]]


def heat_with_source(K: int = 200) -> dm.Model:
    """Rows without a leaf (v' = 1) and leaves of t (a source sin(t)), no algebraic variable."""
    m = dm.Model("heat")
    u, v = m.states("u", K), m.states("v", 40)
    padded = [0, *u, 0]
    for k in range(K):
        m.ode(u[k], (padded[k] - 2 * padded[k + 1] + padded[k + 2]) * 100 + sp.sin(m.t) / 10)
    for k in range(40):
        m.ode(v[k], 1)
    m.initial(u=np.linspace(0.0, 1.0, K), v=np.zeros(40))
    return m


def product_rows(K: int = 240, W: int = 12) -> dm.Model:
    """Rows of a product of W - 1 neighbours' sines: a template whose partial derivatives casadi takes by one
    reverse sweep, unless told (the whole model's Jacobian is coloured forward: other roundings)."""
    m = dm.Model("products")
    u = m.states("u", K)
    for k in range(K):
        if k + W <= K:
            product = sp.Mul(*[1 + sp.Rational(1, 100) * sp.sin(u[k + j]) for j in range(1, W)])
            m.ode(u[k], -u[k] + product * sp.cos(u[k]) / 100)
        else:
            m.ode(u[k], -u[k])
    m.initial(u=np.linspace(0.1, 0.9, K))
    return m


@pytest.mark.parametrize(
    "model",
    [lambda: reaction_diffusion(300), lambda: scrambled_grid(300), heat_with_source, product_rows],
    ids=["grid", "scrambled", "source", "products"],
)
def test_the_runs_jacobian_is_casadis_pattern_and_values_bit_for_bit(model):
    """:func:`runs.jacobian_layout`: the pattern of the whole model's casadi Jacobian, in its order, and the
    templates' derivatives (with the rest's Jacobian) its values, bit for bit."""
    from daemodel.compiling.codegen import casadi_jacobian

    compiled = model().compile()
    found = equation_runs(compiled)
    layout = runs_module.jacobian_layout(found)
    assert layout is not None and layout[0].dtype == np.int32 and layout[2].dtype == np.int32
    for ours, theirs in zip(layout[:2], compiled.casadi_jacobian_pattern(), strict=True):
        np.testing.assert_array_equal(ours, theirs)
    dae = compiled.casadi_dae()
    whole = casadi_jacobian(casadi.vertcat(dae["ode"], dae["alg"]), casadi.vertcat(dae["x"], dae["z"]))
    plain = casadi.Function("J", [dae["t"], dae["x"], dae["z"], dae["p"]], [whole.nz[:]])
    for seed in (3, 4):
        args = random_args(compiled, seed)
        np.testing.assert_array_equal(jacobian_of_runs(found, layout, args), np.asarray(plain(*args)).ravel())


def test_a_layout_whose_entries_meet_is_none():
    """Two values for one entry (a run given twice) would be summed by nothing: no layout, casadi's Jacobian."""
    found = equation_runs(reaction_diffusion(300).compile())
    assert runs_module.jacobian_layout(found) is not None
    assert runs_module.jacobian_layout(found._replace(runs=[*found.runs, found.runs[0]])) is None


def test_where_casadi_colours_the_whole_model_backward_the_values_agree_to_rounding():
    """A row of 60 unknowns: casadi takes the whole model's Jacobian by reverse sweeps, whose bits neither sweep
    of a template gives (runs.FORWARD); the pattern is still casadi's and the values agree to rounding."""
    from daemodel.compiling.codegen import casadi_jacobian

    m = dm.Model("wide_row")
    u = m.states("u", 300)
    m.ode(u[0], -u[0] + sp.Mul(*[1 + sp.sin(u[j]) / 100 for j in range(1, 60)]) * sp.cos(u[0]) / 100)
    for k in range(1, 300):
        m.ode(u[k], -u[k] + sp.sin(u[k - 1]) * sp.cos(u[k]) * sp.exp(u[k - 1] / 3) * (1 + u[k] ** 2) / 10)
    m.initial(u=np.linspace(0.1, 0.9, 300))
    compiled = m.compile()
    found = equation_runs(compiled)
    assert found.describe() == "1 templates, 1 runs of 299 rows, 1 rows apart"
    layout = runs_module.jacobian_layout(found)
    for ours, theirs in zip(layout[:2], compiled.casadi_jacobian_pattern(), strict=True):
        np.testing.assert_array_equal(ours, theirs)
    dae = compiled.casadi_dae()
    whole = casadi_jacobian(casadi.vertcat(dae["ode"], dae["alg"]), casadi.vertcat(dae["x"], dae["z"]))
    plain = casadi.Function("J", [dae["t"], dae["x"], dae["z"], dae["p"]], [whole.nz[:]])
    args = random_args(compiled)
    want = np.asarray(plain(*args)).ravel()
    np.testing.assert_allclose(jacobian_of_runs(found, layout, args), want, rtol=4e-15, atol=0)

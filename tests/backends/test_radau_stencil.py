"""A repeated stencil's f, g and stage residual in C (backends/radau/stencil.py): the same bits as the
casadi functions they replace, the same solve; models that are not one keep the virtual machine."""

import gc

import numpy as np
import pytest
import sympy as sp
from daemodel.backends.radau import stencil as stencil_module
from daemodel.backends.radau.compiled import Buffered, casadi_functions, find_compiler, lend, stage_f_function
from daemodel.backends.radau.stencil import SlicedBuffered, stencil_equations

import daemodel as dm
from daemodel.compiling.runs import model_runs
from daemodel.errors import CompileError
from daemodel.problems.families import reaction_diffusion
from daemodel.tableau import radau_iia

pytestmark = pytest.mark.skipif(find_compiler() is None, reason="needs a C compiler")


@pytest.mark.parametrize("stages", [3, 5])
def test_the_stencils_residual_is_the_casadi_residual_bit_for_bit(stages):
    compiled = reaction_diffusion(300).compile()  # 600 unknowns
    tableau = radau_iia(stages)
    functions, said = stencil_equations(compiled, tableau)
    assert said.startswith("machine code (2 templates, ") and "rows apart; cache: " in said
    plain = casadi_functions(compiled, tableau)[1]
    rng = np.random.default_rng(stages)
    x = rng.uniform(-0.5, 2.0, plain.nnz_in(0))
    x[1] = 0.013  # (h)
    np.testing.assert_array_equal(Buffered(functions[1])(x), Buffered(plain)(x))
    alone, plain_alone = stage_f_function(compiled, tableau, functions), stage_f_function(compiled, tableau)
    np.testing.assert_array_equal(Buffered(alone)(x), Buffered(plain_alone)(x))
    # (the engine's: the five inputs apart, bound to the caller's arrays)
    np.testing.assert_array_equal(SlicedBuffered(functions.sliced_residual)(x), Buffered(plain)(x))
    np.testing.assert_array_equal(SlicedBuffered(functions.sliced_stage_f)(x), Buffered(plain_alone)(x))
    n, m = len(compiled.states), len(compiled.algebraics)
    args = [0.2, rng.uniform(-0.5, 2.0, n), rng.uniform(-0.5, 2.0, m), np.asarray(compiled.parameter_values)]
    dae = compiled.casadi_dae()
    for got, want in zip(functions[0](*args), (dae["ode"], dae["alg"]), strict=True):
        import casadi

        value = casadi.Function("v", [dae["t"], dae["x"], dae["z"], dae["p"]], [want])(*args)
        np.testing.assert_array_equal(np.asarray(got), np.asarray(value))
    f = np.asarray(functions[0](*args)[0]).ravel()
    np.testing.assert_array_equal(SlicedBuffered(functions.sliced_f).packed(*args), f)
    whole = casadi_functions(compiled, tableau)
    packed = np.concatenate([[args[0]], *args[1:]])
    np.testing.assert_array_equal(SlicedBuffered(functions.sliced_jacobian)(packed), Buffered(whole[2])(packed))


def test_a_sliced_function_binds_the_callers_arrays_and_copies_what_it_cannot_bind():
    """Contiguous float64 parts are read where they are (a part changed between calls is seen, no copy of it is
    kept); strided, float32, list and scalar parts through a copy of their own: the same values each way."""
    compiled, tableau = reaction_diffusion(300).compile(), radau_iia(3)
    functions, _ = stencil_equations(compiled, tableau)
    plain = Buffered(casadi_functions(compiled, tableau)[1])
    n, D = 300, 600
    rng = np.random.default_rng(7)
    y, W, p = rng.uniform(0.1, 1.0, n), rng.uniform(0.1, 1.0, (1, 3, D)), np.asarray(compiled.parameter_values)
    residual = SlicedBuffered(functions.sliced_residual)
    got = residual.packed(0.1, 0.01, y, W, p)
    np.testing.assert_array_equal(got, plain.packed(0.1, 0.01, y, W, p))
    assert sorted(residual._copies) == [0, 1]  # (t and h; y, W and p read in place)
    W[0, 1, 5] += 1.0  # (the caller's array changed: the next call reads it)
    np.testing.assert_array_equal(residual.packed(0.1, 0.01, y, W, p), plain.packed(0.1, 0.01, y, W, p))
    assert not np.array_equal(residual.packed(0.1, 0.01, y, W, p), got)
    strided, single = np.repeat(W.ravel(), 2)[::2], W.astype(np.float32)
    assert not strided.flags.c_contiguous
    for parts in ((0.1, 0.01, list(y), W, p), (0.1, 0.01, y, strided, p), (0.1, 0.01, y, single, p)):
        want = plain.packed(*(np.asarray(part, dtype=float) for part in parts))
        np.testing.assert_array_equal(residual.packed(*parts), want)
    assert sorted(residual._copies) == [0, 1, 2, 3]
    sizes = r"residual takes inputs of sizes \[1, 1, 300, 1800, 1\]; the parts hold \[1, 1, 300, 1799, 1\]"
    with pytest.raises(ValueError, match=sizes):
        residual.packed(0.1, 0.01, y, W.ravel()[1:], p)
    with pytest.raises(ValueError, match=r"takes inputs of sizes .*; the parts hold \[1, 1, 300\]"):
        residual.packed(0.1, 0.01, y)
    with pytest.raises(TypeError, match="residual reads its inputs where each call gives them: call packed"):
        residual.evaluate()
    with pytest.raises(ValueError, match=r"stage_f gives 900 outputs, not \(901,\) \(into a writable contiguous"):
        SlicedBuffered(functions.sliced_stage_f, output=np.zeros(901))
    (read_only := np.zeros(900)).flags.writeable = False
    with pytest.raises(ValueError, match=r"stage_f gives 900 outputs, not \(900,\) \(into a writable contiguous"):
        SlicedBuffered(functions.sliced_stage_f, output=read_only)

    class Owner:
        pass

    lent = lend(owner := Owner(), functions.sliced_jacobian)
    outputs = lent._outputs
    del owner, lent
    gc.collect()
    again = lend(Owner(), functions.sliced_jacobian)  # (taken back, lent again: of its kind, its buffers)
    assert type(again) is SlicedBuffered and again._outputs is outputs
    x = np.r_[0.3, rng.uniform(-0.5, 2.0, D), compiled.parameter_values]
    np.testing.assert_array_equal(again(x), Buffered(casadi_functions(compiled, tableau)[2])(x))


def test_a_solve_on_the_stencil_is_the_virtual_machines_bit_for_bit(monkeypatch):
    """The same steps and values as the residual on casadi's virtual machine (the band LU in C both times:
    jit=False would factor with SuperLU, other bits)."""
    compiled = reaction_diffusion(300).compile()
    options = {"rtol": 1e-6, "atol": 1e-8, "t_eval": np.linspace(0.0, 1.0, 5)}
    fast = dm.solve(compiled, (0.0, 1.0), **options)
    assert fast.stats["stencil"].startswith("machine code (2 templates")
    # (its Jacobian from the templates' derivatives: the model's whole casadi graph was not made)
    assert "casadi_dae" not in compiled._cache and "jacobian-pattern" not in compiled._cache
    # (a start guess: full Newton, on the stage Jacobians of the templates' derivatives)
    guess = lambda t, y, z: np.repeat(np.concatenate([y, z], axis=-1)[:, None, :], 3, axis=1)  # noqa: E731
    fixed = dm.solve(compiled, (0.0, 0.05), h=0.01, stages=3, start_guess=guess)
    assert fixed.stats["stencil"].startswith("machine code (2 templates") and "casadi_dae" not in compiled._cache
    monkeypatch.setattr(stencil_module, "stencil_equations", lambda *args: (None, "off"))
    slow = dm.solve(reaction_diffusion(300).compile(), (0.0, 1.0), **options)
    assert slow.stats["stencil"] == "off" and slow.stats["band_lu"].startswith("machine code (band widths 2 and 2")
    for key in ("steps", "newton_iterations", "rejected_steps", "residual_evaluations"):
        assert fast.stats[key] == slow.stats[key]
    for name in compiled.state_names + compiled.algebraic_names:
        np.testing.assert_array_equal(fast[name], slow[name])
    plain = dm.solve(reaction_diffusion(300).compile(), (0.0, 0.05), h=0.01, stages=3, start_guess=guess)
    assert fixed.stats["jacobian_evaluations"] == plain.stats["jacobian_evaluations"] >= 5
    for name in compiled.state_names + compiled.algebraic_names:
        np.testing.assert_array_equal(fixed[name], plain[name])


def mixed_model(K: int = 150) -> dm.Model:
    """f of distinct structures (each cell's own exponent and coefficient), g a stencil."""
    import sympy as sp

    m = dm.Model(f"mixed{K}")
    c, w = m.states("c", K), m.algebraics("w", K)
    for k in range(K):
        m.ode(c[k], -(c[k] ** (k + 2)) * sp.Rational(1, k + 1) + w[k] - c[(k + 1) % K])
        m.constraint(w[k] - c[k] ** 2 / (1 + c[k]), name=f"rate{k}")
    m.initial(c=np.linspace(0.1, 0.9, K))
    return m


def test_rows_in_no_run_are_computed_apart_bit_for_bit():
    compiled = mixed_model().compile()
    tableau = radau_iia(5)
    functions, said = stencil_equations(compiled, tableau)
    assert said.startswith("machine code (1 templates, 1 runs of 150 rows, 150 rows apart")
    plain = casadi_functions(compiled, tableau)[1]
    x = np.random.default_rng(2).uniform(0.1, 1.5, plain.nnz_in(0))
    np.testing.assert_array_equal(Buffered(functions[1])(x), Buffered(plain)(x))


def boundary_model(K: int = 150) -> dm.Model:
    """Rows apart that read t, a parameter, states and algebraics far apart (the rest's leaves of every input)."""
    m = dm.Model(f"boundary{K}")
    u, w = m.states("u", K), m.algebraics("w", K)
    a = m.parameter("a", 0.7)
    for k in range(K):
        if k in (0, K - 1):
            m.ode(u[k], a * sp.sin(3 * m.t) * u[K - 1 - k] - u[k] + w[k // 2] * w[K - 1])
        else:
            m.ode(u[k], u[k - 1] - 2 * u[k] + u[k + 1] + a * w[k])
        m.constraint(w[k] - u[k] ** 2 / (1 + u[k] ** 2) - (sp.cos(m.t) * a * u[0] if k == K // 3 else 0), name=f"r{k}")
    m.initial(u=np.linspace(0.1, 0.9, K))
    return m


def test_the_rows_apart_read_each_input_where_it_is_bit_for_bit():
    """The rest's leaves gathered in C (rest_gather: t, the parameter, x and z at their places): f, g, the stage
    residual and the Jacobian the casadi functions' of the whole model, bit for bit."""
    compiled, tableau = boundary_model().compile(), radau_iia(3)
    functions, said = stencil_equations(compiled, tableau)
    assert said.startswith("machine code (") and "rows apart" in said
    assert sorted(set(model_runs(compiled).rest_leaves[:, 0].tolist())) == [0, 1, 2, 3]
    plain = casadi_functions(compiled, tableau)
    rng = np.random.default_rng(11)
    for _ in range(3):
        x = rng.uniform(-0.5, 2.0, plain[1].nnz_in(0))
        x[1] = 0.02
        np.testing.assert_array_equal(SlicedBuffered(functions.sliced_residual)(x), Buffered(plain[1])(x))
        point = np.r_[rng.uniform(0.0, 3.0), rng.uniform(-0.5, 2.0, 300), 0.7]
        np.testing.assert_array_equal(SlicedBuffered(functions.sliced_f)(point), Buffered(plain[0])(point))
        np.testing.assert_array_equal(SlicedBuffered(functions.sliced_jacobian)(point), Buffered(plain[2])(point))


@pytest.mark.parametrize("zeros", [False, True])
def test_rows_apart_that_read_no_unknown_have_no_jacobian_to_compile(zeros):
    """Rows apart of a parameter and of t alone (u_0' = a, u_last' = sin t), or zeros (u' = 0): their Jacobian has
    no nonzeros, and casadi dropped the call of its function of none, and of the rows' where they are zeros (a casadi
    RuntimeError from the solve, "No such function 'rest_jacobian_rows'", 'rest_rows'); the stencil's functions the
    model's bit for bit, and the driven rows exact."""
    K = 150
    m = dm.Model(f"driven{K}{zeros}")
    u, w = m.states("u", K), m.algebraics("w", K)
    a = m.parameter("a", 0.7)
    for k in range(K):
        m.ode(u[k], (0 if zeros else a) if k == 0 else (0 if zeros else sp.sin(m.t)) if k == K - 1 else -u[k] + w[k])
        m.constraint(w[k] - u[k] ** 2, name=f"r{k}")
    m.initial(u=np.linspace(0.1, 0.9, K))
    compiled, tableau = m.compile(), radau_iia(3)
    functions, said = stencil_equations(compiled, tableau)
    assert said.startswith("machine code (2 templates, 2 runs of 298 rows, 2 rows apart")
    assert model_runs(compiled).rest_jacobian is None
    plain = casadi_functions(compiled, tableau)
    rng = np.random.default_rng(5)
    x = rng.uniform(-0.5, 2.0, plain[1].nnz_in(0))
    x[1] = 0.02
    np.testing.assert_array_equal(SlicedBuffered(functions.sliced_residual)(x), Buffered(plain[1])(x))
    point = np.r_[0.4, rng.uniform(-0.5, 2.0, 2 * K), compiled.parameter_values]
    np.testing.assert_array_equal(SlicedBuffered(functions.sliced_f)(point), Buffered(plain[0])(point))
    np.testing.assert_array_equal(SlicedBuffered(functions.sliced_jacobian)(point), Buffered(plain[2])(point))
    sol = dm.solve(compiled, (0.0, 1.0), rtol=1e-8, atol=1e-10)
    assert sol.status == "success" and sol.stats["stencil"].startswith("machine code")
    np.testing.assert_allclose(sol["u[0]"], 0.1 + (0 if zeros else 0.7) * sol.t, rtol=0, atol=1e-12)
    np.testing.assert_allclose(sol[f"u[{K - 1}]"], 0.9 if zeros else 1.9 - np.cos(sol.t), rtol=0, atol=1e-9)


def test_a_model_that_is_no_repeated_stencil_keeps_the_virtual_machine(monkeypatch):
    """More rows apart than REST_MAX (the C compiler would take the whole model): casadi's virtual machine."""
    from daemodel.compiling import runs

    monkeypatch.setattr(runs, "REST_MAX", 100)
    compiled = mixed_model().compile()
    functions, said = stencil_equations(compiled, radau_iia(5))
    assert functions is None and said == "casadi's virtual machine (not a repeated stencil)"
    sol = dm.solve(compiled, (0.0, 0.1), rtol=1e-6, atol=1e-8)
    assert sol.stats["stencil"] == "casadi's virtual machine (not a repeated stencil)"
    assert sol.status == "success"


def test_a_compiler_that_fails_leaves_the_stencil_to_the_virtual_machine(monkeypatch):
    def fail(*args):
        raise CompileError("radau's machine code: compiling the stencil's equations with cc failed: boom; fix")

    monkeypatch.setattr(stencil_module, "stencil_function", fail)
    compiled = reaction_diffusion(300).compile()
    sol = dm.solve(compiled, (0.0, 0.1), rtol=1e-6, atol=1e-8)
    assert sol.stats["stencil"].startswith("casadi's virtual machine (the compiler failed: radau's machine code")
    assert sol.status == "success"


def test_no_compiler_leaves_the_stencil_to_the_virtual_machine(monkeypatch):
    monkeypatch.setattr(stencil_module, "find_compiler", lambda: None)
    functions, said = stencil_equations(reaction_diffusion(300).compile(), radau_iia(5))
    assert functions is None and said == "casadi's virtual machine (no C compiler)"


def heavy_boundary_model(K: int = 120, W: int = 70) -> dm.Model:
    """Rows that read their next W - 1 neighbours in a product, and W boundary rows apart whose Jacobian has
    more operations than :data:`stencil.REST_JACOBIAN_C_MAX` (its C took cc over 120 s before that bound)."""
    m = dm.Model("heavy_boundary")
    u = m.states("u", 2 * K)
    for k in range(2 * K):
        if k + W <= 2 * K:
            product = sp.Mul(*[1 + sp.Rational(1, 100) * sp.sin(u[k + j]) for j in range(1, W)])
            m.ode(u[k], -u[k] + product * sp.cos(u[k]) / 100)
        else:
            m.ode(u[k], -u[k])
    m.initial(u=np.linspace(0.1, 0.9, 2 * K))
    return m


def test_a_rest_jacobian_above_the_bound_is_left_to_the_virtual_machine(monkeypatch):
    """Its Jacobian is not put in the library's C (the rest's f and g are: few operations), the runs' are;
    the values are still casadi's whole-model Jacobian's, bit for bit, and the solve the same."""
    from daemodel.compiling.runs import equation_runs

    heavy = equation_runs(heavy_boundary_model().compile())
    assert heavy.rest_jacobian.get_function("rest_jacobian_rows").n_instructions() > stencil_module.REST_JACOBIAN_C_MAX
    assert not stencil_module.rest_jacobian_in_c(heavy) and "rest_jacobian" not in stencil_module.stencil_source(heavy)
    assert heavy.rest.get_function("rest_rows").n_instructions() < stencil_module.REST_JACOBIAN_C_MAX
    monkeypatch.setattr(stencil_module, "REST_JACOBIAN_C_MAX", 0)  # (reaction-diffusion's boundary rows too)
    compiled, tableau = reaction_diffusion(300).compile(), radau_iia(3)
    functions, said = stencil_equations(compiled, tableau)
    assert said.startswith("machine code (2 templates") and "13 rows apart" in said
    plain = casadi_functions(compiled, tableau)
    rng = np.random.default_rng(5)
    for _ in range(2):
        x = np.r_[0.3, rng.uniform(-0.5, 2.0, 600), compiled.parameter_values]
        np.testing.assert_array_equal(np.asarray(functions[2](x)).ravel(), np.asarray(plain[2](x)).ravel())
    options = {"rtol": 1e-6, "atol": 1e-8}
    fast = dm.solve(compiled, (0.0, 1.0), **options)
    assert fast.stats["stencil"] == said
    monkeypatch.setattr(stencil_module, "stencil_equations", lambda *args: (None, "off"))
    slow = dm.solve(reaction_diffusion(300).compile(), (0.0, 1.0), **options)
    assert fast.stats["steps"] == slow.stats["steps"]
    for name in compiled.state_names + compiled.algebraic_names:
        np.testing.assert_array_equal(fast[name], slow[name])

"""radau's two engines run one algorithm: the same results to rounding, the same failures.

The torch engine (batched, dense) and the casadi engine (one trajectory, casadi-compiled
functions, dense or sparse LU) share the step, the controller and the error estimate; their
linear algebra is RADAU5's transformed systems, which must solve the same Newton system as the
full s(n+m) matrix.
"""

import numpy as np
import pytest
import scipy.sparse as sparse
from daemodel.backends import radau
from daemodel.backends.radau import linalg
from daemodel.backends.radau.casadi_engine import CasadiEngine
from daemodel.backends.radau.torch_engine import TorchEngine
from daemodel.backends.radau.transform import StageTransform

import daemodel as dm
from daemodel import errors as E
from daemodel.compiling.initial_states import initial_states
from daemodel.problems import HESSENBERG, PENDULUM
from daemodel.tableau import radau_iia


def _grid(K: int) -> dm.Model:
    """Method of lines for c' = c_xx - w, 0 = w - c^2 / (1 + c) on K interior points (index 1)."""
    m = dm.Model(f"grid{K}")
    c = m.states(" ".join(f"c{k}" for k in range(K)))
    w = m.algebraics(" ".join(f"w{k}" for k in range(K)))
    dx2 = (1.0 / (K + 1)) ** 2
    for k in range(K):
        left = c[k - 1] if k > 0 else 0
        right = c[k + 1] if k < K - 1 else 0
        m.ode(c[k], 0.01 * (left - 2 * c[k] + right) / dx2 - w[k])
        m.constraint(w[k] - c[k] ** 2 / (1 + c[k]), name=f"rate{k}")
    m.initial(**{f"c{k}": float(np.sin(np.pi * (k + 1) / (K + 1))) for k in range(K)})
    return m


@pytest.mark.parametrize("stages", range(1, 8))
def test_the_transformation_block_diagonalises_A_inverse(stages):
    tableau = radau_iia(stages)
    tr = StageTransform.of(tableau.A, radau.embedded_weights(tableau)[0])
    lam = np.zeros((stages, stages))
    for k, eig in tr.blocks:
        if eig.imag == 0:
            lam[k, k] = eig.real
        else:
            lam[k : k + 2, k : k + 2] = [[eig.real, -eig.imag], [eig.imag, eig.real]]
    A_inv = np.linalg.inv(tableau.A)
    np.testing.assert_allclose(tr.T @ lam @ tr.T_inv, A_inv, rtol=0, atol=1e-13 * np.abs(A_inv).max())
    # one real system when s is odd (RADAU5's gamma = 1 / gamma0, the error estimate's matrix too)
    real = [eig for _, eig in tr.blocks if eig.imag == 0]
    assert len(real) == stages % 2 and len(tr.blocks) == (stages + 1) // 2
    shifts = tr.shifts(0.1)
    assert len(shifts) == len(tr.blocks) + (1 - stages % 2)  # even s factors the error matrix apart
    if real:
        assert real[0].real == pytest.approx(1 / tr.gamma0, rel=1e-13)


@pytest.mark.parametrize("engine_name", ["torch", "casadi"])
@pytest.mark.parametrize("problem", [PENDULUM, HESSENBERG], ids=["pendulum", "hessenberg"])
def test_transformed_systems_solve_the_full_newton_system(engine_name, problem):
    """The increment through the real and complex systems equals the full s(n+m) solve with the
    same Jacobian at every stage."""
    compiled = problem.model().compile()
    start = initial_states(compiled)
    tableau = radau_iia(3)
    transform = StageTransform.of(tableau.A, radau.embedded_weights(tableau)[0])
    if engine_name == "torch":
        import torch

        engine = TorchEngine(compiled, start, tableau, transform, torch.float64, torch.device("cpu"))
    else:
        engine = CasadiEngine(compiled, start, tableau, transform)
    y, z = engine.asarray(start.y0), engine.asarray(start.z0)
    J = engine.jacobian(0.0, y, z)
    h = 0.05
    rng = np.random.default_rng(0)
    R = engine.asarray(rng.normal(size=(1, 3, engine.D)))
    transformed = engine.newton_increment(engine.factor(J, h), R)
    stage_J = J[:, None].expand(1, 3, engine.D, engine.D) if engine_name == "torch" else [J] * 3
    full = engine.newton_increment(engine.factor_stages(stage_J, h), R)
    np.testing.assert_allclose(np.asarray(transformed), np.asarray(full), rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("stages", [1, 2, 3, 5, 7])
@pytest.mark.parametrize("problem", [PENDULUM, HESSENBERG], ids=["pendulum", "hessenberg"])
def test_fused_newton_step_equals_residual_and_lu_solves(problem, stages):
    """The casadi engine's one-call Newton step (residual, then the increment through the blocks'
    inverses) gives the residual and the increment of the separate residual and LU solves."""
    compiled = problem.model().compile()
    start = initial_states(compiled)
    tableau = radau_iia(stages)
    engine = CasadiEngine(compiled, start, tableau, StageTransform.of(tableau.A, radau.embedded_weights(tableau)[0]))
    y, z = engine.asarray(start.y0), engine.asarray(start.z0)
    h = 0.05
    factors = engine.factor(engine.jacobian(0.0, y, z), h)
    assert factors.inverse is not None  # a dense system: the fused path is taken
    rng = np.random.default_rng(1)
    W = np.concatenate([y, z], axis=-1)[:, None, :] + 0.01 * rng.normal(size=(1, stages, engine.D))
    r, dW = engine.newton_step(factors, 0.0, h, y, W)
    separate = engine.residual(0.0, h, y, W)
    np.testing.assert_allclose(r.R, separate.R, rtol=1e-14, atol=1e-14)
    np.testing.assert_allclose(r.stage_f, separate.stage_f, rtol=1e-14, atol=1e-14)
    expected = engine.newton_increment(factors, separate.R)
    np.testing.assert_allclose(dW, expected, rtol=1e-9, atol=1e-11 * np.abs(expected).max())


@pytest.mark.parametrize("stages", [1, 2, 3, 5])
@pytest.mark.parametrize("problem", [PENDULUM, HESSENBERG], ids=["pendulum", "hessenberg"])
def test_engines_agree_to_rounding_on_a_fixed_grid(problem, stages):
    compiled = problem.model().compile()
    own = dm.solve(compiled, (0.0, 1.0), stages=stages, h=0.05, engine="torch")
    other = dm.solve(compiled, (0.0, 1.0), stages=stages, h=0.05, engine="casadi")
    assert (own.stats["engine"], other.stats["engine"]) == ("torch", "casadi")
    for name in own.names:
        np.testing.assert_allclose(other[name], own[name], rtol=1e-11, atol=1e-12)
    assert other.stats["steps"] == own.stats["steps"] == 20


@pytest.mark.parametrize("problem", [PENDULUM, HESSENBERG], ids=["pendulum", "hessenberg"])
def test_engines_agree_in_adaptive_mode(problem, monkeypatch):
    """Same steps; values within the tolerance (Newton stops at a tolerance, not at rounding).  The
    casadi engine's compiled step keeps Jacobians longer (its iterations are cheap): here it keeps
    them as long as the torch engine does."""
    from daemodel.backends.radau import control, step

    monkeypatch.setattr(step, "REUSE_THETA_COMPILED", step.REUSE_THETA)
    monkeypatch.setattr(control, "KEEP_H_BAND_COMPILED", control.KEEP_H_BAND)
    compiled = problem.model().compile()
    own = dm.solve(compiled, (0.0, 1.0), rtol=1e-8, atol=1e-10, engine="torch")
    other = dm.solve(compiled, (0.0, 1.0), rtol=1e-8, atol=1e-10, engine="casadi")
    assert abs(other.stats["steps"] - own.stats["steps"]) <= 1
    reference = dm.solve(compiled, (0.0, 1.0), method="reference")
    for sol in (own, other):
        for name in compiled.state_names:
            assert abs(sol[name][-1] - reference[name][-1]) < 1e-7


def test_sparse_lu_path_matches_the_dense_torch_engine():
    """A 120-unknown grid: the casadi engine factors sparsely (SuperLU, complex too)."""
    compiled = _grid(60).compile()
    sparse_run = dm.solve(compiled, (0.0, 0.1), stages=3, h=0.01, engine="casadi")
    dense_run = dm.solve(compiled, (0.0, 0.1), stages=3, h=0.01, engine="torch")
    for name in ("c0", "c30", "w30"):
        np.testing.assert_allclose(sparse_run[name], dense_run[name], rtol=1e-12, atol=1e-13)
    tableau = radau_iia(3)
    engine = CasadiEngine(
        compiled, initial_states(compiled), tableau, StageTransform.of(tableau.A, radau.embedded_weights(tableau)[0])
    )
    assert not engine.dense and len(engine.rows) < 0.05 * engine.D**2


def test_auto_picks_casadi_for_one_trajectory_and_torch_for_batches():
    compiled = PENDULUM.model().compile()
    assert dm.solve(compiled, (0.0, 0.1), h=0.05).stats["engine"] == "casadi"
    assert dm.solve(compiled, (0.0, 0.1), h=0.05, dtype="float32").stats["engine"] == "torch"
    batch = dm.solve(compiled, (0.0, 0.1), h=0.05, y0={"y1": [1.0, 0.9]})
    assert batch.stats["engine"] == "torch"
    single = dm.solve(compiled, (0.0, 0.1), h=0.05, y0={"y1": [0.9]})
    np.testing.assert_allclose(single["y2"][0], batch["y2"][1], rtol=1e-12, atol=1e-13)


def test_engine_option_errors():
    compiled = PENDULUM.model().compile()
    with pytest.raises(E.InvalidOptionError, match=r"engine must be one of 'auto', 'torch', 'casadi'; got 'numpy'"):
        dm.solve(compiled, (0.0, 0.1), h=0.05, engine="numpy")
    with pytest.raises(
        E.InvalidOptionError, match=r"engine='casadi' computes in float64 on the CPU; dtype='float32', device='cpu'"
    ):
        dm.solve(compiled, (0.0, 0.1), h=0.05, engine="casadi", dtype="float32")
    with pytest.raises(E.InvalidOptionError, match=r"engine='casadi' solves one trajectory; this batch has 2 samples"):
        dm.solve(compiled, (0.0, 0.1), h=0.05, engine="casadi", y0={"y1": [1.0, 0.9]})


def test_sign_of_a_sparse_determinant():
    rng = np.random.default_rng(1)
    for size in (1, 2, 5, 30):
        for _ in range(5):
            matrix = rng.normal(size=(size, size)) * (rng.random((size, size)) < 0.3) + np.diag(rng.normal(size=size))
            expected = np.sign(np.linalg.det(matrix))
            assert linalg.sparse_sign_det(sparse.csc_matrix(matrix)) == expected
    assert linalg.sparse_sign_det(sparse.csc_matrix(np.zeros((3, 3)))) == 0.0
    assert linalg.permutation_sign(np.array([1, 0, 2])) == -1.0
    assert linalg.permutation_sign(np.array([1, 2, 0])) == 1.0


def test_the_sign_of_a_z_block_from_the_jacobian_s_entries():
    """block_sign_det on g_z's entries picked from J's (z_block): the sign of det g_z, as sparse_sign_det of the
    sliced sparse J gives it, for triangular, general, singular and not finite blocks, entries in any order."""
    rng = np.random.default_rng(4)
    n, m = 7, 30
    for case in range(24):
        J = rng.normal(size=(n + m, n + m)) * (rng.random((n + m, n + m)) < 0.2)
        block = J[n:, n:]
        block[np.diag_indices(m)] = rng.normal(size=m)
        if case % 4 == 1:
            block[np.tril_indices(m, -1)] = 0.0  # (upper triangular: its diagonal's sign, no LU)
        if case % 4 == 2:
            block[:, 3] = 0.0  # (a zero column: singular)
        if case % 4 == 3:
            block[case % m, (case * 7) % m] = [np.inf, np.nan, -np.inf][case % 3]
        rows, cols = np.nonzero(J)
        order = rng.permutation(len(rows))
        rows, cols, values = rows[order], cols[order], J[rows[order], cols[order]]
        at, z_rows, z_cols = linalg.z_block(rows, cols, n)
        want = linalg.sparse_sign_det(sparse.csr_matrix((values, (rows, cols)), shape=J.shape)[n:, n:].tocsc())
        got = linalg.block_sign_det(values[at], z_rows, z_cols, m)
        assert got == want
        assert got == (0.0 if case % 4 >= 2 else np.sign(np.linalg.det(block)))
    assert linalg.block_sign_det(np.zeros(0), np.zeros(0, int), np.zeros(0, int), 0) == 1.0


@pytest.mark.parametrize("both_sides", [False, True])
def test_a_large_z_block_passing_through_singular_is_refused(both_sides):
    """120 algebraic variables (above DENSE_MAX_SIZE: the z block's sign from J's entries, block_sign_det), g_z
    triangular or not (SuperLU), its determinant through zero at t = 0.7 where z stays smooth (one row
    ``(0.7 - t) (z - q)``): radau refuses the step across it, and solves up to it."""
    import sympy

    K = 120
    model = dm.Model(f"fold{K}")
    q, z = model.states("q", K), model.algebraics("z", K)
    for k in range(K):
        model.ode(q[k], -q[k] + z[k] / 10)
        coupling = z[k - 1] / 10 if k else 0
        coupling += z[(k + 1) % K] / 10 if both_sides and k else 0
        if k == K // 2:
            model.constraint((sympy.Rational(7, 10) - model.t) * (z[k] - q[k]), name=f"c{k}")
        else:
            model.constraint(z[k] + coupling - q[k], name=f"c{k}")
    model.initial(q=np.linspace(0.5, 1.0, K))
    compiled = model.compile()
    options = {"rtol": 1e-6, "atol": 1e-8, "engine": "casadi", "reuse_jacobian": False}  # (a sign each step)
    with pytest.raises(E.ConvergenceError, match=r"stop determining the algebraic variables between t = 0\.[3-7]"):
        dm.solve(compiled, (0.0, 2.0), **options)
    sol = dm.solve(compiled, (0.0, 0.6), **options)
    assert sol.status == "success"
    if both_sides:  # (the constraints named: the first ten and how many more, not 119; c0 went with z[0])
        with pytest.raises(E.ConvergenceError, match=r"the constraints \('c1', 'c2', .*'c10' and 109 more\) stop"):
            dm.solve(compiled, (0.0, 2.0), **options)
    else:  # (the step across t = 0.7 seen by the branch check after the solve: z that moves most, and how many more)
        listed = r"\((z\[\d+\] = \S+, ){7}z\[\d+\] = \S+, and 111 more\)"  # (z[0] = q[0] is substituted)
        with pytest.raises(E.BranchError, match=rf"between t = \S+ {listed} and t = 1 {listed}") as caught:
            dm.solve(compiled, (0.0, 1.0), rtol=1e-6, atol=1e-8, engine="casadi")
        assert "z[119] = 0.617757" in str(caught.value) and len(str(caught.value)) < 1000


@pytest.mark.parametrize("bad", [np.inf, -np.inf, np.nan])
@pytest.mark.parametrize("where", [(1, 1), (0, 1)])  # (on the diagonal, and off it: SuperLU's path)
def test_a_sparse_determinant_with_an_entry_not_finite_has_sign_zero(bad, where):
    """An inf or NaN entry gives the sign 0, as dense_sign_det and determinants.sparse_sign give it (the
    branch check's 'undetermined'); before, an inf on U's diagonal came back as +1 or -1."""
    matrix = np.array([[1.0, 2.0], [3.0, 4.0]])
    matrix[where] = bad
    assert linalg.dense_sign_det(matrix) == 0.0
    assert linalg.sparse_sign_det(sparse.csc_matrix(matrix)) == 0.0
    assert linalg.sparse_sign_det(sparse.csc_matrix(np.triu(matrix))) == 0.0


def test_coloured_forward_ad_jacobian_equals_the_symbolic_one(monkeypatch):
    """Past SYMBOLIC_JACOBIAN_MAX_ENTRIES the torch engine differentiates by forward-mode AD with one
    direction per colour; a grid needs a handful of colours instead of its 2K columns."""
    import torch

    from daemodel.compiling import compiled as compiled_module

    tableau = radau_iia(3)
    transform = StageTransform.of(tableau.A, radau.embedded_weights(tableau)[0])
    for make in (PENDULUM.model, lambda: _grid(12)):
        symbolic = make().compile()
        monkeypatch.setattr(compiled_module, "SYMBOLIC_JACOBIAN_MAX_ENTRIES", 0)
        coloured = make().compile()  # a model of its own: a Model keeps its last compile
        assert coloured.torch_functions().jacobian is None  # generated (and cached) under the limit
        monkeypatch.undo()
        assert symbolic.torch_functions().jacobian is not None
        start = initial_states(symbolic)
        engines = [
            TorchEngine(c, start, tableau, transform, torch.float64, torch.device("cpu")) for c in (symbolic, coloured)
        ]
        y, z = engines[0].asarray(start.y0) * 1.1, engines[0].asarray(start.z0) + 0.3
        np.testing.assert_allclose(
            engines[1].jacobian(0.2, y, z), engines[0].jacobian(0.2, y, z), rtol=1e-13, atol=1e-13
        )
        colour = coloured.column_colouring()
        rows, cols = coloured.jacobian_pattern()
        assert len(set(zip(rows.tolist(), colour[cols].tolist(), strict=True))) == len(
            rows
        )  # no row meets a colour twice
    assert colour.max() + 1 <= 4  # the grid: c_k couples to c_(k-1), c_(k+1), w_k


# A fresh process: torch's first use is charged to the setup clock of the solve that pays it.
FIRST_TORCH_USE = """
import json, sys
import daemodel as dm
from daemodel.problems import PENDULUM

imported = "torch" in sys.modules
c = PENDULUM.model().compile()
radau = {"method": "radau", "h": 0.1, "engine": "torch"}
pinn = {"method": "pinn", "config": dm.PINNConfig(h=0.05, width=4, depth=1, iterations=5)}
first, second = (radau, pinn) if sys.argv[1] == "radau" else (pinn, radau)
clocks = []
for options in (first, second, first):
    sol = dm.solve(c, (0.0, 0.1), **options)
    clocks.append([sol.setup_time, sol.stats["torch_warm_up_seconds"]])
print(json.dumps({"imported_before": imported, "clocks": clocks}))
"""


@pytest.mark.parametrize("first", ["radau", "pinn"])
def test_the_first_torch_use_in_a_process_is_counted_in_the_setup(first):
    """torch's import and first operations (1-4 s) were on no clock: the first torch solve of a
    process reported a setup of 0.1 s.  Now the warm-up runs inside the timed setup, once."""
    import json
    import subprocess
    import sys

    command = [sys.executable, "-W", "ignore", "-c", FIRST_TORCH_USE, first]
    run = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    result = json.loads(run.stdout.strip().splitlines()[-1])
    assert result["imported_before"] is False  # importing daemodel does not import torch: the solve pays
    (setup, warm_up), *later = result["clocks"]
    assert warm_up > 0 and setup >= warm_up  # the warm-up ran, inside the setup clock
    assert [seconds for _, seconds in later] == [0.0, 0.0]  # once per process (and device, dtype)


def test_the_stage_transform_is_made_once_per_tableau(monkeypatch):
    """Every solve's engine reads the tableau's transform and error weights: made once per tableau (they were
    made again by every solve, ~0.4 ms of eigen-decompositions each, 2,700 times in the wheelset's events'
    trial solves); the same numbers as made anew, and the weights a copy the caller may change."""
    from daemodel.backends.radau import transform

    made = []
    original = transform.StageTransform.of
    monkeypatch.setattr(transform.StageTransform, "of", lambda A, gamma0: made.append(1) or original(A, gamma0))
    tableau = radau_iia(4)
    first = transform.stage_transform(tableau)
    assert transform.stage_transform(tableau) is first
    assert len(made) <= 1  # (none where an earlier test made it)
    fresh = original(tableau.A, transform.embedded_weights(tableau)[0])
    np.testing.assert_array_equal(first.T, fresh.T)
    assert first.blocks == fresh.blocks
    gamma0, e = transform.embedded_weights(tableau)
    e[:] = 0.0
    assert transform.embedded_weights(tableau)[1].any()
    assert transform.embedded_weights(tableau)[0] == gamma0


def _traced_peak(call):
    """``(call(), the most bytes numpy and Python held at once during it beyond what they held before)``."""
    import tracemalloc

    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        tracemalloc.reset_peak()
        out = call()
        return out, tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()


@pytest.mark.parametrize("stages", [2, 3, 5])
def test_the_casadi_engines_increment_has_the_general_paths_bits_without_its_temporaries(stages):
    """On sparse systems (SuperLU: 600 unknowns) the casadi engine's Newton increment runs the general
    path's operations one by one in buffers made once (.transform.IncrementBuffers): the same bits, and
    while it runs no more memory than the increment it returns and two complex solves (the general path
    held its transformed right-hand side, its parts, their stack: ~3 increments)."""
    compiled = _grid(300).compile()
    start = initial_states(compiled)
    tableau = radau_iia(stages)
    engine = CasadiEngine(compiled, start, tableau, StageTransform.of(tableau.A, radau.embedded_weights(tableau)[0]))
    assert not engine.dense
    y, z = engine.asarray(start.y0), engine.asarray(start.z0)
    factors = engine.factor(engine.jacobian(0.0, y, z), 0.05)
    R = np.random.default_rng(2).normal(size=(1, stages, engine.D))
    engine.newton_increment(factors, R)  # (the transform's arrays made)
    dW, peak = _traced_peak(lambda: engine.newton_increment(factors, R))
    assert peak <= dW.nbytes + 2 * 16 * engine.D + 4096
    engine.increment = None  # the general path
    general = engine.newton_increment(factors, R)
    assert dW.tobytes() == general.tobytes()


def test_the_casadi_engine_writes_its_inputs_into_the_bound_buffer():
    """The residual's packed input ``[t, h, y, W, p]`` is written part by part into the function's
    buffer (at 10^5 unknowns a 4.4 MB array a call): the same outputs, and no input-sized array made;
    parts of the wrong size are refused."""
    compiled = _grid(300).compile()
    start = initial_states(compiled)
    tableau = radau_iia(3)
    engine = CasadiEngine(compiled, start, tableau, StageTransform.of(tableau.A, radau.embedded_weights(tableau)[0]))
    y, z = engine.asarray(start.y0), engine.asarray(start.z0)
    W = np.concatenate([y, z], axis=-1)[:, None, :] + 0.01 * np.random.default_rng(3).normal(size=(1, 3, engine.D))
    r, peak = _traced_peak(lambda: engine.residual(0.1, 0.05, y, W))
    outputs = engine._residual._outputs.nbytes
    assert peak <= outputs + 4096  # (its copy of the outputs alone)
    inputs = np.concatenate([[0.1, 0.05], y[0], W.ravel(), engine.p])
    assert r.R.tobytes() == engine._residual(inputs)[: r.R.size].tobytes()
    with pytest.raises(ValueError, match=r"casadi function residual takes \d+ inputs; the parts hold \d+"):
        engine._residual.packed(0.1, 0.05, y[0])  # (W left out)


@pytest.mark.parametrize("stages", [1, 2, 3, 5])
def test_newtons_step_writes_the_increment_over_the_residual_with_the_same_bits(stages):
    """On sparse systems (600 unknowns) newton_step's increment is written over the residual's buffer (its R,
    read first), not into a buffer of its own: the bits of newton_increment from a copy of R, no memory beyond
    a complex solve's (SuperLU's) while it runs, and the residual's f at the stages untouched; a residual that
    cannot take it (not C-contiguous) is refused by name.  The stages' f (the error estimate's) reads the
    residual's input and writes f at the stages into its output: the values of the residual's own."""
    compiled = _grid(300).compile()
    start = initial_states(compiled)
    tableau = radau_iia(stages)
    engine = CasadiEngine(compiled, start, tableau, StageTransform.of(tableau.A, radau.embedded_weights(tableau)[0]))
    assert not engine.dense and engine._stage_f is not None
    y, z = engine.asarray(start.y0), engine.asarray(start.z0)
    factors = engine.factor(engine.jacobian(0.0, y, z), 0.05)
    W = np.concatenate([y, z], axis=-1)[:, None, :] + 0.01 * np.random.default_rng(4).normal(size=(1, stages, engine.D))
    r = engine.residual(0.1, 0.05, y, W)
    R, f = r.R.copy(), r.stage_f.copy()
    want = engine.newton_increment(factors, R.copy())  # (into the increment's own buffer)
    engine.newton_step(factors, 0.1, 0.05, y, W)  # (the transform's arrays made)
    (r, dW), peak = _traced_peak(lambda: engine.newton_step(factors, 0.1, 0.05, y, W))
    assert dW.base is r.R.base and np.shares_memory(dW, engine._residual._outputs)
    assert dW.tobytes() == want.tobytes() and r.stage_f.tobytes() == f.tobytes()
    assert peak <= 3 * 16 * engine.D + 4096  # (SuperLU's complex solve: its right-hand side in its order, two more)
    alone = engine.stage_values(0.1, 0.05, y, W)
    assert np.shares_memory(alone.stage_f, engine._residual._outputs) and alone.stage_f.tobytes() == f.tobytes()
    with pytest.raises(ValueError, match=r"the increment is written over a writable C-contiguous residual"):
        engine.newton_increment(factors, np.asfortranarray(R[0])[None] if stages > 1 else R[:, :, ::-1], over=True)


def test_a_buffered_function_refuses_an_input_or_output_of_another_size():
    """Buffered(function, input_of=, output=) shares another's first input and writes into a given array of its
    output's size; another size, or an output not float64, is refused naming the function."""
    import casadi
    from daemodel.backends.radau.compiled import Buffered

    x = casadi.MX.sym("x", 4)
    twice, head = casadi.Function("twice", [x], [2 * x]), casadi.Function("head", [x], [x[:2] + 1])
    first = Buffered(twice)
    out = np.zeros(6)
    second = Buffered(head, input_of=first, output=out[4:])
    first(np.arange(4.0))
    np.testing.assert_array_equal(second.evaluate(copy=False), [1.0, 2.0])
    assert second._inputs is first._inputs and np.shares_memory(second._outputs, out)
    y = casadi.MX.sym("y", 3)
    small = Buffered(casadi.Function("small", [y], [y[0]]))
    with pytest.raises(ValueError, match=r"casadi function head takes 4 inputs; small 3"):
        Buffered(head, input_of=small)
    with pytest.raises(ValueError, match=r"casadi function head gives 2 outputs, not \(3,\)"):
        Buffered(head, output=np.zeros(3))
    with pytest.raises(ValueError, match=r"casadi function head gives 2 outputs, not \(2,\) \(into a writable"):
        Buffered(head, output=np.zeros(2, dtype=np.float32))
    with pytest.raises(ValueError, match=r"casadi function head gives 2 outputs, not \(2,\) \(into a writable"):
        Buffered(head, output=np.zeros(4)[::2])  # (strided: casadi's own error was a bare NotImplementedError)
    frozen = np.zeros(2)
    frozen.flags.writeable = False
    with pytest.raises(ValueError, match=r"casadi function head gives 2 outputs, not \(2,\) \(into a writable"):
        Buffered(head, output=frozen)


@pytest.mark.parametrize("options", [{}, {"h": 0.1, "stages": 3}])
def test_a_nan_jacobian_in_the_torch_engine_is_the_casadi_engine_s_named_error(options):
    # u' = sqrt(-x) from x = 1: torch's LU of a matrix holding the nan passed with info = 0, and the solve went on to
    # torch's bare RuntimeError "expected scalar type Double but found ComplexDouble"; the casadi engine's error
    # names the Jacobian that is not finite, at t = 0, and (both engines) its entry: d(u')/d(x)
    m = dm.Model("sqrtneg")
    m.states("x u")
    m.ode("x", "-x")
    m.ode("u", "sqrt(-x)")
    m.initial(x=1.0, u=0.0)
    messages, message = [], r"at t = 0 with h = .*: the Jacobian of f and g is not finite there \(d\(u'\)/d\(x\) = nan"
    for engine in ("casadi", "torch"):
        with pytest.raises(E.ConvergenceError, match=message) as e:
            dm.solve(m, (0.0, 1.0), method="radau", engine=engine, **options)
        messages.append(str(e.value))
    assert messages[0] == messages[1]


def test_forward_ad_jacobians_in_two_threads_at_once_take_turns(monkeypatch):
    """torch's forward-mode AD level is the process's: a thread's Jacobian by forward AD (past
    SYMBOLIC_JACOBIAN_MAX_ENTRIES) while another's is inside its dual level raised torch's RuntimeError ("Nested
    forward mode AD is not supported"; two radau solves of a 600-unknown model in two threads); they take turns,
    each with the bits of a Jacobian alone."""
    import threading
    import types

    import torch

    from daemodel.compiling import compiled as compiled_module

    monkeypatch.setattr(compiled_module, "SYMBOLIC_JACOBIAN_MAX_ENTRIES", 0)
    compiled = _grid(12).compile()
    assert compiled.torch_functions().jacobian is None
    tableau = radau_iia(3)
    start = initial_states(compiled)
    transform = StageTransform.of(tableau.A, radau.embedded_weights(tableau)[0])
    engines = [TorchEngine(compiled, start, tableau, transform, torch.float64, torch.device("cpu")) for _ in range(2)]
    y, z = engines[0].asarray(start.y0) * 1.1, engines[0].asarray(start.z0) + 0.3
    want = engines[0].jacobian(0.2, y, z)
    inside, other_done, found = threading.Event(), threading.Event(), {}
    functions = engines[0].tf

    def held_f(*args):  # (the first thread's f waits, inside its dual level, for the second's Jacobian)
        inside.set()
        other_done.wait(timeout=1.0)
        return functions.f(*args)

    engines[0].tf = types.SimpleNamespace(**{k: getattr(functions, k) for k in ("g", "jacobian")}, f=held_f)

    def jacobian(k):
        if k == 1:
            inside.wait(timeout=10.0)
        try:
            found[k] = engines[k].jacobian(0.2, y, z)
        except RuntimeError as error:
            found[k] = error
        if k == 1:
            other_done.set()

    threads = [threading.Thread(target=jacobian, args=(k,)) for k in range(2)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    for k in range(2):
        assert isinstance(found[k], torch.Tensor), found[k]
        assert torch.equal(found[k], want)


def test_the_casadi_engines_solve_into_out_gives_what_it_returns_for_every_kind_of_factors():
    """CasadiEngine.solve(lu, rhs, out=) writes what solve(lu, rhs) returns into out (and returns it) for every kind
    of factors (the grid's: SuperLU in the band order), a singular system's NaN too (``("singular",)``: reading its
    second entry, for the band kernel's and the ordered factors, raised IndexError), also where out is rhs."""
    compiled = _grid(60).compile()
    start = initial_states(compiled)
    tableau = radau_iia(3)
    engine = CasadiEngine(compiled, start, tableau, StageTransform.of(tableau.A, radau.embedded_weights(tableau)[0]))
    y, z = engine.asarray(start.y0), engine.asarray(start.z0)
    factors = engine.factor(engine.jacobian(0.0, y, z), 0.05)
    rhs = np.random.default_rng(5).standard_normal((1, engine.D))
    for sigma, lu in ((0.0, ("singular",)), *factors.lu.items()):
        b = rhs.astype(complex) if sigma.imag else rhs
        want = engine.solve(lu, b.copy())
        out = np.full_like(want, 7.0)
        np.testing.assert_array_equal(engine.solve(lu, b.copy(), out=out), want)
        np.testing.assert_array_equal(out, want)
        same = b.copy()
        if same.dtype == want.dtype:
            np.testing.assert_array_equal(engine.solve(lu, same, out=same), want)
            np.testing.assert_array_equal(same, want)
    assert np.isnan(engine.solve(("singular",), rhs)).all()

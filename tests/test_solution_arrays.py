"""A solution of a model declared by arrays: sol["u"] (shape (*shape, T)), sol["u[3]"], sol[T[:, 0]],
batches, pruned elements, the errors that name the culprit, files and plots."""

import numpy as np
import pytest

import daemodel as dm
from daemodel import errors as E

# radau's default on casadi's virtual machine, but in the tests marked machine_code (tests/conftest.py)
pytestmark = pytest.mark.virtual_machine

RATES = np.array([[1.0, 2.0, 3.0], [0.5, 1.5, 2.5]])


def decays() -> tuple[dm.Model, np.ndarray, np.ndarray]:
    """T[i,j]' = -k[i,j] T[i,j] (exact: exp(-k t)), and an algebraic array w = 2 T + w^3 / 100
    (a real algebraic variable, not an alias), shape (2, 3)."""
    m = dm.Model("decays")
    T = m.states("T", (2, 3))
    w = m.algebraics("w", (2, 3))
    k = m.parameters("k", (2, 3), value=RATES)
    m.ode(T, -k * T)
    m.constraint(w - 2 * T - w**3 / 100, name="law")
    m.initial(T=1.0)
    m.guess(w=2.0)
    return m, T, w


def test_an_array_reads_as_one_array_and_elements_as_its_entries():
    m, T, _ = decays()
    sol = dm.solve(m, (0.0, 1.0), rtol=1e-10, atol=1e-12, t_eval=np.linspace(0.0, 1.0, 5))
    values = sol["T"]
    assert values.shape == (2, 3, 5) and not values.flags.writeable
    exact = np.exp(-RATES[..., None] * sol.t)
    assert np.max(np.abs(values - exact)) < 1e-8
    assert np.array_equal(sol["T[1,2]"], values[1, 2]) and np.array_equal(sol["T[1, 2]"], values[1, 2])
    assert np.array_equal(sol[T[1, 2]], values[1, 2])  # the symbol
    assert np.array_equal(sol[T[:, 0]], values[:, 0]) and sol[T[:, 0]].shape == (2, 5)  # an array of symbols
    W = sol["w"]
    # (between steps, the dense output holds the constraint to its interpolation error, ~rtol: 1.7e-10 with s = 7)
    assert W.shape == (2, 3, 5) and np.max(np.abs(W - 2 * values - W**3 / 100)) < 1e-9
    assert sol.names[:2] == ("T[0,0]", "T[0,1]")


def test_a_batch_puts_the_samples_first():
    m, _, _ = decays()
    sol = dm.solve(m, (0.0, 1.0), rtol=1e-10, atol=1e-12, parameters={"k[0,0]": np.array([1.0, 4.0])})
    assert sol["T"].shape == (2, 2, 3, len(sol.t)) and sol["T[0,0]"].shape == (2, len(sol.t))
    assert np.max(np.abs(sol["T"][:, 0, 0, -1] - np.exp(-np.array([1.0, 4.0]) * sol.t[-1]))) < 1e-8
    assert np.array_equal(sol["T"][1, 1], sol["T"][0, 1])  # the other rates are the model's


@pytest.mark.parametrize(
    ("name", "pattern"),
    [
        ("T[2,0]", r"sol\['T\[2,0\]'\]: index 2 is out of range for axis 0 of 'T', shape \(2, 3\) \(0 to 1\)"),
        ("T[1, 3]", r"index 3 is out of range for axis 1 of 'T'"),
        ("T[1]", r"T\[1\] gives 1 index\(es\) for the 2-d array 'T' of shape \(2, 3\)"),
        ("k", r"the solution has no variable 'k'; it has \['T\[...\]' \(6 elements\), 'w\[...\]' \(6 elements\)\]"),
        ("U[0]", r"the solution has no variable 'U\[0\]'"),
    ],
)
def test_a_wrong_array_name_or_index_is_named(name, pattern):
    sol = dm.solve(decays()[0], (0.0, 0.1), h=0.05)
    with pytest.raises(E.UnknownSymbolError, match=pattern):
        sol[name]


def test_pruned_elements_are_named_with_the_fix():
    m, T, _ = decays()
    sol = dm.solve(m.compile(outputs=["T[0,1]"]), (0.0, 0.1), h=0.05)
    assert sol.names == ("T[0,1]",) and sol["T[0,1]"].shape == (len(sol.t),)
    with pytest.raises(
        E.UnknownSymbolError,
        match=r"no values of 'T\[0,0\]', 'T\[0,2\]', 'T\[1,0\]', 'T\[1,1\]', 'T\[1,2\]': pruned by compile\(outputs",
    ):
        sol["T"]
    with pytest.raises(E.UnknownSymbolError, match=r"no values of 'T\[1,1\]': pruned by compile\(outputs=...\)"):
        sol["T[1,1]"]
    with pytest.raises(E.UnknownSymbolError, match=r"no values of 'x': not variables of it"):
        sol[np.array(["T[0,1]", "x"], dtype=object)]
    assert dm.solve(m.compile(outputs=["T"]), (0.0, 0.1), h=0.05).names == tuple(s.name for s in T.flat)


def test_a_saved_solution_reads_back_its_arrays(tmp_path):
    m, _, _ = decays()
    sol = dm.solve(m, (0.0, 1.0), rtol=1e-8, atol=1e-10)
    loaded = dm.Solution.load(sol.save(tmp_path / "decays.npz"), m)
    assert np.array_equal(loaded["T"], sol["T"]) and np.array_equal(loaded["w"], sol["w"])
    assert np.array_equal(loaded["w[1,2]"], sol["w[1,2]"]) and loaded.names == sol.names


def test_saving_and_loading_print_each_equation_once(tmp_path, monkeypatch):
    # the fingerprint printed every equation (sympy's str) at each call, twice a save and again a load:
    # a 10^4-unknown solution took 19 s of CPU to save (cProfile, loaded machine), ~0.3 ms an equation
    from sympy.printing.str import StrPrinter

    m, _, _ = decays()
    sol = dm.solve(m, (0.0, 1.0), rtol=1e-8, atol=1e-10)
    printed, depth, doprint = [0], [0], StrPrinter.doprint

    def counted(self, expr):
        printed[0] += depth[0] == 0  # (an expression, not the parts sympy prints inside it)
        depth[0] += 1
        try:
            return doprint(self, expr)
        finally:
            depth[0] -= 1

    monkeypatch.setattr(StrPrinter, "doprint", counted)
    path = sol.save(tmp_path / "decays.npz")
    for _ in range(2):
        loaded = dm.Solution.load(path, m)
    assert printed[0] <= 12  # (6 right-hand sides and 6 constraints, once)
    assert np.array_equal(loaded["T"], sol["T"])
    m.set_parameters(k=2 * RATES)  # (other values: another model, which the file does not match)
    with pytest.raises(E.SolutionFileError, match="parameter values"):
        dm.Solution.load(path, m)


def test_report_and_plot_name_the_elements(tmp_path):
    m, _, _ = decays()
    sol = dm.solve(m, (0.0, 0.2), h=0.05)
    report = m.compile().report()
    assert "T[1,2]' = -T[1,2]*k[1,2]" in report and "law[0,0]" in report
    figure = sol.plot(tmp_path / "T.png", names=["T", "w[1, 2]"])
    titles = [ax.get_title() for ax in figure.axes if ax.get_title()]
    assert titles[:2] == ["T[0,0]", "T[0,1]"] and titles[-1] == "w[1,2]" and len(titles) == 7
    assert (tmp_path / "T.png").stat().st_size > 0
    with pytest.raises(E.UnknownSymbolError, match=r"plot\(names=...\): index 5 is out of range for axis 1 of 'w'"):
        sol.plot(names=["w[0,5]"])


def test_an_objective_of_elements_differentiates_by_an_element_parameter():
    """sol.gradient(T[0, 1]**2) goes through the parser as text ('T[0,1]**2'): elements parse there
    too.  Exact: J = sum_t exp(-2 k t), dJ/dk = sum_t -2 t exp(-2 k t) at k = 2."""
    m, T, _ = decays()
    sol = dm.solve(m, (0.0, 1.0), rtol=1e-10, atol=1e-12, t_eval=np.linspace(0.0, 1.0, 5))
    exact = np.sum(-2 * sol.t * np.exp(-4 * sol.t))
    for objective in (T[0, 1] ** 2, "T[0, 1]**2"):
        assert abs(sol.gradient(objective, wrt=["k[0,1]"])["k[0,1]"] - exact) < 1e-8


def test_many_missing_names_are_counted():
    sol = dm.solve(decays()[0], (0.0, 0.1), h=0.05)
    with pytest.raises(E.UnknownSymbolError, match=r"no values of 'a', 'b', 'c', 'd', 'e' and 2 more: not variables"):
        sol[np.array(list("abcdefg"), dtype=object)]


def test_initial_states_by_array_for_one_sample_and_a_batch():
    m, _, _ = decays()
    c = m.compile()
    start = np.linspace(0.5, 1.5, 6).reshape(2, 3)  # (w = 2 T + w^3 / 100 has a root near 2 T up to T ~ 1.9)
    sol = dm.solve(c, (0.0, 1.0), rtol=1e-10, atol=1e-12, y0={"T": start})
    assert np.max(np.abs(sol["T"][..., -1] - start * np.exp(-RATES))) < 1e-8
    batch = dm.solve(c, (0.0, 1.0), rtol=1e-10, atol=1e-12, y0={"T": np.stack([start, start / 2])})
    assert batch["T"].shape == (2, 2, 3, len(batch.t))
    assert np.max(np.abs(batch["T"][1, ..., -1] - start / 2 * np.exp(-RATES))) < 1e-8
    with pytest.raises(E.ShapeError, match=r"y0\['T'\] must have the array's shape \(2, 3\), or \(batch, \*\(2, 3\)\)"):
        dm.solve(c, (0.0, 1.0), y0={"T": np.ones(6)})
    with pytest.raises(E.UnknownSymbolError, match=r"z0 names 'T\[0,0\]', .* not among \['w\[...\]' \(6 elements\)\]"):
        dm.solve(c, (0.0, 1.0), z0={"T": start})

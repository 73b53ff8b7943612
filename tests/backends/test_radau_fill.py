"""The LU fill of the Newton systems, found within the memory limit (backends/radau/fill.py).

The bound from the pattern must hold SuperLU's factors on every kind of pattern, the column counts must be
the Cholesky factor's, a model whose factors cannot fit is refused before any full factorisation, and one
whose bound says nothing (a dense row) is measured in a child process that cannot take more than it is given.
"""

import math

import numpy as np
import pytest
import scipy.sparse as sparse
import scipy.sparse.linalg as splinalg
import sympy as sp
from daemodel.backends.radau import fill
from daemodel.backends.radau.linalg import pattern_matrix

import daemodel as dm
from daemodel import errors as E


def _pattern(name: str, D: int) -> tuple:
    """``(rows, cols, n)`` of a D x D Jacobian pattern of the kind ``name`` (n differential unknowns)."""
    rng, i = np.random.default_rng(0), np.arange(D)
    if name == "random":  # (four entries a row, and the diagonal)
        return np.r_[rng.integers(0, D, 4 * D), i], np.r_[rng.integers(0, D, 4 * D), i], D
    if name == "arrow":
        return np.r_[i, np.zeros(D, int), i], np.r_[i, i, np.zeros(D, int)], D
    if name == "banded":
        ok = [(i + o >= 0) & (i + o < D) for o in range(-3, 4)]
        return (
            np.concatenate([i[k] for k in ok]),
            np.concatenate([i[k] + o for k, o in zip(ok, range(-3, 4), strict=True)]),
            D,
        )
    if name == "block-dense":  # (dense 20 x 20 blocks on the diagonal)
        return np.repeat(i, 20), (i[:, None] // 20 * 20 + np.arange(20)[None, :]).ravel() % D, D
    if name == "dense row":  # (a chain of states and one algebraic row summing them all: a mean's constraint)
        return np.r_[i, i[1:], i[:-1], np.full(D, D - 1)], np.r_[i, i[:-1], i[1:], i], D - 1
    side = math.isqrt(D)  # ("2-D grid": five-point, side x side = D)
    x, y = i % side, i // side
    steps = [(0, 0), (1, 0), (-1, 0), (0, 1), (0, -1)]
    ok = [(x + dx >= 0) & (x + dx < side) & (y + dy >= 0) & (y + dy < side) for dx, dy in steps]
    return (
        np.concatenate([i[k] for k in ok]),
        np.concatenate([i[k] + dx + dy * side for k, (dx, dy) in zip(ok, steps, strict=True)]),
        D,
    )


@pytest.mark.parametrize("name", ["random", "arrow", "banded", "block-dense", "dense row", "2-D grid"])
def test_the_bound_holds_superlus_factors(name):
    """George and Ng's bound, in SuperLU's column order, is at least the fill SuperLU makes (L's and U's
    entries) whatever rows it pivots on: measured 1.0-1.9 times it without dense rows, more with them."""
    D = 900
    rows, cols, n = _pattern(name, D)
    matrix = pattern_matrix(rows, cols, n, D)
    lu = splinalg.splu(matrix)
    bound = fill.fill_bound(matrix)
    assert lu.L.nnz + lu.U.nnz <= bound
    assert fill.dense_lines(rows, cols, D) == (name in ("arrow", "dense row"))
    if name not in ("arrow", "dense row"):
        assert bound <= 2 * (lu.L.nnz + lu.U.nnz)  # (1.0-1.9 measured; the refusal allows BOUND_SLACK)
    order = fill.superlu_column_order(matrix)
    assert np.array_equal(np.argsort(order), lu.perm_c)  # (SuperLU's own order, without its factorisation)


FAMILIES = [("pendulum_chain", 40), ("sphere_particles", 20), ("reaction_diffusion", 60)]


@pytest.mark.parametrize(("family", "size"), FAMILIES)
def test_index_two_and_three_patterns_have_a_bound_and_keep_the_trial_here(monkeypatch, family, size):
    """The algebraic columns of an index-2 or 3 model have no diagonal: the order's incomplete factorisation
    met zero pivots there (no bound: every such model's trial went to a child process) until the dropped
    entries were added to the diagonal.  The bound holds, and the trial stays in this process."""
    import sys
    from pathlib import Path

    from daemodel.backends.radau import sparse as radau_sparse

    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
    import scaling_models

    compiled = getattr(scaling_models, family)(size).compile()
    rows, cols = radau_sparse.jacobian_pattern(compiled)
    n, D = len(compiled.states), len(compiled.states) + len(compiled.algebraics)
    matrix = pattern_matrix(rows, cols, n, D)
    lu = splinalg.splu(matrix)
    bound = fill.fill_bound(matrix)
    assert bound is not None and lu.L.nnz + lu.U.nnz <= bound <= fill.BOUND_SLACK * (lu.L.nnz + lu.U.nnz)
    monkeypatch.setattr(fill, "capped_trial", lambda *args: pytest.fail("no child process where the bound fits"))
    assert fill.measured_fill(rows, cols, n, D, 1e9) == lu.L.nnz + lu.U.nnz


@pytest.mark.parametrize(("m", "D", "density"), [(1, 1, 1.0), (30, 30, 0.1), (300, 300, 0.01), (80, 50, 0.05)])
def test_the_column_counts_are_the_cholesky_factors_of_ata(m, D, density):
    """The counts, from the column elimination tree without forming A^T A, are those of the symbolic
    Cholesky factor of A^T A (casadi's ldl of the pattern A^T A, formed here)."""
    A = sparse.random(m, D, density, random_state=np.random.default_rng(D), format="csc")
    if m == D:
        A = (A + sparse.eye(D)).tocsc()
    product = (abs(A).T @ abs(A)).tocsc()
    product.sort_indices()
    import casadi

    factor, _ = casadi.Sparsity(D, D, product.indptr.tolist(), product.indices.tolist()).ldl(False)
    assert int(fill.ata_column_counts(A).sum()) == factor.nnz() + D  # (ldl's L^T without its unit diagonal)


def _random_model(K: int) -> dm.Model:
    """y_i' = -y_i + sum of sin(y_j) / 10 over four random j: a random sparse pattern (fills ~0.14 n^2)."""
    rng = np.random.default_rng(0)
    m = dm.Model(f"random_{K}")
    y = m.states("y", K)
    picks = rng.integers(0, K, (K, 4))
    m.ode(y, np.array([-y[i] + sum(sp.sin(y[j]) for j in picks[i]) / 10 for i in range(K)], dtype=object))
    m.initial(y=np.linspace(0.1, 1.0, K))
    return m


def _mean_model(K: int) -> dm.Model:
    """y_i' = -(1 + i / K) y_i + z / 10 with z the mean of the y's: one dense row and one dense column."""
    m = dm.Model(f"mean_{K}")
    y = m.states("y", K)
    (z,) = m.algebraics("z")
    m.ode(y, np.array([-y[i] * (1 + sp.Rational(i, K)) + z / 10 for i in range(K)], dtype=object))
    m.constraint(z - sum(y) / K, name="mean")
    m.initial(y=np.linspace(0.1, 1.0, K))
    return m


def test_a_model_whose_factors_cannot_fit_is_refused_before_any_factorisation(monkeypatch):
    """The guard factored the pattern to count its fill (a random model of 10^5 unknowns: ~17 GB and hours
    for that trial alone); where even the bound over BOUND_SLACK does not fit, it refuses at once, naming the
    size, the fill and the limit, and SuperLU never runs."""
    compiled = _random_model(400).compile()
    factored = []
    monkeypatch.setattr(splinalg, "splu", lambda *args, **kwargs: factored.append(1) / 0)
    monkeypatch.setenv("DAEMODEL_MEMORY_LIMIT", "128K")
    refused = (
        r"radau on 1 sample\(s\) of 400 unknowns: the LU factors of its sparse Newton systems would hold about "
        r"[\d.e+]+ entries or more \(the bound [\d.e+]+ from the Jacobian's pattern .*\), [\d.e+-]+ GiB with its 5 "
        r"stages' systems, more than the 0.000122 GiB allowed \(the fill that fits: [\d.e+]+ entries; set "
        r"DAEMODEL_MEMORY_LIMIT"
    )
    with pytest.raises(E.ResourceLimitError, match=refused):
        dm.solve(compiled, (0.0, 1.0), rtol=1e-6, atol=1e-8, jit=False)
    assert not factored


def test_a_model_that_fits_keeps_the_trial_in_this_process(monkeypatch):
    """Where the bound's trial fits the limit the fill is counted as before, in this process."""
    from daemodel.backends.radau import sparse as radau_sparse

    monkeypatch.setattr(fill, "capped_trial", lambda *args: pytest.fail("no child process where the bound fits"))
    compiled = _random_model(400).compile()
    sol = dm.solve(compiled, (0.0, 0.5), rtol=1e-6, atol=1e-8, jit=False)
    assert sol.status == "success"
    rows, cols = radau_sparse.jacobian_pattern(compiled)
    assert compiled.cached("radau-factor-entries", lambda: None) == fill.factor_entries(rows, cols, 400, 400)


def test_a_dense_row_is_measured_in_a_child_process_and_solves_as_before(monkeypatch):
    """A constraint summing every state makes the bound the dense n^2 (the pattern's A^T A is dense) where the
    factors hold ~4n entries: the trial runs in a child process capped at the limit, and the solve is the
    same as under a limit that lets the trial run here."""
    compiled = _mean_model(300).compile()
    free = dm.solve(compiled, (0.0, 1.0), rtol=1e-8, atol=1e-10, jit=False)
    children = []
    trial = fill.capped_trial
    monkeypatch.setattr(fill, "capped_trial", lambda *args: children.append(trial(*args)) or children[-1])
    capped = _mean_model(300).compile()
    monkeypatch.setenv("DAEMODEL_MEMORY_LIMIT", "4M")  # (the bound's trial, 80 bytes x 9 x 10^4: 7 MB, not here)
    sol = dm.solve(capped, (0.0, 1.0), rtol=1e-8, atol=1e-10, jit=False)
    assert len(children) == 1 and children[0] == compiled.cached("radau-factor-entries", lambda: None)
    assert sol.status == "success" and sol.stats["steps"] == free.stats["steps"]
    assert np.array_equal(sol["y"], free["y"]) and np.array_equal(sol["z"], free["z"])


def test_the_child_process_stops_at_the_memory_it_is_given(monkeypatch):
    """A dense row whose fill is ~0.3 n^2 under SuperLU's order: the child runs out of the memory it was given
    and the guard refuses, naming it; with room it counts what this process's factorisation counts."""
    D = 5000  # (~0.22 n^2 = 5.5e6 entries: their values alone 44 MB, beyond the 32 MiB given, whatever the heap)
    rows, cols, n = _pattern("dense row", D)
    matrix = pattern_matrix(rows, cols, n, D)
    monkeypatch.setenv("DAEMODEL_MEMORY_LIMIT", "32M")
    with pytest.raises(fill.FillOverLimit, match=r"one factorisation of the pattern ran out of the 0.0312 GiB"):
        fill.measured_fill(rows, cols, n, D, 10**5)
    lu = splinalg.splu(matrix)
    assert fill.capped_trial(matrix, 2**30, 120.0) == lu.L.nnz + lu.U.nnz


def test_rows_that_pivot_last_are_measured_not_refused_on_the_bound(monkeypatch):
    """Many algebraic rows of 16 states each (no dense line) make the bound 30-50 times the fill, since it lets
    any row pivot where these pivot last: a slack of 4 refused a model whose factors fit.  Such a pattern is
    counted (here in the child process) and the count is SuperLU's."""
    D, hubs, width = 3000, 150, 16
    i, rng = np.arange(D), np.random.default_rng(0)
    rows = np.r_[i, i[1:], i[:-1], np.repeat(np.arange(D - hubs, D), width)]
    cols = np.r_[i, i[:-1], i[1:], rng.integers(0, D - hubs, hubs * width)]
    matrix = pattern_matrix(rows, cols, D - hubs, D)
    lu = splinalg.splu(matrix)
    bound, count = fill.fill_bound(matrix), lu.L.nnz + lu.U.nnz
    assert bound > 8 * count and not fill.dense_lines(rows, cols, D)
    monkeypatch.setenv("DAEMODEL_MEMORY_LIMIT", str(TRIAL_BYTES := fill.TRIAL_BYTES_PER_ENTRY * bound // 2))
    assert TRIAL_BYTES < fill.TRIAL_BYTES_PER_ENTRY * bound  # (the trial is not allowed in this process)
    assert fill.measured_fill(rows, cols, D - hubs, D, 2 * count) == count


def test_a_dense_row_whose_count_runs_out_of_memory_is_refused(monkeypatch):
    """A chain of states whose boundary value is their total (one dense row): under SuperLU's order its
    factors fill ~0.22 n^2 (1.95e6 entries at 3,000), the bound says little, and the count in the child runs out of
    the memory allowed: the guard refuses, naming the size and why."""
    K = 5000  # (~0.22 n^2 = 5.5e6 entries: their values alone 44 MB, beyond the 32 MiB allowed, whatever the heap)
    m = dm.Model("chain_and_sum")
    y = m.states("y", K)
    (z,) = m.algebraics("z")
    padded = np.array([0, *y, z / K], dtype=object)  # (the right boundary's value: the states' mean)
    m.ode(y, padded[:-2] - 2 * padded[1:-1] + padded[2:])
    m.constraint(z - sp.Add(*y), name="total")
    m.initial(y=np.linspace(0.1, 1.0, K))
    compiled = m.compile()
    monkeypatch.setenv("DAEMODEL_MEMORY_LIMIT", "32M")
    refused = (
        r"radau on 1 sample\(s\) of 5001 unknowns: the LU factors of its sparse Newton systems could not be "
        r"counted within the 0.0312 GiB allowed \(one factorisation of the pattern ran out of the 0.0312 GiB it "
        r"was given; set DAEMODEL_MEMORY_LIMIT, e.g. '64G', to change it\): fewer unknowns"
    )
    with pytest.raises(E.ResourceLimitError, match=refused):
        dm.solve(compiled, (0.0, 1.0), rtol=1e-6, atol=1e-8, jit=False)


def test_a_child_process_out_of_time_is_stopped_and_named(monkeypatch):
    """The count in the child stops at its time limit: the child is killed and waited for, and the reason
    names the limit (a random pattern of 2 x 10^4 unknowns fills ~0.14 n^2: far more than 10 ms)."""
    import os

    D, children, fork = 20_000, [], os.fork
    monkeypatch.setattr(os, "fork", lambda: children.append(fork()) or children[-1])
    rows, cols, n = _pattern("random", D)
    outcome = fill.capped_trial(pattern_matrix(rows, cols, n, D), 2**30, 0.01)
    assert outcome == "one factorisation of the pattern did not finish within 0.01 s"
    with pytest.raises(ProcessLookupError):  # (the child is gone, reaped: none left behind)
        os.kill(children[0], 0)


def test_the_column_order_of_a_pattern_without_a_full_diagonal_does_not_abort_the_process():
    """A random pattern of 300 unknowns, 180 of them differential, whose algebraic columns have no diagonal: the
    incomplete factorisation that reads SuperLU's order, at a fill ratio of 1, overran its work space and glibc
    aborted the whole process ("double free or corruption"), so it runs in a child interpreter here.  Now it
    finishes, with SuperLU's own order and a bound that holds its factors."""
    import subprocess
    import sys

    code = (
        "import numpy as np, scipy.sparse.linalg as splinalg\n"
        "from daemodel.backends.radau import fill\n"
        "from daemodel.backends.radau.linalg import pattern_matrix\n"
        "D = 300\n"
        "rng, i = np.random.default_rng(24), np.arange(D)\n"
        "k = int(rng.integers(1, 6)) * D\n"
        "rows, cols = np.r_[rng.integers(0, D, k), i], np.r_[rng.integers(0, D, k), rng.permutation(D)]\n"
        "matrix = pattern_matrix(rows, cols, 180, D)\n"
        "lu = splinalg.splu(matrix)\n"
        "order = fill.superlu_column_order(matrix)\n"
        "print(int(np.array_equal(np.argsort(order), lu.perm_c)), fill.fill_bound(matrix), lu.L.nnz + lu.U.nnz)\n"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr[-300:]
    same, bound, count = (int(word) for word in run.stdout.split())
    assert same == 1 and count <= bound


def test_the_pattern_matrix_is_made_once_for_the_bound_and_the_count(monkeypatch):
    """measured_fill made ``sigma M - J`` for the bound and again for the count (factor_entries): now the count
    factors the matrix it is given, and counts what factor_entries counts."""
    rows, cols, n = _pattern("random", 900)
    made, make = [], fill.pattern_matrix
    monkeypatch.setattr(fill, "pattern_matrix", lambda *args: made.append(1) or make(*args))
    count = fill.measured_fill(rows, cols, n, 900, 1e9)
    assert len(made) == 1
    assert count == fill.factor_entries(rows, cols, n, 900)


@pytest.mark.parametrize(
    ("seconds", "said"),
    [(0, "positive"), (-1.0, "positive"), (math.nan, "finite"), (math.inf, "finite"), ("5", "a real number"),
     (True, "a real number"), (None, "a real number")],  # (None was taken: select's wait without a bound)
)  # fmt: skip
def test_fill_seconds_must_be_a_positive_finite_number(seconds, said):
    with pytest.raises(E.InvalidOptionError, match=f"fill_seconds must be {said}; got"):
        dm.solve(_mean_model(3).compile(), (0.0, 1.0), method="radau", fill_seconds=seconds)


def test_fill_seconds_is_the_child_process_s_time_limit(monkeypatch):
    """TRIAL_SECONDS (30 s) was fixed: the count in a child process (a dense row, the trial not allowed here) now
    takes radau's fill_seconds (a count past it: test_a_child_process_out_of_time_is_stopped_and_named)."""
    seconds, trial = [], fill.capped_trial
    monkeypatch.setattr(fill, "capped_trial", lambda matrix, limit, s: seconds.append(s) or trial(matrix, limit, s))
    monkeypatch.setenv("DAEMODEL_MEMORY_LIMIT", "4M")
    sol = dm.solve(_mean_model(300).compile(), (0.0, 1.0), rtol=1e-8, atol=1e-10, jit=False, fill_seconds=7.5)
    assert sol.status == "success" and seconds == [7.5]


@pytest.mark.parametrize("max_bytes", [1e30, 2.0**63, 2.0**64])
def test_a_child_given_more_memory_than_setrlimit_takes_counts_unlimited(max_bytes):
    # before: setrlimit's OverflowError in the child, "one factorisation of the pattern failed in a child process
    # given 9.31e+20 GiB (error OverflowError)": a refusal under a limit no model reaches
    rows, cols, n = _pattern("dense row", 300)
    matrix = pattern_matrix(rows, cols, n, 300)
    lu = splinalg.splu(matrix)
    assert fill.capped_trial(matrix, max_bytes, 60.0) == lu.L.nnz + lu.U.nnz


def test_a_child_process_that_cannot_be_made_leaves_the_bound_to_decide(monkeypatch):
    """fork's OSError (EAGAIN: a process limit reached) came out of the solve as a bare BlockingIOError; now the
    bound decides, as on a system without fork: here the bound (9.1e4 entries) is more than the 4 MiB leave
    (5.2e4), and the solve is refused naming it."""
    import os

    def no_fork():
        raise BlockingIOError(11, "Resource temporarily unavailable")

    compiled = _mean_model(300).compile()
    monkeypatch.setattr(os, "fork", no_fork)
    monkeypatch.setenv("DAEMODEL_MEMORY_LIMIT", "4M")  # (the trial not allowed here: a child process is asked for)
    refused = (
        r"would hold about 9.09e\+04 entries or more \(the bound 9.09e\+04 from the Jacobian's pattern; not factored\)"
    )
    with pytest.raises(E.ResourceLimitError, match=refused):
        dm.solve(compiled, (0.0, 1.0), rtol=1e-8, atol=1e-10, jit=False)


def test_a_fill_seconds_past_the_clocks_range_waits_without_an_overflow(monkeypatch):
    """fill_seconds = 1e300 passed the option's check and reached select, whose wait must fit the platform's
    time_t: an OverflowError out of dm.solve; now the wait is at most fill.MAX_WAIT_SECONDS (31 years)."""
    monkeypatch.setenv("DAEMODEL_MEMORY_LIMIT", "4M")
    sol = dm.solve(_mean_model(300).compile(), (0.0, 1.0), rtol=1e-8, atol=1e-10, jit=False, fill_seconds=1e300)
    assert sol.status == "success"

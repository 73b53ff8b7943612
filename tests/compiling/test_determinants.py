"""Signs of determinants for the branch check: sparse LU against dense slogdet, permutation parity
against a count of inversions, and the branch check itself on 200 algebraic variables."""

import itertools

import numpy as np
import pytest
import scipy.sparse as sparse

import daemodel as dm
from daemodel import errors as E
from daemodel.compiling import determinants
from daemodel.compiling.determinants import determinant_signs, odd_permutation, sparse_sign
from daemodel.compiling.initial_states import check_branch


def inversions(p) -> int:
    return sum(1 for i in range(len(p)) for j in range(i + 1, len(p)) if p[i] > p[j])


def test_the_parity_of_a_permutation_is_that_of_its_inversions():
    rng = np.random.default_rng(1)
    for n in (1, 2, 3, 7, 64, 257):
        for _ in range(25):
            p = rng.permutation(n)
            assert odd_permutation(p) == inversions(p) % 2, p
    assert odd_permutation(np.arange(10)) == 0 and odd_permutation([1, 0]) == 1 and odd_permutation([]) == 0


def test_the_parity_of_permutations_near_the_identity():
    """A few swaps of a long identity (SuperLU's row orders): short cycles, whose passes stop early,
    beside one long cycle whose least index is found only at the last pass."""
    rng = np.random.default_rng(2)
    for n in (2, 9, 300, 1000):
        for swaps in range(6):
            p = np.arange(n)
            for _ in range(swaps):
                i, j = rng.integers(0, n, 2)
                p[[i, j]] = p[[j, i]]
            assert odd_permutation(p) == inversions(p) % 2, p
        cycle = np.r_[1:n, 0]  # (one cycle through all n: n - 1 transpositions)
        assert odd_permutation(cycle) == (n - 1) % 2


def test_the_parity_of_every_small_permutation_and_of_long_cycles_in_any_order():
    """The passes' early stop (daedd48) against the inversions' parity on every permutation of up to 7
    and random ones of 8 and 9; and one cycle through all n visited in a random order (its least index
    reaches the others only at the last pass) beside many 2-cycles, up to 2^16 + 1."""
    for n in range(8):
        for p in itertools.permutations(range(n)):
            assert odd_permutation(np.array(p, dtype=np.int64)) == inversions(p) % 2, p
    rng = np.random.default_rng(3)
    for n in (8, 9):
        for _ in range(300):
            p = rng.permutation(n)
            assert odd_permutation(p) == inversions(p) % 2, p
    for n in (1000, 2**16 + 1):
        visit = rng.permutation(n)
        cycle = np.empty(n, dtype=np.int64)
        cycle[visit] = np.roll(visit, -1)
        assert odd_permutation(cycle) == (n - 1) % 2
        pairs = cycle.copy()
        half = visit[: 2 * (n // 4)].reshape(-1, 2)  # (these as 2-cycles, the rest one cycle of its own)
        rest = visit[2 * (n // 4) :]
        pairs[half[:, 0]], pairs[half[:, 1]] = half[:, 1], half[:, 0]
        pairs[rest] = np.roll(rest, -1)
        assert odd_permutation(pairs) == (len(half) + len(rest) - 1) % 2


def test_sparse_signs_are_dense_slogdets_signs():
    rng = np.random.default_rng(2)
    for m in (64, 150, 400):
        for _ in range(15):
            A = (sparse.random(m, m, density=0.02, random_state=rng) + sparse.diags(rng.normal(size=m))).tocoo()
            assert sparse_sign(A.row, A.col, A.data, m) == np.linalg.slogdet(A.toarray())[0]


def test_singular_or_non_finite_matrices_have_sign_zero_on_both_paths():
    m = 100
    diagonal = np.arange(m)
    values = np.ones((3, m))
    values[1, 17] = 0.0  # a zero pivot: singular
    values[2, 5] = np.nan
    signs = determinant_signs(diagonal, diagonal, values, m)
    np.testing.assert_array_equal(signs, [1.0, 0.0, 0.0])
    assert determinants.sparse_enough(m, m)
    dense = determinant_signs(diagonal[:10], diagonal[:10], values[:, :10], 10)  # (10 x 10: the dense path)
    np.testing.assert_array_equal(dense, [1.0, 1.0, 0.0])  # (the NaN at 5)
    negated = determinant_signs(diagonal[:11], diagonal[:11], -values[:, 10:21], 11)  # (-1)^11; the 0 at 17
    np.testing.assert_array_equal(negated, [-1.0, 0.0, -1.0])


def test_triangular_signs_of_many_matrices_at_once_are_their_slogdets_signs():
    # the branch check's one call per solve: K lower (then upper) triangular 100 x 100 matrices with
    # random diagonals of either sign, against each one's dense slogdet and the one-matrix sparse_sign
    rng = np.random.default_rng(7)
    m, K = 100, 40
    below = rng.choice(m * m, 300, replace=False)
    r, c = np.divmod(below, m)
    keep = r > c
    rows, cols = np.r_[np.arange(m), r[keep]], np.r_[np.arange(m), c[keep]]
    values = rng.normal(size=(K, len(rows)))
    values[3, 7] = 0.0  # a zero pivot
    values[5, m + 2] = np.inf  # off the diagonal, yet not finite: 0, as sparse_sign gives it
    for r_, c_ in ((rows, cols), (cols, rows)):
        signs = determinant_signs(r_, c_, values, m)
        dense = np.zeros((K, m, m))
        dense[:, r_, c_] = values
        expected = [0.0 if not np.isfinite(d).all() else np.linalg.slogdet(d)[0] for d in dense]
        np.testing.assert_array_equal(signs, expected)
        np.testing.assert_array_equal(signs, [sparse_sign(r_, c_, v, m) for v in values])
        assert {-1.0, 1.0} <= set(signs) and signs[3] == signs[5] == 0.0


def test_positions_given_as_lists_or_without_entries_take_the_triangular_path():
    # np.bincount (counting repeated diagonal positions) refused the float64 array that np.asarray makes of an
    # empty list: a TypeError where np.unique gave the signs; lists of ints are positions as arrays are
    np.testing.assert_array_equal(determinants.triangular_signs([], [], np.zeros((2, 0)), 3), [0.0, 0.0])
    signs = determinants.triangular_signs([0, 1, 1], [0, 0, 1], np.array([[2.0, 5.0, -3.0], [2.0, 5.0, 3.0]]), 2)
    np.testing.assert_array_equal(signs, [-1.0, 1.0])


def test_entries_at_one_position_add_up_on_both_paths():
    # diag(-3 + 2, 1, ...): det < 0 where the two entries at (0, 0) add up; whichever of them came last
    # alone (2 in one order, -3 in the other) would give +1 in one of the two orders
    for m in (2, 100):  # (the dense path; the sparse one)
        rows, cols = np.r_[0, np.arange(m)], np.r_[0, np.arange(m)]
        values = np.r_[-3.0, 2.0, np.ones(m - 1)][None]
        assert determinants.sparse_enough(len(rows), m) == (m == 100)
        np.testing.assert_array_equal(determinant_signs(rows, cols, values, m), [-1.0])
        np.testing.assert_array_equal(determinant_signs(rows, cols, values[:, [1, 0, *range(2, m + 1)]], m), [-1.0])


def cubic_folds(m: int):
    """``x_i' = 0``, ``0 = z_i^3 / 3 - z_i - x_i``: dH/dz = diag(z_i^2 - 1), singular at |z_i| = 1 (a fold)."""
    model = dm.Model("folds")
    xs = model.states([f"x{i}" for i in range(m)])
    zs = model.algebraics([f"z{i}" for i in range(m)])
    for i in range(m):
        model.ode(xs[i], 0)
        model.constraint(zs[i] ** 3 / 3 - zs[i] - xs[i], name=f"g{i}")
    model.initial(**{f"x{i}": 2 / 3 + 1.0 for i in range(m)})  # z = 2 solves z^3/3 - z = 2/3
    model.guess(**{f"z{i}": 2.0 for i in range(m)})
    return model.compile()


@pytest.mark.parametrize("sparse_path", [True, False])
def test_the_branch_check_on_200_algebraic_variables_names_the_fold(sparse_path, monkeypatch):
    """At 200 algebraic variables the check takes the sparse LU (the dense one was 26 s at 5,000); the
    dense path (forced) finds the same."""
    if not sparse_path:
        monkeypatch.setattr(determinants, "SPARSE_MIN_SIZE", 10**9)
    m = 200
    c = cubic_folds(m)
    x, z = np.full(m, 2 / 3 + 1.0), np.full(m, 2.0)
    on_branch = np.array([np.r_[x, z], np.r_[x, z * 1.5]])[None]  # z^2 - 1 > 0 at both
    check_branch("radau", c, np.array([0.0, 1.0]), on_branch, np.zeros((1, 0)))
    crossed = on_branch.copy()
    crossed[0, 1, m + 137] = 0.5  # z_137^2 - 1 < 0: det(dH/dz) changed sign
    with pytest.raises(E.BranchError, match=r"radau: .* between t = 0 \(.*z137 = 2.*\) and t = 1 \(.*z137 = 0\.5"):
        check_branch("radau", c, np.array([0.0, 1.0]), crossed, np.zeros((1, 0)))
    twice = on_branch.copy()
    twice[0, 1, m + 3] = twice[0, 1, m + 9] = 0.5  # two sign changes: det keeps its sign (what the check can see)
    check_branch("radau", c, np.array([0.0, 1.0]), twice, np.zeros((1, 0)))


def test_a_time_limit_inside_the_sparse_lu_is_not_a_zero_determinant(monkeypatch):
    """A time limit's TimeLimitError (a RuntimeError too), raised as SuperLU returns, read as sign 0."""
    import scipy.sparse.linalg

    def struck(*_, **__):
        raise E.TimeLimitError("stop here")

    monkeypatch.setattr(scipy.sparse.linalg, "splu", struck)
    with pytest.raises(E.TimeLimitError, match=r"^stop here$"):  # (a matrix not triangular: SuperLU's)
        sparse_sign(np.r_[0, 1, 2, 1, 0], np.r_[0, 1, 2, 0, 1], np.r_[2.0, 2.0, 2.0, 1.0, 1.0], 3)


def test_triangular_matrices_take_their_diagonals_sign_without_an_lu(monkeypatch):
    """Diagonal, lower and upper triangular matrices (with repeated entries, a zero on the diagonal, off-
    diagonal entries large enough that SuperLU would pivot): the sign of their dense slogdet, and SuperLU
    is not called (a diagonal g_z: 13 LUs of 5 x 10^4 a solve at 10^5 unknowns); a matrix with entries on
    both sides still takes SuperLU."""
    import scipy.sparse.linalg as splinalg
    from daemodel.backends.radau import linalg

    rng = np.random.default_rng(5)
    m = 120
    cases = []
    for _ in range(10):
        diagonal = sparse.diags(rng.choice([-1.0, 1.0], m) * rng.uniform(0.5, 2.0, m))
        below = sparse.tril(
            sparse.random(m, m, density=0.03, random_state=rng, data_rvs=lambda k: 50 * rng.normal(size=k)), -1
        )
        cases += [diagonal, diagonal + below, (diagonal + below).T]
    repeated = (np.r_[0, np.arange(m)], np.r_[0, np.arange(m)], np.r_[-3.0, 2.0, np.ones(m - 1)])  # (0, 0): -1
    singular = sparse.diags(np.r_[np.ones(m - 1), 0.0]) + sparse.eye(m, k=-1)
    calls = []
    real_splu = splinalg.splu
    monkeypatch.setattr(splinalg, "splu", lambda *a, **k: calls.append(1) or real_splu(*a, **k))
    for A in cases:
        A = A.tocoo()
        expected = np.linalg.slogdet(A.toarray())[0]
        assert sparse_sign(A.row, A.col, A.data, m) == expected == linalg.sparse_sign_det(A.tocsc())
    assert sparse_sign(*repeated, m) == -1.0
    A = singular.tocoo()
    assert sparse_sign(A.row, A.col, A.data, m) == 0.0 == linalg.sparse_sign_det(A.tocsc())
    assert calls == []
    both = (sparse.diags(np.ones(m)) + sparse.eye(m, k=1) + sparse.eye(m, k=-1)).tocoo()
    assert sparse_sign(both.row, both.col, both.data, m) == np.linalg.slogdet(both.toarray())[0] and calls == [1]


def _householder(rows, cols, m):
    """casadi's function of a sparse (m, m) matrix's nonzeros (column-major triplet order) to the sign of its
    determinant read off its sparse Householder QR (:func:`determinants.householder_sign`)."""
    import casadi

    x = casadi.SX.sym("x", len(rows))
    A = casadi.SX(casadi.Sparsity.triplet(m, m, list(rows), list(cols)), x)
    V, R, beta, row_order, col_order = casadi.qr_sparse(A)
    assert V.size1() == m
    parity = (-1) ** (odd_permutation(np.asarray(row_order)) + odd_permutation(np.asarray(col_order)))
    return casadi.Function("sign", [x], [determinants.householder_sign(casadi, A, beta, casadi.diag(R), parity)])


def test_the_householder_sign_is_numpys_or_unknown():
    """The QR's sign of det A (what radau's solve at the outputs hands the branch check) against numpy's LU
    (slogdet) on 200 random sparse patterns of order 1-9, 25 matrices each, some with exact zeros and NaN: equal
    wherever it is known; unknown (NaN) wherever an entry is not finite, and only on matrices within rounding of
    a singular one (never where the condition number is below 10^6)."""
    rng = np.random.default_rng(7)
    unknown_finite = 0
    for _ in range(200):
        m = int(rng.integers(1, 10))
        mask = rng.random((m, m)) < 0.4
        mask[np.arange(m), rng.permutation(m)] = True  # (structurally nonsingular)
        rows, cols = np.nonzero(mask.T)[::-1]  # (column by column, as casadi's nonzeros)
        sign = _householder(rows, cols, m)
        for k in range(25):
            values = rng.standard_normal(len(rows)) * 10.0 ** rng.integers(-3, 4)
            if k % 5 == 0:
                values[rng.random(len(rows)) < 0.3] = 0.0
            if k % 7 == 0:
                values[rng.integers(len(values))] = np.nan
            got = float(sign(values))
            A = np.zeros((m, m))
            A[rows, cols] = values
            if not np.isfinite(values).all():
                assert np.isnan(got)
            elif np.isnan(got):
                assert np.linalg.cond(A) > 1e6
                unknown_finite += 1
            else:
                assert got == np.linalg.slogdet(A)[0], (A, got)
    assert unknown_finite < 1000  # (the exactly singular ones: a few hundred of the 5,000)


def test_the_householder_sign_of_extreme_and_singular_matrices_is_unknown():
    """Where the QR's reading could be wrong: a zero pivot, a diagonal spread beyond HOUSEHOLDER_SURE_RATIO, an
    entry beyond HOUSEHOLDER_RANGE (casadi's beta reads 0 where 1 / (R_cc v_c0) overflows), an infinite one."""
    rows, cols = np.array([0, 1, 0, 1]), np.array([0, 0, 1, 1])
    sign = _householder(rows, cols, 2)
    assert float(sign([2.0, 1.0, 1.0, 3.0])) == 1.0 and float(sign([1.0, 2.0, 3.0, 1.0])) == -1.0
    for values in ([1.0, 2.0, 2.0, 4.0], [1.0, 0.0, 0.0, 1e-9], [1e160, 0.0, 0.0, 1e160], [1e-160, 0, 0, 1e-160],
                   [np.inf, 1.0, 1.0, 1.0], [1.0, 1.0, 1.0, -np.inf]):  # fmt: skip
        assert np.isnan(float(sign(values))), values
    assert float(sign([1.0, 0.0, 0.0, -1e-7])) == -1.0  # (spread 1e7: still read)


def test_the_branch_check_reads_the_signs_given_and_evaluates_the_unknown_ones(monkeypatch):
    """check_branch(signs=...): the signs a method read (radau's at its outputs) are taken as they are, NaN ones
    evaluated as without them; a change among them is the BranchError, naming the times."""
    m = 4
    c = cubic_folds(m)
    x, z = np.full(m, 2 / 3 + 1.0), np.full(m, 2.0)
    values = np.array([np.r_[x, z]] * 3)[None]  # (det(dH/dz) > 0 at each)
    evaluated = []
    signs_of = determinants.determinant_signs

    def counted(rows, cols, entries, size):
        evaluated.append(len(entries))
        return signs_of(rows, cols, entries, size)

    monkeypatch.setattr("daemodel.compiling.initial_states.determinant_signs", counted)
    times = np.array([0.0, 1.0, 2.0])
    check_branch("radau", c, times, values, np.zeros((1, 0)), signs=np.array([[1.0, 1.0, 1.0]]))
    assert evaluated == []
    check_branch("radau", c, times, values, np.zeros((1, 0)), signs=np.array([[1.0, np.nan, 1.0]]))
    assert evaluated == [1]
    with pytest.raises(E.BranchError, match=r"radau: .* between t = 1 \(.*\) and t = 2 \(.*\) \(sample 0 of 'folds'\)"):
        check_branch("radau", c, times, values, np.zeros((1, 0)), signs=np.array([[1.0, 1.0, -1.0]]))
    crossed = values.copy()
    crossed[0, 2, m + 1] = 0.5  # (evaluated: det changed sign)
    with pytest.raises(E.BranchError, match=r"radau: .* between t = 1 \(.*\) and t = 2 \(.*z1 = 0\.5"):
        check_branch("radau", c, times, crossed, np.zeros((1, 0)), signs=np.array([[1.0, 1.0, np.nan]]))

"""Sparse LU factors of the transformed systems with a fixed pivot order, as casadi SX functions.

Above :data:`.casadi_engine.COMPILED_FACTOR_MAX_SIZE` unknowns a dense inverse of each transformed
system costs 0.16-0.75 ms at 100-200 unknowns, and the Newton iteration's products with it 40 us;
SuperLU factors cheaper but only from Python, once per iteration's solve.  Chains and grids are
sparse: with a pivot order chosen once (:func:`matched_order`, static pivoting, else SuperLU's
partial pivoting, :func:`partial_order`) and kept fixed, the elimination's pattern is fixed too, and
the factorisation and the triangular solves are straight-line code on the nonzeros: measured on
casadi's virtual machine, a factor 5.5-40 us and a real solve 4-38 us on the chain and
reaction-diffusion families at 100-200 unknowns.  The factors then live in the compiled step like the dense inverses do.

A fixed pivot order suits the matrix it was chosen at; where values move far from it a pivot may
grow small against the entries below it.  Each factorisation reports its
growth, the larger of its largest multiplier |L| (at most 1 under partial pivoting) and its largest
|U| entry over the matrix's largest entry (Wilkinson's growth factor), and its smallest pivot;
beyond :data:`MAX_GROWTH`, at a zero pivot, or not finite, the caller factors with LAPACK or
SuperLU instead (:class:`.casadi_engine.CasadiEngine` does, and names a singular matrix).
"""

from __future__ import annotations

import math

import numpy as np
from daemodel.backends.radau.fill import TRIAL_BYTES_PER_ENTRY, measured_fill
from daemodel.backends.radau.linalg import BandOrder, band_order, sorted_unique, sparse_lu

# Growth of the factors (max |L|, and max |U| over max |matrix|) beyond which the fixed pivot order is
# not trusted: partial pivoting keeps |L| <= 1, and a pivot grown small against the entries below it
# shows as a large multiplier (a 1e-16 pivot under O(1) entries: |L| ~ 1e16); the solve's backward
# error grows with it, and beyond 1e6 Newton's iteration, which absorbs a relative error well below 1,
# would contract too slowly.
MAX_GROWTH = 1e6
# How a StaticLU chooses its pivot order, in the order a model's first order tries them: static pivoting
# on a matching (matched_order), else SuperLU's partial pivoting (partial_order)
PIVOTING = ("matched", "partial")


def partial_order(A) -> tuple[np.ndarray, np.ndarray]:
    """``(perm_r, perm_c)`` of SuperLU's factorisation of the sparse ``A`` (COLAMD columns, rows by
    partial pivoting): the order that holds best at ``A`` itself, and depends on every value of it.
    RuntimeError where ``A`` is exactly singular."""
    import scipy.sparse.linalg as splinalg

    lu = splinalg.splu(A.tocsc(), permc_spec="COLAMD")
    return lu.perm_r.copy(), lu.perm_c.copy()


def matched_order(A, n: int, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """``(perm_r, perm_c)`` of static pivoting for ``A = sigma M - J`` (``n`` differential variables first,
    ``sigma`` large against J: a short step), in three stages, each pivot chosen by structure and by
    how large it is against its column, not by the values of one matrix:

    1. the differential variables' diagonal entries (``sigma - J_ii``), in a minimum-degree order;
    2. the algebraic block's pivots by a matching on its Schur complement ``S = A_zz - A_zy A_yy^-1 A_yz``
       (here ``A_zz - A_zy A_yz / sigma``: ``A_yy ~ sigma I``), as SuperLU_DIST and MUMPS choose static
       pivots (Duff and Koster's MC64): the assignment of rows to columns of largest product of
       ``|s_ij| / max_i |s_ij|`` (scipy's minimum-weight full matching of ``log max_i |s_ij| - log |s_ij|``);
    3. those pivots in a minimum-degree order of ``S + S^T``, stably sorted so that the rows with an
       entry in an algebraic column (index 1: O(1) pivots) come before those with none (index 2: their
       Schur complement entries are O(1 / sigma), and an O(1) entry under one would be a multiplier
       growing as 1 / h).

    Partial pivoting takes the largest entry under each pivot at one matrix: the wheelset's order, picked
    at its start at rest, pivots on creep forces' derivatives that vanish where tanh saturates, and met a
    zero pivot at 4,599 of the 5,307 steps of a solve over [0, 10] at rtol 1e-6; this order met no growth
    past :data:`MAX_GROWTH` at every 8th of them, at their own h, at 1e-6 and at 0.1 (measured offline; a
    matching of the whole matrix, without stages 1 and 3, grew as 12 / h, past the bound below h = 1e-5).
    RuntimeError where the algebraic block has no full matching of nonzero entries."""
    import scipy.sparse as sparse
    import scipy.sparse.csgraph as csgraph

    A = sparse.csr_matrix(A)
    D = A.shape[0]
    m = D - n
    perm_r, perm_c = np.empty(D, dtype=np.int64), np.empty(D, dtype=np.int64)
    if n:
        states = _diagonal_order(A[:n, :n])  # states[k]: the state eliminated k-th
        perm_r[states] = perm_c[states] = np.arange(n)
    if not m:
        return perm_r, perm_c
    S = (A[n:, n:] - A[n:, :n] @ A[:n, n:] / sigma).tocsr()
    S.eliminate_zeros()
    magnitude = abs(S)
    largest = np.asarray(magnitude.max(axis=0).todense()).ravel()
    entries = magnitude.tocoo()
    # (+1: the weights must be nonzero, and a matching has m of them whatever it takes)
    cost = np.log(largest[entries.col]) - np.log(entries.data) + 1.0
    try:
        matched_rows, matched_cols = csgraph.min_weight_full_bipartite_matching(
            sparse.csr_matrix((cost, (entries.row, entries.col)), shape=S.shape)
        )
    except ValueError as error:  # ("no full matching exists")
        raise RuntimeError(f"no full matching of the algebraic block's nonzero entries: {error}") from error
    row_of = np.empty(m, dtype=np.int64)
    row_of[matched_cols] = matched_rows  # column j's pivot row
    order = _diagonal_order(S[row_of, :])  # order[k]: the column eliminated k-th
    index_two = np.diff(sparse.csr_matrix(A[n:, n:]).indptr) == 0  # (rows with no algebraic entry)
    order = order[np.argsort(index_two[row_of[order]], kind="stable")]
    perm_c[n + order] = n + np.arange(m)
    perm_r[n + row_of[order]] = n + np.arange(m)
    return perm_r, perm_c


def _diagonal_order(B) -> np.ndarray:
    """The order SuperLU eliminates the square ``B``'s diagonal in, keeping it as the pivots (threshold 0)
    in a minimum-degree order of ``B + B^T``: ``order[k]`` is the index eliminated k-th.  A zero on the
    diagonal is made nonzero for the ordering alone (the growth check sees the real one)."""
    import scipy.sparse as sparse
    import scipy.sparse.linalg as splinalg

    B = sparse.csc_matrix(B, dtype=float)
    k = B.shape[0]
    pattern = sparse.csc_matrix((np.ones(B.nnz), B.indices, B.indptr), shape=B.shape) + sparse.eye(k) * (k + 1)
    options = {"SymmetricMode": True}
    lu = splinalg.splu(pattern.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options=options)
    return np.argsort(lu.perm_c)


class OverBudgetError(RuntimeError):
    """A pivot order's elimination beyond the multiply-adds it may take (:class:`StaticLU`'s
    ``max_flops``): its symbolic elimination stops there, as its cost in Python grows with them (5.5 s
    for static pivoting's order of reaction-diffusion at 1,000 unknowns, which no bound would take).
    Internal: the callers catch it and take no order from that elimination."""


class StaticLU:
    """The elimination pattern of ``sigma M - J`` for the Jacobian pattern ``(rows, cols)`` with a
    pivot order chosen at ``values`` (J's nonzeros) and step ``h`` (sigma = ``shift / h``); ``n``
    differential variables of ``D`` (M = diag(1 x n, 0 x m)).  ``pivoting`` (one of :data:`PIVOTING`):
    ``"partial"``, the order SuperLU picks (:func:`partial_order`), or ``"matched"``, static pivoting
    on a matching of large entries (:func:`matched_order`).  RuntimeError where the matrix is (structurally or
    exactly) singular at ``values``; :class:`OverBudgetError` (a RuntimeError: the callers take no order
    from either) where the elimination takes more than ``max_flops`` multiply-adds.

    Row i of the matrix is row ``perm_r[i]`` of the permuted one, column j its column ``perm_c[j]``
    (scipy's convention: ``Pr A Pc = L U``).
    """

    def __init__(
        self,
        rows: np.ndarray,
        cols: np.ndarray,
        n: int,
        D: int,
        values: np.ndarray,
        h: float,
        shift: float,
        pivoting: str = "partial",
        max_flops: float = math.inf,
    ):
        import scipy.sparse as sparse

        self.rows, self.cols, self.n, self.D, self.pivoting = rows, cols, n, D, pivoting
        M = sparse.diags(np.r_[np.ones(n), np.zeros(D - n)])
        A = (shift / h * M - sparse.csc_matrix((values, (rows, cols)), shape=(D, D))).tocsc()
        if pivoting == "matched":
            self.perm_r, self.perm_c = matched_order(A, n, shift / h)
        else:
            self.perm_r, self.perm_c = partial_order(A)
        # the permuted pattern, and the fill of elimination without further pivoting
        pattern = [set() for _ in range(D)]
        for i, j in zip(rows, cols, strict=True):
            pattern[self.perm_r[i]].add(int(self.perm_c[j]))
        for i in range(n):
            pattern[self.perm_r[i]].add(int(self.perm_c[i]))
        for k in range(D):
            pattern[k].add(k)  # (a structurally zero pivot is computed as 0: singular, SuperLU then names it)
        lower = [[] for _ in range(D)]  # lower[i]: columns k < i of L's row i
        rows_below = [[] for _ in range(D)]  # rows i > k with an entry in column k
        for i in range(D):
            for j in pattern[i]:
                if j < i:
                    rows_below[j].append(i)
        flops = 0  # (column k's rows below and its entries right of the pivot are complete when k is reached)
        for k in range(D):
            upper_k = [j for j in sorted(pattern[k]) if j > k]
            flops += len(rows_below[k]) * len(upper_k)
            if flops > max_flops:
                raise OverBudgetError(
                    f"{pivoting} pivoting's elimination takes more than {max_flops:.0f} multiply-adds"
                )
            for i in sorted(rows_below[k]):
                lower[i].append(k)
                for j in upper_k:
                    if j not in pattern[i]:
                        pattern[i].add(j)
                        if j < i:
                            rows_below[j].append(i)
        self.flops = flops
        self.lower = [sorted(columns) for columns in lower]
        self.below = [sorted(rows) for rows in rows_below]  # below[k]: the rows of L's column k
        self.upper = [sorted(j for j in pattern[k] if j >= k) for k in range(D)]
        self.L_size = sum(len(columns) for columns in self.lower)
        self.U_size = sum(len(columns) for columns in self.upper)
        self.entries = self.L_size + self.U_size

    def size(self, complex_: bool) -> int:
        """Entries of one system's packed factors: L's then U's nonzeros (real and imaginary parts)."""
        return (2 if complex_ else 1) * (self.L_size + self.U_size)

    # ---- building the SX expressions ----------------------------------------------------------
    def _entries(self, casadi, h, J, shift, complex_):
        """The permuted matrix ``shift / h M - J`` as {(row, col): value} (complex: (re, im))."""
        entries = {}
        for k, (i, j) in enumerate(zip(self.rows, self.cols, strict=True)):
            key = (int(self.perm_r[i]), int(self.perm_c[j]))
            entries[key] = entries.get(key, 0) - J[k]
        for i in range(self.n):
            key = (int(self.perm_r[i]), int(self.perm_c[i]))
            entries[key] = entries.get(key, 0) + shift.real / h
        if not complex_:
            return entries
        out = {key: (value, casadi.SX(0)) for key, value in entries.items()}
        for i in range(self.n):
            key = (int(self.perm_r[i]), int(self.perm_c[i]))
            out[key] = (out[key][0], out[key][1] + shift.imag / h)
        return out

    def factor_expressions(self, casadi, h, J, shift: complex, complex_: bool):
        """SX ``(packed factors, growth, smallest pivot)`` of ``shift / h M - J`` (complex arithmetic where
        ``complex_``); growth: the larger of max |L| and max |U| over max |matrix| (see the module
        docstring); a pivot of 0 with no entry below it leaves the factors finite, and only the solve
        would divide by it."""
        entries = self._entries(casadi, h, J, shift, complex_)
        zero = (casadi.SX(0), casadi.SX(0)) if complex_ else casadi.SX(0)
        A = [dict() for _ in range(self.D)]
        for (i, j), value in entries.items():
            A[i][j] = value
        L = [dict() for _ in range(self.D)]
        largest_matrix = _largest(casadi, [value for row in A for value in row.values()], complex_)
        for k in range(self.D):
            pivot = A[k].get(k, zero)
            upper_k = [j for j in self.upper[k] if j > k]
            for i in self.below[k]:
                factor = _div(A[i].get(k, zero), pivot, complex_)
                L[i][k] = factor
                for j in upper_k:
                    A[i][j] = _sub(A[i].get(j, zero), _mul(factor, A[k].get(j, zero), complex_), complex_)
        L_values = [L[i][k] for i in range(self.D) for k in self.lower[i]]
        U_values = [A[k].get(j, zero) for k in range(self.D) for j in self.upper[k]]
        growth = casadi.fmax(
            _largest(casadi, L_values, complex_) if L_values else casadi.SX(0),
            _largest(casadi, U_values, complex_) / casadi.fmax(largest_matrix, 1e-300),
        )
        pivots = [A[k].get(k, zero) for k in range(self.D)]
        smallest = _smallest(casadi, pivots, complex_)
        if complex_:
            packed = [v[0] for v in L_values] + [v[1] for v in L_values] + [v[0] for v in U_values]
            packed += [v[1] for v in U_values]
        else:
            packed = L_values + U_values
        return packed, growth, smallest

    def solve_function(self, complex_: bool):
        """casadi SX function of ``x`` solving ``A x = b`` from ``[packed factors, b]`` (complex: b and x
        as (re (D), im (D)))."""
        import casadi

        D = self.D
        factors = casadi.SX.sym("factors", self.size(complex_))
        b = casadi.SX.sym("b", (2 if complex_ else 1) * D)
        nL, nU = self.L_size, self.U_size
        if complex_:
            L_values = [(factors[q], factors[nL + q]) for q in range(nL)]
            U_values = [(factors[2 * nL + q], factors[2 * nL + nU + q]) for q in range(nU)]
            rhs = [(b[i], b[D + i]) for i in range(D)]
        else:
            L_values = [factors[q] for q in range(nL)]
            U_values = [factors[nL + q] for q in range(nU)]
            rhs = [b[i] for i in range(D)]
        inverse_r = np.empty(D, dtype=int)
        inverse_r[self.perm_r] = np.arange(D)
        y, q = [None] * D, 0
        for i in range(D):  # L y = Pr b (L unit lower)
            value = rhs[inverse_r[i]]
            for k in self.lower[i]:
                value = _sub(value, _mul(L_values[q], y[k], complex_), complex_)
                q += 1
            y[i] = value
        offsets = np.cumsum([0] + [len(columns) for columns in self.upper])
        x = [None] * D
        for i in reversed(range(D)):  # U x' = y
            value, diagonal = y[i], None
            for position, j in enumerate(self.upper[i]):
                u = U_values[offsets[i] + position]
                if j == i:
                    diagonal = u
                else:
                    value = _sub(value, _mul(u, x[j], complex_), complex_)
            x[i] = _div(value, diagonal, complex_)
        solution = [x[self.perm_c[k]] for k in range(D)]  # x = Pc x'
        if complex_:
            out = casadi.vertcat(*(v[0] for v in solution), *(v[1] for v in solution))
        else:
            out = casadi.vertcat(*solution)
        return casadi.Function("static_solve_complex" if complex_ else "static_solve", [factors, b], [out])


def _mul(a, b, complex_):
    if not complex_:
        return a * b
    return (a[0] * b[0] - a[1] * b[1], a[0] * b[1] + a[1] * b[0])


def _sub(a, b, complex_):
    if not complex_:
        return a - b
    return (a[0] - b[0], a[1] - b[1])


def _div(a, b, complex_):
    if not complex_:
        return a / b
    denominator = b[0] * b[0] + b[1] * b[1]
    return ((a[0] * b[0] + a[1] * b[1]) / denominator, (a[1] * b[0] - a[0] * b[1]) / denominator)


def _smallest(casadi, values, complex_):
    """min |value| over ``values`` (complex: of |re| + |im|, zero exactly where the value is)."""
    if complex_:
        values = [casadi.fabs(v[0]) + casadi.fabs(v[1]) for v in values]
    else:
        values = [casadi.fabs(v) for v in values]
    while len(values) > 1:
        pairs = range(0, len(values) - 1, 2)
        values = [casadi.fmin(values[i], values[i + 1]) for i in pairs] + values[len(values) - len(values) % 2 :]
    return values[0]


def _largest(casadi, values, complex_):
    """max |value| over ``values`` (a balanced tree of fmax; complex: max of |re|, |im|)."""
    if complex_:
        values = [casadi.fmax(casadi.fabs(v[0]), casadi.fabs(v[1])) for v in values]
    else:
        values = [casadi.fabs(v) for v in values]
    while len(values) > 1:
        values = [
            casadi.fmax(values[i], values[i + 1]) if i + 1 < len(values) else values[i]
            for i in range(0, len(values), 2)
        ]
    return values[0] if values else casadi.SX(0)


# ---- the model's pattern and the factors' size -------------------------------------------
def jacobian_pattern(compiled, stencil: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The rows and columns of the nonzeros of ``[f_y f_z; g_y g_z]`` (casadi's sparsity of the model's
    equations; no function is built), made once per model: :meth:`.CompiledDAE.casadi_jacobian_pattern`, or
    where the solve runs a repeated ``stencil`` (:mod:`.stencil`) the same from its templates' derivatives
    (:func:`daemodel.compiling.runs.runs_jacobian_layout`: the model's whole casadi graph is not made)."""
    if stencil:
        from daemodel.compiling.runs import runs_jacobian_layout

        layout = runs_jacobian_layout(compiled)
        if layout is not None:
            return layout[0], layout[1]
    return compiled.casadi_jacobian_pattern()


def unique_entries(rows: np.ndarray, cols: np.ndarray, n: int, D: int) -> int:
    """A lower bound of the entries of ``sigma M - J``'s LU factors, J of the pattern ``(rows, cols)``
    and ``D`` unknowns, ``n`` of them differential: the matrix's distinct entries (J's and M's), and at
    least the D pivots."""
    diagonal = np.arange(n, dtype=np.int64) * (D + 1)
    return max(D, int(sorted_unique(np.concatenate([rows.astype(np.int64) * D + cols, diagonal])).size))


def band_orders(compiled, rows: np.ndarray, cols: np.ndarray, n: int, D: int) -> BandOrder | None:
    """The band order of the model's sparse shifted systems (:func:`.linalg.band_order`, measured against
    the fill of :func:`.fill.factor_entries`), or None: made once per model.  Each trial factorisation
    stays within the memory limit: the fill's (:func:`.fill.measured_fill`, which :func:`.backend.memory_parts`
    made first in a solve; here at most one complex system's factors), and the band order's, skipped where
    the band's own bound on it (D times its band storage) would not fit."""
    from daemodel.files import memory_limit

    def build():
        most = memory_limit() / 16  # (without the solve's options: one complex system's factors, at least)
        fill = compiled.cached("radau-factor-entries", lambda: measured_fill(rows, cols, n, D, most))
        return band_order(rows, cols, n, D, fill, memory_limit() / TRIAL_BYTES_PER_ENTRY)

    return compiled.cached("radau-band-order", build)


def shifted_layout(compiled, rows: np.ndarray, cols: np.ndarray, n: int, band: list | None = None) -> tuple:
    """The CSC pattern of ``sigma M - J`` (J's entries at ``(rows, cols)``, M's diagonal over the ``n``
    differential unknowns of the model ``compiled``), in the model's band order where it has one
    (:func:`band_orders`: equation ``order.rows[k]`` is the k-th row, unknown ``order.columns[k]`` the k-th
    column): ``(order or None, (indices,
    indptr, nnz), where J's values go, where M's diagonal goes)``.  With ``band`` (a list: what the disk
    cache did is added to it) the order is its :class:`.band.BandKernel` where the band is narrow.  Made once per
    model and pattern (3 MB of a later solve at 10^5 unknowns, and the kernel's positions of J's and M's entries
    read from it: :meth:`.band.BandKernel.factor_shifted`); its arrays are read, never written."""
    made = []

    def build():
        made.append(True)
        return _shifted_layout(compiled, rows, cols, n, band)

    layout = compiled.cached(("radau-shifted-layout", band is not None), build, on=(rows, cols))
    if band is not None and not made and hasattr(layout[0], "factor_shifted"):  # (its kernel, made before)
        band.append("memory")
    return layout


def _shifted_layout(compiled, rows: np.ndarray, cols: np.ndarray, n: int, band: list | None) -> tuple:
    """:func:`shifted_layout`'s, made."""
    D = len(compiled.states) + len(compiled.algebraics)
    order = band_orders(compiled, rows, cols, n, D)
    # (equation k's row and unknown k's column)
    row_of, column_of = (np.arange(D),) * 2 if order is None else (np.argsort(order.rows), np.argsort(order.columns))
    rows, cols = row_of[rows], column_of[cols]
    keys_J = cols * D + rows  # CSC order: by column, then row
    keys_M = column_of[:n] * D + row_of[:n]
    keys = sorted_unique(np.concatenate([keys_J, keys_M]))  # (int64: D^2 passes 2^31 at 46,341 unknowns)
    # (held as int32, SuperLU's own index type, where every index fits, which it does below 2^31 entries:
    # half of the layout's 0.6 MB at 10^4 unknowns, and no copy of it at each factorisation)
    small = np.int32 if max(D, len(keys)) < np.iinfo(np.int32).max else np.int64
    indptr = np.searchsorted(keys // D, np.arange(D + 1)).astype(small)
    csc = ((keys % D).astype(small), indptr, len(keys))
    if band is not None:
        from daemodel.backends.radau.band import band_factors

        order = band_factors(compiled, order, csc, band)
    return order, csc, np.searchsorted(keys, keys_J).astype(small), np.searchsorted(keys, keys_M).astype(small)


def factor_shifts(values: np.ndarray, shifts, csc: tuple, pos_J: np.ndarray, pos_M: np.ndarray, order) -> tuple:
    """``sigma M - J`` factored for each of ``shifts`` (:func:`.linalg.sparse_lu`: SuperLU's factors, or the
    band kernel's where ``order`` is one), J's nonzeros ``values`` placed at ``pos_J`` and M's at ``pos_M`` of
    :func:`shifted_layout`'s ``csc`` = (indices, indptr, nnz): ``({sigma: factors}, singular (1,))``.  -J's
    entries are placed once for all the shifts (a scatter of 3 x 10^5 at 10^5 unknowns, 2 of 3 saved), each
    shift adds sigma at M's: the same values as placing both per shift."""
    import scipy.sparse as sparse

    indices, indptr, nnz = csc
    D = len(indptr) - 1
    if hasattr(order, "factor_shifted"):  # (a .band.BandKernel: -J and sigma placed by its C, no copies)

        def factor(sigma):
            return order.factor_shifted(values, sigma, pos_J, pos_M)

    else:
        minus_J = np.zeros(nnz)
        minus_J[pos_J] = -values

        def factor(sigma):
            real = sigma.imag == 0
            data = minus_J.copy() if real else minus_J.astype(complex)  # (freed before the next shift's are made)
            data[pos_M] += sigma.real if real else sigma
            return sparse_lu(sparse.csc_matrix((data, indices, indptr), shape=(D, D)), order)

    lu, singular = {}, None
    for sigma in shifts:
        lu[sigma], bad = factor(sigma)
        singular = bad if singular is None else singular | bad
    return lu, singular
    minus_J = np.zeros(nnz)
    minus_J[pos_J] = -values
    lu, singular = {}, None
    for sigma in shifts:
        real = sigma.imag == 0
        data = minus_J.copy() if real else minus_J.astype(complex)
        data[pos_M] += sigma.real if real else sigma
        lu[sigma], bad = sparse_lu(sparse.csc_matrix((data, indices, indptr), shape=(D, D)), order)
        del data  # (freed before the next shift's are made: two complex systems' values were 0.96 MB at 10^4)
        singular = bad if singular is None else singular | bad
    return lu, singular

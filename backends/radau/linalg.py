"""Dense and sparse factorisations of the casadi engine, and signs of determinants (scipy's LAPACK and SuperLU)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from daemodel.errors import DaemodelError

# casadi engine: factor the (n+m)-sized systems densely (LAPACK) up to this size, or above it when
# more than DENSE_FILL of the Jacobian is nonzero; sparse (SuperLU) otherwise.  Measured on this
# project's CPU: at 100 unknowns a dense LU of a 3 %-full matrix is ~0.1 ms, as SuperLU's overhead.
DENSE_MAX_SIZE, DENSE_FILL = 100, 0.2
# The band order is taken where its factors hold at most this many times COLAMD's entries: on the pattern's
# test values reaction-diffusion's are 1.005 times (600 unknowns) and 0.9999 (10^4), the chain of 200
# pendulums' 1.09, a 2-D grid's (30 x 30) 1.33; the memory guard's count (COLAMD's) stays within the
# "same order" its factors on their own values are of anyway.
BAND_FILL_RATIO = 1.1
# SuperLU's supernode relaxation and panel width for factors in the band order: a band a few entries wide has
# no wide supernodes, and its defaults' padding of the narrow ones cost more than it saved (reaction-diffusion,
# 10^5 unknowns: 17 and 18 ms for the real and complex factors against 27 and 48 with the defaults, 32 and
# 52 in COLAMD's order; the same entries)
BAND_RELAX, BAND_PANEL = 1, 1
# Breadth-first sweeps of the search for a component's peripheral node (each from the last node the one
# before reached; a chain, a 1-D grid and their leaves need 2) and the components beyond which the search
# is not made (one Python loop each): scipy's order is then taken as it is
PERIPHERAL_SWEEPS = 4
PERIPHERAL_MAX_COMPONENTS = 64


def dense_systems(D: int, nonzeros: int) -> bool:
    """Whether the casadi engine factors systems of ``D`` unknowns whose Jacobian has ``nonzeros``
    entries densely (LAPACK), else with SuperLU (:data:`DENSE_MAX_SIZE`, :data:`DENSE_FILL`)."""
    return D <= DENSE_MAX_SIZE or nonzeros > DENSE_FILL * D * D


@dataclass(frozen=True)
class BandOrder:
    """The rows' and columns' order of a band factorisation of ``sigma M - J`` (D unknowns): unknown
    ``columns[k]`` is the k-th column, equation ``rows[k]`` the k-th row.  They differ only where the
    constraints were declared in another order than the algebraic variables they determine
    (:func:`constraint_match`): ``rows = match[columns]``, ``match[u]`` the equation paired with unknown u
    (a differential unknown's own equation; None where every unknown keeps its own row)."""

    columns: np.ndarray
    match: np.ndarray | None = None

    @property
    def rows(self) -> np.ndarray:
        """``rows[k]``: the equation at the k-th row."""
        return self.columns if self.match is None else self.match[self.columns]

    def same(self, other: BandOrder) -> bool:
        """Whether ``other`` is the same order."""
        return np.array_equal(self.columns, other.columns) and np.array_equal(self.rows, other.rows)


def dense_inverse(matrix: np.ndarray, identity: np.ndarray) -> tuple:
    """``("inverse", matrix^-1)`` by LAPACK (``gesv`` on ``identity``, of the matrix's dtype), or
    ``("singular",)`` when it is singular or the inverse overflows."""
    from scipy.linalg import lapack

    gesv = lapack.zgesv if np.iscomplexobj(matrix) else lapack.dgesv
    _, _, inverse, info = gesv(matrix, identity)
    # (the sum is not finite when any entry is not, or when the entries are near overflow: singular enough)
    return ("inverse", inverse) if info == 0 and np.isfinite(inverse.sum()) else ("singular",)


def dense_lu(matrix: np.ndarray):
    """LAPACK's LU of a dense square matrix: ``(("dense", LU, pivots, getrs), singular (1,))``."""
    from scipy.linalg import lapack

    getrf, getrs = (lapack.zgetrf, lapack.zgetrs) if np.iscomplexobj(matrix) else (lapack.dgetrf, lapack.dgetrs)
    LU, piv, info = getrf(matrix, overwrite_a=True)
    return ("dense", LU, piv, getrs), np.array([info > 0 or not np.isfinite(LU).all()])


def sparse_lu(matrix, order: BandOrder | None = None):
    """SuperLU's factors of a sparse CSC matrix: ``(("sparse", lu), singular (1,))``.  With ``order``
    (:func:`band_order`) the matrix is already ``A[order.rows][:, order.columns]``, factored in that order (SuperLU's
    ``NATURAL``, no ordering of its own) and ``lu.solve`` solves with ``A`` (:class:`OrderedLU`); with a
    :class:`.band.BandKernel` for ``order``, by its band LU in C (:class:`.band.BandLU`, the same ``solve``)."""
    import scipy.sparse.linalg as splinalg

    if order is not None and not isinstance(order, BandOrder):  # (a .band.BandKernel, which imports this module:
        return order.factor(matrix.data)  # the band order's LU in C, the matrix's values all it reads)
    try:
        if order is not None:
            lu = splinalg.splu(matrix, permc_spec="NATURAL", relax=BAND_RELAX, panel_size=BAND_PANEL)
            return ("sparse", OrderedLU(lu, order)), np.array([False])
        return ("sparse", splinalg.splu(matrix)), np.array([False])
    except DaemodelError:  # (a time limit's signal, raised inside the call: not a singular system)
        raise
    except RuntimeError:  # SuperLU: "Factor is exactly singular"
        return ("singular",), np.array([True])


class OrderedLU:
    """SuperLU's factors of ``A[order.rows][:, order.columns]``, solving with ``A``: ``A x = b`` is
    ``A[rows][:, columns] x[columns] = b[rows]``."""

    def __init__(self, lu, order: BandOrder):
        self.lu, self.order = lu, order
        self._rows, self._columns = order.rows, order.columns

    @property
    def L(self):
        """The lower factor (SuperLU's, of the ordered matrix)."""
        return self.lu.L

    @property
    def U(self):
        """The upper factor (SuperLU's, of the ordered matrix)."""
        return self.lu.U

    def solve(self, rhs: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """``x`` with ``A x = rhs``, ``rhs`` of shape (D,); in ``out`` (of the solution's dtype) where given,
        which may be ``rhs`` itself (read first)."""
        y = self.lu.solve(rhs[self._rows])
        x = np.empty_like(y) if out is None else out
        if x.dtype != y.dtype or x.shape != y.shape:
            raise ValueError(f"a solve's out= is {x.dtype} {x.shape}, its solution {y.dtype} {y.shape}")
        x[self._columns] = y
        return x


def band_order(
    rows: np.ndarray, cols: np.ndarray, n: int, D: int, fill: int, max_entries: float = math.inf
) -> BandOrder | None:
    """The reverse Cuthill-McKee order of ``sigma M - J`` (J of the pattern ``(rows, cols)``, ``D``
    unknowns, ``n`` of them differential) where SuperLU's factors in that order hold at most
    :data:`BAND_FILL_RATIO` times ``fill`` entries (COLAMD's, :func:`.fill.factor_entries`), else None.

    On a banded pattern (a chain, a 1-D grid) the order keeps the factors within the band, and a
    factorisation in it skips SuperLU's own ordering (COLAMD) each time and pads no supernode
    (:data:`BAND_RELAX`): 2.3x faster on reaction-diffusion's pair of systems at 10^5 unknowns.
    Elsewhere (a 2-D grid: its band is ~sqrt(D) wide) COLAMD fills less, and the order is None; None too,
    untried, where the band's bound on its factors (D times :func:`band_storage`) is over ``max_entries``.

    Of scipy's order and :func:`peripheral_cuthill_mckee`'s, the one with the narrower band storage is
    taken: scipy starts each component at a node of least degree, which on reaction-diffusion's pattern
    (every w_k a leaf of the chain of c's) is a leaf in the middle of the chain, and two fronts walk out
    of it: band widths 4 and 4 in the declared order, 44 and 44 in a shuffled one (600 unknowns), where
    a start at the chain's end gives 2 and 2 in either.
    """
    import scipy.sparse as sparse
    import scipy.sparse.linalg as splinalg
    from scipy.sparse.csgraph import reverse_cuthill_mckee

    matrix = pattern_matrix(rows, cols, n, D)
    candidates, paired_rows = [], constraint_match(rows, cols, n, D)
    for match in (None,) if paired_rows is None else (None, paired_rows):
        paired = matrix if match is None else matrix[match]  # (row u: the equation paired with unknown u)
        graph = (abs(paired) + abs(paired).T).tocsr()
        peripheral = peripheral_cuthill_mckee(graph)
        if peripheral is not None:
            candidates.append(BandOrder(peripheral, match))
        if match is None:
            candidates.append(BandOrder(np.asarray(reverse_cuthill_mckee(graph, symmetric_mode=True), np.int64)))
    order = min(candidates, key=lambda o: band_storage(o, rows, cols))  # (the first of the narrowest)
    if D * band_storage(order, rows, cols) > max_entries:  # (its trial might not fit: the band bounds its fill)
        return None
    ordered = sparse.csc_matrix(matrix[order.rows][:, order.columns])
    try:
        lu = splinalg.splu(ordered, permc_spec="NATURAL")
    except DaemodelError:  # (a time limit's signal, raised inside the call: not a singular system)
        raise
    except RuntimeError:  # (structurally singular at these values: SuperLU's own order then)
        return None
    return order if lu.L.nnz + lu.U.nnz <= BAND_FILL_RATIO * fill else None


def peripheral_cuthill_mckee(graph) -> np.ndarray | None:
    """The reverse Cuthill-McKee order of the symmetric pattern ``graph`` (CSR, D x D) with each
    connected component started at a pseudo-peripheral node (George and Liu's search, simplified: up
    to :data:`PERIPHERAL_SWEEPS` breadth-first sweeps, each from the last node the one before reached),
    so that one front walks the component from its end; None where it has more than
    :data:`PERIPHERAL_MAX_COMPONENTS` components (their per-component loop runs in Python).

    Cuthill-McKee visits each node's neighbours by increasing degree: here every node is relabelled by
    its rank in (degree, index), so that scipy's breadth-first search, which follows the CSR's sorted
    columns, visits them in that order.  No step depends on the order the unknowns were declared in,
    beyond ties of degree."""
    import scipy.sparse as sparse
    from scipy.sparse.csgraph import breadth_first_order, connected_components

    D = graph.shape[0]
    rank = np.lexsort((np.arange(D), np.diff(graph.indptr)))  # (the node of rank k)
    relabelled = sparse.csr_matrix(graph[rank][:, rank])
    relabelled.sort_indices()
    count, component = connected_components(relabelled, directed=False)
    if count > PERIPHERAL_MAX_COMPONENTS:
        return None
    parts = []
    for start in np.unique(component, return_index=True)[1]:  # (each component's node of least rank)
        visit = breadth_first_order(relabelled, start, directed=False, return_predecessors=False)
        for _ in range(PERIPHERAL_SWEEPS):
            if visit[-1] == start:
                break
            start = visit[-1]
            visit = breadth_first_order(relabelled, start, directed=False, return_predecessors=False)
        parts.append(visit)
    return np.asarray(rank[np.concatenate(parts)[::-1]], dtype=np.int64)


def band_storage(order: BandOrder, rows: np.ndarray, cols: np.ndarray) -> int:
    """``2 kl + ku + 1``: the rows a band LU with partial pivoting stores of the pattern ``(rows,
    cols)`` (and M's diagonal) in ``order``."""
    offset = np.concatenate([np.argsort(order.rows)[rows] - np.argsort(order.columns)[cols], [0]])
    return 2 * max(int(offset.max()), 0) + max(int(-offset.min()), 0) + 1


def constraint_match(rows: np.ndarray, cols: np.ndarray, n: int, D: int) -> np.ndarray | None:
    """``match``: ``match[u]`` the equation paired with unknown ``u`` -- its own for the ``n`` differential
    unknowns, and for the algebraic ones a perfect matching of the constraints to them in ``g_z``'s
    pattern (scipy's Hopcroft-Karp) -- or None where ``g_z``'s diagonal is already full (each constraint
    sits on its own variable's row) or it has no perfect matching (an index-2 constraint: ``g_z``
    structurally singular).

    A banded system whose constraints were declared in another order than their variables has its
    constraint rows far from their variables' columns: no symmetric order of rows and columns together
    makes it narrow; paired first, it is the same band as in the declared order."""
    import scipy.sparse as sparse
    from scipy.sparse.csgraph import maximum_bipartite_matching

    m = D - n
    block = (rows >= n) & (cols >= n)
    if m == 0 or np.unique(rows[block & (rows == cols)]).size == m:
        return None
    g_z = sparse.csr_matrix((np.ones(int(block.sum())), (rows[block] - n, cols[block] - n)), shape=(m, m))
    paired = maximum_bipartite_matching(g_z, perm_type="row")  # (paired[j]: the constraint of variable j)
    if (paired < 0).any():
        return None
    return np.concatenate([np.arange(n), n + paired]).astype(np.int64)


def pattern_matrix(rows: np.ndarray, cols: np.ndarray, n: int, D: int):
    """``sigma M - J`` with J of the pattern ``(rows, cols)`` at values drawn once (uniform in
    [0.5, 1.5], seed 0) and sigma 2, as CSC: the matrix whose factors' fill the memory guard and
    :func:`band_order` measure."""
    import scipy.sparse as sparse

    values = np.random.default_rng(0).uniform(0.5, 1.5, rows.size)
    matrix = sparse.csc_matrix((values, (rows, cols)), shape=(D, D))
    return (matrix + sparse.diags(np.r_[np.full(n, 2.0), np.zeros(D - n)]).tocsc()).tocsc()


def small_sign_det(values: np.ndarray, m: int) -> float:
    """Sign of the determinant of the (m, m) matrix of ``values`` (column-major): by its formula up to
    m = 3 (a few Python operations, where a LAPACK call costs 7 us), else :func:`dense_sign_det`."""
    if m == 1:
        det = values[0]
    elif m == 2:
        det = values[0] * values[3] - values[1] * values[2]
    elif m == 3:
        a, b, c, d, e, f, g, h, i = values.tolist()  # columns (a, b, c), (d, e, f), (g, h, i)
        det = a * (e * i - f * h) - d * (b * i - c * h) + g * (b * f - c * e)
    else:
        return dense_sign_det(values.reshape(m, m, order="F"))
    return float(np.sign(det)) if math.isfinite(det) else 0.0


def dense_sign_det(matrix: np.ndarray) -> float:
    """Sign of the determinant of a dense square matrix (0 when singular or not finite): a triangular
    one's from its diagonal, exact where an LU's pivots may round to the wrong sign or to zero (LAPACK's
    partial pivoting on a badly scaled lower triangle: 7 of 20 random 100 x 100 ones), as the kernel's C
    (``dm_sign_of_det``) reads it; else from LAPACK's LU (numpy's slogdet costs 10 us of overhead on the
    few-element matrices of a step)."""
    from scipy.linalg import lapack

    if matrix.shape[0] == 0:
        return 1.0
    if not np.isfinite(matrix).all():
        return 0.0
    if not (np.triu(matrix, 1).any() and np.tril(matrix, -1).any()):
        diagonal = matrix.diagonal()
        if (diagonal == 0).any():
            return 0.0
        return -1.0 if np.count_nonzero(diagonal < 0) % 2 else 1.0
    LU, piv, info = lapack.dgetrf(matrix)
    diagonal = LU.diagonal()
    if info > 0 or not np.isfinite(diagonal).all():
        return 0.0
    swaps = int(np.count_nonzero(piv != np.arange(len(piv))))
    return float(np.prod(np.sign(diagonal))) * (-1.0 if swaps % 2 else 1.0)


def sparse_sign_det(matrix) -> float:
    """Sign of the determinant of a sparse square matrix (0 when singular or an entry is not finite, as
    :func:`dense_sign_det` and :func:`daemodel.compiling.determinants.sparse_sign`), from SuperLU's factors."""
    import scipy.sparse.linalg as splinalg

    from daemodel.compiling.determinants import triangular_sign

    if matrix.shape[0] == 0:
        return 1.0
    entries = matrix.tocoo()
    if not np.isfinite(entries.data).all():  # (an inf reached U's diagonal as a sign of +-1 before)
        return 0.0
    triangular = triangular_sign(entries.row, entries.col, entries.data, matrix.shape[0])
    if triangular is not None:  # (one side of the diagonal: its diagonal's sign, no LU)
        return triangular
    try:
        lu = splinalg.splu(matrix)
    except DaemodelError:  # (a time limit's signal, raised inside the call: not a singular system)
        raise
    except RuntimeError:
        return 0.0
    sign = float(np.prod(np.sign(lu.U.diagonal())))
    return sign * permutation_sign(lu.perm_r) * permutation_sign(lu.perm_c)


def z_block(rows: np.ndarray, cols: np.ndarray, n: int) -> tuple:
    """``(at, rows, cols)``: where J's nonzeros at ``(rows, cols)`` (unknowns y then z, n states) lie in its z block
    ``g_z``, and their places in it."""
    at = np.flatnonzero((rows >= n) & (cols >= n))
    index = np.int32 if max(len(rows), 1) <= np.iinfo(np.int32).max else np.int64
    return at.astype(index), (rows[at] - n).astype(index), (cols[at] - n).astype(index)


def block_sign_det(values: np.ndarray, rows: np.ndarray, cols: np.ndarray, m: int) -> float:
    """:func:`sparse_sign_det` of the (m, m) matrix of the nonzeros ``values`` at ``(rows, cols)`` (one a place):
    the same sign, without a sparse matrix where they lie on one side of the diagonal (:func:`triangular_sign`)."""
    from daemodel.compiling.determinants import triangular_sign

    if m == 0:
        return 1.0
    if not np.isfinite(values).all():
        return 0.0
    triangular = triangular_sign(rows, cols, values, m)
    if triangular is not None:
        return triangular
    import scipy.sparse as sparse

    return sparse_sign_det(sparse.csc_matrix((values, (rows, cols)), shape=(m, m)))


def permutation_sign(perm: np.ndarray) -> float:
    """+1 or -1: the parity of a permutation, from its cycles (counted vectorised,
    :func:`daemodel.compiling.determinants.odd_permutation`: a Python walk of the cycles took 35 ms a
    sign at 10^5 unknowns, twice per fresh Jacobian)."""
    from daemodel.compiling.determinants import odd_permutation

    return -1.0 if odd_permutation(perm) else 1.0


def sorted_unique(keys: np.ndarray) -> np.ndarray:
    """The distinct values of the integer array ``keys``, ascending: ``np.unique``'s result by a sort
    (numpy 2.4's ``np.unique`` hashes first: 2.8 s against 0.2 s for the 3 x 10^5 keys of a 10^5
    tridiagonal pattern on a loaded core)."""
    ordered = np.sort(keys, kind="stable")
    return ordered[np.r_[True, ordered[1:] != ordered[:-1]]] if ordered.size else ordered

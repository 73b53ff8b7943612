"""The signs of the determinants of many matrices given by their nonzeros: dense LU where the matrices
are small or full, sparse LU (SuperLU) where they are large and sparse.

The branch check after every solve (:func:`daemodel.compiling.initial_states.check_branch`) reads
``sign(det H_z)`` at every output time: at 10^4 unknowns a dense ``slogdet`` of the 5,000 x 5,000
algebraic Jacobian at each output cost 26 s of a solve whose integration took 0.36 s.
"""

from __future__ import annotations

import numpy as np

from daemodel.errors import DaemodelError

# Matrices of at least this order whose nonzeros fill at most SPARSE_MAX_DENSITY of them take the
# sparse LU: below it a dense one costs microseconds.
SPARSE_MIN_SIZE = 64
SPARSE_MAX_DENSITY = 0.1
# The dense path factors at most this many bytes of matrices at a time (a large batch of outputs
# would otherwise hold all of them at once).
DENSE_CHUNK_BYTES = 64 * 2**20


def sparse_enough(nnz: int, m: int) -> bool:
    """Whether (m, m) matrices with ``nnz`` nonzeros take the sparse LU."""
    return m >= SPARSE_MIN_SIZE and nnz <= SPARSE_MAX_DENSITY * m * m


def determinant_signs(rows: np.ndarray, cols: np.ndarray, values, m: int) -> np.ndarray:
    """``sign(det A_k)`` of the (m, m) matrices whose nonzeros at ``(rows, cols)`` are ``values[k]``
    (K, nnz), shape (K,): +1 or -1, 0 where ``A_k`` is singular or an entry is not finite.  Entries
    at one position add up (as in a sparse matrix), on both paths."""
    values = np.asarray(values, dtype=float)
    K = len(values)
    if m == 1 and len(rows) == 1:  # (one entry, the matrix: its sign, as an LU's; 0 where it is 0 or not finite)
        entry = values[:, 0]
        return np.sign(np.where(np.isfinite(entry), entry, 0.0))
    if not sparse_enough(len(rows), m):
        rows, cols = np.asarray(rows, dtype=np.int64), np.asarray(cols, dtype=np.int64)
        repeated = len(np.unique(rows * m + cols)) < len(rows)
        out = np.empty(K)
        chunk = max(1, DENSE_CHUNK_BYTES // (8 * m * m))
        for a in range(0, K, chunk):
            block = values[a : a + chunk]
            dense = np.zeros((len(block), m, m))
            if repeated:
                np.add.at(dense, (slice(None), rows, cols), block)
            else:
                dense[:, rows, cols] = block
            out[a : a + chunk] = dense_signs(dense)
        return out
    signs = triangular_signs(rows, cols, values, m)
    if signs is not None:
        return signs
    return np.array([sparse_sign(rows, cols, v, m) for v in values])


def dense_signs(J: np.ndarray) -> np.ndarray:
    """``sign(det J)`` per matrix of a stack (K, m, m), 0 where an entry is not finite."""
    finite = np.isfinite(J).all(axis=(1, 2))
    if finite.all():  # (the usual case: no copy of the finite ones)
        return np.linalg.slogdet(J)[0]
    out = np.zeros(len(J))
    if finite.any():
        out[finite] = np.linalg.slogdet(J[finite])[0]
    return out


def sparse_sign(rows: np.ndarray, cols: np.ndarray, values: np.ndarray, m: int) -> float:
    """``sign(det A)`` of one sparse (m, m) matrix by SuperLU: ``P_r A P_c = L U`` with unit ``L``, so
    the sign is that of ``prod(diag U)`` times the parities of both permutations; 0 where A is
    singular (SuperLU refuses it, or a pivot is 0) or an entry is not finite."""
    import scipy.sparse as sparse
    from scipy.sparse.linalg import splu

    if not np.isfinite(values).all():
        return 0.0
    triangular = triangular_sign(rows, cols, values, m)
    if triangular is not None:
        return triangular
    A = sparse.csc_matrix((values, (rows, cols)), shape=(m, m))
    try:
        lu = splu(A)
    except DaemodelError:  # (a time limit's signal, raised as the call returns: not a singular matrix)
        raise
    except RuntimeError:  # ("Factor is exactly singular")
        return 0.0
    diagonal = lu.U.diagonal()
    if not np.isfinite(diagonal).all() or (diagonal == 0).any():
        return 0.0
    negative = int(np.count_nonzero(diagonal < 0)) + odd_permutation(lu.perm_r) + odd_permutation(lu.perm_c)
    return -1.0 if negative % 2 else 1.0


# Diagonal entries :func:`triangular_signs` reads at once (32 kB): one matrix at a time at 10^4 unknowns, a
# batch's small matrices many at a time
SIGN_CHUNK_ENTRIES = 4096


def triangular_sign(rows: np.ndarray, cols: np.ndarray, values: np.ndarray, m: int) -> float | None:
    """``sign(det A)`` of an (m, m) matrix whose nonzeros ``values`` (finite) at ``(rows, cols)`` lie on one
    side of the diagonal, from its diagonal alone (0 where an entry of it is 0), or None where they lie
    on both: a diagonal g_z (each constraint explicit in its own variable, as reaction-diffusion's) skips
    SuperLU (6-30 ms a sign at 5 x 10^4, 13 signs a solve at 10^5 unknowns).  One matrix of
    :func:`triangular_signs`."""
    signs = triangular_signs(rows, cols, np.asarray(values, dtype=float)[None], m)
    return None if signs is None else float(signs[0])


def triangular_signs(rows: np.ndarray, cols: np.ndarray, values: np.ndarray, m: int) -> np.ndarray | None:
    """``sign(det A_k)`` of the triangular matrices whose nonzeros at ``(rows, cols)`` are the rows of ``values``
    (K, nnz), all at once, (K,) (see :func:`triangular_sign`), 0 where a row holds
    an entry that is not finite; None where the nonzeros lie on both sides of the diagonal.  The
    branch check reads one sign per output time: at 200 unknowns one call per output was 0.3 ms of
    a 1.5 ms solve (21 outputs)."""
    rows, cols = np.asarray(rows, dtype=np.intp), np.asarray(cols, dtype=np.intp)  # (np.bincount: ints, [] too)
    if not ((rows >= cols).all() or (rows <= cols).all()):
        return None
    values = np.asarray(values, dtype=float)
    on = np.flatnonzero(rows == cols)
    if np.bincount(rows[on], minlength=1).max() <= 1:  # (no repeats; np.unique hashes: 4.5 ms at 5 x 10^4)
        # the matrices' diagonals read SIGN_CHUNK_ENTRIES at a time (a (K, m) copy of them all was 0.44 MB of a
        # first solve's peak at 10^4 unknowns and 11 outputs; one row at a time, a Python loop over a batch's
        # every sample and output); a diagonal entry without a nonzero is a zero
        signs = np.zeros(len(values))
        if len(on) < m:
            return signs
        step = max(1, SIGN_CHUNK_ENTRIES // max(m, 1))
        for first in range(0, len(values), step):
            part = values[first : first + step]
            diagonal = part[:, on]
            negative = np.count_nonzero(diagonal < 0, axis=1)
            fine = (diagonal != 0).all(axis=1) & np.isfinite(part).all(axis=1)
            signs[first : first + step] = np.where(fine, np.where(negative % 2, -1.0, 1.0), 0.0)
        return signs
    diagonal = np.zeros((len(values), m))
    np.add.at(diagonal, (slice(None), rows[on]), values[:, on])  # (repeats add)
    negative = np.count_nonzero(diagonal < 0, axis=1)
    signs = np.where(negative % 2, -1.0, 1.0)
    signs[(diagonal == 0).any(axis=1) | ~np.isfinite(values).all(axis=1)] = 0.0
    return signs


def odd_permutation(perm: np.ndarray) -> int:
    """1 where the permutation ``perm`` (of 0..n-1) is odd, else 0: n minus its number of cycles, mod 2.

    The cycles are counted by pointer doubling (each index learns the least index of its cycle in
    at most log2(n) vectorised passes), not by a Python loop over the indices.  A pass that changes no
    index's least stops it: after k passes each index holds the least of the 2^k indices from it along
    its cycle, and where doubling the window changes none, those windows' least is the same all along
    the cycle, so its own (SuperLU's row orders are near the identity: 1 pass where 17 were taken, 43 ms
    each time at 5 x 10^4 on a loaded machine, 22 times per solve's branch check)."""
    perm = np.asarray(perm, dtype=np.int64)
    n = len(perm)
    least, step = np.arange(n), perm.copy()
    for _ in range(max(1, int(n).bit_length())):
        longer = np.minimum(least, least[step])
        if np.array_equal(longer, least):
            break
        least, step = longer, step[step]
    cycles = int(np.count_nonzero(least == np.arange(n)))
    return (n - cycles) % 2


# A Householder QR's sign of det A is taken where its smallest |R_cc| is above this fraction of its largest; below,
# A may lie within rounding of a singular matrix, where the QR's sign and an LU's may differ (an LU of an exactly
# singular matrix reads 0, which the branch check never counts as a change; the QR's R_cc reads rounding there):
# such matrices' signs are left to :func:`determinant_signs` (:func:`householder_sign`'s NaN).
HOUSEHOLDER_SURE_RATIO = 1e-8
# ... and where every R_cc lies within these bounds: casadi's ``beta = -1 / (R_cc v_c0)`` of a true reflection reads
# +0, as the identity's, where the product overflows, and a column's squares below the diagonal sum to 0 where they
# underflow (there the reflection is skipped).
HOUSEHOLDER_RANGE = (1e-150, 1e150)


def householder_sign(casadi, matrix, beta, diagonal, parity: int):
    """``sign(det A)`` of the matrix ``matrix`` (m, m) from casadi's sparse Householder QR of it
    (``casadi.qr_sparse``: ``A = P_r^T Q R P_c``, ``Q`` the product of the reflections ``I - beta_c v_c v_c^T``), as
    a casadi expression of its ``beta`` (m,) and ``R``'s diagonal ``diagonal`` (m,), ``parity`` that of ``P_r``
    times that of ``P_c`` (+1 or -1): -1, +1, or NaN where the QR cannot tell (the caller reads those by
    :func:`determinant_signs`).

    casadi's reflection of column c (``casadi_house``) makes ``R_cc = |column| >= 0``; it is a true reflection
    (determinant -1, ``beta_c = -1 / (R_cc v_c0) > 0``) except where the column below the diagonal is exactly
    zero and its diagonal entry positive (the identity, ``beta_c = 0``).  So ``sign(det A) = parity
    (-1)^#(beta > 0)`` where every ``R_cc > 0``.  NaN where a nonzero of ``matrix`` or ``R_cc`` is not finite, the
    smallest ``R_cc`` is at most :data:`HOUSEHOLDER_SURE_RATIO` times the largest, or one lies outside
    :data:`HOUSEHOLDER_RANGE`."""
    m = diagonal.numel()
    flips = sum((beta[i] > 0 for i in range(1, m)), beta[0] > 0)
    least, largest = diagonal[0], diagonal[0]
    for i in range(1, m):
        least, largest = casadi.fmin(least, diagonal[i]), casadi.fmax(largest, diagonal[i])
    # (a sum is not finite where a term is not, which casadi's fmin and fmax pass over, and which may leave R's
    # diagonal finite; |x| < inf where x is finite)
    total = casadi.sum1(casadi.vec(matrix.nz[:])) + casadi.sum1(diagonal)
    sure = casadi.logic_and(least > casadi.fmax(HOUSEHOLDER_SURE_RATIO * largest, HOUSEHOLDER_RANGE[0]),
                            casadi.logic_and(largest < HOUSEHOLDER_RANGE[1], casadi.fabs(total) < np.inf))  # fmt: skip
    return casadi.if_else(sure, parity * (1 - 2 * casadi.fmod(flips, 2)), np.nan)

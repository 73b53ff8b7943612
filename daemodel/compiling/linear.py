"""The linear algebra of the algebraic Newton: Jacobian stacks solved dense or sparse.

Small systems are dense stacks ``(B, m, m)``: :func:`least_squares`, block by block where the
pattern splits (:func:`square_blocks`).  From :data:`SPARSE_MIN_SIZE` unknowns on, a Jacobian is a
:class:`SparseStack` (its structural nonzeros only): a sparse LU per sample for Newton's step,
``|J| |x|`` as a sparse product, and the rank judged by the LU and a condition estimate, so that no
dense ``m x m`` array is ever made where m is large.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.sparse
import scipy.sparse.csgraph
import scipy.sparse.linalg

from daemodel.errors import DaemodelError

# Iteration matrices of at least this size are split into their independent square blocks for
# the rank check and Newton's dense linear solves: a dense SVD or LU is O(m^3), the blocks of a
# sparse system cost next to nothing.  Smaller ones are factored whole (microseconds either way).
BLOCK_MIN_SIZE = 16
# From this many algebraic unknowns on, Newton's Jacobian is a SparseStack.  Measured on the
# reaction-diffusion grid (solve_algebraic from zero, one sample and 16): the dense path (its
# (B, m, m) scatter, block split and solves) and the per-sample sparse LU are even at m ~ 100-150
# (1.2 vs 1.3 ms at m = 50, 3.2 vs 2.3 ms at 200, 30 vs 18 ms at 1,000; 16 samples: 1.9 vs 7.4 ms at
# 50, 302 vs 43 ms at 1,000), and the dense one grows as m^2 in memory; below it the dense path
# keeps today's bits.
SPARSE_MIN_SIZE = 200
# A singular sparse Jacobian up to this size gets the dense pseudo-inverse step (the dense
# path's step, 32 MB at most); larger ones a least-squares step by LSQR.
DENSE_FALLBACK_MAX = 2000
# LSQR's stopping tolerances and iteration cap (times m) for the step of a large singular J:
# the step of a Newton that is reported as failed, so a modest accuracy suffices.
LSQR_TOL, LSQR_ITERATIONS = 1e-12, 4


def square_blocks(pattern) -> list[tuple[np.ndarray, np.ndarray]] | None:
    """The independent diagonal blocks of a square matrix with nonzero ``pattern``, grouped by size.

    Rows and columns are linked where an entry is nonzero; each connected set of rows and
    columns is one block, and the matrix is block diagonal after permuting them.

    Parameters
    ----------
    pattern : ndarray of bool, shape (m, m), or scipy.sparse matrix (m, m)
        The nonzeros (of a sparse matrix: its stored entries).

    Returns
    -------
    list of (rows, cols), or None
        For each block size k, ``rows`` and ``cols`` of shape (blocks, k): the row and column
        indices of every block of that size.  None when a block is not square (then the matrix
        is singular, whatever its values).
    """
    m = pattern.shape[0]
    if scipy.sparse.issparse(pattern):
        coo = pattern.tocoo()
        i, j = coo.row, coo.col
    else:
        i, j = np.nonzero(pattern)
    graph = scipy.sparse.coo_matrix((np.ones(len(i)), (i, m + j)), shape=(2 * m, 2 * m))
    _, labels = scipy.sparse.csgraph.connected_components(graph, directed=False)
    row_labels, col_labels = labels[:m], labels[m:]
    row_order, col_order = np.argsort(row_labels, kind="stable"), np.argsort(col_labels, kind="stable")
    row_counts = np.bincount(row_labels, minlength=labels.max() + 1)
    col_counts = np.bincount(col_labels, minlength=labels.max() + 1)
    if not np.array_equal(row_counts, col_counts):
        return None
    # blocks of one size side by side: rows sorted by label, then split into equal chunks
    starts = np.concatenate([[0], np.cumsum(row_counts)[:-1]])
    groups = []
    for k in np.unique(row_counts[row_counts > 0]):
        first = starts[row_counts == k]
        take = first[:, None] + np.arange(k)[None, :]
        groups.append((row_order[take], col_order[take]))
    return groups


def least_squares(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Least-squares solutions of ``A[i] x = b[i]`` for a dense stack; finite garbage never arises
    from a singular A (the pseudo-inverse's minimum-norm step is used).  Large systems with
    independent blocks are solved block by block (:func:`square_blocks`)."""
    if A.shape[-1] >= BLOCK_MIN_SIZE:
        out = block_solve(A, b)
        if out is not None:
            return out
    try:
        out = np.linalg.solve(A, b[..., None])[..., 0]
        if np.isfinite(out).all():
            return out
    except np.linalg.LinAlgError:
        pass
    return np.einsum("bij,bj->bi", np.linalg.pinv(A), b)


def block_solve(A: np.ndarray, b: np.ndarray) -> np.ndarray | None:
    """``A[i] x = b[i]`` solved on the independent blocks of the stack's joint nonzero pattern;
    None where a block is not square, singular or gives a non-finite solution (the caller then
    takes the whole-matrix path)."""
    groups = square_blocks((A != 0).any(axis=0))
    if groups is None:
        return None
    out = np.empty_like(b)
    try:
        for rows, cols in groups:
            blocks = A[:, rows[:, :, None], cols[:, None, :]]  # (B, blocks, k, k)
            out[:, cols] = np.linalg.solve(blocks, b[:, rows][..., None])[..., 0]
    except np.linalg.LinAlgError:
        return None
    return out if np.isfinite(out).all() else None


def factor(A) -> tuple[scipy.sparse.linalg.SuperLU | None, float]:
    """``(LU, condition)``: the sparse LU of a square matrix and an estimate of its 1-norm condition
    number ``|A|_1 |A^-1|_1`` (Hager-Higham's, from a few solves with the factors); ``(None, inf)``
    where the factorisation meets an exactly zero pivot or the matrix is not finite.

    The 1-norm condition is within a factor m of the 2-norm one that a dense rank check reads.
    """
    A = scipy.sparse.csc_matrix(A)
    m = A.shape[0]
    if m == 0:
        return None, 1.0
    if not np.isfinite(A.data).all():
        return None, np.inf
    try:
        lu = scipy.sparse.linalg.splu(A)
    except DaemodelError:  # (a time limit's signal, raised as the call returns: not a singular matrix)
        raise
    except RuntimeError:  # "Factor is exactly singular"
        return None, np.inf
    norm = abs(A).sum(axis=0).max()
    if norm == 0:
        return lu, np.inf
    with np.errstate(all="ignore"):
        inverse = scipy.sparse.linalg.LinearOperator(
            (m, m), matvec=lu.solve, rmatvec=lambda v: lu.solve(np.asarray(v, dtype=float), trans="T"), dtype=float
        )
        estimate = scipy.sparse.linalg.onenormest(inverse) if m > 1 else abs(1 / lu.U.diagonal()[0])
    condition = float(norm * estimate)
    return lu, condition if np.isfinite(condition) else np.inf


@dataclass(frozen=True)
class SparseStack:
    """B square Jacobians of one sparsity pattern, stored by their structural nonzeros.

    Attributes
    ----------
    rows, cols : ndarray of int, shape (nnz,)
        The positions of the nonzeros (each at most once).
    values : ndarray, shape (B, nnz)
    size : int
        m: the matrices are m x m.
    """

    rows: np.ndarray
    cols: np.ndarray
    values: np.ndarray
    size: int

    def __len__(self) -> int:
        return len(self.values)

    @cached_property
    def _csc(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(order, indices, indptr)``: a sample's values in column-major order make its CSC matrix."""
        order = np.lexsort((self.rows, self.cols))
        indptr = np.concatenate([[0], np.cumsum(np.bincount(self.cols, minlength=self.size))])
        return order, self.rows[order], indptr

    def take(self, index) -> SparseStack:
        """The samples ``index`` (a slice, indices or a boolean mask) as a stack."""
        return SparseStack(self.rows, self.cols, self.values[index], self.size)

    def matrix(self, b: int) -> scipy.sparse.csc_matrix:
        """Sample ``b`` as a CSC matrix (m, m)."""
        order, indices, indptr = self._csc
        return scipy.sparse.csc_matrix((self.values[b][order], indices, indptr), shape=(self.size, self.size))

    def dense(self) -> np.ndarray:
        """The stack as a dense array (B, m, m): for small m only."""
        out = np.zeros((len(self), self.size, self.size))
        out[:, self.rows, self.cols] = self.values
        return out

    def finite(self) -> np.ndarray:
        """``(B,)`` whether every entry of a sample is finite."""
        return np.isfinite(self.values).all(axis=1)

    def abs_product(self, x: np.ndarray) -> np.ndarray:
        """``|J| |x|`` of every sample, shape (B, m), for ``x`` (B, m)."""
        gather = scipy.sparse.csr_matrix(
            (np.ones(len(self.rows)), (self.rows, np.arange(len(self.rows)))), shape=(self.size, len(self.rows))
        )
        return np.asarray(gather @ (np.abs(self.values) * np.abs(x[:, self.cols])).T).T

    def solve(self, b: np.ndarray) -> np.ndarray:
        """Least-squares solutions of ``J[i] x = b[i]``, shape (B, m), as :func:`least_squares` for
        dense stacks: the LU's solution where it is finite; else the pseudo-inverse's minimum-norm
        solution (up to :data:`DENSE_FALLBACK_MAX` unknowns) or LSQR's (above)."""
        out = np.empty_like(b, dtype=float)
        for k in range(len(self)):
            A = self.matrix(k)
            x = None
            with np.errstate(all="ignore"):
                try:
                    x = scipy.sparse.linalg.splu(A).solve(b[k])
                except DaemodelError:  # (a time limit's signal, raised as the call returns: not a singular matrix)
                    raise
                except RuntimeError:  # an exactly zero pivot
                    pass
                if x is None or not np.isfinite(x).all():
                    if self.size <= DENSE_FALLBACK_MAX:
                        x = np.linalg.pinv(A.toarray()) @ b[k]
                    else:
                        x = scipy.sparse.linalg.lsqr(
                            A, b[k], atol=LSQR_TOL, btol=LSQR_TOL, iter_lim=LSQR_ITERATIONS * self.size
                        )[0]
            out[k] = x
        return out

    def singular(self) -> np.ndarray:
        """``(B,)`` numerically singular samples, with ``np.linalg.matrix_rank``'s threshold: a
        condition number above ``1 / (m eps)`` (the 1-norm estimate of :func:`factor`)."""
        limit = 1 / (self.size * np.finfo(float).eps)
        return np.array([factor(self.matrix(k))[1] > limit for k in range(len(self))], dtype=bool)

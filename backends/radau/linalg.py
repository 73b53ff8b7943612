"""Dense and sparse factorisations of the casadi engine, and signs of determinants (scipy's LAPACK and SuperLU)."""

from __future__ import annotations

import math

import numpy as np

from daemodel.errors import DaemodelError


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


def sparse_lu(matrix):
    """SuperLU's factors of a sparse CSC matrix: ``(("sparse", lu), singular (1,))``."""
    import scipy.sparse.linalg as splinalg

    try:
        return ("sparse", splinalg.splu(matrix)), np.array([False])
    except DaemodelError:  # (a time limit's signal, raised inside the call: not a singular system)
        raise
    except RuntimeError:  # SuperLU: "Factor is exactly singular"
        return ("singular",), np.array([True])


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
    """Sign of the determinant of a dense square matrix (0 when singular or not finite), from LAPACK's LU
    (numpy's slogdet costs 10 us of overhead on the few-element matrices of a step)."""
    from scipy.linalg import lapack

    if matrix.shape[0] == 0:
        return 1.0
    LU, piv, info = lapack.dgetrf(matrix)
    diagonal = LU.diagonal()
    if info > 0 or not np.isfinite(diagonal).all():
        return 0.0
    swaps = int(np.count_nonzero(piv != np.arange(len(piv))))
    return float(np.prod(np.sign(diagonal))) * (-1.0 if swaps % 2 else 1.0)


def sparse_sign_det(matrix) -> float:
    """Sign of the determinant of a sparse square matrix (0 when singular), from SuperLU's factors."""
    import scipy.sparse.linalg as splinalg

    if matrix.shape[0] == 0:
        return 1.0
    try:
        lu = splinalg.splu(matrix)
    except DaemodelError:  # (a time limit's signal, raised inside the call: not a singular system)
        raise
    except RuntimeError:
        return 0.0
    sign = float(np.prod(np.sign(lu.U.diagonal())))
    return sign * permutation_sign(lu.perm_r) * permutation_sign(lu.perm_c)


def permutation_sign(perm: np.ndarray) -> float:
    """+1 or -1: the parity of a permutation, from its cycles."""
    seen = np.zeros(len(perm), dtype=bool)
    transpositions = 0
    for start in range(len(perm)):
        length = 0
        k = start
        while not seen[k]:
            seen[k] = True
            k = perm[k]
            length += 1
        transpositions += max(length - 1, 0)
    return -1.0 if transpositions % 2 else 1.0

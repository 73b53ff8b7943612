"""The Radau IIA tableau in RADAU5's form: ``A^-1 = T Lambda T^-1`` and the embedded error estimate.

With one Jacobian ``J`` per step, the Newton matrix of the s stages, ``(h A)^-1 (x) M - I (x) J``
with ``M = diag(I, 0)``, is block-diagonalised by ``A^-1 = T Lambda T^-1`` into one real system
``(gamma / h) M - J`` per real eigenvalue and one complex system ``((alpha + i beta) / h) M - J``
per complex pair, each of size n + m (Hairer & Wanner, Solving ODEs II, IV.8): for s = 3, one real
and one complex LU of size n + m instead of one real LU of size 3(n + m), about five times less work.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

# T Lambda T^-1 must reproduce A^-1 to this relative accuracy (float64 eigenvectors of A^-1).
TRANSFORM_CHECK = 1e-12


@dataclass(frozen=True, eq=False)
class StageTransform:
    """``A^-1 = T Lambda T^-1`` with ``Lambda`` real block-diagonal, and the shifts of the blocks.

    Attributes
    ----------
    T, T_inv, T_inv_A_inv : ndarray (s, s)
    blocks : tuple of (k, eigenvalue)
        Real eigenvalue ``gamma``: stage k of the transformed system alone.  Complex
        ``alpha + i beta`` (beta > 0): stages k, k+1 as one complex system.
    gamma0 : float
        The error estimate's ``gamma0`` (:func:`~daemodel.backends.radau.embedded_weights`); its
        matrix is ``(1 / (h gamma0)) M - J``, the real block itself when s is odd.
    """

    T: np.ndarray
    T_inv: np.ndarray
    T_inv_A_inv: np.ndarray
    blocks: tuple
    gamma0: float

    @classmethod
    def of(cls, A: np.ndarray, gamma0: float) -> StageTransform:
        A_inv = np.linalg.inv(A)
        eig, vectors = np.linalg.eig(A_inv)
        columns, blocks, diagonal = [], [], []
        for lam, v in sorted(zip(eig, vectors.T, strict=True), key=lambda pair: (pair[0].real, pair[0].imag)):
            if abs(lam.imag) < 1e-12:
                blocks.append((len(columns), complex(lam.real)))
                columns.append(v.real / np.linalg.norm(v.real))
                diagonal.append(np.array([[lam.real]]))
            elif lam.imag > 0:  # its conjugate gives the same pair
                blocks.append((len(columns), complex(lam)))
                columns += [v.real, -v.imag]  # A^-1 [vr, -vi] = [vr, -vi] [[alpha, -beta], [beta, alpha]]
                diagonal.append(np.array([[lam.real, -lam.imag], [lam.imag, lam.real]]))
        T = np.array(columns).T
        T_inv = np.linalg.inv(T)
        Lam = np.zeros_like(A_inv)
        k = 0
        for d in diagonal:
            Lam[k : k + len(d), k : k + len(d)] = d
            k += len(d)
        if np.abs(T @ Lam @ T_inv - A_inv).max() > TRANSFORM_CHECK * np.abs(A_inv).max():
            raise ArithmeticError("radau: the eigen-decomposition of A^-1 is inaccurate")  # daemodel's own bug
        return cls(T=T, T_inv=T_inv, T_inv_A_inv=T_inv @ A_inv, blocks=tuple(blocks), gamma0=gamma0)

    @functools.cached_property
    def error_block(self) -> int | None:
        """Which block's system is the error estimate's (the real one when s is odd), or None."""
        error = 1.0 / self.gamma0
        return next((i for i, (_, lam) in enumerate(self.blocks) if abs(lam - error) <= 1e-12 * error), None)

    def shifts(self, h: float) -> tuple:
        """The shifts ``sigma`` of every ``sigma M - J`` to factor for step ``h``: the blocks',
        then the error estimate's where it is no block's (s even)."""
        out = tuple(lam / h for _, lam in self.blocks)
        return out if self.error_block is not None else (*out, complex(1.0 / (h * self.gamma0)))

    def error_shift(self, shifts: tuple) -> complex:
        """The error estimate's shift among ``shifts`` (of :meth:`shifts`)."""
        return shifts[self.error_block] if self.error_block is not None else shifts[-1]


def stage_transform(tableau) -> StageTransform:
    """:meth:`StageTransform.of` the tableau's ``A`` and its error estimate's ``gamma0``, made once per tableau
    (a tableau compares by identity; :func:`daemodel.tableau.radau_iia` keeps one per s): its
    eigen-decompositions cost ~0.4 ms a solve, 2,700 times in the wheelset's events' trial solves."""
    return _stage_transform(tableau)


@functools.cache
def _stage_transform(tableau) -> StageTransform:
    return StageTransform.of(tableau.A, embedded_weights(tableau)[0])


def embedded_weights(tableau) -> tuple[float, np.ndarray]:
    """``(gamma0, bhat - b)`` of the order-s error estimate (made once per tableau; the array a copy).

    ``gamma0`` is A's real eigenvalue (s odd, as in RADAU5 and Hairer-Wanner's RADAU); for even
    s, A has no real eigenvalue and ``det(A)^(1/s)`` (the geometric mean of their moduli) is used.
    ``bhat`` solves ``gamma0 * 0^(k-1) + sum_i bhat_i c_i^(k-1) = 1/k`` for k = 1..s.
    """
    gamma0, weights = _embedded_weights(tableau)
    return gamma0, weights.copy()


@functools.cache
def _embedded_weights(tableau) -> tuple[float, np.ndarray]:
    s, c = tableau.stages, tableau.c
    eig = np.linalg.eigvals(tableau.A)
    real = eig[np.abs(eig.imag) < 1e-12].real
    gamma0 = float(real.max()) if real.size else float(abs(np.linalg.det(tableau.A)) ** (1 / s))
    V = np.vander(c, s, increasing=True).T  # V[k, i] = c_i^k
    rhs = 1.0 / np.arange(1, s + 1)
    rhs[0] -= gamma0
    return gamma0, np.linalg.solve(V, rhs) - tableau.b


class IncrementBuffers:
    """Newton's increment through the transformed systems for one sample on numpy, in buffers made
    once per engine: the operations of :meth:`.engines.AbstractEngine._newton_increment` one by one,
    so the same bits, without its temporaries (at 10^5 unknowns and s = 5 each iteration allocated
    ~25 MB, whose first touch was ~460 page faults an iteration, 70 % of a solve's).

    ``R (1, s, D)``; ``solve(lu, rhs (1, D), out=)`` the engine's (its solution in ``out``); ``arrays`` its
    (T, T^-1, T^-1 A^-1).  A call returns the increment in a buffer of its own, which the next call overwrites
    (Newton adds it to its stage values before it asks for the next: a new array an iteration was 0.4 MB of the
    solve's peak at 10^4 unknowns, s = 5), or ``over`` R: the engine's residual buffer, C-contiguous float64,
    which the next evaluation overwrites anyway (:meth:`.engines.AbstractEngine.newton_step`'s: its own buffer,
    never made then, was 4 MB of a later solve's peak at 10^5 unknowns, s = 5)."""

    def __init__(self, transform: StageTransform, n: int, D: int):
        self.transform, self.n = transform, n
        self.rhs = np.empty((1, len(transform.T), D))
        self._out = None

    @property
    def scratch(self) -> np.ndarray:
        """An array of the increment's shape (1, s, D) that a caller may overwrite between two calls: the
        right-hand sides' buffer, whose values a call has read (Newton squares the increment's scaled
        entries in it: a temporary of 0.4 MB an iteration at 10^4 unknowns, s = 5)."""
        return self.rhs

    def __call__(self, factors, R: np.ndarray, solve, arrays, over: bool = False) -> np.ndarray:
        T, T_inv, T_inv_A_inv = arrays
        n, rhs, h = self.n, self.rhs, factors.h
        if over and (R.shape != rhs.shape or R.dtype != rhs.dtype or not (R.flags.c_contiguous and R.flags.writeable)):
            raise ValueError(
                f"the increment is written over a writable C-contiguous residual {rhs.shape}, got {R.shape}"
            )
        if not over and self._out is None:
            self._out = np.empty_like(rhs)
        out = R if over else self._out
        # (h A)^-1 on the F rows, -1 on the G rows: the system becomes ((h A)^-1 (x) M - I (x) J) dU = rhs
        np.matmul(T_inv_A_inv, R[..., :n], out=rhs[..., :n])
        np.multiply(rhs[..., :n], -1.0 / h, out=rhs[..., :n])
        np.matmul(T_inv, R[..., n:], out=rhs[..., n:])
        # (R read: a complex system's right-hand side in out's first 2 D entries, the increment in it at the end; a
        # complex block has s >= 2.  Each system's solution in its right-hand side's place, which the solve reads
        # first: a new array a system was 108 arrays of 0.8-1.6 MB a solve at 10^5 unknowns, s = 5)
        for (k, lam), shift in zip(self.transform.blocks, factors.shifts, strict=False):
            lu = factors.lu[shift]
            if lam.imag == 0:
                solve(lu, rhs[:, k], out=rhs[:, k])
            else:  # (rhs_k + 1j rhs_k+1, as the temporaries made it: 1j times the real array, then the sum)
                complex_ = out.reshape(-1)[: 2 * out.shape[-1]].view(complex)[None]
                w = np.add(rhs[:, k], np.multiply(1j, rhs[:, k + 1], out=complex_), out=complex_)
                w = solve(lu, w, out=w)
                rhs[:, k], rhs[:, k + 1] = w.real, w.imag
        return np.matmul(T, rhs, out=out)  # (T @ rhs: overwritten by the next call, or the next evaluation)

"""Radau IIA Butcher tableaus, computed from the Radau polynomial.

The nodes ``c`` are the roots of the right Radau polynomial
``d^{s-1}/dx^{s-1} [x^{s-1} (x-1)^s]`` on ``[0, 1]`` (so ``c_s = 1``).  The polynomial has
integer coefficients; its roots are found by mpmath at ``PRECISION_DIGITS + 20`` digits (sympy's
exact root isolation, used before, cost 0.1-0.3 s in every process's first solve), and
:meth:`RadauIIA.exact_nodes` gives them as exact algebraic numbers.  ``A`` and ``b`` follow from
the simplifying conditions C(s) and B(s),

    sum_j a_ij c_j^(k-1) = c_i^k / k,   sum_j b_j c_j^(k-1) = 1 / k,   k = 1..s,

solved at ``PRECISION_DIGITS`` decimal digits and rounded to float64 once.  No decimals are
typed by hand.  The high-precision values stay on the tableau (``A_hp``, ``b_hp``, ``c_hp``)
so the order conditions can be checked far below float64 round-off.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache

import mpmath
import numpy as np
import sympy as sp

from daemodel.errors import StagesError

# 60 digits: far below float64's 16, so rounding the tableau to float64 is exact to the last
# bit and order-condition residuals of 1e-50 are distinguishable from real failures (>1e-20).
PRECISION_DIGITS = 60
# The bound on mpmath's root iterations (s = 30 converges well within it).
ROOT_STEPS = 200


@dataclass(frozen=True, eq=False)
class RadauIIA:
    """An s-stage Radau IIA method (order 2s-1, stage order s).

    Attributes
    ----------
    stages : int
        Number of stages s.
    order : int
        Classical order 2s - 1 (differential variables of an index-2 DAE also reach it).
    stage_order : int
        Stage order s (the order of the algebraic variables of an index-2 DAE).
    A : ndarray, shape (s, s)
        Runge-Kutta matrix, float64, read-only.
    b : ndarray, shape (s,)
        Weights, float64, read-only (equal to the last row of ``A``: stiffly accurate).
    c : ndarray, shape (s,)
        Nodes, float64, read-only, strictly increasing, ``c[-1] == 1``.
    A_hp, b_hp, c_hp : tuple of mpmath.mpf
        The same coefficients at ``PRECISION_DIGITS`` digits (``A_hp`` row by row).
    """

    stages: int
    order: int
    stage_order: int
    A: np.ndarray
    b: np.ndarray
    c: np.ndarray
    A_hp: tuple
    b_hp: tuple
    c_hp: tuple

    def __post_init__(self) -> None:
        s = self.stages
        if self.A.shape != (s, s) or self.b.shape != (s,) or self.c.shape != (s,):
            raise StagesError(
                f"Radau IIA tableau with {s} stages needs A (s, s), b (s,), c (s,); "
                f"got A {self.A.shape}, b {self.b.shape}, c {self.c.shape}"
            )
        if not (np.all(np.diff(self.c) > 0) and self.c[-1] == 1.0 and self.c[0] > 0):
            raise StagesError(f"Radau IIA nodes must increase in (0, 1] and end at 1; got {self.c}")
        if not np.array_equal(self.A[-1], self.b):
            raise StagesError("Radau IIA is stiffly accurate: the last row of A must equal b")
        for array in (self.A, self.b, self.c):
            array.flags.writeable = False

    def to_torch(self, dtype=None, device=None):
        """Return ``(A, b, c)`` as torch tensors of the given dtype (default float64) and device."""
        import torch

        dtype = torch.float64 if dtype is None else dtype
        return tuple(torch.tensor(x.copy(), dtype=dtype, device=device) for x in (self.A, self.b, self.c))

    def exact_nodes(self) -> tuple:
        """The nodes as exact algebraic numbers (sympy ``CRootOf``, ascending)."""
        return tuple(sp.Poly(radau_polynomial(self.stages)).real_roots())

    def __repr__(self) -> str:
        return f"RadauIIA(stages={self.stages}, order={self.order}, c={np.array2string(self.c)})"


def radau_polynomial(s: int) -> sp.Poly:
    """The right Radau polynomial of degree s whose roots are the Radau IIA nodes (rational)."""
    x = sp.Symbol("x")
    return sp.Poly(sp.diff(x ** (s - 1) * (x - 1) ** s, x, s - 1), x)


def radau_iia(s: int) -> RadauIIA:
    """The s-stage Radau IIA tableau (cached).

    Parameters
    ----------
    s : int
        Number of stages, s >= 1.  Order 2s - 1; stage order s.

    Returns
    -------
    RadauIIA
    """
    if isinstance(s, bool) or not isinstance(s, (int, np.integer)) or s < 1:
        raise StagesError(f"Radau IIA needs an integer number of stages s >= 1; got {s!r}")
    return _radau_iia(int(s))


def radau_coefficients(s: int) -> list[int]:
    """The Radau polynomial's integer coefficients, highest power first:
    ``d^{s-1}/dx^{s-1} [x^{s-1} (x-1)^s] = sum_k binom(s, k) (-1)^(s-k) (k+s-1)! / k! x^k``."""
    return [
        math.comb(s, k) * (-1) ** (s - k) * math.factorial(k + s - 1) // math.factorial(k) for k in range(s, -1, -1)
    ]


@cache
def _radau_iia(s: int) -> RadauIIA:
    # A context of its own, not mpmath's global one: mpmath.workdps sets the process-wide precision, so
    # two threads' first calls (functools.cache does not lock) changed each other's digits mid-solve and
    # left the global precision at 60 or 152 digits behind them (and polyroots raised NoConvergence).
    mp = mpmath.MPContext()
    mp.dps = PRECISION_DIGITS + 20
    try:
        found = mp.polyroots(radau_coefficients(s), maxsteps=ROOT_STEPS, extraprec=4 * PRECISION_DIGITS)
    except mp.NoConvergence as error:
        raise StagesError(
            f"Radau polynomial of degree {s}: mpmath's roots did not converge in {ROOT_STEPS} steps ({error})"
        ) from error
    found = found if isinstance(found, list) else [found]
    if any(abs(mp.im(r)) > mp.mpf(10) ** -PRECISION_DIGITS for r in found):  # (s simple real roots)
        raise StagesError(f"Radau polynomial of degree {s}: mpmath found complex roots {found}")
    roots = sorted(mp.re(r) for r in found)
    if not (len(roots) == s and 0 < roots[0] and abs(roots[-1] - 1) < mp.mpf(10) ** -PRECISION_DIGITS):
        raise StagesError(f"Radau polynomial of degree {s}: roots {roots} are not s in (0, 1] ending at 1")
    roots[-1] = mp.mpf(1)
    mp.dps = PRECISION_DIGITS  # (the values on the tableau keep this context: their arithmetic at 60 digits)
    c = [+r for r in roots]  # (rounded to PRECISION_DIGITS)
    vandermonde = mp.matrix([[cj ** (k - 1) for k in range(1, s + 1)] for cj in c])
    rhs = mp.matrix([[ci**k / k for k in range(1, s + 1)] for ci in c])
    # C(s): A V = R with V[j, k] = c_j^(k-1), R[i, k] = c_i^k / k  ->  A = R V^-1
    a = rhs * mp.inverse(vandermonde)
    A_hp = tuple(tuple(a[i, j] for j in range(s)) for i in range(s))
    b_hp = A_hp[-1]  # stiffly accurate: c_s = 1 makes C(s) for the last row equal to B(s)
    return RadauIIA(
        stages=s,
        order=2 * s - 1,
        stage_order=s,
        A=np.array([[float(v) for v in row] for row in A_hp]),
        b=np.array([float(v) for v in b_hp]),
        c=np.array([float(v) for v in c]),
        A_hp=A_hp,
        b_hp=b_hp,
        c_hp=tuple(c),
    )

"""The fixed pivot order of a model's static factors (:mod:`.sparse`), re-derived where it stops holding.

The static factors' pivot order is chosen at one matrix, the start of the model's first adaptive solve:
static pivoting (:func:`.sparse.matched_order`: the differential diagonals, then a matching on the
algebraic block, index-1 rows before index-2 ones) where it holds there, else SuperLU's partial
pivoting.  Partial pivoting's order depends on every value of that one matrix: the wheelset starts at
rest, and its order pivoted on creep forces' derivatives that vanish where tanh saturates; after t ~ 0.45
nearly every factorisation had a zero pivot (4,599 of 5,307 steps over [0, 10] at rtol 1e-6), each
factored again by LAPACK on the general path in Python, and the orders re-derived from the first
failures depended on which matrices the first steps happened to factor (190 fallbacks over [0, 2] with
the probed first step, 455 from h0 = 1e-6).  The static-pivoting order held at every step, from any h0:
no fallback over [0, 2] from the default, 3e-4 or 1e-6.

:class:`PivotOrders` keeps the order with the model, counts the factorisations it did not hold, and
keeps a few of their matrices.  The next solve of the model (each piece between events and
breakpoints is one) derives a new order from them, in its setup: both orders at each kept matrix are
candidates, and the one whose factors hold at most of the kept matrices (growth within the bound
and no zero pivot, by :func:`fixed_order_growth`) replaces the order, if it holds at more of them
than the order in use.  A new order is new code (the static factors and the compiled step are built
for it, and compiled once, through the disk cache); at most :data:`MAX_PIVOT_ORDERS` are derived per
model, so a solution that visits many regions does not compile without end.  A solve from a start that
an earlier solve of the model started from takes that solve's order: solving again gives the same bits.
"""

from __future__ import annotations

import itertools

import numpy as np
from daemodel.backends.radau.sparse import MAX_GROWTH, PIVOTING, StaticLU

from daemodel.errors import DaemodelError

# Pivot orders derived per model after the first (each is a compile of the step's library, 0.5-1 s on the
# Test Set problems from a cold cache): the wheelset at rtol 1e-6 needs none since its first order is
# static pivoting's (it needed 1-2 with SuperLU's).
MAX_PIVOT_ORDERS = 4
# Factorisations the order must have failed before the next solve derives another: one failure is a
# singular system as often as a poor order (every order fails there, and LAPACK names it).
REDERIVE_AFTER = 3
# Failing matrices kept (over every order derived: the first third and the latest) as candidates and as
# the test set of the candidates: each candidate is an elimination at each kept matrix, milliseconds at
# D <= a few hundred.
KEPT_FAILURES = 12
# Static pivoting's elimination (the differential variables first) may fill in where partial pivoting's
# interleaves them (reaction-diffusion of 100 unknowns: 4,000 entries against < 1,000): beyond this many
# times partial pivoting's multiply-adds its robustness costs more than the factorisations it saves.
MATCHED_MAX_COST = 1.5


def fixed_order_growth(lu: StaticLU, J: np.ndarray, h: float, shift: complex) -> float:
    """The growth that the static factors of ``lu``'s pivot order report for ``shift / h M - J`` (J's
    nonzeros at ``lu``'s pattern): the larger of max |L| and max |U| over max |matrix|, inf at a zero
    pivot, a singular matrix or a value that is not finite.  SuperLU's elimination of the matrix
    permuted into that order, told to keep every diagonal pivot (threshold 0, no reordering beyond a
    postorder of the elimination tree, which leaves the factors' entries as they are): the kernel's
    number, up to rounding, in O(the elimination's flops)."""
    import scipy.sparse as sparse
    import scipy.sparse.linalg as splinalg

    D, n = lu.D, lu.n
    values = -np.asarray(J, dtype=float)
    if not np.isfinite(values).all():
        return float("inf")
    complex_ = bool(complex(shift).imag)
    diagonal = shift / h if complex_ else complex(shift).real / h
    A = sparse.csc_matrix(
        (np.r_[values, np.full(n, diagonal)], (lu.perm_r[np.r_[lu.rows, :n]], lu.perm_c[np.r_[lu.cols, :n]])),
        shape=(D, D),
        dtype=complex if complex_ else float,
    )
    largest = float(_magnitude(A.data).max(initial=0.0))
    if not np.isfinite(largest):
        return float("inf")
    try:
        factors = splinalg.splu(
            A, permc_spec="NATURAL", diag_pivot_thresh=0.0, options={"SymmetricMode": True, "Equil": False}
        )
    except RuntimeError:  # (exactly singular)
        return float("inf")
    if not np.array_equal(factors.perm_r, factors.perm_c):  # (a zero diagonal pivot: SuperLU took another row)
        return float("inf")
    L = factors.L.tocoo()
    multipliers = L.data[L.row != L.col]
    growth = max(
        float(_magnitude(multipliers).max(initial=0.0)),
        float(_magnitude(factors.U.data).max(initial=0.0)) / max(largest, 1e-300),
    )
    return growth if np.isfinite(growth) else float("inf")


def first_order(orders: list) -> StaticLU | None:
    """The first order of a model's static factors, of ``orders`` (:class:`.sparse.StaticLU`, each of one
    kind of :data:`.sparse.PIVOTING`, each holding at the start): static pivoting's where its elimination
    takes at most :data:`MATCHED_MAX_COST` times partial pivoting's multiply-adds, else partial
    pivoting's; None where there is none."""
    by_kind = {lu.pivoting: lu for lu in orders}
    matched, partial = by_kind.get("matched"), by_kind.get("partial")
    if matched is not None and (partial is None or matched.flops <= MATCHED_MAX_COST * partial.flops):
        return matched
    return partial


def holds(lu: StaticLU, J: np.ndarray, h: float, shifts: list) -> bool:
    """Whether the factors in ``lu``'s order hold at ``J`` and step ``h`` for every one of ``shifts``: growth
    within :data:`.sparse.MAX_GROWTH` and no zero pivot (:func:`fixed_order_growth`)."""
    return all(fixed_order_growth(lu, J, h, lam) <= MAX_GROWTH for lam in shifts)


def _magnitude(values: np.ndarray) -> np.ndarray:
    """|value| as the kernel takes it for its growth: complex ones as max(|re|, |im|)."""
    if np.iscomplexobj(values):
        return np.maximum(np.abs(values.real), np.abs(values.imag))
    return np.abs(values)


class PivotOrders:
    """The pivot order of one model's static factors (``lu``: a :class:`.sparse.StaticLU`, or None where
    there are none), its ``version`` (0 for the first; part of every cache key of code built for it),
    the factorisations it did not hold since it was derived (``failures``) and a few of their matrices."""

    def __init__(self, lu: StaticLU | None):
        self.lu, self.version, self.failures, self.derived = lu, 0, 0, 0
        self._kept = []  # (J, h) of failed factorisations: the first KEPT_FAILURES // 3 and the latest
        self._orders = {0: lu}  # version -> order
        self._by_start = {}  # a solve's start -> the version it took

    def for_start(self, start: bytes, shifts: list, max_flops: int, max_entries: int) -> tuple:
        """``(order, version)`` for a solve from ``start`` (its t0, y0, z0 and parameters as bytes): the one
        an earlier solve from the same start took (solving again gives the same bits), else the latest,
        re-derived first where it failed (:meth:`rederive`): each piece between events starts elsewhere."""
        if start not in self._by_start:
            self.rederive(shifts, max_flops, max_entries)
            self._by_start[start] = self.version
        version = self._by_start[start]
        return self._orders[version], version

    def record(self, J: np.ndarray, h: float) -> None:
        """A factorisation in this order that did not hold (growth, zero pivot or a value not finite)."""
        self.failures += 1
        if not np.isfinite(J).all():
            return  # (a step that diverged: no matrix to derive an order from)
        sample = (np.array(J, dtype=float), float(h))
        if len(self._kept) >= KEPT_FAILURES:
            del self._kept[KEPT_FAILURES // 3]  # (keep the first ones: where the order first stopped holding)
        self._kept.append(sample)

    def rederive(self, shifts: list, max_flops: int, max_entries: int) -> bool:
        """Derive a new order from the kept matrices (see the module docstring) where the order failed at
        least :data:`REDERIVE_AFTER` times and fewer than :data:`MAX_PIVOT_ORDERS` were derived; the
        systems are ``lam / h M - J`` for each ``lam`` of ``shifts`` (the transform's eigenvalues); a
        candidate whose elimination takes more than ``max_flops`` multiply-adds or whose factors hold more than
        ``max_entries`` entries is not taken (the static factors' own bounds).
        True where the order changed (``version`` counts up); the failures start again from 0 either way."""
        if self.lu is None or self.failures < REDERIVE_AFTER or self.derived >= MAX_PIVOT_ORDERS or not self._kept:
            return False
        self.derived += 1
        kept, self.failures = self._kept, 0
        real = max((lam.real for lam in shifts if lam.imag == 0), default=abs(shifts[0]))
        best, best_held = None, self._held(self.lu, kept, shifts)
        # candidates: both orders of .sparse (static pivoting and SuperLU's) at each kept matrix, and at the
        # latest with every entry that vanished in any of them set to 0 (an entry of J that a saturation or a
        # branch makes 0 is no pivot to keep)
        vanished = np.any([J == 0 for J, _ in kept], axis=0)
        samples = [*kept, (np.where(vanished, 0.0, kept[-1][0]), kept[-1][1])]
        for (J, h), pivoting in itertools.product(samples, PIVOTING):
            try:
                candidate = StaticLU(self.lu.rows, self.lu.cols, self.lu.n, self.lu.D, J, h, real, pivoting, max_flops)
            except DaemodelError:  # (a time limit's signal, raised inside the call: not a singular system)
                raise
            except RuntimeError:  # (exactly singular there, or over max_flops: no order from it)
                continue
            if candidate.entries > max_entries:
                continue
            held = self._held(candidate, kept, shifts)
            if held > best_held or (best is not None and held == best_held and candidate.flops < best.flops):
                best, best_held = candidate, held
        if best is None:
            return False
        self.lu, self.version = best, self.version + 1
        self._orders[self.version] = best
        return True

    @staticmethod
    def _held(lu: StaticLU, kept: list, shifts: list) -> int:
        """At how many of the ``kept`` matrices the factors in ``lu``'s order hold for every shift."""
        return sum(holds(lu, J, h, shifts) for J, h in kept)

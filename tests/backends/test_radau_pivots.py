"""The static factors' pivot order re-derived where it stops holding (backends/radau/pivots.py).

The growth the numpy elimination computes must be the static factors' own (so that a candidate order
is judged as the compiled step will judge it); an order that meets a zero pivot is replaced by one
that holds there, only after REDERIVE_AFTER failures and at most MAX_PIVOT_ORDERS times; and on the
wheelset, which starts at rest, the solve's factorisations stop falling back to LAPACK.
"""

import sys
from pathlib import Path

import numpy as np
import pytest
from daemodel.backends.radau.compiled import Buffered, find_compiler
from daemodel.backends.radau.increments import StaticFactors, static_factor_function
from daemodel.backends.radau.pivots import (
    MATCHED_MAX_COST,
    MAX_PIVOT_ORDERS,
    REDERIVE_AFTER,
    PivotOrders,
    first_order,
    fixed_order_growth,
)
from daemodel.backends.radau.sparse import MAX_GROWTH, StaticLU

import daemodel as dm

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import scaling_models


def test_the_growth_is_the_static_factors_own(first_engine):
    """On the 20-pendulum chain with its Jacobian perturbed, the largest growth over the transformed
    systems (a real and a complex shift) is the one the static factor function reports."""
    compiled, engine = first_engine(scaling_models.pendulum_chain(20))
    lu = engine._static_pattern()
    J = engine.jacobian(0.0, np.array([compiled.y0]), np.array([compiled.z0]))
    J = J * (1 + 0.5 * np.random.default_rng(3).random(len(engine.rows)))
    factor = Buffered(static_factor_function(lu, engine.transform))
    for h in (1e-4, 1e-2, 1.0):
        reported = factor(np.concatenate([[h], J]))[-2]
        shifts = [lam for _, lam in engine.transform.blocks]
        assert max(fixed_order_growth(lu, J, h, lam) for lam in shifts) == pytest.approx(reported, rel=1e-9)
    assert StaticFactors(lu, engine.transform).size > 0


def _two_by_two():
    """A full 2 x 2 pattern (no differential variables), its order at ``[[2, 1], [1, 1]]``, and a
    nonsingular matrix that is 0 at that order's first pivot."""
    rows, cols = np.array([0, 0, 1, 1]), np.array([0, 1, 0, 1])
    first = StaticLU(rows, cols, 0, 2, -np.array([2.0, 1.0, 1.0, 1.0]), 1.0, 1.0)
    i0, j0 = int(np.flatnonzero(first.perm_r == 0)[0]), int(np.flatnonzero(first.perm_c == 0)[0])
    failing = -np.array([0.0 if (i, j) == (i0, j0) else 1.0 for i, j in zip(rows, cols, strict=True)])
    return first, failing


def test_an_order_that_meets_a_zero_pivot_is_replaced_by_one_that_holds():
    first, failing = _two_by_two()
    assert fixed_order_growth(first, failing, 1.0, 1.0) == float("inf")
    orders = PivotOrders(first)
    for _ in range(REDERIVE_AFTER - 1):
        orders.record(failing, 1.0)
    assert not orders.rederive([1.0 + 0j], 10**5, 5000)  # (too few failures: a singular system as often)
    orders.record(failing, 1.0)
    assert orders.rederive([1.0 + 0j], 10**5, 5000)
    assert orders.version == 1 and orders.lu is not first and orders.failures == 0
    assert fixed_order_growth(orders.lu, failing, 1.0, 1.0) <= MAX_GROWTH


def test_a_solve_from_an_earlier_solves_start_takes_its_order():
    """Solving again from the same start gives the same bits (the transistor amplifier's compiled run
    and single attempts, tests/backends/test_radau_loop.py, are two solves of one model); a new start
    (the next piece after an event) takes the order re-derived from the failures."""
    first, failing = _two_by_two()
    orders = PivotOrders(first)
    assert orders.for_start(b"t0", [1.0 + 0j], 10**5, 5000) == (first, 0)
    for _ in range(REDERIVE_AFTER):
        orders.record(failing, 1.0)
    assert orders.for_start(b"t0", [1.0 + 0j], 10**5, 5000) == (first, 0)
    lu, version = orders.for_start(b"t1", [1.0 + 0j], 10**5, 5000)
    assert version == 1 and lu is not first and fixed_order_growth(lu, failing, 1.0, 1.0) <= MAX_GROWTH
    assert orders.for_start(b"t0", [1.0 + 0j], 10**5, 5000) == (first, 0)


def test_the_orders_derived_per_model_are_bounded():
    first, failing = _two_by_two()
    orders = PivotOrders(first)
    changed = 0
    for _ in range(2 * MAX_PIVOT_ORDERS):
        for _ in range(REDERIVE_AFTER):
            orders.record(failing, 1.0)
        changed += orders.rederive([1.0 + 0j], 10**5, 5000)
    assert orders.derived == MAX_PIVOT_ORDERS and changed <= MAX_PIVOT_ORDERS
    assert not orders.rederive([1.0 + 0j], 10**5, 5000)


def test_no_candidate_beyond_the_static_factors_bounds_is_taken():
    first, failing = _two_by_two()
    orders = PivotOrders(first)
    for _ in range(REDERIVE_AFTER):
        orders.record(failing, 1.0)
    assert not orders.rederive([1.0 + 0j], 0, 5000)  # (every candidate's elimination is over 0 flops)
    assert orders.lu is first and orders.version == 0


def test_matrices_that_are_not_finite_are_counted_and_not_kept():
    first, failing = _two_by_two()
    orders = PivotOrders(first)
    for _ in range(REDERIVE_AFTER):
        orders.record(failing * np.nan, 1.0)
    assert orders.failures == REDERIVE_AFTER
    assert not orders.rederive([1.0 + 0j], 10**5, 5000)  # (nothing to derive an order from)


def test_static_pivoting_holds_an_index_two_system_at_every_step_size():
    """y' = -y + z, 0 = y - 1 (index 2) and w' = -w + u, 0 = u - y w (index 1): static pivoting takes the
    differential diagonals first, then the index-1 row before the index-2 one, and its growth stays
    bounded from h = 1e-8 to 1; a matching of the constraint row onto y before y's own row would grow as
    1 / h (a multiplier sigma / 1)."""
    # unknowns (y, w, z, u); J's nonzeros at (y, z), (y, y), (w, w), (w, u), (g1, y), (g2, u), (g2, y), (g2, w)
    rows, cols = np.array([0, 0, 1, 1, 2, 3, 3, 3]), np.array([0, 2, 1, 3, 0, 3, 0, 1])
    J = np.array([-1.0, 1.0, -1.0, 1.0, 1.0, 1.0, -0.5, -2.0])
    lu = StaticLU(rows, cols, 2, 4, J, 1e-8, 1.0, "matched")
    assert sorted(lu.perm_c[:2]) == [0, 1] and list(lu.perm_r[:2]) == list(lu.perm_c[:2])  # (diagonals first)
    assert lu.perm_r[3] < lu.perm_r[2]  # (the index-1 row pivots before the index-2 one)
    for h in (1e-8, 1e-4, 1e-2, 1.0):
        assert max(fixed_order_growth(lu, J, h, lam) for lam in (3.64 + 0j, 2.68 + 3.05j)) < 10


def test_static_pivoting_is_the_first_order_unless_it_fills_in(first_engine):
    """Static pivoting's order where its elimination costs at most MATCHED_MAX_COST times partial
    pivoting's; on reaction-diffusion (100 unknowns) taking the differential variables first fills in."""
    _, engine = first_engine(scaling_models.reaction_diffusion(50))
    assert engine._static_pattern().pivoting == "partial"
    rows, cols, J = np.array([0, 0, 1, 1]), np.array([0, 1, 0, 1]), -np.array([2.0, 1.0, 1.0, 1.0])
    matched, partial = (StaticLU(rows, cols, 0, 2, J, 1.0, 1.0, kind) for kind in ("matched", "partial"))
    assert first_order([partial, matched]) is matched and first_order([partial]) is partial
    matched.flops = MATCHED_MAX_COST * partial.flops + 1
    assert first_order([matched, partial]) is partial and first_order([matched]) is matched
    assert first_order([]) is None


def test_an_elimination_beyond_its_budget_stops_where_it_passes_it(first_engine):
    """Reaction-diffusion at 600 unknowns: static pivoting's elimination takes ~4,700 x SuperLU's
    multiply-adds, which first_order would never take; traced to its end it cost 1.3 of a 2.3 s setup.
    With a budget it stops past it (OverBudgetError, a RuntimeError: no order from it), and within one
    it is the same elimination."""
    from daemodel.backends.radau.sparse import OverBudgetError

    _, engine = first_engine(scaling_models.reaction_diffusion(300))
    J, n, D = np.linspace(-2.0, -1.0, engine.rows.size), engine.n, engine.D
    partial = StaticLU(engine.rows, engine.cols, n, D, J, 1e-3, 1.0, "partial")
    with pytest.raises(OverBudgetError, match=r"matched pivoting's elimination takes more than \d+ multiply-adds"):
        StaticLU(engine.rows, engine.cols, n, D, J, 1e-3, 1.0, "matched", MATCHED_MAX_COST * partial.flops)
    again = StaticLU(engine.rows, engine.cols, n, D, J, 1e-3, 1.0, "partial", partial.flops)
    assert (again.flops, again.entries, again.upper) == (partial.flops, partial.entries, partial.upper)
    assert issubclass(OverBudgetError, RuntimeError)
    assert engine._static_pattern().pivoting == "partial"


@pytest.mark.slow
@pytest.mark.skipif(find_compiler() is None, reason="the static factors run in machine code (jit)")
@pytest.mark.parametrize("h0", [None, 3e-4, 1e-6])
def test_the_wheelset_keeps_its_factorisations_in_the_static_order(h0):
    """The wheelset starts at rest, where its first order is chosen: SuperLU's partial pivoting there
    pivoted on creep forces' derivatives that vanish later (190 LAPACK fallbacks over [0, 2] at rtol 1e-6
    from the probed first step, 175 from h0 = 3e-4, 455 from 1e-6, with the orders re-derived from the
    failures); static pivoting's order holds from any start (0 fallbacks from each, measured)."""
    from daemodel.problems import WHEELSET

    compiled = WHEELSET.model().compile()
    options = {} if h0 is None else {"h0": h0}
    sol = dm.solve(compiled, (0.0, 2.0), rtol=1e-6, atol=1e-6, jit=True, **options)
    assert sol.status == "success"
    assert sol.stats["pivot_failures"] <= 40

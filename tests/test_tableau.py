"""Radau IIA tableaus: order conditions B(2s-1), C(s), D(s-1) hold and B(2s) fails, s = 1..7."""

import math

import mpmath
import numpy as np
import pytest
import torch

import daemodel as dm
from daemodel.errors import StagesError
from daemodel.tableau import PRECISION_DIGITS

STAGES = range(1, 8)
HOLDS = mpmath.mpf(10) ** (-(PRECISION_DIGITS - 10))  # 1e-50: exact up to working precision


def _hp(s):
    t = dm.radau_iia(s)
    return t.A_hp, t.b_hp, t.c_hp


def B(s, k):
    """Residual of B at power k: sum_j b_j c_j^(k-1) - 1/k."""
    _, b, c = _hp(s)
    with mpmath.workdps(PRECISION_DIGITS):
        return abs(mpmath.fsum(bj * cj ** (k - 1) for bj, cj in zip(b, c, strict=True)) - mpmath.mpf(1) / k)


def C(s, k):
    A, _, c = _hp(s)
    with mpmath.workdps(PRECISION_DIGITS):
        return max(
            abs(mpmath.fsum(aij * cj ** (k - 1) for aij, cj in zip(row, c, strict=True)) - ci**k / k)
            for row, ci in zip(A, c, strict=True)
        )


def D(s, k):
    A, b, c = _hp(s)
    with mpmath.workdps(PRECISION_DIGITS):
        return max(
            abs(mpmath.fsum(b[i] * c[i] ** (k - 1) * A[i][j] for i in range(s)) - b[j] * (1 - c[j] ** k) / k)
            for j in range(s)
        )


@pytest.mark.parametrize("s", STAGES)
def test_order_conditions_hold(s):
    assert max(B(s, k) for k in range(1, 2 * s)) < HOLDS  # B(2s-1)
    assert max(C(s, k) for k in range(1, s + 1)) < HOLDS  # C(s)
    assert max((D(s, k) for k in range(1, s)), default=0) < HOLDS  # D(s-1)


@pytest.mark.parametrize("s", STAGES)
def test_order_is_exactly_2s_minus_1(s):
    # B(2s) fails by the Radau quadrature error constant, far above working precision.
    assert B(s, 2 * s) > mpmath.mpf(10) ** -20
    t = dm.radau_iia(s)
    assert (t.order, t.stage_order, t.stages) == (2 * s - 1, s, s)


@pytest.mark.parametrize("s", STAGES)
def test_float64_tableau_is_rounded_high_precision(s):
    t = dm.radau_iia(s)
    assert t.A.dtype == np.float64
    assert np.array_equal(t.A, np.array([[float(v) for v in row] for row in t.A_hp]))
    assert np.array_equal(t.b, t.A[-1]) and t.c[-1] == 1.0
    # float64 order conditions hold to round-off
    for k in range(1, 2 * s):
        assert abs(t.b @ t.c ** (k - 1) - 1 / k) < 1e-14


def test_known_closed_forms():
    two = dm.radau_iia(2)
    np.testing.assert_array_equal(two.c, [1 / 3, 1.0])
    np.testing.assert_allclose(two.A, [[5 / 12, -1 / 12], [3 / 4, 1 / 4]], rtol=0, atol=1e-16)
    three = dm.radau_iia(3)
    r6 = math.sqrt(6)
    np.testing.assert_allclose(three.c, [(4 - r6) / 10, (4 + r6) / 10, 1.0], rtol=0, atol=2e-16)
    np.testing.assert_allclose(three.b, [(16 - r6) / 36, (16 + r6) / 36, 1 / 9], rtol=0, atol=2e-16)
    np.testing.assert_allclose(
        three.A[0], [(88 - 7 * r6) / 360, (296 - 169 * r6) / 1800, (-2 + 3 * r6) / 225], atol=2e-16
    )
    one = dm.radau_iia(1)  # implicit Euler
    assert one.A.tolist() == [[1.0]] and one.b.tolist() == [1.0] and one.c.tolist() == [1.0]


def test_cached_and_read_only():
    t = dm.radau_iia(3)
    assert dm.radau_iia(3) is t
    with pytest.raises(ValueError, match="read-only"):
        t.A[0, 0] = 1.0


def test_to_torch():
    A, b, c = dm.radau_iia(3).to_torch()
    assert A.dtype == torch.float64 and A.shape == (3, 3) and b.shape == c.shape == (3,)
    A32, _, _ = dm.radau_iia(3).to_torch(dtype=torch.float32)
    assert A32.dtype == torch.float32


@pytest.mark.parametrize("bad", [0, -2, 2.5, True, "3", None])
def test_invalid_stages(bad):
    with pytest.raises(StagesError, match=r"integer number of stages s >= 1; got"):
        dm.radau_iia(bad)


def test_tableau_checks_itself():
    t = dm.radau_iia(2)
    with pytest.raises(StagesError, match=r"needs A \(s, s\)"):
        dm.RadauIIA(2, 3, 2, np.zeros((3, 3)), t.b.copy(), t.c.copy(), (), (), ())
    with pytest.raises(StagesError, match="nodes must increase"):
        dm.RadauIIA(2, 3, 2, t.A.copy(), t.b.copy(), t.c[::-1].copy(), (), (), ())
    with pytest.raises(StagesError, match="stiffly accurate"):
        dm.RadauIIA(2, 3, 2, t.A.copy(), t.b.copy() + 1, t.c.copy(), (), (), ())


@pytest.mark.parametrize("s", [1, 2, 3, 5, 7])
def test_the_nodes_are_the_radau_polynomials_exact_roots(s):
    """mpmath's roots of the integer polynomial (how the tableau is made, in milliseconds) are sympy's
    exact algebraic roots to far below float64."""
    import mpmath
    import sympy as sp

    t = dm.radau_iia(s)
    exact = t.exact_nodes()
    assert len(exact) == s and exact[-1] == 1
    with mpmath.workdps(PRECISION_DIGITS):
        for node, root in zip(t.c_hp, exact, strict=True):
            assert abs(node - mpmath.mpf(str(sp.N(root, PRECISION_DIGITS + 10)))) < mpmath.mpf(10) ** -(
                PRECISION_DIGITS - 5
            )


def test_first_calls_from_threads_agree_and_leave_mpmaths_precision_alone():
    """Concurrent first calls (functools.cache does not lock) each get the one tableau, bit for bit,
    and leave mpmath's global precision as it was: with the global context's workdps they changed each
    other's digits, left mp.dps at 60 or 152 behind them, and polyroots raised NoConvergence."""
    import threading

    import mpmath

    from daemodel import tableau

    expected = {s: tableau.radau_iia(s) for s in range(1, 10)}
    for _ in range(6):
        tableau._radau_iia.cache_clear()
        found, errors = [], []

        def first_call(s, found=found, errors=errors):
            try:
                found.append((s, tableau.radau_iia(s)))
            except Exception as error:  # (collected: a thread's exception would not fail the test)
                errors.append(error)

        threads = [threading.Thread(target=first_call, args=(s,)) for _ in range(2) for s in range(1, 10)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        assert errors == [] and mpmath.mp.dps == 15 and len(found) == 18
        for s, t in found:
            for name in ("A", "b", "c"):
                assert np.array_equal(getattr(t, name), getattr(expected[s], name))


def test_roots_that_do_not_converge_are_a_stages_error(monkeypatch):
    import mpmath

    from daemodel import tableau

    def no_convergence(self, *args, **kwargs):
        raise self.NoConvergence("Didn't converge in maxsteps=200 steps.")

    monkeypatch.setattr(mpmath.MPContext, "polyroots", no_convergence)
    tableau._radau_iia.cache_clear()
    try:
        with pytest.raises(StagesError, match="degree 4: mpmath's roots did not converge in 200 steps"):
            dm.radau_iia(4)
    finally:
        tableau._radau_iia.cache_clear()

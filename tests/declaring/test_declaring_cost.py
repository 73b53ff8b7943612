"""Declaring costs O(1) per call: a loop of n ``m.ode`` / ``m.constraint`` calls is O(n) in total.

Measured by the memory one more call allocates (deterministic, unlike a timing): merging every
declared name into a new dict on every call, as declaring did, allocated O(n) per call (100 KB at
2,000 unknowns, 420 KB at 8,000: quadratic in all), and a test against it fails.
"""

import gc
import tracemalloc

import daemodel as dm


def peak_bytes_of_one_more_equation_pair(n: int, as_text: bool) -> int:
    m = dm.Model("chain")
    u = m.states([f"u{i}" for i in range(n)])
    v = m.algebraics([f"v{i}" for i in range(n)])
    for i in range(n - 1):
        m.ode(u[i], -u[i] + v[i])
        m.constraint(v[i] - 2 * u[i], name=f"g{i}")
    rhs, constraint = (
        (f"-u{n - 1} + v{n - 1}", f"v{n - 1} = 2*u{n - 1}") if as_text else (-u[-1] + v[-1], v[-1] - 2 * u[-1])
    )
    # (no cyclic collection inside the measured calls: one there runs the finalizers of earlier tests'
    # garbage, whose allocations count in the peak; seen once in a full run: 87 KB at 2,000 unknowns)
    gc.collect()
    gc.disable()
    tracemalloc.start()
    try:
        m.ode(u[-1], rhs)
        m.constraint(constraint, name="last")
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
        gc.enable()


def test_one_declaration_costs_the_same_at_100_and_at_4000_unknowns():
    # (the least of three models each: tracemalloc counts every thread's allocations, and once in a full run, on
    # another worker's tail of tests, the text declaration at 2,000 read 79 KB against 17 KB alone; an O(n) cost
    # a call is in all three)
    for as_text in (False, True):
        small = min(peak_bytes_of_one_more_equation_pair(50, as_text) for _ in range(3))
        large = min(peak_bytes_of_one_more_equation_pair(2000, as_text) for _ in range(3))
        assert large < 1.5 * small, (as_text, small, large)


def peak_bytes_of_an_array_declaration(n: int, what: str) -> int:
    """Peak bytes of ``m.states("u", n)`` (what="states") or of ``m.ode(u, -u)`` on n states (what="odes")."""
    m = dm.Model("arrays")
    u = m.states("u", n) if what == "odes" else None
    rhs = -u if what == "odes" else None
    gc.collect()
    gc.disable()
    tracemalloc.start()
    try:
        if what == "states":
            m.states("v", n)
        else:
            m.ode(u, rhs)
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
        gc.enable()


def test_an_array_declaration_is_linear_in_its_size():
    """10^5 states in one call cost ten times what 10^4 do (measured 11.6: the tables' growth), not a
    hundred (a check per element against every name declared so far); an array of ODEs likewise."""
    small, large = (peak_bytes_of_an_array_declaration(n, "states") for n in (10_000, 100_000))
    assert large < 15 * small, (small, large)
    small, large = (peak_bytes_of_an_array_declaration(n, "odes") for n in (500, 5_000))
    assert large < 15 * small, (small, large)

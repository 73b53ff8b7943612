"""The compiled model's derived structure (daemodel/compiling/compiled.py)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import sympy as sp

import daemodel as dm
from daemodel.compiling.initial_states import branch_check_functions
from daemodel.compiling.switches import with_state_events
from daemodel.problems import PENDULUM, PROBLEMS

# radau's default on casadi's virtual machine, but in the tests marked machine_code (tests/conftest.py)
pytestmark = pytest.mark.virtual_machine


def index_by_search_from_each(compiled) -> tuple[int, ...]:
    """RADAU5's index of each algebraic variable by the definition: one graph search from each z
    (the highest index among the constraints owning a z it reaches through H_z's rows)."""
    position = {v: k for k, v in enumerate(compiled.algebraics)}
    state_rows = {v: i for i, v in enumerate(compiled.states)}
    in_f = [{position[v] for v in f.free_symbols if v in position} for f in compiled.rhs]
    rows = []
    for c in compiled.constraints:
        if c.index == 1:
            rows.append({position[v] for v in c.expr.free_symbols if v in position})
        else:
            rows.append(set().union(*[in_f[state_rows[v]] for v in c.expr.free_symbols if v in state_rows]))
    owner = list(compiled.determined_by)
    index = []
    for k in range(len(compiled.algebraics)):
        seen, stack = {k}, [k]
        while stack:
            for nxt in rows[owner[stack.pop()]] - seen:
                seen.add(nxt)
                stack.append(nxt)
        index.append(max(compiled.constraints[owner[j]].index for j in seen))
    return tuple(index)


@pytest.mark.parametrize("name", sorted(PROBLEMS))
def test_algebraic_index_is_the_search_from_each_variable(name):
    problem = PROBLEMS[name]
    compiled = problem.model().compile()
    if compiled.index > 2:
        compiled = compiled.reduced(2)
    assert compiled.algebraic_index == index_by_search_from_each(compiled)


def mixed_chain(N: int) -> dm.Model:
    """N masses on springs, each with a velocity-level constraint on the last (index 2) and an index-1
    chain of multipliers w_k = w_{k+1} + x_k: every w reaches the index-2 multiplier at the end."""
    m = dm.Model(f"mixed_chain_{N}")
    x = m.states([f"x{k}" for k in range(N)])
    v = m.states([f"v{k}" for k in range(N)])
    w = m.algebraics([f"w{k}" for k in range(N)])
    (lam,) = m.algebraics(["lam"])
    for k in range(N):
        m.ode(x[k], v[k])
        m.ode(v[k], -x[k] + (lam if k == N - 1 else 0))
    for k in range(N - 1):
        m.constraint(w[k] - w[k + 1] - x[k], name=f"link{k}")
    m.constraint(w[N - 1] - lam * sp.Integer(2), name="end")
    m.constraint(v[N - 1] - sp.Integer(0), name="still")
    m.initial(**{f"x{k}": 0.0 for k in range(N)}, **{f"v{k}": 0.0 for k in range(N)})
    return m


def test_algebraic_index_of_a_chain_reaching_an_index_two_variable():
    compiled = mixed_chain(30).compile()
    expected = index_by_search_from_each(compiled)
    assert compiled.algebraic_index == expected
    assert [compiled.constraints[j].index for j in compiled.determined_by] == [1] * 30 + [2]
    assert set(expected) == {2}  # (every w, matched to an index-1 row, reaches lam through the chain)


def test_a_copy_with_other_constraints_does_not_reuse_their_cached_index_or_branch_check():
    """dataclasses.replace shares the model's cache; the index and the branch check's functions, kept
    there since 6bf1b97, are made from the constraints, so a copy with other constraints makes its own
    (the pendulum's index 2 was read back for a copy whose constraint says index 1)."""
    compiled = PENDULUM.model().compile()
    assert compiled.index == 2
    *_, values = branch_check_functions(compiled)
    lowered = tuple(dataclasses.replace(c, chain=c.chain[-1:]) for c in compiled.constraints)
    copy = dataclasses.replace(compiled, constraints=lowered)
    assert copy.index == 1 and compiled.index == 2
    x = sp.Symbol(compiled.algebraics[0].name)
    other = tuple(dataclasses.replace(c, chain=(*c.chain[:-1], c.chain[-1] + x**3)) for c in compiled.constraints)
    copy = dataclasses.replace(compiled, constraints=other)
    fresh = dataclasses.replace(copy, _cache={})
    at = (0.0, np.array([compiled.y0]), np.array([compiled.z0]) + 1.0, np.array([compiled.parameter_values]))
    want, got = branch_check_functions(fresh), branch_check_functions(copy)
    assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
    assert np.allclose(got[2](*at), want[2](*at)) and not np.allclose(values(*at), want[2](*at))


def _decay():
    m = dm.Model("decay")
    m.states("x")
    m.parameter("k", 1.0)
    m.ode("x", "-k*x")
    m.initial(x=1.0)
    return m.compile()


@pytest.mark.parametrize("method", ["radau", "casadi-idas", "reference"])
def test_a_users_copy_with_other_equations_solves_its_own(method):
    """dataclasses.replace(compiled, rhs=...) handed the copy its model's cache: radau and casadi-idas solved
    the original's generated x' = -x for the copy's x' = -2x (x(1) = exp(-1) = 0.368 for exp(-2) = 0.135,
    "success").  A copy that changes more than the initial values now has a cache of its own."""
    compiled = _decay()
    assert abs(dm.solve(compiled, (0.0, 1.0), method=method)["x"][-1] - np.exp(-1.0)) < 1e-6
    x, k = compiled.states[0], compiled.parameters[0]
    copy = dataclasses.replace(compiled, rhs=(-2 * k * x,))
    assert abs(dm.solve(copy, (0.0, 1.0), method=method)["x"][-1] - np.exp(-2.0)) < 1e-6
    assert abs(dm.solve(compiled, (0.0, 1.0), method=method)["x"][-1] - np.exp(-1.0)) < 1e-6  # (and the original)


def test_every_cached_entry_follows_a_users_copy():
    """Whatever a copy changes but its initial values, no entry of its model's cache is read back for it: the
    Jacobian's pattern of a copy with another constraint, the numeric system of a copy with other symbols'
    equations, its event functions; a copy that changes only the initial values shares them (a solve's
    pieces), and its reduction carries its own t0, y0 and z0 (before: the original's t0 = 0 for a copy at 2)."""
    compiled = PENDULUM.model().compile()
    pattern = compiled.jacobian_pattern()
    numeric, reduced = compiled.numeric, compiled.reduced(1)
    lam = compiled.algebraics[0]
    other = tuple(dataclasses.replace(c, chain=(c.chain[0] + lam, *c.chain[1:])) for c in compiled.constraints)
    copy = dataclasses.replace(compiled, constraints=other)
    rows, cols = copy.jacobian_pattern()
    n = len(compiled.states)
    assert (n, n) in set(zip(rows.tolist(), cols.tolist(), strict=True))  # (the new d g / d lam entry)
    assert len(rows) > len(pattern[0]) and compiled.jacobian_pattern() is pattern
    # a copy at other initial values: the same generated code, its own initial values in its reduction
    moved = dataclasses.replace(compiled, t0=2.0, y0=compiled.y0.copy(), z0=compiled.z0.copy())
    assert moved.numeric is numeric and moved.jacobian_pattern() is pattern
    assert moved.reduced(1).t0 == 2.0 and moved.reduced(1).y0 is moved.y0 and moved.reduced(1).z0 is moved.z0
    assert moved.reduced(1).constraints is reduced.constraints and compiled.reduced(1) is reduced
    assert moved.reduced(1).torch_functions() is reduced.torch_functions()  # (its generated code, not made again)
    assert with_state_events(compiled) is compiled and with_state_events(moved) is moved  # (no switch on a variable)
    # any other field: a cache of its own
    changes = {
        "rhs": tuple(list(compiled.rhs)),  # (equal, but another object: the cache tells by identity, not by value)
        "parameter_values": np.array(compiled.parameter_values),
        "invariants": tuple(list(compiled.invariants)),
        "name": "other",
    }
    for name, changed in changes.items():
        assert dataclasses.replace(compiled, **{name: changed}).numeric is not numeric, name


def test_a_users_copy_with_other_events_locates_its_own():
    """The event functions are cached by the events, and a copy with other events (and so other switches'
    events) builds its own; with other right-hand sides, the crossing moves with them."""
    m = dm.Model("decay")
    m.states("x")
    m.ode("x", "-x")
    m.initial(x=1.0)
    m.event("half", "x - 0.5", direction=-1, terminal=True)
    compiled = m.compile()
    sol = dm.solve(compiled, (0.0, 2.0), rtol=1e-10, atol=1e-10)
    assert abs(sol.events["half"]["t"][0, 0] - np.log(2.0)) < 1e-8
    x = compiled.states[0]
    copy = dataclasses.replace(compiled, rhs=(-2 * x,))
    sol = dm.solve(copy, (0.0, 2.0), rtol=1e-10, atol=1e-10)
    assert abs(sol.events["half"]["t"][0, 0] - np.log(2.0) / 2) < 1e-8


def test_the_switches_events_of_a_copy_at_other_initial_values_carry_them():
    """with_state_events keeps the model with its switches' events in the cache; a copy at other initial
    values (a piece of a solve) gets it with its own t0, y0 and z0, and the same events (before: the
    first model's t0 and y0, whichever asked first)."""
    m = dm.Model("switching")
    m.states("x")
    m.ode("x", "1 - Max(x, 0.5)")
    m.initial(x=0.0)
    compiled = m.compile()
    located = with_state_events(compiled)
    assert len(located.events) == 1 and located.t0 == 0.0
    moved = dataclasses.replace(compiled, t0=3.0, y0=np.array([0.25]))
    again = with_state_events(moved)
    assert again.t0 == 3.0 and again.y0 is moved.y0 and again.events is located.events
    assert again.numeric is located.numeric  # (the same generated code)


@pytest.mark.parametrize("method", ["radau", "reference"])
def test_a_copy_at_other_initial_states_solves_its_algebraic_values_again(method):
    """dataclasses.replace(compiled, y0=..., parameter_values=...) keeps the z0 made for the first values (z = 2 x
    = 2 at x = 1): taken as it was, radau gave z(t0) = 2 beside x(t0) = 0.4 (and an event at 1e-13), and the
    reference locked Min(1, z) to the branch of z = 2: u = 2.0 for 0.393, status "success"."""
    m = dm.Model("stale")
    m.states("x u")
    m.algebraics("z")
    m.parameter("k", 1.0)
    m.ode("x", "-k*x")
    m.ode("u", "Min(1, z)")
    m.constraint("z - 2*x", name="zc")
    m.initial(x=1.0, u=0.0)
    copy = dataclasses.replace(m.compile(), y0=np.array([0.4, 0.0]), parameter_values=np.array([2.0]))
    sol = dm.solve(copy, (0.0, 2.0), method=method, **({"rtol": 1e-10, "atol": 1e-10} if method == "radau" else {}))
    assert sol.status == "success" and abs(sol["z"][0] - 0.8) < 1e-12
    assert abs(sol["u"][-1] - 0.4 * (1.0 - math.exp(-4.0))) < 1e-8  # (z = 0.8 e^(-2t) < 1 throughout)
    assert all(np.asarray(event["t"]).size == 0 for event in sol.events.values())


def test_the_generated_functions_labels_are_made_when_read():
    """The labels and comments of the generated functions (an equation's name and number in error messages
    and generated source) are made when read, not held: the first checked outputs of a model of 2,000
    unknowns keep under 16 bytes an equation (before: five lists of strings, 415 KB, ~140 bytes an
    equation, 20 MB at 10^5 unknowns, made at the first solve)."""
    import gc
    import tracemalloc

    K = 1000
    m = dm.Model("labels")
    c, w = m.states("c", K), m.algebraics("w", K)
    for i in range(K):
        m.ode(c[i], -w[i])
        m.constraint(w[i] - c[i] ** 2, name=f"rate{i}")
    m.initial(**{str(c[i]): 1.0 + i / K for i in range(K)})
    compiled = m.compile()
    equations = len(compiled.states) + len(compiled.constraints) + len(compiled.invariants)
    gc.collect()
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        outputs = compiled._outputs()
        gc.collect()
        kept = tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()
    assert kept < 16 * equations, kept / equations
    (_, f_labels, f_comments, _), (_, g_labels, g_comments, _) = outputs["f"], outputs["g"]
    assert len(f_labels) == len(f_comments) == len(g_labels) == len(g_comments) == K
    number = compiled.ode_numbers[K - 1]
    assert f_labels[K - 1] == f"{compiled.state_names[K - 1]}' (#{number})" == f_labels[-1]
    assert f_comments[K - 1] == f"f[{K - 1}]: ODE #{number}"
    rate = compiled.constraints[3]
    assert (
        g_labels[3] == f"rate3 (#{rate.number}, index 1)"
        and g_comments[3] == f"g[3]: constraint #{rate.number}, index 1"
    )
    assert list(g_labels[1:3]) == [g_labels[1], g_labels[2]] and list(f_labels)[-1] == f_labels[-1]
    with pytest.raises(IndexError):
        f_labels[K]

"""The compiled model's derived structure (daemodel/compiling/compiled.py)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import sympy as sp

import daemodel as dm
from daemodel.compiling.initial_states import branch_check_functions
from daemodel.problems import PENDULUM, PROBLEMS


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

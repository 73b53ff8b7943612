"""Model only what a scene needs: alias elimination and output-driven pruning."""

import math

import pytest
import sympy as sp
import torch

import daemodel as dm
from daemodel import errors as E
from daemodel.problems import HESSENBERG


def with_aliases(alias_constraint: str) -> dm.Model:
    m = dm.Model("aliased")
    y1, y2 = m.states("y1 y2")
    w, x = m.algebraics("w x")
    m.ode(y1, -w)
    m.ode(y2, x - y2)  # uses the alias
    m.constraint(w - y1**2, name="law")
    m.constraint(alias_constraint, name="same")
    m.initial(y1=2.0, y2=0.5)
    return m


@pytest.mark.parametrize(
    ("constraint", "sign"), [("x - y1", 1), ("y1 - x", 1), ("2*x - 2*y1", 1), ("x + y1", -1), ("x = y1", 1)]
)
def test_alias_eliminated_and_readable(constraint, sign):
    c = with_aliases(constraint).compile()
    y1, y2 = c.states
    assert c.algebraic_names == ("w",) and c.constraint_names == ("law",)
    assert c.alias_names == ("x",) and c.aliases[0][1] == sign * y1
    assert c.rhs[1] == sign * y1 - y2
    tf = c.torch_functions()
    y = torch.tensor([[2.0, 0.5], [3.0, 1.0]], dtype=torch.float64)
    z = torch.tensor([[4.0], [9.0]], dtype=torch.float64)
    torch.testing.assert_close(tf.aliases(0.0, y, z), sign * y[:, :1])
    assert f"x = {sign * y1}   (from constraint 'same' (#4))" in c.report()


def test_alias_of_an_algebraic_and_chains():
    m = dm.Model("chain")
    (y,) = m.states("y")
    a, b, c_ = m.algebraics("a b c")
    m.ode(y, -a * y)
    m.constraint(a - b, name="ab")
    m.constraint(b - c_, name="bc")
    m.constraint(c_ - y**2 - 1, name="law")
    m.initial(y=1.0, a=2.0)
    c = m.compile()
    assert c.algebraic_names == ("c",) and set(c.alias_names) == {"a", "b"}
    assert dict((n, e) for n, e, _ in c.aliases) == {"a": c.algebraics[0], "b": c.algebraics[0]}
    assert c.z0[0] == 2.0
    m.initial(a=3.0)  # a given alias value is checked like any algebraic value
    with pytest.raises(
        E.InconsistentAlgebraicValueError, match=r"initial value a = 3 disagrees with the consistent value a = 2\.0"
    ):
        m.compile()


def test_eliminating_many_aliases_rewrites_only_where_they_occur(monkeypatch):
    # each elimination scanned every right-hand side, constraint and alias: n aliases cost O(n^2) look-ups
    # (1.5 million free-symbol look-ups for these 1,000 aliases; 64 s of compile for 3,000, more than 5
    # minutes for 10^4), now the equations each alias occurs in (12,000 here)
    import numpy as np

    from daemodel.compiling.structure import Differentiator

    K = 500
    m = dm.Model("aliases")
    c, w, v = m.states("c", K), m.algebraics("w", K), m.algebraics("v", K)
    k = np.arange(1.0, K + 1)
    m.ode(c, -k * v)
    m.constraint(v - w, name="link")  # (v = w, then w = c: v's alias rewritten when w goes)
    m.constraint(w - c, name="rate")
    m.initial(c=1.0)
    calls, free_symbols = [0], Differentiator.free_symbols

    def counted(self, expr):
        calls[0] += 1
        return free_symbols(self, expr)

    monkeypatch.setattr(Differentiator, "free_symbols", counted)
    compiled = m.compile()
    assert calls[0] <= 20 * 3 * K  # (20 look-ups an equation)
    assert compiled.algebraic_names == () and len(compiled.aliases) == 2 * K
    assert dict((n, e) for n, e, _ in compiled.aliases) == {
        **{f"v[{i}]": c[i] for i in range(K)},
        **{f"w[{i}]": c[i] for i in range(K)},
    }
    labels = [label for _, _, label in compiled.aliases]
    assert labels[0].startswith("constraint 'link[0]' (#501)") and labels[1].startswith("constraint 'link[1]'")
    sol = dm.solve(compiled, (0.0, 0.01), rtol=1e-10, atol=1e-12)
    assert np.allclose(sol["c"][:, -1], np.exp(-k * 0.01), rtol=1e-8, atol=0)
    assert np.array_equal(sol["v"], sol["c"]) and np.array_equal(sol["w"], sol["c"])


def hessenberg_plus_decay() -> dm.Model:
    m = HESSENBERG.model()
    (q,) = m.states("q")
    (r,) = m.algebraics("r")
    k = m.parameter("k", 0.5)
    m.ode(q, -k * q)
    m.constraint(r - q**2, name="square")
    m.initial(q=2.0)
    return m


def test_outputs_keep_the_coupled_system():
    c = hessenberg_plus_decay().compile(outputs=["y1", "y5"])
    assert c.state_names == ("y1", "y2", "y3", "y4") and c.algebraic_names == ("y5",)
    assert c.constraint_names == ("invariant",) and c.parameter_names == ()
    assert c.dropped == {
        "differential variables": ("q",),
        "algebraic variables": ("r",),
        "constraints": ("square",),
        "aliases": (),
        "parameters": ("k",),
    }
    report = c.report()
    assert "differential variables: q" in report and "constraints: square" in report and "parameters: k" in report


def test_output_on_the_other_subsystem():
    c = hessenberg_plus_decay().compile(outputs="r")
    assert c.state_names == ("q",) and c.algebraic_names == ("r",) and c.parameter_names == ("k",)
    assert set(c.dropped["differential variables"]) == {"y1", "y2", "y3", "y4"}
    assert c.z0[0] == 4.0 and c.index == 1


def test_pure_ode_after_pruning():
    c = hessenberg_plus_decay().compile(outputs=["q"])
    assert c.state_names == ("q",) and c.algebraic_names == () and c.index == 0
    tf = c.torch_functions()
    y, z = torch.ones(3, 1, dtype=torch.float64), torch.zeros(3, 0, dtype=torch.float64)
    assert tf.g(0.0, y, z).shape == (3, 0)
    torch.testing.assert_close(tf.f(0.0, y, z), -0.5 * y)
    assert "Model 'model' " not in c.report() and "ODE (semi-explicit)" in c.report()


def test_single_state_depends_on_everything_it_reads():
    # y3' = 2 y3 y4 y1 y2 reads y1, whose ODE reads y5, which is solved with the invariant
    c = hessenberg_plus_decay().compile(outputs=["y3"])
    assert c.state_names == ("y1", "y2", "y3", "y4") and c.algebraic_names == ("y5",)


def test_dropped_states_need_no_initial_value():
    m = hessenberg_plus_decay()
    m._initial.pop("q")  # as if never given
    with pytest.raises(E.MissingInitialValueError, match="'q'"):
        m.compile()
    assert m.compile(outputs=["y5"]).y0.tolist() == [1.0, 1.0, 1.0, 1.0]


def test_unknown_output():
    with pytest.raises(
        E.UnknownOutputError, match=r"compile\(outputs=...\): 'y9' not a variable of model 'hessenberg'"
    ):
        hessenberg_plus_decay().compile(outputs=["y1", "y9"])


def test_outputs_can_name_an_alias():
    m = with_aliases("x - y2")
    c = m.compile(outputs=["x"])
    assert c.state_names == ("y2",) and c.alias_names == ("x",) and c.algebraic_names == ()
    assert c.aliases[0][1] == sp.Symbol("y2")


def test_a_parameter_only_an_event_reads_is_kept():
    """Before: compile() refused it as pruned by the outputs, with no outputs requested."""
    m = dm.Model("ball")
    m.states("h v")
    m.parameter("e", 0.8)
    m.parameter("level", 0.0)
    m.ode("h", "v")
    m.ode("v", "-9.81")
    m.initial(h=1.0, v=0.0)
    m.event("hit", "h - level", direction=-1, reset={"v": "-e*v"})
    assert m.compile().parameter_names == ("e", "level")
    sol = dm.solve(m, (0.0, 0.6), rtol=1e-10, atol=1e-10, parameters={"e": 0.5, "level": 0.5})
    hit = math.sqrt(2 * 0.5 / 9.81)  # (a fall of 0.5, then up at half the speed)
    assert abs(sol.events["hit"]["t"][0, 0] - hit) < 1e-11
    assert sol["v"][-1] == pytest.approx(0.5 * 9.81 * hit - 9.81 * (0.6 - hit), rel=1e-10)
    assert m.compile(outputs=["h"]).parameter_names == ("e", "level")  # (h needs v: both kept)

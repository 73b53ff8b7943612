"""The compiled model's report (daemodel/compiling/report.py): long runs of a section summarised by
default, every entry with full=True, and only what is shown printed."""

import numpy as np
import pytest

import daemodel as dm


def grid(K: int, arrays: bool = True) -> dm.Model:
    """u' = -u + w, 0 = w - u^2 on K points, as arrays u[0..K-1], w[0..K-1] or as scalars u_0, ..."""
    m = dm.Model("grid")
    if arrays:
        u, w = m.states("u", K), m.algebraics("w", K)
        m.ode(u, -u + w)
        m.constraint(w - u**2, name="law")
        m.initial(u=1.0 / np.arange(1, K + 1))
        return m
    u, w = m.states([f"u_{i}" for i in range(K)]), m.algebraics([f"w_{i}" for i in range(K)])
    for i in range(K):
        m.ode(u[i], -u[i] + w[i])
        m.constraint(w[i] - u[i] ** 2, name=f"law_{i}")
    m.initial(**{u[i].name: 1.0 / (i + 1) for i in range(K)})
    return m


def counting_prints(monkeypatch) -> list:
    """A counter of the expressions sympy's str prints (not the parts it prints inside one)."""
    from sympy.printing.str import StrPrinter

    printed, depth, doprint = [0], [0], StrPrinter.doprint

    def counted(self, expr):
        printed[0] += depth[0] == 0
        depth[0] += 1
        try:
            return doprint(self, expr)
        finally:
            depth[0] -= 1

    monkeypatch.setattr(StrPrinter, "doprint", counted)
    return printed


def test_a_long_array_is_summarised_by_its_first_elements_a_count_and_its_last():
    c = grid(200).compile()
    lines = c.report().splitlines()
    i = lines.index("Differential variables (200):")
    assert lines[i + 1 : i + 9] == [
        "  #1   u[0]' = -u[0] + w[0]",
        "        u[0](t0) = 1",
        "  #2   u[1]' = -u[1] + w[1]",
        "        u[1](t0) = 0.5",
        "  #3   u[2]' = -u[2] + w[2]",
        "        u[2](t0) = 0.3333333333333333",
        "  ... 196 more, u[3] to u[198] (report(full=True) lists every one)",
        "  #200 u[199]' = -u[199] + w[199]",
    ]
    assert "  ... 196 more, w[3] to w[198] (report(full=True) lists every one)" in lines
    assert "  ... 196 more, law[3] to law[198] (report(full=True) lists every one)" in lines
    invariants = "Invariants (drift): law[0], law[1], law[2], ... 196 more ..., law[199]"
    assert f"{invariants} (report(full=True) lists every one)" in lines
    assert len(lines) < 40


def test_full_lists_every_entry():
    c = grid(200).compile()
    full = c.report(full=True)
    for i in range(200):
        assert f"u[{i}]' = -u[{i}] + w[{i}]\n" in full and f"  w[{i}](t0) = {(1 / (i + 1)) ** 2:.16g}   " in full
        assert f" law[{i}]: 0 = -u[{i}]**2 + w[{i}]\n" in full
    assert "lists every one" not in full and len(full.splitlines()) == 1 + 1 + 400 + 1 + 200 + 1 + 400 + 3


def test_up_to_fifty_entries_are_listed_and_scalar_runs_are_summarised_as_arrays():
    fifty = grid(50).compile()
    assert fifty.report() == fifty.report(full=True) and "u[49]' = -u[49] + w[49]" in fifty.report()
    scalars = grid(60, arrays=False).compile().report()
    assert "  ... 56 more, u_3 to u_58 (report(full=True) lists every one)" in scalars
    # (equations are numbered as declared: the loop's odes and constraints alternate)
    assert "  #119 u_59' = -u_59 + w_59" in scalars and "u_30'" not in scalars


def test_runs_are_the_elements_of_one_array_or_consecutive_scalars():
    from daemodel.compiling.report import runs

    names = ["a", "b", "u[0]", "u[1]", "v[0,0]", "v[0,1]", "u'", "c", "u[2]"]
    assert runs(names) == [(0, 2), (2, 4), (4, 6), (6, 8), (8, 9)]
    assert runs(["law[0]'", "law[1]'", "x"]) == [(0, 2), (2, 3)]  # (a reduced constraint's name)


def test_pruned_names_are_summarised():
    m = grid(100)
    (x,) = m.states("x")
    m.ode(x, -x)
    m.initial(x=1.0)
    report = m.compile(outputs=["x"]).report()
    assert "  differential variables: u[0], u[1], u[2], ... 96 more ..., u[99] (report(full=True) lists every one)" in (
        report
    )
    assert "u[50]" in m.compile(outputs=["x"]).report(full=True)


@pytest.mark.parametrize("arrays", [True, False])
def test_the_report_prints_only_what_it_shows(monkeypatch, arrays):
    """At 10^5 unknowns the report printed every equation (sympy's str, its terms sorted): 38.5 s and
    17.7 MB, linear; now a few equations per run, whatever the size (benchmarks/refusal_and_report.json)."""
    c = grid(1000, arrays).compile()
    printed = counting_prints(monkeypatch)
    c.report()
    assert printed[0] <= 3 * (4 + 4)  # (4 right-hand sides, 4 constraints, and at most one more print each)

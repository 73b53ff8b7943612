"""A switch that closes at t1 = 0.3: found by the compiler, cut into the grid, order kept.

A source V closes onto an RC branch at t1:   C v' = i,   0 = i - [t >= t1] (V - v) / R,
v(0) = 0.5.  Before t1 no current flows; after it v relaxes to V: v = V + (v0 - V) exp(-(t - t1)/RC),
and the algebraic current i jumps from 0 to (V - v0) / R at t1.

The compiler lists the switch (a time breakpoint: it depends on t only); every method integrates
from breakpoint to breakpoint, each side on its own branch, and solves i anew at the switch.  So
fixed-step radau keeps its order 2s - 1 across it (without the cut the step across the switch
would be first order), and IDAS, collocation and the reference cross it to their tolerance.

Run: python examples/switches.py [--quick]
"""

import argparse
import math

import numpy as np

import daemodel as dm

V, R, C, T1, V0 = 2.0, 0.5, 0.4, 0.3, 0.5


def build_model() -> dm.Model:
    m = dm.Model("closing-switch")
    m.states("v")
    m.algebraics("i")
    m.parameter("V", V)
    m.parameter("R", R)
    m.parameter("C", C)
    m.ode("v", "i / C")
    m.constraint(f"i - Piecewise((0, t < {T1}), ((V - v) / R, True))", name="switch")
    m.initial(v=V0)
    return m


def exact(t):
    return np.where(t < T1, V0, V + (V0 - V) * np.exp(-(t - T1) / (R * C)))


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer step sizes")
    args = parser.parse_args(argv)
    compiled = build_model().compile()
    print(compiled.report())
    assert "Piecewise in switch: t - 0.3 crosses 0 (time breakpoint)" in compiled.report()

    hs = [0.1, 0.05, 0.025] if args.quick else [0.1, 0.05, 0.025, 0.0125]
    print("\nfixed-step radau across the switch: error in v(1) against the exact solution")
    print(f"{'s':>2} " + " ".join(f"{'h = ' + format(h, 'g'):>12}" for h in hs) + "   order (fit)   expected 2s-1")
    for s in (1, 2, 3):
        errors = [
            abs(dm.solve(compiled, (0.0, 1.0), stages=s, h=h, estimate_bound=1.0)["v"][-1] - exact(1.0)) for h in hs
        ]
        order = float(np.polyfit(np.log(hs), np.log(errors), 1)[0])
        print(f"{s:>2} " + " ".join(f"{e:12.2e}" for e in errors) + f"   {order:11.2f}   {2 * s - 1:13d}")
        assert order > 2 * s - 1 - 0.3, (s, errors)

    sol = dm.solve(compiled, (0.0, 1.0), stages=3, h=0.05)
    before, after = sol.breakpoints["before"]["i"][0, 0], sol.breakpoints["after"]["i"][0, 0]
    jump = f"i jumps from {before:g} to {after:.15g} (exact {(V - V0) / R:g})"
    print(f"\nbreakpoints {sol.breakpoints['t'][0].tolist()}: {jump}")
    assert before == 0.0 and abs(after - (V - V0) / R) < 1e-12

    grid = np.linspace(0.0, 1.0, 11)
    print("\nevery method across the switch (max error in v at 11 times):")
    for method, options, tol in (
        ("radau", {"rtol": 1e-8, "atol": 1e-8}, 1e-8),
        ("casadi-idas", {"rtol": 1e-8, "atol": 1e-8}, 1e-7),
        ("casadi-collocation", {}, 1e-8),
        ("reference", {}, 1e-11),
    ):
        sol = dm.solve(compiled, (0.0, 1.0), method=method, t_eval=grid, **options)
        error = float(np.abs(sol["v"] - exact(sol.t)).max())
        print(f"  {method:<20s} {error:.2e}  ({sol.stats['segments']} segments, status {sol.status})")
        assert error < tol and math.isclose(sol["i"][3], (V - V0) / R, rel_tol=1e-6)


if __name__ == "__main__":
    main()

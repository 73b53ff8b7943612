"""A pendulum that hits a wall: a declared event, located, reset, and the constraints kept.

Cartesian pendulum (index 3, solved through its index-2 reduction) released at x = 1:

    x' = u,  y' = v,  u' = -lam x,  v' = -lam y - g,  0 = x^2 + y^2 - 1

and a wall at x = -0.5: ``m.event("wall", "x + 0.5", direction=-1, reset={"u": "-0.8*u", "v": "-0.8*v"})``.
Each impact is located to 1e-12 in t by trial solves (the located state has the method's own
accuracy), the velocities are reset (scaling both keeps x u + y v = 0, so nothing needs projecting),
and the multiplier lam is solved anew from the constraints at the new velocities.  The script
checks the impact times against a solve at rtol 1e-13 (s = 7), the constraints after each reset,
lam's consistency, a terminal event, and a batch whose samples hit the wall at different times.

Run: python examples/events.py [--quick]
"""

import argparse
import math

import numpy as np

import daemodel as dm

G = 9.81


def build_model(terminal: bool = False, x0: float = 1.0) -> dm.Model:
    m = dm.Model("wall")
    m.states("x y u v")
    m.algebraics("lam")
    m.ode("x", "u")
    m.ode("y", "v")
    m.ode("u", "-lam*x")
    m.ode("v", f"-lam*y - {G}")
    m.constraint("x**2 + y**2 - 1", name="rod")
    m.initial(x=x0, y=-math.sqrt(max(0.0, 1 - x0**2)), u=0.0, v=0.0)
    m.event("wall", "x + 0.5", direction=-1, reset={"u": "-0.8*u", "v": "-0.8*v"}, terminal=terminal)
    return m


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a batch of 10 samples instead of 100")
    args = parser.parse_args(argv)
    compiled = build_model().compile()
    print(compiled.report())

    reference = dm.solve(compiled, (0.0, 3.0), rtol=1e-13, atol=1e-13, stages=7)
    sol = dm.solve(compiled, (0.0, 3.0), rtol=1e-10, atol=1e-10)
    wall = sol.events["wall"]
    gap = float(np.abs(wall["t"] - reference.events["wall"]["t"]).max())
    print(f"\nimpacts at t = {wall['t'][0].tolist()} (rtol 1e-10); against rtol 1e-13: {gap:.1e}")
    assert gap < 1e-9
    x, y, u, v, lam = (wall["after"][k][0] for k in ("x", "y", "u", "v", "lam"))
    position, velocity = float(np.abs(x**2 + y**2 - 1).max()), float(np.abs(x * u + y * v).max())
    consistent = float(np.abs(lam - (u**2 + v**2 - G * y) / (x**2 + y**2)).max())
    levels = f"|x^2 + y^2 - 1| <= {position:.1e}, |x u + y v| <= {velocity:.1e}"
    print(f"after each reset: {levels}, lam off by {consistent:.1e}")
    print(f"lam jumps at the impacts: {wall['before']['lam'][0].round(4).tolist()} -> {lam.round(4).tolist()}")
    assert position < 1e-12 and velocity < 1e-12 and consistent < 1e-10

    for method, options in (("casadi-idas", {"rtol": 1e-10, "atol": 1e-10}), ("radau", {"stages": 3, "h": 0.005})):
        other = dm.solve(compiled, (0.0, 3.0), method=method, **options)
        gap = float(np.abs(other.events["wall"]["t"] - reference.events["wall"]["t"]).max())
        print(f"{method} {options}: impact times within {gap:.1e}")
        assert gap < 1e-8

    stop = dm.solve(build_model(terminal=True), (0.0, 3.0), rtol=1e-10, atol=1e-10)
    print(f"terminal: the solve ends at t = {stop.t[-1]:.12f}, x = {stop['x'][-1]:.12f}")
    assert stop.t[-1] == stop.events["wall"]["t"][0, 0] and abs(stop["x"][-1] + 0.5) < 1e-9

    samples = 10 if args.quick else 100
    x0 = np.linspace(0.6, 1.0, samples)
    grid = np.linspace(0.0, 2.0, 11)
    y0 = {"x": x0, "y": -np.sqrt(1 - x0**2), "u": np.zeros(samples), "v": np.zeros(samples)}
    batch = dm.solve(compiled, (0.0, 2.0), rtol=1e-8, atol=1e-8, t_eval=grid, y0=y0)
    first = batch.events["wall"]["t"][:, 0]
    print(f"a batch of {samples}: first impacts from t = {first.min():.4f} to {first.max():.4f}")
    # each sample alone: the same steps to rounding (the batch runs on torch, a single trajectory in
    # machine code where a C compiler is found; with jit=False both are bit for bit the same)
    gap = 0.0
    for b in (0, samples // 2, samples - 1):
        single = dm.solve(build_model(x0=float(x0[b])), (0.0, 2.0), rtol=1e-8, atol=1e-8, t_eval=grid)
        gap = max(gap, float(np.abs(batch["x"][b] - single["x"]).max()))
    print(f"the batch against each sample solved alone: within {gap:.1e}")
    assert gap < 1e-9


if __name__ == "__main__":
    main()

"""The pendulum of the Radau-PINN paper, index 2 (velocity-level constraint), solved three ways.

    y1' = y3      y2' = y4      y3' = -y1 y5      m y4' = -y2 y5 - lam
    0   = y1 y3 + y2 y4         y(0) = (1, 0, 0, 1),  m = lam = 1

The position-level form 0 = y1^2 + y2^2 - 1 has index 3; the compiler classifies it and
reduces it to the velocity form.  Both give y5(0) = 1.

The system has no closed form, so, as in the paper, the reference is a tight-tolerance solve
(DOP853 at 1e-12 on the underlying ODE).  Own Radau IIA and casadi's Radau collocation solve
the same equations (s = 3, h = 0.05) and must agree to rounding; IDAS runs on the index-1
reduction at rtol = 1e-8.

Run: python examples/pendulum.py [--quick] [--plot pendulum.png]
    --quick   t in [0, 1] (the paper's interval) instead of [0, 10]
"""

import argparse

import numpy as np

import daemodel as dm

METHODS = {
    "radau": {"stages": 3, "h": 0.05},
    "casadi-collocation": {"stages": 3, "h": 0.05},
    "casadi-idas": {"rtol": 1e-8, "atol": 1e-10},
}


def build_model(position_level: bool = False) -> dm.Model:
    m = dm.Model("pendulum-index3" if position_level else "pendulum")
    y1, y2, y3, y4 = m.states("y1 y2 y3 y4")
    (y5,) = m.algebraics("y5")
    mass = m.parameter("m", 1.0)
    lam = m.parameter("lam", 1.0)
    m.ode(y1, y3)
    m.ode(y2, y4)
    m.ode(y3, -y1 * y5)
    m.ode(y4, (-y2 * y5 - lam) / mass)
    if position_level:
        m.constraint(y1**2 + y2**2 - 1, name="rod")
    else:
        m.constraint(y1 * y3 + y2 * y4, name="velocity")
    m.initial(y1=1, y2=0, y3=0, y4=1)
    return m


def compare(compiled, t1: float):
    """Solve with every method; return the solutions and their errors against the reference."""
    grid = np.linspace(0.0, t1, round(t1 / 0.05) + 1)  # the Radau grid, where every method reports
    reference = dm.solve(compiled, (0.0, t1), method="reference", t_eval=grid)
    solutions, errors = {}, {}
    for method, options in METHODS.items():
        extra = {"t_eval": grid} if method == "casadi-idas" else {}
        solutions[method] = dm.solve(compiled, (0.0, t1), method=method, **options, **extra)
        errors[method] = solutions[method].errors(reference)
    return reference, solutions, errors


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="t in [0, 1] instead of [0, 10]")
    parser.add_argument("--plot", metavar="PNG", help="write the Radau solution with the reference dashed")
    args = parser.parse_args(argv)

    compiled = build_model().compile()
    print(compiled.report())
    assert compiled.index == 2
    assert abs(compiled.z0[0] - 1.0) < 1e-14

    position = build_model(position_level=True).compile()
    velocity_form = position.reduced(index=2)
    print("\n" + position.report())
    print(f"\nposition form: index {position.index}; reduced to index {velocity_form.index}: 0 = {velocity_form.g[0]}")
    assert position.index == 3 and velocity_form.index == 2
    assert abs(position.z0[0] - 1.0) < 1e-14

    t1 = 1.0 if args.quick else 10.0
    reference, solutions, errors = compare(compiled, t1)
    names = [*compiled.state_names, *compiled.algebraic_names]
    print(f"\nMax absolute error against the reference on [0, {t1:g}] (DOP853, rtol = atol = 1e-12):")
    print(f"{'method':<20}{'settings':<22}" + "".join(f"{n:>10}" for n in names) + f"{'drift':>10}{'solve [s]':>10}")
    for method, sol in solutions.items():
        settings = ", ".join(f"{k}={v:g}" for k, v in METHODS[method].items())
        row = "".join(f"{errors[method][n]['max']:>10.1e}" for n in names)
        print(f"{method:<20}{settings:<22}{row}{sol.drift()['velocity']:>10.1e}{sol.solve_time:>10.3f}")

    own, col = solutions["radau"], solutions["casadi-collocation"]
    gap = max(np.max(np.abs(own[n] - col[n])) for n in names)
    print(f"\nradau vs casadi-collocation (same s, h): max difference {gap:.1e}")
    if args.plot:
        own.plot(args.plot, reference=reference)
        print(f"wrote {args.plot}")

    # same equations, two Newton solvers; Radau IIA accuracy: y order 5, z (index 2) order 3
    assert gap < 1e-8
    for method in ("radau", "casadi-collocation"):
        assert max(errors[method][n]["max"] for n in compiled.state_names) < 1e-8 * t1**2
        assert errors[method]["y5"]["max"] < 5e-5 * t1
    assert max(e["max"] for e in errors["casadi-idas"].values()) < 1e-5 * t1
    assert own.drift()["velocity"] < 1e-12


if __name__ == "__main__":
    main()

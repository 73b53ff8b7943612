"""The Hessenberg index-2 problem of the Radau-PINN paper: declare, compile, report.

    y1' = (y3 y4 + y1 y2) y5      y2' = -y3 y4^2 y2^2 y5
    y3' = 2 y3 y4 y1 y2           y4' = -y3 y4 y2^2
    0   = y1 y4 - y2 y3           y(0) = (1, 1, 1, 1)

Exact solution: y1 = y3 = e^{2t}, y2 = y4 = e^{-t}, y5 = e^{t}.  The algebraic y5 is not
given: the compiler finds y5(0) = 1 from the hidden constraint d/dt (y1 y4 - y2 y3) = 0.

Run: python examples/hessenberg.py
"""

import daemodel as dm


def build_model() -> dm.Model:
    m = dm.Model("hessenberg")
    y1, y2, y3, y4 = m.states("y1 y2 y3 y4")
    (y5,) = m.algebraics("y5")
    m.ode(y1, (y3 * y4 + y1 * y2) * y5)
    m.ode(y2, -y3 * y4**2 * y2**2 * y5)
    m.ode(y3, 2 * y3 * y4 * y1 * y2)
    m.ode(y4, -y3 * y4 * y2**2)
    m.constraint(y1 * y4 - y2 * y3, name="invariant")
    m.initial(y1=1, y2=1, y3=1, y4=1)
    return m


def main() -> None:
    compiled = build_model().compile()
    print(compiled.report())
    print(f"\nindex = {compiled.index}, z0 = {dict(zip(compiled.algebraic_names, compiled.z0.tolist(), strict=True))}")
    assert compiled.index == 2
    assert abs(compiled.z0[0] - 1.0) < 1e-14  # exact: y5(0) = e^0


if __name__ == "__main__":
    main()

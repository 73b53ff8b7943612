"""The pendulum of the Radau-PINN paper, index 2 (velocity-level constraint).

    y1' = y3      y2' = y4      y3' = -y1 y5      m y4' = -y2 y5 - lam
    0   = y1 y3 + y2 y4         y(0) = (1, 0, 0, 1),  m = lam = 1

The position-level form 0 = y1^2 + y2^2 - 1 has index 3; the compiler classifies it and
reduces it to the velocity form.  Both give y5(0) = 1.

Run: python examples/pendulum.py
"""

import daemodel as dm


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


def main() -> None:
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


if __name__ == "__main__":
    main()

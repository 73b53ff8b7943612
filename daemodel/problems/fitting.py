"""Problems for parameter fitting (issue 29), outside :data:`~daemodel.problems.library.PROBLEMS`:
they have no published reference to compare methods on."""

from __future__ import annotations

from daemodel.problems.problem import Problem

# A fitting problem (issue 29), not in PROBLEMS (it has no exact solution or published reference to
# compare methods on): a pendulum of length L and mass m with known linear damping c, released from
# rest at the angle of (0.6, -0.8).  The damping makes the mass visible in the positions (c/m is the
# decay rate; without it the positions do not depend on m at all); L enters through the initial
# position, which compiled.consistent(parameters=...) moves onto the longer rod at the same angle.
DAMPED_PENDULUM = Problem(
    name="damped-pendulum",
    odes={"x": "u", "y": "v", "u": "(-x*lam - c*u)/m", "v": "(-y*lam - c*v)/m - g"},
    algebraics=("lam",),
    constraints={"rod": "x**2 + y**2 - L**2"},
    parameters={"L": 1.0, "m": 1.0, "c": 0.3, "g": 9.81},
    initial={"x": 0.6, "y": -0.8, "u": 0.0, "v": 0.0},
    t_span=(0.0, 5.0),
    index=3,
    source="a damped planar pendulum in Cartesian coordinates (Hairer & Wanner, Solving ODEs II, VII.1, with damping)",
)

# A second fitting problem, outside PROBLEMS: exponential decay with an index-1 algebraic variable
# that depends on a parameter of its own (z0 = c y0^2 moves with c).
DECAY = Problem(
    name="decay",
    odes={"y": "-k*y"},
    algebraics=("z",),
    constraints={"square": "z - c*y**2"},
    parameters={"k": 1.5, "c": 0.7},
    initial={"y": 1.0},
    t_span=(0.0, 2.0),
    index=1,
    exact={"y": "exp(-1.5*t)", "z": "0.7*exp(-3*t)"},
    source="exponential decay with an algebraic square (the fitting tests and benchmarks/fit_inverse.py)",
)

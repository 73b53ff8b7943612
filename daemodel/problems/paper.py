"""The problems of the paper daemodel's Radau-PINN follows (Chen, Tang et al., PINNs for solving
high-index DAE systems based on Radau methods): the Hessenberg index-2 example with its closed
form, the pendulum at velocity level (index 2), and the same pendulum at position level (index 3)."""

from __future__ import annotations

from daemodel.problems.problem import Problem

PAPER = "Chen, Tang et al., PINNs for solving high-index DAE systems based on Radau methods"

HESSENBERG = Problem(
    name="hessenberg",
    odes={
        "y1": "(y3*y4 + y1*y2)*y5",
        "y2": "-y3*y4**2*y2**2*y5",
        "y3": "2*y3*y4*y1*y2",
        "y4": "-y3*y4*y2**2",
    },
    algebraics=("y5",),
    constraints={"invariant": "y1*y4 - y2*y3"},
    initial={"y1": 1.0, "y2": 1.0, "y3": 1.0, "y4": 1.0},
    index=2,
    exact={"y1": "exp(2*t)", "y2": "exp(-t)", "y3": "exp(2*t)", "y4": "exp(-t)", "y5": "exp(t)"},
    source=PAPER + " (Hessenberg index-2 example)",
)

PENDULUM = Problem(
    name="pendulum",
    odes={"y1": "y3", "y2": "y4", "y3": "-y1*y5", "y4": "(-y2*y5 - lam)/m"},
    algebraics=("y5",),
    constraints={"velocity": "y1*y3 + y2*y4"},
    parameters={"m": 1.0, "lam": 1.0},
    initial={"y1": 1.0, "y2": 0.0, "y3": 0.0, "y4": 1.0},
    index=2,
    source=PAPER + " (pendulum, velocity-level constraint, index 2; no closed form)",
)

PENDULUM_INDEX3 = Problem(
    name="pendulum-index3",
    odes=PENDULUM.odes,
    algebraics=("y5",),
    constraints={"rod": "y1**2 + y2**2 - 1"},
    parameters=PENDULUM.parameters,
    initial=PENDULUM.initial,
    index=3,
    source="position-level form of the pendulum (Hairer & Wanner, Solving ODEs II, VII.1)",
)

"""A small library of test problems: equations as data, initial values, interval, exact
solution where one exists, and the source.  Tests, benchmarks and examples draw on it; the
equations are strings so the library exercises the same parser users do.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import sympy as sp

from daemodel.init import NUMERIC_MODULES
from daemodel.model import Model
from daemodel.parse import parse_equation


@dataclass(frozen=True, kw_only=True)
class Problem:
    """A semi-explicit DAE test problem.

    Attributes
    ----------
    name : str
    odes : dict state -> right-hand side (str)
    algebraics : tuple of str
    constraints : dict name -> expression (str), meaning ``0 = expression``
    parameters : dict name -> value
    initial : dict name -> value (states; algebraic values where the source gives them)
    t_span : (float, float)
    index : int
        The index the compiler must find.
    exact : dict name -> expression in t (str), or empty when no closed form exists
    source : str
    """

    name: str
    odes: dict
    algebraics: tuple
    constraints: dict
    parameters: dict = field(default_factory=dict)
    initial: dict
    t_span: tuple = (0.0, 1.0)
    index: int
    exact: dict = field(default_factory=dict)
    source: str = ""

    def model(self) -> Model:
        """A fresh :class:`Model` of this problem."""
        m = Model(self.name)
        m.states(list(self.odes))
        if self.algebraics:
            m.algebraics(list(self.algebraics))
        for name, value in self.parameters.items():
            m.parameter(name, value)
        for state, rhs in self.odes.items():
            m.ode(state, rhs)
        for name, expr in self.constraints.items():
            m.constraint(expr, name=name)
        m.initial(**self.initial)
        return m

    def exact_solution(self):
        """``solution(t) -> dict name -> ndarray`` from the closed form (None if there is none)."""
        if not self.exact:
            return None
        t = sp.Symbol("t")
        functions = {
            name: sp.lambdify(t, parse_equation(expr, {"t": t}, f"exact solution of {name}"), NUMERIC_MODULES)
            for name, expr in self.exact.items()
        }

        def solution(times):
            times = np.asarray(times, dtype=float)
            return {name: np.broadcast_to(fn(times), times.shape).astype(float) for name, fn in functions.items()}

        return solution


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

ROBERTSON = Problem(
    name="robertson",
    odes={"y1": "-0.04*y1 + 1e4*y2*y3", "y2": "0.04*y1 - 1e4*y2*y3 - 3e7*y2**2"},
    algebraics=("y3",),
    constraints={"mass": "y1 + y2 + y3 - 1"},
    initial={"y1": 1.0, "y2": 0.0},
    t_span=(0.0, 40.0),
    index=1,
    source="Robertson's chemical kinetics as an index-1 DAE, stiff after t ~ 0.01 (Hairer & Wanner, "
    "Solving ODEs II, VI.1)",
)

PROBLEMS = {p.name: p for p in (HESSENBERG, PENDULUM, PENDULUM_INDEX3, ROBERTSON)}

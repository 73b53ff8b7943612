"""What a test problem is: :class:`Problem` (equations as strings, initial values, interval, exact
solution or published reference values, and the source) and :class:`ExactSolution` (its closed
form, evaluated)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import sympy as sp

from daemodel.backends.grids import SWEEP_FIRST_STEPS
from daemodel.compiling.compiler import Model
from daemodel.compiling.init import NUMERIC_MODULES
from daemodel.declaring.parse import parse_equation


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
    guesses : dict name -> value
        Newton's starting values for algebraic variables (``Model.guess``: they pick the root and
        claim nothing), where the source gives none to full precision or zero is no start.
    t_span : (float, float)
    index : int
        The index the compiler must find.
    exact : dict name -> expression in t (str), or empty when no closed form exists
    reference : dict name -> float
        Published values of the solution at ``t_span[1]`` where the source gives them and no
        closed form exists (empty otherwise); ``source`` says how they were computed.
    source : str
    compare_steps : int
        Steps over ``t_span`` of the coarsest fixed-step setting ``daemodel compare`` sweeps
        (``h = span / compare_steps``, then halved): 10 where the solution is smooth on the
        span, more where it oscillates or has fast transients that a coarser step cannot follow.
    events : tuple of dict
        Declared events, each the keyword arguments of :meth:`Model.event` (``name``, ``when``,
        ``direction``, ``reset`` with str expressions, ``terminal``).
    scd_names : tuple of str
        The components whose relative error at ``t_span[1]`` ``dm.bench`` reads significant
        correct digits from (empty: every component of ``reference``, or of ``exact``).
    exact_events : dict name -> tuple of str
        The exact solution's event times (expressions), where ``exact`` jumps.  ``exact`` is then a
        ``Piecewise`` in t whose conditions are ``t < t_k``: at ``t_k`` it gives the values after the
        event (as a Solution does), and the same expressions with ``t <= t_k`` the values just before.
    """

    name: str
    odes: dict
    algebraics: tuple
    constraints: dict
    parameters: dict = field(default_factory=dict)
    initial: dict
    guesses: dict = field(default_factory=dict)
    t_span: tuple = (0.0, 1.0)
    index: int
    exact: dict = field(default_factory=dict)
    reference: dict = field(default_factory=dict)
    source: str = ""
    compare_steps: int = SWEEP_FIRST_STEPS
    events: tuple = ()
    scd_names: tuple = ()
    exact_events: dict = field(default_factory=dict)

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
        if self.guesses:
            m.guess(**self.guesses)
        for event in self.events:
            m.event(**event)
        return m

    def exact_solution(self) -> ExactSolution | None:
        """``solution(t) -> dict name -> ndarray`` from the closed form (None if there is none); with
        :attr:`exact_events`, ``solution.events`` holds its event times and the values on each side."""
        if not self.exact:
            return None
        t = sp.Symbol("t")
        expressions = {
            name: parse_equation(expr, {"t": t}, f"exact solution of {name}") for name, expr in self.exact.items()
        }
        # the left limits: the same pieces, each closed at its right end (t <= t_k for t < t_k)
        closed = {
            name: expr.replace(lambda e: isinstance(e, sp.StrictLessThan), lambda e: sp.LessThan(*e.args))
            for name, expr in expressions.items()
        }
        right = ExactSolution({name: sp.lambdify(t, e, NUMERIC_MODULES) for name, e in expressions.items()})
        left = ExactSolution({name: sp.lambdify(t, e, NUMERIC_MODULES) for name, e in closed.items()})
        events = {}
        for name, times in self.exact_events.items():
            # (through lambdify, as the pieces' conditions are: the same digits give the same doubles)
            instants = np.array(
                [
                    float(sp.lambdify((), parse_equation(v, {}, f"time of event {name}"), NUMERIC_MODULES)())
                    for v in times
                ]
            )
            events[name] = {
                "t": instants[None, :],
                "before": {k: v[None, :] for k, v in left(instants).items()},
                "after": {k: v[None, :] for k, v in right(instants).items()},
            }
        return ExactSolution(right.functions, events)


@dataclass(frozen=True, eq=False)
class ExactSolution:
    """A closed-form solution: ``solution(t)`` gives a dict name -> ndarray shaped like ``t``.

    Attributes
    ----------
    functions : dict name -> callable of t
    events : dict
        Its events in :attr:`Solution.events`' layout (name -> ``"t"``, ``"before"``, ``"after"``,
        each (1, K)), which :meth:`Solution.errors` and :func:`compare` measure each side's
        event instants with; empty without events.
    """

    functions: dict
    events: dict = field(default_factory=dict)

    def __call__(self, times) -> dict:
        times = np.asarray(times, dtype=float)
        return {name: np.broadcast_to(fn(times), times.shape).astype(float) for name, fn in self.functions.items()}

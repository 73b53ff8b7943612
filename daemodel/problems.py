"""A small library of test problems: equations as data, initial values, interval, exact
solution where one exists, and the source.  Tests, benchmarks and examples draw on it; the
equations are strings so the library exercises the same parser users do.
"""

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

# ---- Andrews' squeezing mechanism (the seven-body mechanism), index-2 formulation -------------
#
# Source of every number below: the Test Set for IVP Solvers (F. Mazzia, C. Magherini, Univ. of
# Bari; formerly the CWI test set of W. M. Lioen and J. J. B. de Swart), problem "Andrews'
# squeezing mechanism", file andrews.f (revision 1.2, 2006/10/02), after Hairer & Wanner, Solving
# ODEs II, section VII.7.  Read in the copy the R package deTestSet (K. Soetaert, J. Cash,
# F. Mazzia) distributes: src/Ex_andrews.f ("derived from the Test Set for IVP solvers") for the
# equations, the 42 parameters (common block andcom) and the reference solution at t = 0.03
# (subroutine andsoln: "computed at Cray C90, using Cray double precision ... using PSIDE",
# rtol = atol = 1e-14), and R/ex_andrews.R for the consistent initial values (yini: positions to
# 30 digits, velocities 0, the two nonzero accelerations and multipliers).  J. Cash's MEBDFI
# driver for the same problem lists identical parameters, initial values and reference.  The test
# set states the problem in index-3 form (position constraints g(q) = 0); the index-2 form here
# replaces them by their time derivative G(q) v = 0 with G = dg/dq (Hairer & Wanner, VII.7), so
# the exact solution, and hence the reference, is the same (the published q0 satisfies g(q0) = 0
# to rounding: SQUEEZER_POSITION_CONSTRAINTS).  The test set counts its "scd" digits on the seven
# positions only (the other 20 values are printed but skipped).
#
# Unknowns (the test set's y(1..27)): angles q1..q7 = (beta, Theta, gamma, Phi, delta, Omega,
# epsilon), velocities v = q', accelerations w = v' and multipliers lam1..lam6.  Equations:
#   q' = v,  v' = w,
#   0 = M(q) w - f(q, v) + G(q)^T lam   (7 rows, index 1: they contain w and lam),
#   0 = G(q) v                          (6 rows, index 2: G v' = G w is where w appears).

SQUEEZER_PARAMETERS = {
    "m1": 0.04325, "m2": 0.00365, "m3": 0.02373, "m4": 0.00706, "m5": 0.07050, "m6": 0.00706,
    "m7": 0.05498, "xa": -0.06934, "ya": -0.00227, "xb": -0.03635, "yb": 0.03273, "xc": 0.014,
    "yc": 0.072, "c0": 4530.0, "i1": 2.194e-6, "i2": 4.410e-7, "i3": 5.255e-6, "i4": 5.667e-7,
    "i5": 1.169e-5, "i6": 5.667e-7, "i7": 1.912e-5, "d": 28e-3, "da": 115e-4, "e": 2e-2,
    "ea": 1421e-5, "rr": 7e-3, "ra": 92e-5, "l0": 7785e-5, "ss": 35e-3, "sa": 1874e-5,
    "sb": 1043e-5, "sc": 18e-3, "sd": 2e-2, "ta": 2308e-5, "tb": 916e-5, "u": 4e-2,
    "ua": 1228e-5, "ub": 449e-5, "zf": 2e-2, "zt": 4e-2, "fa": 1421e-5, "mom": 33e-3,
}  # fmt: skip

# The mass matrix M(q): the lower triangle (andrews.f's m(i, j), i >= j); M is symmetric.
_SQUEEZER_MASS = {
    (1, 1): "m1*ra**2 + m2*(rr**2 - 2*da*rr*cos(q2) + da**2) + i1 + i2",
    (2, 1): "m2*(da**2 - da*rr*cos(q2)) + i2",
    (2, 2): "m2*da**2 + i2",
    (3, 3): "m3*(sa**2 + sb**2) + i3",
    (4, 4): "m4*(e - ea)**2 + i4",
    (5, 4): "m4*((e - ea)**2 + zt*(e - ea)*sin(q4)) + i4",
    (5, 5): "m4*(zt**2 + 2*zt*(e - ea)*sin(q4) + (e - ea)**2) + m5*(ta**2 + tb**2) + i4 + i5",
    (6, 6): "m6*(zf - fa)**2 + i6",
    (7, 6): "m6*((zf - fa)**2 - u*(zf - fa)*sin(q6)) + i6",
    (7, 7): "m6*((zf - fa)**2 - 2*u*(zf - fa)*sin(q6) + u**2) + m7*(ua**2 + ub**2) + i6 + i7",
}
# The spring between the fixed point C and the point D on body 3 (andrews.f's xd, yd, lang, force).
_SQ_XD, _SQ_YD = "(sd*cos(q3) + sc*sin(q3) + xb - xc)", "(sd*sin(q3) - sc*cos(q3) + yb - yc)"
_SQ_LENGTH = f"sqrt({_SQ_XD}**2 + {_SQ_YD}**2)"
_SQ_FORCE = f"(-c0*({_SQ_LENGTH} - l0)/{_SQ_LENGTH})"
# The applied and centrifugal forces f(q, v) (andrews.f's ff).
_SQUEEZER_FORCES = (
    "mom - m2*da*rr*v2*(v2 + 2*v1)*sin(q2)",
    "m2*da*rr*v1**2*sin(q2)",
    f"{_SQ_FORCE}*({_SQ_XD}*(sc*cos(q3) - sd*sin(q3)) + {_SQ_YD}*(sd*cos(q3) + sc*sin(q3)))",
    "m4*zt*(e - ea)*v5**2*cos(q4)",
    "-m4*zt*(e - ea)*v4*(v4 + 2*v5)*cos(q4)",
    "-m6*u*(zf - fa)*v7**2*cos(q6)",
    "m6*u*(zf - fa)*v6*(v6 + 2*v7)*cos(q6)",
)
# The constraint Jacobian G(q) = dg/dq, its nonzero entries (andrews.f's gp(k, j)).
_SQUEEZER_G = {
    (1, 1): "-rr*sin(q1) + d*sin(q1 + q2)", (1, 2): "d*sin(q1 + q2)", (1, 3): "-ss*cos(q3)",
    (2, 1): "rr*cos(q1) - d*cos(q1 + q2)", (2, 2): "-d*cos(q1 + q2)", (2, 3): "-ss*sin(q3)",
    (3, 1): "-rr*sin(q1) + d*sin(q1 + q2)", (3, 2): "d*sin(q1 + q2)",
    (3, 4): "-e*cos(q4 + q5)", (3, 5): "-e*cos(q4 + q5) + zt*sin(q5)",
    (4, 1): "rr*cos(q1) - d*cos(q1 + q2)", (4, 2): "-d*cos(q1 + q2)",
    (4, 4): "-e*sin(q4 + q5)", (4, 5): "-e*sin(q4 + q5) - zt*cos(q5)",
    (5, 1): "-rr*sin(q1) + d*sin(q1 + q2)", (5, 2): "d*sin(q1 + q2)",
    (5, 6): "zf*sin(q6 + q7)", (5, 7): "zf*sin(q6 + q7) - u*cos(q7)",
    (6, 1): "rr*cos(q1) - d*cos(q1 + q2)", (6, 2): "-d*cos(q1 + q2)",
    (6, 6): "-zf*cos(q6 + q7)", (6, 7): "-zf*cos(q6 + q7) - u*sin(q7)",
}  # fmt: skip
# The position constraints g(q) = 0 of the index-3 form (andrews.f's g): not part of the index-2
# problem, but its invariants; the published q0 satisfies them, and drift from them is measurable.
SQUEEZER_POSITION_CONSTRAINTS = {
    "g1": "rr*cos(q1) - d*cos(q1 + q2) - ss*sin(q3) - xb",
    "g2": "rr*sin(q1) - d*sin(q1 + q2) + ss*cos(q3) - yb",
    "g3": "rr*cos(q1) - d*cos(q1 + q2) - e*sin(q4 + q5) - zt*cos(q5) - xa",
    "g4": "rr*sin(q1) - d*sin(q1 + q2) + e*cos(q4 + q5) - zt*sin(q5) - ya",
    "g5": "rr*cos(q1) - d*cos(q1 + q2) - zf*cos(q6 + q7) - u*sin(q7) - xa",
    "g6": "rr*sin(q1) - d*sin(q1 + q2) - zf*sin(q6 + q7) + u*cos(q7) - ya",
}


def _squeezer_constraints() -> dict:
    """``{"motion1".."motion7": M w - f + G^T lam, "velocity1".."velocity6": G v}`` as strings."""
    mass = {**_SQUEEZER_MASS, **{(j, i): entry for (i, j), entry in _SQUEEZER_MASS.items()}}
    constraints = {}
    for i in range(1, 8):
        terms = [f"({mass[i, j]})*w{j}" for j in range(1, 8) if (i, j) in mass]
        terms.append(f"-({_SQUEEZER_FORCES[i - 1]})")
        terms += [f"({_SQUEEZER_G[k, i]})*lam{k}" for k in range(1, 7) if (k, i) in _SQUEEZER_G]
        constraints[f"motion{i}"] = " + ".join(terms)
    for k in range(1, 7):
        constraints[f"velocity{k}"] = " + ".join(
            f"({_SQUEEZER_G[k, j]})*v{j}" for j in range(1, 8) if (k, j) in _SQUEEZER_G
        )
    return constraints


SQUEEZER = Problem(
    name="squeezer",
    odes={**{f"q{i}": f"v{i}" for i in range(1, 8)}, **{f"v{i}": f"w{i}" for i in range(1, 8)}},
    algebraics=(*(f"w{i}" for i in range(1, 8)), *(f"lam{k}" for k in range(1, 7))),
    constraints=_squeezer_constraints(),
    parameters=SQUEEZER_PARAMETERS,
    # deTestSet's yini (y(1..7), y(15..16), y(22..23); every other value is 0); the digits beyond
    # float64's are the source's and round on reading
    initial={
        "q1": -0.0617138900142764496358948458001,
        "q2": 0.0,
        "q3": 0.455279819163070380255912382449,
        "q4": 0.222668390165885884674473185609,
        "q5": 0.487364979543842550225598953530,
        "q6": -0.222668390165885884674473185609,
        "q7": 1.23054744454982119249735015568,
        **{f"v{i}": 0.0 for i in range(1, 8)},
        "w1": 14222.4439199541138705911625887,
        "w2": -10666.8329399655854029433719415,
        **{f"w{i}": 0.0 for i in range(3, 8)},
        "lam1": 98.5668703962410896057654982170,
        "lam2": -6.12268834425566265503114393122,
        **{f"lam{k}": 0.0 for k in range(3, 7)},
    },
    t_span=(0.0, 0.03),
    compare_steps=40,  # a fast mechanism: h = 7.5e-4 first (at 1.5e-3, radau's local error bound stops step 8)
    index=2,
    # andrews.f, subroutine andsoln: y(1..27) at t = 0.03 (PSIDE, rtol = atol = 1e-14, Cray C90)
    reference={
        "q1": 0.1581077119629904e2,
        "q2": -0.1575637105984298e2,
        "q3": 0.4082224013073101e-1,
        "q4": -0.5347301163226948e0,
        "q5": 0.5244099658805304e0,
        "q6": 0.5347301163226948e0,
        "q7": 0.1048080741042263e1,
        "v1": 0.1139920302151208e4,
        "v2": -0.1424379294994111e4,
        "v3": 0.1103291221937134e2,
        "v4": 0.1929337464421385e2,
        "v5": 0.5735699284790808e0,
        "v6": -0.1929337464421385e2,
        "v7": 0.3231791658026955e0,
        "w1": -0.2463176316945196e5,
        "w2": 0.5185037701610329e5,
        "w3": 0.3241025686413781e6,
        "w4": 0.5667493645176213e6,
        "w5": 0.1674362929479361e5,
        "w6": -0.5667493645176222e6,
        "w7": 0.9826520791458422e4,
        "lam1": 0.1991753333731910e3,
        "lam2": -0.2975531228015052e2,
        "lam3": 0.2306654119098399e2,
        "lam4": 0.3145271365475927e2,
        "lam5": 0.2264249232082739e2,
        "lam6": 0.1161740700019673e2,
    },
    source="Andrews' squeezing mechanism (seven-body mechanism), index-2 form of Hairer & Wanner, Solving "
    "ODEs II, VII.7; parameters, initial values and the reference at t = 0.03 from the Test Set for IVP "
    "Solvers (Mazzia & Magherini, Univ. of Bari), andrews.f rev. 1.2 (2006), reference by PSIDE at "
    "rtol = atol = 1e-14",
)

# ---- Chemical Akzo Nobel problem, index 1 ----------------------------------------------------
#
# Source: the Test Set for IVP Solvers (Mazzia & Magherini, Univ. of Bari), problem "Chemical
# Akzo Nobel" (chemakzo.f): two reactants bubbled with CO2 in a stirred vessel, stiff, with the
# fast equilibrium y6 = Ks y1 y4 as the algebraic equation.  The reference at t = 180 is the test
# set's (RADAU5 at rtol = atol = 1e-12 there); scipy's reference at 1e-12 and radau at 1e-10
# reproduce it to 1e-13 relative here (tests/test_benchmark_problems.py).
AKZO_NOBEL_PARAMETERS = {
    "k1": 18.7,
    "k2": 0.58,
    "k3": 0.09,
    "k4": 0.42,
    "Kc": 34.4,  # the equilibrium constant K of r3 = k2 / K y1 y5
    "klA": 3.3,
    "Ks": 115.83,
    "pCO2": 0.9,
    "H": 737.0,
}
_AKZO_RATES = {
    "r1": "k1*y1**4*sqrt(y2)",
    "r2": "k2*y3*y4",
    "r3": "k2/Kc*y1*y5",
    "r4": "k3*y1*y4**2",
    "r5": "k4*y6**2*sqrt(y2)",
    "Fin": "klA*(pCO2/H - y2)",
}


def _akzo(expr: str) -> str:
    """An Akzo Nobel right-hand side with the rates written out."""
    for name, rate in _AKZO_RATES.items():
        expr = expr.replace(name, f"({rate})")
    return expr


AKZO_NOBEL = Problem(
    name="akzo-nobel",
    odes={
        "y1": _akzo("-2*r1 + r2 - r3 - r4"),
        "y2": _akzo("-0.5*r1 - r4 - 0.5*r5 + Fin"),
        "y3": _akzo("r1 - r2 + r3"),
        "y4": _akzo("-r2 + r3 - 2*r4"),
        "y5": _akzo("r2 - r3 + r5"),
    },
    algebraics=("y6",),
    constraints={"equilibrium": "Ks*y1*y4 - y6"},
    parameters=AKZO_NOBEL_PARAMETERS,
    initial={"y1": 0.444, "y2": 0.00123, "y3": 0.0, "y4": 0.007, "y5": 0.0},
    t_span=(0.0, 180.0),
    index=1,
    # chemakzo.f, subroutine solut: y(1..6) at t = 180
    reference={
        "y1": 0.1150794920661702,
        "y2": 0.1203831471567715e-2,
        "y3": 0.1611562887407974,
        "y4": 0.3656156421249283e-3,
        "y5": 0.1708010885264404e-1,
        "y6": 0.4873531310307455e-2,
    },
    source="Chemical Akzo Nobel problem (index 1, stiff chemistry) of the Test Set for IVP Solvers "
    "(Mazzia & Magherini, Univ. of Bari), chemakzo.f; reference at t = 180 from the test set",
)

# ---- Car axis problem, index 3 --------------------------------------------------------------
#
# Source: the Test Set for IVP Solvers (Mazzia & Magherini, Univ. of Bari), problem "Car Axis"
# (caraxis.f, revision 1.2, 2006/10/02), read in deTestSet's copy: src/Ex_car.f for the equations
# (carfunc) and the reference at t = 3 (carsoln), R/ex_caraxis.R for the parameters and initial
# values.  A car axis on a bumpy road: the left wheel (xl, yl) and the right wheel (xr, yr) are
# springs of rest length L0 to the chassis, the axis keeps length L between them, and the right
# wheel's road point (xb, yb) oscillates, yb = r sin(w t).  The test set's form is
# M y' = f(t, y) with mass k = M eps^2 / 2 on the four velocities and zero on the two position
# constraints; dividing those rows by k gives the semi-explicit form here.  The stiff springs
# (eps = 1e-2) make the motion a fast oscillation about a slow one.
CAR_AXIS_PARAMETERS = {"eps": 1e-2, "M": 10.0, "L": 1.0, "L0": 0.5, "r": 0.1, "w": 10.0, "g": 1.0}
_CAR_K = "(M*eps**2/2)"
_CAR_YB = "(r*sin(w*t))"
_CAR_XB = f"sqrt(L**2 - {_CAR_YB}**2)"
_CAR_LL = "sqrt(xl**2 + yl**2)"
_CAR_LR = f"sqrt((xr - {_CAR_XB})**2 + (yr - {_CAR_YB})**2)"

CAR_AXIS = Problem(
    name="car-axis",
    odes={
        "xl": "ul",
        "yl": "vl",
        "xr": "ur",
        "yr": "vr",
        "ul": f"((L0 - {_CAR_LL})*xl/{_CAR_LL} + lam1*{_CAR_XB} + 2*lam2*(xl - xr))/{_CAR_K}",
        "vl": f"((L0 - {_CAR_LL})*yl/{_CAR_LL} + lam1*{_CAR_YB} + 2*lam2*(yl - yr))/{_CAR_K} - g",
        "ur": f"((L0 - {_CAR_LR})*(xr - {_CAR_XB})/{_CAR_LR} - 2*lam2*(xl - xr))/{_CAR_K}",
        "vr": f"((L0 - {_CAR_LR})*(yr - {_CAR_YB})/{_CAR_LR} - 2*lam2*(yl - yr))/{_CAR_K} - g",
    },
    algebraics=("lam1", "lam2"),
    constraints={"road": f"{_CAR_XB}*xl + {_CAR_YB}*yl", "axis": "(xl - xr)**2 + (yl - yr)**2 - L**2"},
    parameters=CAR_AXIS_PARAMETERS,
    # ex_caraxis.R's yini: xl = 0, yl = L0, xr = L, yr = L0, ul = ur = -L0/L, vl = vr = 0, lam = 0
    initial={"xl": 0.0, "yl": 0.5, "xr": 1.0, "yr": 0.5, "ul": -0.5, "vl": 0.0, "ur": -0.5, "vr": 0.0},
    t_span=(0.0, 3.0),
    compare_steps=120,  # the stiff springs' oscillation, period ~0.14: h = 0.025 first
    index=3,
    # caraxis.f, subroutine carsoln: y(1..10) at t = 3
    reference={
        "xl": 0.4934557842755629e-1,
        "yl": 0.4969894602303324e0,
        "xr": 0.1041742524885400e1,
        "yr": 0.3739110272652214e0,
        "ul": -0.7705836840321485e-1,
        "vl": 0.7446866596327776e-2,
        "ur": 0.1755681574942899e-1,
        "vr": 0.7703410437794031e0,
        "lam1": -0.4736886750784630e-2,
        "lam2": -0.1104680411345730e-2,
    },
    source="Car axis problem (index 3 mechanism, stiff and oscillatory) of the Test Set for IVP Solvers "
    "(Mazzia & Magherini, Univ. of Bari), caraxis.f rev. 1.2 (2006); reference at t = 3 from the test set",
)

# ---- Transistor amplifier, index 1 ---------------------------------------------------------
#
# Source: the Test Set for IVP Solvers (Mazzia & Magherini, Univ. of Bari), problem "Transistor
# Amplifier" (transamp.f, revision 1.3, 2006/10/25), read in deTestSet's copy: src/Ex_transistor.f
# for the equations (transres, transfunc) and the reference at t = 0.2 (transsoln: PSIDE at
# rtol = atol = 1e-14), R/ex_transistor.R for the 19 parameters and the initial values.  The
# circuit's node potentials U1..U8 obey M U' = f(t, U) with a singular capacitance matrix M:
# C1 joins nodes 1-2, C3 nodes 4-5, C5 nodes 7-8, C2 and C4 ground nodes 3 and 6.  Semi-explicit
# form: the capacitor voltages are the states (u12 = U1 - U2, U3, u45 = U4 - U5, U6, u78 = U7 - U8),
# Kirchhoff's current law at the two ends of each floating capacitor adds up to an algebraic
# equation (the capacitor's current cancels), and U1, U2, U4, U5, U7, U8 are algebraic, tied to the
# states by the three voltage definitions.  Same solution, index 1.  The input Ue = 0.1 sin(200 pi t)
# drives 20 periods on [0, 0.2]; the transistors' exponential g(U) = beta (exp(U / UF) - 1) makes
# the problem stiff.
TRANSISTOR_PARAMETERS = {
    "Ub": 6.0, "UF": 0.026, "alpha": 0.99, "beta": 1e-6, "R0": 1000.0,
    **{f"R{k}": 9000.0 for k in range(1, 10)},
    **{f"C{k}": k * 1e-6 for k in range(1, 6)},
}  # fmt: skip
_TRANSISTOR_G1 = "beta*(exp((U2 - U3)/UF) - 1)"
_TRANSISTOR_G2 = "beta*(exp((U5 - U6)/UF) - 1)"
# transfunc's currents f(1..8): the rows of M U' = f, each the current leaving node k through its
# resistors and transistor terminals (with the sign the test set gives it)
_TRANSISTOR_F = {
    1: "(U1 - 0.1*sin(200*pi*t))/R0",
    2: f"U2/R1 + (U2 - Ub)/R2 + (1 - alpha)*{_TRANSISTOR_G1}",
    3: f"U3/R3 - {_TRANSISTOR_G1}",
    4: f"(U4 - Ub)/R4 + alpha*{_TRANSISTOR_G1}",
    5: f"U5/R5 + (U5 - Ub)/R6 + (1 - alpha)*{_TRANSISTOR_G2}",
    6: f"U6/R7 - {_TRANSISTOR_G2}",
    7: f"(U7 - Ub)/R8 + alpha*{_TRANSISTOR_G2}",
    8: "U8/R9",
}

TRANSISTOR_AMPLIFIER = Problem(
    name="transistor-amplifier",
    # row 1 of M U' = f: -C1 (U1 - U2)' = f1; rows 3 and 6: -C2 U3' = f3, -C4 U6' = f6; rows 4, 7 alike
    odes={
        "u12": f"-({_TRANSISTOR_F[1]})/C1",
        "U3": f"-({_TRANSISTOR_F[3]})/C2",
        "u45": f"-({_TRANSISTOR_F[4]})/C3",
        "U6": f"-({_TRANSISTOR_F[6]})/C4",
        "u78": f"-({_TRANSISTOR_F[7]})/C5",
    },
    algebraics=("U1", "U2", "U4", "U5", "U7", "U8"),
    constraints={
        # rows 1 + 2, 4 + 5, 7 + 8 of M U' = f: the floating capacitor's current cancels
        "node12": f"{_TRANSISTOR_F[1]} + {_TRANSISTOR_F[2]}",
        "node45": f"{_TRANSISTOR_F[4]} + {_TRANSISTOR_F[5]}",
        "node78": f"{_TRANSISTOR_F[7]} + {_TRANSISTOR_F[8]}",
        "C1": "U1 - U2 - u12",
        "C3": "U4 - U5 - u45",
        "C5": "U7 - U8 - u78",
    },
    parameters=TRANSISTOR_PARAMETERS,
    # ex_transistor.R's yini: U = (0, Ub/(R2/R1 + 1), Ub/(R2/R1 + 1), Ub, Ub/(R6/R5 + 1), Ub/(R6/R5 + 1), Ub, 0)
    initial={
        "u12": -3.0,
        "U3": 3.0,
        "u45": 3.0,
        "U6": 3.0,
        "u78": 6.0,
        "U1": 0.0,
        "U2": 3.0,
        "U4": 6.0,
        "U5": 3.0,
        "U7": 6.0,
        "U8": 0.0,
    },
    t_span=(0.0, 0.2),
    compare_steps=800,  # 20 periods of the 100 Hz input: h = 2.5e-4 first, 40 steps a period
    index=1,
    # transamp.f, subroutine transsoln: U(1..8) at t = 0.2 (PSIDE, rtol = atol = 1e-14)
    reference={
        "U1": -0.5562145012262709e-2,
        "U2": 0.3006522471903042e1,
        "U3": 0.2849958788608128e1,
        "U4": 0.2926422536206241e1,
        "U5": 0.2704617865010554e1,
        "U6": 0.2761837778393145e1,
        "U7": 0.4770927631616772e1,
        "U8": 0.1236995868091548e1,
    },
    source="Transistor amplifier (index 1 circuit, stiff, driven at 100 Hz) of the Test Set for IVP Solvers "
    "(Mazzia & Magherini, Univ. of Bari), transamp.f rev. 1.3 (2006), in semi-explicit form with the "
    "capacitor voltages as states; reference at t = 0.2 from the test set (PSIDE at rtol = atol = 1e-14)",
)

# ---- Wheelset, index 2 ------------------------------------------------------------------------
#
# Source: the Test Set for IVP Solvers (Mazzia & Magherini, Univ. of Bari), problem "Wheelset"
# (wheel.f, revision 1.2, 2006/10/02; after B. Simeon, C. Fuehrer, P. Rentrop, Introduction to
# differential-algebraic equations in vehicle system dynamics, Surv. Math. Ind. 1 (1991) 1-37),
# read in deTestSet's copy: src/Ex_wheelset.f for the equations (reswhs, constm, creep, railp,
# wheelp) and the reference at t = 10 (wheelsoln), R/ex_wheelset.R for the parameters and the
# initial values.  A railway wheelset (a conical wheel profile on each side) runs at V = 30 m/s on
# a straight track of circular rail profiles: position p = (x, y, z, theta, phi) (lateral,
# vertical, longitudinal, yaw, roll), velocities v = p', the rotation-speed deviation beta, and on
# each side the contact point's coordinates (psi, xi) (angle on the wheel and lateral position).
# Straight track, no propulsion (the source's S = ALPHA = MA = FA = LA = 0): those terms vanish
# here.  The left wheel touches at xi > 0, the right one at xi < 0 (the source's |xi| and
# sign(xi) are written with those signs; the wheelset derails, and the source stops, before
# either changes).
#
# The test set's index-2 form has 17 unknowns: 11 states, and 6 algebraic (the 4 contact
# coordinates, from the index-1 contact conditions, and the 2 multipliers, from the velocity
# constraint G(p, q) v = 0).  That velocity constraint holds the algebraic contact coordinates,
# so it is not of the semi-explicit Hessenberg form a constraint-by-constraint index takes.  Here
# the contact coordinates are states with their rates as algebraic variables (q' = dq), which
# makes the 4 contact conditions index-2 constraints (their derivative determines dq) and keeps
# G(p, q) v = 0 of index 2: the same solution, 4 more unknowns.  The normal forces (the source's
# FNL, FNR: linear in the multipliers) and the creep forces before creep's scaling onto the
# friction circle (TX, TY on each side; the scaling multiplies them where they enter) are
# algebraic variables too, defined by index-1 equations: written out inline they would repeat the
# contact geometry dozens of times (over the parser's size limit).  27 unknowns in all.  The
# multipliers are the source's scaled ones (E1 = 1e4 lam1).  The Test Set's DASSL needed 58,510
# steps at 1e-9: the creep forces make the problem stiff, and the wheelset settles into a hunting
# oscillation (theta ~ -0.0136 at t = 10).
WHEELSET_PARAMETERS = {
    "MR": 16.08, "G": 9.81, "V": 30.0, "RN0": 0.1, "LI1": 0.0605, "LI2": 0.366, "MU": 0.12,
    "XL": 0.19, "CX": 6400.0, "CZ": 6400.0, "E": 1.3537956, "GG": 0.7115218, "SIGMA": 0.28,
    "GM": 7.92e10, "C11": 4.72772197, "C22": 4.27526987, "C23": 1.97203505, "DELTA0": 0.0262,
    "AR": 0.1506, "RS": 0.06,
}  # fmt: skip
# creep's own pi, to the 8 digits it is typed with there (the contact ellipse's size)
_WHEEL_PI = "3.1415926"
_WHEEL_OMEGA = "(V/RN0)"  # nominal angular speed of the wheels


def _wheel_side(side: str) -> dict:
    """The contact geometry and creep forces of one side (``"L"``: xi > 0, ``"R"``: xi < 0) as strings."""
    sign = "" if side == "L" else "-"  # the source's sign(xi)
    psi, xi = f"psi{side}", f"xi{side}"
    sis, cos_ = f"sin({psi})", f"cos({psi})"
    out = {}
    # wheelp: the cone r(xi) = RN0 + tan(DELTA0) (AR - |xi|), r' = -sign(xi) tan(DELTA0)
    out["RX"] = f"(RN0 + tan(DELTA0)*(AR - {sign}{xi}))"
    out["DRX"] = f"({'-' if side == 'L' else ''}tan(DELTA0))"
    rx, drx = out["RX"], out["DRX"]
    # the contact point's lateral position on the track
    xg = f"(x + {xi}*cos(theta)*cos(phi) + {rx}*(cos(theta)*sin(phi)*{cos_} - sin(theta)*{sis}))"
    # railp: a circle of radius RS; g(X) = T - RN0 - cos(DELTA0) RS, g' = sign(X) (AR + sin(DELTA0) RS - |X|)/T
    root = f"sqrt(RS**2 - ({sign}{xg} - AR - sin(DELTA0)*RS)**2)"
    out["DGX"] = dgx = f"({sign}(AR + sin(DELTA0)*RS - {sign}{xg})/{root})"
    out["D2GX"] = f"(-RS**2/{root}**3)"
    # constm: the constraint Jacobian's row G = (Q1..Q5) of this side's contact
    out["Q"] = (
        dgx,
        "(-1)",
        "0",
        f"({dgx}*({rx}*(-cos(theta)*{sis} - {cos_}*sin(phi)*sin(theta)) - cos(phi)*sin(theta)*{xi}))",
        f"(-{cos_}*{rx}*sin(phi) - cos(phi)*{xi} + {dgx}*(cos(phi)*{cos_}*cos(theta)*{rx} - cos(theta)*sin(phi)*{xi}))",
    )
    # the contact plane's angle delta
    if side == "L":
        w1 = f"(({drx}*cos(phi) - sin(phi)*{cos_})*cos(theta) + {sis}*sin(theta))"
        w2 = f"(-{drx}*sin(phi) - {cos_}*cos(phi))"
    else:
        w1 = f"(({drx}*cos(phi) - sin(phi)*{cos_})*cos(theta) + {sis}*sin(theta))"
        w2 = f"({drx}*sin(phi) + {cos_}*cos(phi))"
    out["DELTA"] = f"atan({w1}/{w2})"
    # the contact conditions G_2(p, q) = 0: the normals of wheel and rail are parallel
    out["contact1"] = (
        f"{dgx}*({drx}*sin(phi) + cos(phi)*{cos_}) + {drx}*cos(theta)*cos(phi) "
        f"- cos(theta)*sin(phi)*{cos_} + sin(theta)*{sis}"
    )
    out["contact2"] = f"{drx}*sin(theta)*cos(phi) - sin(theta)*sin(phi)*{cos_} - cos(theta)*{sis}"
    return out


_WL, _WR = _wheel_side("L"), _wheel_side("R")
_E1, _E2 = "(1e4*lam1)", "(1e4*lam2)"  # the source scales its multipliers


def _wheel_creep(side: str) -> dict:
    """creep: the tangential forces (TX, TY) of one side before saturation, given its normal force."""
    w, fn = (_WL, "FNL") if side == "L" else (_WR, "FNR")
    psi, xi, rx = f"psi{side}", f"xi{side}", w["RX"]
    sis, cos_ = f"sin({psi})", f"cos({psi})"
    sid, cod = f"sin({w['DELTA']})", f"cos({w['DELTA']})"
    sit, cot = f"sin(theta/{cod})", f"cos(theta/{cod})"
    om = f"({_WHEEL_OMEGA} + beta)"
    # the contact ellipse's semi-axis (Hertz), from the curvatures of wheel (a cone: 0) and rail
    rr = f"({rx}*sqrt(1 + {w['DRX']}**2))"
    b = f"(0.5*(-{w['D2GX']}/(1 + {w['DGX']}**2)**1.5))"
    # |FN| as sqrt(FN**2): the same value, and a derivative that sympy keeps real (that of Abs of a
    # symbol of unknown sign holds re/im parts, which no Jacobian can evaluate)
    c = f"(((3*sqrt({fn}**2)*(1 - SIGMA)*E)/(2*{_WHEEL_PI}*(0.5/{rr} + {b})*GM*sqrt(GG)))**(1/3))"
    # the relative velocity at the contact point, and the rolling velocity
    k1 = (
        f"(-{om}*{rx}*({sit}*{cos_} + {cot}*sin(phi)*{sis}) + vx "
        f"- vtheta*({rx}*({sit}*sin(phi)*{cos_} + {cot}*{sis}) + {xi}*{sit}*cos(phi)) "
        f"- vphi*{cot}*({xi}*sin(phi) - {rx}*cos(phi)*{cos_}))"
    )
    k2 = f"({om}*{rx}*cos(phi)*{sis} + vy + vphi*({xi}*cos(phi) + {rx}*sin(phi)*{cos_}))"
    k3 = (
        f"(-{om}*{rx}*({cot}*{cos_} - {sit}*sin(phi)*{sis}) + V + vz "
        f"- vtheta*({xi}*{cot}*cos(phi) + {rx}*({cot}*sin(phi)*{cos_} - {sit}*{sis})) "
        f"+ vphi*{sit}*({xi}*sin(phi) - {rx}*cos(phi)*{cos_}))"
    )
    vr = f"(0.5*sqrt(({k1} - 2*vx)**2 + ({k2} - 2*vy)**2 + ({k3} - 2*vz - 2*V)**2))"
    s = "-" if side == "L" else ""  # the spin creepage: -sin(delta) on the left, +sin(delta) on the right
    nux = f"(({sit}*{k1} + {cot}*{k3})/{vr})"
    nuy = f"(({cot}*{cod}*{k1} {'+' if side == 'L' else '-'} {sid}*{k2} - {sit}*{cod}*{k3})/{vr})"
    spin = f"(({s}{sid}*{om} + {cod}*vtheta)/{vr})"
    wt = f"(MU*{fn})"
    tx = f"(-{wt}*tanh(GM*{c}**2*C11*{nux}/{wt}))"
    ty = f"(-{wt}*tanh(GM*{c}**2*C22*{nuy}/{wt} + GM*{c}**3*C23*{spin}/{wt}))"
    return {"TX": tx, "TY": ty, "sit": sit, "cot": cot, "sid": sid, "cod": cod}


_CL, _CR = _wheel_creep("L"), _wheel_creep("R")
# creep scales (TX, TY) back onto the friction circle |T| <= |MU FN| where it leaves it (written
# here on the algebraic TX, TY: a Min of the whole creep expressions takes sympy minutes to build)
_SAT_L = "Min(1, MU*sqrt(FNL**2/(TXL**2 + TYL**2)))"
_SAT_R = "Min(1, MU*sqrt(FNR**2/(TXR**2 + TYR**2)))"
# the creep forces in the nominal frame (creep's TL, TR)
_TL = (
    f"({_CL['sit']}*TXL + {_CL['cot']}*{_CL['cod']}*TYL)*{_SAT_L}",
    f"({_CL['sid']}*TYL)*{_SAT_L}",
    f"({_CL['cot']}*TXL - {_CL['sit']}*{_CL['cod']}*TYL)*{_SAT_L}",
)
_TR = (
    f"({_CR['sit']}*TXR + {_CR['cot']}*{_CR['cod']}*TYR)*{_SAT_R}",
    f"(-{_CR['sid']}*TYR)*{_SAT_R}",
    f"({_CR['cot']}*TXR - {_CR['sit']}*{_CR['cod']}*TYR)*{_SAT_R}",
)


def _wheel_euler(side: str) -> tuple:
    """The creep forces' moments of one side on yaw, roll and the rotation (reswhs's W1 / W2 terms)."""
    w, t = (_WL, _TL) if side == "L" else (_WR, _TR)
    psi, xi, rx = f"psi{side}", f"xi{side}", w["RX"]
    sis, cos_ = f"sin({psi})", f"cos({psi})"
    yaw = (
        f"(-({xi}*sin(theta) + {rx}*{sis}*cos(theta)*cos(phi))*{t[0]} - {rx}*{sis}*sin(phi)*{t[1]} "
        f"+ (-{xi}*cos(theta) + {rx}*{sis}*sin(theta)*cos(phi))*{t[2]})"
    )
    roll = (
        f"(-({xi}*cos(theta)*sin(phi) - {rx}*{cos_}*cos(theta)*cos(phi))*{t[0]} "
        f"+ ({xi}*cos(phi) + {rx}*{cos_}*sin(phi))*{t[1]} "
        f"+ ({xi}*sin(theta)*sin(phi) - {rx}*{cos_}*sin(theta)*cos(phi))*{t[2]})"
    )
    spin = (
        f"(-{rx}*({cos_}*sin(theta) + {sis}*cos(theta)*sin(phi))*{t[0]} + {rx}*{sis}*cos(phi)*{t[1]} "
        f"- {rx}*({cos_}*cos(theta) - {sis}*sin(theta)*sin(phi))*{t[2]})"
    )
    return yaw, roll, spin


_EL, _ER = _wheel_euler("L"), _wheel_euler("R")
_QL, _QR = _WL["Q"], _WR["Q"]
_WOM = f"({_WHEEL_OMEGA} + beta)"
# reswhs's right-hand sides of M v' = f (DELTA(6..11)); the mass matrix is diag(MR, MR, MR) on the
# translations and [[LI2 cos(phi), 0, 0], [0, LI2, 0], [LI1 sin(phi), 0, LI1]] on (theta, phi, beta)
_WHEEL_F = {
    "vx": f"{_TL[0]} + {_TR[0]} + {_QL[0]}*{_E1} + {_QR[0]}*{_E2} - 2*CX*x",
    "vy": f"{_TL[1]} + {_TR[1]} - MR*G + {_QL[1]}*{_E1} + {_QR[1]}*{_E2}",
    "vz": f"{_TL[2]} + {_TR[2]} - 2*CZ*z",
    "vtheta": (
        f"LI2*vtheta*vphi*sin(phi) - LI1*{_WOM}*vphi - (LI1 - LI2)*vtheta*sin(phi)*vphi "
        f"+ {_EL[0]} + {_ER[0]} + cos(phi)*(-2*XL**2*CZ*theta) + {_QL[3]}*{_E1} + {_QR[3]}*{_E2}"
    ),
    "vphi": (
        f"LI1*{_WOM}*vtheta*cos(phi) + (LI1 - LI2)*vtheta*sin(phi)*vtheta*cos(phi) "
        f"+ {_EL[1]} + {_ER[1]} + {_QL[4]}*{_E1} + {_QR[4]}*{_E2}"
    ),
    "beta": f"-LI1*vtheta*vphi*cos(phi) + {_EL[2]} + {_ER[2]} + sin(phi)*(-2*XL**2*CZ*theta)",
}
# the normal forces (reswhs's FNL, FNR) from the multipliers, through the contact planes' angles
_WHEEL_W1 = f"({_QL[0]}*{_E1} + {_QR[0]}*{_E2})"
_WHEEL_W2 = f"(-{_E1} - {_E2})"
_WHEEL_DETER = f"(-sin({_WL['DELTA']})*cos({_WR['DELTA']}) - sin({_WR['DELTA']})*cos({_WL['DELTA']}))"
_WHEEL_QDOT = {"psiL": "dpsiL", "xiL": "dxiL", "psiR": "dpsiR", "xiR": "dxiR"}

WHEELSET = Problem(
    name="wheelset",
    odes={
        "x": "vx",
        "y": "vy",
        "z": "vz",
        "theta": "vtheta",
        "phi": "vphi",
        "vx": f"({_WHEEL_F['vx']})/MR",
        "vy": f"({_WHEEL_F['vy']})/MR",
        "vz": f"({_WHEEL_F['vz']})/MR",
        "vtheta": f"({_WHEEL_F['vtheta']})/(LI2*cos(phi))",
        "vphi": f"({_WHEEL_F['vphi']})/LI2",
        "beta": f"({_WHEEL_F['beta']})/LI1 - sin(phi)*({_WHEEL_F['vtheta']})/(LI2*cos(phi))",
        **_WHEEL_QDOT,
    },
    algebraics=("dpsiL", "dxiL", "dpsiR", "dxiR", "lam1", "lam2", "FNL", "FNR", "TXL", "TYL", "TXR", "TYR"),
    constraints={
        "contactL1": _WL["contact1"],
        "contactL2": _WL["contact2"],
        "contactR1": _WR["contact1"],
        "contactR2": _WR["contact2"],
        # G(p, q) v = 0, the contact points' normal velocities (index 2: the multipliers enter v')
        "velocityL": " + ".join(f"{q}*{v}" for q, v in zip(_QL, ("vx", "vy", "vz", "vtheta", "vphi"), strict=True)),
        "velocityR": " + ".join(f"{q}*{v}" for q, v in zip(_QR, ("vx", "vy", "vz", "vtheta", "vphi"), strict=True)),
        "normalL": f"FNL*{_WHEEL_DETER} - (cos({_WR['DELTA']})*{_WHEEL_W1} - sin({_WR['DELTA']})*{_WHEEL_W2})",
        "normalR": f"FNR*{_WHEEL_DETER} - (-cos({_WL['DELTA']})*{_WHEEL_W1} - sin({_WL['DELTA']})*{_WHEEL_W2})",
        "creepXL": f"TXL - {_CL['TX']}",
        "creepYL": f"TYL - {_CL['TY']}",
        "creepXR": f"TXR - {_CR['TX']}",
        "creepYR": f"TYR - {_CR['TY']}",
    },
    parameters=WHEELSET_PARAMETERS,
    # ex_wheelset.R's yini (its q1..q4 = psiR, xiR, psiL, xiL and lam1, lam2); the velocities are 0
    initial={
        "x": 0.14941e-02,
        "y": 0.40089e-06,
        "z": 0.11241e-05,
        "theta": -0.28573e-03,
        "phi": 0.26459e-03,
        **{v: 0.0 for v in ("vx", "vy", "vz", "vtheta", "vphi", "beta")},
        "psiR": -7.4122380357667139e-06,
        "xiR": -0.1521364296121248,
        "psiL": 7.5634406395172940e-06,
        "xiL": 0.1490635714733819,
    },
    # the source's multipliers at t = 0 (5 digits: starts, not values); the normal and creep forces
    # they give there (Newton from 0 divides by the zero normal force)
    guesses={
        "lam1": -8.3593e-3,
        "lam2": -7.4144e-3,
        "FNL": 83.62,
        "FNR": 74.17,
        "TXL": 9.56,
        "TYL": -7.71,
        "TXR": -8.54,
        "TYR": -7.92,
    },
    t_span=(0.0, 10.0),
    index=2,
    # wheel.f, subroutine wheelsoln: y(1..17) at t = 10 (DASSL at rtol = atol = 1e-9 on p, v, q;
    # the multipliers excluded from error control)
    reference={
        "x": 0.86355386965811e-02,
        "y": 0.13038281022727e-04,
        "z": -0.93635784016818e-04,
        "theta": -0.13642299804033e-01,
        "phi": 0.15292895005422e-02,
        "vx": -0.76985374142666e-01,
        "vy": -0.25151106429207e-03,
        "vz": 0.20541188079539e-02,
        "vtheta": -0.23904837703692e00,
        "vphi": -0.13633468454173e-01,
        "beta": -0.24421377661131e00,
        "psiR": -0.33666751972196e-03,
        "xiR": -0.15949425684022e00,
        "psiL": 0.37839614386969e-03,
        "xiL": 0.14173214964613e00,
        "lam1": -0.10124044903201e-01,
        "lam2": -0.56285630573753e-02,
    },
    source="Wheelset (index 2 railway mechanism, contact geometry and creep forces) of the Test Set for IVP "
    "Solvers (Mazzia & Magherini, Univ. of Bari), wheel.f rev. 1.2 (2006), after Simeon, Fuehrer & Rentrop "
    "(1991); contact coordinates as states with their rates algebraic; reference at t = 10 from the test set "
    "(DASSL, rtol = atol = 1e-9)",
)


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

# ---- a bouncing ball: events ---------------------------------------------------------------------
#
# Dropped from h = 1 at rest, g = 9.81, restitution e = 0.8: the k-th impact is at
# t_k = sqrt(2/g) (1 + 2 (e + ... + e^(k-1))), the speed after it u_k = e^k sqrt(2 g), and on the flight
# after it h = u_k s - g s^2 / 2, v = u_k - g s with s = t - t_k.  The impacts accumulate at
# sqrt(2/g) (1 + 2 e / (1 - e)) = 4.0637 (Zeno): the span ends before it, after 6 impacts.
# (e is a number in the reset, not a parameter: compile() refuses a parameter used only in an event, issue 40
# item 10)
BALL_G, BALL_E, BALL_IMPACTS = 9.81, 0.8, 12  # (12 impacts: the closed form holds up to t = 3.9)


def _ball_exact() -> tuple[dict, tuple]:
    """The bouncing ball's closed form: Piecewise h and v, each piece ``t < t_k`` (the values at an
    impact are those after it), and the impact times."""
    g, e = BALL_G, BALL_E
    times = [float(np.sqrt(2 / g) * (1 + 2 * sum(e**j for j in range(1, k)))) for k in range(1, BALL_IMPACTS + 1)]
    speeds = [float(e**k * np.sqrt(2 * g)) for k in range(1, BALL_IMPACTS + 1)]
    h = [f"(1 - {g / 2!r}*t**2, t < {times[0]!r})"]
    v = [f"(-{g!r}*t, t < {times[0]!r})"]
    for k, (t_k, u_k) in enumerate(zip(times, speeds, strict=True)):
        until = f"t < {times[k + 1]!r}" if k + 1 < len(times) else "True"
        h.append(f"({u_k!r}*(t - {t_k!r}) - {g / 2!r}*(t - {t_k!r})**2, {until})")
        v.append(f"({u_k!r} - {g!r}*(t - {t_k!r}), {until})")
    exact = {"h": f"Piecewise({', '.join(h)})", "v": f"Piecewise({', '.join(v)})"}
    return exact, tuple(repr(t_k) for t_k in times)


_BALL_EXACT, _BALL_IMPACT_TIMES = _ball_exact()

BOUNCING_BALL = Problem(
    name="bouncing-ball",
    odes={"h": "v", "v": "-g"},
    algebraics=(),
    constraints={},
    parameters={"g": BALL_G},
    initial={"h": 1.0, "v": 0.0},
    t_span=(0.0, 3.0),
    index=0,
    # h = 0.075 first: at h = 0.3 a flight of 0.30 lies inside two outputs and its impacts go unseen (issue 40)
    compare_steps=40,
    exact=_BALL_EXACT,
    exact_events={"floor": _BALL_IMPACT_TIMES},
    events=({"name": "floor", "when": "h", "direction": -1, "reset": {"v": f"-{BALL_E!r}*v"}},),
    source="a ball dropped from h = 1 that bounces with restitution 0.8 (an event with a reset; closed form "
    "by parabolas between the impacts)",
)

PROBLEMS = {
    p.name: p
    for p in (
        HESSENBERG, PENDULUM, PENDULUM_INDEX3, ROBERTSON, SQUEEZER, AKZO_NOBEL, CAR_AXIS, TRANSISTOR_AMPLIFIER,
        WHEELSET, BOUNCING_BALL,
    )
}  # fmt: skip

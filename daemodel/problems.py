"""A small library of test problems: equations as data, initial values, interval, exact
solution where one exists, and the source.  Tests, benchmarks and examples draw on it; the
equations are strings so the library exercises the same parser users do.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import sympy as sp

from daemodel.backends.grids import SWEEP_FIRST_STEPS
from daemodel.compiling.init import NUMERIC_MODULES
from daemodel.declaring.model import Model
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
    reference: dict = field(default_factory=dict)
    source: str = ""
    compare_steps: int = SWEEP_FIRST_STEPS

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

PROBLEMS = {
    p.name: p
    for p in (
        HESSENBERG, PENDULUM, PENDULUM_INDEX3, ROBERTSON, SQUEEZER, AKZO_NOBEL, CAR_AXIS, TRANSISTOR_AMPLIFIER,
    )
}  # fmt: skip

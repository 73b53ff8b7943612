"""The chemical Akzo Nobel problem from the Test Set for IVP Solvers (index 1, stiff), with the
test set's reference at t = 180."""

from __future__ import annotations

from daemodel.problems.problem import Problem

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

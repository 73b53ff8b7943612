"""HIRES from the Test Set for IVP Solvers (a stiff ODE of 8 equations, plant physiology), with the
test set's reference at t = 321.8122."""

from __future__ import annotations

from daemodel.problems.problem import Problem

# ---- HIRES, index 0 ----------------------------------------------------------------------------
#
# Source: F. Mazzia and C. Magherini, Test Set for Initial Value Problem Solvers, release 2.4
# (Dept. of Mathematics, Univ. of Bari, February 2008), the ODE problem "HIRES" (hires.f, revision
# 1.2, 2006/10/02), after Schaefer (1975) as in Hairer & Wanner, Solving ODEs II, IV.10; read in
# deTestSet's copy: src/Ex_hires.f (hiresfun: the equations; hiressol: the reference, computed by
# RADAU5 in quadruple precision at rtol = atol = h0 = 1.1e-18) and R/ex_hires.R (k1..k9, oks, y(0),
# [0, 321.8122]).  "High Irradiance RESponse": how light drives phytochrome, the pigment through
# which a plant's growth follows light, between its red-absorbing form Pr and far-red-absorbing
# form Pfr, free and bound to a receptor X (and, as PfrX2E, to an enzyme E).  The unknowns keep the
# test set's order y1..y8 under the species' names.
HIRES_PARAMETERS = {
    "k1": 1.71, "k2": 0.43, "k3": 8.32, "k4": 0.69, "k5": 0.035,
    "k6": 8.32, "k7": 280.0, "k8": 0.69, "k9": 0.69, "oks": 0.0007,
}  # fmt: skip

HIRES = Problem(
    name="hires",
    odes={
        "Pr": "-k1*Pr + k2*Pfr + k6*PrX + oks",
        "Pfr": "k1*Pr - (k2 + k3)*Pfr",
        "PrX": "-(k6 + k1)*PrX + k2*PfrX + k5*PrX2",
        "PfrX": "k3*Pfr + k1*PrX - (k4 + k2)*PfrX",
        "PrX2": "-(k5 + k1)*PrX2 + k2*(PfrX2 + PfrX2E)",
        "PfrX2": "-k7*PfrX2*E + k8*PfrX + k1*PrX2 - k2*PfrX2 + k8*PfrX2E",
        "PfrX2E": "k7*PfrX2*E - (k2 + k8 + k9)*PfrX2E",
        "E": "-k7*PfrX2*E + (k2 + k8 + k9)*PfrX2E",  # (hiresfun: f(8) = -f(7))
    },
    algebraics=(),
    constraints={},
    parameters=HIRES_PARAMETERS,
    initial={"Pr": 1.0, "Pfr": 0.0, "PrX": 0.0, "PfrX": 0.0, "PrX2": 0.0, "PfrX2": 0.0, "PfrX2E": 0.0, "E": 0.0057},
    t_span=(0.0, 321.8122),
    compare_steps=400,  # (the start: PfrX2 and E react at k7 = 280; 200 fixed steps keep no digit)
    index=0,
    # hires.f, subroutine solut (hiressol): y(1..8) at t = 321.8122
    reference={
        "Pr": 0.7371312573325668e-3,
        "Pfr": 0.1442485726316185e-3,
        "PrX": 0.5888729740967575e-4,
        "PfrX": 0.1175651343283149e-2,
        "PrX2": 0.2386356198831331e-2,
        "PfrX2": 0.6238968252742796e-2,
        "PfrX2E": 0.2849998395185769e-2,
        "E": 0.2850001604814231e-2,
    },
    source="HIRES problem (stiff ODE of 8 equations, Schaefer 1975) of the Test Set for IVP Solvers "
    "(Mazzia & Magherini, Univ. of Bari), hires.f rev. 1.2 (2006); reference at t = 321.8122 from the test set",
)

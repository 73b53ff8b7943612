"""The ring modulator from the Test Set for IVP Solvers (an ODE of 15 equations, stiff, with the
diodes' exponentials switching on and off at 10 kHz), with the test set's reference at t = 1e-3."""

from __future__ import annotations

from daemodel.problems.problem import Problem

# ---- Ring modulator, index 0 -------------------------------------------------------------------
#
# Source: F. Mazzia and C. Magherini, Test Set for Initial Value Problem Solvers, release 2.4
# (Dept. of Mathematics, Univ. of Bari, February 2008), the ODE problem "Ring Modulator"
# (ringmod.f, revision 1.2, 2006/10/02), after Horneber (1976) as in Kampowsky, Rentrop & Schmidt
# (Surv. Math. Ind. 2, 1992), contributed by CWI's parallel-IVP group; read in deTestSet's copy:
# src/Ex_ring.f (ringfunc: the equations; ringsoln: the reference) and R/ex_ring.R (the 16
# parameters, y(0) = 0, [0, 1e-3]).  With Cs = 2e-12 (the capacitance at the diodes' nodes) it is
# a stiff ODE of 15 equations (Cs = 0 makes it an index-2 DAE).  The ring's two inputs are the
# signal Uin1 = 0.5 sin(2000 pi t) (1 kHz) and the carrier Uin2 = 2 sin(20000 pi t) (10 kHz); each
# of the four diodes conducts q(U) = gamma (exp(delta U) - 1) (delta = 17.7, so q grows e-fold per
# 56 mV), and the carrier switches them in turn.  The unknowns keep the test set's numbering, read
# off the equations: y1, y2 are the voltages across the two capacitors C, y3..y6 those across the
# four Cs at the diodes' ends, y7 that across Cp; y8, y9 are the currents through the two Lh, y10,
# y12 through Ls2, y11, y13 through Ls3, y14 (with Ri and Uin1) and y15 (with Rc) through Ls1.
RING_MODULATOR_PARAMETERS = {
    "C": 1.6e-8, "Cs": 2e-12, "Cp": 1e-8, "R": 25e3, "Rp": 50.0,
    "Lh": 4.45, "Ls1": 2e-3, "Ls2": 5e-4, "Ls3": 5e-4,
    "Rg1": 36.3, "Rg2": 17.3, "Rg3": 17.3, "Ri": 50.0, "Rc": 600.0,
    "gamma": 40.67286402e-9, "delta": 17.7493332,
}  # fmt: skip
_UIN1 = "0.5*sin(2000*pi*t)"
_UIN2 = "2*sin(20000*pi*t)"
# ringfunc's diode voltages UD1..UD4 and currents q(UDk) = gamma (exp(delta UDk) - 1)
_RING_UD = {
    "q1": f"y3 - y5 - y7 - {_UIN2}",
    "q2": f"-y4 + y6 - y7 - {_UIN2}",
    "q3": f"y4 + y5 + y7 + {_UIN2}",
    "q4": f"-y3 - y6 + y7 + {_UIN2}",
}


def _ring(expr: str) -> str:
    """A ring modulator right-hand side with the diode currents written out."""
    for name, voltage in _RING_UD.items():
        expr = expr.replace(name, f"gamma*(exp(delta*({voltage})) - 1)")
    return expr


RING_MODULATOR = Problem(
    name="ring-modulator",
    odes={
        "y1": "(y8 - 0.5*y10 + 0.5*y11 + y14 - y1/R)/C",
        "y2": "(y9 - 0.5*y12 + 0.5*y13 + y15 - y2/R)/C",
        "y3": _ring("(y10 - q1 + q4)/Cs"),
        "y4": _ring("(-y11 + q2 - q3)/Cs"),
        "y5": _ring("(y12 + q1 - q3)/Cs"),
        "y6": _ring("(-y13 - q2 + q4)/Cs"),
        "y7": _ring("(-y7/Rp + q1 + q2 - q3 - q4)/Cp"),
        "y8": "-y1/Lh",
        "y9": "-y2/Lh",
        "y10": "(0.5*y1 - y3 - Rg2*y10)/Ls2",
        "y11": "(-0.5*y1 + y4 - Rg3*y11)/Ls3",
        "y12": "(0.5*y2 - y5 - Rg2*y12)/Ls2",
        "y13": "(-0.5*y2 + y6 - Rg3*y13)/Ls3",
        "y14": f"(-y1 + {_UIN1} - (Ri + Rg1)*y14)/Ls1",
        "y15": "(-y2 - (Rc + Rg1)*y15)/Ls1",
    },
    algebraics=(),
    constraints={},
    parameters=RING_MODULATOR_PARAMETERS,
    initial={f"y{k}": 0.0 for k in range(1, 16)},
    t_span=(0.0, 1e-3),
    # the windings ringing with Cs, period 2 pi sqrt(Ls2 Cs) = 2e-7, restarted at every switch of the
    # diodes: h = 5e-8 first, 4 steps a period
    compare_steps=20_000,
    index=0,
    # ringmod.f's reference (deTestSet's subroutine ringsoln): y(1..15) at t = 1e-3, by RADAU (Hairer's
    # variable-order code) at rtol = atol = 1e-12, h0 = 1e-14 (23,541 accepted steps).  They carry 9.6 digits:
    # radau at rtol 1e-10, 1e-12 and 1e-13 (s = 7) agrees with itself to 2e-11 in y1..y7 (5e-11 in the
    # tiny y9) and with them to 2.7e-10 (y3), as RADAU's internal tolerance at 1e-12, 0.1 rtol^(2/3) = 1e-9,
    # lets it
    reference={
        "y1": -0.2339057358486745e-1,
        "y2": -0.7367485485540825e-2,
        "y3": 0.2582956709291169,
        "y4": -0.4064465721283450,
        "y5": -0.4039455665149794,
        "y6": 0.2607966765422943,
        "y7": 0.1106761861269975,
        "y8": 0.2939904342435596e-6,
        "y9": -0.2840029933642329e-7,
        "y10": 0.7267198267264553e-3,
        "y11": 0.7929487196960840e-3,
        "y12": -0.7255283495698965e-3,
        "y13": -0.7941401968526521e-3,
        "y14": 0.7088495416976114e-4,
        "y15": 0.2390059075236570e-4,
    },
    source="Ring modulator (stiff ODE of 15 equations, Cs = 2e-12) of the Test Set for IVP Solvers, "
    "release 2.4 (Mazzia & Magherini, Univ. of Bari, 2008), ringmod.f rev. 1.2 (2006), after Horneber (1976) "
    "and Kampowsky, Rentrop & Schmidt (1992); reference at t = 1e-3 from the test set (RADAU at "
    "rtol = atol = 1e-12)",
)

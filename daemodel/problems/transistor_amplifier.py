"""The transistor amplifier from the Test Set for IVP Solvers (an index-1 circuit, stiff, driven at
100 Hz) in semi-explicit form, with the test set's reference at t = 0.2."""

from __future__ import annotations

from daemodel.problems.problem import Problem

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

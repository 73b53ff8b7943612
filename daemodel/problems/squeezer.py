"""Andrews' squeezing mechanism (the seven-body mechanism) from the Test Set for IVP Solvers, in
index-2 form, with the test set's parameters, initial values and reference at t = 0.03."""

from __future__ import annotations

from daemodel.problems.problem import Problem

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
    # the positions: the index-1 components, whose error an adaptive code controls (the velocities,
    # accelerations and multipliers are of higher index); dm.bench reads the scd from these
    scd_names=tuple(f"q{k}" for k in range(1, 8)),
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

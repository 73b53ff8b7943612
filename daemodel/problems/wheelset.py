"""The wheelset from the Test Set for IVP Solvers (a railway wheelset on a straight track, index
2), with the test set's reference at t = 10."""

from __future__ import annotations

from daemodel.problems.problem import Problem

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

"""The car axis problem from the Test Set for IVP Solvers (index 3, stiff and oscillatory), with
the test set's reference at t = 3."""

from __future__ import annotations

from daemodel.problems.problem import Problem

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

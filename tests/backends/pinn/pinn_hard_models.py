"""Models on which radau at a fixed step is flagged or raises (tests/backends/pinn): a double
pendulum, a stiff CSTR and a diode rectifier, declared through the public API."""

import math

import sympy as sp

import daemodel as dm


def double_pendulum(angle1: float, angle2: float) -> dm.Model:
    """Two point masses on massless rods of length 1 (Cartesian coordinates, index 3): the first
    hangs from the origin at ``angle1`` (degrees from the downward vertical), the second from the
    first at ``angle2``, both at rest; l1 and l2 are the rods' tensions per unit length and mass."""
    m = dm.Model("double_pendulum")
    x1, y1, x2, y2, u1, v1, u2, v2 = m.states("x1 y1 x2 y2 u1 v1 u2 v2")
    l1, l2 = m.algebraics("l1 l2")
    g = m.parameter("g", 9.81)
    for position, velocity in ((x1, u1), (y1, v1), (x2, u2), (y2, v2)):
        m.ode(position, velocity)
    m.ode(u1, -l1 * x1 + l2 * (x2 - x1))
    m.ode(v1, -l1 * y1 + l2 * (y2 - y1) - g)
    m.ode(u2, -l2 * (x2 - x1))
    m.ode(v2, -l2 * (y2 - y1) - g)
    m.constraint(x1**2 + y1**2 - 1, name="rod1")
    m.constraint((x2 - x1) ** 2 + (y2 - y1) ** 2 - 1, name="rod2")
    a1, a2 = math.radians(angle1), math.radians(angle2)
    X1, Y1 = math.sin(a1), -math.cos(a1)
    m.initial(x1=X1, y1=Y1, x2=X1 + math.sin(a2), y2=Y1 - math.cos(a2), u1=0.0, v1=0.0, u2=0.0, v2=0.0)
    return m


def cstr() -> dm.Model:
    """An exothermic continuous stirred tank (Seborg's, time in minutes, scaled): concentration C,
    temperature T, and the Arrhenius reaction rate r algebraic (index 1, stiff in T)."""
    m = dm.Model("cstr")
    C, T = m.states("C T")
    (r,) = m.algebraics("r")
    values = {"F": 1.0, "Cf": 1.0, "Tf": 350.0, "Tc": 300.0, "k0": 7.2e10, "EoverR": 8750.0, "J": 209.2, "UA": 2.092}
    p = {name: m.parameter(name, value) for name, value in values.items()}
    m.ode(C, p["F"] * (p["Cf"] - C) - r)
    m.ode(T, p["F"] * (p["Tf"] - T) + p["J"] * r + p["UA"] * (p["Tc"] - T))
    m.constraint(r - p["k0"] * sp.exp(-p["EoverR"] / T) * C, name="rate")
    m.initial(C=0.5, T=350.0)
    return m


def rectifier() -> dm.Model:
    """A half-wave diode rectifier (Shockley diode, Vt = 26 mV) charging a small capacitor C loaded
    by RL: the diode current is algebraic and switches on and off sharply (stiff)."""
    m = dm.Model("rectifier")
    (vC,) = m.states("vC")
    (iD,) = m.algebraics("iD")
    values = {"C": 0.01, "RL": 2.0, "Rs": 0.5, "Is": 1e-6, "Vt": 0.026}
    p = {name: m.parameter(name, value) for name, value in values.items()}
    source = sp.sin(2 * sp.pi * sp.Symbol("t"))
    m.ode(vC, (iD - vC / p["RL"]) / p["C"])
    m.constraint(iD - p["Is"] * (sp.exp((source - vC - p["Rs"] * iD) / p["Vt"]) - 1), name="diode")
    m.initial(vC=0.0)
    return m


def root() -> dm.Model:
    """x' = sqrt(0.05 - t) + w, 0 = x - w (index 1): the right-hand side leaves its domain at t = 0.05."""
    m = dm.Model("root")
    m.states(["x"])
    m.algebraics(["w"])
    m.ode("x", "sqrt(0.05 - t) + w")
    m.constraint("x - w", name="tie")
    m.initial(x=0.0)
    return m

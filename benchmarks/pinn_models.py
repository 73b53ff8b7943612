"""Models people bring, declared through the public API: the Radau-PINN's cases beyond the paper.

Each ``build_*`` returns a :class:`daemodel.Model`; :data:`CASES` lists what
``benchmarks/pinn_ceiling.py`` and ``tests/backends/test_pinn_models.py`` solve: the model, the span, the
step and the stages, and the batch (initial states or parameters) where there is one.

* ``heat``: the heat equation by lines, 20 interior points, the boundary values algebraic
  (a driven Dirichlet end and a Robin end): 22 unknowns, index 1, stiff (h lambda ~ 90).
* ``grid``: a 3-bus power grid, two generators (swing equations) and a constant-power load,
  lossless lines, the six bus voltages and angles algebraic (power-flow balance): index 1.
* ``slider_crank`` / ``slider_crank_index2``: a planar slider-crank, the crank pin and the
  slider as point masses joined by a massless rod, driven by a torque, with Lagrange
  multipliers: position constraints (index 3, reduced to 2 by the compiler) or velocity
  constraints (index 2).
* ``sqrt_decay``: ``y' = -z, 0 = z^2 - y``, singular at z = 0 (g_z = 2z): the guess z = 2
  picks the root.  Exact: y = (2 - t/2)^2, z = 2 - t/2.
* ``rectifier``: a half-wave diode rectifier with an RC load, the diode current algebraic
  through Shockley's exponential (stiff), for 1000 load resistances in one batch.
* The Test Set problems daemodel compares already: akzo-nobel, the transistor amplifier, the
  squeezer, the car axis (:mod:`daemodel.problems`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import sympy as sp

import daemodel as dm


def build_heat(points: int = 20) -> dm.Model:
    """u_t = u_xx on [0, 1] by lines: ``points`` interior values as states, the two boundary
    values algebraic: u(0, t) = sin(2 pi t) / 2 (Dirichlet) and -u_x(1, t) = k (u(1, t) - u_air)
    (Robin), each discretised at the boundary."""
    m = dm.Model("heat")
    u = m.states([f"u{i}" for i in range(1, points + 1)])
    left, right = m.algebraics("uL uR")
    k, air = m.parameter("k", 2.0), m.parameter("u_air", 0.2)
    t = sp.Symbol("t")
    dx = 1.0 / (points + 1)
    values = [left, *u, right]
    for i in range(1, points + 1):
        m.ode(u[i - 1], (values[i - 1] - 2 * values[i] + values[i + 1]) / dx**2)
    m.constraint(left - sp.sin(2 * sp.pi * t) / 2, name="driven_end")
    m.constraint((right - u[-1]) / dx + k * (right - air), name="robin_end")
    m.initial(**{f"u{i}": math.sin(math.pi * i * dx) for i in range(1, points + 1)})
    return m


def build_grid() -> dm.Model:
    """Two generators behind reactances xd (swing equations: rotor angle d, speed w relative to
    the grid's) and a constant-power load on a triangle of lossless lines; every bus voltage V
    and angle th algebraic, from the active and reactive power balance at the three buses."""
    m = dm.Model("grid")
    d1, w1, d2, w2 = m.states("d1 w1 d2 w2")
    V1, th1, V2, th2, V3, th3 = m.algebraics("V1 th1 V2 th2 V3 th3")
    values = {"E1": 1.1, "E2": 1.05, "xd1": 0.3, "xd2": 0.35, "M1": 0.2, "M2": 0.15, "D1": 0.3, "D2": 0.25}
    values |= {"Pm1": 0.8, "Pm2": 0.6, "PL": 1.35, "QL": 0.45, "b12": 8.0, "b13": 6.0, "b23": 7.0}
    p = {name: m.parameter(name, value) for name, value in values.items()}
    V, th = (V1, V2, V3), (th1, th2, th3)
    b = {(0, 1): p["b12"], (0, 2): p["b13"], (1, 2): p["b23"]}

    def line(i, j):
        return b[(min(i, j), max(i, j))]

    def network(i):  # power the lines take out of bus i
        others = [j for j in range(3) if j != i]
        P = sum(V[i] * V[j] * line(i, j) * sp.sin(th[i] - th[j]) for j in others)
        Q = sum(V[i] * (V[i] - V[j] * sp.cos(th[i] - th[j])) * line(i, j) for j in others)
        return P, Q

    generators = ((d1, w1), (d2, w2))
    for i, (d, w) in enumerate(generators):
        E, xd, M, D, Pm = (p[f"{name}{i + 1}"] for name in ("E", "xd", "M", "D", "Pm"))
        Pg = E * V[i] * sp.sin(d - th[i]) / xd
        Qg = (E * V[i] * sp.cos(d - th[i]) - V[i] ** 2) / xd
        m.ode(d, w)
        m.ode(w, (Pm - Pg - D * w) / M)
        P, Q = network(i)
        m.constraint(Pg - P, name=f"P{i + 1}")
        m.constraint(Qg - Q, name=f"Q{i + 1}")
    P, Q = network(2)
    m.constraint(-p["PL"] - P, name="P3")
    m.constraint(-p["QL"] - Q, name="Q3")
    m.initial(d1=0.35, w1=0.2, d2=0.25, w2=0.0)
    m.guess(V1=1.0, V2=1.0, V3=1.0, th1=0.0, th2=0.0, th3=0.0)  # the normal operating branch, not V ~ 0
    return m


SLIDER_CRANK = {"r": 0.2, "l": 0.5, "m1": 1.0, "m2": 2.0, "torque": 0.5, "c": 0.5, "g": 9.81}


def _slider_crank(name: str, index: int) -> dm.Model:
    """The crank pin (x1, y1) of mass m1 on a circle of radius r, the slider x3 of mass m2 on
    the x-axis, a massless rod of length l between them, a torque on the crank, viscous
    friction c on the slider, gravity g on the pin; multipliers lam1 (crank), lam2 (rod)."""
    m = dm.Model(name)
    x1, y1, x3, u1, v1, u3 = m.states("x1 y1 x3 u1 v1 u3")
    lam1, lam2 = m.algebraics("lam1 lam2")
    p = {key: m.parameter(key, value) for key, value in SLIDER_CRANK.items()}
    r, rod = p["r"], p["l"]
    m.ode(x1, u1)
    m.ode(y1, v1)
    m.ode(x3, u3)
    push = p["torque"] / r**2  # the torque as a force r x F on the pin, perpendicular to the crank
    m.ode(u1, (-2 * lam1 * x1 + 2 * lam2 * (x3 - x1) - push * y1) / p["m1"])
    m.ode(v1, (-2 * lam1 * y1 - 2 * lam2 * y1 + push * x1) / p["m1"] - p["g"])
    m.ode(u3, (-2 * lam2 * (x3 - x1) - p["c"] * u3) / p["m2"])
    if index == 3:
        m.constraint(x1**2 + y1**2 - r**2, name="crank")
        m.constraint((x3 - x1) ** 2 + y1**2 - rod**2, name="rod")
    else:
        m.constraint(2 * x1 * u1 + 2 * y1 * v1, name="crank_velocity")
        m.constraint(2 * (x3 - x1) * (u3 - u1) + 2 * y1 * v1, name="rod_velocity")
    angle, speed = math.pi / 4, 2.0
    r0, l0 = SLIDER_CRANK["r"], SLIDER_CRANK["l"]
    X1, Y1 = r0 * math.cos(angle), r0 * math.sin(angle)
    X3 = X1 + math.sqrt(l0**2 - Y1**2)
    U1, V1 = -r0 * speed * math.sin(angle), r0 * speed * math.cos(angle)
    m.initial(x1=X1, y1=Y1, x3=X3, u1=U1, v1=V1, u3=U1 - Y1 * V1 / (X3 - X1))
    return m


def build_slider_crank() -> dm.Model:
    """Position constraints: index 3 (the compiler reduces it to index 2 for radau and the PINN)."""
    return _slider_crank("slider_crank", 3)


def build_slider_crank_index2() -> dm.Model:
    """Velocity constraints: index 2 as declared."""
    return _slider_crank("slider_crank_index2", 2)


def build_sqrt_decay() -> dm.Model:
    """y' = -z, 0 = z^2 - y: g_z = 2z is singular at z = 0, and z = -sqrt(y) is a root too."""
    m = dm.Model("sqrt_decay")
    (y,) = m.states("y")
    (z,) = m.algebraics("z")
    m.ode(y, -z)
    m.constraint(z**2 - y, name="root")
    m.initial(y=4.0)
    m.guess(z=2.0)
    return m


def sqrt_decay_exact(t):
    t = np.asarray(t, dtype=float)
    return {"y": (2 - t / 2) ** 2, "z": 2 - t / 2}


def build_rectifier() -> dm.Model:
    """A sine source through a series resistance Rs and a diode (Shockley: i = Is (exp(vd/Vt) - 1))
    charging a capacitor C loaded by RL: the diode current iD is algebraic, implicit through
    the exponential."""
    m = dm.Model("rectifier")
    (vC,) = m.states("vC")
    (iD,) = m.algebraics("iD")
    values = {"C": 1.0, "RL": 2.0, "Rs": 0.5, "Is": 1e-6, "Vt": 0.05, "amplitude": 1.0}
    p = {name: m.parameter(name, value) for name, value in values.items()}
    t = sp.Symbol("t")
    source = p["amplitude"] * sp.sin(2 * sp.pi * t)
    m.ode(vC, (iD - vC / p["RL"]) / p["C"])
    m.constraint(iD - p["Is"] * (sp.exp((source - vC - p["Rs"] * iD) / p["Vt"]) - 1), name="diode")
    m.initial(vC=0.0)
    return m


@dataclass(frozen=True)
class Case:
    """One benchmark case: ``model()`` solved over ``t_span`` at step ``h`` with ``stages``."""

    name: str
    model: object
    t_span: tuple
    h: float
    stages: int = 3
    options: dict = field(default_factory=dict)  # y0 / parameters of a batch
    exact: object = None  # t -> dict name -> values, where a closed form exists
    note: str = ""


def _problem(name):
    from daemodel.problems import PROBLEMS

    return PROBLEMS[name].model


RECTIFIER_LOADS = np.geomspace(1.0, 10.0, 1000)

CASES = (
    Case("heat", build_heat, (0.0, 0.5), 0.05, note="22 unknowns, algebraic boundary values"),
    Case("grid", build_grid, (0.0, 1.0), 0.05, note="3 buses, 6 algebraic voltages and angles"),
    Case("slider_crank h=0.05", build_slider_crank, (0.0, 0.5), 0.05, note="index 3, reduced"),
    Case("slider_crank h=0.01", build_slider_crank, (0.0, 0.5), 0.01, note="index 3, reduced"),
    Case("slider_crank_index2 h=0.05", build_slider_crank_index2, (0.0, 0.5), 0.05, note="index 2"),
    Case("slider_crank_index2 h=0.01", build_slider_crank_index2, (0.0, 0.5), 0.01, note="index 2"),
    Case("sqrt_decay", build_sqrt_decay, (0.0, 1.0), 0.05, exact=sqrt_decay_exact, note="singular at z = 0"),
    Case(
        "rectifier x1000",
        build_rectifier,
        (0.0, 0.5),
        0.01,
        options={"parameters": {"RL": RECTIFIER_LOADS}},
        note="1000 load resistances in one call",
    ),
    Case("akzo_nobel", _problem("akzo-nobel"), (0.0, 2.0), 0.1, note="Test Set"),
    Case("transistor_amplifier", _problem("transistor-amplifier"), (0.0, 0.002), 1e-4, note="Test Set"),
    Case("squeezer", _problem("squeezer"), (0.0, 0.009), 0.00075, note="Test Set"),
    Case("car_axis", _problem("car-axis"), (0.0, 1.0), 0.01, note="Test Set"),
)

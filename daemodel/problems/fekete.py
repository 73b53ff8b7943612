"""The Fekete problem from the Test Set for IVP Solvers (an index-2 DAE of 160 unknowns: 20 charged
particles on the unit sphere settling into the elliptic Fekete points), with the test set's
reference at t = 1000."""

from __future__ import annotations

import math

from daemodel.problems.problem import Problem

# ---- Fekete, index 2 ---------------------------------------------------------------------------
#
# Source: F. Mazzia and C. Magherini, Test Set for Initial Value Problem Solvers, release 2.4
# (Dept. of Mathematics, Univ. of Bari, February 2008), the DAE problem "Fekete" in its stabilised
# index-2 formulation (fekete.f, revision 1.2, 2006/10/02), after Bendtsen & Thomsen and Sloan &
# Womersley; read in deTestSet's copy: src/Ex_fekete.f (fekfunc: the equations; fekinit: the initial
# values; feksoln: the reference at t = 1000, computed by RADAU5 at rtol = atol = h0 = 1e-12) and
# R/ex_fekete.R ([0, 1000]).  N = 20 particles p_i on the unit sphere repel each other with the force
# sum_j (p_i - p_j) / |p_i - p_j|^2 and are damped by alpha = 1/2; the equilibrium they reach
# maximises the product of their distances (the elliptic Fekete points).  In the stabilised
# formulation the velocities q_i are kept tangent and the positions on the sphere by two
# multipliers each:
#
#     p_i' = q_i + 2 mu_i p_i
#     q_i' = -alpha q_i + sum_j (p_i - p_j) / |p_i - p_j|^2 + 2 lam_i p_i
#        0 = |p_i|^2 - 1                    (on the sphere)
#        0 = 2 p_i . q_i                    (the velocity tangent to it)
#
# Each constraint depends on the states only and fixes one multiplier through its derivative, so
# the system is semi-explicit of index 2.  The unknowns are p<i>x, p<i>y, p<i>z, q<i>x, ... , lam<i>,
# mu<i> (i = 1..20): the test set's y(3(i-1)+k), y(60+3(i-1)+k), y(120+i), y(140+i).
FEKETE_PARTICLES = 20
FEKETE_PARAMETERS = {"alpha": 0.5}
_AXES = ("x", "y", "z")


def _fekete_start() -> tuple[list, list]:
    """fekinit's positions (four rings of 3, 7, 6 and 4 particles, each turned a little) and the
    multipliers consistent with them at rest: mu = 0 and lam_i = -p_i . F_i / 2, F_i the force on
    particle i, which makes the derivative of 2 p_i . q_i vanish at t = 0."""
    pi = math.pi
    rings = ((3, pi / 13, 3 * pi / 8), (7, pi / 29, pi / 8), (6, pi / 7, -2 * pi / 15), (4, pi / 17, -3 * pi / 10))
    positions = []
    for count, turn, beta in rings:
        for k in range(1, count + 1):
            # (fekinit's last ring counts from 0: alpha = 2 pi (i - 17) / 4 + pi / 17, i = 17..20)
            alpha = 2 * pi * (k - (1 if count == 4 else 0)) / count + turn
            positions.append((math.cos(alpha) * math.cos(beta), math.sin(alpha) * math.cos(beta), math.sin(beta)))
    lams = []
    for i, p in enumerate(positions):
        force = [0.0, 0.0, 0.0]
        for j, other in enumerate(positions):
            if i != j:
                d = [p[k] - other[k] for k in range(3)]
                r2 = sum(c * c for c in d)
                force = [force[k] + d[k] / r2 for k in range(3)]
        lams.append(-sum(p[k] * force[k] for k in range(3)) / 2)
    return positions, lams


def _force(i: int, k: int) -> str:
    terms = []
    for j in range(1, FEKETE_PARTICLES + 1):
        if j != i:
            r2 = " + ".join(f"(p{i}{a} - p{j}{a})**2" for a in _AXES)
            terms.append(f"(p{i}{_AXES[k]} - p{j}{_AXES[k]})/({r2})")
    return " + ".join(terms)


def _fekete_odes() -> dict:
    odes = {}
    for i in range(1, FEKETE_PARTICLES + 1):
        for a in _AXES:
            odes[f"p{i}{a}"] = f"q{i}{a} + 2*mu{i}*p{i}{a}"
    for i in range(1, FEKETE_PARTICLES + 1):
        for k, a in enumerate(_AXES):
            odes[f"q{i}{a}"] = f"-alpha*q{i}{a} + {_force(i, k)} + 2*lam{i}*p{i}{a}"
    return odes


_POSITIONS, _LAMS = _fekete_start()
_N = range(1, FEKETE_PARTICLES + 1)

# feksoln: y(1..60) (the positions), y(121..140) (lam, all -4.75 to 15 digits); the velocities
# y(61..120) and mu y(141..160) are below 3e-15 there (the particles are at rest)
_FEKETE_POSITIONS_T1 = (
    -0.4070263380333202, 0.3463758772791802, 0.8451942450030429,
    0.7752934752521549e-1, -0.2628662719972299, 0.9617122871829146,
    0.7100577833343567, 0.1212948055586120, 0.6936177005172217,
    0.2348267744557627, 0.7449277976923311, 0.6244509285956391,
    -0.4341114738782885, 0.8785430442262876, 0.1992720444237660,
    -0.9515059600312596, 0.2203508762787005, 0.2146669498274008,
    -0.6385191643609878, -0.4310833259390688, 0.6375425027722121,
    -0.1464175087914336, -0.9380871635228862, 0.3139337298744690,
    0.5666974065069942, -0.6739221885076542, 0.4740073135462156,
    0.9843259538440293, -0.1696995357819996, -0.4800504290609090e-1,
    0.1464175087914331, 0.9380871635228875, -0.3139337298744656,
    -0.7092757549979014, 0.5264062637139616, -0.4688542938854929,
    -0.8665731819284478, -0.4813878059756024, -0.1315929352982178,
    -0.2347897778700538, -0.8594340408013130, -0.4541441287957579,
    0.5530976940074118, -0.7674370265615124, -0.3242273140037833,
    0.7711050969896927, 0.6357041816577034, 0.3573685519777001e-1,
    0.7103951209379591, 0.2403570431280519, -0.6614886725910596,
    -0.3038208738735660e-1, 0.4501923293640461, -0.8924145871442046,
    -0.5772996158107093, -0.1766763414971813, -0.7971892020969544,
    0.2414481766969039, -0.3416456818373135, -0.9082846503446250,
)  # fmt: skip
_FEKETE_LAMS_T1 = (
    -4.750000000000000, -4.750000000000001, -4.750000000000000, -4.750000000000000, -4.750000000000000,
    -4.750000000000000, -4.750000000000000, -4.750000000000000, -4.750000000000000, -4.750000000000000,
    -4.750000000000001, -4.750000000000001, -4.750000000000000, -4.750000000000000, -4.750000000000000,
    -4.750000000000000, -4.749999999999999, -4.750000000000000, -4.750000000000000, -4.750000000000000,
)  # fmt: skip
_POSITION_NAMES = tuple(f"p{i}{a}" for i in _N for a in _AXES)

FEKETE = Problem(
    name="fekete",
    odes=_fekete_odes(),
    algebraics=tuple(f"lam{i}" for i in _N) + tuple(f"mu{i}" for i in _N),
    constraints={f"sphere{i}": " + ".join(f"p{i}{a}**2" for a in _AXES) + " - 1" for i in _N}
    | {f"tangent{i}": " + ".join(f"2*p{i}{a}*q{i}{a}" for a in _AXES) for i in _N},
    parameters=FEKETE_PARAMETERS,
    initial={f"p{i + 1}{a}": _POSITIONS[i][k] for i in range(FEKETE_PARTICLES) for k, a in enumerate(_AXES)}
    | {f"q{i}{a}": 0.0 for i in _N for a in _AXES}
    | {f"lam{i}": _LAMS[i - 1] for i in _N}
    | {f"mu{i}": 0.0 for i in _N},
    t_span=(0.0, 1000.0),
    compare_steps=100,
    index=2,
    reference=dict(zip(_POSITION_NAMES, _FEKETE_POSITIONS_T1, strict=True))
    | {f"lam{i}": v for i, v in zip(_N, _FEKETE_LAMS_T1, strict=True)},
    source="Fekete problem (index-2 DAE of 160 unknowns, stabilised formulation) of the Test Set for IVP "
    "Solvers (Mazzia & Magherini, Univ. of Bari), fekete.f rev. 1.2 (2006); reference at t = 1000 from the "
    "test set (positions and lam; the velocities and mu, below 3e-15 there, are left out)",
)

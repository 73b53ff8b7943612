"""Three scalable DAE families for the scaling benchmark (issue 12), declared through the public API.

Each function returns a fresh :class:`daemodel.Model` whose size grows with one integer:

============================  ==============================  =============  ========================
family                        unknowns (n states + m alg.)    index          coupling
============================  ==============================  =============  ========================
``pendulum_chain(N)``         4N + N = 5N  (40 at N = 8)      3 (-> 2)       nearest neighbour (banded)
``reaction_diffusion(K)``     K + K = 2K   (600 at K = 300)   1              nearest neighbour (banded)
``sphere_particles(P)``       6P + 2P = 8P (160 at P = 20)    2              all pairs (dense)
============================  ==============================  =============  ========================

The chain and the grid live in the package (:mod:`daemodel.problems.families`, where the
``families`` suite of ``daemodel bench`` runs them) and are imported from there; the particles are
declared here; :func:`reaction_diffusion_arrays` declares the grid's equations as arrays, by numpy's
arithmetic or by :func:`daemodel.stencil` (:data:`DECLARATIONS`).  The equations are built as sympy
expressions from the symbols that ``m.states`` and ``m.algebraics`` return, as a user would write
them; ``T_SPAN`` below holds each family's benchmark interval.  Run
``python benchmarks/scaling_models.py`` to compile each family at a small size and print its report.
"""

from __future__ import annotations

import math

import numpy as np
import sympy as sp

import daemodel as dm
from daemodel.problems.families import DIFFUSION, pendulum_chain, reaction_diffusion

# Benchmark interval of each family: long enough for the chain to swing through a large angle,
# for the grid's slowest mode to decay to about a third and for the particles to move well off their start.
T_SPAN = {
    "pendulum_chain": (0.0, 1.0),
    "reaction_diffusion": (0.0, 1.0),
    "sphere_particles": (0.0, 1.0),
}

# Softening of the particles' repulsion: keeps the force smooth (bounded by ~eps^-1) if two
# particles come close; 0.05 is small next to their squared spacing at the start (closest pair
# 0.69 apart at P = 20, so |d|^2 = 0.48).
SOFTENING = 0.05
# Total repulsion strength shared by P - 1 partners (the pair strength is this / P), so a
# particle's force stays O(1) and the time scale of the motion does not shrink as P grows.
REPULSION = 1.0
# Scale of the initial tangent velocities: a rigid rotation plus a per-particle twist of this
# size, so that the sphere both rotates and deforms.
PARTICLE_SPEED = 0.5


def fibonacci_sphere(P: int) -> np.ndarray:
    """P points spread evenly on the unit sphere (the golden-angle spiral), shape (P, 3)."""
    i = np.arange(P) + 0.5
    z = 1.0 - 2.0 * i / P
    r = np.sqrt(1.0 - z * z)
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def sphere_particles(P: int) -> dm.Model:
    """P particles on the unit sphere with all-pairs smooth repulsion, GGL form (index 2, dense).

    Position ``x_i`` and velocity ``v_i`` in R^3 for i = 1..P; with ``d_ij = x_i - x_j``::

        x_i' = v_i - mu_i x_i
        v_i' = F_i - lam_i x_i,        F_i = (k / P) sum_{j != i} d_ij / (|d_ij|^2 + eps)^(3/2)
        0    = |x_i|^2 - 1             (constraint ``sphere_i``, index 2 through mu_i)
        0    = x_i . v_i               (constraint ``tangent_i``, index 2 through lam_i)

    This is the Gear-Gupta-Leimkuhler stabilisation of the index-3 system: mu_i is zero on the
    exact solution and keeps the position constraint enforced.  States px_i, py_i, pz_i, vx_i,
    vy_i, vz_i (n = 6P), algebraic variables lam_i, mu_i (m = 2P): 8P unknowns (160 at P = 20).
    Every right-hand side v_i' depends on every position: the Jacobian's f_y block is dense.
    Parameters ``k`` = :data:`REPULSION` and ``eps`` = :data:`SOFTENING`.

    Initial state: the points of :func:`fibonacci_sphere` (exactly on the sphere), each moving
    with ``v_i = (omega + a_i) x x_i``, a rigid rotation ``omega`` plus a per-particle twist
    ``a_i`` (both of size ~ :data:`PARTICLE_SPEED`), so every velocity is tangent (``x_i . v_i = 0``).

    Parameters
    ----------
    P : int
        Number of particles, >= 2.
    """
    if isinstance(P, bool) or not isinstance(P, int) or P < 2:
        raise ValueError(f"sphere_particles needs an integer P >= 2 particles; got {P!r}")
    m = dm.Model(f"sphere_particles_{P}")
    idx = range(1, P + 1)
    pos = [m.states([f"px_{i}", f"py_{i}", f"pz_{i}"]) for i in idx]
    vel = [m.states([f"vx_{i}", f"vy_{i}", f"vz_{i}"]) for i in idx]
    lam = m.algebraics([f"lam_{i}" for i in idx])
    mu = m.algebraics([f"mu_{i}" for i in idx])
    strength = m.parameter("k", REPULSION)
    eps = m.parameter("eps", SOFTENING)
    # one softened inverse-cube factor per unordered pair, shared by both partners
    factor = {}
    for i in range(P):
        for j in range(i + 1, P):
            d2 = sum((pos[i][a] - pos[j][a]) ** 2 for a in range(3))
            factor[i, j] = factor[j, i] = (d2 + eps) ** sp.Rational(-3, 2)
    for i in range(P):
        for a in range(3):
            force = strength / P * sp.Add(*[(pos[i][a] - pos[j][a]) * factor[i, j] for j in range(P) if j != i])
            m.ode(pos[i][a], vel[i][a] - mu[i] * pos[i][a])
            m.ode(vel[i][a], force - lam[i] * pos[i][a])
    for i in range(P):
        m.constraint(sum(pos[i][a] ** 2 for a in range(3)) - 1, name=f"sphere_{i + 1}")
        m.constraint(sum(pos[i][a] * vel[i][a] for a in range(3)), name=f"tangent_{i + 1}")
    points = fibonacci_sphere(P)
    omega = PARTICLE_SPEED * np.array([0.3, -0.2, 1.0])
    start = {}
    for i, x in enumerate(points, start=1):
        twist = PARTICLE_SPEED * np.array([math.sin(1.7 * i), math.cos(2.3 * i), math.sin(0.9 * i)])
        velocity = np.cross(omega + twist, x)
        for a, axis in enumerate("xyz"):
            start[f"p{axis}_{i}"] = float(x[a])
            start[f"v{axis}_{i}"] = float(velocity[a])
    m.initial(**start)
    return m


def reaction_diffusion_arrays(K: int, stencils: bool = True) -> dm.Model:
    """The equations of :func:`reaction_diffusion` declared as arrays ``c[0..K-1]``, ``w[0..K-1]``.

    ``stencils=True``: by :func:`daemodel.stencil` (the arithmetic recorded once, one template per
    block); ``stencils=False``: by numpy's arithmetic on the arrays of symbols (one sympy tree per
    element, built an operation at a time).  Both declare the same equations, tree for tree (the same
    compiled model: ``tests/declaring/test_stencils.py``).  Constraints ``rate[0..K-1]``.
    """
    if isinstance(K, bool) or not isinstance(K, int) or K < 1:
        raise ValueError(f"reaction_diffusion_arrays needs an integer K >= 1 grid points; got {K!r}")
    m = dm.Model(f"reaction_diffusion_{K}")
    c, w = m.states("c", K), m.algebraics("w", K)
    D = m.parameter("D", DIFFUSION)
    padded = np.array([0, *c, 0], dtype=object)  # the Dirichlet boundary values around the interior points
    if stencils:
        padded, c, w = dm.stencil(padded), dm.stencil(c), dm.stencil(w)
    inv_dx2 = sp.Integer(K + 1) ** 2  # 1 / dx^2, exact
    laplacian = (padded[:-2] - 2 * padded[1:-1] + padded[2:]) * inv_dx2  # (as the loop of the family writes it)
    m.ode("c", D * laplacian - w)
    m.constraint(w - c**2 / (1 + c), name="rate")
    m.initial(c=np.sin(np.pi * np.arange(1, K + 1) / (K + 1)))
    return m


# How the scaling benchmarks declare the reaction-diffusion family: name -> builder of K.
DECLARATIONS = {
    "loop": reaction_diffusion,  # a Python loop of m.ode and m.constraint on scalar names c_1, ...
    "arrays": lambda K: reaction_diffusion_arrays(K, stencils=False),
    "stencils": lambda K: reaction_diffusion_arrays(K, stencils=True),
}


FAMILIES = {
    "pendulum_chain": pendulum_chain,
    "reaction_diffusion": reaction_diffusion,
    "sphere_particles": sphere_particles,
}


def unknowns(family: str, size: int) -> int:
    """Number of unknowns (states + algebraic variables) of ``family`` at ``size``."""
    per = {"pendulum_chain": 5, "reaction_diffusion": 2, "sphere_particles": 8}
    return per[family] * size


if __name__ == "__main__":
    for name, build in FAMILIES.items():
        compiled = build(3).compile()
        print(f"{name}(3): {len(compiled.states)} states, {len(compiled.algebraics)} algebraic, index {compiled.index}")

"""Three scalable DAE families for the scaling benchmark (issue 12), declared through the public API.

Each function returns a fresh :class:`daemodel.Model` whose size grows with one integer:

============================  ==============================  =============  ========================
family                        unknowns (n states + m alg.)    index          coupling
============================  ==============================  =============  ========================
``pendulum_chain(N)``         4N + N = 5N  (40 at N = 8)      3 (-> 2)       nearest neighbour (banded)
``reaction_diffusion(K)``     K + K = 2K   (600 at K = 300)   1              nearest neighbour (banded)
``sphere_particles(P)``       6P + 2P = 8P (160 at P = 20)    2              all pairs (dense)
============================  ==============================  =============  ========================

The equations are built as sympy expressions from the symbols that ``m.states`` and
``m.algebraics`` return, as a user would write them; ``T_SPAN`` below holds each family's
benchmark interval.  Run ``python benchmarks/scaling_models.py`` to compile each family at a
small size and print its report.
"""

from __future__ import annotations

import math

import numpy as np
import sympy as sp

import daemodel as dm

# Benchmark interval of each family: long enough for the chain to swing through a large angle,
# for the grid's slowest mode to decay to about a third and for the particles to move well off their start.
T_SPAN = {
    "pendulum_chain": (0.0, 1.0),
    "reaction_diffusion": (0.0, 1.0),
    "sphere_particles": (0.0, 1.0),
}

# Gravity of the pendulum chain (m / s^2): unit masses and rods make it the only scale.
GRAVITY = 9.81
# Angle of the straight chain at release, below the horizontal: gravity has a component along
# the rods (nonzero tensions from t0, unlike a horizontal release where every lam_i(t0) = 0) and
# one across them (the chain swings and folds rather than hanging still).
CHAIN_RELEASE_ANGLE = math.pi / 4

# Diffusion coefficient of the grid: stiffness 4 D / dx^2 grows from ~50 (K = 10) to ~36,000
# (K = 300) while the slowest mode decays as exp(-D pi^2 t), to 37 % at t = 1: mildly stiff.
DIFFUSION = 0.1

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


def pendulum_chain(N: int) -> dm.Model:
    """A chain of N planar pendulums in Cartesian coordinates (index 3).

    Unit masses joined by unit massless rods; mass 0 is the fixed origin and rod i joins mass
    i-1 and mass i.  For i = 1..N, with ``x_0 = y_0 = 0`` and the last term absent for i = N::

        x_i' = u_i,   y_i' = v_i
        u_i' = -lam_i (x_i - x_{i-1}) + lam_{i+1} (x_{i+1} - x_i)
        v_i' = -lam_i (y_i - y_{i-1}) + lam_{i+1} (y_{i+1} - y_i) - grav
        0    = (x_i - x_{i-1})^2 + (y_i - y_{i-1})^2 - 1          (constraint ``rod_i``)

    ``lam_i`` is the tension of rod i per unit length.  States x_i, y_i, u_i, v_i (n = 4N),
    algebraic variables lam_i (m = N): 5N unknowns (40 at N = 8, 160 at N = 32).  Each rod is
    an index-3 constraint; solvers that need it get the compiler's index-2 reduction (the
    velocity-level constraints ``rod_i'``).  Parameter ``grav`` = :data:`GRAVITY`.

    Initial state: the chain at rest, straight, pointing down from the origin at
    :data:`CHAIN_RELEASE_ANGLE` (45 degrees) below the horizontal (``x_i = i cos 45deg``,
    ``y_i = -i sin 45deg``).  It is consistent (every rod has unit length, no velocity), the
    tensions are nonzero from the start, and the chain swings and folds over ``T_SPAN``.

    Parameters
    ----------
    N : int
        Number of links, >= 1.
    """
    if isinstance(N, bool) or not isinstance(N, int) or N < 1:
        raise ValueError(f"pendulum_chain needs an integer N >= 1 links; got {N!r}")
    m = dm.Model(f"pendulum_chain_{N}")
    idx = range(1, N + 1)
    x = m.states([f"x_{i}" for i in idx])
    y = m.states([f"y_{i}" for i in idx])
    u = m.states([f"u_{i}" for i in idx])
    v = m.states([f"v_{i}" for i in idx])
    lam = m.algebraics([f"lam_{i}" for i in idx])
    grav = m.parameter("grav", GRAVITY)
    zero = sp.Integer(0)
    # positions with the fixed mass 0 first: px[i] is mass i, i = 0..N
    px, py = (zero, *x), (zero, *y)
    for k in range(N):  # k = i - 1: mass i = k + 1
        i = k + 1
        fx = -lam[k] * (px[i] - px[i - 1])
        fy = -lam[k] * (py[i] - py[i - 1])
        if i < N:
            fx += lam[k + 1] * (px[i + 1] - px[i])
            fy += lam[k + 1] * (py[i + 1] - py[i])
        m.ode(x[k], u[k])
        m.ode(y[k], v[k])
        m.ode(u[k], fx)
        m.ode(v[k], fy - grav)
    for k in range(N):
        i = k + 1
        m.constraint((px[i] - px[i - 1]) ** 2 + (py[i] - py[i - 1]) ** 2 - 1, name=f"rod_{i}")
    cos_a, sin_a = math.cos(CHAIN_RELEASE_ANGLE), math.sin(CHAIN_RELEASE_ANGLE)
    start = {}
    for i in idx:
        start.update({f"x_{i}": i * cos_a, f"y_{i}": -i * sin_a, f"u_{i}": 0.0, f"v_{i}": 0.0})
    m.initial(**start)
    return m


def reaction_diffusion(K: int) -> dm.Model:
    """Method of lines for ``c_t = D c_xx - c^2 / (1 + c)`` on [0, 1], the reaction as an algebraic variable (index 1).

    K interior points ``x_k = k dx``, ``dx = 1 / (K + 1)``, homogeneous Dirichlet boundaries
    ``c_0 = c_{K+1} = 0``.  For k = 1..K::

        c_k' = D (c_{k-1} - 2 c_k + c_{k+1}) / dx^2 - w_k
        0    = w_k - c_k^2 / (1 + c_k)                       (constraint ``rate_k``)

    States c_k (n = K), algebraic variables w_k (m = K): 2K unknowns (200 at K = 100, 600 at
    K = 300).  Each constraint has index 1 (``dg/dw = 1``).  Parameter ``D`` =
    :data:`DIFFUSION`: the stiffness ``4 D / dx^2`` grows with K (about 36,000 at K = 300)
    while the solution stays smooth, so the family is mildly stiff.

    Initial state: ``c_k = sin(pi x_k)`` (it meets the boundary values); ``w_k`` is computed
    by the compiler.

    Parameters
    ----------
    K : int
        Number of interior grid points, >= 1.
    """
    if isinstance(K, bool) or not isinstance(K, int) or K < 1:
        raise ValueError(f"reaction_diffusion needs an integer K >= 1 grid points; got {K!r}")
    m = dm.Model(f"reaction_diffusion_{K}")
    idx = range(1, K + 1)
    c = m.states([f"c_{k}" for k in idx])
    w = m.algebraics([f"w_{k}" for k in idx])
    D = m.parameter("D", DIFFUSION)
    inv_dx2 = sp.Integer(K + 1) ** 2  # 1 / dx^2, exact
    zero = sp.Integer(0)
    padded = (zero, *c, zero)  # the Dirichlet boundary values around the interior points
    for j in range(K):  # padded[j + 1] is c_{j+1}
        laplacian = (padded[j] - 2 * padded[j + 1] + padded[j + 2]) * inv_dx2
        m.ode(c[j], D * laplacian - w[j])
    for j in range(K):
        m.constraint(w[j] - c[j] ** 2 / (1 + c[j]), name=f"rate_{j + 1}")
    m.initial(**{f"c_{k}": math.sin(math.pi * k / (K + 1)) for k in idx})
    return m


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

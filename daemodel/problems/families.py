"""The two scalable families of the ``families`` suite of ``daemodel bench``, declared through the
public API (a :class:`Model` built from the symbols ``m.states`` and ``m.algebraics`` return, as a
user would write it), each at three sizes, with a reference at the end of its interval.

============================  ==============================  =============  ========================
family                        unknowns (n states + m alg.)    index          coupling
============================  ==============================  =============  ========================
``pendulum_chain(N)``         4N + N = 5N  (40 at N = 8)      3 (-> 2)       nearest neighbour (banded)
``reaction_diffusion(K)``     K + K = 2K   (600 at K = 300)   1              nearest neighbour (banded)
============================  ==============================  =============  ========================

Neither has a closed form.  The references (:data:`REFERENCES`) are not daemodel's own: they come
from scipy's ``solve_ivp`` (Radau, rtol 1e-12, atol 1e-14) on each family's index-reduced ODE,
written out independently of daemodel in ``benchmarks/family_references.py``; DOP853 at the same
tolerances agrees with them to 6e-12 (relative) or better on every component of every member.
``benchmarks/scaling_models.py`` (the scaling benchmark) imports the two builders from here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import sympy as sp

from daemodel.backends.grids import SWEEP_FIRST_STEPS
from daemodel.compiling.compiler import Model
from daemodel.errors import InvalidValueError

# Gravity of the pendulum chain (m / s^2): unit masses and rods make it the only scale.
GRAVITY = 9.81
# Angle of the straight chain at release, below the horizontal: gravity has a component along
# the rods (nonzero tensions from t0, unlike a horizontal release where every lam_i(t0) = 0) and
# one across them (the chain swings and folds rather than hanging still).
CHAIN_RELEASE_ANGLE = math.pi / 4

# Diffusion coefficient of the grid: stiffness 4 D / dx^2 grows from ~50 (K = 10) to ~36,000
# (K = 300) while the slowest mode decays as exp(-D pi^2 t), to 37 % at t = 1: mildly stiff.
DIFFUSION = 0.1


def check_size(value, family: str, name: str, what: str) -> None:
    """A family's size ``name`` must be an integer >= 1 (a bool is not): else InvalidValueError."""
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise InvalidValueError(f"{family} needs an integer {name} >= 1 {what}; got {value!r}")


def pendulum_chain(N: int) -> Model:
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
    check_size(N, "pendulum_chain", "N", "links")
    m = Model(f"pendulum_chain_{N}")
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


def reaction_diffusion(K: int) -> Model:
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
    check_size(K, "reaction_diffusion", "K", "grid points")
    m = Model(f"reaction_diffusion_{K}")
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


# Interval of both families: long enough for the chain to swing through a large angle and for the
# grid's slowest mode to decay to about a third.
T_SPAN = (0.0, 1.0)
# The sizes of the suite: unknowns 20, 40, 80 (chain) and 50, 100, 200 (grid), small enough for
# every method of a default sweep on a laptop, large enough to show how each method's cost grows.
SIZES = {"pendulum_chain": (4, 8, 16), "reaction_diffusion": (25, 50, 100)}
SOURCE = (
    "daemodel's scalable families (daemodel.problems.families); reference at t = 1 from scipy "
    "solve_ivp (Radau, rtol 1e-12, atol 1e-14) on the index-reduced ODE, benchmarks/family_references.py"
)

# Made by `python benchmarks/family_references.py` (scipy 1.17.1, float64); each member's largest
# relative difference between Radau and DOP853 at rtol 1e-12 is in the comment above it.
# fmt: off
REFERENCES = {
    # pendulum_chain-4: Radau vs DOP853 differ by 2.7e-12 (relative)
    "pendulum_chain-4": {
        "x_4": -0.5161633497612408, "y_4": -3.9649556796538414,
        "u_4": -6.611040065235936, "v_4": 0.8846376450446867,
        "lam_1": 62.17202357501454, "lam_4": 28.041324593758432,
    },
    # pendulum_chain-8: Radau vs DOP853 differ by 4.0e-12 (relative)
    "pendulum_chain-8": {
        "x_8": 2.4723237248318046, "y_8": -7.375803349521143,
        "u_8": -7.25918160628116, "v_8": -2.5240064002844296,
        "lam_1": 100.93960096441944, "lam_8": 15.21859338135312,
    },
    # pendulum_chain-16: Radau vs DOP853 differ by 6.1e-12 (relative)
    "pendulum_chain-16": {
        "x_16": 8.354240644505818, "y_16": -13.259240644233786,
        "u_16": -6.459813092628171, "v_16": -3.3501868980628413,
        "lam_1": 176.0222860180919, "lam_16": 11.664543480653236,
    },
    # reaction_diffusion-25: Radau vs DOP853 differ by 3.9e-12 (relative)
    "reaction_diffusion-25": {
        "c_1": 0.0336475682898305, "c_6": 0.18330196677418878,
        "c_13": 0.2737720684870725, "w_1": 0.0010953045182430638,
        "w_6": 0.02839479014378894, "w_13": 0.05884188179186077,
    },
    # reaction_diffusion-50: Radau vs DOP853 differ by 3.1e-13 (relative)
    "reaction_diffusion-50": {
        "c_1": 0.017172986287004265, "c_12": 0.18601411332659015,
        "c_25": 0.2734351580732836, "w_1": 0.0002899324519914302,
        "w_12": 0.029174400176087488, "w_25": 0.0587126758646151,
    },
    # reaction_diffusion-100: Radau vs DOP853 differ by 1.2e-12 (relative)
    "reaction_diffusion-100": {
        "c_1": 0.008674056814512096, "c_25": 0.19353190142364768,
        "c_50": 0.27347354422773007, "w_1": 7.459224425677847e-05,
        "w_25": 0.03138131190626455, "w_50": 0.058727391496640496,
    },
}
# fmt: on


def scd_components(family: str, size: int) -> tuple:
    """The components a member's scd is read from: the chain's tip (position and velocity) and its
    first and last rod tensions; the grid's concentration and reaction rate at its first point, a
    quarter along and in the middle (the solution is symmetric about the middle)."""
    if family == "pendulum_chain":
        return (f"x_{size}", f"y_{size}", f"u_{size}", f"v_{size}", "lam_1", f"lam_{size}")
    points = (1, (size + 1) // 4, (size + 1) // 2)
    return tuple(f"c_{k}" for k in points) + tuple(f"w_{k}" for k in points)


BUILDERS = {"pendulum_chain": pendulum_chain, "reaction_diffusion": reaction_diffusion}


@dataclass(frozen=True)
class FamilyMember:
    """One member of a family at one size, as the ``families`` suite runs it.

    Attributes
    ----------
    name : str
        ``"<family>-<size>"``, e.g. ``"pendulum_chain-8"``.
    family : str
        A key of :data:`BUILDERS`.
    size : int
    t_span : (float, float)
    reference : dict name -> float
        The values at ``t_span[1]`` of :func:`scd_components` (:data:`REFERENCES`).
    source : str
    compare_steps : int
        Steps over ``t_span`` of the fixed-step methods' coarsest setting.
    """

    name: str
    family: str
    size: int
    t_span: tuple = T_SPAN
    reference: dict = field(default_factory=dict)
    source: str = SOURCE
    compare_steps: int = SWEEP_FIRST_STEPS

    @property
    def scd_names(self) -> tuple:
        return tuple(self.reference)

    def model(self) -> Model:
        """A fresh :class:`Model` of this member."""
        return BUILDERS[self.family](self.size)


FAMILIES = {
    f"{family}-{size}": FamilyMember(f"{family}-{size}", family, size, reference=REFERENCES[f"{family}-{size}"])
    for family, sizes in SIZES.items()
    for size in sizes
}

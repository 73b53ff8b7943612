"""A small library of test problems: equations as data, initial values, interval, exact
solution or published reference values where one exists, and the source.  Tests, benchmarks and
examples draw on it; the equations are strings so the library exercises the same parser users do.

``problem.py`` says what a problem is; ``paper.py`` holds the paper's problems, ``textbook.py``
Robertson and the bouncing ball, one module per problem of the Test Set for IVP Solvers
(``squeezer.py``, ``akzo_nobel.py``, ``car_axis.py``, ``transistor_amplifier.py``,
``wheelset.py``, ``ring_modulator.py``, ``hires.py``, ``pollution.py``, ``fekete.py``),
``fitting.py`` the fitting problems, ``families.py`` the scalable families of the ``families`` suite
(:data:`FAMILIES`); ``library.py`` gathers :data:`PROBLEMS`.
"""

from daemodel.problems.akzo_nobel import AKZO_NOBEL, AKZO_NOBEL_PARAMETERS
from daemodel.problems.car_axis import CAR_AXIS, CAR_AXIS_PARAMETERS
from daemodel.problems.families import FAMILIES
from daemodel.problems.fekete import FEKETE
from daemodel.problems.fitting import DAMPED_PENDULUM, DECAY
from daemodel.problems.hires import HIRES, HIRES_PARAMETERS
from daemodel.problems.library import PROBLEMS
from daemodel.problems.paper import HESSENBERG, PAPER, PENDULUM, PENDULUM_INDEX3
from daemodel.problems.pollution import POLLUTION, POLLUTION_PARAMETERS, POLLUTION_SPECIES
from daemodel.problems.problem import ExactSolution, Problem
from daemodel.problems.ring_modulator import RING_MODULATOR, RING_MODULATOR_PARAMETERS
from daemodel.problems.squeezer import SQUEEZER, SQUEEZER_PARAMETERS, SQUEEZER_POSITION_CONSTRAINTS
from daemodel.problems.textbook import BALL_E, BALL_G, BALL_IMPACTS, BOUNCING_BALL, ROBERTSON
from daemodel.problems.transistor_amplifier import TRANSISTOR_AMPLIFIER, TRANSISTOR_PARAMETERS
from daemodel.problems.wheelset import WHEELSET, WHEELSET_PARAMETERS

__all__ = [
    "AKZO_NOBEL",
    "AKZO_NOBEL_PARAMETERS",
    "BALL_E",
    "BALL_G",
    "BALL_IMPACTS",
    "BOUNCING_BALL",
    "CAR_AXIS",
    "CAR_AXIS_PARAMETERS",
    "DAMPED_PENDULUM",
    "DECAY",
    "FAMILIES",
    "FEKETE",
    "HESSENBERG",
    "HIRES",
    "HIRES_PARAMETERS",
    "PAPER",
    "PENDULUM",
    "PENDULUM_INDEX3",
    "POLLUTION",
    "POLLUTION_PARAMETERS",
    "POLLUTION_SPECIES",
    "PROBLEMS",
    "RING_MODULATOR",
    "RING_MODULATOR_PARAMETERS",
    "ROBERTSON",
    "SQUEEZER",
    "SQUEEZER_PARAMETERS",
    "SQUEEZER_POSITION_CONSTRAINTS",
    "TRANSISTOR_AMPLIFIER",
    "TRANSISTOR_PARAMETERS",
    "WHEELSET",
    "WHEELSET_PARAMETERS",
    "ExactSolution",
    "Problem",
]

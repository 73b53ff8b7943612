"""The problem library: every problem ``daemodel compare``, the benchmarks and the tests run by
name (the fitting problems are outside it: they have no reference to compare methods on)."""

from __future__ import annotations

from daemodel.problems.akzo_nobel import AKZO_NOBEL
from daemodel.problems.car_axis import CAR_AXIS
from daemodel.problems.fekete import FEKETE
from daemodel.problems.hires import HIRES
from daemodel.problems.paper import HESSENBERG, PENDULUM, PENDULUM_INDEX3
from daemodel.problems.pollution import POLLUTION
from daemodel.problems.ring_modulator import RING_MODULATOR
from daemodel.problems.squeezer import SQUEEZER
from daemodel.problems.textbook import BOUNCING_BALL, ROBERTSON
from daemodel.problems.transistor_amplifier import TRANSISTOR_AMPLIFIER
from daemodel.problems.wheelset import WHEELSET

PROBLEMS = {
    p.name: p
    for p in (
        HESSENBERG, PENDULUM, PENDULUM_INDEX3, ROBERTSON, SQUEEZER, AKZO_NOBEL, CAR_AXIS, TRANSISTOR_AMPLIFIER,
        WHEELSET, RING_MODULATOR, HIRES, POLLUTION, FEKETE, BOUNCING_BALL,
    )
}  # fmt: skip

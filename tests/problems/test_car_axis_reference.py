"""The car axis against its extended-precision reference at t = 3 (``benchmarks/car_axis_reference.py``,
stored in ``benchmarks/car_axis_reference.json``; issue 42): the reference is what its script computes,
the Test Set's published values carry the digits measured against it (the multipliers 7), and radau at
rtol = atol = 1e-10 reads the digits measured against it."""

import dataclasses
import importlib.util
import json
import math
import sys
from pathlib import Path

import mpmath
import pytest
import sympy as sp

import daemodel as dm
from daemodel.problems import CAR_AXIS

BENCHMARKS = Path(__file__).resolve().parents[2] / "benchmarks"
STATES = ("xl", "yl", "xr", "yr", "ul", "vl", "ur", "vr")
MULTIPLIERS = ("lam1", "lam2")
# Digits by which the Test Set's published values agree with the extended reference (measured by
# benchmarks/car_axis_reference.py): the positions 12.2-13.6, the velocities 9.2 (vl) to 12.6, the
# multipliers 7.5 and 7.1.
PUBLISHED_DIGITS = {
    "xl": 12.19, "yl": 12.19, "xr": 13.60, "yr": 12.41, "ul": 11.31,
    "vl": 9.24, "ur": 9.63, "vr": 12.59, "lam1": 7.47, "lam2": 7.14,
}  # fmt: skip


@pytest.fixture(scope="module")
def script():
    """``benchmarks/car_axis_reference.py`` as a module (in sys.modules meanwhile: it holds a dataclass)."""
    name = "_car_axis_reference"
    spec = importlib.util.spec_from_file_location(name, BENCHMARKS / "car_axis_reference.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
        yield module
    finally:
        del sys.modules[name]


@pytest.fixture(scope="module")
def stored():
    return json.loads((BENCHMARKS / "car_axis_reference.json").read_text())


@pytest.fixture(scope="module")
def system(script):
    return script.reduced_system({k: sp.Rational(repr(v)) for k, v in CAR_AXIS.parameters.items()})


def agreement(value, reference) -> float:
    """-log10 of the relative difference, at 30 digits."""
    with mpmath.workdps(30):
        difference = abs(mpmath.mpf(value) - mpmath.mpf(reference)) / abs(mpmath.mpf(reference))
        return math.inf if difference == 0 else float(-mpmath.log10(difference))


def test_the_stored_reference_passed_its_own_checks(stored):
    """Half the steps, order 20 instead of 24 and 50 digits instead of 40 agree with it to 30 digits
    (20 are stored), and mpmath's Taylor-series integrator at 25 digits to 24.45; the constraints hold
    at t = 3 to 1e-25 (measured: 2.4e-36); the Test Set's lam(0) = 0 is consistent."""
    assert set(stored["reference"]) == set(STATES + MULTIPLIERS)
    assert all(len(v.lstrip("-").split("e")[0].replace(".", "")) == 20 for v in stored["reference"].values())
    assert stored["verified_digits"] >= 29.5
    assert min(stored["taylor_check"]["digits"].values()) > 24.0
    assert max(float(r) for r in stored["constraints_at_t_end"].values()) < 1e-25
    assert stored["lam_at_0"] == [0.0, 0.0]


@pytest.mark.slow  # ~3 s of CPU, 15 s of wall on the shared machine
def test_the_stored_reference_is_what_the_script_computes(script, system, stored):
    """150 steps of order 18 at 25 digits (12,300 rates) agree with the stored 600 steps of order
    24 at 40 digits to 15 digits in every component (measured: 14.98)."""
    run = script.integrate(system, 150, 9, 25)
    assert run["lam_at_0"] == [0.0, 0.0]
    for name in STATES + MULTIPLIERS:
        assert agreement(run["values"][name], stored["reference"][name]) > 14.5, name


def test_the_published_reference_carries_the_digits_measured_against_the_extended_one(stored):
    """Issue 42: the published multipliers carry 7 digits (7.47 and 7.14), vl 9.2, every other state
    9.6-13.6; the float64 solvers' agreement (docs/benchmarks/compare.md) said so, this measures it."""
    for name, expected in PUBLISHED_DIGITS.items():
        assert agreement(CAR_AXIS.reference[name], stored["reference"][name]) == pytest.approx(expected, abs=0.01)
        assert stored["published_digits"][name] == pytest.approx(expected, abs=0.01)
    assert 7.0 < min(PUBLISHED_DIGITS[n] for n in MULTIPLIERS) < 7.5
    assert min(PUBLISHED_DIGITS[n] for n in STATES) > 9.2


def test_radau_at_1e_10_against_the_extended_reference(system, stored):
    """Default radau (7 stages) at rtol = atol = 1e-10: 10.79 digits in the states (vl), 13.55 in the
    multipliers (against the published values 9.26 and 7.14).  The multipliers are solved from radau's
    end states (backends/radau/outputs.py); the collocation's own multipliers read 8.30 (order s in h for
    an index-2 algebraic variable, its estimate weighted by h), which this test's bound of 13 refused.
    The same states solved here at 30 digits by the acceleration-level constraints read 13.58."""
    extended = {n: float(v) for n, v in stored["reference"].items()}
    sol = dm.solve(CAR_AXIS.model(), CAR_AXIS.t_span, rtol=1e-10, atol=1e-10, t_eval=[0.0, 3.0])
    assert sol.status == "success"
    end = {n: float(sol[n][-1]) for n in STATES + MULTIPLIERS}
    assert min(agreement(end[n], extended[n]) for n in STATES) > 10.5
    assert min(agreement(end[n], extended[n]) for n in MULTIPLIERS) > 13.0
    assert max(abs(end[n] - extended[n]) for n in MULTIPLIERS) < 1e-12
    with mpmath.workdps(30):
        solved = system.multipliers(mpmath.mpf(3), [mpmath.mpf(end[n]) for n in STATES])
    assert min(agreement(value, extended[n]) for n, value in zip(MULTIPLIERS, solved, strict=True)) > 13.0


def test_the_reduction_refuses_a_problem_it_does_not_fit(script):
    moved = dataclasses.replace(CAR_AXIS, odes={**CAR_AXIS.odes, "xl": "2*ul"})
    with pytest.raises(script.ReferenceCheckError, match=r"the rate of xl is 2\*ul, not ul"):
        script.reduced_system({}, moved)
    squared = dataclasses.replace(CAR_AXIS, odes={**CAR_AXIS.odes, "ur": f"{CAR_AXIS.odes['ur']} + lam1**2"})
    with pytest.raises(script.ReferenceCheckError, match="not linear in lam1, lam2"):
        script.reduced_system({}, squared)


def test_a_run_that_fails_its_checks_is_refused(script):
    good = {"lam_at_0": [0.0, 0.0], "constraints": [1e-37, 1e-36, 1e-37, 1e-37]}
    script.check_run(good)
    with pytest.raises(script.ReferenceCheckError, match=r"lam\(0\) = 0 is not consistent"):
        script.check_run({**good, "lam_at_0": [1e-3, 0.0]})
    with pytest.raises(script.ReferenceCheckError, match=r"drift to 1\.0e-20 at t = 3, beyond 1e-25"):
        script.check_run({**good, "constraints": [1e-20, 0.0, 0.0, 0.0]})
    script.check_digits(22.0)
    with pytest.raises(script.ReferenceCheckError, match=r"to 21\.9 digits only, fewer than the 20 stored and 2 more"):
        script.check_digits(21.9)

"""Digits of radau (3, 5 and 7 stages) and casadi-idas on the car axis at t = 3, against the Test Set's
published reference and against the extended-precision one (``benchmarks/car_axis_reference.json``,
written by ``benchmarks/car_axis_reference.py``), per component, at rtol = atol = 1e-8, 1e-10, 1e-12.

Digits are the Test Set's scd: -log10 of the relative error (of the largest one over a group of
components for the group's figure).  Two more columns say where the multipliers' error comes from:
``multipliers_from_states``, the digits of the multipliers solved from the method's own end states by
the acceleration-level constraints (``car_axis_reference.reduced_system``), and
``multiplier_error_along_run``, the largest ``|lam - lam(y)| / (atol + rtol |lam(y)|)`` over the
method's output times of a solve without ``t_eval`` (its steps), with lam(y) solved so from its states;
and ``algebraic_correction``, radau's own figure of that distance for its collocation multipliers (adaptive
radau returns the multipliers solved from its states: ``stats["algebraic_correction"]``).

Run ``python benchmarks/car_axis_digits.py`` to write ``benchmarks/car_axis_digits.json``.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import mpmath
import numpy as np
import sympy as sp
from car_axis_reference import reduced_system

import daemodel as dm
from daemodel.files import atomic_write
from daemodel.problems.car_axis import CAR_AXIS

HERE = Path(__file__).resolve().parent
STATES = ("xl", "yl", "xr", "yr", "ul", "vl", "ur", "vr")
MULTIPLIERS = ("lam1", "lam2")
TOLERANCES = (1e-8, 1e-10, 1e-12)
METHODS = {"radau s=3": ("radau", {"stages": 3}), "radau s=5": ("radau", {"stages": 5})}
METHODS |= {"radau s=7": ("radau", {"stages": 7}), "radau default": ("radau", {}), "casadi-idas": ("casadi-idas", {})}


def extended_reference() -> dict:
    """The extended-precision values at t = 3 (name -> float) from ``car_axis_reference.json``."""
    stored = json.loads((HERE / "car_axis_reference.json").read_text())
    return {name: float(value) for name, value in stored["reference"].items()}


def digits(values: dict, reference: dict, names) -> float:
    """-log10 of the largest relative error over ``names``."""
    worst = max(abs(values[n] - reference[n]) / abs(reference[n]) for n in names)
    return math.inf if worst == 0 else -math.log10(worst)


def multipliers_from_states(system, t: float, states) -> list:
    """(lam1, lam2) as floats, solved at 30 digits from the 8 ``states`` at ``t``."""
    with mpmath.workdps(30):
        return [float(m) for m in system.multipliers(mpmath.mpf(t), [mpmath.mpf(float(v)) for v in states])]


def error_along_run(system, sol, tol: float) -> float:
    """The largest ``|lam - lam(y)| / (tol + tol |lam(y)|)`` over ``sol``'s times after t = 0."""
    worst = 0.0
    for i in range(1, len(sol.t)):
        solved = multipliers_from_states(system, float(sol.t[i]), [sol[n][i] for n in STATES])
        for name, value in zip(MULTIPLIERS, solved, strict=True):
            worst = max(worst, abs(float(sol[name][i]) - value) / (tol + tol * abs(value)))
    return worst


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=str(Path(__file__).with_suffix(".json")), help="the JSON file to write")
    args = parser.parse_args(argv)
    compiled = CAR_AXIS.model().compile()
    system = reduced_system({k: sp.Rational(repr(v)) for k, v in CAR_AXIS.parameters.items()})
    references = {"published": CAR_AXIS.reference, "extended": extended_reference()}
    rows = []
    for label, (method, options) in METHODS.items():
        for tol in TOLERANCES:
            began = time.perf_counter()
            sol = dm.solve(compiled, CAR_AXIS.t_span, method=method, rtol=tol, atol=tol, t_eval=[0.0, 3.0], **options)
            seconds = time.perf_counter() - began
            end = {n: float(sol[n][-1]) for n in STATES + MULTIPLIERS}
            steps = sol.stats.get("steps", sol.stats.get("nsteps"))  # (IDAS: its own count)
            row = {"method": label, "tol": tol, "status": sol.status, "steps": int(steps)}
            row["wall_s"] = round(seconds, 4)
            for which, reference in references.items():
                row[which] = {
                    "states": round(digits(end, reference, STATES), 2),
                    "multipliers": round(digits(end, reference, MULTIPLIERS), 2),
                    "per_component": {n: round(digits(end, reference, (n,)), 2) for n in STATES + MULTIPLIERS},
                }
            solved = multipliers_from_states(system, 3.0, [end[n] for n in STATES])
            row["multipliers_from_states"] = round(
                digits(dict(zip(MULTIPLIERS, solved, strict=True)), references["extended"], MULTIPLIERS), 2
            )
            run = dm.solve(compiled, CAR_AXIS.t_span, method=method, rtol=tol, atol=tol, **options)
            row["multiplier_error_along_run"] = round(error_along_run(system, run, tol), 3)
            # (adaptive radau: its collocation multipliers' distance from those solved from its states, which it
            # returns: backends/radau/outputs.py)
            row["algebraic_correction"] = run.stats.get("algebraic_correction")
            row["output_times"] = int(np.size(run.t))
            rows.append(row)
            print(
                f"{label:14s} {tol:6.0e} {sol.status:8s} steps {row['steps']:6d}  published: states "
                f"{row['published']['states']:5.2f} lam {row['published']['multipliers']:5.2f}   extended: states "
                f"{row['extended']['states']:5.2f} lam {row['extended']['multipliers']:5.2f}  lam(y) "
                f"{row['multipliers_from_states']:5.2f}  along: {row['multiplier_error_along_run']:.3g} tol"
            )
    result = {"command": "python benchmarks/car_axis_digits.py", "rows": rows}
    atomic_write(Path(args.out), lambda h: h.write(json.dumps(result, indent=1) + "\n"), text=True)
    print(f"wrote {args.out}")
    return result


if __name__ == "__main__":
    main()

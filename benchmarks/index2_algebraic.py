"""Adaptive radau's algebraic variables of index 2 at its step ends: the collocation's values against those
solved from the returned states (``backends/radau/outputs.py``), in tolerances ``|z - exact| / (atol + rtol
|exact|)``, on two index-2 systems with a closed form (the Hessenberg example of ``daemodel.problems`` and the
circle of ``tests/backends/test_radau_outputs.py``) and on the pendulum at index 2 against scipy at 1e-12 (the
reference method), at rtol = atol = 1e-4 ... 1e-10, three stages and the default; with the steps, the solve
time (fastest of ``--passes``, the two interleaved) and the part of it the Newton solve at the outputs takes;
and that part on larger models (``cost``): chains of 20, 60 and 250 pendulums (index 3, solved at index 2:
100 to 1,250 unknowns) and reaction-diffusion at 10^4 unknowns (index 1: nothing solved again).

The collocation's values are read by switching the solve at the outputs off (``collocation_values``): what
radau returned before it.  Run ``python benchmarks/index2_algebraic.py`` to write
``benchmarks/index2_algebraic.json``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import time
from pathlib import Path

import numpy as np
import sympy as sp
from daemodel.backends.radau import backend

import daemodel as dm
from daemodel.files import atomic_write
from daemodel.problems import HESSENBERG, PENDULUM

TOLERANCES = (1e-4, 1e-6, 1e-8, 1e-10)
STAGES = (3, None)


@contextlib.contextmanager
def collocation_values():
    """radau as before the solve at the outputs: the collocation's values returned."""
    original = backend.resolve_outputs
    backend.resolve_outputs = lambda method, compiled, start, options, times, values, stats: (values, None, None)
    try:
        yield
    finally:
        backend.resolve_outputs = original


def circle():
    """``y = (cos t, sin t, e^-t)``, ``z = 1 + sin(3t)/2`` on the circle ``y1^2 + y2^2 = 1`` (index 2, y3 stiff):
    the model of tests/backends/test_radau_outputs.py, and its closed form."""
    m = dm.Model("circle")
    y1, y2, y3 = m.states("y1 y2 y3")
    (z,) = m.algebraics("z")
    ze = 1 + sp.sin(3 * m.t) / 2
    m.ode(y1, -y2 - y1 * ze + y1 * z)
    m.ode(y2, y1 - y2 * ze + y2 * z)
    m.ode(y3, -1000.0 * (y3 - sp.exp(-m.t)) - sp.exp(-m.t) - y3 * ze + y3 * z)
    m.constraint(y1**2 + y2**2 - 1, name="circle")
    m.initial(y1=1.0, y2=0.0, y3=1.0)
    exact = {"y1": np.cos, "y2": np.sin, "y3": lambda t: np.exp(-t), "z": lambda t: 1 + np.sin(3 * t) / 2}
    return m, exact


def in_tolerances(values, exact, tol: float) -> float:
    values, exact = np.ravel(values), np.ravel(exact)
    return float(np.max(np.abs(values - exact) / (tol + tol * np.abs(exact))))


def problems():
    model, exact = circle()
    closed = HESSENBERG.exact_solution()
    hessenberg = {n: (lambda t, n=n: np.ravel(closed(t)[n])) for n in ("y1", "y2", "y3", "y4", "y5")}
    pendulum = PENDULUM.model().compile()

    def pendulum_reference(t):
        ref = dm.solve(pendulum, (0.0, 10.0), method="reference", rtol=1e-12, atol=1e-12, t_eval=t)
        return {n: ref[n] for n in ref.names}

    yield "circle", model.compile(), (0.0, 1.0), lambda t: {n: f(t) for n, f in exact.items()}
    yield "hessenberg", HESSENBERG.model().compile(), (0.0, 1.0), lambda t: {n: f(t) for n, f in hessenberg.items()}
    yield "pendulum", pendulum, (0.0, 10.0), pendulum_reference


def larger_models():
    from scaling_models import reaction_diffusion_arrays

    from daemodel.problems.families import pendulum_chain

    for N in (20, 60, 250):
        yield f"pendulum_chain({N}) over [0, 1]", pendulum_chain(N).compile(), (0.0, 1.0)
    yield "reaction_diffusion_arrays(5000) over [0, 0.1]", reaction_diffusion_arrays(5000).compile(), (0.0, 0.1)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=str(Path(__file__).with_suffix(".json")), help="the JSON file to write")
    parser.add_argument("--passes", type=int, default=3, help="solves of each kind per case (fastest kept)")
    args = parser.parse_args(argv)
    spent = []
    timed = backend.resolve_outputs

    def measured(*arguments):
        began = time.perf_counter()
        try:
            return timed(*arguments)
        finally:
            spent.append(time.perf_counter() - began)

    rows = []
    for name, compiled, span, exact_at in problems():
        (z,) = compiled.algebraic_names
        for stages in STAGES:
            for tol in TOLERANCES:
                options = {"rtol": tol, "atol": tol} | ({} if stages is None else {"stages": stages})
                before, after, spent[:] = [], [], []
                backend.resolve_outputs = measured
                try:
                    for _ in range(args.passes):
                        with collocation_values():
                            before.append(dm.solve(compiled, span, **options))
                        after.append(dm.solve(compiled, span, **options))
                finally:
                    backend.resolve_outputs = timed
                old, new = before[0], after[0]
                if not np.array_equal(old.t, new.t):  # (the same steps: the solve at the outputs changes none)
                    raise RuntimeError(f"{name}: the steps differ with and without the solve at the outputs")
                exact = exact_at(new.t)
                row = {
                    "problem": name,
                    "stages": stages if stages is not None else f"default ({new.settings['stages']})",
                    "tol": tol,
                    "status": new.status,
                    "steps": int(new.stats["steps"]),
                    "steps_before": int(old.stats["steps"]),
                    "z_collocation_tolerances": round(in_tolerances(old[z], exact[z], tol), 3),
                    "z_returned_tolerances": round(in_tolerances(new[z], exact[z], tol), 3),
                    "y_tolerances": round(max(in_tolerances(new[n], exact[n], tol) for n in compiled.state_names), 3),
                    "algebraic_correction": round(new.stats["algebraic_correction"], 3),
                    "solve_s_before": round(min(s.solve_time for s in before), 5),
                    "solve_s_after": round(min(s.solve_time for s in after), 5),
                    "resolve_s": round(min(spent), 5),
                }
                rows.append(row)
                print(
                    f"{name:10s} s={row['stages']!s:12s} {tol:6.0e} steps {row['steps']:5d} ({row['steps_before']})  "
                    f"z: collocation {row['z_collocation_tolerances']:8.3f} tol, returned "
                    f"{row['z_returned_tolerances']:6.3f} tol (y {row['y_tolerances']:.3f})  "
                    f"solve {row['solve_s_before'] * 1e3:7.2f} -> "
                    f"{row['solve_s_after'] * 1e3:7.2f} ms, of which resolve {row['resolve_s'] * 1e3:.2f} ms",
                    flush=True,
                )
    cost = []
    for name, compiled, span in larger_models():
        dm.solve(compiled, span, rtol=1e-6, atol=1e-6)  # (the first solve builds the functions: setup and solve)
        spent[:] = []
        backend.resolve_outputs = measured
        try:
            sols = [dm.solve(compiled, span, rtol=1e-6, atol=1e-6) for _ in range(args.passes)]
        finally:
            backend.resolve_outputs = timed
        row = {
            "model": name,
            "unknowns": len(compiled.states) + len(compiled.algebraics),
            "steps": int(sols[0].stats["steps"]),
            "solve_s": round(min(s.solve_time for s in sols), 4),
            "resolve_s": round(min(spent), 4),
            "resolved": bool(sols[0].stats.get("algebraic_resolved", False)),
        }
        cost.append(row)
        print(row, flush=True)
    result = {"command": "python benchmarks/index2_algebraic.py", "rows": rows, "cost": cost}
    atomic_write(Path(args.out), lambda h: h.write(json.dumps(result, indent=1) + "\n"), text=True)
    print(f"wrote {args.out}")
    return result


if __name__ == "__main__":
    main()

"""Events at a large t0: each cell's outcome, against exact answers, for t0 in {1e6, 1e9, 1e12, 1e13, 1e14, 1e15,
-1e13} x methods {radau, casadi-idas, casadi-collocation, reference} x models over (t0, t0 + 2.5):

- ``ball``: tests/solving/test_events.py's bouncing ball (restitution 0.8), impacts at the closed-form times;
- ``offset``: x' = 1 with an event at t - (t0 + 1.3) that adds 1 to x;
- ``max``: x = cos(tau - 1) (as states), u' = Max(0, x - 0.5): the switch at tau = 1 + acos(0.5), u in closed form.

rtol = atol = 1e-6 (casadi-collocation: h = 0.01, estimate_bound = 1e-6).  Each cell runs in a fresh process under a
wall bound (``--limit``, default 90 s: a cell past it is a hang) and reads: "OK" (status "success", the events and
the end values within 5e-5, ten times the states' tolerance at |v| ~ 4.4), "WRONG" (status "success", not within),
"flag" / "flag-acc" (status "flagged: ...", not / within), or the named error it raised.

    python benchmarks/events_large_t0.py [--before DIR] [--limit 90] [--out benchmarks/events_large_t0_after]

``--before``: a directory holding an earlier tree's ``daemodel`` package (with its ``backends`` inside, as the
install maps it) and its ``tests``, imported in place of the editable install.  Writes ``<out>.json``;
benchmarks/events_large_t0_after.json holds the latest run (its command says on which tree).
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import subprocess
import sys
from pathlib import Path

from daemodel.files import atomic_write

T0S = (1e6, 1e9, 1e12, 1e13, 1e14, 1e15, -1e13)
METHODS = ("radau", "casadi-idas", "casadi-collocation", "reference")
MODELS = ("ball", "offset", "max")
SPAN, TOL = 2.5, 1e-6
# Within the stated accuracy: events' effect and end values within this (ten tolerances at the ball's |v| ~ 4.4).
WITHIN = 10 * TOL * 5

ONE = """
import json, math, os, sys, time, warnings
tree = os.environ.get("DAEMODEL_TREE")
if tree:  # (an earlier tree, ahead of the editable install's finder)
    sys.meta_path[:] = [f for f in sys.meta_path if "editable" not in repr(f).lower()]
    sys.path.insert(0, tree)
sys.path.insert(0, os.path.join(tree or os.getcwd(), "tests", "solving"))
import numpy as np
import torch
torch.set_num_threads(1)
from test_events import G, _ball, _impacts
import daemodel as dm
from daemodel import errors as E

model, t0, method, T, tol = sys.argv[1], float(sys.argv[2]), sys.argv[3], float(sys.argv[4]), float(sys.argv[5])
opts = {"casadi-collocation": {"h": 0.01, "estimate_bound": tol}}.get(method, {"rtol": tol, "atol": tol})
if model == "ball":
    m = _ball(t0=t0)
elif model == "offset":
    m = dm.Model("offset")
    m.states("x")
    m.ode("x", "1")
    m.initial(t=t0, x=0.0)
    m.event("mark", f"t - {t0 + 1.3!r}", reset={"x": "x + 1"})
else:
    m = dm.Model("cap")
    m.states("x v u")
    m.ode("x", "v")
    m.ode("v", "-x")
    m.ode("u", "Max(0, x - 0.5)")
    m.initial(t=t0, x=math.cos(1.0), v=math.sin(1.0), u=0.0)
out = {"model": model, "t0": t0, "method": method}
started = time.perf_counter()
try:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sol = dm.solve(m, (t0, t0 + T), method=method, **opts)
    out["status"] = sol.status
    out["warnings"] = sorted({w.category.__name__ for w in caught})
    name = list(sol.events)[0]
    located = np.asarray(sol.events[name]["t"][0]) - t0
    if model == "ball":
        exact = _impacts(10)
        exact = exact[exact < T]
        last, v = exact[-1], math.sqrt(2 * G) * 0.8 ** len(exact)
        s = T - last
        end = max(abs(sol["h"][-1] - (v * s - 0.5 * G * s * s)), abs(sol["v"][-1] - (v - G * s)))
    elif model == "offset":
        exact = np.array([(t0 + 1.3) - t0])
        end = abs(sol["x"][-1] - (T + 1.0))
    else:
        c = math.acos(0.5)
        exact = np.array([1.0 + c])
        u = math.sin(c) + math.sin(1.0) - 0.5 * (1.0 + c)
        end = max(abs(sol["u"][-1] - u), abs(sol["x"][-1] - math.cos(T - 1.0)))
    k = min(len(located), len(exact))
    out |= {"events": len(located), "exact_events": len(exact), "end_error": float(end)}
    out["event_error"] = float(np.abs(located[:k] - exact[:k]).max()) if k else None
except Exception as error:
    out |= {"error": type(error).__name__, "named": isinstance(error, E.DaemodelError), "message": str(error)}
out["wall"] = time.perf_counter() - started
print("RESULT " + json.dumps(out))
"""


def verdict(row: dict) -> str:
    if "error" in row:
        return row["error"]
    within = row["end_error"] <= WITHIN and row["events"] == row["exact_events"]
    if row["status"] == "success":
        return "OK" if within else "WRONG"
    return "flag-acc" if within else "flag"


def cell(model: str, t0: float, method: str, before: str | None, limit: float) -> dict:
    env = dict(os.environ, OMP_NUM_THREADS="1")
    if before:
        env["DAEMODEL_TREE"] = before
    command = [sys.executable, "-c", ONE, model, repr(t0), method, repr(SPAN), repr(TOL)]
    try:
        done = subprocess.run(command, capture_output=True, text=True, timeout=limit, env=env, check=False)
    except subprocess.TimeoutExpired:
        return {"model": model, "t0": t0, "method": method, "error": "HANG", "wall": limit}
    lines = [line for line in done.stdout.splitlines() if line.startswith("RESULT ")]
    if not lines:
        return {"model": model, "t0": t0, "method": method, "error": "CRASH", "message": done.stderr[-500:]}
    return json.loads(lines[-1][len("RESULT ") :])


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--before", default=None)
    parser.add_argument("--limit", type=float, default=90.0)
    parser.add_argument("--out", default="benchmarks/events_large_t0_after")
    args = parser.parse_args(argv)
    rows = []
    for model, t0, method in itertools.product(MODELS, T0S, METHODS):
        row = cell(model, t0, method, args.before, args.limit)
        row["verdict"] = verdict(row)
        rows.append(row)
        print(f"{model:7s} {t0:9.0e} {method:18s} {row['verdict']}", flush=True)
    command = "python benchmarks/events_large_t0.py " + " ".join(argv if argv is not None else sys.argv[1:])
    text = json.dumps({"command": command.strip(), "rows": rows}, indent=1) + "\n"
    atomic_write(Path(args.out + ".json"), lambda handle: handle.write(text), text=True)


if __name__ == "__main__":
    main()

"""The cost of checking near misses of event functions (daemodel/solving/misses.py): solves with events under
casadi-idas and radau, each in a fresh process, interleaved over passes; status, events found and expected,
location trials, the tighter solves that checked near misses, steps, and the wall (setup + solve).

Rows: the library's bouncing ball (t_span (0, 3)) and the wheelset (rtol = atol = 1e-6, its events), an
oscillator over (0, 3000) whose switch on s - 1 its peaks only touch (default tolerances), and the declared
event on ``c - sin(t + 1.5779)`` over (0, 20) at rtol = atol = 1e-7 with outputs only at the ends, for humps
that cross (c = 0.99, 0.99999, 0.999999) and that do not (c = 1.000001, 1.001); and ``halves-c``: the same over
(0, 40) with a second event at each zero of s (a piece every half period, each near miss's check starting from the
values the pieces before left: misses.CarriedErrors).

    python benchmarks/event_near_misses.py [--passes 3] [--out benchmarks/event_near_misses] [--skip-wheelset]

Writes ``<out>.json`` (one row per solve, and the minimum wall per case).  Timings on a shared machine move
by 2-3x; the counts do not.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from daemodel.files import atomic_write

ONE = """
import json, math, sys, time
import numpy as np
import daemodel as dm
from daemodel.problems import PROBLEMS
method, case = sys.argv[1], sys.argv[2]
if case == "touching-switch":  # (an oscillator whose switch on s - 1 its peaks only touch: 477 peaks near it)
    m = dm.Model("touch")
    m.states("s c w")
    m.ode("s", "c")
    m.ode("c", "-s")
    m.ode("w", "(s - 1)*Heaviside(s - 1)")
    m.initial(s=0.0, c=1.0, w=0.0)
    compiled, t_span, options, expected = m.compile(), (0.0, 3000.0), {}, 0
elif case in PROBLEMS:
    problem = PROBLEMS[case]
    compiled, t_span = problem.model().compile(), problem.t_span
    options = {"rtol": 1e-6, "atol": 1e-6} if case == "wheelset" else {}
    expected = None
else:
    halves = case.startswith("halves-")
    c, phi, t1 = float(case.removeprefix("halves-")), 1.5779, 40.0 if halves else 20.0
    m = dm.Model("humps")
    m.states("s c n")
    m.ode("s", "c")
    m.ode("c", "-s")
    m.ode("n", "0")
    m.initial(s=math.sin(phi), c=math.cos(phi), n=0.0)
    m.event("hump", f"{c} - s", reset={"n": "n + 1"})
    if halves:
        m.event("zero", "s")
    compiled, t_span = m.compile(), (0.0, t1)
    options = {"rtol": 1e-7, "atol": 1e-7, "t_eval": [0.0, t1]}
    if c < 1:
        k = 2 * math.pi * np.arange(8)
        times = np.concatenate([math.pi / 2 - math.acos(c) + k, math.pi / 2 + math.acos(c) + k]) - phi
        expected = int(np.sum((times > 0) & (times < t1)))
    else:
        expected = 0
began = time.perf_counter()
sol = dm.solve(compiled, t_span, method=method, **options)
wall = time.perf_counter() - began
s = sol.stats
print(json.dumps({"status": sol.status if sol.status == "success" else "flagged: " + sol.status[:80],
    "events": int(np.asarray(sol.events["hump"]["t"]).shape[-1] if "hump" in sol.events else
        sum(np.asarray(e["t"]).shape[-1] for e in sol.events.values())), "expected": expected,
    "location_trials": s.get("location_trials"), "near_miss_checks": s.get("near_miss_checks"),
    "steps": s.get("steps", s.get("nsteps")), "setup": sol.setup_time, "solve": sol.solve_time, "wall": wall}))
"""

CASES = [("casadi-idas", "bouncing-ball"), ("radau", "bouncing-ball")]
CASES += [("casadi-idas", "touching-switch"), ("radau", "touching-switch")]
CASES += [
    (method, c) for c in ("0.99", "0.99999", "0.999999", "1.000001", "1.001") for method in ("casadi-idas", "radau")
]
CASES += [("casadi-idas", f"halves-{c}") for c in ("0.99999", "0.999999", "1.000001")]
WHEELSET = [("casadi-idas", "wheelset")]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--passes", type=int, default=3)
    parser.add_argument("--out", default=str(Path(__file__).with_suffix("")))
    parser.add_argument("--skip-wheelset", action="store_true")
    args = parser.parse_args()
    cases = CASES + ([] if args.skip_wheelset else WHEELSET)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
    env.setdefault("DAEMODEL_CACHE", tempfile.mkdtemp(prefix="daemodel-bench-"))
    rows = []
    for k in range(args.passes):
        for method, case in cases:
            done = subprocess.run(
                [sys.executable, "-c", ONE, method, case], capture_output=True, text=True, env=env, check=True
            )
            row = {"pass": k, "method": method, "case": case, **json.loads(done.stdout.strip().splitlines()[-1])}
            rows.append(row)
            print(json.dumps(row), flush=True)
    best = {}
    for row in rows:
        key = f"{row['method']} {row['case']}"
        best[key] = min(best.get(key, float("inf")), row["wall"])
    command = "python benchmarks/event_near_misses.py " + " ".join(sys.argv[1:])
    result = {"command": command.strip(), "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "rows": rows}
    result["min_wall"] = best
    atomic_write(Path(f"{args.out}.json"), lambda handle: handle.write(json.dumps(result, indent=1)), text=True)


if __name__ == "__main__":
    main()

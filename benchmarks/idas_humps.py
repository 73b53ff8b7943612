"""casadi-idas's event search on crossings between its outputs: the declared event on 0.99 - sin t over
(0, 3000) at rtol = atol = 1e-7 with outputs only at the ends (956 crossings, two a hump, 0.28 apart, 2 pi
between humps), and the wheelset at rtol = atol = 1e-6 (radau: 268-280 events); each solve in a fresh
process: crossings found and missed, status (or the error raised), wall and CPU seconds, IDAS's steps.

    python benchmarks/idas_humps.py [--passes 1] [--wheelset] [--label after] [--out benchmarks/idas_humps]

Appends its rows to ``<out>.json`` (``label`` tells runs apart: "before" was run on the commit before the
windowed search).  Timings on a shared machine move by 2-3x; the counts do not.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from daemodel.files import atomic_write

HUMPS = """
import json, math, sys, time
import numpy as np
import daemodel as dm
c, t1 = 0.99, 3000.0
m = dm.Model("humps")
m.states("s c n")
m.ode("s", "c")
m.ode("c", "-s")
m.ode("n", "0")
m.initial(s=0.0, c=1.0, n=0.0)
m.event("hump", f"{c} - s", reset={"n": "n + 1"})
k = 2.0 * math.pi * np.arange(int(t1 / (2.0 * math.pi)) + 2)
exact = np.sort(np.concatenate([math.pi / 2 - math.acos(c) + k, math.pi / 2 + math.acos(c) + k]))
exact = exact[exact < t1]
began, cpu = time.perf_counter(), time.process_time()
sol = dm.solve(m, (0.0, t1), method="casadi-idas", rtol=1e-7, atol=1e-7, t_eval=[0.0, t1])
wall, cpu = time.perf_counter() - began, time.process_time() - cpu
found = sol.events["hump"]["t"][0]
near = np.abs(found[:, None] - exact[None, :]).min(axis=1) if len(found) else np.zeros(0)
print(json.dumps({
    "problem": "humps 0.99 - sin t, (0, 3000), rtol 1e-7", "status": sol.status, "crossings": len(exact),
    "found": len(found), "missed": len(exact) - len(found), "worst_location": float(near.max(initial=0.0)),
    "wall": wall, "cpu": cpu, "idas_steps": sol.stats.get("nsteps"),
}))
"""

WHEELSET = """
import json, time
import numpy as np
import daemodel as dm
from daemodel.errors import SolverError
from daemodel.problems import WHEELSET
compiled = WHEELSET.model().compile()
began, cpu = time.perf_counter(), time.process_time()
row = {"problem": "wheelset, rtol 1e-6"}
try:
    sol = dm.solve(compiled, WHEELSET.t_span, method="casadi-idas", rtol=1e-6, atol=1e-6, t_eval=[0.0, 10.0])
except SolverError as error:
    row |= {"status": f"raised {type(error).__name__}: {error}"}
else:
    names = [n for n in WHEELSET.reference if not n.startswith("lam")]
    digits = -np.log10(max(abs(sol[n][-1] - WHEELSET.reference[n]) / abs(WHEELSET.reference[n]) for n in names))
    row |= {"status": sol.status, "events": sol.stats.get("events"), "digits": float(digits)}
row |= {"wall": time.perf_counter() - began, "cpu": time.process_time() - cpu}
print(json.dumps(row))
"""


def one(script: str) -> dict:
    """One solve in a fresh process, one thread."""
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    out = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--passes", type=int, default=1)
    parser.add_argument("--wheelset", action="store_true")
    parser.add_argument("--label", default="after")
    parser.add_argument("--out", default="benchmarks/idas_humps")
    args = parser.parse_args()
    path = Path(f"{args.out}.json")
    record = json.loads(path.read_text()) if path.exists() else {"runs": []}
    rows = []
    for p in range(args.passes):
        for script in (HUMPS, WHEELSET) if args.wheelset else (HUMPS,):
            rows.append({"pass": p, "label": args.label, **one(script)})
            print(rows[-1], flush=True)
    command = " ".join(["python", *sys.argv])
    record["runs"].append({"command": command, "date": time.strftime("%Y-%m-%d %H:%M"), "rows": rows})
    atomic_write(path, lambda handle: handle.write(json.dumps(record, indent=1)), text=True)


if __name__ == "__main__":
    main()

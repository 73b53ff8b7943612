"""The wheelset at rtol = atol = 1e-6 (issue 42 item 6): radau with its defaults from a cold and a warm
disk cache, and casadi-idas, each solve in a fresh process, interleaved; steps, rejections, events, the
static factorisations that fell back to LAPACK, setup, solve, wall and the digits at t = 10.

    python benchmarks/wheelset.py [--passes 3] [--out benchmarks/wheelset]

Writes ``<out>.json`` (one row per solve; a solve that raises a named error is a row with its status and
wall).  Timings on a shared machine move by 2-3x; the counts do not.
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
import json, sys, time
import numpy as np
import daemodel as dm
from daemodel.problems import WHEELSET
method, rtol = sys.argv[1], float(sys.argv[2])
compiled = WHEELSET.model().compile()
began = time.perf_counter()
options = {"max_steps": 400_000} if method == "radau" else {}
try:
    sol = dm.solve(compiled, WHEELSET.t_span, method=method, rtol=rtol, atol=rtol, t_eval=[0.0, 10.0], **options)
except dm.errors.DaemodelError as error:  # (a named failure is a row too: casadi-idas since its search)
    wall = time.perf_counter() - began
    status = f"raised {type(error).__name__}: {str(error)[:300]}"
    print(json.dumps({"method": method, "rtol": rtol, "status": status, "wall": wall, "t": getattr(error, "t", None)}))
    sys.exit(0)
wall = time.perf_counter() - began
def digits(names):
    return float(-np.log10(max(abs(sol[n][-1] - WHEELSET.reference[n]) / abs(WHEELSET.reference[n]) for n in names)))
s = sol.stats
print(json.dumps({
    "method": method, "rtol": rtol, "status": sol.status, "setup": sol.setup_time, "solve": sol.solve_time,
    "wall": wall, "events": s.get("events"), "steps": s.get("steps", s.get("nsteps")),
    "rejected": s.get("rejected_steps", s.get("netfails")), "pivot_failures": s.get("pivot_failures"),
    "cache": s.get("compiled_cache"),
    "digits": digits([n for n in WHEELSET.reference if not n.startswith("lam")]),
    "digits_multipliers": digits(["lam1", "lam2"]),
}))
"""


def one(method: str, rtol: float, cache: str) -> dict:
    """One solve in a fresh process with ``DAEMODEL_CACHE=cache``."""
    env = {**os.environ, "DAEMODEL_CACHE": cache, "OMP_NUM_THREADS": "1"}
    out = subprocess.run(
        [sys.executable, "-c", ONE, method, repr(rtol)], env=env, capture_output=True, text=True, check=True
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--passes", type=int, default=3)
    parser.add_argument("--rtol", type=float, default=1e-6)
    parser.add_argument("--out", default="benchmarks/wheelset")
    args = parser.parse_args()
    rows = []
    for p in range(args.passes):
        with tempfile.TemporaryDirectory() as cache:
            os.chmod(cache, 0o700)
            for kind in ("cold", "warm"):
                rows.append({"pass": p, "kind": kind, **one("radau", args.rtol, cache)})
                print(rows[-1], flush=True)
            rows.append({"pass": p, "kind": "-", **one("casadi-idas", args.rtol, cache)})
            print(rows[-1], flush=True)
    record = {"command": " ".join(["python", *sys.argv]), "date": time.strftime("%Y-%m-%d"), "rows": rows}
    atomic_write(Path(f"{args.out}.json"), lambda handle: handle.write(json.dumps(record, indent=1)), text=True)


if __name__ == "__main__":
    main()

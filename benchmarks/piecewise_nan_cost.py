"""The cost of Piecewise passing a nan on (functions.compared: a nan compared in a condition gives a nan, not the
otherwise branch): a switch-heavy model, x'' = -x with u' = Piecewise((x, x > 0.5), (0, True)) and w' = Piecewise((1,
(x < -0.5) & (v > 0)), (-1, x > 0.9), (0, True)) over (0, 20) at rtol 1e-6 (26 switch crossings), solved by radau,
and its numpy right-hand side on 10^5 samples.  Each pass runs each tree in a fresh process, interleaved; the
minimum wall per tree.

    python benchmarks/piecewise_nan_cost.py [--passes 5] [--before DIR] [--out benchmarks/piecewise_nan_cost]

``--before``: a directory holding an earlier tree's ``daemodel`` package (with its ``backends`` inside).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

from daemodel.files import atomic_write

ONE = """
import json, os, sys, time
if os.environ.get("DAEMODEL_TREE"):  # (an earlier tree, ahead of the editable install's finder)
    sys.meta_path[:] = [f for f in sys.meta_path if "editable" not in repr(f).lower()]
    sys.path.insert(0, os.environ["DAEMODEL_TREE"])
import numpy as np
import torch
torch.set_num_threads(1)
import daemodel as dm
m = dm.Model("pwheavy")
m.states("x v u w")
m.ode("x", "v")
m.ode("v", "-x")
m.ode("u", "Piecewise((x, x > 0.5), (0, True))")
m.ode("w", "Piecewise((1, (x < -0.5) & (v > 0)), (-1, x > 0.9), (0, True))")
m.initial(x=1.0, v=0.0, u=0.0, w=0.0)
c = m.compile()
f = c.numeric.batch_function(list(c.rhs))
Y = np.random.default_rng(0).normal(size=(100000, 4))
args = (np.zeros(len(Y)), Y, np.zeros((len(Y), 0)), np.zeros((1, 0)))
f(*args)
times = []
for _ in range(20):
    started = time.perf_counter()
    f(*args)
    times.append(time.perf_counter() - started)
dm.solve(m, (0.0, 1.0), rtol=1e-6, atol=1e-6)
walls = []
for _ in range(3):
    started = time.perf_counter()
    sol = dm.solve(m, (0.0, 20.0), rtol=1e-6, atol=1e-6)
    walls.append(time.perf_counter() - started)
out = {"numpy_rhs_1e5_s": min(times), "solve_s": min(walls), "events": int(sol.stats["events"]),
       "steps": int(sol.stats["steps"]), "u_end": float(sol["u"][-1]), "w_end": float(sol["w"][-1])}
print("RESULT " + json.dumps(out))
"""


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--passes", type=int, default=5)
    parser.add_argument("--before", default=None)
    parser.add_argument("--out", default="benchmarks/piecewise_nan_cost")
    args = parser.parse_args(argv)
    rows = []
    trees = [("after", None)] + ([("before", args.before)] if args.before else [])
    for _ in range(args.passes):
        for tree, path in trees:
            env = dict(os.environ, OMP_NUM_THREADS="1")
            env.pop("DAEMODEL_TREE", None)
            if path:
                env["DAEMODEL_TREE"] = path
            done = subprocess.run([sys.executable, "-c", ONE], capture_output=True, text=True, env=env, check=True)
            line = [x for x in done.stdout.splitlines() if x.startswith("RESULT ")][-1]
            rows.append({"tree": tree, **json.loads(line[len("RESULT ") :])})
            print(rows[-1], flush=True)
    minima = {
        tree: {key: min(r[key] for r in rows if r["tree"] == tree) for key in ("numpy_rhs_1e5_s", "solve_s")}
        for tree, _ in trees
    }
    command = "python benchmarks/piecewise_nan_cost.py " + " ".join(argv if argv is not None else sys.argv[1:])
    text = json.dumps({"command": command.strip(), "minima": minima, "rows": rows}, indent=1) + "\n"
    atomic_write(Path(args.out + ".json"), lambda handle: handle.write(text), text=True)


if __name__ == "__main__":
    main()

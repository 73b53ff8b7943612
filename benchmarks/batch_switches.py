"""A batch without t_eval whose model switches on its states (daemodel/solving/batches.py): x' = -Min(1, x)
over (0, 3) from B initial values in [1.2, 2.8] at the default tolerance, against the closed form (x = x0 - t
until x = 1, then exp(-(t - (x0 - 1)))).  Each solve in a fresh process, the trees interleaved over passes;
the batch without t_eval, with t_eval (31 times), and (B = 3) each sample alone.

    python benchmarks/batch_switches.py [--passes 3] [--before DIR] [--out benchmarks/batch_switches]

``--before``: a directory holding an earlier tree's ``daemodel`` package (with its ``backends`` inside, as the
install maps it), imported in place of the editable install.  Writes ``<out>.json`` (one row per solve,
and the minimum wall per case and tree).  Timings on a shared machine move by 2-3x; the errors do not.
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
import json, math, os, sys, time
if os.environ.get("DAEMODEL_TREE"):  # (an earlier tree, ahead of the editable install's finder)
    sys.meta_path[:] = [f for f in sys.meta_path if "editable" not in repr(f).lower()]
    sys.path.insert(0, os.environ["DAEMODEL_TREE"])
import numpy as np
import torch
torch.set_num_threads(1)
import daemodel as dm
B, how = int(sys.argv[1]), sys.argv[2]
m = dm.Model("minmod")
m.states("x")
m.ode("x", "-Min(1, x)")
m.initial(x=2.0)
x0 = np.linspace(1.2, 2.8, B)
exact = lambda x0, t: x0 - t if t <= x0 - 1 else math.exp(-(t - (x0 - 1)))
dm.solve(m, (0.0, 0.1), y0={"x": x0[:2]})  # (warm: imports, code generation)
began = time.perf_counter()
if how == "alone":
    sols = []
    for value in x0:
        m.initial(x=float(value))
        sols.append(dm.solve(m, (0.0, 3.0)))
    wall = time.perf_counter() - began
    error = max(abs(s["x"][-1] - exact(v, 3.0)) for s, v in zip(sols, x0))
    status, steps, alone = sols[0].status, sum(s.stats["steps"] for s in sols), None
else:
    options = {"t_eval": np.linspace(0.0, 3.0, 31)} if how == "t_eval" else {}
    sol = dm.solve(m, (0.0, 3.0), y0={"x": x0}, **options)
    wall = time.perf_counter() - began
    error = max(abs(sol["x"][b][-1] - exact(v, 3.0)) for b, v in enumerate(x0))
    status, steps, alone = sol.status, int(sol.stats["steps"]), sol.stats.get("samples_alone_steps")
print(json.dumps(dict(status=status, error_at_t1=error, steps=steps, samples_alone_steps=alone, wall=wall)))
"""

CASES = [(3, "no t_eval"), (3, "t_eval"), (3, "alone"), (50, "no t_eval"), (50, "t_eval")]


def run(tree: str | None, B: int, how: str) -> dict:
    env = dict(os.environ, OMP_NUM_THREADS="1")
    if tree is not None:
        env["DAEMODEL_TREE"] = tree
    out = subprocess.run([sys.executable, "-c", ONE, str(B), how], env=env, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--passes", type=int, default=3)
    parser.add_argument("--before", default=None)
    parser.add_argument("--out", default="benchmarks/batch_switches")
    args = parser.parse_args(argv)
    trees = {"after": None} if args.before is None else {"before": args.before, "after": None}
    rows = []
    for k in range(args.passes):
        for B, how in CASES:
            for name, tree in trees.items():
                row = dict(tree=name, pass_=k, B=B, case=how, **run(tree, B, how))
                print(row, flush=True)
                rows.append(row)
    best = {}
    for row in rows:
        key = f"{row['tree']} B={row['B']} {row['case']}"
        best[key] = min(best.get(key, float("inf")), row["wall"])
    command = "python benchmarks/batch_switches.py " + " ".join(argv if argv is not None else sys.argv[1:])
    text = json.dumps(dict(command=command, rows=rows, min_wall=best), indent=1, default=float)
    atomic_write(Path(args.out + ".json"), lambda handle: handle.write(text), text=True)


if __name__ == "__main__":
    main()

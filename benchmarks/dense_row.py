"""One dense row and one dense column (issue 44): radau's setup and solve against the number of states.

Run as ``python benchmarks/dense_row.py [--sizes 1000 2000 3000] [--before DIR] [--out PATH]``.  The model:
``y_i' = -(1 + i / K) y_i + z / 10`` for K states and ``0 = z - mean(y)``: the constraint reads every state
(a dense row) and every rate reads z (a dense column), on t in [0, 1] at radau's defaults.  Each cell runs in a
fresh process (one BLAS and torch thread) that declares and compiles the model and solves it once: declare,
compile, the solve's setup and solve clocks, steps, the final states' max difference from casadi-idas at rtol
1e-10, and the process's peak resident memory.  ``--before DIR``: a checkout of the code before a change
(``git archive <commit> | tar -x -C DIR`` and ``ln -s ../backends DIR/daemodel/backends``), run with the
editable install's import hook removed and DIR first on the path.  Writes ``<out>.json`` (every number, the
command).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
WORKER_LIMIT = 1_200  # (seconds a cell may take: compiling 3,000 states took ~60 s on a loaded core)


def mean_model(K: int):
    """The model of the module docstring, with K states."""
    import sympy as sp

    import daemodel as dm

    m = dm.Model(f"mean_{K}")
    y = m.states("y", K)
    (z,) = m.algebraics("z")
    m.ode(y, np.array([-y[i] * (1 + sp.Rational(i, K)) + z / 10 for i in range(K)], dtype=object))
    m.constraint(z - sum(y) / K, name="mean")
    m.initial(y=np.linspace(0.1, 1.0, K))
    return m


def worker(task: dict) -> dict:
    """One cell, in this fresh process (``task["before"]``: that checkout's code)."""
    if task.get("before"):
        sys.meta_path[:] = [f for f in sys.meta_path if getattr(f, "__name__", "") != "_EditableFinder"]
        sys.path.insert(0, task["before"])
    import torch

    import daemodel as dm

    torch.set_num_threads(1)
    began = time.perf_counter()
    model = mean_model(task["size"])
    declared = time.perf_counter()
    compiled = model.compile()
    done = time.perf_counter()
    sol = dm.solve(compiled, (0.0, 1.0))
    reference = dm.solve(compiled, (0.0, 1.0), method="casadi-idas", rtol=1e-10, atol=1e-12)
    return {
        "code": dm.__file__,
        "declare_s": declared - began,
        "compile_s": done - declared,
        "setup_s": sol.setup_time,
        "solve_s": sol.solve_time,
        "steps": sol.stats["steps"],
        "status": sol.status,
        "error_y_final": float(np.abs(np.asarray(sol["y"])[..., -1] - np.asarray(reference["y"])[..., -1]).max()),
        "peak_rss_MB": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }


def run(task: dict) -> dict:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    command = [sys.executable, __file__, "--worker", json.dumps(task)]
    try:
        done = subprocess.run(command, env=env, timeout=WORKER_LIMIT, capture_output=True, text=True)
    except subprocess.TimeoutExpired:
        return {"failed": f"stopped after {WORKER_LIMIT} s"}
    if done.returncode != 0:
        return {"failed": done.stderr[-1500:]}
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1_000, 2_000, 3_000])
    parser.add_argument("--before", type=str, default=None)
    parser.add_argument("--out", type=Path, default=HERE / "dense_row")
    parser.add_argument("--worker", type=str, default=None)
    args = parser.parse_args()
    if args.worker:
        print(json.dumps(worker(json.loads(args.worker))))
        return
    versions = {"after": None} | ({"before": str(Path(args.before).resolve())} if args.before else {})
    results = {}
    for size in args.sizes:
        for version, before in versions.items():  # (interleaved: each size's versions one after the other)
            cell = run({"size": size, "before": before})
            print(size, version, json.dumps(cell)[:400], file=sys.stderr, flush=True)
            results.setdefault(str(size), {})[version] = cell
    command = "python benchmarks/dense_row.py " + " ".join(sys.argv[1:])
    record = {"command": command, "machine": os.uname().nodename, "load": os.getloadavg(), "results": results}
    args.out.with_suffix(".json").write_text(json.dumps(record, indent=1))


if __name__ == "__main__":
    main()

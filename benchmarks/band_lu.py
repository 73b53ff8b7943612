"""Issue 44 at 10^3-10^5 unknowns: radau (default settings) against casadi-idas, before and after a change.

Run as ``python benchmarks/band_lu.py [--unknowns 1000 10000 100000] [--passes 2] [--before DIR] [--out PATH]``.
The reaction-diffusion family (``scaling_models.DECLARATIONS["stencils"]``: index 1, tridiagonal, one
state and one algebraic variable per point) on t in [0, 1] with 11 output times.  Each cell runs in a
fresh process (one BLAS and torch thread) that declares and compiles the model, then solves it twice;
the cells are interleaved (pass by pass: every version and method once per pass) and the minimum over
passes is kept.  Per cell: declare and compile seconds, the first solve's setup and solve, the second
solve's solve, steps, residual evaluations, Newton iterations and factorisations (radau), the max
absolute error of the states and algebraic variables at the output times against casadi-idas at rtol
1e-10 (atol 1e-12, computed once per size), and the process's peak resident memory.

``--before DIR``: a checkout of the code before the change (``git archive <commit> | tar -x -C DIR``),
run with the editable install's import hook removed and DIR first on the path (``daemodel/backends``
there a link to ``DIR/backends``, as the install maps it).  Methods: radau at its defaults (rtol 1e-6,
atol 1e-8); casadi-idas at rtol 1e-7 and 1e-8 (atol rtol / 100), the two that bracket radau's error.
Writes ``<out>.json`` (every number, the command) and ``<out>.png``.
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
METHODS = {
    "radau": {"method": "radau"},
    "idas-1e-7": {"method": "casadi-idas", "rtol": 1e-7, "atol": 1e-9},
    "idas-1e-8": {"method": "casadi-idas", "rtol": 1e-8, "atol": 1e-10},
}
OUTPUT_POINTS = 11
WORKER_LIMIT = 1_200  # (seconds a cell may take: declaring and compiling 10^5 unknowns take ~15 s)


def worker(task: dict) -> dict:
    """One cell, in this fresh process (``task["before"]``: that checkout's code)."""
    if task.get("before"):
        sys.meta_path[:] = [f for f in sys.meta_path if getattr(f, "__name__", "") != "_EditableFinder"]
        sys.path.insert(0, task["before"])
    sys.path.insert(0, str(HERE))
    import scaling_models
    import torch

    import daemodel as dm

    torch.set_num_threads(1)
    began = time.perf_counter()
    model = scaling_models.DECLARATIONS["stencils"](task["unknowns"] // 2)
    declared = time.perf_counter()
    compiled = model.compile()
    done = time.perf_counter()
    times = np.linspace(0.0, 1.0, OUTPUT_POINTS)
    names = [*compiled.state_names, *compiled.algebraic_names]
    options = METHODS.get(task["method"], {"method": "casadi-idas", "rtol": 1e-10, "atol": 1e-12})
    first = dm.solve(compiled, (0.0, 1.0), t_eval=times, **options)
    second = dm.solve(compiled, (0.0, 1.0), t_eval=times, **options)
    values = np.stack([np.asarray(second[name], dtype=float) for name in names])
    out = {
        "code": dm.__file__,
        "declare_s": declared - began,
        "compile_s": done - declared,
        "setup_s": first.setup_time,
        "first_solve_s": first.solve_time,
        "solve_s": second.solve_time,
        "peak_rss_MB": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "stats": {k: v for k, v in second.stats.items() if isinstance(v, int | float | str | type(None))},
    }
    if task.get("reference"):
        np.save(task["reference"], values)
    else:
        reference = np.load(task["reference_file"])
        n = len(compiled.state_names)
        out["error_y"] = float(np.abs(values[:n] - reference[:n]).max())
        out["error_z"] = float(np.abs(values[n:] - reference[n:]).max())
    return out


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


def plot(results: dict, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    for (version, method), style in {
        ("before", "radau"): "o--",
        ("after", "radau"): "o-",
        ("after", "idas-1e-7"): "s:",
        ("after", "idas-1e-8"): "s-",
    }.items():
        sizes = [int(u) for u in results if (version, method) in map(tuple, results[u]["keys"])]
        cells = [results[str(u)]["cells"][f"{version}/{method}"] for u in sizes]
        solve = [c["solve_s"] for c in cells if "solve_s" in c]
        if solve:
            ax.loglog(sizes[: len(solve)], solve, style, label=f"{method} ({version})")
    ax.set_xlabel("unknowns")
    ax.set_ylabel("solve (s), min over passes")
    ax.set_title("reaction-diffusion, t in [0, 1]: radau default vs casadi-idas")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(out.with_suffix(".png"), dpi=120)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--unknowns", type=int, nargs="+", default=[1_000, 10_000, 100_000])
    parser.add_argument("--passes", type=int, default=2)
    parser.add_argument("--before", type=str, default=None)
    parser.add_argument("--out", type=Path, default=HERE / "band_lu")
    parser.add_argument("--worker", type=str, default=None)
    args = parser.parse_args()
    if args.worker:
        print(json.dumps(worker(json.loads(args.worker))))
        return
    folder = args.out.parent
    versions = {"after": None} | ({"before": str(Path(args.before).resolve())} if args.before else {})
    results = {}
    for unknowns in args.unknowns:
        reference = folder / f".band_lu_reference_{unknowns}.npy"
        ref = run({"unknowns": unknowns, "method": "reference", "reference": str(reference)})
        keys = [(v, m) for m in METHODS for v in versions if not (v == "before" and m != "radau")]
        cells: dict = {}
        for p in range(args.passes):
            for version, method in keys:
                task = {"unknowns": unknowns, "method": method, "reference_file": str(reference)}
                cell = run({**task, "before": versions[version]})
                print(unknowns, p, version, method, json.dumps(cell)[:400], file=sys.stderr, flush=True)
                best = cells.setdefault(f"{version}/{method}", {"passes": []})
                best["passes"].append(cell)
        for cell in cells.values():
            done = [c for c in cell["passes"] if "failed" not in c]
            for key in ("declare_s", "compile_s", "setup_s", "first_solve_s", "solve_s", "peak_rss_MB"):
                if done:
                    cell[key] = min(c[key] for c in done)
        results[str(unknowns)] = {"reference": ref, "keys": keys, "cells": cells}
        reference.unlink(missing_ok=True)
    command = "python benchmarks/band_lu.py " + " ".join(sys.argv[1:])
    record = {"command": command, "machine": os.uname().nodename, "load": os.getloadavg(), "results": results}
    args.out.with_suffix(".json").write_text(json.dumps(record, indent=1))
    plot(results, args.out)


if __name__ == "__main__":
    main()

"""Issue 44: radau against casadi-idas at equal error, in one process, interleaved (for loaded machines).

Run as ``python benchmarks/interleaved_large.py [--unknowns 10000 100000] [--passes 6] [--out PATH]``.
The reaction-diffusion family (``scaling_models.DECLARATIONS["stencils"]``) on t in [0, 1] with 11 output
times, declared and compiled once per size; then, pass by pass, radau at its defaults (rtol 1e-6, atol 1e-8)
and casadi-idas at rtol 1e-7 and 1e-8 (atol rtol / 100: the two that bracket radau's error) each solve it
once, and the minimum of each ``solve_time`` over the passes is kept (``benchmarks/scaling.py --large``
runs each cell in a fresh process, whose single times a machine shared with other jobs makes noisy).
Errors: max absolute over states and algebraic variables at the output times against casadi-idas at rtol
1e-10 (atol 1e-12).  IDAS's solve at radau's error is read off its two points by log-log interpolation.
Writes ``<out>.json`` (every time, the command, the load average).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")  # (one BLAS thread, set before numpy loads it)

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

METHODS = {
    "radau": {"method": "radau"},
    "idas-1e-7": {"method": "casadi-idas", "rtol": 1e-7, "atol": 1e-9},
    "idas-1e-8": {"method": "casadi-idas", "rtol": 1e-8, "atol": 1e-10},
}
OUTPUT_POINTS = 11


def measure(unknowns: int, passes: int) -> dict:
    """Every method's solve times over ``passes`` interleaved passes at one size, with errors and stats."""
    import scaling_models

    import daemodel as dm

    began = time.perf_counter()
    compiled = scaling_models.DECLARATIONS["stencils"](unknowns // 2).compile()
    built = time.perf_counter() - began
    times = np.linspace(0.0, 1.0, OUTPUT_POINTS)
    names = [*compiled.state_names, *compiled.algebraic_names]

    def values(sol):
        return np.stack([np.asarray(sol[name], dtype=float) for name in names])

    reference = values(dm.solve(compiled, (0.0, 1.0), method="casadi-idas", rtol=1e-10, atol=1e-12, t_eval=times))
    cells = {name: {"solve_s": []} for name in METHODS}
    for p in range(passes):
        for name, options in METHODS.items():
            sol = dm.solve(compiled, (0.0, 1.0), t_eval=times, **options)
            cells[name]["solve_s"].append(sol.solve_time)
            if p == 0:
                cells[name]["setup_s"] = sol.setup_time
                cells[name]["error"] = float(np.abs(values(sol) - reference).max())
                stats = ("steps", "newton_iterations", "lu_decompositions", "band_lu")
                cells[name]["stats"] = {k: sol.stats[k] for k in stats if k in sol.stats}
            print(unknowns, p, name, f"{sol.solve_time:.4f}", file=sys.stderr, flush=True)
    for cell in cells.values():
        cell["min_solve_s"] = min(cell["solve_s"])
    (e0, s0), (e1, s1) = ((cells[k]["error"], cells[k]["min_solve_s"]) for k in ("idas-1e-7", "idas-1e-8"))
    error = cells["radau"]["error"]
    x = float(np.log(error / e0) / np.log(e1 / e0))  # (0 at rtol 1e-7's error, 1 at 1e-8's; outside: extrapolated)
    idas = float(np.exp((1 - x) * np.log(s0) + x * np.log(s1)))
    ratio = cells["radau"]["min_solve_s"] / idas
    return {"declare_and_compile_s": built, "cells": cells, "idas_at_radau_error_s": idas, "ratio": ratio, "x": x}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--unknowns", type=int, nargs="+", default=[10_000, 100_000])
    parser.add_argument("--passes", type=int, default=6)
    parser.add_argument("--out", type=Path, default=HERE / "interleaved_large")
    args = parser.parse_args()
    import torch

    torch.set_num_threads(1)
    results = {str(u): measure(u, args.passes) for u in args.unknowns}
    command = "python benchmarks/interleaved_large.py " + " ".join(sys.argv[1:])
    record = {"command": command, "load": os.getloadavg(), "threads": 1, "results": results}
    args.out.with_suffix(".json").write_text(json.dumps(record, indent=1))
    print("| unknowns | radau error | radau solve (min) | IDAS solve at it | ratio |\n|---:|---:|---:|---:|---:|")
    for u, r in results.items():
        c = r["cells"]["radau"]
        idas = r["idas_at_radau_error_s"]
        print(f"| {u} | {c['error']:.2g} | {c['min_solve_s']:.3g} | {idas:.3g} | {r['ratio']:.2f}x |")


if __name__ == "__main__":
    main()

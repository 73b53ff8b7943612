"""Issue 44: radau against casadi-idas at equal error, in one process, interleaved (for loaded machines).

Run as ``python benchmarks/interleaved_large.py [--unknowns 10000 100000] [--passes 6] [--before] [--cpu]
[--out PATH]``.
The reaction-diffusion family (``scaling_models.DECLARATIONS["stencils"]``) on t in [0, 1] with 11 output
times, declared and compiled once per size; then, pass by pass, radau at its defaults (rtol 1e-6, atol 1e-8)
and casadi-idas at rtol 1e-7 and 1e-8 (atol rtol / 100: the two that bracket radau's error) each solve it
once, and the minimum of each ``solve_time`` over the passes is kept (``benchmarks/scaling.py --large``
runs each cell in a fresh process, whose single times a machine shared with other jobs makes noisy).
Errors: max absolute over states and algebraic variables at the output times against casadi-idas at rtol
1e-10 (atol 1e-12).  IDAS's solve at radau's error is read off its two points by log-log interpolation.
With ``--cpu`` the Solutions' clocks are CPU seconds of this one-thread process (``time.perf_counter``
replaced by ``time.process_time`` before any solve, as ``first_solve_cpu.py``: on 2 cores at load 8, wall
minima of one cell spread 1.5-3 s).  With ``--before``, a cell "radau-nostencil" too: radau with its stage
residual on casadi's virtual machine (``backends/radau/stencil.py`` patched out for that cell's solves; the
same bits).  Writes ``<out>.json`` (every time, the command, the load average).
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


def measure(unknowns: int, passes: int, before: bool = False) -> dict:
    """Every method's solve times over ``passes`` interleaved passes at one size, with errors and stats."""
    import scaling_models
    from daemodel.backends.radau import stencil

    import daemodel as dm

    methods = {**METHODS, **({"radau-nostencil": {"method": "radau"}} if before else {})}
    equations = stencil.stencil_equations

    began = time.perf_counter()
    compiled = scaling_models.DECLARATIONS["stencils"](unknowns // 2).compile()
    built = time.perf_counter() - began
    times = np.linspace(0.0, 1.0, OUTPUT_POINTS)
    names = [*compiled.state_names, *compiled.algebraic_names]

    def values(sol):
        return np.stack([np.asarray(sol[name], dtype=float) for name in names])

    reference = values(dm.solve(compiled, (0.0, 1.0), method="casadi-idas", rtol=1e-10, atol=1e-12, t_eval=times))
    cells = {name: {"solve_s": []} for name in methods}
    for p in range(passes):
        for name, options in methods.items():
            stencil.stencil_equations = (lambda *args: (None, "off")) if name.endswith("nostencil") else equations
            sol = dm.solve(compiled, (0.0, 1.0), t_eval=times, **options)
            cells[name]["solve_s"].append(sol.solve_time)
            if p == 0:
                cells[name]["setup_s"] = sol.setup_time
                cells[name]["error"] = float(np.abs(values(sol) - reference).max())
                stats = ("steps", "newton_iterations", "lu_decompositions", "band_lu", "stencil")
                cells[name]["stats"] = {k: sol.stats[k] for k in stats if k in sol.stats}
            print(unknowns, p, name, f"{sol.solve_time:.4f}", file=sys.stderr, flush=True)
    stencil.stencil_equations = equations
    for cell in cells.values():
        cell["min_solve_s"] = min(cell["solve_s"])
        cell["median_solve_s"] = float(np.median(cell["solve_s"]))
    (e0, s0), (e1, s1) = ((cells[k]["error"], cells[k]["min_solve_s"]) for k in ("idas-1e-7", "idas-1e-8"))
    error = cells["radau"]["error"]
    x = float(np.log(error / e0) / np.log(e1 / e0))  # (0 at rtol 1e-7's error, 1 at 1e-8's; outside: extrapolated)
    idas = float(np.exp((1 - x) * np.log(s0) + x * np.log(s1)))
    ratio = cells["radau"]["min_solve_s"] / idas
    out = {"declare_and_compile_s": built, "cells": cells, "idas_at_radau_error_s": idas, "ratio": ratio, "x": x}
    if before:
        out["ratio_nostencil"] = cells["radau-nostencil"]["min_solve_s"] / idas
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--unknowns", type=int, nargs="+", default=[10_000, 100_000])
    parser.add_argument("--passes", type=int, default=6)
    parser.add_argument("--before", action="store_true", help="a cell of radau without the stencil's C too")
    parser.add_argument("--out", type=Path, default=HERE / "interleaved_large")
    parser.add_argument("--cpu", action="store_true", help="the clocks in CPU seconds of this process")
    args = parser.parse_args()
    if args.cpu:
        time.perf_counter = time.process_time  # (the backends' clocks: CPU seconds of this one-thread process)
    import torch

    torch.set_num_threads(1)
    results = {str(u): measure(u, args.passes, args.before) for u in args.unknowns}
    command = "python benchmarks/interleaved_large.py " + " ".join(sys.argv[1:])
    record = {"command": command, "load": os.getloadavg(), "threads": 1, "results": results}
    args.out.with_suffix(".json").write_text(json.dumps(record, indent=1))
    print("| unknowns | radau error | radau solve (min) | IDAS solve at it | ratio |\n|---:|---:|---:|---:|---:|")
    for u, r in results.items():
        c = r["cells"]["radau"]
        idas = r["idas_at_radau_error_s"]
        print(f"| {u} | {c['error']:.2g} | {c['min_solve_s']:.3g} | {idas:.3g} | {r['ratio']:.2f}x |")
        if "ratio_nostencil" in r:
            c = r["cells"]["radau-nostencil"]
            print(f"| {u} (no stencil) | {c['error']:.2g} | {c['min_solve_s']:.3g} | {idas:.3g} | "
                  f"{r['ratio_nostencil']:.2f}x |")  # fmt: skip


if __name__ == "__main__":
    main()

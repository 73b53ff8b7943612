"""Issue 44: radau's solve's own memory against its factors' bytes, on reaction-diffusion (one fresh process a cell).

Run as ``python benchmarks/solve_memory.py [--unknowns 10000 100000] [--out PATH]``.  Each cell is a fresh
process that declares and compiles ``scaling_models.DECLARATIONS["stencils"](unknowns // 2)`` and then
solves it once with radau at its defaults over [0, 1] with 11 output times (``t_eval``), with and without
``dense_output``; that first solve is measured two ways:

* ``traced``: tracemalloc's peak during ``dm.solve`` over what was traced before it (numpy's allocations
  and Python's, not casadi's or the C kernels' own: theirs are the compiled libraries, made in the
  compile or loaded);
* ``rss``: the process's resident set, sampled every millisecond by a thread, its peak during the solve
  over its value before (pages written, not pages merely reserved), read after the C heap's free pages are
  handed back (glibc's ``malloc_trim``, where there is one): without that the declaration's and compile's
  freed heap (~275 MB at 10^5 unknowns, the compile's numpy code) stayed resident and the solve reused it
  unseen, so the growth read 1.5-2x the factors where the solve's own pages were ~9x;
* ``again_rss``: the same for a second solve of the same compiled model (what each later solve needs, the
  model's one-off pieces made).  The factors' buffers are among those pieces (the band kernel keeps one
  factorisation's for the next solve), so a later solve's memory is its growth plus the factors' bytes:
  ``again_total_ratio`` = (growth - outputs + factors) / factors;
* ``cold_rss``: a third solve after the buffers solves hand on to the next are dropped (:func:`drop_reused_buffers`:
  the factors', the casadi functions' bound inputs and outputs, the band kernel's solvers): every array a solve
  works in is made and counted in it, the model's compiled functions, layouts and patterns not;
  ``cold_ratio`` = (its growth - outputs) / factors;
* ``cold_traced``: a fourth, cold too, under tracemalloc: the peak of the arrays it holds at once (numpy's and
  Python's), without the C heap's free pages that the resident set keeps (glibc raises its mmap threshold to the
  largest block freed, ~32 MB after a compile, and keeps freed blocks below it); ``cold_traced_ratio`` likewise.

Beside them: ``stats["factor_bytes"]`` (what one factorisation's buffers hold: the band kernel's real and
two complex systems at s = 5) and ``output_bytes``, what the returned Solution holds that the user asked
for: the values at ``t_eval`` and, with ``dense_output``, each step's collocation nodes.  ``ratio``:
(traced peak - output bytes) / factor bytes.  The first solve counts what a model makes once (its
Jacobian's pattern, the band kernel, the engines' bound buffers, the factors' reserved buffers).
``DAEMODEL_TREE=/path/to/a/tree`` runs another tree of the package (a ``git archive`` of an earlier commit)
through the editable install's finder.  Writes ``<out>.json`` with the command and the load.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
OUTPUT_POINTS = 11


def rss_bytes() -> int:
    """The process's resident set (bytes), from /proc/self/statm."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def drop_reused_buffers(model) -> None:
    """Drop what radau's solves of the compiled ``model`` hand on to the next (for ``cold_rss``): the casadi
    functions' bound buffers lent from one engine to the next (``compiled._LENDABLE``) and its band kernel's
    spare factor buffers and its threads' solvers; its compiled functions, layouts and patterns stay."""
    import gc

    from daemodel.backends.radau import compiled

    gc.collect()  # (an engine or factors in a cycle give their buffers back when collected: before they are dropped)
    compiled._LENDABLE.clear()
    kernel = model._cache.get("radau-band-kernel")  # (.band.band_factors: one a model)
    if kernel is not None:
        kernel._spare = {False: [], True: []}
        kernel._buffers = threading.local()


def cell(unknowns: int, dense_output: bool, traced: bool = True, method: str = "radau") -> dict:
    """One fresh process's measurement (see the module docstring)."""
    import tracemalloc

    tree = os.environ.get("DAEMODEL_TREE")
    if tree:  # (another tree through the editable install's finder)
        import __editable___daemodel_0_1_0_finder as finder

        finder.MAPPING.update(daemodel=f"{tree}/daemodel", **{"daemodel.backends": f"{tree}/backends"})
    sys.path.insert(0, str(HERE))
    import numpy as np
    import scaling_models
    import torch

    import daemodel as dm

    torch.set_num_threads(1)
    compiled = scaling_models.DECLARATIONS["stencils"](unknowns // 2).compile()
    times = np.linspace(0.0, 1.0, OUTPUT_POINTS)
    samples, running = [], [True]

    def sample():
        while running[0]:
            samples.append(rss_bytes())
            time.sleep(0.001)

    import gc

    def settle() -> int:
        """The resident set after a collection and the C heap's free pages handed back (see the docstring)."""
        gc.collect()
        with contextlib.suppress(AttributeError, OSError, TypeError):
            ctypes.CDLL(None).malloc_trim(0)
        return rss_bytes()

    before_rss = settle()
    if traced:
        tracemalloc.start()
    before = tracemalloc.get_traced_memory()[0]
    watcher = threading.Thread(target=sample, daemon=True)
    watcher.start()
    options = {"dense_output": dense_output} if method == "radau" else {}  # (casadi-idas has no dense output)
    sol = dm.solve(compiled, (0.0, 1.0), method=method, t_eval=times, **options)
    running[0] = False
    watcher.join()
    peak = tracemalloc.get_traced_memory()[1] - before if traced else None
    rss_peak = max([*samples, rss_bytes()]) - before_rss
    tracemalloc.stop()
    first = {"steps": sol.stats.get("steps"), "solve_s": sol.solve_time, "status": sol.status}
    del sol

    def watched() -> tuple:
        """A solve under the sampler: ``(Solution, its resident peak over the settled set before it)``."""
        samples[:] = []
        before, running[0] = settle(), True
        watcher = threading.Thread(target=sample, daemon=True)
        watcher.start()
        solved = dm.solve(compiled, (0.0, 1.0), method=method, t_eval=times, **options)
        running[0] = False
        watcher.join()
        return solved, max([*samples, rss_bytes()]) - before

    sol, again_peak = watched()
    del sol
    drop_reused_buffers(compiled)
    sol, cold_peak = watched()
    names = [*compiled.state_names, *compiled.algebraic_names]
    output = sum(np.asarray(sol[name]).nbytes for name in names)
    if sol.dense is not None and hasattr(sol.dense, "nodes"):
        output += sol.dense.nodes.nbytes
    factors, again_solve_s = sol.stats.get("factor_bytes"), sol.solve_time
    del sol
    # (a fourth, cold again, under tracemalloc: the arrays it holds at once, without the C heap's free pages)
    drop_reused_buffers(compiled)
    tracemalloc.start()
    before = tracemalloc.get_traced_memory()[0]
    dm.solve(compiled, (0.0, 1.0), method=method, t_eval=times, **options)
    cold_traced = tracemalloc.get_traced_memory()[1] - before
    tracemalloc.stop()
    return {
        "unknowns": unknowns,
        "dense_output": dense_output,
        "traced_peak_bytes": peak,
        "rss_peak_bytes": rss_peak,
        "factor_bytes": factors,
        "output_bytes": output,
        "ratio": None if not (factors and traced) else (peak - output) / factors,
        "rss_ratio": None if not factors else (rss_peak - output) / factors,
        "again_rss_peak_bytes": again_peak,
        "again_rss_ratio": None if not factors else (again_peak - output) / factors,
        "again_total_ratio": None if not factors else (again_peak - output + factors) / factors,
        "cold_rss_peak_bytes": cold_peak,
        "cold_ratio": None if not factors else (cold_peak - output) / factors,
        "cold_traced_peak_bytes": cold_traced,
        "cold_traced_ratio": None if not factors else (cold_traced - output) / factors,
        "method": method,
        **first,  # (the first solve's steps, solve time and status; the second's time beside them)
        "again_solve_s": again_solve_s,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--unknowns", type=int, nargs="+", default=[10_000, 100_000])
    parser.add_argument("--out", type=Path, default=HERE / "solve_memory")
    parser.add_argument("--dense", choices=("both", "on", "off"), default="both", help="dense_output's cells")
    parser.add_argument(
        "--rss-only", action="store_true", help="no tracemalloc (its cost on every allocation: minutes at 10^5)"
    )
    parser.add_argument("--method", default="radau", help="the method solved (casadi-idas: its growth, no factors)")
    parser.add_argument("--cell", nargs=4, help=argparse.SUPPRESS)  # (unknowns, dense_output, traced, method)
    args = parser.parse_args()
    if args.cell:
        print(json.dumps(cell(int(args.cell[0]), args.cell[1] == "1", args.cell[2] == "1", args.cell[3])))
        return
    env = dict(os.environ, OMP_NUM_THREADS="1")
    cells = []
    for unknowns in args.unknowns:
        for dense in {"both": (True, False), "on": (True,), "off": (False,)}[args.dense]:
            traced = "0" if args.rss_only else "1"
            command = [sys.executable, __file__, "--cell", str(unknowns), "1" if dense else "0", traced, args.method]
            out = subprocess.run(command, env=env, capture_output=True, text=True, check=True).stdout
            cells.append(json.loads(out.strip().splitlines()[-1]))
            c = cells[-1]
            print(
                f"{unknowns} dense_output={dense}: traced {(c['traced_peak_bytes'] or 0) / 1e6:.1f} MB, rss "
                f"{c['rss_peak_bytes'] / 1e6:.1f} MB, factors {(c['factor_bytes'] or 0) / 1e6:.2f} MB, outputs "
                f"{c['output_bytes'] / 1e6:.1f} MB, ratio {c['ratio'] or float('nan'):.2f}, rss ratio "
                f"{c['rss_ratio'] or float('nan'):.2f}; a second solve: rss {c['again_rss_peak_bytes'] / 1e6:.1f} MB, "
                f"ratio {c['again_rss_ratio'] or float('nan'):.2f}, with the factors "
                f"{c['again_total_ratio'] or float('nan'):.2f}; cold: rss {c['cold_rss_peak_bytes'] / 1e6:.1f} MB, "
                f"ratio {c['cold_ratio'] or float('nan'):.2f}; its arrays (traced): "
                f"{(c.get('cold_traced_peak_bytes') or 0) / 1e6:.1f} MB, "
                f"ratio {c.get('cold_traced_ratio') or float('nan'):.2f}",
                flush=True,
            )
    command = "python benchmarks/solve_memory.py " + " ".join(sys.argv[1:])
    record = {"command": command, "tree": os.environ.get("DAEMODEL_TREE"), "load": os.getloadavg(), "cells": cells}
    target = args.out.with_suffix(".json")
    partial = target.with_name(f".{target.name}.partial")
    partial.write_text(json.dumps(record, indent=1))
    os.replace(partial, target)  # (atomic: a run cut short leaves the last file whole)


if __name__ == "__main__":
    main()

"""radau's memory guard (issue 44, item 4): what counting the LU fill costs, before and after the bound.

Run as ``OMP_NUM_THREADS=1 python benchmarks/fill_guard.py [--unknowns 10000 100000] [--passes 5] [--out PATH]``.

* Models that fit: reaction-diffusion (``scaling_models.reaction_diffusion_arrays``, tridiagonal, 2K unknowns)
  at each size: the guard's count before (``sparse.factor_entries``: one SuperLU factorisation of the pattern)
  and after (``fill.measured_fill``: the bound from the pattern, then the same factorisation), interleaved
  pass by pass, the minimum kept; the bound's own time, and both counts (equal).
* Patterns of 10^5 unknowns that do not all fit (``DAEMODEL_MEMORY_LIMIT`` as set, 2 x 10^8 entries allowed):
  random (four entries a row), an arrow (a dense row and column) and a chain with one dense row: the outcome
  (the count, or the refusal and its reason), its seconds and the process's peak memory.  The full trial of
  the random pattern is never run (it would need ~17 GB).

Writes ``<out>.json`` (every number, the command, the machine, the load).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))


def patterns(D: int) -> dict:
    """``name: (rows, cols, n)``: the 10^5 patterns of the module docstring."""
    rng, i = np.random.default_rng(0), np.arange(D)
    return {
        "random": (np.r_[rng.integers(0, D, 4 * D), i], np.r_[rng.integers(0, D, 4 * D), i], D),
        "arrow": (np.r_[i, np.zeros(D, int), i], np.r_[i, i, np.zeros(D, int)], D),
        "dense row": (np.r_[i, i[1:], i[:-1], np.full(D, D - 1)], np.r_[i, i[:-1], i[1:], i], D - 1),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--unknowns", type=int, nargs="+", default=[10_000, 100_000])
    parser.add_argument("--passes", type=int, default=5)
    parser.add_argument("--out", type=Path, default=HERE / "fill_guard")
    args = parser.parse_args()
    import scaling_models
    import torch
    from daemodel.backends.radau import fill
    from daemodel.backends.radau import sparse as radau_sparse

    torch.set_num_threads(1)
    fits = {}
    for D in args.unknowns:
        compiled = scaling_models.reaction_diffusion_arrays(D // 2).compile()
        rows, cols = radau_sparse.jacobian_pattern(compiled)
        n = len(compiled.states)
        before, after, bound_s = [], [], []
        for _ in range(args.passes):
            began = time.perf_counter()
            old = radau_sparse.factor_entries(rows, cols, n, D)
            before.append(time.perf_counter() - began)
            began = time.perf_counter()
            new = fill.measured_fill(rows, cols, n, D, 1e12)
            after.append(time.perf_counter() - began)
            began = time.perf_counter()
            bound = fill.fill_bound(radau_sparse.pattern_matrix(rows, cols, n, D))
            bound_s.append(time.perf_counter() - began)
        fits[str(D)] = {"fill_before": old, "fill_after": new, "bound": bound, "before_s": min(before)}
        fits[str(D)] |= {"after_s": min(after), "bound_s": min(bound_s)}
        print("reaction_diffusion", D, fits[str(D)], file=sys.stderr, flush=True)
    over = {}
    for name, (rows, cols, n) in patterns(100_000).items():
        began = time.perf_counter()
        try:
            outcome = {"fill": fill.measured_fill(rows, cols, n, 100_000, 2e8)}
        except fill.FillOverLimit as refused:
            outcome = {"refused": refused.reason, "entries": refused.entries}
        outcome |= {"seconds": time.perf_counter() - began}
        outcome["peak_rss_MB"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        over[name] = outcome
        print(name, outcome, file=sys.stderr, flush=True)
    command = "OMP_NUM_THREADS=1 python benchmarks/fill_guard.py " + " ".join(sys.argv[1:])
    record = {"command": command, "memory_limit": os.environ.get("DAEMODEL_MEMORY_LIMIT")}
    record |= {"machine": os.uname().nodename}
    record |= {"load": os.getloadavg(), "reaction_diffusion": fits, "patterns_100000": over}
    args.out.with_suffix(".json").write_text(json.dumps(record, indent=1))


if __name__ == "__main__":
    main()

"""Issue 42: the algebraic variables solved again at the outputs (adaptive radau, index 2 or 3 reduced) by the
affine step (``daemodel.compiling.algebraic.AffineStep``: one casadi function mapped over the outputs) against the
batched numpy Newton that did it before (the same code with ``affine_step`` switched off), on the pendulums and
chains of ``benchmarks/radau_idas.py`` at rtol = atol = 1e-4, 1e-6, 1e-8, 21 output times.

Each pass solves every problem, tolerance and variant ``--solves`` times (the variants' order alternating from pass
to pass) and keeps, per variant, the fastest ``sol.solve_time``, the fastest thread CPU time of the whole
``dm.solve`` call, and the fastest time inside ``resolve_outputs`` (the solve at the outputs alone, thread CPU).
One thread (OMP_NUM_THREADS = 1, torch on one thread).  The same states and steps either way: the returned
algebraic variables agree to rounding (their largest difference relative to 1 + |z| is recorded).

Run: python benchmarks/affine_resolve.py [--passes 7] [--solves 5] [--out PATH] [--code-label TEXT]
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse
import contextlib
import datetime
import json
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import adaptive_precision  # noqa: E402
import radau_idas  # noqa: E402
import scaling  # noqa: E402

from daemodel.files import atomic_write  # noqa: E402

PROBLEMS = ("pendulum", "pendulum-index3", "pendulum_chain-20", "pendulum_chain-40")
TOLERANCES = (1e-4, 1e-6, 1e-8)
VARIANTS = ("numpy", "affine")


@contextlib.contextmanager
def variant(name: str):
    """``affine``: the code as it is; ``numpy``: the affine step switched off (the batched numpy Newton)."""
    from daemodel.compiling import algebraic

    original = algebraic.affine_step
    if name == "numpy":
        algebraic.affine_step = lambda compiled: None
    try:
        yield
    finally:
        algebraic.affine_step = original


@contextlib.contextmanager
def timed_resolve(record: list):
    """Thread CPU seconds of each call of radau's ``resolve_outputs`` appended to ``record``."""
    from daemodel.backends.radau import backend

    original = backend.resolve_outputs

    def resolve(*arguments):
        began = time.thread_time()
        try:
            return original(*arguments)
        finally:
            record.append(time.thread_time() - began)

    backend.resolve_outputs = resolve
    try:
        yield
    finally:
        backend.resolve_outputs = original


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--passes", type=int, default=7, help="interleaved passes (default %(default)s)")
    parser.add_argument("--solves", type=int, default=5, help="solves of each kind per pass (default %(default)s)")
    parser.add_argument("--out", default=str(HERE / "affine_resolve"), help="output path without suffix")
    parser.add_argument("--code-label", help="free text recorded with the machine")
    args = parser.parse_args(argv)
    import daemodel as dm

    adaptive_precision.one_thread()
    models = {key: radau_idas.build(key)[:2] for key in PROBLEMS}
    best: dict = {}
    started = time.monotonic()
    for p in range(args.passes):
        for key, (compiled, t_span) in models.items():
            grid = np.linspace(*t_span, radau_idas.OUTPUT_POINTS)
            for tol in TOLERANCES:
                z = {}
                for name in VARIANTS if p % 2 == 0 else VARIANTS[::-1]:
                    row = best.setdefault((key, tol, name), {"solve_s": np.inf, "cpu_s": np.inf, "resolve_s": np.inf})
                    with variant(name):
                        dm.solve(compiled, t_span, rtol=tol, atol=tol, t_eval=grid)  # (its caches, as in a sweep)
                        for _ in range(args.solves):
                            resolves: list = []
                            with timed_resolve(resolves):
                                began = time.thread_time()
                                sol = dm.solve(compiled, t_span, rtol=tol, atol=tol, t_eval=grid)
                                cpu = time.thread_time() - began
                            row["solve_s"] = min(row["solve_s"], sol.solve_time)
                            row["cpu_s"] = min(row["cpu_s"], cpu)
                            row["resolve_s"] = min(row["resolve_s"], sum(resolves))
                    row["steps"] = sol.stats.get("steps")
                    z[name] = np.stack([sol[v] for v in compiled.algebraic_names], axis=-1)
                difference = np.max(np.abs(z["affine"] - z["numpy"]) / (1 + np.abs(z["numpy"])))
                best[(key, tol, "affine")]["z_difference"] = float(difference)
        print(f"pass {p + 1} done after {time.monotonic() - started:.0f} s", file=sys.stderr, flush=True)

    rows = []
    print("| problem | rtol | steps | solve numpy / affine (ms) | ratio | dm.solve CPU (ms) | resolve CPU (ms) |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for key in PROBLEMS:
        for tol in TOLERANCES:
            before, after = best[(key, tol, "numpy")], best[(key, tol, "affine")]
            rows.append({"problem": key, "rtol": tol, "numpy": before, "affine": after})
            ms = {k: f"{1e3 * before[k]:.3f} / {1e3 * after[k]:.3f}" for k in ("solve_s", "cpu_s", "resolve_s")}
            ratio = after["solve_s"] / before["solve_s"]
            cells = [key, f"{tol:g}", after["steps"], ms["solve_s"], f"{ratio:.2f}", ms["cpu_s"], ms["resolve_s"]]
            print("| " + " | ".join(map(str, cells)) + " |")
    record = {
        "benchmark": "affine_resolve",
        "command": "python benchmarks/affine_resolve.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "machine": scaling.machine_info(args.code_label),
        "settings": {"passes": args.passes, "solves": args.solves, "tolerances": TOLERANCES, "outputs": 21},
        "rows": rows,
        "total_seconds": time.monotonic() - started,
    }
    out = Path(args.out).with_suffix(".json")
    atomic_write(out, lambda f: f.write(json.dumps(record, indent=1) + "\n"), text=True)
    print(f"wrote {out}", file=sys.stderr)


if __name__ == "__main__":
    main()

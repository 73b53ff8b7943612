"""Batched Radau IIA in torch against a loop of casadi collocation solves, same s and h.

1000 pendulums (the paper's index-2 pendulum) released at rest from angles in [0.1, 3.0] rad,
solved on [0, 1] with s = 3 stages and h = 0.05 by both methods: ``dm.solve(..., y0=batch)``
once, and casadi's Radau collocation integrator (built once) called once per state.  Both solve
the same stage equations, so "equal accuracy" is checked, not assumed: the script reports their
largest difference and, for a sample of states, each one's error against the tight reference.

torch runs on 1 thread (casadi's integrator is single-threaded); the wall time is the best of
``--repeats`` runs.  Writes benchmarks/batch_radau.json and benchmarks/batch_radau.png.

Run: python benchmarks/batch_radau.py [--quick]
"""

import argparse
import json
import platform
from pathlib import Path

import numpy as np
import torch

import daemodel as dm
from daemodel.problems import PENDULUM

HERE = Path(__file__).resolve().parent
STAGES, H, T1 = 3, 0.05, 1.0


def release(angles):
    zeros = np.zeros_like(angles)
    return {"y1": np.sin(angles), "y2": -np.cos(angles), "y3": zeros, "y4": zeros}


def best_of(repeats, run):
    results = [run() for _ in range(repeats)]
    return min(r.wall_time for r in results), results[-1]


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="batches up to 100, one repeat")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    repeats = 1 if args.quick else args.repeats
    sizes = [1, 10, 100] if args.quick else [1, 10, 100, 1000]

    compiled = PENDULUM.model().compile()
    dm.solve(compiled, (0.0, T1), stages=STAGES, h=H)  # warm-up: code generation, first torch calls
    rows = []
    for size in sizes:
        y0 = release(np.linspace(0.1, 3.0, size))
        own_time, own = best_of(repeats, lambda y0=y0: dm.solve(compiled, (0.0, T1), stages=STAGES, h=H, y0=y0))
        col_time, col = best_of(
            1 if size >= 1000 else repeats,
            lambda y0=y0: dm.solve(compiled, (0.0, T1), method="casadi-collocation", stages=STAGES, h=H, y0=y0),
        )
        gap = max(float(np.max(np.abs(own[n] - col[n]))) for n in own.names)
        picks = np.unique(np.linspace(0, size - 1, min(size, 10)).round().astype(int))
        ref = dm.solve(compiled, (0.0, T1), method="reference", t_eval=own.t, y0={k: v[picks] for k, v in y0.items()})
        errors = {}
        for label, sol in (("radau", own), ("casadi-collocation", col)):
            diff = {n: float(np.max(np.abs(sol[n][picks] - ref[n]))) for n in own.names}
            errors[label] = {"y": max(diff[n] for n in compiled.state_names), "z": diff["y5"]}
        rows.append(
            {
                "batch": size,
                "radau_s": own_time,
                "casadi_loop_s": col_time,
                "speedup": col_time / own_time,
                "max_difference": gap,
                "errors_vs_reference": errors,
                "radau_newton_iterations": own.stats["newton_iterations"],
            }
        )
        print(
            f"batch {size:>5}: radau {own_time:8.4f} s   casadi loop {col_time:8.4f} s   "
            f"speed-up {col_time / own_time:6.1f}x   max |radau - casadi| {gap:.1e}   "
            f"error y {errors['radau']['y']:.1e} / {errors['casadi-collocation']['y']:.1e}, "
            f"z {errors['radau']['z']:.1e} / {errors['casadi-collocation']['z']:.1e}"
        )

    result = {
        "problem": "pendulum (index 2), released at rest from angles in [0.1, 3.0]",
        "interval": [0.0, T1],
        "stages": STAGES,
        "h": H,
        "torch_threads": torch.get_num_threads(),
        "dtype": "float64",
        "machine": f"{platform.processor() or platform.machine()}, {platform.system()}",
        "torch": torch.__version__,
        "repeats": repeats,
        "rows": rows,
    }
    suffix = "_quick" if args.quick else ""
    (HERE / f"batch_radau{suffix}.json").write_text(json.dumps(result, indent=2) + "\n")
    plot(rows, HERE / f"batch_radau{suffix}.png")
    print(f"wrote benchmarks/batch_radau{suffix}.json and .png")


def plot(rows, path) -> None:
    from matplotlib.figure import Figure

    sizes = [r["batch"] for r in rows]
    fig = Figure(figsize=(6.4, 4.2), layout="constrained")
    ax = fig.subplots()
    ax.loglog(sizes, [r["radau_s"] for r in rows], "o-", label="daemodel radau, one batched call (torch, 1 thread)")
    ax.loglog(sizes, [r["casadi_loop_s"] for r in rows], "s-", label="casadi collocation, one call per state")
    for r in rows:
        ax.annotate(f"{r['speedup']:.1f}x", (r["batch"], r["radau_s"]), textcoords="offset points", xytext=(4, -14))
    ax.set_xlabel("number of initial states")
    ax.set_ylabel("wall time [s]")
    ax.set_title(f"Pendulum on [0, {T1:g}], Radau IIA s = {STAGES}, h = {H}: same equations, same accuracy")
    ax.title.set_fontsize(9)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    fig.savefig(path, dpi=130)


if __name__ == "__main__":
    main()

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
    return min(r.solve_time for r in results), results[-1]


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="batches up to 100, one repeat")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument(
        "--map-sizes", type=int, nargs="*", default=[1000, 10000], help="batches also timed on casadi's map"
    )
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    repeats = 1 if args.quick else args.repeats
    sizes = [1, 10, 100] if args.quick else [1, 10, 100, 1000, 10000]

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
        mapped = casadi_map_time(compiled, y0) if size in args.map_sizes and not args.quick else None
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
                "radau_engine": own.stats["engine"],
                "casadi_map_s": None if mapped is None else mapped[0],
                "casadi_map_max_difference": (
                    None if mapped is None else float(np.max(np.abs(mapped[1] - own_end(own))))
                ),
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


# casadi's own batching: the collocation integrator (same s, h, no step check) mapped over the
# batch with this many threads (the machine's cores); integration only, the map is built first.
MAP_THREADS = 2


def own_end(sol) -> np.ndarray:
    """The states at t1 of a batched Solution, (B, n)."""
    return np.stack([np.atleast_2d(sol[n])[:, -1] for n in sol.compiled.state_names], axis=1)


def casadi_map_time(compiled, y0) -> tuple[float, np.ndarray]:
    """Seconds for casadi's collocation integrator mapped over the batch on MAP_THREADS threads, and
    its states at t1 (B, n)."""
    import time

    import casadi

    from daemodel.compiling.initial_states import initial_states

    start = initial_states(compiled, y0=y0)
    dae = compiled.casadi_dae()
    steps = round(T1 / H)
    grid = [H * k for k in range(1, steps + 1)]
    options = {"collocation_scheme": "radau", "interpolation_order": STAGES, "number_of_finite_elements": 1}
    integrator = casadi.integrator("collocation", "collocation", dae, 0.0, grid, options)
    size = start.size
    mapped = integrator.map(size, "thread", MAP_THREADS)
    began = time.perf_counter()
    out = mapped(x0=start.y0.T, z0=start.z0.T, p=start.p.T)
    seconds = time.perf_counter() - began
    xf = np.asarray(out["xf"])  # (n, steps * B): each sample's grid columns in turn
    return seconds, xf.reshape(xf.shape[0], size, steps)[:, :, -1].T


def plot(rows, path) -> None:
    from matplotlib.figure import Figure

    sizes = [r["batch"] for r in rows]
    fig = Figure(figsize=(6.4, 4.2), layout="constrained")
    ax = fig.subplots()
    ax.loglog(sizes, [r["radau_s"] for r in rows], "o-", label="daemodel radau, one batched call (torch, 1 thread)")
    ax.loglog(sizes, [r["casadi_loop_s"] for r in rows], "s-", label="casadi collocation, one call per state")
    mapped = [(r["batch"], r["casadi_map_s"]) for r in rows if r.get("casadi_map_s")]
    if mapped:
        label = f"casadi collocation integrator, map on {MAP_THREADS} threads"
        ax.loglog(*zip(*mapped, strict=True), "^--", label=label)
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

"""Surrogate answers with a certificate: the network-only answer, its error estimate, and Newton
from the networks (``Surrogate.solve(estimate=True)`` and ``newton=True``) against batched radau.

For each paper problem: a surrogate trained on ``--samples`` states drawn from a +-1 % box over
[0, ``--t-end``]; then ``--queries`` new states drawn from the same box.  Reported: the held-out
errors of the network-only answers against radau's collocation solution at the same s and h (max,
median, 99th percentile), how often the error estimate bounds the error (y and z, every grid
time), the Newton iterations from the networks' guesses and from radau's own, and the time of
each path (min of ``--repeats`` runs, one torch thread).

    python benchmarks/surrogate_certified.py --out benchmarks/surrogate_certified.json

Besides the JSON, a PNG beside it: per problem, the histogram of the held-out errors and their
estimates, and each answer's error against its estimate (the calibration: points below the
diagonal are bounded).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

import daemodel as dm
from daemodel.problems import HESSENBERG, PENDULUM

BOXES = {"pendulum": (PENDULUM, ("y1", "y4")), "hessenberg": (HESSENBERG, ("y1", "y2"))}


def timed(repeats: int, call):
    """``(min seconds, last result)`` of ``repeats`` calls."""
    best, result = np.inf, None
    for _ in range(repeats):
        began = time.perf_counter()
        result = call()
        best = min(best, time.perf_counter() - began)
    return best, result


def run(name: str, t_end: float, samples: int, queries: int, repeats: int) -> dict:
    problem, boxed = BOXES[name]
    compiled = problem.model().compile()
    box = {
        state: (0.99 * compiled.y0[i], 1.01 * compiled.y0[i])
        for i, state in enumerate(compiled.state_names)
        if state in boxed
    }
    began = time.perf_counter()
    surrogate = dm.Surrogate.train(compiled, (0.0, t_end), box=box, samples=samples, progress=False)
    training = time.perf_counter() - began
    rng = np.random.default_rng(2024)
    y = {state: np.full(queries, compiled.y0[i]) for i, state in enumerate(compiled.state_names)}
    for state, (low, high) in box.items():
        y[state] = rng.uniform(low, high, queries)
    y0 = compiled.consistent(y0=y)
    config = surrogate.config
    t_network, network = timed(repeats, lambda: surrogate.solve(y0=y0, outside="ignore"))
    t_estimate, estimated = timed(repeats, lambda: surrogate.solve(y0=y0, outside="ignore", estimate=True))
    t_hybrid, hybrid = timed(repeats, lambda: surrogate.solve(y0=y0, outside="ignore", newton=True))
    t_radau, radau = timed(repeats, lambda: dm.solve(compiled, (0.0, t_end), h=config.h, stages=config.stages, y0=y0))
    states, algebraics = compiled.state_names, compiled.algebraic_names
    error_y = np.max([np.abs(network[k] - radau[k]) for k in states], axis=0)[:, 1:]
    error_z = np.max([np.abs(network[k] - radau[k]) for k in algebraics], axis=0)[:, 1:]
    worst = np.maximum(error_y.max(axis=1), error_z.max(axis=1))
    estimate = estimated.stats["error_estimate"]
    bound_y = float(np.mean(error_y <= estimate["y"][:, 1:]))
    bound_z = float(np.mean(error_z <= estimate["z"][:, 1:]))
    agreement = max(float(np.abs(hybrid[k] - radau[k]).max()) for k in (*states, *algebraics))
    out = {
        "problem": name,
        "t_span": [0.0, t_end],
        "h": config.h,
        "stages": config.stages,
        "training_states": samples,
        "queries": queries,
        "training_seconds": training,
        "error": {"max": float(worst.max()), "median": float(np.median(worst)), "p99": float(np.percentile(worst, 99))},
        "estimate_bounds_error": {"y": bound_y, "z": bound_z},
        "estimate_over_error_median": {
            "y": float(np.median(estimate["y"][:, 1:] / np.maximum(error_y, 1e-300))),
            "z": float(np.median(estimate["z"][:, 1:] / np.maximum(error_z, 1e-300))),
        },
        "newton_iterations": {
            "from_networks": hybrid.stats["newton_iterations"],
            "radau": radau.stats["newton_iterations"],
        },
        "hybrid_vs_radau": agreement,
        "seconds": {
            "networks": t_network,
            "networks_and_estimate": t_estimate,
            "networks_and_newton": t_hybrid,
            "radau": t_radau,
        },
        "torch_threads": torch.get_num_threads(),
    }
    print(json.dumps(out, indent=1), flush=True)
    # per sample, worst over the grid: for the figure
    out["_samples"] = {
        "error_y": error_y.max(axis=1),
        "estimate_y": estimate["y"][:, 1:].max(axis=1),
        "error_z": error_z.max(axis=1),
        "estimate_z": estimate["z"][:, 1:].max(axis=1),
    }
    return out


def plot(runs: list, path: Path) -> None:
    """Histograms of the errors and estimates, and error against estimate, one row per problem."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(11, 3.6 * len(runs)), layout="constrained")
    axes = fig.subplots(len(runs), 2, squeeze=False)
    for (hist, calibration), run in zip(axes, runs, strict=True):
        samples = run["_samples"]
        for i, group in enumerate(("y", "z")):
            error, estimate = samples[f"error_{group}"], samples[f"estimate_{group}"]
            low = np.log10(max(min(error.min(), estimate.min()), 1e-17))
            high = np.log10(max(error.max(), estimate.max()))
            bins = np.logspace(low - 0.1, high + 0.1, 50)
            hist.hist(error, bins=bins, alpha=0.6, color=f"C{2 * i}", label=f"{group} error")
            hist.hist(estimate, bins=bins, alpha=0.4, color=f"C{2 * i + 1}", label=f"{group} estimate")
            rate = run["estimate_bounds_error"][group]
            label = f"{group}: estimate >= error at {rate:.2%} of state-times"
            calibration.loglog(estimate, error, ".", ms=2, alpha=0.4, color=f"C{2 * i}", label=label)
        hist.set_xscale("log")
        hist.set_xlabel("max absolute error over the grid, per held-out state")
        hist.set_ylabel("states")
        hist.set_title(f"{run['problem']}: {run['queries']:,} held-out states, {run['training_states']} trained")
        hist.legend(fontsize=8)
        lims = calibration.get_xlim()
        calibration.plot(lims, lims, "k--", lw=1, label="error = estimate")
        calibration.set_xlabel("error estimate (estimate=True)")
        calibration.set_ylabel("error against radau's collocation solution")
        calibration.set_title(f"{run['problem']}: each state's worst error and estimate")
        calibration.legend(fontsize=8, markerscale=4)
    fig.savefig(path, dpi=120)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--t-end", type=float, default=0.25)
    parser.add_argument("--samples", type=int, default=16, help="training states")
    parser.add_argument("--queries", type=int, default=10_000, help="held-out states")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--out", default="benchmarks/surrogate_certified.json")
    args = parser.parse_args()
    torch.set_num_threads(1)
    runs = [run(name, args.t_end, args.samples, args.queries, args.repeats) for name in BOXES]
    out = Path(args.out)
    plot(runs, out.with_suffix(".png"))
    public = [{k: v for k, v in r.items() if not k.startswith("_")} for r in runs]
    out.write_text(json.dumps({"runs": public}, indent=2) + "\n")
    print(f"wrote {out} and {out.with_suffix('.png')}")


if __name__ == "__main__":
    main()

"""Surrogates over boxes of initial states and parameters: held-out accuracy, the error
estimate's calibration, and speed against batched radau from 10^3 to 10^5 queries.

Three cases: each paper problem with its initial state in a +-1 % box, and the pendulum with
its mass m and length-constraint parameter lam in +-5 % as network inputs besides the states.
Each surrogate is trained on ``--samples`` points of its box over [0, ``--t-end``]; queries are
drawn like the training points (uniform in the box), plus ``--margin-queries`` drawn in the
margin just outside it (up to 25 % of the box's width beyond each face).  Errors are against
radau's collocation solution at the same s and h: the answer a perfectly trained surrogate gives.

Paths timed (min of ``--repeats``, one torch thread), at each of ``--queries``:

* ``networks``: the networks alone;
* ``estimate``: the networks and each answer's error estimate (``estimate=True``);
* ``hybrid``: ``tol=--tol``: every answer certified (its distance from the collocation solution,
  one full Newton check per segment), Newton from the networks for the samples whose certified
  distance exceeds tol;
* ``newton``: Newton from the networks for every sample (``newton=True``);
* ``radau``: batched radau from its own start guesses.

    python benchmarks/surrogate.py --out benchmarks/surrogate.json

Besides the JSON, a PNG beside it: per case, the histogram of the held-out errors and their
estimates, each answer's error against its estimate (points below the diagonal are bounded), and
time against the number of queries.
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

# case -> (problem, states boxed at +-1 %, parameters boxed at +-5 %, training points)
CASES = {
    "pendulum": (PENDULUM, ("y1", "y4"), (), 16),
    "hessenberg": (HESSENBERG, ("y1", "y2"), (), 16),
    "pendulum-m-lam": (PENDULUM, ("y1", "y4"), ("m", "lam"), 64),
}
MARGIN = 0.25  # the margin outside the box that margin queries are drawn from, in box widths


def timed(repeats: int, call):
    """``(min seconds, last result)`` of ``repeats`` calls."""
    best, result = np.inf, None
    for _ in range(repeats):
        began = time.perf_counter()
        result = call()
        best = min(best, time.perf_counter() - began)
    return best, result


def draw(compiled, box: dict, count: int, rng, margin: bool = False):
    """``count`` consistent initial states and parameter vectors uniform in ``box`` (or, with
    ``margin``, in the band of MARGIN widths just outside it)."""
    values = {name: np.full(count, compiled.y0[i]) for i, name in enumerate(compiled.state_names)}
    values |= {name: np.full(count, compiled.parameter_values[i]) for i, name in enumerate(compiled.parameter_names)}
    if not margin:
        for name, (low, high) in box.items():
            values[name] = rng.uniform(low, high, count)
    else:  # each point leaves the box through one face chosen at random, the others stay inside
        names = list(box)
        leaving = rng.integers(len(names), size=count)
        for j, name in enumerate(names):
            low, high = box[name]
            width = high - low
            inside = rng.uniform(low, high, count)
            beyond = rng.uniform(0, MARGIN * width, count)
            outside = np.where(rng.random(count) < 0.5, low - beyond, high + beyond)
            values[name] = np.where(leaving == j, outside, inside)
    y0 = compiled.consistent(
        y0={name: values[name] for name in compiled.state_names},
        parameters={name: values[name] for name in compiled.parameter_names},
    )
    return y0, {name: values[name] for name in compiled.parameter_names}


def accuracy(compiled, answer, radau, certified) -> dict:
    """Per held-out state: the worst error over the grid of y and z, their estimates, and the
    certified distance (``certified``: the same queries answered with ``tol=1e300``, certified and
    none corrected) against the worst error over every variable."""
    states, algebraics = compiled.state_names, compiled.algebraic_names
    error_y = np.max([np.abs(answer[k] - radau[k]) for k in states], axis=0)[:, 1:]
    error_z = np.max([np.abs(answer[k] - radau[k]) for k in algebraics], axis=0)[:, 1:]
    estimate = answer.stats["error_estimate"]
    worst = np.maximum(error_y.max(axis=1), error_z.max(axis=1))
    return {
        "error": {"max": float(worst.max()), "median": float(np.median(worst)), "p99": float(np.percentile(worst, 99))},
        "estimate_bounds_error": {
            "y": float(np.mean(error_y <= estimate["y"][:, 1:])),
            "z": float(np.mean(error_z <= estimate["z"][:, 1:])),
        },
        "estimate_over_error_median": {
            "y": float(np.median(estimate["y"][:, 1:] / np.maximum(error_y, 1e-300))),
            "z": float(np.median(estimate["z"][:, 1:] / np.maximum(error_z, 1e-300))),
        },
        "certificate_bounds_error": float(np.mean(worst <= certified.stats["certified_distance"])),
        "certificate_over_error_median": float(
            np.median(certified.stats["certified_distance"] / np.maximum(worst, 1e-300))
        ),
        "_samples": {
            "error_y": error_y.max(axis=1),
            "estimate_y": estimate["y"][:, 1:].max(axis=1),
            "error_z": error_z.max(axis=1),
            "estimate_z": estimate["z"][:, 1:].max(axis=1),
        },
    }


def run(
    case: str,
    t_end: float,
    queries: list,
    held_out_queries: int,
    margin_queries: int,
    repeats: int,
    tol: float,
    samples: int | None = None,
) -> dict:
    problem, boxed, varied, default_samples = CASES[case]
    samples = default_samples if samples is None else samples
    compiled = problem.model().compile()
    box = {name: (0.99 * compiled.y0[i], 1.01 * compiled.y0[i]) for i, name in enumerate(compiled.state_names)}
    box = {name: bounds for name, bounds in box.items() if name in boxed}
    parameter_box = {
        name: (0.95 * value, 1.05 * value)
        for name, value in zip(compiled.parameter_names, compiled.parameter_values, strict=True)
        if name in varied
    }
    began = time.perf_counter()
    surrogate = dm.Surrogate.train(
        compiled, (0.0, t_end), box=box, parameter_box=parameter_box or None, samples=samples, progress=False
    )
    training = time.perf_counter() - began
    config = surrogate.config
    rng = np.random.default_rng(2024)

    def radau(y0, parameters):
        return dm.solve(compiled, (0.0, t_end), h=config.h, stages=config.stages, y0=y0, parameters=parameters)

    held_out = draw(compiled, box | parameter_box, held_out_queries, rng)
    answer = surrogate.solve(y0=held_out[0], parameters=held_out[1], outside="ignore", estimate=True)
    certified = surrogate.solve(y0=held_out[0], parameters=held_out[1], outside="ignore", tol=1e300)
    inside = accuracy(compiled, answer, radau(*held_out), certified)
    margin = draw(compiled, box | parameter_box, margin_queries, rng, margin=True)
    answer = surrogate.solve(y0=margin[0], parameters=margin[1], outside="ignore", estimate=True)
    certified = surrogate.solve(y0=margin[0], parameters=margin[1], outside="ignore", tol=1e300)
    outside = accuracy(compiled, answer, radau(*margin), certified)
    speed = []
    for count in queries:
        y0, parameters = draw(compiled, box | parameter_box, count, rng)
        times, answers = {}, {}
        queried = {"y0": y0, "parameters": parameters, "outside": "ignore"}
        paths = {
            "networks": lambda q=queried: surrogate.solve(**q),
            "estimate": lambda q=queried: surrogate.solve(**q, estimate=True),
            "hybrid": lambda q=queried: surrogate.solve(**q, tol=tol),
            "newton": lambda q=queried: surrogate.solve(**q, newton=True),
            "radau": lambda q=queried: radau(q["y0"], q["parameters"]),
        }
        for path, call in paths.items():
            times[path], answers[path] = timed(repeats if count < 100_000 else max(1, repeats - 1), call)
        names = (*compiled.state_names, *compiled.algebraic_names)
        hybrid_error = max(float(np.abs(answers["hybrid"][k] - answers["radau"][k]).max()) for k in names)
        speed.append(
            {
                "queries": count,
                "seconds": times,
                "hybrid": {
                    "tol": tol,
                    "corrected": int(answers["hybrid"].stats["corrected"].sum()),
                    "max_error": hybrid_error,
                    "newton_iterations": answers["hybrid"].stats["newton_iterations"],
                },
                "newton_iterations": {
                    "from_networks": answers["newton"].stats["newton_iterations"],
                    "radau": answers["radau"].stats["newton_iterations"],
                },
            }
        )
        print(case, json.dumps(speed[-1]), flush=True)
    out = {
        "case": case,
        "problem": problem.name,
        "box": box,
        "parameter_box": parameter_box,
        "t_span": [0.0, t_end],
        "h": config.h,
        "stages": config.stages,
        "training_points": samples,
        "training_seconds": training,
        "held_out": {"queries": held_out_queries, **inside},
        "margin": {"queries": margin_queries, "widths_outside": MARGIN, **outside},
        "speed": speed,
        "torch_threads": torch.get_num_threads(),
    }
    shown = {k: v for k, v in out.items() if k != "speed"}
    print(json.dumps(shown, indent=1, default=lambda a: "..."), flush=True)
    return out


def plot(runs: list, path: Path) -> None:
    """Per case: histograms of errors and estimates, error against estimate, time against queries."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(16, 3.8 * len(runs)), layout="constrained")
    axes = fig.subplots(len(runs), 3, squeeze=False)
    for (hist, calibration, speed), run in zip(axes, runs, strict=True):
        held = run["held_out"]
        samples = held["_samples"]
        for i, group in enumerate(("y", "z")):
            error, estimate = samples[f"error_{group}"], samples[f"estimate_{group}"]
            low = np.log10(max(min(error.min(), estimate.min()), 1e-17))
            high = np.log10(max(error.max(), estimate.max()))
            bins = np.logspace(low - 0.1, high + 0.1, 50)
            hist.hist(error, bins=bins, alpha=0.6, color=f"C{2 * i}", label=f"{group} error")
            hist.hist(estimate, bins=bins, alpha=0.4, color=f"C{2 * i + 1}", label=f"{group} estimate")
            rate = held["estimate_bounds_error"][group]
            label = f"{group}: estimate >= error at {rate:.2%} of state-times"
            calibration.loglog(estimate, error, ".", ms=2, alpha=0.4, color=f"C{2 * i}", label=label)
        hist.set_xscale("log")
        hist.set_xlabel("max absolute error over the grid, per held-out query")
        hist.set_ylabel("queries")
        hist.set_title(f"{run['case']}: {held['queries']:,} held-out queries, {run['training_points']} trained")
        hist.legend(fontsize=8)
        lims = calibration.get_xlim()
        calibration.plot(lims, lims, "k--", lw=1, label="error = estimate")
        calibration.set_xlabel("error estimate (estimate=True)")
        calibration.set_ylabel("error against radau's collocation solution")
        calibration.set_title(f"{run['case']}: each query's worst error and estimate")
        calibration.legend(fontsize=8, markerscale=4)
        counts = [row["queries"] for row in run["speed"]]
        tol = run["speed"][0]["hybrid"]["tol"]
        for j, way in enumerate(("networks", "estimate", "hybrid", "newton", "radau")):
            label = f"hybrid, tol = {tol:g}" if way == "hybrid" else way
            style = "k-s" if way == "radau" else f"C{j}-o"
            speed.loglog(counts, [row["seconds"][way] for row in run["speed"]], style, ms=4, label=label)
        speed.set_xlabel("queries")
        speed.set_ylabel("seconds (one CPU thread)")
        speed.set_title(f"{run['case']}: time against batched radau")
        speed.grid(True, which="major", alpha=0.3)
        speed.legend(fontsize=8)
    fig.savefig(path, dpi=110)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--t-end", type=float, default=0.25)
    parser.add_argument("--queries", type=int, nargs="+", default=[1_000, 10_000, 100_000])
    parser.add_argument("--held-out", type=int, default=10_000, help="held-out queries for the accuracy")
    parser.add_argument("--margin-queries", type=int, default=2_000)
    parser.add_argument("--samples", type=int, help="training points for every case (default: per case, 16 or 64)")
    parser.add_argument("--repeats", type=int, default=3, help="timing repeats (one fewer at 10^5 queries)")
    parser.add_argument("--tol", type=float, default=1e-5, help="the hybrid's tolerance")
    parser.add_argument("--cases", default=",".join(CASES), help="comma-separated: " + ", ".join(CASES))
    parser.add_argument("--out", default="benchmarks/surrogate.json")
    args = parser.parse_args()
    torch.set_num_threads(1)
    cases = [case.strip() for case in args.cases.split(",")]
    runs = [
        run(case, args.t_end, args.queries, args.held_out, args.margin_queries, args.repeats, args.tol, args.samples)
        for case in cases
    ]
    out = Path(args.out)
    plot(runs, out.with_suffix(".png"))
    public = [
        {k: ({kk: vv for kk, vv in v.items() if kk != "_samples"} if isinstance(v, dict) else v) for k, v in r.items()}
        for r in runs
    ]
    out.write_text(json.dumps({"runs": public}, indent=2) + "\n")
    print(f"wrote {out} and {out.with_suffix('.png')}")


if __name__ == "__main__":
    main()

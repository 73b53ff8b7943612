"""Radau-PINN speed and accuracy against classical Radau IIA at the same s and h.

For both paper problems (Hessenberg index 2 with sigmoid, the index-2 pendulum with sin),
s = 3, h = 0.05 on [0, 1]:

* ``radau``: the classical Newton solve (the PINN's accuracy ceiling);
* ``pinn fast``: ``dm.PINNConfig(activation=...)``, Levenberg-Marquardt to tol = 1e-12, warm start;
* ``pinn from radau starts``: the same, every segment trained independently from the radau
  start values, one after another in this process (the local executor; Ray's parallel executor is
  timed in ``benchmarks/ensemble.py``);
* ``pinn paper``: ``dm.PINNConfig.paper(problem)`` (Adam, 5 x 100 networks, 100,000 iterations
  per segment), run for ``--paper-iterations`` iterations per segment; its time is
  extrapolated to 100,000 iterations and its error is the short run's (both labelled).

Errors are max absolute errors per variable against the exact solution (Hessenberg) or a
1e-12 reference (pendulum).  Then, for both problems, a surrogate: networks trained on 256
initial states from a box around the model's, evaluated on 10,000 new states from that box
against batched ``method="radau"`` (target: max error 1e-5, evaluation under 1 s).

torch runs on 1 thread (set deliberately: 2 threads fight with anything else on a 2-core
machine); wall times are the best of ``--repeats`` after a warm-up.  Writes
benchmarks/pinn_speed.json and .png (``_quick`` with --quick).

Run: python benchmarks/pinn_speed.py [--quick]
"""

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np
import torch

import daemodel as dm
from daemodel.problems import HESSENBERG, PENDULUM

HERE = Path(__file__).resolve().parent
STAGES, H, T_SPAN = 3, 0.05, (0.0, 1.0)
PAPER_ITERATIONS = 100_000
PROBLEMS = {"hessenberg": (HESSENBERG, "sigmoid"), "pendulum": (PENDULUM, "sin")}
# Surrogates: new states uniform within this half-width of the model's initial state (then
# projected on the constraint); training draws from a box TRAIN_MARGIN times wider, so that
# new states near the corners are inside the training set's hull.
SURROGATE_HALF_WIDTH, TRAIN_MARGIN = 0.01, 1.1
SURROGATE_ACTIVATION = {"hessenberg": "tanh", "pendulum": "sin"}
SURROGATE_TARGET = 1e-5


def best_of(repeats, run):
    """The least setup + solve time over ``repeats`` runs: for the PINN its training and evaluation,
    for radau its integration (its code, generated at the warm-up, is cached)."""
    results = [run() for _ in range(repeats)]
    return min(r.setup_time + r.solve_time for r in results), results[-1]


def max_errors(sol, reference) -> dict:
    return {name: float(e["max"]) for name, e in sol.errors(reference).items()}


def problem_rows(name, repeats, paper_iterations) -> dict:
    problem, activation = PROBLEMS[name]
    compiled = problem.model().compile()
    radau_run = lambda: dm.solve(compiled, T_SPAN, stages=STAGES, h=H)  # noqa: E731
    fast = dm.PINNConfig(activation=activation, stages=STAGES, h=H)
    radau_run()
    dm.solve(compiled, (0.0, H), method="pinn", config=fast)  # warm-up: code generation, torch.func
    radau_time, radau = best_of(repeats, radau_run)
    reference = problem.exact_solution() or dm.solve(compiled, T_SPAN, method="reference", t_eval=radau.t)
    rows = {"radau": {"seconds": radau_time, "errors": max_errors(radau, reference)}}

    fast_time, sol = best_of(repeats, lambda: dm.solve(compiled, T_SPAN, method="pinn", config=fast))
    rows["pinn fast"] = {
        "seconds": fast_time,
        "errors": max_errors(sol, reference),
        "lm_iterations": int(sum(sol.stats["iterations"])),
        "parameters_per_segment": sol.stats["parameters_per_segment"],
    }
    par_time, par = best_of(
        repeats, lambda: dm.solve(compiled, T_SPAN, method="pinn", config=fast, segment_starts=radau)
    )
    rows["pinn from radau starts (independent segments, local engine)"] = {
        "seconds": par_time,
        "errors": max_errors(par, reference),
        "note": "the radau solve for the starts is not counted",
    }
    paper = dm.PINNConfig.paper(name, iterations=paper_iterations)
    short = dm.solve(compiled, T_SPAN, method="pinn", config=paper)
    per_iteration = short.stats["training_seconds"] / (paper_iterations * short.stats["segments"])
    rows[f"pinn paper (time extrapolated, errors after {paper_iterations} its)"] = {
        "seconds": per_iteration * PAPER_ITERATIONS * short.stats["segments"],
        "errors": max_errors(short, reference),
        "note": (
            f"time: {paper_iterations} Adam iterations per segment measured "
            f"({short.stats['training_seconds']:.1f} s), scaled to {PAPER_ITERATIONS}; "
            f"errors: after the short run of {paper_iterations} iterations"
        ),
        "short_run_seconds": short.stats["training_seconds"],
        "final_L_f": short.stats["L_f"][-1],
    }
    ratio = {v: rows["pinn fast"]["errors"][v] / rows["radau"]["errors"][v] for v in rows["radau"]["errors"]}
    return {"activation": activation, "methods": rows, "fast_over_radau_error": ratio}


def surrogate_rows(name: str, quick: bool, repeats: int) -> dict:
    """Train a surrogate on a box of initial states around the model's, evaluate new states
    drawn from the same distribution (uniform in the box, projected on the constraints)."""
    from daemodel.compiling.initial_states import project_states
    from daemodel.solving.surrogates import SURROGATE_CONFIG

    compiled = PROBLEMS[name][0].model().compile()
    config = SURROGATE_CONFIG.replace(activation=SURROGATE_ACTIVATION[name])
    if quick:
        config = config.replace(iterations=10)
    samples = 64 if quick else 256
    center = np.asarray(compiled.y0, dtype=float)
    trained = SURROGATE_HALF_WIDTH * TRAIN_MARGIN
    box = {v: (c - trained, c + trained) for v, c in zip(compiled.state_names, center, strict=True)}
    began = time.perf_counter()
    surrogate = dm.Surrogate.train(compiled, T_SPAN, box=box, samples=samples, config=config)
    train_seconds = time.perf_counter() - began
    count = 1000 if quick else 10_000
    rng = np.random.default_rng(2026)
    p = np.tile(np.asarray(compiled.parameter_values, dtype=float), (count, 1))
    y0 = project_states(compiled, center + rng.uniform(-SURROGATE_HALF_WIDTH, SURROGATE_HALF_WIDTH, (count, 4)), p)
    surrogate.solve(y0=y0[:10])
    eval_seconds, sol = best_of(repeats, lambda: surrogate.solve(y0=y0))
    radau_seconds, radau = best_of(repeats, lambda: dm.solve(compiled, T_SPAN, stages=STAGES, h=H, y0=y0))
    error = np.stack([np.abs(sol[v] - radau[v]) for v in sol.names])  # (variables, states, times)
    per_state = error.max(axis=(0, 2))
    counts, edges = np.histogram(np.log10(per_state), bins=40)
    return {
        "box": f"{' '.join(compiled.state_names)} within +-{trained:g} of {center.tolist()}, projected on g = 0",
        "new_states": f"{count} uniform within +-{SURROGATE_HALF_WIDTH:g}, projected on g = 0",
        "training_states": samples,
        "config": {
            "architecture": config.architecture,
            "width": config.width,
            "depth": config.depth,
            "activation": config.activation,
            "warm_start": config.warm_start,
            "lm_iterations_per_segment": config.iterations,
        },
        "final_max_residual": [st.max_residual for st in surrogate.stats],
        "training_seconds": train_seconds,
        "count": count,
        "evaluation_seconds": eval_seconds,
        "radau_batch_seconds": radau_seconds,
        "max_error_per_variable": {v: float(error[k].max()) for k, v in enumerate(sol.names)},
        "max_error_over_t": {"t": sol.t.tolist(), "error": error.max(axis=(0, 1)).tolist()},
        "error_percentiles": {str(q): float(np.percentile(per_state, q)) for q in (50, 90, 99, 100)},
        "log10_error_histogram": {"edges": edges.tolist(), "counts": counts.tolist()},
    }


def plot(results, path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    fig = Figure(figsize=(13, 8.4), layout="constrained")
    axes = fig.subplots(2, 2)
    for ax, name in zip(axes[0], PROBLEMS, strict=True):
        rows = results["problems"][name]["methods"]
        labels = list(rows)
        variables = list(rows["radau"]["errors"])
        width = 0.8 / len(labels)
        for i, label in enumerate(labels):
            errs = [max(rows[label]["errors"][v], 1e-16) for v in variables]
            ax.bar(np.arange(len(variables)) + i * width, errs, width, label=f"{label}: {rows[label]['seconds']:.3g} s")
        ax.set_yscale("log")
        ax.set_xticks(np.arange(len(variables)) + width * (len(labels) - 1) / 2, variables)
        ax.set_ylabel("max absolute error")
        ax.set_title(f"{name} ({results['problems'][name]['activation']}), s=3, h=0.05 on [0, 1]")
        ax.legend(fontsize=7)
    histogram, over_t = axes[1]
    for name, s in results["surrogate"].items():
        seconds = f"{s['evaluation_seconds']:.2f} s (batched radau {s['radau_batch_seconds']:.2f} s)"
        label = f"{name}: {s['count']} states in {seconds}"
        edges, counts = s["log10_error_histogram"]["edges"], s["log10_error_histogram"]["counts"]
        histogram.stairs(counts, edges, label=label)
        over_t.semilogy(s["max_error_over_t"]["t"][1:], s["max_error_over_t"]["error"][1:], "o-", ms=3, label=name)
    histogram.axvline(np.log10(SURROGATE_TARGET), color="k", ls="--", label="target 1e-5")
    histogram.set_xlabel("log10 of a new state's max error over variables and t (vs batched radau)")
    histogram.set_ylabel("states")
    histogram.set_title("surrogate: error per new initial state")
    histogram.legend(fontsize=7)
    over_t.axhline(SURROGATE_TARGET, color="k", ls="--", label="target 1e-5")
    over_t.set_xlabel("t")
    over_t.set_ylabel("max error over new states and variables")
    over_t.set_title("surrogate: error along the trajectory")
    over_t.legend(fontsize=7)
    fig.savefig(path, dpi=120)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="50 paper iterations, 1000 surrogate states, one repeat")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--paper-iterations", type=int, default=1000)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    repeats = 1 if args.quick else args.repeats
    paper_iterations = 50 if args.quick else args.paper_iterations
    results = {
        "machine": f"{platform.processor() or platform.machine()}, torch {torch.__version__}, 1 thread",
        "problems": {name: problem_rows(name, repeats, paper_iterations) for name in PROBLEMS},
        "surrogate": {name: surrogate_rows(name, args.quick, repeats) for name in PROBLEMS},
    }
    for name, block in results["problems"].items():
        print(f"{name} ({block['activation']}):")
        for label, row in block["methods"].items():
            errs = "  ".join(f"{v} {e:.1e}" for v, e in row["errors"].items())
            print(f"  {label:<42} {row['seconds']:10.3f} s   {errs}")
    for name, s in results["surrogate"].items():
        print(
            f"surrogate {name}: {s['count']} new states in {s['evaluation_seconds']:.4f} s "
            f"(batched radau {s['radau_batch_seconds']:.3f} s); "
            f"max error {max(s['max_error_per_variable'].values()):.1e}; "
            f"percentiles {s['error_percentiles']}; trained in {s['training_seconds']:.0f} s"
        )
    suffix = "_quick" if args.quick else ""
    (HERE / f"pinn_speed{suffix}.json").write_text(json.dumps(results, indent=2) + "\n")
    plot(results, HERE / f"pinn_speed{suffix}.png")


if __name__ == "__main__":
    main()

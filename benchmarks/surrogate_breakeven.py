"""When does a surrogate pay?  Training plus querying against batched radau at equal error.

Two cases: the pendulum with its start in a +-1 % box of y1, y4 over [0, 0.25] (16 training
states, the surrogate's defaults), and the 3-bus grid of ``benchmarks/pinn_models.py`` with
generator 1's angle and speed in a box over [0, 0.25].  h = 0.05, s = 3.

* The surrogate's error: max absolute error over every variable and grid time of the networks'
  answers to ``--check`` held-out queries against radau at h / 8 (the truth here).
* Radau at equal error: the largest h of the span and h / 2^k whose error on the same queries
  (at the grid times both share) is at most the surrogate's; its batched time is measured at
  each size.
* The networks' time per query, and the networks + Newton (the collocation solution at h = 0.05:
  radau's error at that h, so compared with radau at h = 0.05).

Break-even: the number of queries N at which training + N queries costs what N radau queries
do, ``N = training / (radau per query - surrogate per query)``; "never" when the surrogate's
query is not the cheaper.  Per-query times are from the largest size timed.  One torch thread.

Run: python benchmarks/surrogate_breakeven.py [--queries 1000,10000,100000]
Writes benchmarks/surrogate_breakeven.json and .png.
"""

from __future__ import annotations

import argparse
import json
import time
import warnings
from pathlib import Path

import numpy as np
import torch

import daemodel as dm

HERE = Path(__file__).resolve().parent
H, STAGES, SPAN = 0.05, 3, (0.0, 0.25)


def pendulum_case():
    from daemodel.problems import PENDULUM

    return "pendulum", PENDULUM.model().compile(), {"y1": (0.99, 1.01), "y4": (0.99, 1.01)}


def grid_case():
    import pinn_models

    return "grid", pinn_models.build_grid().compile(), {"d1": (0.3, 0.4), "w1": (0.15, 0.25)}


def draw(compiled, box, count, seed):
    rng = np.random.default_rng(seed)
    y = {name: rng.uniform(low, high, count) for name, (low, high) in box.items()}
    return compiled.consistent(y0=y)


def values(solution, names):
    return np.stack([np.atleast_2d(solution[name]) for name in names], axis=-1)


def best_time(call, repeats):
    best = np.inf
    result = None
    for _ in range(repeats):
        began = time.perf_counter()
        result = call()
        best = min(best, time.perf_counter() - began)
    return best, result


def run(case, sizes, check, repeats) -> dict:
    name, compiled, box = case
    names = (*compiled.state_names, *compiled.algebraic_names)
    began = time.perf_counter()
    surrogate = dm.Surrogate.train(compiled, SPAN, box=box, progress=False)
    training = time.perf_counter() - began
    held = draw(compiled, box, check, seed=1)
    truth = values(dm.solve(compiled, SPAN, method="radau", h=H / 8, stages=STAGES, y0=held), names)[:, ::8]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", dm.errors.OutsideTrainingBoxWarning)
        answer = values(surrogate.solve(y0=held), names)
    surrogate_error = float(np.abs(answer - truth).max())
    # radau at equal error: the coarsest h (the whole span, then H / 2^k) whose error on the
    # held-out queries, at the grid times both share, is at most the surrogate's
    span = SPAN[1] - SPAN[0]
    radau_h, radau_error = None, None
    for h in [span] + [H / 2**k for k in range(6)]:
        sol = dm.solve(compiled, SPAN, method="radau", h=h, stages=STAGES, y0=held)
        common = np.arange(0, span + 1e-12, max(h, H))
        mine = values(sol, names)[:, np.rint(common / h).astype(int)]
        error = float(np.abs(mine - truth[:, np.rint(common / H).astype(int)]).max())
        if error <= surrogate_error:
            radau_h, radau_error = h, error
            break
    if radau_h is None:
        raise SystemExit(f"{name}: radau at h = {H / 32:g} is still less accurate than the surrogate")
    rows = []
    for size in sizes:
        queries = draw(compiled, box, size, seed=2)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", dm.errors.OutsideTrainingBoxWarning)
            t_net, _ = best_time(lambda queries=queries: surrogate.solve(y0=queries), repeats)
            t_newton, _ = best_time(lambda queries=queries: surrogate.solve(y0=queries, newton=True), repeats)
        t_equal, _ = best_time(
            lambda queries=queries: dm.solve(compiled, SPAN, method="radau", h=radau_h, stages=STAGES, y0=queries),
            repeats,
        )
        t_same, _ = best_time(
            lambda queries=queries: dm.solve(compiled, SPAN, method="radau", h=H, stages=STAGES, y0=queries), repeats
        )
        rows.append(
            {
                "queries": size,
                "networks_seconds": t_net,
                "networks_newton_seconds": t_newton,
                "radau_equal_error_seconds": t_equal,
                "radau_same_h_seconds": t_same,
            }
        )
        print(
            f"{name} {size}: networks {t_net:.3f} s, +newton {t_newton:.3f} s, radau at equal error (h={radau_h:g}) "
            f"{t_equal:.3f} s, radau at h={H} {t_same:.3f} s",
            flush=True,
        )
    last = rows[-1]

    def breakeven(surrogate_seconds, radau_seconds):
        saving = (radau_seconds - surrogate_seconds) / last["queries"]
        return None if saving <= 0 else int(np.ceil(training / saving))

    return {
        "case": name,
        "box": {k: list(v) for k, v in box.items()},
        "training_seconds": training,
        "surrogate_error": surrogate_error,
        "radau_equal_error_h": radau_h,
        "radau_equal_error": radau_error,
        "sizes": rows,
        "breakeven_networks": breakeven(last["networks_seconds"], last["radau_equal_error_seconds"]),
        "breakeven_networks_newton": breakeven(last["networks_newton_seconds"], last["radau_same_h_seconds"]),
    }


def plot(runs, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(runs), figsize=(6 * len(runs), 4.5), squeeze=False)
    for ax, r in zip(axes[0], runs, strict=True):
        n = np.array([row["queries"] for row in r["sizes"]], dtype=float)
        for key, label in (
            ("networks_seconds", "surrogate: networks"),
            ("networks_newton_seconds", "surrogate: networks + Newton"),
            ("radau_equal_error_seconds", f"radau at equal error (h = {r['radau_equal_error_h']:g})"),
            ("radau_same_h_seconds", f"radau at h = {H}"),
        ):
            t = np.array([row[key] for row in r["sizes"]])
            ax.plot(n, t, "o-", label=label)
        ax.plot(
            n,
            r["training_seconds"] + np.array([row["networks_seconds"] for row in r["sizes"]]),
            "k--",
            label="training + networks",
        )
        ax.set(xscale="log", yscale="log", xlabel="queries", ylabel="seconds (1 torch thread)")
        ax.set_title(f"{r['case']}: surrogate error {r['surrogate_error']:.1e}, training {r['training_seconds']:.0f} s")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--queries", default="1000,10000,100000")
    parser.add_argument("--check", type=int, default=1000, help="held-out queries for the errors")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--cases", default="pendulum,grid")
    parser.add_argument("--out", default=str(HERE / "surrogate_breakeven"))
    args = parser.parse_args()
    torch.set_num_threads(1)
    sizes = [int(q) for q in args.queries.split(",")]
    builders = {"pendulum": pendulum_case, "grid": grid_case}
    runs = [run(builders[name](), sizes, args.check, args.repeats) for name in args.cases.split(",")]
    out = Path(args.out)
    meta = {"command": "python benchmarks/surrogate_breakeven.py", "torch_threads": 1, "h": H, "stages": STAGES}
    out.with_suffix(".json").write_text(json.dumps({"meta": meta, "runs": runs}, indent=1) + "\n")
    plot(runs, out.with_suffix(".png"))
    for r in runs:
        print(
            r["case"],
            "break-even (networks vs radau at equal error):",
            r["breakeven_networks"],
            "| (networks + Newton vs radau at the same h):",
            r["breakeven_networks_newton"],
        )


if __name__ == "__main__":
    main()

"""Classical fit against the Radau-PINN's inverse mode on the same data (issue 29).

Three problems, each with known parameters that make the synthetic data:

* ``decay``: y' = -k y, 0 = z - c y^2 (index 1), fit (k, c), span (0, 2), PINN h = 0.1;
* ``pendulum``: the paper's pendulum (index 2, ``daemodel.problems.PENDULUM``), fit (m, lam) from
  the positions y1, y2, span (0, 3), h = 0.1;
* ``akzo-nobel``: rate constants (k1, k2, klA) from all six concentrations, span (0, 20), h = 0.5.

Data: the solution at rtol = 1e-12 at ``dense`` equally spaced times (or ``sparse``: a fifth of
them, at least 5), plus normal noise of 0, 1 % or 5 % of each series' root mean square (seeds 0
and 1 for the noisy cases).  Methods, all through ``dm.fit``:

* ``radau``: adaptive radau at rtol = 1e-8 with exact sensitivities (the default);
* ``radau, h``: fixed-step radau at the PINN's h and stages (the PINN's ceiling: a perfectly
  trained PINN reproduces exactly this discrete model, so it can do no better);
* ``pinn``: the inverse mode at that h, three stages.

Recorded: each estimate's relative error against the truth, its standard error, the fit's wall
time (setup included: code generation on first use is excluded by one warm-up fit per method and
problem; the PINN's torch warm-up too), iterations and status (the PINN's certificate).  One thread.

Writes ``benchmarks/fit_inverse.json`` and ``.png`` (error against noise, dense and sparse; time)
and prints the markdown table of docs/benchmarks/fits.md.

Run: python benchmarks/fit_inverse.py [--problems decay pendulum akzo-nobel] [--out benchmarks/fit_inverse]
"""

from __future__ import annotations

import os

for _variable in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_variable] = "1"

import argparse  # noqa: E402
import datetime  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

NOISES = (0.0, 0.01, 0.05)
SEEDS = (0, 1)


def problems() -> dict:
    """name -> (compiled, truth, span, PINN h, outputs measured, dense count, bounds)."""
    from daemodel.problems import AKZO_NOBEL, DECAY, PENDULUM

    akzo = AKZO_NOBEL.model().compile()
    rates = dict(zip(akzo.parameter_names, akzo.parameter_values, strict=True))
    akzo_truth = {k: float(rates[k]) for k in ("k1", "k2", "klA")}
    return {
        "decay": (
            DECAY.model().compile(),
            dict(DECAY.parameters),
            2.0,
            0.1,
            ("y", "z"),
            20,
            {"k": (0.5, 5.0), "c": (0.2, 2.0)},
        ),
        "pendulum": (
            PENDULUM.model().compile(),
            {"m": 1.0, "lam": 1.0},
            3.0,
            0.1,
            ("y1", "y2"),
            30,
            {"m": (0.4, 3.0), "lam": (0.4, 3.0)},
        ),
        "akzo-nobel": (
            akzo,
            akzo_truth,
            20.0,
            0.5,
            ("y1", "y2", "y3", "y4", "y5", "y6"),
            20,
            {k: (v / 3, v * 3) for k, v in akzo_truth.items()},
        ),
    }


def data_for(compiled, truth, span, outputs, count, noise, seed):
    import daemodel as dm

    t = np.linspace(span / count, span, count)
    exact = dm.solve(compiled, (0.0, span), parameters=truth, rtol=1e-12, atol=1e-14, t_eval=np.r_[0.0, t])
    rng = np.random.default_rng(seed)
    return t, {
        k: exact[k][1:] + noise * np.sqrt(np.mean(exact[k][1:] ** 2)) * rng.standard_normal(count) for k in outputs
    }


def run(label, compiled, truth, span, h, outputs, dense, bounds, method, options) -> list:
    import daemodel as dm

    rows = []
    for density, count in (("dense", dense), ("sparse", max(5, dense // 5))):
        for noise in NOISES:
            for seed in SEEDS if noise > 0 else SEEDS[:1]:
                t, data = data_for(compiled, truth, span, outputs, count, noise, seed)
                base = {
                    "problem": label,
                    "method": method,
                    "data": density,
                    "points": count,
                    "noise": noise,
                    "seed": seed,
                }
                started = time.perf_counter()
                with warnings.catch_warnings(record=True) as caught:
                    warnings.simplefilter("always")
                    try:
                        fit = dm.fit(compiled, t, data, bounds, method=method.split(",")[0], **options)
                    except dm.errors.DaemodelError as error:
                        rows.append({**base, "error": f"{type(error).__name__}: {error}"})
                        continue
                seconds = time.perf_counter() - started
                relative = {k: abs(fit.parameters[k] - v) / abs(v) for k, v in truth.items()}
                rows.append(
                    {
                        **base,
                        "estimates": fit.parameters,
                        "std": fit.std,
                        "relative_error": relative,
                        "max_relative_error": max(relative.values()),
                        "max_z": max(
                            abs(fit.parameters[k] - v) / fit.std[k] if fit.std[k] > 0 else np.inf
                            for k, v in truth.items()
                        ),
                        "seconds": seconds,
                        "iterations": fit.iterations,
                        "status": fit.status,
                        "warnings": [str(w.message) for w in caught],
                    }
                )
                print(
                    label,
                    method,
                    density,
                    noise,
                    seed,
                    f"{rows[-1]['max_relative_error']:.2e}",
                    f"{seconds:.2f}s",
                    fit.status[:60],
                    flush=True,
                )
    return rows


def main() -> None:
    from scaling import machine_info

    import daemodel as dm
    from daemodel.files import write_json

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--problems", nargs="+", default=["decay", "pendulum", "akzo-nobel"])
    parser.add_argument("--out", default=str(HERE / "fit_inverse"))
    args = parser.parse_args()
    import torch

    torch.set_num_threads(1)
    rows = []
    table = problems()
    for label in args.problems:
        compiled, truth, span, h, outputs, dense, bounds = table[label]
        for method, options in (
            ("radau", {}),
            ("radau, h", {"h": h, "stages": 3}),
            ("pinn", {"h": h, "stages": 3, "config": dm.PINNConfig(h=h, stages=3)}),
        ):
            t, data = data_for(compiled, truth, span, outputs, 5, 0.0, 0)  # warm-up: code generation, torch
            dm.fit(compiled, t, data, bounds, method=method.split(",")[0], **options)
            rows.extend(run(label, compiled, truth, span, h, outputs, dense, bounds, method, options))
    out = Path(args.out)
    write_json(
        out.with_suffix(".json"),
        {
            "command": "python benchmarks/fit_inverse.py " + " ".join(sys.argv[1:]),
            "date": datetime.date.today().isoformat(),
            "machine": machine_info(None),
            "threads": 1,
            "rows": rows,
        },
    )
    plot(rows, out.with_suffix(".png"))
    summary(rows)


def _groups(rows):
    out = {}
    for r in rows:
        if "error" in r:
            continue
        out.setdefault((r["problem"], r["method"], r["data"], r["noise"]), []).append(r)
    return out


def summary(rows) -> None:
    print("| problem | data | noise | radau: error, time | radau at the PINN's h: error | pinn: error, time, status |")
    print("|---|---|---|---|---|---|")
    groups = _groups(rows)
    keys = sorted({(p, d, n) for p, _, d, n in groups}, key=lambda k: (k[0], k[1], k[2]))
    for problem, density, noise in keys:
        cells = []
        for method in ("radau", "radau, h", "pinn"):
            runs = groups.get((problem, method, density, noise), [])
            if not runs:
                cells.append("failed")
                continue
            error = np.mean([r["max_relative_error"] for r in runs])
            seconds = np.mean([r["seconds"] for r in runs])
            certified = sum(r["status"] == "success" for r in runs)
            cell = f"{error:.1e}, {seconds:.2f} s"
            if method == "radau, h":
                cell = f"{error:.1e}"
            if method == "pinn":
                cell += f", {certified}/{len(runs)} success"
            cells.append(cell)
        points = groups[(problem, "radau", density, noise)][0]["points"]
        print(f"| {problem} | {density} ({points}) | {noise:.0%} | " + " | ".join(cells) + " |")


def plot(rows, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from daemodel.files import save_figure

    groups = _groups(rows)
    names = sorted({r["problem"] for r in rows})
    fig, axes = plt.subplots(1, len(names) + 1, figsize=(4.2 * (len(names) + 1), 3.8))
    styles = {"radau": ("tab:blue", "o"), "radau, h": ("tab:green", "s"), "pinn": ("tab:red", "^")}
    for ax, name in zip(axes, names, strict=False):
        for method, (colour, marker) in styles.items():
            for density, line in (("dense", "-"), ("sparse", ":")):
                points = [
                    (n, np.mean([r["max_relative_error"] for r in groups[(name, method, density, n)]]))
                    for n in NOISES
                    if (name, method, density, n) in groups
                ]
                if points:
                    x = [max(n, 1e-3) for n, _ in points]  # noise 0 drawn at 0.1 %
                    ax.plot(
                        x,
                        [max(e, 1e-16) for _, e in points],
                        line,
                        color=colour,
                        marker=marker,
                        label=f"{method}, {density}",
                    )
        ax.set(xscale="log", yscale="log", xlabel="noise (0 drawn at 0.1 %)", ylabel="max relative error", title=name)
        ax.legend(fontsize=6)
    ax = axes[-1]
    for i, method in enumerate(styles):
        times = [
            np.mean([r["seconds"] for r in groups[(n, method, "dense", 0.01)]])
            for n in names
            if (n, method, "dense", 0.01) in groups
        ]
        ax.bar(np.arange(len(times)) + 0.27 * (i - 1), times, 0.27, color=styles[method][0], label=method)
    ax.set(xticks=range(len(names)), yscale="log", ylabel="fit time (s), dense data, 1 % noise", title="time")
    ax.set_xticklabels(names, fontsize=7)
    ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path, "out", dpi=110)


if __name__ == "__main__":
    main()

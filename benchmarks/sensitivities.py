"""Cost of radau's exact derivatives (issue 29): forward sensitivities for p names, and the adjoint
gradient for every parameter, against the solve they differentiate.

The issue's targets: forward sensitivities for p parameters within (1 + 0.5 p) x a solve, and the
adjoint gradient within 5x a solve for 50 parameters (a reaction network).  Models:

* ``pendulum-index3`` (reduced to index 2 by the solver), adaptive rtol = 1e-8 and fixed h = 0.01, s = 3;
* ``akzo-nobel`` (index 1, stiff), adaptive rtol = 1e-6, with and without ``jit=True``;
* ``network-50``: 25 species, 50 mass-action reactions with one rate constant each, and an index-1
  equilibrium species (built below), adaptive rtol = 1e-6.

Clocks: ``sol.solve_time`` for the plain solve; for forward sensitivities, the same solve's
``solve_time`` with ``sensitivities=`` (it includes the sensitivity pass, also recorded apart as
``stats["sensitivity_seconds"]``); for the adjoint, the wall time of ``sol.gradient(data, names)`` on
the plain solve's result (data: the solution itself plus 1 % noise), and the ratio of solve +
gradient to the solve.  The numeric Jacobians are generated on the first call (setup, cached on the
compiled model) and excluded: every configuration is warmed once before timing.  Best of
``--repeats``, the configurations interleaved in each pass.  One thread (BLAS and torch).

Writes ``benchmarks/sensitivities.json`` (settings, machine, every timing) and ``.png`` (cost ratio
against the number of names, the issue's budget as a line) and prints a markdown table.

Run: python benchmarks/sensitivities.py [--repeats 7] [--out benchmarks/sensitivities]
"""

from __future__ import annotations

import os

for _variable in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_variable] = "1"

import argparse  # noqa: E402
import datetime  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))


def reaction_network(species: int = 25, reactions: int = 50):
    """A mass-action network: reaction r turns species ``r mod S`` (with ``(3r+1) mod S`` for even r,
    a bimolecular step) into ``(7r+3) mod S`` at rate constant ``k{r}``; the species ``e`` is in fast
    equilibrium, ``e = K c0 c1`` (index 1), and feeds c2."""
    import daemodel as dm

    m = dm.Model(f"network-{reactions}")
    c = [f"c{i}" for i in range(species)]
    m.states(c)
    m.algebraics("e")
    m.parameter("K", 0.5)
    rhs = {name: [] for name in c}
    for r in range(reactions):
        m.parameter(f"k{r}", 0.1 * (1 + r % 5))
        a, b = r % species, (7 * r + 3) % species
        rate = f"k{r}*{c[a]}" + (f"*{c[(3 * r + 1) % species]}" if r % 2 == 0 else "")
        rhs[c[a]].append(f"-{rate}")
        if r % 2 == 0:
            rhs[c[(3 * r + 1) % species]].append(f"-{rate}")
        rhs[c[b]].append(f"+{rate}")
    rhs["c2"].append("+0.1*e")
    rhs["c0"].append("-0.1*e")
    for name in c:
        m.ode(name, " ".join(rhs[name]) or "0")
    m.constraint("e - K*c0*c1", name="equilibrium")
    m.initial(**{name: 1.0 / (1 + i) for i, name in enumerate(c)})
    return m


def cases():
    """``(label, compiled, t_span, options, name lists to time)``."""
    from daemodel.problems import AKZO_NOBEL, PENDULUM_INDEX3

    pendulum = PENDULUM_INDEX3.model().compile()
    akzo = AKZO_NOBEL.model().compile()
    network = reaction_network().compile()
    akzo_names = ["k1", "k2", "k3", "k4", "Kc", "klA", "Ks", "pCO2", "H"]
    network_names = [f"k{r}" for r in range(50)]
    return [
        (
            "pendulum-index3, rtol 1e-8",
            pendulum,
            (0.0, 10.0),
            dict(rtol=1e-8),
            [["m"], ["m", "lam"], ["m", "lam", "y2", "y3"]],
        ),
        (
            "pendulum-index3, h 0.01",
            pendulum,
            (0.0, 10.0),
            dict(h=0.01, stages=3),
            [["m"], ["m", "lam"], ["m", "lam", "y2", "y3"]],
        ),
        (
            "akzo-nobel, rtol 1e-6",
            akzo,
            (0.0, 180.0),
            dict(rtol=1e-6),
            [akzo_names[:1], akzo_names[:2], akzo_names[:5], akzo_names],
        ),
        (
            "akzo-nobel, rtol 1e-6, jit",
            akzo,
            (0.0, 180.0),
            dict(rtol=1e-6, jit=True),
            [akzo_names[:1], akzo_names[:2], akzo_names[:5], akzo_names],
        ),
        (
            "network-50, rtol 1e-6",
            network,
            (0.0, 20.0),
            dict(rtol=1e-6),
            [network_names[:1], network_names[:5], network_names[:10], network_names],
        ),
    ]


def measure(repeats: int) -> list:
    import torch

    import daemodel as dm

    torch.set_num_threads(1)
    rows = []
    for label, compiled, span, options, name_lists in cases():
        t_eval = np.linspace(*span, 41)
        plain = dm.solve(compiled, span, t_eval=t_eval, **options)
        rng = np.random.default_rng(0)
        data = {n: plain[n] * (1 + 0.01 * rng.standard_normal(plain[n].shape)) for n in plain.names}
        gradient_names = list(compiled.parameter_names)
        for names in name_lists:  # warm: the numeric Jacobians are made once per compiled model
            dm.solve(compiled, span, t_eval=t_eval, sensitivities=names, **options)
        plain.gradient(data, gradient_names)
        best = {"solve": np.inf, "gradient": np.inf, **{len(n): np.inf for n in name_lists}}
        sensitivity_part = {len(n): np.inf for n in name_lists}
        for _ in range(repeats):
            sol = dm.solve(compiled, span, t_eval=t_eval, **options)
            best["solve"] = min(best["solve"], sol.solve_time)
            started = time.perf_counter()
            sol.gradient(data, gradient_names)
            best["gradient"] = min(best["gradient"], time.perf_counter() - started)
            for names in name_lists:
                with_sens = dm.solve(compiled, span, t_eval=t_eval, sensitivities=names, **options)
                best[len(names)] = min(best[len(names)], with_sens.solve_time)
                sensitivity_part[len(names)] = min(sensitivity_part[len(names)], with_sens.stats["sensitivity_seconds"])
        solve = best["solve"]
        row = {
            "case": label,
            "options": {k: v for k, v in options.items()},
            "steps": int(plain.stats["steps"]),
            "states": len(compiled.states),
            "algebraics": len(compiled.algebraics),
            "solve_seconds": solve,
            "forward": [
                {
                    "names": p,
                    "seconds": best[p],
                    "sensitivity_seconds": sensitivity_part[p],
                    "ratio": best[p] / solve,
                    "budget": 1 + 0.5 * p,
                }
                for p in sorted(k for k in best if isinstance(k, int))
            ],
            "adjoint": {
                "parameters": len(gradient_names),
                "gradient_seconds": best["gradient"],
                "gradient_over_solve": best["gradient"] / solve,
                "solve_and_gradient_over_solve": (solve + best["gradient"]) / solve,
                "budget": 5.0,
            },
        }
        rows.append(row)
        print(json.dumps(row), flush=True)
    return rows


def plot(rows, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for row in rows:
        p = [f["names"] for f in row["forward"]]
        axes[0].plot(p, [f["ratio"] for f in row["forward"]], "o-", label=row["case"])
    span = np.array([1, 50])
    axes[0].plot(span, 1 + 0.5 * span, "k--", label="budget 1 + 0.5 p")
    axes[0].set(
        xscale="log",
        yscale="log",
        xlabel="names p",
        ylabel="solve with sensitivities / solve",
        title="forward sensitivities",
    )
    axes[0].legend(fontsize=7)
    labels = [row["case"] for row in rows]
    values = [row["adjoint"]["solve_and_gradient_over_solve"] for row in rows]
    axes[1].barh(labels, values, color="tab:blue")
    axes[1].axvline(5.0, color="k", ls="--", label="budget 5x")
    for y, row in enumerate(rows):
        axes[1].text(values[y], y, f" {row['adjoint']['parameters']} params", va="center", fontsize=7)
    axes[1].set(xlabel="(solve + adjoint gradient) / solve", title="adjoint gradient, every parameter")
    axes[1].tick_params(axis="y", labelsize=7)
    axes[1].legend(fontsize=7)
    fig.tight_layout()
    from daemodel.files import save_figure

    save_figure(fig, path, "out", dpi=110)


def main() -> None:
    from scaling import machine_info

    from daemodel.files import write_json

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--out", default=str(HERE / "sensitivities"))
    args = parser.parse_args()
    rows = measure(args.repeats)
    out = Path(args.out)
    result = {
        "command": "python benchmarks/sensitivities.py " + " ".join(sys.argv[1:]),
        "date": datetime.date.today().isoformat(),
        "machine": machine_info(None),
        "threads": 1,
        "repeats": args.repeats,
        "rows": rows,
    }
    write_json(out.with_suffix(".json"), result)
    plot(rows, out.with_suffix(".png"))
    print("| case | steps | solve (ms) | p | with sensitivities / solve | budget | adjoint: (solve + gradient)/solve |")
    print("|---|---|---|---|---|---|---|")
    for row in rows:
        for f in row["forward"]:
            adj = row["adjoint"]
            print(
                f"| {row['case']} | {row['steps']} | {1e3 * row['solve_seconds']:.2f} | {f['names']} | "
                f"{f['ratio']:.2f} | {f['budget']:.1f} | {adj['solve_and_gradient_over_solve']:.2f} "
                f"({adj['parameters']} params) |"
            )


if __name__ == "__main__":
    main()

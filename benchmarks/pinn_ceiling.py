"""The Radau-PINN's ceiling on models people bring: error, status, certificate and time against
classical Radau IIA at the same stages and h.

For every case of ``benchmarks/pinn_models.py`` (heat by lines, a 3-bus grid, a slider-crank at
index 3 and 2 and two steps, a model singular at z = 0, a diode rectifier for 1000 load
resistances, and the four Test Set problems):

* ``radau``: ``dm.solve(method="radau", h=h, stages=s)``, the PINN's ceiling;
* ``pinn``: ``dm.solve(method="pinn", h=h, stages=s)``, the fast mode's defaults (per-variable
  networks, Levenberg-Marquardt to tol = 1e-12, warm start, independent networks per sample);
* errors: max absolute error over every variable and grid time against ``method="reference"``
  (scipy at 1e-12; for the 1000-sample batch, on every 100th sample) or the closed form;
* the certificate: the PINN's certified distance from radau's solution and its estimate of
  radau's own error (worst over variables and times), its status, and the true |pinn - radau|;
* times: the PINN's training against radau's solve (``training_ratio``, the issue's measure:
  a PINN's setup is its training, radau's is building its engine), and setup + solve of each
  (the PINN's training, evaluation and certificate against radau's engine and solve,
  ``time_ratio``); each the best of ``--repeats`` calls after a warm-up, radau and the PINN
  called in turn.

torch runs on one thread (set deliberately: the networks are too small to gain from two, and
two threads fight with anything else on a 2-core machine).

Run: python benchmarks/pinn_ceiling.py [--cases heat,grid] [--repeats 2]
Writes benchmarks/pinn_ceiling.json and .png (or --out PREFIX).
"""

from __future__ import annotations

import argparse
import json
import platform
import time
import warnings
from pathlib import Path

import numpy as np
import torch

import daemodel as dm

HERE = Path(__file__).resolve().parent
# The reference of a large batch is solved on every REFERENCE_STRIDE-th sample (scipy solves
# them one by one).
REFERENCE_STRIDE = 100


def timed(functions, repeats: int) -> list:
    """For each of ``functions``, called in turn ``repeats`` times after one warm-up each (in
    turn, so that the machine's slow spells fall on both): the last solution and the best setup,
    solve and setup + solve times, each the least of its own over the calls."""
    for function in functions:
        function()
    best = [{"setup": np.inf, "solve": np.inf, "total": np.inf} for _ in functions]
    solutions = [None] * len(functions)
    for _ in range(repeats):
        for k, function in enumerate(functions):
            solutions[k] = solution = function()
            times = {"setup": solution.setup_time, "solve": solution.solve_time}
            times["total"] = times["setup"] + times["solve"]
            best[k] = {key: min(best[k][key], value) for key, value in times.items()}
    return list(zip(solutions, best, strict=True))


def grid_values(solution, names) -> np.ndarray:
    return np.stack([np.atleast_2d(solution[name]) for name in names], axis=-1)  # (B, T, D)


def truth(case, compiled, t):
    """Exact or reference values (B', T, D) at the grid times, and the samples they cover."""
    names = (*compiled.state_names, *compiled.algebraic_names)
    if case.exact is not None:
        exact = case.exact(t)
        return np.stack([np.atleast_2d(exact[name]) for name in names], axis=-1), slice(None), "exact"
    options = dict(case.options)
    rows = slice(None)
    if "parameters" in options:
        rows = slice(None, None, REFERENCE_STRIDE)
        options["parameters"] = {k: np.asarray(v)[rows] for k, v in options["parameters"].items()}
    reference = dm.solve(compiled, case.t_span, method="reference", t_eval=t, **options)
    label = "reference 1e-12" + (f", every {REFERENCE_STRIDE}th sample" if rows != slice(None) else "")
    return grid_values(reference, names), rows, label


def run_case(case, repeats: int) -> dict:
    compiled = case.model().compile()
    names = (*compiled.state_names, *compiled.algebraic_names)
    common = {"h": case.h, "stages": case.stages, **case.options}
    try:
        dm.solve(compiled, case.t_span, method="radau", **common)
    except dm.errors.SolverError as error:
        return {"case": case.name, "note": case.note, "radau_failure": str(error)}

    def pinn_solve():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", dm.errors.UncertifiedWarning)
            return dm.solve(compiled, case.t_span, method="pinn", **common)

    (radau, radau_time), (pinn, pinn_time) = timed(
        [lambda: dm.solve(compiled, case.t_span, method="radau", **common), pinn_solve], repeats
    )
    true, rows, against = truth(case, compiled, radau.t)
    radau_v, pinn_v = grid_values(radau, names), grid_values(pinn, names)
    certificate = pinn.stats["certificate"]

    def worst(table):
        return max(max(values) for values in table.values())

    return {
        "case": case.name,
        "note": case.note,
        "unknowns": len(names),
        "batch": int(radau_v.shape[0]),
        "h": case.h,
        "stages": case.stages,
        "errors_against": against,
        "pinn_error": float(np.abs(pinn_v[rows] - true).max()),
        "radau_error": float(np.abs(radau_v[rows] - true).max()),
        "pinn_radau_distance": float(np.abs(pinn_v - radau_v).max()),
        "status": pinn.status,
        "certified_distance": worst(certificate["max_distance"]),
        "certified_radau_error": worst(certificate["max_radau_error"]),
        "certified_samples": int(sum(certificate["certified"])),
        "pinn_seconds": pinn_time["total"],
        "pinn_training_seconds": pinn_time["setup"],  # a PINN's setup is its training
        "pinn_certificate_seconds": pinn.stats["certificate_seconds"],
        "lm_iterations": int(sum(pinn.stats["iterations"])),
        "radau_seconds": radau_time["total"],
        "radau_solve_seconds": radau_time["solve"],
        "time_ratio": pinn_time["total"] / radau_time["total"],
        "training_ratio": pinn_time["setup"] / radau_time["solve"],
    }


def plot(rows: list, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    done = [r for r in rows if "status" in r]
    fig, (left, right) = plt.subplots(1, 2, figsize=(13, 5.5))
    for r in done:
        ok = r["status"] == "success"
        left.scatter(r["radau_error"], r["pinn_error"], marker="o" if ok else "x", color="C0" if ok else "C3", s=40)
        left.annotate(
            r["case"], (r["radau_error"], r["pinn_error"]), fontsize=7, xytext=(3, 3), textcoords="offset points"
        )
    low = min(min(r["radau_error"], r["pinn_error"]) for r in done) / 3
    high = max(max(r["radau_error"], r["pinn_error"]) for r in done) * 3
    left.plot([low, high], [low, high], "k-", lw=0.8, label="PINN = radau")
    left.plot([low, high], [2 * low, 2 * high], "k--", lw=0.8, label="2 x radau")
    left.set(xscale="log", yscale="log", xlabel="radau error (same s, h)", ylabel="PINN error")
    left.set_title("error against the reference (o: success, x: flagged)")
    left.legend(loc="upper left")
    where = np.arange(len(done))
    training, total = [r["training_ratio"] for r in done], [r["time_ratio"] for r in done]
    right.barh(where - 0.2, training, height=0.4, color="C0", label="training / radau's solve")
    right.barh(where + 0.2, total, height=0.4, color="C1", label="setup + solve, each")
    right.axvline(20, color="k", ls="--", lw=0.8, label="20 x (the issue's target)")
    for y, (a, b) in enumerate(zip(training, total, strict=True)):
        right.annotate(f"{a:.0f}x", (a, y - 0.2), xytext=(3, -3), textcoords="offset points", fontsize=7)
        right.annotate(f"{b:.0f}x", (b, y + 0.2), xytext=(3, -3), textcoords="offset points", fontsize=7)
    right.set(xscale="log", xlim=(1, 3 * max(total + training)))
    right.set_yticks(where, [r["case"] for r in done])
    right.set_xlabel("PINN time / radau time")
    right.invert_yaxis()
    right.legend(loc="center right", fontsize=8)
    right.set_title("time at the same stages and h, 1 torch thread")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main() -> None:
    import pinn_models

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cases", default="", help="comma-separated case names (default: all)")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--out", default=str(HERE / "pinn_ceiling"))
    args = parser.parse_args()
    torch.set_num_threads(1)
    wanted = [name.strip() for name in args.cases.split(",") if name.strip()]
    rows = []
    for case in pinn_models.CASES:
        if wanted and case.name not in wanted:
            continue
        began = time.perf_counter()
        row = run_case(case, args.repeats)
        rows.append(row)
        if "status" in row:
            print(
                f"{row['case']:28s} pinn {row['pinn_error']:.1e} radau {row['radau_error']:.1e} "
                f"{'success' if row['status'] == 'success' else 'FLAGGED'} cert {row['certified_distance']:.1e} "
                f"(radau est {row['certified_radau_error']:.1e}) training x{row['training_ratio']:.1f} "
                f"total x{row['time_ratio']:.1f} ({row['pinn_training_seconds']:.3f} s / "
                f"{row['radau_solve_seconds']:.4f} s; {row['pinn_seconds']:.3f} s / {row['radau_seconds']:.4f} s) "
                f"[{time.perf_counter() - began:.0f} s]",
                flush=True,
            )
        else:
            print(f"{row['case']:28s} radau failed: {row['radau_failure']}", flush=True)
    out = Path(args.out)
    meta = {
        "command": "python benchmarks/pinn_ceiling.py"
        + (f" --cases {args.cases}" if wanted else "")
        + (f" --repeats {args.repeats}" if args.repeats != 2 else ""),
        "machine": platform.processor() or platform.machine(),
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "repeats": args.repeats,
    }
    out.with_suffix(".json").write_text(json.dumps({"meta": meta, "cases": rows}, indent=1) + "\n")
    plot(rows, out.with_suffix(".png"))
    print(f"wrote {out.with_suffix('.json')} and {out.with_suffix('.png')}")


if __name__ == "__main__":
    main()

"""The paper's recipe run to its full 100,000 Adam iterations per segment, for the first segments.

Chen, Tang et al. report, with v = 3 stages, absolute errors of about 1e-6 (differential) and
1e-5 (algebraic) on their two problems.  Their recipe: h = 0.05, one network of 5 x 100 per
variable (approach 2), the problem's activation with an adaptive slope, Adam at 1e-3 for 100,000
iterations per segment (:meth:`daemodel.PINNConfig.paper`).  On one CPU core a segment takes
minutes, so this runs the first ``--segments`` segments of each problem and reports, per segment,
the error of the PINN's segment-end values against the Radau IIA collocation solution at the
same h (the ceiling a perfectly trained PINN reaches) and against the exact or reference solution.

    python benchmarks/paper_recipe.py --segments 2 --out benchmarks/paper_recipe.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

import daemodel as dm
from daemodel.problems import HESSENBERG, PENDULUM

PROBLEMS = {"hessenberg": HESSENBERG, "pendulum": PENDULUM}


def worst(solution, other, names, k: int) -> float:
    """Largest absolute difference over ``names`` at grid index ``k``."""
    return float(max(abs(solution[name][k] - other[name][k]) for name in names))


def run(name: str, segments: int, iterations: int) -> dict:
    problem = PROBLEMS[name]
    compiled = problem.model().compile()
    config = dm.PINNConfig.paper(name, iterations=iterations)
    t_span = (0.0, segments * config.h)
    began = time.perf_counter()
    pinn = dm.solve(compiled, t_span, method="pinn", config=config, progress=False)
    seconds = time.perf_counter() - began
    ceiling = dm.solve(compiled, t_span, method="radau", stages=config.stages, h=config.h)
    if problem.exact:
        exact = problem.exact_solution()(pinn.t)
        truth, described = exact, "exact solution"
    else:
        truth = dm.solve(compiled, t_span, method="reference", t_eval=pinn.t)
        described = "method='reference' at rtol = atol = 1e-12"
    states, algebraics = compiled.state_names, compiled.algebraic_names
    rows = []
    for k in range(1, segments + 1):
        rows.append(
            {
                "segment": k,
                "t_end": float(pinn.t[k]),
                "seconds": pinn.stats["segment_seconds"][k - 1],
                "iterations": pinn.stats["iterations"][k - 1],
                "L_f": pinn.stats["L_f"][k - 1],
                "L_g": pinn.stats["L_g"][k - 1],
                "L_s": pinn.stats["L_s"][k - 1],
                "pinn_vs_truth": {"y": worst(pinn, truth, states, k), "z": worst(pinn, truth, algebraics, k)},
                "pinn_vs_ceiling": {"y": worst(pinn, ceiling, states, k), "z": worst(pinn, ceiling, algebraics, k)},
                "ceiling_vs_truth": {"y": worst(ceiling, truth, states, k), "z": worst(ceiling, truth, algebraics, k)},
            }
        )
        row = rows[-1]
        error, ceiling_error = row["pinn_vs_truth"], row["ceiling_vs_truth"]
        print(
            f"{name} segment {k}: {row['seconds']:.0f} s, {row['iterations']} Adam iterations; "
            f"error y {error['y']:.1e} z {error['z']:.1e} "
            f"(ceiling y {ceiling_error['y']:.1e} z {ceiling_error['z']:.1e})",
            flush=True,
        )
    return {
        "problem": name,
        "config": {k: v for k, v in config.__dict__.items()},
        "truth": described,
        "seconds": seconds,
        "torch_threads": torch.get_num_threads(),
        "segments": rows,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--segments", type=int, default=1, help="segments of h = 0.05 to train (default 1)")
    parser.add_argument("--iterations", type=int, default=100_000, help="Adam iterations per segment (paper: 100,000)")
    parser.add_argument("--problems", default="hessenberg,pendulum")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", default="benchmarks/paper_recipe.json")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    results = [run(name, args.segments, args.iterations) for name in args.problems.split(",")]
    Path(args.out).write_text(json.dumps({"runs": results}, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()

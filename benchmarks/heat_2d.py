"""The 2-D heat equation declared as arrays (issue 44, item 2): examples/heat_2d.py at N x N, N up to
100 (10^4 states, 200 algebraic boundary values), each stage timed apart, and the error against the
exact eigenmode.

For each N: ``declare`` (building the arrays of sympy expressions and ``m.ode``/``m.constraint`` on
them), ``compile`` (``m.compile()``), and radau's own clocks of one ``dm.solve`` at rtol 1e-7
(``setup``: code generation and engine; ``solve``: integration), then max |T - exact| and its ratio
to h^2 (second order: the ratio levels off).  One process, one thread (torch and BLAS).

    OMP_NUM_THREADS=1 python benchmarks/heat_2d.py --out benchmarks/heat_2d.json   # and heat_2d.png
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import platform
import subprocess
import time
from pathlib import Path

import numpy as np
import torch

import daemodel as dm

ROOT = Path(__file__).resolve().parents[1]


def example():
    spec = importlib.util.spec_from_file_location("heat_2d", ROOT / "examples" / "heat_2d.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def measure(heat, n: int) -> dict:
    began = time.perf_counter()
    m, x, y = heat.build_model(n)
    declared = time.perf_counter()
    compiled = m.compile()
    done = time.perf_counter()
    sol = dm.solve(compiled, (0.0, heat.T_END), rtol=1e-7, atol=1e-9)
    called = time.perf_counter()
    error = float(np.max(np.abs(sol["T"] - heat.exact(x, y, sol.t))))
    h = 1.0 / (n + 1)
    return {
        "n": n,
        "states": len(compiled.state_names),
        "algebraic": len(compiled.algebraic_names),
        "declare_s": declared - began,
        "compile_s": done - declared,
        "setup_s": sol.setup_time,
        "solve_s": sol.solve_time,
        "solve_call_s": called - done,
        "steps": int(sol.stats.get("steps", -1)),
        "status": sol.status,
        "max_error": error,
        "error_per_h2": error / h**2,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=int, nargs="+", default=[10, 20, 40, 70, 100])
    parser.add_argument("--out", default="benchmarks/heat_2d.json")
    args = parser.parse_args()
    torch.set_num_threads(1)
    heat = example()
    records = []
    for n in args.sizes:
        records.append(measure(heat, n))
        print(json.dumps(records[-1]), flush=True)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=ROOT).stdout
    out = {
        "command": "OMP_NUM_THREADS=1 python benchmarks/heat_2d.py --out benchmarks/heat_2d.json",
        "commit": commit.strip(),
        "machine": {"processor": platform.processor() or platform.machine(), "python": platform.python_version()},
        "torch_threads": torch.get_num_threads(),
        "records": records,
    }
    path = Path(args.out)
    path.write_text(json.dumps(out, indent=2) + "\n")
    plot(records, path.with_suffix(".png"))
    print(f"wrote {path} and {path.with_suffix('.png')}")


def plot(records: list, path: Path) -> None:
    """Left: seconds per stage against unknowns (log-log); right: the error against h with an h^2 line."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(11, 4.5), layout="constrained")
    left, right = fig.subplots(1, 2)
    unknowns = [r["states"] + r["algebraic"] for r in records]
    for key, label in (
        ("declare_s", "declare"),
        ("compile_s", "compile"),
        ("setup_s", "radau setup"),
        ("solve_s", "radau solve"),
    ):
        left.loglog(unknowns, [r[key] for r in records], "o-", label=label)
    left.set_xlabel("unknowns (N^2 + 2N)")
    left.set_ylabel("seconds")
    left.set_title("heat_2d: time per stage")
    left.legend()
    h = np.array([1.0 / (r["n"] + 1) for r in records])
    error = np.array([r["max_error"] for r in records])
    right.loglog(h, error, "o-", label="max |T - exact|")
    right.loglog(h, error[-1] * (h / h[-1]) ** 2, "k--", label="h^2")
    right.set_xlabel("h = 1/(N+1)")
    right.set_ylabel("max error at the output times")
    right.set_title("heat_2d: error against the eigenmode")
    right.legend()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    main()

"""Declaring and compiling at 10^3 ... 10^5 unknowns (issue 44): numpy's arithmetic against stencils.

The reaction-diffusion family (``scaling_models.reaction_diffusion_arrays``: 2K unknowns, one state
and one algebraic variable per grid point, tridiagonal) declared as arrays two ways, the same
equations tree for tree: ``arrays`` (numpy's arithmetic on the arrays of symbols: one sympy tree per
element, an evaluated operation at a time) and ``stencils`` (``dm.stencil``: the arithmetic recorded
once as a template, each element made by renaming).  Each (declaration, size) runs in a fresh
process with one thread: ``declare`` (the model's construction), ``compile`` (``Model.compile()``),
their sum, each as wall and as the process's CPU time (on a shared machine the wall is the CPU time
plus the time others held the cores), and the process's peak resident set.  Growth exponents
(time ~ unknowns^k) are fitted over the sizes from :data:`FIT_FROM` unknowns on.

    OMP_NUM_THREADS=1 python benchmarks/declaring.py --out benchmarks/declaring   # .json and .png
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import scaling_models  # noqa: E402

UNKNOWNS = (1_000, 3_000, 10_000, 30_000, 100_000)
DECLARATIONS = ("arrays", "stencils")
# Exponents are fitted over the sizes from this many unknowns on (below, fixed costs dominate).
FIT_FROM = 1_000
# Seconds a worker may take (numpy's arithmetic at 10^5 unknowns took ~45 s on a loaded 2-core machine).
WORKER_LIMIT = 900


def worker(declaration: str, unknowns: int) -> dict:
    """Declare and compile once in this (fresh) process."""
    began, cpu_began = time.perf_counter(), time.process_time()
    model = scaling_models.DECLARATIONS[declaration](unknowns // 2)
    declared, cpu_declared = time.perf_counter(), time.process_time()
    compiled = model.compile()
    done, cpu_done = time.perf_counter(), time.process_time()
    return {
        "declare_s": declared - began,
        "compile_s": done - declared,
        "total_s": done - began,
        "declare_cpu_s": cpu_declared - cpu_began,
        "compile_cpu_s": cpu_done - cpu_declared,
        "total_cpu_s": cpu_done - cpu_began,
        "peak_rss": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
        "equations": len(compiled.rhs) + len(compiled.g),
    }


def run(declaration: str, unknowns: int) -> dict:
    """:func:`worker` in a fresh process with one BLAS thread: its result, or ``{"failed": message}``."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    with tempfile.TemporaryDirectory() as folder:
        result = Path(folder) / "result.json"
        command = [sys.executable, __file__, "--worker", declaration, str(unknowns), str(result)]
        try:
            done = subprocess.run(command, env=env, timeout=WORKER_LIMIT, capture_output=True, text=True)
        except subprocess.TimeoutExpired:
            return {"failed": f"stopped after {WORKER_LIMIT} s"}
        if done.returncode != 0 or not result.exists():
            return {"failed": (done.stderr or "")[-1500:] or f"exit code {done.returncode}"}
        return json.loads(result.read_text())


def slope(points: list) -> float | None:
    """Fitted exponent of log(value) against log(unknowns) over the sizes from :data:`FIT_FROM` on."""
    points = [(n, v) for n, v in points if n >= FIT_FROM and v > 0]
    if len(points) < 2:
        return None
    return float(np.polyfit(np.log([p[0] for p in points]), np.log([p[1] for p in points]), 1)[0])


def table(result: dict) -> str:
    """Markdown: one row per size, the two declarations side by side."""
    head = "| unknowns |" + "".join(
        f" {d} declare | {d} compile | {d} total (CPU) | {d} peak (GB) |" for d in DECLARATIONS
    )
    lines = [head, "|" + "---:|" * (1 + 4 * len(DECLARATIONS))]
    for r in result["records"]:
        row = [f"{r['unknowns']:,}"]
        for d in DECLARATIONS:
            c = r[d]
            if "failed" in c:
                row += ["failed", "", "", ""]
                continue
            row += [f"{c['declare_s']:.2f}", f"{c['compile_s']:.2f}", f"{c['total_s']:.2f} ({c['total_cpu_s']:.2f})"]
            row += [f"{c['peak_rss'] / 1e9:.2f}"]
        lines.append("| " + " | ".join(row) + " |")
    lines += ["", f"Growth exponents (from {FIT_FROM:,} unknowns on):", ""]
    lines += [f"- {label}: {value:.2f}" for label, value in result["slopes"].items() if value is not None]
    return "\n".join(lines)


def plot(result: dict, path: Path) -> None:
    """Log-log: declare, compile and their sum (left), peak memory (right)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(11, 4.6), layout="constrained")
    times, memory = fig.subplots(1, 2)
    for d, style in zip(DECLARATIONS, ("--", "-"), strict=True):
        for field in ("declare_s", "compile_s", "total_s", "total_cpu_s"):
            points = [(r["unknowns"], r[d][field]) for r in result["records"] if field in r[d]]
            fit = result["slopes"].get(f"{d} {field[:-2]}")
            label = f"{d}: {field[:-2]}" + (f" (n^{fit:.2f})" if fit else "")
            times.loglog(*zip(*points, strict=True), ls=style, marker="o", label=label)
        points = [(r["unknowns"], r[d]["peak_rss"] / 1e9) for r in result["records"] if "peak_rss" in r[d]]
        memory.loglog(*zip(*points, strict=True), ls=style, marker="o", label=f"{d}: peak resident set")
    times.axhline(20, color="grey", lw=0.8, label="20 s (issue 44's target at 10^5)")
    for ax, title, unit in ((times, "declare and compile", "seconds"), (memory, "peak memory", "GB")):
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("unknowns (reaction-diffusion, 2K)")
        ax.set_ylabel(unit)
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7)
    fig.suptitle(f"numpy's arithmetic vs stencils, each in a fresh process; {result['machine']}", fontsize=9)
    fig.savefig(path, dpi=110)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--worker", nargs=3, help=argparse.SUPPRESS)
    parser.add_argument("--unknowns", type=int, nargs="+", default=list(UNKNOWNS), help="sizes (even: 2K)")
    parser.add_argument("--out", default=str(HERE / "declaring"), help="output path without suffix")
    parser.add_argument("--from-json", help="redraw the plot and table of an earlier run's JSON")
    args = parser.parse_args(argv)
    if args.from_json:
        result = json.loads(Path(args.from_json).read_text())
        plot(result, Path(args.out).with_suffix(".png"))
        print(table(result))
        return
    if args.worker:
        declaration, unknowns, path = args.worker
        Path(path).write_text(json.dumps(worker(declaration, int(unknowns))))
        return
    import daemodel

    started, records = time.monotonic(), []
    for unknowns in sorted(args.unknowns):
        record = {"unknowns": unknowns}
        for declaration in DECLARATIONS:
            print(f"{unknowns} unknowns: {declaration}", file=sys.stderr, flush=True)
            record[declaration] = run(declaration, unknowns)
        records.append(record)
    slopes = {
        f"{d} {field[:-2]}": slope([(r["unknowns"], r[d][field]) for r in records if field in r[d]])
        for d in DECLARATIONS
        for field in ("declare_s", "compile_s", "total_s", "declare_cpu_s", "compile_cpu_s", "total_cpu_s")
    }
    commit = subprocess.run(
        ["git", "-C", str(Path(daemodel.__file__).resolve().parents[1]), "rev-parse", "HEAD"],
        capture_output=True,
        text=True,
    ).stdout.strip()
    result = {
        "benchmark": "declaring and compiling: numpy's arithmetic vs stencils (issue 44)",
        "command": " ".join(["python benchmarks/declaring.py", *(sys.argv[1:] if argv is None else argv)]),
        "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
        f"load {os.getloadavg()[0]:.1f} at the end",
        "git_commit": commit,
        "total_seconds": time.monotonic() - started,
        "records": records,
        "slopes": slopes,
    }
    out = Path(args.out)
    out.with_suffix(".json").write_text(json.dumps(result, indent=1) + "\n")
    plot(result, out.with_suffix(".png"))
    print(table(result))


if __name__ == "__main__":
    main()

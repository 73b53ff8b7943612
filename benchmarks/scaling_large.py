"""Scaling to 10^5 unknowns (issue 44): declare, compile, setup, solve, wall and peak memory.

Run as ``python benchmarks/scaling.py --large [--unknowns 100 1000 ...] [--out PATH]``, or this file
directly with the same arguments.  The reaction-diffusion family of ``scaling_models.py`` (index 1,
tridiagonal, 2K unknowns: one state and one algebraic variable per grid point), declared as
``--declaration`` says (``scaling_models.DECLARATIONS``: ``stencils``, the default, ``arrays`` by
numpy's arithmetic, or ``loop``, a Python loop of ``m.ode`` and ``m.constraint``), at each size:

* ``declare`` and ``compile`` (``Model.compile()``) in one fresh process;
* ``radau`` (its default settings: adaptive, the casadi engine, ``jit="auto"``) and ``casadi-idas``
  (its default sparse linear solver), each in its own fresh process that declares and compiles the
  model again (outside every clock: nothing a process makes travels to another), at the same
  tolerances (:data:`RTOL`, :data:`ATOL`, radau's defaults), on :data:`OUTPUT_POINTS` output times:
  ``setup`` and ``solve`` are the Solution's clocks, ``wall`` their sum (every second of the
  ``dm.solve`` call: each method pays, in its own process, every one-off per model it needs, such as
  the casadi conversion both share);
* a reference (casadi-idas at :data:`REFERENCE_TOL`) in a third process, against which the max
  absolute error of each method's states and algebraic variables is measured (equal error: compare
  the error columns);
* peak memory: each process's peak resident set (``ru_maxrss``) and the one after compiling the
  model, so that the solve's own peak is their difference; radau's memory guard's estimate of its
  factors (``memory_parts``) is recorded beside it.

Growth exponents (time ~ unknowns^k) are fitted over the sizes from :data:`FIT_FROM` unknowns on.
Writes ``<out>.json`` (every number, the command, the machine) and ``<out>.png`` (log-log).
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
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

# Unknowns (2K) measured by default: 10^2 ... 10^5.
UNKNOWNS = (100, 300, 1_000, 3_000, 10_000, 30_000, 100_000)
# Tolerances of both methods: radau's defaults (IDAS's own are 1e-8 / 1e-10), the same for both.
RTOL, ATOL = 1e-6, 1e-8
# The reference: casadi-idas at this rtol (atol 1e-2 times it), 3-4 digits below the methods' error.
REFERENCE_TOL = 1e-10
# Output times on [0, 1], the same for the methods and the reference (their errors are read there).
OUTPUT_POINTS = 11
# Exponents are fitted over the sizes from this many unknowns on (below, fixed costs dominate).
FIT_FROM = 1_000
# Seconds a worker process may take before it is stopped (declaring 10^5 unknowns took ~3 minutes on
# a loaded 2-core machine).
WORKER_LIMIT = 1_800
METHODS = ("radau", "casadi-idas")
# casadi-idas is also run at these tighter rtols (atol in the same ratio), each in its own process,
# so that its solve time at radau's error can be read off its line (equal error, not equal rtol).
IDAS_TIGHTER = (1e-7, 1e-8)


def peak_rss() -> int:
    """This process's peak resident set so far, in bytes (Linux reports kilobytes)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def worker(task: dict) -> dict:
    """One task in this (fresh) process: ``build`` (declare, compile) or one method's solve."""
    import torch

    import daemodel as dm

    torch.set_num_threads(1)
    K = task["unknowns"] // 2
    began = time.perf_counter()
    model = scaling_models.DECLARATIONS[task["declaration"]](K)
    declared = time.perf_counter()
    compiled = model.compile()
    done = time.perf_counter()
    if task["job"] == "build":
        return {"declare_s": declared - began, "compile_s": done - declared, "peak_rss": peak_rss()}
    loaded = peak_rss()
    times = np.linspace(0.0, 1.0, OUTPUT_POINTS)
    rtol = task.get("rtol", RTOL)
    tol = (REFERENCE_TOL, 1e-2 * REFERENCE_TOL) if task["job"] == "reference" else (rtol, rtol * ATOL / RTOL)
    method = "casadi-idas" if task["job"] == "reference" else task["job"]
    sol = dm.solve(compiled, (0.0, 1.0), method=method, rtol=tol[0], atol=tol[1], t_eval=times)
    names = [*compiled.state_names, *compiled.algebraic_names]
    values = np.stack([np.asarray(sol[name], dtype=float) for name in names])  # (n + m, T)
    np.save(task["values"], values)
    steps = sol.stats.get("steps", sol.stats.get("nsteps"))
    out = {
        "setup_s": sol.setup_time,
        "solve_s": sol.solve_time,
        "wall_s": sol.setup_time + sol.solve_time,
        "steps": int(steps) if steps is not None else None,
        "status": sol.status,
        "peak_rss": peak_rss(),
        "rss_after_compile": loaded,
        "stats": {k: v for k, v in sol.stats.items() if isinstance(v, int | float | str) and not isinstance(v, bool)},
    }
    if method == "radau":
        from daemodel.backends.radau.backend import memory_parts
        from daemodel.backends.radau.options import RadauOptions

        out["memory_estimate"] = memory_parts(compiled, (0.0, 1.0), 1, RadauOptions(rtol=RTOL, atol=ATOL), "casadi")
    return out


def run_task(task: dict) -> dict:
    """``task`` in a fresh process with one BLAS thread: its result, or ``{"failed": message}``."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    with tempfile.TemporaryDirectory() as folder:
        result = Path(folder) / "result.json"
        command = [sys.executable, __file__, "--worker", json.dumps({**task, "result": str(result)})]
        try:
            done = subprocess.run(command, env=env, timeout=WORKER_LIMIT, capture_output=True, text=True)
        except subprocess.TimeoutExpired:
            return {"failed": f"stopped after {WORKER_LIMIT} s"}
        if done.returncode != 0 or not result.exists():
            return {"failed": (done.stderr or "")[-1500:] or f"exit code {done.returncode}"}
        return json.loads(result.read_text())


def measure(unknowns: int, folder: Path, declaration: str) -> dict:
    """Every cell at one size: build, the reference, each method, and their errors."""
    record = {"unknowns": unknowns}
    print(f"{unknowns} unknowns: declare and compile", file=sys.stderr, flush=True)
    record["build"] = run_task({"job": "build", "unknowns": unknowns, "declaration": declaration})
    if "failed" in record["build"]:
        return record
    values = {}
    cells = [(job, job, {}) for job in ("reference", *METHODS)]
    cells += [(f"casadi-idas@{rtol:g}", "casadi-idas", {"rtol": rtol}) for rtol in IDAS_TIGHTER]
    for cell, job, extra in cells:
        print(f"{unknowns} unknowns: {cell}", file=sys.stderr, flush=True)
        values[cell] = folder / f"{cell}_{unknowns}.npy"
        task = {"job": job, "unknowns": unknowns, "declaration": declaration, "values": str(values[cell]), **extra}
        record[cell] = run_task(task)
    if "failed" not in record["reference"]:
        reference = np.load(values["reference"])
        n = unknowns // 2
        for cell, _, _ in cells[1:]:
            if "failed" not in record[cell]:
                error = np.abs(np.load(values[cell]) - reference)
                record[cell]["error_y"], record[cell]["error_z"] = float(error[:n].max()), float(error[n:].max())
    record["idas_at_radau_error"] = idas_at_radau_error(record)
    return record


def idas_at_radau_error(record: dict) -> dict | None:
    """casadi-idas's solve and wall time at radau's error (the larger of its y and z errors), read off
    IDAS's line over its rtols by log-log interpolation between the two points that bracket it; outside
    the line, IDAS's time at its nearest point and ``"bound"``: ``"more than"`` (radau more accurate
    than IDAS's tightest point: IDAS needs more than that) or ``"less than"``."""
    radau = record.get("radau", {})
    line = sorted(
        (max(c["error_y"], c["error_z"]), c["solve_s"], c["wall_s"])
        for k, c in record.items()
        if k.startswith("casadi-idas") and isinstance(c, dict) and "error_y" in c
    )
    if "error_y" not in radau or len(line) < 2:
        return None
    error = max(radau["error_y"], radau["error_z"])
    if error <= line[0][0] or error >= line[-1][0]:
        _, solve, wall = line[0] if error <= line[0][0] else line[-1]
        bound = "more than" if error <= line[0][0] else "less than"
        return {"error": error, "solve_s": solve, "wall_s": wall, "bound": bound}
    (e0, s0, w0), (e1, s1, w1) = next((a, b) for a, b in itertools.pairwise(line) if a[0] <= error <= b[0])
    x = np.log(error / e0) / np.log(e1 / e0) if e1 > e0 else 0.0
    solve, wall = (float(np.exp((1 - x) * np.log(a) + x * np.log(b))) for a, b in ((s0, s1), (w0, w1)))
    return {"error": error, "solve_s": solve, "wall_s": wall, "bound": None}


def series(records: list, cell: str, field: str, per_step: bool = False) -> list:
    """(unknowns, value) of a cell's field over the sizes where it was measured."""
    out = []
    for r in records:
        c = r.get(cell) or {}
        if field in c and (not per_step or c.get("steps")):
            out.append((r["unknowns"], c[field] / c["steps"] if per_step else c[field]))
    return out


def slope(points: list) -> float | None:
    """Fitted exponent of log(value) against log(unknowns) over the sizes from :data:`FIT_FROM` on."""
    points = [(n, v) for n, v in points if n >= FIT_FROM and v > 0]
    if len(points) < 2:
        return None
    return float(np.polyfit(np.log([p[0] for p in points]), np.log([p[1] for p in points]), 1)[0])


CURVES = {  # label -> (cell, field, per step)
    "declare": ("build", "declare_s", False),
    "compile": ("build", "compile_s", False),
    **{f"{m} {what}": (m, f"{what}_s", False) for m in METHODS for what in ("setup", "solve", "wall")},
    **{f"{m} solve per step": (m, "solve_s", True) for m in METHODS},
    "casadi-idas solve at radau's error": ("idas_at_radau_error", "solve_s", False),
}


def plot(result: dict, path: Path) -> None:
    """Log-log: times (left), per-step solve time (middle), peak memory (right)."""
    from matplotlib.figure import Figure

    records, slopes = result["records"], result["slopes"]
    fig = Figure(figsize=(16, 5.2), layout="constrained")
    times, steps, memory = fig.subplots(1, 3)
    for label, (cell, field, per_step) in CURVES.items():
        points = series(records, cell, field, per_step)
        if not points:
            continue
        ax = steps if per_step else times
        fit = slopes.get(label)
        ax.loglog(*zip(*points, strict=True), marker="o", label=f"{label}" + (f" (n^{fit:.2f})" if fit else ""))
    for cell in ("build", *METHODS):
        points = [(n, v / 1e9) for n, v in series(records, cell, "peak_rss")]
        if points:
            memory.loglog(*zip(*points, strict=True), marker="o", label=f"{cell}: peak resident set")
    points = [
        (r["unknowns"], sum(r["radau"]["memory_estimate"].values()) / 1e9)
        for r in records
        if "memory_estimate" in r.get("radau", {})
    ]
    if points:
        memory.loglog(*zip(*points, strict=True), ls="--", label="radau's memory guard (its factors, outputs)")
    for ax, title, unit in (
        (times, "declare, compile, setup, solve, wall", "seconds"),
        (steps, "solve time per step", "seconds"),
        (memory, "peak memory (each in its own process)", "GB"),
    ):
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("unknowns (reaction-diffusion, 2K)")
        ax.set_ylabel(unit)
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7)
    fig.suptitle(f"daemodel at scale: rtol = {RTOL:g}, atol = {ATOL:g}; {result['machine']}", fontsize=9)
    fig.savefig(path, dpi=110)


def table(result: dict) -> str:
    """Markdown: one row per size."""
    head = (
        "| unknowns | declare | compile | radau setup | radau solve | radau wall | radau steps | radau error y/z "
        "| radau peak (GB) | IDAS setup | IDAS solve | IDAS wall | IDAS steps | IDAS error y/z | IDAS peak (GB) |"
    )
    lines = [head, "|" + "---:|" * 15]
    for r in result["records"]:
        b = r.get("build", {})
        row = [str(r["unknowns"]), f"{b.get('declare_s', float('nan')):.3g}", f"{b.get('compile_s', float('nan')):.3g}"]
        for m in METHODS:
            c = r.get(m, {})
            if "wall_s" not in c:
                row += ["failed"] + [""] * 5
                continue
            row += [f"{c['setup_s']:.3g}", f"{c['solve_s']:.3g}", f"{c['wall_s']:.3g}", str(c["steps"])]
            row += [f"{c.get('error_y', float('nan')):.1e} / {c.get('error_z', float('nan')):.1e}"]
            row += [f"{c['peak_rss'] / 1e9:.2f}"]
        lines.append("| " + " | ".join(row) + " |")
    lines += [
        "",
        "radau against casadi-idas at radau's error (IDAS's line over rtol "
        + ", ".join(f"{r:g}" for r in (RTOL, *IDAS_TIGHTER))
        + ", log-log interpolation):",
        "",
    ]
    lines += [
        "| unknowns | radau error | radau solve | IDAS solve at it | ratio | radau wall | IDAS wall at it | ratio |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in result["records"]:
        at, c = r.get("idas_at_radau_error"), r.get("radau", {})
        if not at:
            continue
        # radau more accurate than IDAS's tightest point: IDAS needs more time (">"), the ratio is a "<" bound
        idas, ratio = {"more than": (">", "<"), "less than": ("<", ">"), None: ("", "")}[at["bound"]]
        lines.append(
            f"| {r['unknowns']} | {at['error']:.1e} | {c['solve_s']:.3g} | {idas}{at['solve_s']:.3g} "
            f"| {ratio}{c['solve_s'] / at['solve_s']:.2f}x | {c['wall_s']:.3g} | {idas}{at['wall_s']:.3g} "
            f"| {ratio}{c['wall_s'] / at['wall_s']:.2f}x |"
        )
    lines += ["", "Growth exponents (fitted from " + f"{FIT_FROM} unknowns on):", ""]
    lines += [f"- {label}: {value:.2f}" for label, value in result["slopes"].items() if value is not None]
    failures = [
        (r["unknowns"], k, c["failed"])
        for r in result["records"]
        for k, c in r.items()
        if isinstance(c, dict) and "failed" in c
    ]
    lines += [f"- failed at {n}, {k}: {why[-300:]}" for n, k, why in failures]
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    parser.add_argument("--unknowns", type=int, nargs="+", default=list(UNKNOWNS), help="sizes (even: 2K)")
    parser.add_argument("--out", default=str(HERE / "scaling_large"), help="output path without suffix")
    parser.add_argument("--from-json", help="redraw the plot and table of an earlier run's JSON")
    parser.add_argument(
        "--declaration", choices=sorted(scaling_models.DECLARATIONS), default="stencils", help="how to declare"
    )
    args = parser.parse_args(argv)
    if args.worker:
        task = json.loads(args.worker)
        Path(task["result"]).write_text(json.dumps(worker(task)))
        return
    if args.from_json:
        result = json.loads(Path(args.from_json).read_text())
        plot(result, Path(args.out).with_suffix(".png"))
        print(table(result))
        return
    import platform

    import daemodel

    started = time.monotonic()
    records = []
    with tempfile.TemporaryDirectory() as folder:
        for unknowns in sorted(args.unknowns):
            records.append(measure(unknowns, Path(folder), args.declaration))
    slopes = {label: slope(series(records, *spec)) for label, spec in CURVES.items()}
    load = os.getloadavg()[0]  # (at the end: the machine is shared)
    commit = subprocess.run(
        ["git", "-C", str(Path(daemodel.__file__).resolve().parents[1]), "rev-parse", "HEAD"],
        capture_output=True,
        text=True,
    ).stdout.strip()
    result = {
        "benchmark": "scaling to 10^5 unknowns (issue 44)",
        "command": " ".join(["python benchmarks/scaling.py --large", *(sys.argv[1:] if argv is None else argv)]),
        "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, load {load:.1f}",
        "git_commit": commit,
        "settings": {
            "rtol": RTOL,
            "atol": ATOL,
            "reference_rtol": REFERENCE_TOL,
            "output_points": OUTPUT_POINTS,
            "declaration": args.declaration,
        },
        "total_seconds": time.monotonic() - started,
        "records": records,
        "slopes": slopes,
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(result, indent=1) + "\n")
    plot(result, out.with_suffix(".png"))
    print(table(result))


if __name__ == "__main__":
    main()

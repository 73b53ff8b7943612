"""Scaling benchmark (issue 12): compile, code generation and every solver against the number of unknowns.

Three model families from ``benchmarks/scaling_models.py`` at growing size: a chain of N planar
pendulums (index 3, reduced to 2; 5N unknowns), a method-of-lines reaction-diffusion grid of K
points (index 1; 2K unknowns) and P particles on a sphere with all-pairs repulsion (index 2,
dense; 8P unknowns).  For each model it measures, separately:

* ``compile``: ``m.compile()`` (building the sympy model is timed apart, as ``build``);
* ``codegen``: ``compiled.torch_functions()`` on the system radau solves (the index-2 reduction
  of the chain), so that the radau and pinn cells below measure integration only;
* ``radau_fixed``: ``method="radau"``, s = 3, fixed h; ``casadi_collocation``: same s and h;
* ``radau_adaptive``: ``rtol = atol = 1e-8`` with radau's default stages (s = 5 at that
  tolerance); ``casadi_idas``: ``rtol = atol = 1e-8`` (``benchmarks/adaptive_precision.py``
  compares the two at equal achieved error);
* ``pinn`` (with ``--pinn``): the Radau-PINN's fast mode at the same s and h;
* the achieved max absolute error of each solve against a tight reference (casadi-idas at
  ``rtol = atol = 1e-12`` on the fixed grid's times; at each family's smallest size, up to
  :data:`REFERENCE_CHECK_MAX_UNKNOWNS`, it is checked against ``method="reference"``, scipy at
  1e-12), for the states (y) and the algebraic variables (z) separately.

Clocks.  A solve's time is the :class:`~daemodel.solution.Solution`'s own integration clock
where it reports one (``solve_time``) and its ``wall_time`` otherwise (older code); a setup clock
(``setup_time``, attribute or stats entry) is recorded apart and shown as "+ setup".  The JSON
keeps them all, plus the time of the whole ``dm.solve`` call.  At a22f60f radau's
``wall_time`` excludes code generation (done in the ``codegen`` cell) while casadi's includes
building its integrator.

Limits.  Each (family, size) runs in its own process with one thread (torch, BLAS), each cell
under ``--cell-limit`` seconds (``--setup-limit`` for compile and codegen, ``--pinn-limit`` for
the PINN; SIGALRM, and the process's own timeout as a backstop).  radau's fixed step is first
run for :data:`PROBE_STEPS` steps and skipped (adaptive radau with it) when the projected time
exceeds :data:`PROJECTION_MARGIN` times the limit; a cell that ran past its limit is not tried
at larger sizes of its family.  Failures are recorded with their message; nothing stops the
benchmark.

Writes ``<out>.json`` (all raw numbers, machine information, torch threads) and ``<out>.png``
(log-log time against unknowns, one panel per family, growth exponents fitted to the largest
sizes in the legend) and prints markdown tables.

``--large`` runs ``benchmarks/scaling_large.py`` instead (issue 44): reaction-diffusion from 10^2 to
10^5 unknowns, declare, compile, setup, solve, wall and peak memory of radau and casadi-idas at their
defaults, each in a fresh process (``python benchmarks/scaling.py --large [--unknowns ...]``).

Run: python benchmarks/scaling.py [--quick] [--pinn] [--cell-limit 60] [--setup-limit 60] [--budget 1800]
     [--families ...] [--chain 2 4 ...] [--grid ...] [--particles ...] [--out PATH] [--from-json PATH]
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import functools
import json
import math
import os
import platform
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))  # scaling_models, when run from elsewhere or as a worker

import scaling_models  # noqa: E402

# Radau IIA stages of radau, casadi-collocation and pinn: the paper's s = 3 (order 5).
STAGES = 3
# Fixed step of radau, casadi-collocation and pinn: 20 steps over each family's unit interval,
# the step of the tables in docs/benchmarks/scaling.md; every family stays within the local-error bound at it.
STEP = 0.05
# Tolerance of both adaptive methods (rtol = atol): the comparison point.
ADAPTIVE_TOL = 1e-8
# Tolerance of the reference (casadi-idas, rtol = atol): 4 digits below the adaptive methods.
REFERENCE_TOL = 1e-12
# Default sizes of each family: the table rows and the 160-unknown dense system.
SIZES = {
    "pendulum_chain": [2, 4, 8, 16, 32],
    "reaction_diffusion": [10, 30, 100, 300],
    "sphere_particles": [5, 10, 20],
}
# --quick: the sizes that each take seconds, not minutes, on a 2-core machine.
QUICK_SIZES = {
    "pendulum_chain": [2, 4, 8],
    "reaction_diffusion": [10, 30, 100],
    "sphere_particles": [5, 10],
}
# Per-cell limit in seconds (default and --quick): a minute keeps the full run near 15 minutes.
CELL_LIMIT = 60.0
QUICK_CELL_LIMIT = 30.0
# Whole run's budget in seconds; (family, size) pairs not started by then are recorded as skipped.
BUDGET = 1800.0
# radau's fixed step is first run for this many steps to project the full run's time (the first
# step pays torch's warm-up, so one step would over-project).
PROBE_STEPS = 2
# The probe's steps carry torch's warm-up and the first, longer Newton solves: on small models it
# projected up to 6x the real time, so a cell is skipped only beyond this factor times the limit
# (the limit's alarm stops the rest).
PROJECTION_MARGIN = 2.0
# Repeat a solve (best of --repeats) only when one run took less than this: cheap cells are the
# noisy ones, and repeating an expensive one would spend the budget on nothing new.
REPEAT_BELOW = 1.0
# Sizes used to fit a growth exponent: the largest this many with a measured time (at least 2).
FIT_POINTS = 3
# A worker process gets this many seconds beyond the sum of its cells' limits before it is
# stopped (process start, imports, the reference check).
WORKER_MARGIN = 60.0
# The scipy reference check runs at each family's smallest size only up to this many unknowns: it
# solves for z by Newton in Python at every right-hand-side call (minutes at hundreds of unknowns).
REFERENCE_CHECK_MAX_UNKNOWNS = 100
# Error messages are kept up to this many characters (casadi's can quote whole input dumps).
MESSAGE_CHARS = 1500
# Timing fields a Solution may carry (issue 12 asks every backend to report setup apart from
# integration); read by name where present, so the benchmark runs on code before and after.
INTEGRATION_FIELDS, SETUP_FIELD = ("solve_time", "integration_time"), "setup_time"

# Cells of one (family, size), in the order they run: key -> (label in tables and plot, method, options).
SOLVES = {
    "radau_fixed": ("radau fixed", "radau", {"stages": STAGES, "h": STEP}),
    "casadi_collocation": ("casadi-collocation", "casadi-collocation", {"stages": STAGES, "h": STEP}),
    "radau_adaptive": (f"radau adaptive {ADAPTIVE_TOL:g}", "radau", {"rtol": ADAPTIVE_TOL, "atol": ADAPTIVE_TOL}),
    "casadi_idas": (f"casadi-idas {ADAPTIVE_TOL:g}", "casadi-idas", {"rtol": ADAPTIVE_TOL, "atol": ADAPTIVE_TOL}),
    "pinn": ("pinn (fast mode)", "pinn", {}),
}
SETUP_CELLS = {"compile": "compile", "codegen": "torch codegen"}
LABELS = {**SETUP_CELLS, **{key: label for key, (label, _, _) in SOLVES.items()}}
# Cells that need the torch functions of the codegen cell (otherwise they would time code generation).
NEEDS_CODEGEN = ("radau_fixed", "radau_adaptive", "pinn")
# Solves given output times (the fixed grid) so that they compare with the reference point by point.
WITH_T_EVAL = ("radau_adaptive", "casadi_idas")


class CellTimeout(BaseException):
    """A cell ran past its limit.  A BaseException, like KeyboardInterrupt, so that no library
    ``except Exception`` on the way (Newton's, casadi's) mistakes it for a solver failure."""


def message(error: BaseException) -> str:
    """``Type: text`` of an exception, clipped to :data:`MESSAGE_CHARS`."""
    text = f"{type(error).__name__}: {error}"
    return text if len(text) <= MESSAGE_CHARS else text[: MESSAGE_CHARS - 3] + "..."


def _alarm(signum, frame):
    raise CellTimeout


@contextlib.contextmanager
def time_limit(seconds: float):
    """Raise :class:`CellTimeout` in the block after ``seconds`` (checked between Python bytecodes:
    a long casadi call ends before it is noticed; the worker's process timeout is the backstop)."""
    previous = signal.signal(signal.SIGALRM, _alarm)
    signal.setitimer(signal.ITIMER_REAL, max(seconds, 1e-3))
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def attempt(limit: float, job):
    """``job()`` under ``limit`` seconds: ``(status, value, seconds, message)``, status "ok",
    "timeout" or "failed" (any exception, its message recorded)."""
    began = time.perf_counter()
    try:
        with time_limit(limit):
            value = job()
    except CellTimeout:
        return "timeout", None, time.perf_counter() - began, f"did not finish in {limit:g} s (its limit)"
    except Exception as error:  # recorded, never raised: one failing cell must not stop the benchmark
        return "failed", None, time.perf_counter() - began, message(error)
    return "ok", value, time.perf_counter() - began, None


def scalar_stats(stats: dict) -> dict:
    """The JSON-ready scalar entries of a Solution's stats (lists per segment are dropped)."""
    out = {}
    for key, value in stats.items():
        if isinstance(value, bool | int | str) or value is None:
            out[key] = value
        elif isinstance(value, float | np.floating | np.integer):
            out[key] = float(value) if math.isfinite(float(value)) else str(value)
    return out


def solution_clock(sol) -> tuple[float, str, float | None]:
    """``(seconds, clock name, setup seconds or None)`` of a Solution: its integration clock where
    it has one (``solve_time``; attribute or stats entry), else ``wall_time`` (older code); its
    setup clock where it has one."""

    def field(name):
        value = getattr(sol, name, None)
        value = sol.stats.get(name) if value is None else value
        return float(value) if isinstance(value, int | float) and math.isfinite(value) else None

    setup = field(SETUP_FIELD)
    for name in INTEGRATION_FIELDS:
        if field(name) is not None:
            return field(name), name, setup
    return float(sol.wall_time), "wall_time", setup


def max_errors(sol, reference, compiled) -> dict:
    """Max absolute error of the states (y) and algebraic variables (z) against ``reference``."""
    per = sol.errors(reference, names=[*compiled.state_names, *compiled.algebraic_names])

    def worst(names):
        if not names:
            return None, None
        name = max(names, key=lambda n: per[n]["max"])
        return per[name]["max"], name

    (y, y_name), (z, z_name) = worst(compiled.state_names), worst(compiled.algebraic_names)
    return {"y": y, "z": z, "worst_y": y_name, "worst_z": z_name}


# ---- worker: one (family, size) ----------------------------------------------------------
def run_worker(spec: dict) -> None:
    """Measure every cell of one (family, size) and write the record to ``spec["out"]`` after each cell."""
    import torch

    import daemodel as dm

    torch.set_num_threads(1)
    family, size, limit, setup_limit = spec["family"], spec["size"], spec["cell_limit"], spec["setup_limit"]
    blocked, out = spec["blocked"], Path(spec["out"])
    t_span = scaling_models.T_SPAN[family]
    grid = t_span[0] + STEP * np.arange(round((t_span[1] - t_span[0]) / STEP) + 1)
    grid[-1] = t_span[1]
    record = {
        "family": family,
        "size": size,
        "unknowns": scaling_models.unknowns(family, size),
        "t_span": list(t_span),
        "torch_threads": torch.get_num_threads(),
        "cells": {},
    }
    cells = record["cells"]

    def save() -> None:
        tmp = out.with_suffix(".tmp")
        tmp.write_text(json.dumps(record, indent=1))
        tmp.replace(out)

    def note(key: str, cell: dict) -> None:
        cells[key] = cell
        save()
        shown = f"{cell['time_s']:.3g} s" if cell.get("time_s") is not None else ""
        print(
            f"  {family}({size}) {LABELS.get(key, key):<26} {cell['status']:<8} {shown:>10}  "
            f"{cell.get('message') or cell.get('reason') or ''}"[:220],
            file=sys.stderr,
            flush=True,
        )

    def skip(key: str, reason: str, **extra) -> None:
        note(key, {"status": "skipped", "reason": reason, **extra})

    # build and compile
    status, model, seconds, msg = attempt(limit, lambda: scaling_models.FAMILIES[family](size))
    note("build", {"status": status, "time_s": seconds, "message": msg})
    if status != "ok":
        for key in ("compile", "codegen", "reference", *spec["solves"]):
            skip(key, "the model could not be built")
        return
    if "compile" in blocked:
        skip("compile", blocked["compile"])
    else:
        status, compiled, seconds, msg = attempt(setup_limit, model.compile)
        note("compile", {"status": status, "time_s": seconds, "message": msg, "limit_s": setup_limit})
    if cells["compile"]["status"] != "ok":
        for key in ("codegen", "reference", *spec["solves"]):
            skip(key, "needs compile, which did not complete")
        return
    record.update(
        n_states=len(compiled.states),
        n_algebraics=len(compiled.algebraics),
        index=compiled.index,
        parameters=dict(zip(compiled.parameter_names, map(float, compiled.parameter_values), strict=True)),
    )
    # the system radau, collocation and pinn solve: dm.solve would reduce an index-3 model on
    # every call (with an empty code cache), so it is reduced once here and passed to every solve
    began = time.perf_counter()
    system = compiled.reduced(2) if compiled.index > 2 else compiled
    record["reduce_s"] = time.perf_counter() - began

    if "codegen" in blocked:
        skip("codegen", blocked["codegen"])
    else:
        status, _, seconds, msg = attempt(setup_limit, system.torch_functions)
        note("codegen", {"status": status, "time_s": seconds, "message": msg, "limit_s": setup_limit})
    codegen_ok = cells["codegen"]["status"] == "ok"

    # the reference on the fixed grid's times
    status, reference, seconds, msg = attempt(
        limit,
        lambda: dm.solve(system, t_span, method="casadi-idas", rtol=REFERENCE_TOL, atol=REFERENCE_TOL, t_eval=grid),
    )
    note(
        "reference",
        {
            "status": status,
            "method": "casadi-idas",
            "rtol": REFERENCE_TOL,
            "time_s": seconds,
            "message": msg,
            "stats": scalar_stats(reference.stats) if reference is not None else None,
        },
    )
    if spec["check_reference"] and reference is not None:
        status, scipy_ref, seconds, msg = attempt(
            limit, lambda: dm.solve(system, t_span, method="reference", t_eval=grid)
        )
        check = {"status": status, "method": "reference (scipy, 1e-12)", "time_s": seconds, "message": msg}
        if scipy_ref is not None:
            check.update(max_errors(reference, scipy_ref, system))
        note("reference_check", check)

    # radau fixed's full time, measured or projected: adaptive radau at 1e-8 takes more steps than
    # the fixed grid (2-8x in the runs so far), so it is not tried when this already exceeds the limit
    fixed_estimate = None
    for key in spec["solves"]:
        _, method, options = SOLVES[key]
        if key in blocked:
            skip(key, blocked[key])
            continue
        if key in NEEDS_CODEGEN and not codegen_ok:
            skip(key, "needs torch code generation, which did not complete (its time would land in this cell)")
            continue
        options = dict(options)
        if key == "pinn":
            options = {"config": dm.PINNConfig(stages=STAGES, h=STEP), "progress": False}
        if key in WITH_T_EVAL:
            options["t_eval"] = grid
        cell_limit = spec["pinn_limit"] if key == "pinn" else limit
        cell = {"method": method, "options": {k: v for k, v in options.items() if k not in ("t_eval", "config")}}
        if key == "radau_fixed":
            probe_span = (t_span[0], t_span[0] + PROBE_STEPS * STEP)
            status, sol, seconds, msg = attempt(
                cell_limit, functools.partial(dm.solve, system, probe_span, method=method, **options)
            )
            if status != "ok":
                fixed_estimate = math.inf if status == "timeout" else None
                msg = f"in the {PROBE_STEPS}-step probe: {msg}"
                note(key, {**cell, "status": status, "message": msg, "limit_s": cell_limit})
                continue
            cell["projected_s"] = solution_clock(sol)[0] / PROBE_STEPS * (len(grid) - 1)
            if cell["projected_s"] > PROJECTION_MARGIN * cell_limit:
                fixed_estimate = cell["projected_s"] / PROJECTION_MARGIN
                reason = (
                    f"projected {cell['projected_s']:.3g} s from {PROBE_STEPS} steps, over "
                    f"{PROJECTION_MARGIN:g} x the {cell_limit:g} s limit"
                )
                skip(key, reason, projected_s=cell["projected_s"], over_limit=True)
                continue
        if key == "radau_adaptive" and fixed_estimate is not None and fixed_estimate > cell_limit:
            reason = (
                f"radau's fixed {len(grid) - 1} steps {'did not finish' if math.isinf(fixed_estimate) else 'take'}"
                + ("" if math.isinf(fixed_estimate) else f" ~{fixed_estimate:.3g} s")
                + f" and adaptive steps at rtol {ADAPTIVE_TOL:g} are more: over the {cell_limit:g} s limit"
            )
            skip(key, reason, over_limit=True)
            continue
        runs, sol = [], None
        for _ in range(spec["repeats"]):
            status, result, call_s, msg = attempt(
                cell_limit, functools.partial(dm.solve, system, t_span, method=method, **options)
            )
            if status != "ok":
                break
            sol = result
            seconds, clock, setup = solution_clock(result)
            runs.append({"time_s": seconds, "call_s": call_s, "setup_s": setup})
            if seconds >= REPEAT_BELOW:
                break
        if sol is None:
            if key == "radau_fixed":
                fixed_estimate = math.inf if status == "timeout" else None
            note(key, {**cell, "status": status, "message": msg, "limit_s": cell_limit})
            continue
        best = min(runs, key=lambda r: r["time_s"])
        if key == "radau_fixed":
            fixed_estimate = best["time_s"]
        cell.update(status="ok", clock=clock, runs=runs, **best)
        cell["stats"] = scalar_stats(sol.stats)
        cell["solution_status"] = sol.status
        cell["output_times"] = len(sol.t)
        if reference is None:
            cell["errors"] = None
            cell["errors_message"] = "no reference: " + (cells["reference"].get("message") or "")
        else:
            try:
                cell["errors"] = max_errors(sol, reference, system)
            except Exception as error:  # recorded: a comparison that cannot be made is a result too
                cell["errors"], cell["errors_message"] = None, message(error)
        note(key, cell)


# ---- driver ------------------------------------------------------------------------------
def machine_info(code_label: str | None) -> dict:
    """Where and on what the numbers were measured."""
    import casadi
    import sympy
    import torch

    import daemodel

    cpu = platform.processor() or platform.machine()
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    root = Path(daemodel.__file__).resolve().parent.parent
    git = {}
    for key, command in (
        ("commit", ["rev-parse", "HEAD"]),
        ("changes", ["status", "--porcelain", "--", "daemodel", "backends"]),
    ):
        try:
            done = subprocess.run(["git", "-C", str(root), *command], capture_output=True, text=True, timeout=10)
            git[key] = done.stdout.strip() if done.returncode == 0 else None
        except (OSError, subprocess.SubprocessError) as error:
            git[key] = None
            git["git_error"] = message(error)
    return {
        "cpu": cpu,
        "cpu_count": os.cpu_count(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "torch_threads": 1,
        "blas_threads": 1,
        "casadi": casadi.__version__,
        "sympy": sympy.__version__,
        "numpy": np.__version__,
        "daemodel_code": str(root),
        "code_label": code_label,
        "git_commit": git.get("commit"),
        "git_changes_in_daemodel_and_backends": git.get("changes"),
        "load_average_at_start": list(os.getloadavg()),
    }


def run_worker_process(script: str, spec: dict, timeout: float) -> tuple[dict, int | None, float]:
    """``python script --worker spec`` with one BLAS thread, under ``timeout`` seconds.

    The worker writes its record to ``spec["out"]`` as it goes.  Returns that record (``{}`` if it
    wrote none), the worker's exit code (None when it was stopped at the timeout) and its seconds.
    """
    # read by the BLAS libraries when numpy loads: set for the worker before it starts
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    began = time.monotonic()
    try:
        code = subprocess.run(
            [sys.executable, script, "--worker", json.dumps(spec)], env=env, timeout=timeout
        ).returncode
    except subprocess.TimeoutExpired:
        code = None
    out = Path(spec["out"])
    return (json.loads(out.read_text()) if out.exists() else {}), code, time.monotonic() - began


def run_size(family: str, size: int, args, blocked: dict, solves: list, check_reference: bool, deadline: float) -> dict:
    """One worker process for (family, size); its record, completed for cells it could not report."""
    cell_count = 3 + len(solves) + check_reference
    ceiling = (
        args.cell_limit * cell_count
        + 2 * (args.setup_limit - args.cell_limit)
        + (args.pinn_limit - args.cell_limit) * ("pinn" in solves)
        + WORKER_MARGIN
    )
    timeout = max(1.0, min(ceiling, deadline - time.monotonic() + WORKER_MARGIN))
    with tempfile.TemporaryDirectory() as folder:
        out = Path(folder) / "record.json"
        spec = {
            "family": family,
            "size": size,
            "cell_limit": args.cell_limit,
            "pinn_limit": args.pinn_limit,
            "setup_limit": args.setup_limit,
            "repeats": args.repeats,
            "solves": solves,
            "blocked": blocked,
            "check_reference": check_reference,
            "out": str(out),
        }
        record, code, seconds = run_worker_process(__file__, spec, timeout)
    timed_out = code is None
    if timed_out:
        ended = f"the worker process was stopped after {timeout:.0f} s (a cell did not return to honour its limit)"
    else:
        ended = f"the worker process exited with code {code} before reporting this cell"
    record.setdefault("family", family)
    record.setdefault("size", size)
    record.setdefault("unknowns", scaling_models.unknowns(family, size))
    record["worker_seconds"] = seconds
    cells = record.setdefault("cells", {})
    for key in ("build", "compile", "codegen", "reference", *solves):
        if key not in cells:
            cells[key] = {"status": "timeout" if timed_out else "failed", "message": ended}
    return record


def block_larger(record: dict, blocked: dict) -> None:
    """Cells that ran past the limit at this size are not tried at larger sizes of the family."""
    for key, cell in record["cells"].items():
        if key not in blocked and (cell.get("over_limit") or cell["status"] == "timeout"):
            why = cell.get("message") or cell.get("reason") or "over the limit"
            blocked[key] = f"not tried: over the limit at size {record['size']} ({record['unknowns']} unknowns): {why}"


def growth_exponents(records: list, key: str) -> dict | None:
    """Slope of log(time) against log(unknowns) over the largest :data:`FIT_POINTS` measured sizes."""
    points = [
        (r["unknowns"], r["cells"][key]["time_s"])
        for r in records
        if key in r["cells"] and r["cells"][key]["status"] == "ok" and r["cells"][key].get("time_s")
    ]
    points = sorted(points)[-FIT_POINTS:]
    if len(points) < 2:
        return None
    x, y = np.log([p[0] for p in points]), np.log([p[1] for p in points])
    slope = float(np.polyfit(x, y, 1)[0])
    return {"exponent": slope, "unknowns": [p[0] for p in points]}


def main(argv=None) -> None:
    argv = sys.argv[1:] if argv is None else list(argv)
    if "--large" in argv:  # issue 44: 10^2 ... 10^5 unknowns, radau against casadi-idas (scaling_large.py)
        import scaling_large

        scaling_large.main([a for a in argv if a != "--large"])
        return
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    parser.add_argument("--quick", action="store_true", help="small sizes, 30 s cell limit, one repeat")
    parser.add_argument("--chain", type=int, nargs="+", help="pendulum-chain sizes N (default 2 4 8 16 32)")
    parser.add_argument("--grid", type=int, nargs="+", help="reaction-diffusion sizes K (default 10 30 100 300)")
    parser.add_argument("--particles", type=int, nargs="+", help="sphere-particle sizes P (default 5 10 20)")
    parser.add_argument("--cell-limit", type=float, help=f"seconds per cell (default {CELL_LIMIT:g}, quick 30)")
    parser.add_argument("--budget", type=float, default=BUDGET, help="seconds for the whole run (default %(default)s)")
    parser.add_argument("--pinn", action="store_true", help="also train the Radau-PINN (fast mode)")
    parser.add_argument("--pinn-limit", type=float, help="seconds for a pinn cell (default: the cell limit)")
    parser.add_argument(
        "--setup-limit", type=float, help="seconds for compile and for codegen each (default: the cell limit)"
    )
    parser.add_argument(
        "--families", nargs="+", choices=list(SIZES), default=list(SIZES), help="families to run (default: all)"
    )
    parser.add_argument("--repeats", type=int, help="best of this many runs for solves under 1 s (default 3, quick 1)")
    parser.add_argument("--out", default=str(HERE / "scaling"), help="output path without suffix (default %(default)s)")
    parser.add_argument("--code-label", help="free text recorded with the machine (e.g. which commit was measured)")
    parser.add_argument("--from-json", help="redraw the plot and tables of an earlier run's JSON (written to --out)")
    args = parser.parse_args(argv)
    if args.worker:
        run_worker(json.loads(args.worker))
        return
    if args.from_json:
        result = json.loads(Path(args.from_json).read_text())
        plot(result, Path(args.out).with_suffix(".png"))
        print(tables(result))
        return

    import torch

    torch.set_num_threads(1)
    args.cell_limit = args.cell_limit or (QUICK_CELL_LIMIT if args.quick else CELL_LIMIT)
    args.pinn_limit = args.pinn_limit or args.cell_limit
    args.setup_limit = args.setup_limit or args.cell_limit
    args.repeats = args.repeats or (1 if args.quick else 3)
    base = QUICK_SIZES if args.quick else SIZES
    given = {"pendulum_chain": args.chain, "reaction_diffusion": args.grid, "sphere_particles": args.particles}
    sizes = {family: given[family] or base[family] for family in SIZES if family in args.families}
    solves = [key for key in SOLVES if key != "pinn" or args.pinn]
    started = time.monotonic()
    deadline = started + args.budget
    info = machine_info(args.code_label)
    print(f"daemodel code: {info['daemodel_code']} ({info['code_label'] or info['git_commit']})", file=sys.stderr)

    # interleave the families, smallest sizes first, so that a spent budget cuts the largest sizes of all
    order = sorted(
        ((rank, family, size) for family, values in sizes.items() for rank, size in enumerate(sorted(values))),
        key=lambda item: (item[0], list(sizes).index(item[1])),
    )
    blocked = {family: {} for family in sizes}
    records = []
    for rank, family, size in order:
        if time.monotonic() >= deadline:
            cells = {
                key: {"status": "skipped", "reason": f"the run's budget of {args.budget:g} s was spent"}
                for key in ("compile", "codegen", *solves)
            }
            records.append(
                {"family": family, "size": size, "unknowns": scaling_models.unknowns(family, size), "cells": cells}
            )
            continue
        print(f"{family}({size}): {scaling_models.unknowns(family, size)} unknowns", file=sys.stderr, flush=True)
        check = rank == 0 and scaling_models.unknowns(family, size) <= REFERENCE_CHECK_MAX_UNKNOWNS
        record = run_size(family, size, args, dict(blocked[family]), solves, check, deadline)
        block_larger(record, blocked[family])
        records.append(record)

    records.sort(key=lambda r: (list(sizes).index(r["family"]), r["size"]))
    exponents = {
        family: {key: growth_exponents([r for r in records if r["family"] == family], key) for key in LABELS}
        for family in sizes
    }
    result = {
        "benchmark": "scaling (issue 12)",
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "machine": {**info, "load_average_at_end": list(os.getloadavg())},
        "settings": {
            "stages": STAGES,
            "h": STEP,
            "adaptive_rtol_atol": ADAPTIVE_TOL,
            "reference": f"casadi-idas, rtol = atol = {REFERENCE_TOL:g}, on the fixed grid's times",
            "cell_limit_s": args.cell_limit,
            "pinn_limit_s": args.pinn_limit if args.pinn else None,
            "setup_limit_s": args.setup_limit,
            "budget_s": args.budget,
            "repeats": args.repeats,
            "repeat_below_s": REPEAT_BELOW,
            "probe_steps": PROBE_STEPS,
            "quick": args.quick,
            "sizes": sizes,
            "t_span": scaling_models.T_SPAN,
            "dtype": "float64",
        },
        "total_seconds": time.monotonic() - started,
        "records": records,
        "growth_exponents": exponents,
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(result, indent=1) + "\n")
    plot(result, out.with_suffix(".png"))
    print(tables(result))
    print(f"\nwrote {out.with_suffix('.json')} and {out.with_suffix('.png')} in {result['total_seconds']:.0f} s")


# ---- output ------------------------------------------------------------------------------
def time_text(cell: dict | None) -> str:
    """A table cell: the time, or why there is none."""
    if cell is None:
        return ""
    if cell["status"] == "ok":
        setup = cell.get("setup_s")
        return f"{cell['time_s']:.3g} s" + (f" (+ {setup:.2g} s setup)" if setup else "")
    if cell["status"] == "timeout":
        return f"> {cell['limit_s']:g} s" if cell.get("limit_s") else "did not finish"
    if cell["status"] == "failed":
        return "failed"
    if cell.get("projected_s") is not None:
        return f"skipped (~{cell['projected_s']:.3g} s projected)"
    return "skipped"


def error_text(cell: dict | None) -> str:
    """A table cell: max error of y and z, or nothing."""
    if not cell or cell["status"] != "ok" or not cell.get("errors"):
        return ""
    e = cell["errors"]
    text = f"{e['y']:.1e}" + ("" if e["z"] is None else f" / {e['z']:.1e}")
    if "rtol" in cell.get("options", {}):  # adaptive: the steps it took (radau "steps", IDAS "nsteps")
        stats = cell.get("stats", {})
        steps = stats.get("steps", stats.get("nsteps"))
        text += f" ({steps} steps)" if steps is not None else ""
    return text


def tables(result: dict) -> str:
    """Markdown: times, errors, growth exponents, and every failure's message."""
    solves = [k for k in SOLVES if any(k in r["cells"] for r in result["records"])]
    timed = [*SETUP_CELLS, *solves]
    head = "| model | unknowns | " + " | ".join(LABELS[k] for k in timed) + " |"
    lines = [
        f"### Time (s = {STAGES}, h = {STEP:g}; adaptive at rtol = atol = {ADAPTIVE_TOL:g}, radau's default stages)",
        "",
        head,
    ]
    lines.append("|---|---:|" + "---:|" * len(timed))
    for r in result["records"]:
        row = [time_text(r["cells"].get(k)) for k in timed]
        lines.append(f"| {r['family']} {r['size']} | {r['unknowns']} | " + " | ".join(row) + " |")
    lines += ["", "### Max error against the reference: y / z (steps of adaptive methods)", ""]
    lines.append("| model | unknowns | " + " | ".join(LABELS[k] for k in solves) + " |")
    lines.append("|---|---:|" + "---:|" * len(solves))
    for r in result["records"]:
        row = [error_text(r["cells"].get(k)) for k in solves]
        lines.append(f"| {r['family']} {r['size']} | {r['unknowns']} | " + " | ".join(row) + " |")
    checks = [(r, r["cells"]["reference_check"]) for r in result["records"] if "reference_check" in r["cells"]]
    if checks:
        lines += ["", "Reference check (casadi-idas 1e-12 against scipy's `reference` at 1e-12, max difference y / z):"]
        for r, c in checks:
            got = f"{c['y']:.1e} / {c['z']:.1e}" if c["status"] == "ok" else f"{c['status']}: {c.get('message')}"
            lines.append(f"- {r['family']} {r['size']}: {got}")
    lines += ["", "### Growth exponents (time ~ unknowns^k, fitted to the largest measured sizes)", ""]
    lines.append("| family | " + " | ".join(LABELS[k] for k in timed) + " |")
    lines.append("|---|" + "---:|" * len(timed))
    for family, fits in result["growth_exponents"].items():
        row = [f"{fits[k]['exponent']:.2f}" if fits.get(k) else "" for k in timed]
        lines.append(f"| {family} | " + " | ".join(row) + " |")
    problems = [
        (r, k, c) for r in result["records"] for k, c in r["cells"].items() if c["status"] in ("failed", "timeout")
    ]
    problems += [
        (r, k + " errors", {"message": c["errors_message"]})
        for r in result["records"]
        for k, c in r["cells"].items()
        if c.get("errors_message")
    ]
    if problems:
        lines += ["", "### Failures and time-outs", ""]
        lines += [f"- {r['family']} {r['size']}, {LABELS.get(k, k)}: {c.get('message')}" for r, k, c in problems]
    skipped = [(r, k, c) for r in result["records"] for k, c in r["cells"].items() if c["status"] == "skipped"]
    if skipped:
        lines += ["", "### Skipped", ""]
        lines += [
            f"- {r['family']} {r['size']}, {LABELS.get(k, k)}: {c.get('reason') or c.get('message')}"
            for r, k, c in skipped
        ]
    return "\n".join(lines)


def plot(result: dict, path: Path) -> None:
    """Log-log time against unknowns, one panel per family, one line per cell.

    Hollow markers: over the limit, at the projected time (radau's probe) or at the limit for a
    cell stopped there (a lower bound).
    """
    from matplotlib.figure import Figure
    from matplotlib.ticker import NullFormatter

    families = list(result["settings"]["sizes"])
    fig = Figure(figsize=(5.2 * len(families), 5.6), layout="constrained")
    axes = fig.subplots(1, len(families), squeeze=False)[0]
    keys = [*SETUP_CELLS, *SOLVES]
    markers = dict(zip(keys, "os^vDPX", strict=True))
    colors = {key: f"C{i}" for i, key in enumerate(keys)}
    for ax, family in zip(axes, families, strict=True):
        records = [r for r in result["records"] if r["family"] == family]
        for key in keys:
            done, over = [], []
            for r in records:
                cell = r["cells"].get(key, {})
                if cell.get("status") == "ok":
                    done.append((r["unknowns"], cell["time_s"]))
                elif cell.get("status") == "timeout" and cell.get("limit_s"):
                    over.append((r["unknowns"], cell["limit_s"]))
                elif cell.get("over_limit") and cell.get("projected_s"):
                    over.append((r["unknowns"], cell["projected_s"]))
            if not done and not over:
                continue
            fit = result["growth_exponents"][family].get(key)
            label = LABELS[key] + (f"  (n^{fit['exponent']:.2f})" if fit else "")
            if done:
                ax.loglog(*zip(*done, strict=True), marker=markers[key], color=colors[key], label=label)
            if over:
                ax.loglog(
                    *zip(*over, strict=True),
                    marker=markers[key],
                    color=colors[key],
                    ls="none",
                    mfc="none",
                    label=None if done else f"{label} (over the limit)",
                )
        ax.axhline(result["settings"]["cell_limit_s"], color="0.6", lw=0.8, ls=":")
        index = next((r["index"] for r in records if r.get("index")), None)
        ax.set_title(f"{family}" + (f" (index {index})" if index else ""), fontsize=10)
        sizes = sorted({r["unknowns"] for r in records})
        ax.set_xticks(sizes, [str(n) for n in sizes])
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_xlabel("unknowns (states + algebraic variables)")
        ax.set_ylabel("seconds")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=2)  # below: never on the data
    machine = result["machine"]
    fig.suptitle(
        f"daemodel scaling: s = {STAGES}, h = {STEP}, adaptive rtol = {ADAPTIVE_TOL:g}; torch on 1 thread; "
        f"{machine['cpu']} ({machine['cpu_count']} cores); hollow: over the "
        f"{result['settings']['cell_limit_s']:g} s limit (projected, or the limit)",
        fontsize=9,
    )
    fig.savefig(path, dpi=120)


if __name__ == "__main__":
    main()

"""Work-precision benchmark (issue 26): adaptive radau against casadi-idas at equal achieved error.

The issue's targets: adaptive ``method="radau"`` (its default stages) no slower than
``method="casadi-idas"`` at the same *achieved* error wherever that error is 1e-6 or below, and
within 2x of it above (:data:`TARGETS`).  The problems: the Test Set problems of
``daemodel.problems.PROBLEMS`` named in :data:`PROBLEM_NAMES`, each over its own ``t_span``, and
the families of ``benchmarks/scaling_models.py`` at about 100 and 200 unknowns
(:data:`FAMILY_SIZES`), over their ``T_SPAN``.  Each is compiled once (``model().compile()``) and
solved with::

    dm.solve(compiled, t_span, method=..., rtol=tol, atol=tol, t_eval=grid)   # grid: 21 equal times

* radau with no ``stages`` argument (the stages its default picks from rtol are recorded from its
  stats) at rtol = atol in :data:`RADAU_TOLS`; casadi-idas at :data:`IDAS_TOLS`, one decade
  looser and two tighter so that its curve covers radau's errors.  A method's tighter tolerances are skipped once
  one of its solves failed or its integration took more than ``--solve-limit`` seconds; failures
  are recorded with their message.
* Error: for each variable, the max over the 21 times of |value - reference| divided by the
  variable's own peak |reference| over those times (1 where the peak is 0); a solve's state error
  is the largest over the states, its algebraic error, reported apart, the largest over the
  algebraic variables (:func:`peak_relative_error`).  Peak-relative, so that a small component
  (Robertson's y2, about 4e-5) counts as much as a large one.
* Reference: radau with s = :data:`REFERENCE_STAGES` at rtol = atol = 1e-13 (the next looser of
  :data:`REFERENCE_TOLS` where it fails), cross-checked with casadi-idas at
  :data:`IDAS_REFERENCE_TOL`.  Their difference, in the same measure, is the reference's
  uncertainty; an error below :data:`UNRESOLVED_FACTOR` times it is flagged unresolved (it
  measures the reference as much as the method).
* Clock: ``sol.solve_time`` (integration only); ``sol.setup_time`` is recorded apart.  Each solve
  is timed in ``--passes`` interleaved passes (pass 1 runs every problem, method and tolerance
  once, then pass 2, ...) and keeps its minimum.  In every pass each method's first timed solve of
  a problem follows one untimed solve of that method on that problem (its loosest tolerance), for
  both methods alike: without it the first timed point of each problem carried the previous
  problem's cache misses, radau's loosest tolerance for radau (measured: the pendulum at rtol 1e-4
  0.56 ms in the sweep, 0.27 ms warm; both methods about double after a 20 MB cache flush) and a
  point outside the compared range for IDAS.  One thread: the worker process starts with
  OMP/OPENBLAS/MKL_NUM_THREADS = 1 and sets torch to one thread wherever something imported it.
* Equal-error ratio: each radau point's time over IDAS's time at radau's achieved state error,
  read off IDAS's sweep by ``adaptive_precision.time_at_error`` (log-log interpolation on the
  monotone envelope of its points; outside IDAS's range a bound, ``<`` or ``>``, never an
  extrapolation).  Per problem: the worst ratio over radau's points with state error <= 1e-6 and
  the worst over those above (:func:`worst_ratio`), each beside its target.
* Fixed step (a second, small section): reaction_diffusion K = 50, ``method="radau"`` against
  ``method="casadi-collocation"`` at the same ``h`` (:data:`FIXED_STEPS`) and ``stages = 3``,
  same passes; the ratio radau / collocation.

Writes ``<out>.json`` (settings, machine, every solve: problem, unknowns, method, rtol, stages,
time, setup, status, errors, the solution's stats; the references; the summaries) and ``<out>.png``
(solve time against achieved state error, log-log, one panel per problem, the 1e-6 line dashed),
and prints markdown tables.

Run: python benchmarks/radau_idas.py [--quick] [--jit auto|true|false] [--problems ...] [--passes 3] [--solve-limit 20]
     [--out PATH] [--code-label TEXT]
(``--jit``: radau's adaptive solves with that ``jit``; the default ``auto`` is radau's own default, the
step in machine code where a C compiler is found; ``false`` keeps casadi's virtual machine;
docs/benchmarks/radau-idas.md quotes ``python benchmarks/radau_idas.py --jit false`` and
``python benchmarks/radau_idas.py --jit true --no-fixed --out benchmarks/radau_idas_jit``.)
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))  # scaling, scaling_models and adaptive_precision, when run from elsewhere or as a worker

import adaptive_precision  # noqa: E402  (time_at_error, one_thread: one copy of each)
import scaling  # noqa: E402  (machine_info, message, scalar_stats, run_worker_process)
import scaling_models  # noqa: E402

from daemodel.files import atomic_write  # noqa: E402

IDAS = adaptive_precision.IDAS
RADAU = "radau"
# Test Set and textbook problems of daemodel.problems, each over its own t_span.
PROBLEM_NAMES = (
    "akzo-nobel",
    "transistor-amplifier",
    "squeezer",
    "car-axis",
    "pendulum",
    "pendulum-index3",
    "robertson",
    "ring-modulator",
)
# The scaling families at about 100 and at least 200 unknowns (5N for the chain, 2K for the grid).
FAMILY_SIZES = (("pendulum_chain", 20), ("pendulum_chain", 40), ("reaction_diffusion", 50), ("reaction_diffusion", 100))
# --quick: one index-2 and one stiff problem, seconds in all.
QUICK_PROBLEMS = ("pendulum", "robertson")
# radau's sweep, rtol = atol by decades; IDAS's goes one decade looser and two tighter, so that its
# curve covers radau's errors (at rtol 1e-4 radau's error on the pendulums, 4e-5, lies below IDAS's
# at 1e-4) and the ratio is read, not extrapolated.
RADAU_TOLS = [1e-4, 1e-5, 1e-6, 1e-7, 1e-8, 1e-9, 1e-10]
IDAS_TOLS = [1e-3, *RADAU_TOLS, 1e-11, 1e-12]
# --quick: radau every other decade to 1e-8; IDAS's whole sweep (milliseconds), the curve the ratio is read from.
QUICK_RADAU_TOLS = [1e-4, 1e-6, 1e-8]
# Reference: radau at its highest order, the tightest tolerance first, a looser one only if it fails,
# cross-checked by IDAS at the tightest tolerance it is swept to.
REFERENCE_STAGES = adaptive_precision.REFERENCE_STAGES
REFERENCE_TOLS = adaptive_precision.REFERENCE_TOLS
IDAS_REFERENCE_TOL = 1e-12
# An error below this many times the two references' difference is not resolved by the reference.
UNRESOLVED_FACTOR = adaptive_precision.UNRESOLVED_FACTOR
# Output times: 21 equal times over each problem's span.
OUTPUT_POINTS = adaptive_precision.OUTPUT_POINTS
# The split of the error range and its target for the worst ratio (radau / IDAS) on each side.
ACCURATE_ERROR = 1e-6
TARGETS = {"accurate": 1.0, "loose": 2.0}
# A solve whose integration took longer (seconds) ends its method's sweep: tighter tolerances cost more.
SOLVE_LIMIT = adaptive_precision.SOLVE_LIMIT
PASSES = 3
# The fixed-step section: a banded index-1 model of 100 unknowns at two steps, radau's paper stages.
FIXED_MODEL = ("reaction_diffusion", 50)
FIXED_STEPS = [0.02, 0.01]
FIXED_STAGES = 3
FIXED_METHODS = (RADAU, "casadi-collocation")
# Tolerances at which the table shows each method's counters (steps, Jacobians, LU).
COUNTER_TOLS = (1e-6, 1e-8)
# The worker process is stopped after this many seconds (a backstop: the solve limit and the methods'
# own step budgets end runaways first); what it recorded until then is kept.
WORKER_LIMIT = 4 * 3600.0


# ---- arithmetic (tested in tests/comparing/test_benchmark_tools.py) ---------------------------------
def peak_relative_error(values, reference, names) -> tuple[float | None, str | None]:
    """The largest over ``names`` of max |values - reference| / the variable's peak |reference|.

    Parameters
    ----------
    values, reference : mapping name -> array, shape (T,)
        A variable's values at the same T times (a :class:`~daemodel.solution.Solution` is such a
        mapping).
    names : sequence of str
        The variables compared.

    Returns
    -------
    (error, name)
        The largest peak-relative error and the variable it belongs to; ``(None, None)`` when
        ``names`` is empty.  A variable whose reference is zero at every time is measured
        absolutely (its peak counts as 1).
    """
    worst, culprit = None, None
    for name in names:
        got, want = np.asarray(values[name], dtype=float), np.asarray(reference[name], dtype=float)
        if got.shape != want.shape:
            raise ValueError(f"{name!r}: values have shape {got.shape}, the reference {want.shape}")
        peak = float(np.max(np.abs(want)))
        error = float(np.max(np.abs(got - want))) / (peak if peak > 0 else 1.0)
        if worst is None or error > worst or (math.isnan(error) and not math.isnan(worst)):  # NaN: the worst
            worst, culprit = error, name
    return worst, culprit


def worst_ratio(rows: list[dict]) -> dict | None:
    """The worst (largest) of several ratios, some of them bounds.

    Parameters
    ----------
    rows : list of dict
        Each with ``ratio`` (float) and ``relation``: ``"="`` (the ratio), ``">"`` (a lower bound:
        the ratio is at least this) or ``"<"`` (an upper bound).

    Returns
    -------
    dict or None
        ``{"ratio", "relation", "points"}``: ``"="`` when the largest value is an exact ratio and no
        lower bound could exceed it; ``">"`` when some ratio is only bounded below (the worst is at
        least the largest exact or lower-bound value); ``"<"`` when the largest value is an upper
        bound (the worst is at most it).  None for no rows.
    """
    if not rows:
        return None
    largest = max(row["ratio"] for row in rows)
    if any(row["relation"] == ">" for row in rows):
        floor = max(row["ratio"] for row in rows if row["relation"] in "=>")
        return {"ratio": floor, "relation": ">", "points": len(rows)}
    exact = any(row["relation"] == "=" and row["ratio"] == largest for row in rows)
    return {"ratio": largest, "relation": "=" if exact else "<", "points": len(rows)}


def meets(worst: dict | None, target: float) -> bool | None:
    """Whether a worst ratio meets ``target`` (at most): True, False, or None where a bound cannot tell."""
    if worst is None:
        return None
    ratio, relation = worst["ratio"], worst["relation"]
    if ratio <= target:
        return None if relation == ">" else True
    return None if relation == "<" else False


# ---- problems ----------------------------------------------------------------------------
def problem_keys() -> list[str]:
    """Every problem's key: the Test Set names, then ``family-size``."""
    return [*PROBLEM_NAMES, *(f"{family}-{size}" for family, size in FAMILY_SIZES)]


def build(key: str):
    """``(compiled, t_span, unknowns)`` of a problem key."""
    from daemodel.problems import PROBLEMS

    if key in PROBLEMS:
        problem = PROBLEMS[key]
        compiled = problem.model().compile()
        return compiled, tuple(problem.t_span), len(compiled.state_names) + len(compiled.algebraic_names)
    family, _, size = key.rpartition("-")
    compiled = scaling_models.FAMILIES[family](int(size)).compile()
    return compiled, tuple(scaling_models.T_SPAN[family]), scaling_models.unknowns(family, int(size))


def shared_times(sol, reference) -> tuple[list[int], list[int]]:
    """Indices of the times that ``sol`` and ``reference`` both report, in each (a fixed step's
    grid meets the 21 output times at some of them)."""
    mine, theirs = [], []
    for j, t in enumerate(reference.t):
        hit = np.flatnonzero(np.isclose(sol.t, t, rtol=0, atol=1e-12 * max(1.0, abs(t))))
        if hit.size:
            mine.append(int(hit[0]))
            theirs.append(j)
    if not mine:
        raise ValueError(f"the solution's {len(sol.t)} times share none with the reference's {len(reference.t)}")
    return mine, theirs


# ---- worker: every problem, every pass ---------------------------------------------------
def say(text: str) -> None:
    print(f"  {text}"[:220], file=sys.stderr, flush=True)


def solve(compiled, t_span, method: str, **options):
    """``dm.solve`` on one thread."""
    import daemodel as dm

    adaptive_precision.one_thread()
    return dm.solve(compiled, t_span, method=method, **options)


def measure_errors(run: dict, sol, reference, names: dict, floor: dict) -> None:
    """Peak-relative state (y) and algebraic (z) errors of ``sol`` into ``run``, flagged unresolved
    where below :data:`UNRESOLVED_FACTOR` times ``floor`` (the reference's uncertainty)."""
    mine, theirs = shared_times(sol, reference)
    for part in ("y", "z"):
        values = {name: sol[name][mine] for name in names[part]}
        wanted = {name: reference[name][theirs] for name in names[part]}
        value, culprit = peak_relative_error(values, wanted, names[part])
        unresolved = value is not None and bool(floor.get(part)) and value < UNRESOLVED_FACTOR * floor[part]
        run.update({f"error_{part}": value, f"worst_{part}": culprit, f"unresolved_{part}": unresolved})
    run["error_times"] = len(mine)


def warm_up(model: dict, method: str, options: dict) -> None:
    """One untimed solve, so that the timed ones after it start from the same warm caches for every
    method; its failure is left to the timed solve to record."""
    try:
        solve(model["compiled"], model["t_span"], method, **options)
    except Exception:  # the timed solve with the same options records it
        pass


def timed(run: dict, model: dict, options: dict, first: bool) -> float:
    """One solve of ``run["method"]`` into ``run``, which keeps its fastest; the first pass also records
    the status, stats and errors.  Returns the seconds that count against the solve limit."""
    began = time.perf_counter()
    try:
        sol = solve(model["compiled"], model["t_span"], run["method"], **options)
    except Exception as error:  # recorded, never raised: one failing solve must not stop the sweep
        if first:
            run.update(status="failed", message=scaling.message(error))
        else:
            run.setdefault("later_failures", []).append(scaling.message(error))
        return time.perf_counter() - began
    call = time.perf_counter() - began
    run.setdefault("runs", []).append(
        {"solve_time_s": float(sol.solve_time), "setup_time_s": float(sol.setup_time), "call_s": call}
    )
    run.update(min(run["runs"], key=lambda r: r["solve_time_s"]))
    if first:
        stats = sol.stats
        run.update(
            status="ok",
            solution_status=sol.status,
            stages=stats.get("stages", run.get("stages")),
            steps=stats.get("steps", stats.get("nsteps")),
            stats=scaling.scalar_stats(stats),
        )
        if model["reference"] is not None:
            try:
                measure_errors(run, sol, model["reference"], model["names"], model["uncertainty"])
                if "t_eval" in options and run["error_times"] != len(options["t_eval"]):
                    raise ValueError(
                        f"the solution reports {run['error_times']} of the {len(options['t_eval'])} output times"
                    )
            except ValueError as error:  # recorded: a comparison that cannot be made is a result too
                run.update(status="failed", message=scaling.message(error))
    return float(sol.solve_time)


def prepare(key: str, spec: dict) -> tuple[dict, dict | None]:
    """Compile a problem and solve its references: its record (solves pending) and the model
    (compiled, t_span, grid, reference, names, uncertainty), None where either failed."""
    entry = {"problem": key, "solves": [], "reference": {}}
    began = time.perf_counter()
    try:
        compiled, t_span, unknowns = build(key)
    except Exception as error:  # recorded: the other problems go on
        entry["message"] = "build or compile failed: " + scaling.message(error)
        return entry, None
    names = {"y": list(compiled.state_names), "z": list(compiled.algebraic_names)}
    grid = np.linspace(*t_span, OUTPUT_POINTS)
    entry.update(
        unknowns=unknowns,
        n_states=len(names["y"]),
        n_algebraics=len(names["z"]),
        index=compiled.index,
        t_span=list(t_span),
        compile_s=time.perf_counter() - began,
    )
    references = {}
    for method, stages, tols in ((RADAU, REFERENCE_STAGES, REFERENCE_TOLS), (IDAS, None, [IDAS_REFERENCE_TOL])):
        ref = {"method": method, "stages": stages, "rtol": None, "failures": []}
        for tol in tols:
            options = {"rtol": tol, "atol": tol, "t_eval": grid, **({"stages": stages} if stages else {})}
            try:
                references[method] = solve(compiled, t_span, method, **options)
            except Exception as error:  # the next looser tolerance is tried
                ref["failures"].append({"rtol": tol, "message": scaling.message(error)})
                continue
            ref.update(rtol=tol, solve_time_s=references[method].solve_time)
            ref["stats"] = scaling.scalar_stats(references[method].stats)
            break
        entry["reference"][method] = ref
    used = RADAU if RADAU in references else IDAS if IDAS in references else None
    uncertainty = {"y": None, "z": None}
    if len(references) == 2:
        for part in ("y", "z"):
            uncertainty[part] = peak_relative_error(references[IDAS], references[RADAU], names[part])[0]
    entry["reference"].update(used=used, uncertainty=uncertainty)
    shown = ", ".join(f"{m} at {entry['reference'][m]['rtol']:g}" for m in references)
    say(f"{key}: {unknowns} unknowns, reference {shown or 'failed'}; uncertainty y {uncertainty['y']}")
    if used is None:
        entry["message"] = "no reference: radau and casadi-idas failed at every reference tolerance"
        return entry, None
    for method, tols in ((RADAU, spec["radau_tols"]), (IDAS, spec["idas_tols"])):
        entry["solves"] += [
            {"problem": key, "unknowns": unknowns, "method": method, "rtol": tol, "status": "pending"} for tol in tols
        ]
    model = {
        "compiled": compiled,
        "t_span": t_span,
        "grid": grid,
        "reference": references[used],
        "names": names,
        "uncertainty": uncertainty,
    }
    return entry, model


def prepare_fixed(models: dict, steps: list[float]) -> tuple[list[dict], dict | None, str | None]:
    """The fixed-step section's runs (pending), its model (the adaptive section's where it ran it)
    and a message where something failed."""
    key = "{}-{}".format(*FIXED_MODEL)
    model, message = models.get(key), None
    if model is None:  # the adaptive section did not run it: compiled here, with its own reference
        try:
            compiled, t_span, _ = build(key)
        except Exception as error:  # recorded: the adaptive section goes on
            return [], None, "build or compile failed: " + scaling.message(error)
        grid = np.linspace(*t_span, OUTPUT_POINTS)
        names = {"y": list(compiled.state_names), "z": list(compiled.algebraic_names)}
        model = {"compiled": compiled, "t_span": t_span, "reference": None, "names": names, "uncertainty": {}}
        try:
            options = {"rtol": REFERENCE_TOLS[0], "atol": REFERENCE_TOLS[0], "t_eval": grid}
            model["reference"] = solve(compiled, t_span, RADAU, stages=REFERENCE_STAGES, **options)
        except Exception as error:  # errors are then not measured, times still are
            message = "no reference: " + scaling.message(error)
    unknowns = scaling_models.unknowns(*FIXED_MODEL)
    runs = [
        {"problem": key, "unknowns": unknowns, "method": m, "h": h, "stages": FIXED_STAGES, "status": "pending"}
        for h in steps
        for m in FIXED_METHODS
    ]
    return runs, model, message


def run_worker(spec: dict) -> None:
    """References, then ``spec["passes"]`` interleaved passes over every problem, method and
    tolerance, and the fixed-step section; the record goes to ``spec["out"]`` after each problem
    and pass."""
    out = Path(spec["out"])
    record = {"problems": [], "fixed": [], "passes_done": 0}

    def save() -> None:
        atomic_write(out, lambda f: f.write(json.dumps(record, indent=1)), text=True)

    models = {}
    for key in spec["problems"]:
        entry, model = prepare(key, spec)
        record["problems"].append(entry)
        if model is not None:
            models[key] = model
        save()
    fixed = None
    if spec["fixed"]:
        record["fixed"], fixed, record["fixed_message"] = prepare_fixed(models, spec["fixed_steps"])

    for sweep in range(spec["passes"]):
        first = sweep == 0
        for entry in record["problems"]:
            if entry["problem"] not in models:
                continue
            model = models[entry["problem"]]
            stopped = {}  # method -> why its tighter tolerances are skipped (first pass)
            warmed = set()  # methods that had their untimed solve on this problem in this pass
            for run in entry["solves"]:
                method, tol = run["method"], run["rtol"]
                if first and method in stopped:
                    run.update(status="skipped", message=stopped[method])
                    continue
                if not first and run["status"] != "ok":
                    continue
                options = {"rtol": tol, "atol": tol, "t_eval": model["grid"]}
                if method == RADAU and spec["jit"] != "auto":
                    options["jit"] = spec["jit"] == "true"
                if method not in warmed:
                    warmed.add(method)
                    warm_up(model, method, options)
                seconds = timed(run, model, options, first)
                if not first:
                    continue
                if run["status"] != "ok":
                    stopped[method] = f"not run: the solve at rtol = {tol:g} failed"
                elif seconds > spec["solve_limit"]:
                    stopped[method] = (
                        f"not run: the solve at rtol = {tol:g} took {seconds:.3g} s, over the {spec['solve_limit']:g} s"
                        " limit"
                    )
                shown = (
                    f"{run['solve_time_s']:.3g} s  err y {run['error_y']:.1e}  {run['steps']} steps"
                    if run["status"] == "ok"
                    else run.get("message", "")
                )
                say(f"{entry['problem']} {method:<11} {tol:.0e}  {run['status']:<6} {shown}")
            save()
        for run in record["fixed"]:
            if not first and run["status"] != "ok":
                continue
            timed(run, fixed, {"h": run["h"], "stages": run["stages"]}, first)
            if first:
                shown = f"{run['solve_time_s']:.3g} s" if run["status"] == "ok" else run.get("message", "")
                say(f"fixed {run['method']:<18} h = {run['h']:g}  {run['status']:<6} {shown}")
        record["passes_done"] = sweep + 1
        say(f"pass {sweep + 1} of {spec['passes']} done")
        save()


# ---- summaries ---------------------------------------------------------------------------
def comparisons(entry: dict) -> list[dict]:
    """Each radau point against IDAS's time at radau's achieved state error."""
    ok = [r for r in entry["solves"] if r["status"] == "ok" and r.get("error_y") is not None]
    idas = [(r["error_y"], r["solve_time_s"]) for r in ok if r["method"] == IDAS]
    rows = []
    for run in ok:
        if run["method"] != RADAU:
            continue
        row = {
            "rtol": run["rtol"],
            "stages": run.get("stages"),
            "error_y": run["error_y"],
            "unresolved_y": run.get("unresolved_y", False),
            "solve_time_s": run["solve_time_s"],
            "idas_time_s": None,
            "idas_relation": "",
            "ratio": None,
            "relation": "",
        }
        seconds, relation = adaptive_precision.time_at_error(idas, run["error_y"])
        if seconds is not None:
            # a bound on IDAS's time is the opposite bound on the ratio
            flip = {"=": "=", ">": "<", "<": ">"}[relation]
            row.update(idas_time_s=seconds, idas_relation=relation, ratio=run["solve_time_s"] / seconds, relation=flip)
        rows.append(row)
    return rows


def summary(entry: dict) -> dict:
    """The worst ratio on each side of :data:`ACCURATE_ERROR` and whether it meets its target."""
    rows = [r for r in entry.get("comparisons", []) if r["ratio"] is not None]
    sides = {
        "accurate": [r for r in rows if r["error_y"] <= ACCURATE_ERROR],
        "loose": [r for r in rows if r["error_y"] > ACCURATE_ERROR],
    }
    out = {"stages_used": sorted({r["stages"] for r in entry.get("comparisons", []) if r["stages"] is not None})}
    for side, chosen in sides.items():
        worst = worst_ratio(chosen)
        out[side] = {
            "worst": worst,
            "target": TARGETS[side],
            "meets": meets(worst, TARGETS[side]),
            "unresolved_points": sum(r["unresolved_y"] for r in chosen),
        }
    return out


def fixed_ratios(fixed: list[dict]) -> list[dict]:
    """radau's time over casadi-collocation's at each step."""
    out = []
    for h in sorted({r["h"] for r in fixed}, reverse=True):
        runs = {r["method"]: r for r in fixed if r["h"] == h and r["status"] == "ok"}
        row = {"h": h, "ratio": None}
        if len(runs) == len(FIXED_METHODS):
            row["ratio"] = runs[RADAU]["solve_time_s"] / runs[FIXED_METHODS[1]]["solve_time_s"]
        out.append(row)
    return out


# ---- driver ------------------------------------------------------------------------------
def main(argv=None) -> None:
    keys = problem_keys()
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    parser.add_argument(
        "--quick",
        action="store_true",
        help=f"{' and '.join(QUICK_PROBLEMS)} only, radau at {', '.join(f'{t:g}' for t in QUICK_RADAU_TOLS)}, one pass",
    )
    parser.add_argument("--problems", nargs="+", choices=keys, help="problems to run (default: all)")
    parser.add_argument("--passes", type=int, default=PASSES, help="interleaved timing passes (default %(default)s)")
    parser.add_argument(
        "--solve-limit",
        type=float,
        default=SOLVE_LIMIT,
        help="a solve whose integration takes longer (s) ends its method's sweep (default %(default)s)",
    )
    parser.add_argument(
        "--no-fixed", action="store_true", help="leave out the fixed-step section (radau against casadi-collocation)"
    )
    parser.add_argument(
        "--out", default=str(HERE / "radau_idas"), help="output path without suffix (default %(default)s)"
    )
    parser.add_argument("--code-label", help="free text recorded with the machine (e.g. which commit was measured)")
    parser.add_argument(
        "--jit",
        choices=("auto", "true", "false"),
        default="auto",
        help="radau's adaptive solves' jit (default %(default)s, radau's default: the step in machine code where "
        "a C compiler is found; its build is setup, apart)",
    )
    args = parser.parse_args(argv)
    if args.worker:
        run_worker(json.loads(args.worker))
        return
    if args.passes < 1:
        parser.error(f"--passes must be at least 1; got {args.passes}")

    problems = args.problems or list(QUICK_PROBLEMS if args.quick else keys)
    passes = 1 if args.quick else args.passes
    spec = {
        "problems": problems,
        "radau_tols": QUICK_RADAU_TOLS if args.quick else RADAU_TOLS,
        "idas_tols": IDAS_TOLS,
        "passes": passes,
        "solve_limit": args.solve_limit,
        "fixed": not args.no_fixed,
        "fixed_steps": FIXED_STEPS,
        "jit": args.jit,
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    started = time.monotonic()
    info = scaling.machine_info(args.code_label)
    info["torch_threads"] = "1 where imported (radau's casadi engine does not import torch)"
    print(f"daemodel code: {info['daemodel_code']} ({info['code_label'] or info['git_commit']})", file=sys.stderr)
    with tempfile.TemporaryDirectory() as folder:
        worker = {**spec, "out": str(Path(folder) / "record.json")}
        record, code, seconds = scaling.run_worker_process(__file__, worker, WORKER_LIMIT)
    message = None
    if code is None:
        message = f"the worker process was stopped after {WORKER_LIMIT:g} s"
    elif code != 0:
        message = f"the worker process exited with code {code}"
    entries = record.get("problems", [])
    for entry in entries:
        entry["comparisons"] = comparisons(entry)
        entry["summary"] = summary(entry)
    fixed = record.get("fixed", [])
    result = {
        "benchmark": "adaptive radau against casadi-idas at equal achieved error (issue 26)",
        "command": " ".join(["python", "benchmarks/radau_idas.py", *(sys.argv[1:] if argv is None else argv)]),
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "machine": {**info, "load_average_at_end": list(os.getloadavg())},
        "settings": {
            "problems": problems,
            "radau": "method='radau' without stages (its default picks them from rtol; recorded per solve)"
            + f", jit={ {'auto': repr('auto'), 'true': 'True', 'false': 'False'}[args.jit] }",
            "radau_tols": spec["radau_tols"],
            "idas_tols": spec["idas_tols"],
            "reference": (
                f"radau, s = {REFERENCE_STAGES}, rtol = atol = {REFERENCE_TOLS[0]:g} (looser: {REFERENCE_TOLS[1:]}), "
                f"cross-checked with casadi-idas at {IDAS_REFERENCE_TOL:g}"
            ),
            "unresolved_factor": UNRESOLVED_FACTOR,
            "output_points": OUTPUT_POINTS,
            "error": (
                "per variable max over the output times of |value - reference| / its peak |reference| over them "
                "(1 where the peak is 0); the largest over the states (y) and, apart, the algebraic variables (z)"
            ),
            "clock": "sol.solve_time (integration only), minimum over the passes; sol.setup_time apart",
            "warm_up": "in every pass, one untimed solve of each method on each problem before its timed ones",
            "passes": passes,
            "interpolation": "adaptive_precision.time_at_error: log-log on IDAS's monotone envelope; bounds outside",
            "accurate_error": ACCURATE_ERROR,
            "targets": TARGETS,
            "solve_limit_s": args.solve_limit,
            "worker_limit_s": WORKER_LIMIT,
            "fixed": {"model": list(FIXED_MODEL), "steps": FIXED_STEPS, "stages": FIXED_STAGES}
            if spec["fixed"]
            else None,
            "quick": args.quick,
            "dtype": "float64",
        },
        "worker_seconds": seconds,
        "passes_done": record.get("passes_done", 0),
        "message": message,
        "problems": entries,
        "fixed": fixed,
        "fixed_message": record.get("fixed_message"),
        "fixed_ratios": fixed_ratios(fixed),
        "total_seconds": time.monotonic() - started,
    }
    atomic_write(out.with_suffix(".json"), lambda f: f.write(json.dumps(result, indent=1) + "\n"), text=True)
    plot(result, out.with_suffix(".png"))
    print(table(result))
    print(f"\nwrote {out.with_suffix('.json')} and {out.with_suffix('.png')} in {result['total_seconds']:.0f} s")


# ---- output ------------------------------------------------------------------------------
def ratio_text(worst: dict | None) -> str:
    if worst is None:
        return "-"
    return f"{worst['relation'].strip('=')}{worst['ratio']:.2g}x"


def verdict(side: dict) -> str:
    mark = {True: "met", False: "missed", None: "undecided"}[side["meets"]]
    if side["worst"] is None:
        return "no points"
    dagger = f", {side['unresolved_points']} †" if side["unresolved_points"] else ""
    return f"{ratio_text(side['worst'])} ({mark}: target ≤ {side['target']:g}x{dagger})"


def counters(entry: dict, method: str, tol: float) -> str:
    """A method's counters at ``tol``: radau steps / Jacobians / LU, IDAS steps / linear setups."""
    run = next((r for r in entry["solves"] if r["method"] == method and r["rtol"] == tol), None)
    if run is None or run["status"] != "ok":
        return "-" if run is None else run["status"]
    stats = run.get("stats", {})
    keys = ("steps", "jacobian_evaluations", "lu_decompositions") if method == RADAU else ("nsteps", "nlinsetups")
    return " / ".join(str(stats.get(k, "?")) for k in keys)


def error_text(run: dict, part: str) -> str:
    error = run.get(f"error_{part}")
    if error is None:
        return "-"
    return f"{error:.1e}" + (" †" if run.get(f"unresolved_{part}") else "")


def table(result: dict) -> str:
    """Markdown: the per-problem summary, every radau point, the fixed-step section, references, failures."""
    tols = " and ".join(f"{t:g}" for t in COUNTER_TOLS)
    lines = [
        "### adaptive radau (default stages) against casadi-idas at equal achieved state error",
        "",
        f"| problem | unknowns | radau stages | worst ratio, error ≤ {ACCURATE_ERROR:g} "
        f"| worst ratio, error > {ACCURATE_ERROR:g} | radau steps / Jac / LU at {tols} "
        f"| IDAS steps / lin. setups at {tols} |",
        "|---|---:|---|---|---|---|---|",
    ]
    for entry in result["problems"]:
        if "summary" not in entry or entry.get("message"):
            lines.append(f"| {entry['problem']} | {entry.get('unknowns', '')} | {entry.get('message', 'not run')} ||||")
            continue
        s = entry["summary"]
        lines.append(
            f"| {entry['problem']} | {entry['unknowns']} | {','.join(map(str, s['stages_used'])) or '-'} "
            f"| {verdict(s['accurate'])} | {verdict(s['loose'])} "
            f"| {' ; '.join(counters(entry, RADAU, t) for t in COUNTER_TOLS)} "
            f"| {' ; '.join(counters(entry, IDAS, t) for t in COUNTER_TOLS)} |"
        )
    lines += [
        "",
        "ratio: radau's solve time / IDAS's at radau's achieved state error (peak-relative), interpolated in "
        "log-log on IDAS's sweep; `>`/`<`: radau's error lies outside IDAS's sweep (a bound).  "
        f"†: points below {UNRESOLVED_FACTOR:g}x the reference's uncertainty (counted, not resolved).",
        "",
        "### Every radau point",
        "",
        "| problem | rtol | stages | time (s) | setup (s) | error y | error z | steps | IDAS time at equal error (s) "
        "| ratio |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for entry in result["problems"]:
        rows = {r["rtol"]: r for r in entry.get("comparisons", [])}
        for run in entry["solves"]:
            if run["method"] != RADAU:
                continue
            if run["status"] != "ok":
                lines.append(f"| {entry['problem']} | {run['rtol']:g} | {run['status']} ||||||||")
                continue
            row = rows.get(run["rtol"], {})
            idas = (
                "-" if row.get("idas_time_s") is None else f"{row['idas_relation'].strip('=')}{row['idas_time_s']:.3g}"
            )
            ratio = "-" if row.get("ratio") is None else f"{row['relation'].strip('=')}{row['ratio']:.2g}"
            lines.append(
                f"| {entry['problem']} | {run['rtol']:g} | {run.get('stages')} | {run['solve_time_s']:.3g} "
                f"| {run['setup_time_s']:.2g} | {error_text(run, 'y')} | {error_text(run, 'z')} | {run.get('steps')} "
                f"| {idas} | {ratio} |"
            )
    if result["fixed"]:
        lines += [
            "",
            f"### Fixed step: radau against casadi-collocation, stages = {FIXED_STAGES}",
            "",
            "| problem | unknowns | h | radau time (s) | collocation time (s) | radau error y | collocation error y "
            "| ratio |",
            "|---|---:|---:|---:|---:|---:|---:|---:|",
        ]
        for row in result["fixed_ratios"]:
            runs = {r["method"]: r for r in result["fixed"] if r["h"] == row["h"]}
            radau, colloc = runs.get(RADAU, {}), runs.get(FIXED_METHODS[1], {})

            def seconds(run):
                return f"{run['solve_time_s']:.3g}" if run.get("status") == "ok" else run.get("status", "-")

            ratio = "-" if row["ratio"] is None else f"{row['ratio']:.2g}"
            lines.append(
                f"| {radau.get('problem', '')} | {radau.get('unknowns', '')} | {row['h']:g} | {seconds(radau)} "
                f"| {seconds(colloc)} | {error_text(radau, 'y')} | {error_text(colloc, 'y')} | {ratio} |"
            )
    lines += ["", "### References (peak-relative difference of radau's and IDAS's: y / z)", ""]
    for entry in result["problems"]:
        ref = entry.get("reference", {})
        parts = []
        for method in (RADAU, IDAS):
            r = ref.get(method)
            if r:
                parts.append(f"{method} at {r['rtol']:g}" if r["rtol"] else f"{method} failed")
                parts += [f"({method} at {f['rtol']:g} failed: {f['message']})" for f in r["failures"]]
        unc = ref.get("uncertainty") or {}
        shown = " / ".join("-" if unc.get(p) is None else f"{unc[p]:.1e}" for p in ("y", "z"))
        lines.append(f"- {entry['problem']}: {', '.join(parts) or 'none'}; uncertainty {shown}")
    problems = [
        f"- {entry['problem']}, {run['method']} at {run['rtol']:g}: {run['status']}: {run.get('message', '')}"
        for entry in result["problems"]
        for run in entry["solves"]
        if run["status"] != "ok"
    ]
    problems += [
        f"- {entry['problem']}, {run['method']} at {run['rtol']:g}: later pass failed: {text}"
        for entry in result["problems"]
        for run in entry["solves"]
        for text in run.get("later_failures", [])
    ]
    problems += [f"- {entry['problem']}: {entry['message']}" for entry in result["problems"] if entry.get("message")]
    problems += [
        f"- fixed {run['method']} h = {run['h']:g}: {run['status']}: {run.get('message', '')}"
        for run in result["fixed"]
        if run["status"] != "ok"
    ]
    problems += [f"- {text}" for text in (result.get("fixed_message"), result.get("message")) if text]
    if problems:
        lines += ["", "### Failures and skipped solves", "", *problems]
    return "\n".join(lines)


def plot(result: dict, path: Path) -> None:
    """Solve time against achieved state error, log-log, one panel per problem: radau (marker by
    stages) and IDAS, the 1e-6 line dashed, errors the reference does not resolve shaded."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    entries = [e for e in result["problems"] if any(r["status"] == "ok" for r in e["solves"])]
    if not entries:
        return
    columns = min(4, len(entries))
    rows = math.ceil(len(entries) / columns)
    fig = Figure(figsize=(4.4 * columns, 3.8 * rows + 0.8), layout="constrained")
    axes = fig.subplots(rows, columns, squeeze=False).ravel()
    markers = {3: "o", 5: "s", 7: "^"}
    for ax, entry in zip(axes, entries, strict=False):
        for method, color in ((RADAU, "C0"), (IDAS, "k")):
            runs = sorted(
                (r for r in entry["solves"] if r["method"] == method and r["status"] == "ok" and r.get("error_y")),
                key=lambda r: r["rtol"],
                reverse=True,
            )
            if not runs:
                continue
            errors, times = [r["error_y"] for r in runs], [r["solve_time_s"] for r in runs]
            ax.loglog(errors, times, color=color, lw=1)
            for r in runs:
                marker = "x" if method == IDAS else markers.get(r.get("stages"), "D")
                ax.loglog(
                    r["error_y"], r["solve_time_s"], marker, color=color, ms=5, mfc="none" if method == RADAU else None
                )
        ax.axvline(ACCURATE_ERROR, color="0.4", ls="--", lw=1)
        floor = (entry.get("reference", {}).get("uncertainty") or {}).get("y")
        if floor:
            left = min(ax.get_xlim()[0], floor)
            ax.axvspan(left, UNRESOLVED_FACTOR * floor, color="0.88", zorder=0)
            ax.set_xlim(left=left)
        s = entry["summary"]
        ax.set_title(
            f"{entry['problem']} ({entry['unknowns']} unknowns)\nworst radau/IDAS: "
            f"≤1e-6 {ratio_text(s['accurate']['worst'])}, >1e-6 {ratio_text(s['loose']['worst'])}",
            fontsize=8,
        )
        ax.set_xlabel("max peak-relative state error")
        ax.set_ylabel("solve time (s)")
        ax.grid(alpha=0.3, which="both")
    for ax in axes[len(entries) :]:
        ax.set_axis_off()
    handles = [Line2D([], [], marker=m, color="C0", mfc="none", label=f"radau, s = {s}") for s, m in markers.items()]
    handles += [
        Line2D([], [], marker="x", color="k", label=IDAS),
        Line2D([], [], color="0.4", ls="--", label=f"error {ACCURATE_ERROR:g}"),
        Patch(color="0.88", label=f"< {UNRESOLVED_FACTOR:g}x the reference's uncertainty"),
    ]
    fig.legend(handles=handles, loc="outside lower center", ncol=len(handles), fontsize=8)
    machine = result["machine"]
    fig.suptitle(
        f"daemodel: adaptive radau (default stages) against casadi-idas, rtol = atol by decades, "
        f"min of {result['passes_done']} pass(es); one thread; {machine['cpu']}",
        fontsize=9,
    )
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    main()

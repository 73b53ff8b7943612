"""What radau's default machine code costs and saves (issue 42): first compile, cached load, break-even.

For each problem (the Test Set problems of ``benchmarks/radau_idas.py`` and its families at about
100 and 200 unknowns), adaptive radau with its defaults (``jit="auto"``, no ``stages``) at
``rtol = atol = --rtol``, over the problem's ``t_span``:

* **first compile**: ``setup_time`` of the first solve in a fresh process with an empty cache folder
  (``DAEMODEL_CACHE`` a new temporary folder; ``stats["compiled_cache"]``, recorded, says ``"miss"``), and
  the same process's ``setup_time`` with ``jit=False`` on a fresh compile of the model (what the
  virtual machine's setup costs anyway); **compiler CPU**: the CPU seconds (user + system) of the
  compiler's processes in that first solve, all translation units together (less sensitive to the
  machine's load than the wall time; the wall time of units compiled at once is less than their sum);
* **cached load**: ``setup_time`` of the first solve in a second process on the same folder
  (``"hit"``): the libraries loaded, nothing compiled;
* **solve**: ``solve_time``, the minimum of ``--repeats`` solves, with machine code and with
  ``jit=False``, in that second process;
* **break-even**: the solves after which the first compile has paid for itself,
  ``(first compile - virtual machine's setup) / (solve with jit=False - solve in machine code)``
  (inf where machine code is not faster).

One BLAS thread (each process starts with OMP/OPENBLAS/MKL_NUM_THREADS = 1); the model's own
``compile()`` is timed apart and counted in neither.  Writes ``<out>.json`` (settings, machine,
per problem: unknowns, stages, the seconds above, the cache's outcomes, gcc runs where known) and
``<out>.png`` (first compile and cached load per problem, log scale, beside the solve times), and
prints a markdown table.

Run: python benchmarks/compile_cost.py [--rtol 1e-6] [--repeats 5] [--problems ...] [--out PATH]
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import radau_idas  # noqa: E402
import scaling  # noqa: E402

# The problems: the Test Set's of radau_idas.py, then its families ("family:size").
PROBLEMS = [*radau_idas.PROBLEM_NAMES, *(f"{family}:{size}" for family, size in radau_idas.FAMILY_SIZES)]
# Seconds a worker process may take (the largest first compile is well under a minute).
WORKER_LIMIT = 900.0


def model_and_span(name: str):
    """The model (not compiled) and t_span of a problem name of :data:`PROBLEMS`."""
    import scaling_models

    from daemodel.problems import PROBLEMS as LIBRARY

    if ":" in name:
        family, size = name.split(":")
        return scaling_models.FAMILIES[family](int(size)), scaling_models.T_SPAN[family]
    problem = LIBRARY[name]
    return problem.model(), problem.t_span


def run_worker(spec: dict) -> None:
    """One process of one problem: ``spec["phase"]`` "first" (cold cache) or "cached" (warm)."""
    import numpy as np

    import daemodel as dm

    model, span = model_and_span(spec["problem"])
    began = time.perf_counter()
    compiled = model.compile()
    record = {"model_compile_s": time.perf_counter() - began}
    options = {"rtol": spec["rtol"], "atol": spec["rtol"]}
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    sol = dm.solve(compiled, span, **options)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    record.update(
        setup_s=sol.setup_time,
        compiler_cpu_s=(after.ru_utime - children.ru_utime) + (after.ru_stime - children.ru_stime),
        solve_s=sol.solve_time,
        cache=sol.stats.get("compiled_cache"),
        jit=sol.stats.get("jit"),
        stages=sol.stats["stages"],
        steps=sol.stats["steps"],
        unknowns=len(compiled.state_names) + len(compiled.algebraic_names),
    )
    if spec["phase"] == "first":
        fresh = model_and_span(spec["problem"])[0].compile()
        record["vm_setup_s"] = dm.solve(fresh, span, jit=False, **options).setup_time
    else:
        for jit, key in (("auto", "solve_jit_s"), (False, "solve_vm_s")):
            times = [dm.solve(compiled, span, jit=jit, **options).solve_time for _ in range(spec["repeats"])]
            record[key] = float(np.min(times))
    Path(spec["out"]).write_text(json.dumps(record))


def run_phase(problem: str, rtol: float, repeats: int, phase: str, folder: str) -> tuple[dict, str | None]:
    """One worker process of ``problem``: its record, and what went wrong (None: nothing)."""
    spec = {"problem": problem, "rtol": rtol, "repeats": repeats, "phase": phase, "out": f"{folder}/{phase}.json"}
    record, code, _ = scaling.run_worker_process(__file__, spec, WORKER_LIMIT)
    if code != 0 or not record:
        return record, f"the {phase} process " + ("timed out" if code is None else f"exited with {code}")
    return record, None


def measure(problem: str, rtol: float, repeats: int) -> dict:
    """Both processes of ``problem`` on one fresh cache folder; the entry of the JSON file."""
    entry = {"problem": problem}
    before = os.environ.get("DAEMODEL_CACHE")
    with tempfile.TemporaryDirectory() as folder:
        os.environ["DAEMODEL_CACHE"] = str(Path(folder) / "cache")  # (the workers' cache; restored below)
        try:
            records = [run_phase(problem, rtol, repeats, phase, folder) for phase in ("first", "cached")]
        finally:
            if before is None:
                os.environ.pop("DAEMODEL_CACHE", None)
            else:
                os.environ["DAEMODEL_CACHE"] = before
    for phase, (record, message) in zip(("first", "cached"), records, strict=True):
        if message is not None:
            entry["message"] = message
            return entry
        entry[phase] = record
    first, cached = entry["first"], entry["cached"]
    saved = cached["solve_vm_s"] - cached["solve_jit_s"]
    paid = first["setup_s"] - first["vm_setup_s"]
    entry.update(
        unknowns=first["unknowns"],
        stages=first["stages"],
        first_compile_s=first["setup_s"],
        compiler_cpu_s=first["compiler_cpu_s"],
        vm_setup_s=first["vm_setup_s"],
        cached_load_s=cached["setup_s"],
        solve_jit_s=cached["solve_jit_s"],
        solve_vm_s=cached["solve_vm_s"],
        break_even_solves=paid / saved if saved > 0 else math.inf,
    )
    return entry


def table(entries: list) -> str:
    lines = [
        "| problem | unknowns | s | first compile (s) | compiler CPU (s) | cached load (s) | setup jit=False (s) | "
        "solve jit (ms) | solve jit=False (ms) | break-even solves | cache |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    for e in entries:
        if "message" in e:
            lines.append(f"| {e['problem']} | | | {e['message']} | | | | | | | |")
            continue
        lines.append(
            f"| {e['problem']} | {e['unknowns']} | {e['stages']} | {e['first_compile_s']:.2f} | "
            f"{e['compiler_cpu_s']:.2f} | {e['cached_load_s']:.3f} | {e['vm_setup_s']:.3f} | "
            f"{1e3 * e['solve_jit_s']:.2f} | {1e3 * e['solve_vm_s']:.2f} | {e['break_even_solves']:.0f} | "
            f"{e['first']['cache']} → {e['cached']['cache']} |"
        )
    return "\n".join(lines)


def plot(entries: list, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    done = [e for e in entries if "message" not in e]
    if not done:
        return
    names = [e["problem"] for e in done]
    x = np.arange(len(done))
    fig, (left, right) = plt.subplots(1, 2, figsize=(13, 4.8))
    for offset, key, label in ((-0.2, "first_compile_s", "first compile"), (0.2, "cached_load_s", "cached load")):
        left.bar(x + offset, [e[key] for e in done], 0.4, label=label)
    left.set_yscale("log")
    left.set_ylabel("setup of the first solve (s)")
    left.set_title("radau's machine code: compiled once, then loaded")
    for offset, key, label in ((-0.2, "solve_jit_s", "machine code"), (0.2, "solve_vm_s", "jit=False")):
        right.bar(x + offset, [1e3 * e[key] for e in done], 0.4, label=label)
    right.set_yscale("log")
    right.set_ylabel("solve_time (ms, min of repeats)")
    right.set_title("solve time")
    for axis in (left, right):
        axis.set_xticks(x, names, rotation=40, ha="right", fontsize=8)
        axis.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    parser.add_argument("--rtol", type=float, default=1e-6, help="rtol = atol of every solve (default %(default)g)")
    parser.add_argument("--repeats", type=int, default=5, help="solves timed per code, the minimum kept")
    parser.add_argument("--problems", nargs="+", choices=PROBLEMS, help="default: all of them")
    parser.add_argument("--out", default=str(HERE / "compile_cost"), help="output path without suffix")
    parser.add_argument("--code-label", help="free text recorded with the machine (e.g. which commit was measured)")
    args = parser.parse_args(argv)
    if args.worker:
        run_worker(json.loads(args.worker))
        return
    if args.repeats < 1:
        parser.error(f"--repeats must be at least 1; got {args.repeats}")
    entries = []
    for problem in args.problems or PROBLEMS:
        entries.append(measure(problem, args.rtol, args.repeats))
        print(f"{problem}: done", file=sys.stderr, flush=True)
    result = {
        "benchmark": "radau's default machine code: first compile, cached load, break-even (issue 42)",
        "command": " ".join(["python", "benchmarks/compile_cost.py", *(sys.argv[1:] if argv is None else argv)]),
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "machine": {**scaling.machine_info(args.code_label), "load_average_at_end": list(os.getloadavg())},
        "settings": {"rtol": args.rtol, "atol": args.rtol, "repeats": args.repeats},
        "problems": entries,
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(result, indent=1, default=str))
    plot(entries, out.with_suffix(".png"))
    print(table(entries))


if __name__ == "__main__":
    main()

"""Issue 44 items 2 and 6 at scale: the PINN's refusal of a model too large for it, and the report.

Run as ``python benchmarks/refusal_and_report.py [--unknowns 10000 100000] [--full] [--out PATH]``.  The
reaction-diffusion family of ``scaling_models.py`` (declared by stencils), at each size, each job in
a fresh process (one torch and BLAS thread) that declares and compiles the model first:

* ``refuse``: ``dm.solve(compiled, (0, 1), method="pinn")`` with its defaults, which raises a
  ``ResourceLimitError`` (its dense Radau stage system does not fit): the seconds until it does, the
  error's first words, and the process's peak resident set against the one after compiling;
* ``report``: ``compiled.report()`` (the default, summarised) and, with ``--full``,
  ``compiled.report(full=True)`` (every equation): seconds, characters, lines, peak memory.

``declare_s`` and ``compile_s`` are what the model costs before either; ``*_cpu_s`` the process's CPU
seconds (the machine is shared: wall seconds carry the load).  Writes ``<out>.json``.
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

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

UNKNOWNS = (10_000, 100_000)
# Seconds a worker may take (the full report of 10^5 unknowns took 38.5 s, the compile ~10 s, on a
# loaded 2-core machine).
WORKER_LIMIT = 1_200


def peak_rss() -> int:
    """This process's peak resident set so far, in bytes (Linux reports kilobytes)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def worker(task: dict) -> dict:
    import scaling_models
    import torch

    import daemodel as dm

    torch.set_num_threads(1)
    began = time.perf_counter()
    model = scaling_models.DECLARATIONS["stencils"](task["unknowns"] // 2)
    declared = time.perf_counter()
    compiled = model.compile()
    compiled_at = time.perf_counter()
    out = {"declare_s": declared - began, "compile_s": compiled_at - declared, "rss_after_compile": peak_rss()}
    if task["job"] == "refuse":
        start, cpu = time.perf_counter(), time.process_time()
        try:
            dm.solve(compiled, (0.0, 1.0), method="pinn")
            out["error"] = None
        except dm.errors.ResourceLimitError as error:
            out["error"] = f"{type(error).__name__}: {str(error)[:160]}"
        out["refuse_s"], out["refuse_cpu_s"] = time.perf_counter() - start, time.process_time() - cpu
    else:
        start, cpu = time.perf_counter(), time.process_time()
        text = compiled.report(full=task["full"]) if task["full"] else compiled.report()
        out.update(report_s=time.perf_counter() - start, report_cpu_s=time.process_time() - cpu)
        out.update(chars=len(text), lines=text.count("\n") + 1)
    out["peak_rss"] = peak_rss()
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


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    parser.add_argument("--unknowns", type=int, nargs="+", default=list(UNKNOWNS), help="sizes (even: 2K)")
    parser.add_argument("--full", action="store_true", help="also time report(full=True)")
    parser.add_argument("--out", default=str(HERE / "refusal_and_report"), help="output path without suffix")
    args = parser.parse_args(argv)
    if args.worker:
        task = json.loads(args.worker)
        Path(task["result"]).write_text(json.dumps(worker(task)))
        return
    import daemodel

    records = []
    for unknowns in args.unknowns:
        record = {"unknowns": unknowns}
        jobs = [("refuse", False), ("report", False)] + ([("report_full", True)] if args.full else [])
        for label, full in jobs:
            print(f"{unknowns} unknowns: {label}", file=sys.stderr, flush=True)
            job = "refuse" if label == "refuse" else "report"
            record[label] = run_task({"job": job, "unknowns": unknowns, "full": full})
        records.append(record)
    root = Path(daemodel.__file__).resolve().parents[1]
    commit = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True)
    changes = subprocess.run(
        ["git", "-C", str(root), "status", "--porcelain", "--", "daemodel", "backends"], capture_output=True, text=True
    )
    result = {
        "benchmark": "the PINN's refusal and report() at scale (issue 44 items 2 and 6)",
        "command": " ".join(["python benchmarks/refusal_and_report.py", *(sys.argv[1:] if argv is None else argv)]),
        "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
        f"load {os.getloadavg()[0]:.1f} (shared)",
        "git_commit": commit.stdout.strip(),
        "uncommitted_changes": changes.stdout.strip(),
        "records": records,
    }
    Path(args.out).with_suffix(".json").write_text(json.dumps(result, indent=1) + "\n")
    for r in records:
        print(json.dumps(r))


if __name__ == "__main__":
    main()

"""dm.ensemble on 10^5 pendulum states: one batched radau call, the local engine, and Ray with 1
and 2 workers on this machine; time, agreement and peak memory per worker.

Each Ray configuration starts its own local cluster.  Its first ensemble call (cluster start,
workers importing torch and generating code) is timed apart from a second, warm call: the
warm call is what more chunks on a running cluster cost.

    python benchmarks/ensemble.py --out benchmarks/ensemble.json
"""

from __future__ import annotations

import argparse
import json
import resource
import time
from pathlib import Path

import numpy as np
import torch

import daemodel as dm
from daemodel.problems import PENDULUM


def timed(call):
    began = time.perf_counter()
    result = call()
    return time.perf_counter() - began, result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--samples", type=int, default=100_000)
    parser.add_argument("--chunk", type=int, default=10_000)
    parser.add_argument("--out", default="benchmarks/ensemble.json")
    args = parser.parse_args()
    torch.set_num_threads(1)
    c = PENDULUM.model().compile()
    rng = np.random.default_rng(0)
    B = args.samples
    y0 = c.consistent(y0={"y1": rng.uniform(0.99, 1.01, B), "y4": rng.uniform(0.99, 1.01, B)})
    span, names = (0.0, 1.0), (*c.state_names, *c.algebraic_names)
    runs = {}
    seconds, one = timed(lambda: dm.solve(c, span, h=0.05, y0=y0))
    runs["one batched radau call"] = {"seconds": seconds}
    print(runs, flush=True)

    def record(label, seconds, ensemble, first=None):
        runs[label] = {
            "seconds": seconds,
            "first_call_seconds": first,
            "max_difference_from_one_call": max(float(np.abs(ensemble[k] - one[k]).max()) for k in names),
            "failures": len(ensemble.stats["failures"]),
            "chunk_seconds": [chunk["seconds"] for chunk in ensemble.stats["chunks"]],
            "peak_memory_mb_per_task": ensemble.stats["peak_memory_mb"],
        }
        print(label, json.dumps(runs[label]), flush=True)

    seconds, local = timed(lambda: dm.ensemble(c, span, y0=y0, h=0.05, chunk=args.chunk))
    record("local", seconds, local)
    runs["local"]["peak_memory_mb_process"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    import ray

    for workers in (1, 2):
        ray.init(num_cpus=workers, log_to_driver=False, include_dashboard=False)
        first, _ = timed(lambda: dm.ensemble(c, span, y0=y0, h=0.05, chunk=args.chunk, engine="ray"))
        seconds, ensemble = timed(lambda: dm.ensemble(c, span, y0=y0, h=0.05, chunk=args.chunk, engine="ray"))
        record(f"ray, {workers} worker{'s' if workers > 1 else ''}", seconds, ensemble, first)
        ray.shutdown()
    one_worker, two_workers = runs["ray, 1 worker"]["seconds"], runs["ray, 2 workers"]["seconds"]
    out = {
        "problem": "pendulum",
        "samples": B,
        "chunk": args.chunk,
        "t_span": list(span),
        "h": 0.05,
        "stages": 3,
        "machine_cpus": __import__("os").cpu_count(),
        "torch_threads": 1,
        "speedup_2_workers_over_1": one_worker / two_workers,
        "runs": runs,
    }
    Path(args.out).write_text(json.dumps(out, indent=2) + "\n")
    print(f"speed-up of 2 workers over 1: {one_worker / two_workers:.2f}; wrote {args.out}")


if __name__ == "__main__":
    main()

"""dm.ensemble on 10^5 pendulum states: one batched radau call, the local executor (in memory and
written to files), and Ray with 1 and 2 workers on this machine; time, agreement and peak memory
per worker.  Then a Ray worker's peak memory against the chunk size, and segment-parallel PINN
training (Hessenberg, 20 segments) locally and on Ray.

Each Ray configuration starts its own local cluster.  Its first call (cluster start, workers
importing torch and generating code) is timed apart from a second, warm call: the warm call is
what more work on a running cluster costs.

    python benchmarks/ensemble.py --out benchmarks/ensemble.json   # and ensemble.png
"""

from __future__ import annotations

import argparse
import json
import resource
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

import daemodel as dm
from daemodel.problems import HESSENBERG, PENDULUM


def timed(call):
    began = time.perf_counter()
    result = call()
    return time.perf_counter() - began, result


PARTS = ("ensemble", "memory", "training", "surrogate")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--samples", type=int, default=100_000)
    parser.add_argument("--chunk", type=int, default=10_000)
    parser.add_argument("--out", default="benchmarks/ensemble.json")
    parser.add_argument(
        "--parts", nargs="+", choices=PARTS, default=list(PARTS), help="run these; keep the others' results in --out"
    )
    args = parser.parse_args()
    torch.set_num_threads(1)
    path = Path(args.out)
    out = json.loads(path.read_text()) if path.exists() and set(args.parts) != set(PARTS) else {}
    c = PENDULUM.model().compile()
    rng = np.random.default_rng(0)
    B = args.samples
    y0 = c.consistent(y0={"y1": rng.uniform(0.99, 1.01, B), "y4": rng.uniform(0.99, 1.01, B)})
    span = (0.0, 1.0)
    if "ensemble" in args.parts:
        out.update(ensemble_runs(c, span, y0, args.chunk))
    if "memory" in args.parts:
        out["worker_memory_by_chunk"] = worker_memory(c, span, y0)
    if "training" in args.parts:
        out["segment_training"] = segment_training()
    if "surrogate" in args.parts:
        out["surrogate_training"] = surrogate_training()
    path.write_text(json.dumps(out, indent=2) + "\n")
    plot(out, path.with_suffix(".png"))
    print(f"wrote {path} and {path.with_suffix('.png')}")


def ensemble_runs(c, span, y0, chunk) -> dict:
    """10^5 states: one batched call, the local executor in memory and to files, Ray 1 and 2 workers."""
    names = (*c.state_names, *c.algebraic_names)
    B = len(next(iter(y0.values())))
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
            "peak_memory_mb_per_task": np.asarray(ensemble.stats["peak_memory_mb"]).tolist(),  # stats hold arrays
        }
        print(label, json.dumps(runs[label]), flush=True)

    seconds, local = timed(lambda: dm.ensemble(c, span, y0=y0, h=0.05, chunk=chunk))
    record("local", seconds, local)
    runs["local"]["peak_memory_mb_process"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    with tempfile.TemporaryDirectory() as directory:
        seconds, files = timed(lambda: dm.ensemble(c, span, y0=y0, h=0.05, chunk=chunk, write_to=directory))
        read, back = timed(files.solution)
        runs["local, written to files"] = {
            "seconds": seconds,
            "read_back_seconds": read,
            "megabytes_written": sum(p.stat().st_size for p in Path(directory).iterdir()) / 2**20,
            "max_difference_from_one_call": max(float(np.abs(back[k] - one[k]).max()) for k in names),
        }
        print("files", json.dumps(runs["local, written to files"]), flush=True)
    del local, back
    import ray

    for workers in (1, 2):
        ray.init(num_cpus=workers, log_to_driver=False, include_dashboard=False)
        first, _ = timed(lambda: dm.ensemble(c, span, y0=y0, h=0.05, chunk=chunk, executor="ray"))
        seconds, ensemble = timed(lambda: dm.ensemble(c, span, y0=y0, h=0.05, chunk=chunk, executor="ray"))
        record(f"ray, {workers} worker{'s' if workers > 1 else ''}", seconds, ensemble, first)
        ray.shutdown()
    one_worker, two_workers = runs["ray, 1 worker"]["seconds"], runs["ray, 2 workers"]["seconds"]
    print(f"speed-up of 2 workers over 1: {one_worker / two_workers:.2f}", flush=True)
    return {
        "problem": "pendulum",
        "samples": B,
        "chunk": chunk,
        "t_span": list(span),
        "h": 0.05,
        "stages": 3,
        "machine_cpus": __import__("os").cpu_count(),
        "torch_threads": 1,
        "speedup_2_workers_over_1": one_worker / two_workers,
        "runs": runs,
    }


def worker_memory(c, span, y0) -> list:
    """A fresh one-worker cluster per chunk size (ru_maxrss only grows in a reused worker): the
    largest peak over its tasks, and the seconds per chunk."""
    import ray

    rows = []
    for chunk in (1_000, 10_000, 30_000):
        ray.init(num_cpus=1, log_to_driver=False, include_dashboard=False)
        part = {name: values[: 3 * chunk] for name, values in y0.items()}
        ensemble = dm.ensemble(c, span, y0=part, h=0.05, chunk=chunk, executor="ray")
        ray.shutdown()
        rows.append(
            {
                "chunk": chunk,
                "peak_memory_mb": float(max(ensemble.stats["peak_memory_mb"])),
                "chunk_seconds": [item["seconds"] for item in ensemble.stats["chunks"]],
            }
        )
        print("memory", json.dumps(rows[-1]), flush=True)
    return rows


def segment_training() -> dict:
    """Hessenberg on [0, 1], h = 0.05 (20 segments), the fast mode: each segment from the previous
    one's prediction, then independently from radau's start values, locally and on Ray."""
    import ray

    m = HESSENBERG.model().compile()
    span = (0.0, 1.0)
    radau = dm.solve(m, span, method="radau", stages=3, h=0.05)
    names = (*m.state_names, *m.algebraic_names)

    def entry(seconds, sol, first=None):
        return {
            "seconds": seconds,
            "first_call_seconds": first,
            "training_seconds": sol.stats["training_seconds"],
            "max_error_against_radau": max(float(np.abs(sol[k] - radau[k]).max()) for k in names),
            "segment_seconds": np.asarray(sol.stats["segment_seconds"]).tolist(),
        }

    out = {}
    out["chained, local"] = entry(*timed(lambda: dm.solve(m, span, method="pinn")))
    out["from radau starts, local"] = entry(*timed(lambda: dm.solve(m, span, method="pinn", segment_starts=radau)))
    for workers in (1, 2):
        ray.init(num_cpus=workers, log_to_driver=False, include_dashboard=False)

        def call():
            return dm.solve(m, span, method="pinn", segment_starts=radau, executor="ray")

        first, _ = timed(call)
        out[f"from radau starts, ray, {workers} worker{'s' if workers > 1 else ''}"] = entry(*timed(call), first)
        ray.shutdown()
    for label, row in out.items():
        print("training", label, f"{row['seconds']:.2f} s, error {row['max_error_against_radau']:.1e}", flush=True)
    return out


def surrogate_training() -> dict:
    """Surrogate.train on Hessenberg, 64 states from a +-2 % box over [0, 0.2] (4 segments of
    0.05; at 64 states a segment's LM works in parameter space, about 16 s each): chained, and
    from radau's solution of the training states locally and on Ray; held-out max error on 2,000
    states from the +-1 % box against batched radau at the same s and h."""
    import ray

    from daemodel.compiling.initial_states import project_states

    m = HESSENBERG.model().compile()
    span, box = (0.0, 0.2), {name: (0.98, 1.02) for name in m.state_names}
    rng = np.random.default_rng(1)
    y0 = project_states(m, rng.uniform(0.99, 1.01, (2000, 4)), np.zeros((2000, 0)))
    radau = dm.solve(m, span, method="radau", stages=3, h=0.05, y0=y0)

    def entry(seconds, surrogate, first=None):
        sol = surrogate.solve(y0=y0)
        return {
            "seconds": seconds,
            "first_call_seconds": first,
            "held_out_max_error_y": max(float(np.abs(sol[k] - radau[k]).max()) for k in m.state_names),
            "held_out_max_error_z": max(float(np.abs(sol[k] - radau[k]).max()) for k in m.algebraic_names),
            "segment_seconds": [s.seconds for s in surrogate.stats],
        }

    def train(**options):
        return dm.Surrogate.train(m, span, box=box, samples=64, **options)

    out = {"chained, local": entry(*timed(train))}
    print("surrogate chained", json.dumps(out["chained, local"]), flush=True)
    out["from radau starts, local"] = entry(*timed(lambda: train(starts="radau")))
    for workers in (1, 2):
        ray.init(num_cpus=workers, log_to_driver=False, include_dashboard=False)
        label = f"from radau starts, ray, {workers} worker{'s' if workers > 1 else ''}"
        out[label] = entry(*timed(lambda: train(starts="radau", executor="ray")))  # the cluster's first call
        print("surrogate", label, json.dumps(out[label]), flush=True)
        ray.shutdown()
    return out


def plot(out: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(13, 8))
    axes = axes.ravel()
    runs = out["runs"]
    labels = list(runs)
    axes[0].barh(labels, [runs[k]["seconds"] for k in labels], color="tab:blue", label="warm call")
    firsts = [runs[k].get("first_call_seconds") or 0 for k in labels]
    axes[0].barh(labels, firsts, color="none", edgecolor="tab:red", label="first call (workers start)")
    axes[0].set_xlabel("seconds")
    axes[0].set_title(f"{out['samples']:,} pendulum states, chunks of {out['chunk']:,}")
    axes[0].legend(loc="lower right", fontsize=8)
    memory = out["worker_memory_by_chunk"]
    axes[1].plot([r["chunk"] for r in memory], [r["peak_memory_mb"] for r in memory], "o-")
    axes[1].set_xlabel("samples per chunk")
    axes[1].set_ylabel("peak memory of a Ray worker (MB)")
    axes[1].set_title("memory per task")
    training = out["segment_training"]
    labels = list(training)
    axes[2].barh(labels, [training[k]["seconds"] for k in labels], color="tab:green")
    axes[2].set_xlabel("seconds (warm)")
    axes[2].set_title("PINN, Hessenberg, 20 segments")
    surrogate = out["surrogate_training"]
    labels = list(surrogate)
    axes[3].barh(labels, [surrogate[k]["seconds"] for k in labels], color="tab:purple")
    axes[3].set_xlabel("seconds (on Ray: a new cluster, its workers starting)")
    axes[3].set_title("Surrogate.train, Hessenberg, 64 states, 4 segments")
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    main()

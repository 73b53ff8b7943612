"""GPU checks and timings, for a session lent a CUDA machine (results: gpu_probe.json).

* Adam per iteration on the paper's networks: one captured CUDA graph per iteration against the
  eager loop on the same GPU, and the eager loop on one CPU thread (the first GPU run of a
  process includes CUDA's start-up);
* fast-mode PINN on CUDA against the CPU and against radau on CUDA (the ceiling);
* a surrogate (16 states, +-1 % box, [0, 0.25]) loaded on CUDA: networks, estimate and Newton
  from the networks against batched radau on CUDA at 10^3 ... 10^5 queries.

    PYTHONPATH=... python benchmarks/gpu_probe.py      # writes $OUT/probe.json (or /tmp)
"""

import json
import os
import time
import traceback

import numpy as np
import torch
from daemodel.backends.pinn import first_order

import daemodel as dm
from daemodel.problems import HESSENBERG, PENDULUM

OUT = os.environ.get("OUT", "/tmp")
res = {"torch": torch.__version__, "gpu": torch.cuda.get_device_name(0)}
PROBLEMS = {"hessenberg": HESSENBERG, "pendulum": PENDULUM}
graphed = first_order.adam_graphed


def save():
    (open(f"{OUT}/probe.json", "w")).write(json.dumps(res, indent=1, default=str))


def paper(name, iters, device, mode):
    first_order.adam_graphed = graphed if mode == "graph" else first_order.adam_eager
    c = PROBLEMS[name].model().compile()
    cfg = dm.PINNConfig.paper(name, iterations=iters, device=device)
    t0 = time.perf_counter()
    s = dm.solve(c, (0.0, cfg.h), method="pinn", config=cfg, progress=False)
    sec = time.perf_counter() - t0
    r = {
        "seconds": sec,
        "per_iter_ms": 1e3 * s.stats["segment_seconds"][0] / iters,
        "L_f": s.stats["L_f"][0],
        "L_g": s.stats["L_g"][0],
        "L_s": s.stats["L_s"][0],
        "end": {k: float(s[k][-1]) for k in (*c.state_names, *c.algebraic_names)},
    }
    print(name, device, mode, iters, json.dumps(r), flush=True)
    return r


for name in PROBLEMS:
    for device, mode, iters in (("cuda", "graph", 3000), ("cuda", "eager", 1000), ("cuda", "graph", 1000)):
        try:
            res[f"paper/{name}/{device}/{mode}/{iters}"] = paper(name, iters, device, mode)
        except Exception as e:
            res[f"paper/{name}/{device}/{mode}/{iters}"] = repr(e)[:2000]
            print("FAILED", name, mode, repr(e)[:2000], flush=True)
        save()
torch.set_num_threads(1)
for name in PROBLEMS:
    try:
        res[f"paper/{name}/cpu/eager/300"] = paper(name, 300, "cpu", "eager")
    except Exception as e:
        res[f"paper/{name}/cpu/eager/300"] = repr(e)[:2000]
    save()
first_order.adam_graphed = graphed

# fast LM on cuda against cpu
for name, prob in PROBLEMS.items():
    c = prob.model().compile()
    try:
        a = dm.solve(c, (0.0, 1.0), method="pinn", progress=False)
        b = dm.solve(c, (0.0, 1.0), method="pinn", config=dm.PINNConfig(device="cuda"), progress=False)
        rr = dm.solve(c, (0.0, 1.0), method="radau", stages=3, h=0.05, device="cuda")
        res[f"lm/{name}"] = {
            "cpu_vs_cuda": max(float(np.abs(a[k] - b[k]).max()) for k in (*c.state_names, *c.algebraic_names)),
            "cuda_vs_radau_cuda": max(float(np.abs(rr[k] - b[k]).max()) for k in (*c.state_names, *c.algebraic_names)),
            "cuda_seconds": b.stats.get("train_seconds", None),
        }
    except Exception as e:
        res[f"lm/{name}"] = repr(e)[:2000]
    print(name, res[f"lm/{name}"], flush=True)
    save()

# surrogate: train on cpu, load on cuda, solve with 1e3..1e5 queries vs batched radau on cuda
torch.set_num_threads(8)
for name, prob in PROBLEMS.items():
    c = prob.model().compile()
    boxed = ("y1", "y4") if name == "pendulum" else ("y1", "y2")
    box = {s: (0.99 * c.y0[i], 1.01 * c.y0[i]) for i, s in enumerate(c.state_names) if s in boxed}
    try:
        sur = dm.Surrogate.train(c, (0.0, 0.25), box=box, samples=16, progress=False)
        sur.save(f"/tmp/{name}.pt")
        g = dm.Surrogate.load(f"/tmp/{name}.pt", c, device="cuda")
        rows = []
        for Q in (1000, 10000, 100000):
            rng = np.random.default_rng(1)
            y = {s: np.full(Q, c.y0[i]) for i, s in enumerate(c.state_names)}
            for s, (lo, hi) in box.items():
                y[s] = rng.uniform(lo, hi, Q)
            y0 = c.consistent(y0=y)
            row = {"queries": Q}
            for label, call in (
                ("networks", lambda g=g, y0=y0: g.solve(y0=y0, outside="ignore")),
                ("estimate", lambda g=g, y0=y0: g.solve(y0=y0, outside="ignore", estimate=True)),
                ("newton", lambda g=g, y0=y0: g.solve(y0=y0, outside="ignore", newton=True)),
                ("radau", lambda c=c, y0=y0: dm.solve(c, (0.0, 0.25), h=0.05, stages=3, y0=y0, device="cuda")),
            ):
                best = 1e9
                for _ in range(3):
                    torch.cuda.synchronize()
                    t0 = time.perf_counter()
                    sol = call()
                    torch.cuda.synchronize()
                    best = min(best, time.perf_counter() - t0)
                row[label] = best
                if label == "radau":
                    row["radau_newton_iterations"] = sol.stats.get("newton_iterations")
                if label == "newton":
                    row["hybrid_newton_iterations"] = sol.stats.get("newton_iterations")
            print(name, row, flush=True)
            rows.append(row)
        res[f"surrogate/{name}"] = rows
    except Exception as e:
        import traceback

        traceback.print_exc()
        res[f"surrogate/{name}"] = repr(e)[:2000]
    save()
print("done")

"""Issue 15's paths on CUDA, for a session lent a GPU machine (results: gpu_issue15.json).

* Hessenberg, 20 segments trained independently from radau's start values (the local executor),
  on the CPU and on CUDA (warm: the second call of each);
* ``Surrogate.train(starts="radau")``, 64 states from a +-2 % box over [0, 0.2], on the CPU and
  on CUDA, with the held-out max error on 500 states from the +-1 % box;
* ``executor="ray"`` with ``device="cuda"``: the error it raises;
* 10^5 pendulum states by radau on CUDA: one call against ensembles of chunks of 10^4 and 5*10^4.

    PYTHONPATH=... OUT=... python benchmarks/gpu_issue15.py
"""

import json
import os
import time
import warnings

import numpy as np
import torch

import daemodel as dm
from daemodel.compiling.initial_states import project_states
from daemodel.errors import InvalidOptionError
from daemodel.problems import HESSENBERG, PENDULUM


def timed(call):
    began = time.perf_counter()
    result = call()
    return time.perf_counter() - began, result


def largest(a, b, names) -> float:
    return max(float(np.abs(a[k] - b[k]).max()) for k in names)


def main() -> None:
    warnings.simplefilter("ignore")
    out = {"gpu": torch.cuda.get_device_name(0), "torch": torch.__version__}
    c = HESSENBERG.model().compile()
    radau = dm.solve(c, (0.0, 1.0), method="radau", stages=3, h=0.05)
    names = (*c.state_names, *c.algebraic_names)
    for device in ("cpu", "cuda"):
        config = dm.PINNConfig(device=device)

        def segments(config=config):
            return dm.solve(c, (0.0, 1.0), method="pinn", segment_starts=radau, config=config)

        segments()  # warm-up
        seconds, sol = timed(segments)
        out[f"segments from radau starts, {device}"] = {
            "seconds": seconds,
            "max_error_vs_radau": largest(sol, radau, names),
        }
    try:
        dm.solve(
            c, (0.0, 1.0), method="pinn", segment_starts=radau, executor="ray", config=dm.PINNConfig(device="cuda")
        )
    except InvalidOptionError as error:
        out["ray with cuda"] = str(error)

    box = {name: (0.98, 1.02) for name in c.state_names}
    rng = np.random.default_rng(0)
    y0 = project_states(c, rng.uniform(0.99, 1.01, (500, 4)), np.zeros((500, 0)))
    reference = dm.solve(c, (0.0, 0.2), method="radau", stages=3, h=0.05, y0=y0)
    for device in ("cpu", "cuda"):
        config = dm.PINNConfig(width=16, warm_start=False, tol=None, iterations=40, device=device)
        seconds, surrogate = timed(
            lambda config=config: dm.Surrogate.train(c, (0.0, 0.2), box=box, samples=64, config=config, starts="radau")
        )
        sol = surrogate.solve(y0=y0)
        out[f"surrogate starts=radau, 64 states, 4 segments, {device}"] = {
            "seconds": seconds,
            "held_out_y": largest(sol, reference, c.state_names),
            "held_out_z": largest(sol, reference, c.algebraic_names),
        }
        print(out, flush=True)

    p = PENDULUM.model().compile()
    B = 100_000
    rng = np.random.default_rng(0)
    states = p.consistent(y0={"y1": rng.uniform(0.99, 1.01, B), "y4": rng.uniform(0.99, 1.01, B)})
    dm.solve(p, (0.0, 1.0), h=0.05, y0={k: v[:100] for k, v in states.items()}, device="cuda")  # warm-up
    seconds, one = timed(lambda: dm.solve(p, (0.0, 1.0), h=0.05, y0=states, device="cuda"))
    out["pendulum 1e5 one radau call, cuda"] = seconds
    for chunk in (10_000, 50_000):
        seconds, ensemble = timed(
            lambda chunk=chunk: dm.ensemble(p, (0.0, 1.0), y0=states, h=0.05, chunk=chunk, device="cuda")
        )
        out[f"pendulum 1e5 ensemble chunk {chunk}, cuda"] = {
            "seconds": seconds,
            "max_diff_vs_one_call": largest(ensemble, one, ("y1", "y2", "y3", "y4", "y5")),
        }
    print(json.dumps(out, indent=1))
    with open(os.path.join(os.environ.get("OUT", "/tmp"), "gpu_issue15.json"), "w") as handle:
        json.dump(out, handle, indent=1)


if __name__ == "__main__":
    main()

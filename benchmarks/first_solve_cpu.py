"""Issue 44, item 5: a fresh process's first solve at 10^4 / 10^5 unknowns, its clocks in CPU seconds.

Run one cell per fresh process as ``python benchmarks/first_solve_cpu.py UNKNOWNS METHOD RTOL`` (atol = rtol /
100, 11 output times on [0, 1], reaction-diffusion declared by stencils); it prints one JSON line.  The
Solution's clocks (``setup_time``, ``solve_time``) are read from this one-thread process's CPU time
(``time.perf_counter`` replaced by ``time.process_time`` before any solve), so that a machine shared with
other jobs (load 6-11 on 2 cores when ``first_solve_cpu.json`` was measured: wall clocks 2-3.5x their quiet
values) does not decide the comparison; page faults and the kernel's page clearing are counted (sys time).
With ``DAEMODEL_OLD_PATHS=1`` the three changes of 7ac3759 and 49d6374 are patched back out (Newton's
increment with its temporaries, the packed inputs made by ``np.concatenate``, no band buffers reserved in
the setup): the "before" cells.  With ``DAEMODEL_NO_STENCIL=1`` radau's stage residual stays on casadi's
virtual machine (``backends/radau/stencil.py`` patched out: the "-nostencil" cells, the same bits).  The
errors are those of ``scaling_large.json`` (the same bits).
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
time.perf_counter = time.process_time  # (the backends' clocks: CPU seconds of this one-thread process)
sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402
import scaling_models  # noqa: E402
import torch  # noqa: E402

import daemodel as dm  # noqa: E402


def main() -> None:
    torch.set_num_threads(1)
    unknowns, method, rtol = int(sys.argv[1]), sys.argv[2], float(sys.argv[3])
    old = bool(os.environ.get("DAEMODEL_OLD_PATHS"))
    if old:
        from daemodel.backends.radau import band, casadi_engine
        from daemodel.backends.radau import compiled as radau_compiled

        casadi_engine.IncrementBuffers = lambda *args: None
        radau_compiled.Buffered.packed = lambda self, *parts: self(np.concatenate([np.ravel(p) for p in parts]))
        band.BandKernel.reserve = lambda self, counts: None
    nostencil = bool(os.environ.get("DAEMODEL_NO_STENCIL"))
    if nostencil:
        from daemodel.backends.radau import stencil

        stencil.stencil_equations = lambda *args: (None, "off")
    compiled = scaling_models.DECLARATIONS["stencils"](unknowns // 2).compile()
    times = np.linspace(0.0, 1.0, 11)
    sol = dm.solve(compiled, (0.0, 1.0), method=method, rtol=rtol, atol=rtol / 100, t_eval=times)
    suffix = ("-before" if old else "") + ("-nostencil" if nostencil else "")
    cell = {"unknowns": unknowns, "method": method + suffix, "rtol": rtol}
    print(json.dumps({**cell, "setup_cpu": sol.setup_time, "solve_cpu": sol.solve_time, "load": os.getloadavg()[0]}))


if __name__ == "__main__":
    main()

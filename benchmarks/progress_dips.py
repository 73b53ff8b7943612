"""Stiff layers and the progress watch's dips (backends/progress.py): counts, not times.

Van der Pol, ``y1' = y2, y2' = ((1 - y1^2) y2 - y1) / eps`` from (2, -0.66), is solved by radau at
rtol = atol in :data:`TOLERANCES`, three and five stages, over the spans of :data:`CASES`, with the
default budget (max_steps = 100,000).  Each record keeps the outcome (status, attempts, or the
error's class and where it stopped) and the longest dip the watch saw: windows of
``PROGRESS_WINDOW`` attempts in a row with h below ``DIP_FACTOR`` of the largest step taken (read
from a watch that records, around the real one).  A dip may take ``DIP_SHARE`` of max_steps (at
least ``DIP_WINDOWS`` windows) before its projections count; a fixed 10 windows (before a9f579d)
stopped the three-stage solves whose longest dip is above 10 windows, whatever max_steps.  Three stages
at rtol 1e-12 over [0, 11] need more than the budget (170,022 and 216,184 attempts with max_steps = 10**6,
both "success"): their StepLimitError is the right answer.

Writes ``<out>.json`` and prints a markdown table.

Run: python benchmarks/progress_dips.py [--out PATH]
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse
import datetime
import json
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
# (eps, t1): one jump and two (eps = 1e-10 over [0, 2]), six (eps = 1e-6 and 1e-8 over [0, 11])
CASES = [(1e-6, 11.0), (1e-8, 11.0), (1e-10, 2.0)]
TOLERANCES = (1e-4, 1e-6, 1e-8, 1e-10, 1e-12)
STAGES = (3, 5)


def van_der_pol(eps: float):
    import daemodel as dm

    m = dm.Model("vdp")
    m.states("y1 y2")
    m.ode("y1", "y2")
    m.ode("y2", f"((1 - y1**2)*y2 - y1)/{eps}")
    m.initial(y1=2.0, y2=-0.66)
    return m.compile()


def longest_dips(progress) -> list:
    """Patch ``progress.ProgressWatch.hopeless`` to record each watch's longest dip (in windows); the list
    of those records (one per watch, i.e. per solve)."""
    seen, original = [], progress.ProgressWatch.hopeless

    def hopeless(self, count, t, h, t1, budget, extra=None, accepted=None):
        _, count_w, h_w, _ = self.start
        if count - count_w >= progress.PROGRESS_WINDOW and count < budget:
            if not hasattr(self, "_record"):
                self._record = {"now": 0, "longest": 0}
                seen.append(self._record)
            low = max(abs(h), abs(h_w)) < progress.DIP_FACTOR * self.h_max
            self._record["now"] = self._record["now"] + 1 if low else 0
            self._record["longest"] = max(self._record["longest"], self._record["now"])
        return original(self, count, t, h, t1, budget, extra, accepted)

    progress.ProgressWatch.hopeless = hopeless
    return seen


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=str(HERE / "progress_dips"))
    args = parser.parse_args()
    import torch

    torch.set_num_threads(1)
    from daemodel.backends import progress

    import daemodel as dm
    from daemodel.errors import SolverError

    seen = longest_dips(progress)
    records = []
    for eps, t1 in CASES:
        compiled = van_der_pol(eps)
        for stages in STAGES:
            for tol in TOLERANCES:
                before = len(seen)
                record = {"eps": eps, "t1": t1, "stages": stages, "rtol": tol}
                try:
                    sol = dm.solve(compiled, (0.0, t1), stages=stages, rtol=tol, atol=tol)
                    record.update(outcome=sol.status, attempts=sol.stats["attempts"])
                except SolverError as error:
                    record.update(outcome=type(error).__name__, error=str(error)[:200])
                record["longest_dip_windows"] = max((r["longest"] for r in seen[before:]), default=0)
                records.append(record)
                print(record, file=sys.stderr)
    meta = {
        "command": "python benchmarks/progress_dips.py",
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "dip": {"DIP_FACTOR": progress.DIP_FACTOR, "DIP_WINDOWS": progress.DIP_WINDOWS,
                "DIP_SHARE": progress.DIP_SHARE, "PROGRESS_WINDOW": progress.PROGRESS_WINDOW},
    }  # fmt: skip
    Path(args.out + ".json").write_text(json.dumps({"meta": meta, "records": records}, indent=1) + "\n")
    print("| eps | t1 | stages | rtol | outcome | attempts | longest dip (windows) |")
    print("|---|---|---|---|---|---|---|")
    for r in records:
        print(f"| {r['eps']:g} | {r['t1']:g} | {r['stages']} | {r['rtol']:g} | {r['outcome']} | "
              f"{r.get('attempts', '')} | {r['longest_dip_windows']} |")  # fmt: skip


if __name__ == "__main__":
    main()

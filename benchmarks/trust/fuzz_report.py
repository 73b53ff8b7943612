"""Count how daemodel fails on fuzz cases, per outcome and per category.

The cases and the classifier live in ``tests/solving/fuzz_cases.py`` (its docstring defines the
outcomes).  Every run includes the fixed cases (the issue's own, hostile strings, model, API and
CLI edges) plus ``--cases`` random ones drawn from ``--seed``.  The code under test is whichever
``daemodel`` Python imports: the installed one, or the one that ``PYTHONPATH`` puts first.

After (the current checkout)::

    OMP_NUM_THREADS=1 python benchmarks/trust/fuzz_report.py --cases 300 --seed 1 --timeout 20 --jobs 2 \\
        --out benchmarks/trust/fuzz_after.json

Before (commit aeec8f3, in a separate clone; ``backends/`` installs as ``daemodel.backends``)::

    git clone -q /work/main /tmp/before && git -C /tmp/before checkout -q aeec8f3
    ln -s /tmp/before/backends /tmp/before/daemodel/backends
    OMP_NUM_THREADS=1 PYTHONPATH=/tmp/before python benchmarks/trust/fuzz_report.py --cases 300 --seed 1 \\
        --timeout 20 --jobs 2 --out benchmarks/trust/fuzz_before.json

It prints a table of counts (category x outcome), writes the JSON (counts; every non-ok case
with its category, description, outcome, exception type and message, and a program that
reproduces it) and a bar chart next to it (same name, ``.png``).  A hang costs ``--timeout``
seconds; 880 cases take about 15 minutes on two cores.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests" / "solving"))

import fuzz_cases as F  # noqa: E402 - after the path to tests/solving/

# One colour per outcome, "ok" green and the failures from worst to mildest.
COLOURS = {
    "ok": "#4caf50",
    "code-executed": "#000000",
    "raw-exception": "#e53935",
    "hang": "#8e24aa",
    "silently-wrong": "#fb8c00",
    "refused-valid": "#1e88e5",
}


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--cases", type=int, default=300, help="random cases besides the fixed ones (default 300)")
    p.add_argument("--seed", type=int, default=1, help="seed of the random cases (default 1)")
    p.add_argument(
        "--timeout", type=float, default=20.0, help="seconds per case before it counts as a hang (default 20)"
    )
    p.add_argument("--jobs", type=int, default=2, choices=(1, 2), help="cases at a time (default 2)")
    p.add_argument("--out", default="benchmarks/trust/fuzz_after.json", help="JSON path; the PNG goes next to it")
    p.add_argument("--no-fixed", action="store_true", help="random cases only")
    p.add_argument("--category", action="append", help="only these categories (repeatable)")
    p.add_argument("--quiet", action="store_true", help="no line per failing case while running")
    return p.parse_args(argv)


def code_version(path: str | None) -> dict:
    """Git commit and number of modified files of the repository holding the code under test."""
    if not path:
        return {}
    repo = os.path.dirname(path.rstrip(os.sep))
    try:
        rev = subprocess.run(
            ["git", "-C", repo, "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True
        )
        status = subprocess.run(
            ["git", "-C", repo, "status", "--porcelain", "--untracked-files=no"],
            capture_output=True,
            text=True,
            check=True,
        )
    except (OSError, subprocess.CalledProcessError):
        return {"repository": repo}
    return {"repository": repo, "commit": rev.stdout.strip(), "modified_files": len(status.stdout.splitlines())}


def table(results: list[dict]) -> str:
    cats = [c for c in F.CATEGORIES if any(r["category"] == c for r in results)]
    counts = collections.Counter((r["category"], r["outcome"]) for r in results)
    width = max(14, *(len(c) for c in cats)) + 2
    head = f"{'category':<{width}}" + "".join(f"{o:>16}" for o in F.OUTCOMES) + f"{'total':>8}"
    lines = [head, "-" * len(head)]
    for c in cats:
        row = [counts[(c, o)] for o in F.OUTCOMES]
        lines.append(f"{c:<{width}}" + "".join(f"{n:>16}" for n in row) + f"{sum(row):>8}")
    totals = [sum(counts[(c, o)] for c in cats) for o in F.OUTCOMES]
    lines += ["-" * len(head), f"{'all':<{width}}" + "".join(f"{n:>16}" for n in totals) + f"{sum(totals):>8}"]
    return "\n".join(lines)


def plot(results: list[dict], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    cats = [c for c in F.CATEGORIES if any(r["category"] == c for r in results)]
    counts = collections.Counter((r["category"], r["outcome"]) for r in results)
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(15, 6), gridspec_kw={"width_ratios": [3, 1]})
    y = np.arange(len(cats))
    left = np.zeros(len(cats))
    for outcome in F.OUTCOMES:
        n = np.array([counts[(c, outcome)] for c in cats], dtype=float)
        ax.barh(y, n, left=left, color=COLOURS[outcome], label=outcome, edgecolor="white", linewidth=0.5)
        for i, v in enumerate(n):
            if v >= 4 and outcome != "ok":
                ax.text(left[i] + v / 2, y[i], str(int(v)), ha="center", va="center", color="white", fontsize=8)
        left += n
    ax.set_yticks(y, cats)
    ax.invert_yaxis()
    ax.set_xlabel("cases")
    ax.set_title("outcome per category")
    ax.legend(loc="lower right", fontsize=8)
    failures = [o for o in F.OUTCOMES if o != "ok"]
    totals = [sum(counts[(c, o)] for c in cats) for o in failures]
    ax2.bar(range(len(failures)), totals, color=[COLOURS[o] for o in failures])
    for i, v in enumerate(totals):
        ax2.text(i, v, str(v), ha="center", va="bottom", fontsize=9)
    ax2.set_xticks(range(len(failures)), failures, rotation=30, ha="right")
    ax2.set_title("failures, all categories")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    args = parse_args(argv)
    began = time.time()
    fixed = [] if args.no_fixed else F.fixed_cases()
    random_ = F.random_cases(args.cases, seed=args.seed) if args.cases > 0 else []
    cases = [c for c in fixed + random_ if not args.category or c.category in args.category]
    print(
        f"{len(cases)} cases ({len(fixed)} fixed, {len(random_)} random, seed {args.seed}), generated in "
        f"{time.time() - began:.0f} s; timeout {args.timeout:g} s, {args.jobs} at a time",
        flush=True,
    )
    done = [0]

    def report(record):
        done[0] += 1
        if record["outcome"] != "ok" and not args.quiet:
            what = record.get("error_type") or ""
            why = (record.get("message") or record.get("why") or "")[:110]
            head = f"[{done[0]:4d}/{len(cases)}] {record['outcome']:<15}{record['id']:<28}"
            print(f"{head}{record['description'][:70]!r} {what}: {why}", flush=True)

    results, meta = F.run_cases(cases, timeout=args.timeout, jobs=args.jobs, on_result=report)
    by_id = {c.id: c for c in cases}
    counts = collections.Counter(r["outcome"] for r in results)
    by_category = {
        c: {o: sum(1 for r in results if r["category"] == c and r["outcome"] == o) for o in F.OUTCOMES}
        for c in F.CATEGORIES
        if any(r["category"] == c for r in results)
    }
    version = code_version(meta.get("daemodel"))
    out = {
        "meta": {
            "command": " ".join(
                [
                    os.path.relpath(sys.argv[0], ROOT) if argv is None else "fuzz_report.py",
                    *(sys.argv[1:] if argv is None else argv),
                ]
            ),
            "pythonpath": os.environ.get("PYTHONPATH", ""),
            **meta,
            **version,
            "seed": args.seed,
            "random_cases": len(random_),
            "fixed_cases": len(fixed),
            "cases": len(cases),
            "timeout_s": args.timeout,
            "jobs": args.jobs,
            "started": time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(began)),
            "duration_s": round(time.time() - began, 1),
        },
        "counts": {o: counts.get(o, 0) for o in F.OUTCOMES},
        "by_category": by_category,
        "by_expect": {
            e: {o: sum(1 for r in results if r["expect"] == e and r["outcome"] == o) for o in F.OUTCOMES}
            for e in F.EXPECTS
        },
        "non_ok": [
            {
                **{
                    k: r.get(k)
                    for k in (
                        "id",
                        "category",
                        "description",
                        "expect",
                        "outcome",
                        "error_type",
                        "message",
                        "where",
                        "why",
                        "seconds",
                    )
                },
                "program": by_id[r["id"]].program()[:3000],
            }
            for r in results
            if r["outcome"] != "ok"
        ],
        "cases": [
            {k: r.get(k) for k in ("id", "category", "expect", "outcome", "error_type", "seconds")} for r in results
        ],
    }
    path = Path(args.out)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=1, default=str) + "\n")
    where = version.get("commit", "") + (
        f" + {version['modified_files']} modified" if version.get("modified_files") else ""
    )
    title = f"daemodel fuzz: {len(cases)} cases on {meta.get('daemodel', '?')} {where}"
    title += f" (seed {args.seed}, timeout {args.timeout:g} s)"
    plot(results, path.with_suffix(".png"), title)
    print()
    print(title)
    print(table(results))
    print(f"\nwrote {path} and {path.with_suffix('.png')} in {time.time() - began:.0f} s")
    if meta.get("import_error") or meta.get("runner_error"):
        print(f"runner: {meta.get('import_error') or meta.get('runner_error')}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())

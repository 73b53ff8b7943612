"""The markdown tables of docs/benchmarks/bench.md, read from a `daemodel bench` results.json.

    python benchmarks/bench_tables.py bench/results.json            # most digits per problem, against radau
    python benchmarks/bench_tables.py b10/results.json --at-one-tolerance   # one row per problem and method

Nothing is solved here: the runs are the report's.
"""

from __future__ import annotations

import argparse
import collections
import json
from pathlib import Path

from daemodel.comparing.bench_report import AGAINST_RADAU_HEAD, against_radau_cells


def seconds(value: float) -> str:
    return f"{value * 1e3:.3g} ms" if value < 1 else f"{value:.3g} s"


def cell(text: str) -> str:
    """A markdown table cell: a '|' in a method's settings or error would end it."""
    return str(text).replace("|", "\\|")


def row(cells) -> str:
    return "| " + " | ".join(cell(c) for c in cells) + " |"


def most_digits(results: dict) -> list[str]:
    """Per problem and method: the largest scd of a successful run and its solve time (of ties, the
    fastest, as the report's table against radau takes), or what happened."""
    methods, runs = results["methods"], results["runs"]
    best, other = {}, collections.defaultdict(collections.Counter)
    for run in runs:
        key = (run["problem"], run["method"])
        if run["status"] == "success" and run["scd"] is not None:
            if key not in best or (run["scd"], -run["solve_time"]) > (best[key]["scd"], -best[key]["solve_time"]):
                best[key] = run
        else:
            other[key][run["error_class"] or run["status"]] += 1
    lines = ["| problem | " + " | ".join(methods) + " |", "|---|" + "---:|" * len(methods)]
    for problem in (p["name"] for p in results["problems"]):
        cells = []
        for method in methods:
            if (problem, method) in best:
                run = best[(problem, method)]
                cells.append(f"{run['scd']:.1f} ({seconds(run['solve_time'])})")
            else:
                counts = other[(problem, method)]
                what = ", ".join(f"{n} {k}" if n > 1 else k for k, n in sorted(counts.items()))
                cells.append("none: " + (what or "no run"))
        lines.append(row([problem, *cells]))
    return lines


def at_one_tolerance(results: dict) -> list[str]:
    """One column per method: scd (the component it is read from, solve time) of its single setting;
    a results.json with more than one run of a method on a problem is refused (SystemExit naming it)."""
    methods = results["methods"]
    rows = collections.defaultdict(dict)
    for run in results["runs"]:
        if run["method"] in rows[run["problem"]]:
            raise SystemExit(
                f"{run['method']} has more than one run on {run['problem']} ({run.get('settings')}): "
                "--at-one-tolerance reads a bench of one setting per method (--tolerances with one value)"
            )
        rows[run["problem"]][run["method"]] = run
    lines = ["| problem | " + " | ".join(methods) + " |", "|---|" + "---:|" * len(methods)]
    for problem in (p["name"] for p in results["problems"]):
        cells = []
        for method in methods:
            run = rows[problem].get(method)
            if run is None:
                cells.append("")
            elif run["status"] == "success":
                cells.append(f"{run['scd']:.1f} ({run['scd_component']}, {seconds(run['solve_time'])})")
            else:
                cells.append(f"{run['status']}: {run['error_class'] or run['flag'] or run['reason']}")
        lines.append(row([problem, *cells]))
    return lines


def against_radau_table(results: dict) -> list[str]:
    lines = ["| " + " | ".join(AGAINST_RADAU_HEAD) + " |", "|---|---|---|---|---:|"]
    lines += [row(against_radau_cells(r)) for r in results.get("against_radau", [])]
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("results", type=Path, help="a results.json that `daemodel bench` wrote")
    parser.add_argument("--at-one-tolerance", action="store_true", help="one run per problem and method")
    args = parser.parse_args()
    results = json.loads(args.results.read_text())
    if args.at_one_tolerance:
        print("\n".join(at_one_tolerance(results)))
        return
    print("\n".join(most_digits(results)))
    print()
    print("\n".join(against_radau_table(results)))


if __name__ == "__main__":
    main()

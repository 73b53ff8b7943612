"""A benchmark's report: per problem a work-precision plot (significant correct digits at the end
against time, one line per method), a summary table per method, every run; as one self-contained
HTML file (plots inline as base64 PNG), ``results.json`` and ``results.csv``.

In the plots a success is a filled circle on its method's line, a flagged run a hollow square off
the line, a failure an ``x`` on the row labelled "failed" below the digits, at the time it took to
fail.  The left panel places each run by its solve time, the right one by setup + solve (the wall:
the PINN's training, the compiled code's build), so a method that prepares for long is seen both
ways.
"""

from __future__ import annotations

import base64
import csv
import html
import io
import math
from collections import Counter
from pathlib import Path

import numpy as np

from daemodel.files import atomic_write, write_json

# The digits the summary reports each method's time to reach.
TARGET_DIGITS = (6, 8, 10)
CSV_FIELDS = (
    "problem", "method", "index", "settings", "status", "scd", "scd_component", "setup_time", "solve_time",
    "wall_time", "error_class", "error", "flag", "reason",
)  # fmt: skip
PLOT_DPI = 110


def summary(records, methods, problems) -> list[dict]:
    """Per method: ``problems_solved`` (a successful run with scd >= 1 on it), for each target digit
    ``d`` ``time_to_d``: the median over the problems where it got there of its fastest successful
    solve reaching ``d`` digits (seconds; None where none) and ``reached_d`` (on how many problems),
    ``failures``: error class -> count, ``flagged`` and ``skipped`` counts."""
    out = []
    for method in methods:
        runs = [r for r in records if r["method"] == method]
        good = [r for r in runs if r["status"] == "success" and r["scd"] is not None]
        row = {
            "method": method,
            "problems": len(problems),
            "problems_solved": len({r["problem"] for r in good if r["scd"] >= 1}),
            "runs": len(runs),
            "flagged": sum(r["status"] == "flagged" for r in runs),
            "skipped": sum(r["status"] == "skipped" for r in runs),
            "failures": dict(Counter(r["error_class"] for r in runs if r["status"] == "failed")),
        }
        for digits in TARGET_DIGITS:
            fastest = [
                min(r["solve_time"] for r in good if r["problem"] == p.name and r["scd"] >= digits)
                for p in problems
                if any(r["problem"] == p.name and r["scd"] >= digits for r in good)
            ]
            row[f"time_to_{digits}"] = float(np.median(fastest)) if fastest else None
            row[f"reached_{digits}"] = len(fastest)
        out.append(row)
    return out


def summary_text(rows: list[dict], problems: int) -> str:
    """The summary rows as a text table."""
    head = ["method", "solved", *(f"t({d} scd)" for d in TARGET_DIGITS), "flagged", "skipped", "failures"]
    lines = [head]
    for row in rows:
        lines.append(
            [
                row["method"],
                f"{row['problems_solved']}/{problems}",
                *(_time_cell(row, d, problems) for d in TARGET_DIGITS),
                str(row["flagged"]),
                str(row["skipped"]),
                ", ".join(f"{n} {name}" for name, n in sorted(row["failures"].items())) or "-",
            ]
        )
    widths = [max(len(line[i]) for line in lines) for i in range(len(head))]
    text = ["  ".join(cell.ljust(w) for cell, w in zip(line, widths, strict=True)).rstrip() for line in lines]
    text.insert(1, "  ".join("-" * w for w in widths))
    return (
        "\n".join(text)
        + f"\nt(d scd): median over the problems reached (of {problems}) of the fastest solve with d digits"
    )


# The classical methods; every other one (the Radau-PINN, a plugged-in neural method) is set against
# radau at equal error in the report.
CLASSICAL = ("radau", "casadi-collocation", "casadi-idas", "reference")


def against_radau(records, methods, problems) -> list[dict]:
    """Per problem and method other than the classical ones (:data:`CLASSICAL`): its most accurate
    successful run (``scd``, ``wall``: setup + solve, the training included, ``solve``) beside radau's
    fastest successful solve reaching at least those digits (``radau_solve``, its ``radau_scd``), and
    the ratios ``wall_ratio`` and ``solve_ratio``; ``none`` says why a row has no run (its runs'
    statuses and errors) or no radau run to set it against (radau not among ``methods``, none of its
    runs on the problem a success, or none as accurate)."""
    out = []
    radau = [r for r in records if r["method"] == "radau" and r["status"] == "success" and r["scd"] is not None]
    for method in methods:
        if method in CLASSICAL:
            continue
        for problem in problems:
            runs = [r for r in records if r["method"] == method and r["problem"] == problem.name]
            good = [r for r in runs if r["status"] == "success" and r["scd"] is not None]
            row = {"problem": problem.name, "method": method, "none": None}
            if not good:
                counts = Counter(r["error_class"] or r["status"] for r in runs)
                row["none"] = ", ".join(f"{n} {what}" for what, n in sorted(counts.items())) or "no run"
                out.append(row)
                continue
            best = max(good, key=lambda r: (r["scd"], -r["solve_time"]))
            row.update(scd=best["scd"], settings=best["settings"], solve=best["solve_time"])
            row["wall"] = best["setup_time"] + best["solve_time"]
            match = [r for r in radau if r["problem"] == problem.name and r["scd"] >= best["scd"]]
            if not match:
                row["none"] = _no_radau_match(records, methods, problem.name, best["scd"])
            else:
                fastest = min(match, key=lambda r: r["solve_time"])
                row.update(radau_scd=fastest["scd"], radau_solve=fastest["solve_time"])
                row.update(
                    wall_ratio=row["wall"] / fastest["solve_time"], solve_ratio=row["solve"] / fastest["solve_time"]
                )
            out.append(row)
    return out


def _no_radau_match(records, methods, problem: str, digits: float) -> str:
    """Why a row of :func:`against_radau` has no radau run beside it."""
    if "radau" not in methods:
        return "radau is not among the methods run"
    runs = [r for r in records if r["method"] == "radau" and r["problem"] == problem]
    if not any(r["status"] == "success" and r["scd"] is not None for r in runs):
        counts = Counter(r["error_class"] or r["status"] for r in runs)
        return (
            "no radau run succeeded ("
            + (", ".join(f"{n} {what}" for what, n in sorted(counts.items())) or "none ran")
            + ")"
        )
    return f"no successful radau run reaches {digits:.1f} digits"


def against_radau_cells(row: dict) -> list[str]:
    """One row of :func:`against_radau` as table cells: problem, method, its best run, radau's, the ratios."""
    if "scd" not in row:
        return [row["problem"], row["method"], f"none: {row['none']}", "", ""]
    # (a clock a plugged-in method reported as NaN or inf is None in results.json: "not finite", not a crash)
    wall, solve = _finite_or(row["wall"], _seconds), _finite_or(row["solve"], _seconds)
    mine = f"{row['scd']:.1f} scd at {row['settings']}: {wall} setup + solve, {solve} solve"
    if row["none"] is not None:
        return [row["problem"], row["method"], mine, row["none"], ""]
    theirs = f"{row['radau_scd']:.1f} scd in {_finite_or(row['radau_solve'], _seconds)}"
    wall_ratio, solve_ratio = (_finite_or(row[k], lambda v: f"{v:.3g}x") for k in ("wall_ratio", "solve_ratio"))
    return [row["problem"], row["method"], mine, theirs, f"{wall_ratio} ({solve_ratio} solve)"]


def _finite_or(value, show) -> str:
    return show(value) if value is not None and math.isfinite(value) else "not finite"


AGAINST_RADAU_HEAD = (
    "problem",
    "method",
    "its most accurate success",
    "radau's fastest solve as accurate",
    "time ratio",
)


def _time_cell(row: dict, digits: int, problems: int) -> str:
    value = row[f"time_to_{digits}"]
    return "-" if value is None else f"{_seconds(value)} ({row[f'reached_{digits}']}/{problems})"


def _seconds(value: float) -> str:
    return f"{value * 1e3:.3g} ms" if value < 1 else f"{value:.3g} s"


def work_precision_figure(problem, methods, records):
    """One problem's figure: scd at the end against solve time (left) and setup + solve (right), one
    line per method through its successful runs; flagged runs hollow squares, failures ``x`` on a
    row labelled "failed" below every run's digits, at the time they failed."""
    from matplotlib.figure import Figure

    from daemodel.comparing.plots import readable_log_axis

    fig = Figure(figsize=(11.0, 4.4), layout="constrained")
    axes = fig.subplots(1, 2, sharey=True)
    digits = [r["scd"] for r in records if r["scd"] is not None and r["status"] in ("success", "flagged")]
    # failures sit on a row of their own below every run's digits, labelled "failed"
    failed_row = math.floor(min([0.0, *digits])) - 1
    for ax, clock, title in ((axes[0], "solve_time", "solve time [s]"), (axes[1], "wall_time", "setup + solve [s]")):
        times = []
        for i, method in enumerate(methods):
            runs = [r for r in records if r["method"] == method and r["problem"] == problem.name]
            good = [r for r in runs if r["status"] == "success" and r["scd"] is not None]
            flagged = [r for r in runs if r["status"] == "flagged" and r[clock] is not None and r["scd"] is not None]
            failed = [r for r in runs if r["status"] == "failed" and r["solve_time"]]
            label = f"{method} ({len(good)} of {len(runs)} succeeded)"
            ax.plot([r[clock] for r in good], [r["scd"] for r in good], "o-", color=f"C{i}", label=label)
            if flagged:
                ax.plot(
                    [r[clock] for r in flagged], [r["scd"] for r in flagged], "s", mfc="none", color=f"C{i}",
                    label=f"{method}: flagged",
                )  # fmt: skip
            if failed:  # at the time it took to fail: no digits to place it by
                ax.plot(
                    [r["solve_time"] for r in failed], [failed_row] * len(failed), "x", ms=9, mew=2, color=f"C{i}",
                    label=f"{method}: failed",
                )  # fmt: skip
            times += [r[clock] for r in good + flagged] + [r["solve_time"] for r in failed]
        positive = [t for t in times if t is not None and t > 0]
        ax.set_xscale("log")
        if positive:
            readable_log_axis(ax.xaxis, min(positive), max(positive))
        ax.axhline(failed_row + 0.5, color="0.6", lw=0.8, ls=":")
        ax.set_xlabel(title)
        ax.grid(which="major", alpha=0.3)
    top = math.ceil(max([1.0, *digits]))
    step = max(1, math.ceil((top - failed_row) / 10))
    first = math.ceil((failed_row + 1) / step) * step
    ticks = [failed_row, *range(first, top + 1, step)]
    axes[0].set_yticks(ticks, ["failed", *(str(t) for t in ticks[1:])])
    axes[0].set_ylim(failed_row - 0.6, top + 0.4)
    axes[0].set_ylabel("significant correct digits at the end (scd)")
    handles, labels = axes[0].get_legend_handles_labels()
    if labels:
        fig.legend(handles, labels, loc="outside lower center", ncols=min(len(labels), 3), fontsize=8)
    t0, t1 = problem.t_span
    against = problem.reference_source.partition(":")[0]  # "published", "closed form", "scipy (...)"
    fig.suptitle(f"{problem.name} on [{t0:g}, {t1:g}]: scd at t = {t1:g} against the {against} values", fontsize=10)
    return fig


def figure_png(fig) -> bytes:
    """A figure as PNG bytes."""
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=PLOT_DPI)
    return buffer.getvalue()


def write_report(out: Path, problems, methods, records) -> list[Path]:
    """``report.html``, ``results.json`` and ``results.csv`` in ``out``, each written atomically."""
    rows = summary(records, methods, problems)
    paths = [
        write_json(
            Path(out) / "results.json",
            {
                "problems": [
                    {
                        "name": p.name,
                        "suite": p.suite,
                        "t_span": list(p.t_span),
                        "reference_source": p.reference_source,
                        "scd_components": list(p.scd_names or p.reference),
                    }
                    for p in problems
                ],
                "methods": list(methods),
                "summary": rows,
                "against_radau": [_finite(r) for r in against_radau(records, methods, problems)],
                "runs": [_finite(r) for r in records],
            },
        )
    ]

    def write_csv(handle):
        writer = csv.DictWriter(handle, fieldnames=CSV_FIELDS, extrasaction="ignore")
        writer.writeheader()
        for record in records:
            writer.writerow({k: ("" if record.get(k) is None else record[k]) for k in CSV_FIELDS})

    paths.append(atomic_write(Path(out) / "results.csv", write_csv, text=True))
    page = _html(problems, methods, records, rows)
    paths.insert(0, atomic_write(Path(out) / "report.html", lambda handle: handle.write(page), text=True))
    return paths


def _finite(record: dict) -> dict:
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in record.items()}


_STYLE = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 1200px; color: #222; }
table { border-collapse: collapse; margin: 0.6em 0 1.6em; font-size: 0.9em; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.6em; text-align: left; vertical-align: top; }
th { background: #f3f3f3; }
td.success { color: #176117; } td.flagged { color: #8a5a00; } td.failed { color: #a11; } td.skipped { color: #666; }
img { max-width: 100%; }
details { margin-bottom: 2em; }
"""


def _html(problems, methods, records, rows) -> str:
    e = html.escape
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8"><title>daemodel bench</title>',
        f"<style>{_STYLE}</style></head><body>",
        "<h1>daemodel bench</h1>",
        f"<p>{_plural(len(problems), 'problem')}, {_plural(len(methods), 'method')}, {_plural(len(records), 'run')}. "
        "scd: significant correct digits at the end of the interval, -log10 of the largest relative error "
        "over the problem's components (absolute where the reference value is 0). Times on one clock per run: "
        "setup, solve, wall = setup + solve.</p>",
        "<h2>Summary</h2>",
        _summary_table(rows, len(problems)),
    ]
    versus = against_radau(records, methods, problems)
    if versus:
        parts += [
            "<h2>Against radau at equal error</h2>",
            "<table><tr>" + "".join(f"<th>{e(h)}</th>" for h in AGAINST_RADAU_HEAD) + "</tr>"
            + "".join("<tr>" + "".join(f"<td>{e(c)}</td>" for c in against_radau_cells(r)) + "</tr>" for r in versus)
            + "</table><p>Each method beyond the classical ones at its most accurate successful run (setup + solve: "
            "the training included), beside radau's fastest successful solve with at least as many digits; the "
            "ratio divides the first by radau's solve time (in brackets: its solve alone).</p>",
        ]  # fmt: skip
    notes = _skip_notes(records)
    if notes:
        parts.append("<h2>Settings not run</h2><ul>" + "".join(f"<li>{e(n)}</li>" for n in notes) + "</ul>")
    for problem in problems:
        mine = [r for r in records if r["problem"] == problem.name]
        fig = work_precision_figure(problem, methods, mine)
        image = base64.b64encode(figure_png(fig)).decode("ascii")
        parts += [
            f'<h2 id="{e(problem.name)}">{e(problem.name)}</h2>',
            f"<p>Suite {e(problem.suite)}; [{problem.t_span[0]:g}, {problem.t_span[1]:g}]; reference: "
            f"{e(problem.reference_source)}; scd over {e(', '.join(problem.scd_names or problem.reference))}.</p>",
            f'<img alt="work-precision plot of {e(problem.name)}" data-problem="{e(problem.name)}" '
            f'src="data:image/png;base64,{image}">',
            "<details><summary>every run</summary>",
            _runs_table(mine),
            "</details>",
        ]
    parts.append("</body></html>")
    return "\n".join(parts) + "\n"


def _summary_table(rows, problems: int) -> str:
    e = html.escape
    head = ["method", "problems solved", *(f"time to {d} scd" for d in TARGET_DIGITS), "flagged", "skipped", "failures"]
    body = []
    for row in rows:
        failures = ", ".join(f"{n} {name}" for name, n in sorted(row["failures"].items())) or "none"
        cells = [
            row["method"],
            f"{row['problems_solved']} of {problems}",
            *(_time_cell(row, d, problems) for d in TARGET_DIGITS),
            str(row["flagged"]),
            str(row["skipped"]),
            failures,
        ]
        body.append("<tr>" + "".join(f"<td>{e(c)}</td>" for c in cells) + "</tr>")
    return (
        "<table><tr>"
        + "".join(f"<th>{e(h)}</th>" for h in head)
        + "</tr>"
        + "".join(body)
        + "</table><p>Time to d scd: the median, over the problems where the method reached d digits (how many in "
        "brackets), of its fastest successful solve that did.</p>"
    )


def _runs_table(records) -> str:
    e = html.escape
    head = ["method", "settings", "status", "scd", "setup", "solve", "wall", "steps", "why"]
    body = []
    for r in records:
        why = f"{r['error_class']}: {r['error']}" if r["error"] else (r["flag"] or r["reason"] or "")
        cells = [
            (r["method"], ""),
            (r["settings"], ""),
            (r["status"], f' class="{r["status"]}"'),
            ("" if r["scd"] is None else f"{r['scd']:.2f}", ""),
            *(("" if r[k] is None else _seconds(r[k]), "") for k in ("setup_time", "solve_time", "wall_time")),
            (_steps(r["stats"]), ""),
            (why[:400], ""),
        ]
        body.append("<tr>" + "".join(f"<td{attr}>{e(c)}</td>" for c, attr in cells) + "</tr>")
    return "<table><tr>" + "".join(f"<th>{h}</th>" for h in head) + "</tr>" + "".join(body) + "</table>"


# What each method calls its steps in stats: radau and collocation "steps", IDAS "nsteps" (casadi's
# name), the PINN "segments" (one network per step of its grid).
STEP_COUNTS = ("steps", "nsteps", "segments")


def _steps(stats: dict) -> str:
    return next((str(stats[k]) for k in STEP_COUNTS if k in stats), "")


def _plural(count: int, word: str) -> str:
    return f"{count} {word}" + ("" if count == 1 else "s")


def _skip_notes(records) -> list[str]:
    """One line per method and problem for the settings skipped before any solve (the PINN beyond its
    segment budget, a setting its method refuses), with the first one's reason."""
    groups: dict = {}
    for r in records:
        if r["status"] == "skipped":
            groups.setdefault((r["method"], r["problem"]), []).append(r)
    return [f"{m} on {p}: {len(runs)} setting(s) not run; {runs[0]['reason']}" for (m, p), runs in groups.items()]

"""The ``daemodel`` command.

    daemodel compare hessenberg pendulum
    daemodel compare examples/pendulum.py --methods radau,casadi-idas,pinn --out results/
    daemodel bench testset paper --out bench/ --workers 2
    daemodel cache info
    daemodel cache clear

A target is the name of a problem in :mod:`daemodel.problems`, each on its own interval,

    {problems}

or a Python file that defines

* ``build_model()`` returning a :class:`~daemodel.Model` (or a module-level ``model``: a
  Model, a CompiledDAE, or a function returning one); and optionally
* ``T_SPAN = (t0, t1)``, the interval, finite with t0 < t1 (default (0, 1); ``--t-end``
  overrides t1), and
* ``exact(t)``, returning a dict name -> values, the reference for the errors (default: a
  tight scipy solve, ``method="reference"``).

The file runs as ``python model.py`` would: it may import the modules beside it
(``from params import K`` with ``params.py`` in its folder); each target imports its own.

Fixed-step methods start their sweep at ``--steps`` steps over the interval (h = span / steps,
then halved at each of ``--points``); the default is the problem's own (fine enough for its
oscillations and transients), or 10 for a model file.

For each target it prints the table and writes ``<model>.json``, ``<model>.csv`` and
``<model>_work_precision.png`` into ``--out``.

Every argument, the ``--out`` directory (created, and a file written and removed in it) and
every target are checked before the first solve.  An error is one line on stderr,
``daemodel compare TARGET: message``.  Exit status: 0 when every table was produced (a
method that failed at some or all settings is shown as failed in it); 2 for a user mistake
(nothing is solved then); 1 when a solver failure stopped a target (the default reference
solve failed).
"""

from __future__ import annotations

import argparse
import math
import re
import sys
from pathlib import Path

from daemodel.comparing.targets import load_target
from daemodel.errors import DaemodelError, ModelError, TargetError
from daemodel.files import writable_directory

# Exit statuses of `daemodel compare`.
EXIT_USER_MISTAKE, EXIT_SOLVER_FAILURE = 2, 1


def check_out(out: str) -> Path:
    """The ``--out`` directory, created, with a probe file written and removed in it."""
    return writable_directory(out, "--out")


class _UsageError(Exception):
    """An argparse error, reported as one line instead of argparse's usage text and exit."""


class _Parser(argparse.ArgumentParser):
    def error(self, message):
        raise _UsageError(f"{self.prog}: {message} (see {self.prog} --help)")


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("daemodel")
    except PackageNotFoundError:  # run from a source tree that was never installed
        return "unknown (not installed)"


def help_text() -> str:
    """This module's documentation as ``daemodel compare --help`` prints it: the problem list
    filled in from :data:`daemodel.problems.PROBLEMS`, and the reST markup read as plain text."""
    from daemodel.problems import PROBLEMS

    names = ", ".join(f"{name} [{p.t_span[0]:g}, {p.t_span[1]:g}]" for name, p in PROBLEMS.items())
    return plain_text(__doc__.replace("{problems}", names))


def plain_text(text: str) -> str:
    """reST inline markup as plain text: ``x`` -> x, :class:`~a.b.C` -> C, :mod:`a.b` -> a.b."""

    def role(match) -> str:
        target = match.group(2)
        return target.split(".")[-1] if match.group(1) else target

    return re.sub(r":[a-z]+:`(~?)([^`]*)`", role, text).replace("``", "")


def _parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="daemodel", description="Solve and compare DAEs.")
    parser.add_argument("--version", action="version", version=f"daemodel {_version()}")
    commands = parser.add_subparsers(dest="command", required=True)
    cmp = commands.add_parser(
        "compare",
        help="every method on a model: table of solve and setup times and errors, work-precision plot",
        description=help_text(),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    cmp.add_argument("targets", nargs="+", metavar="TARGET", help="problem name or model file")
    cmp.add_argument("--methods", help="comma-separated methods (default: every method but 'reference')")
    cmp.add_argument("--out", default="results", help="directory for the JSON, CSV and PNG (default results/)")
    cmp.add_argument("--points", type=int, default=4, help="settings per method in the sweep (default 4, at most 12)")
    cmp.add_argument(
        "--steps",
        type=int,
        help="steps of the coarsest fixed-step setting (default: the problem's own, or 10 for a model file)",
    )
    cmp.add_argument("--t-end", type=float, help="end of the interval (default: the target's T_SPAN or 1)")
    cmp.add_argument("--threads", type=int, default=1, help="torch threads, fixed for comparable timings (default 1)")
    cmp.add_argument(
        "--detail", action="store_true", help="a max (mean) error column per variable (default: worst per group)"
    )
    cmp.add_argument("--no-progress", action="store_true", help="no progress bar")
    run = commands.add_parser(
        "bench",
        help="every method on suites of problems: scd at the end against time, one HTML report, resumable",
        description="Every method on the problems of each SUITE (testset, paper, families) or model file: a sweep per "
        "method (rtol = atol 1e-3 ... 1e-11, or step sizes), scd = -log10 of the largest relative error at the end, "
        "setup, solve and wall times; each run stored in --out as it finishes (a rerun solves only what is missing), "
        "then report.html (work-precision plots inline), results.json and results.csv.",
    )
    run.add_argument("suites", nargs="+", metavar="SUITE", help="testset, paper, families, or a .py model file")
    run.add_argument("--out", default="bench", help="output folder (default bench/); its runs are reused")
    run.add_argument("--methods", help="comma-separated methods (default: every method but 'reference')")
    run.add_argument("--workers", type=int, default=1, help="processes (or Ray CPUs) to run on (default 1)")
    run.add_argument("--executor", choices=("local", "processes", "ray"), help="where runs go (default: by --workers)")
    run.add_argument("--address", help="a Ray cluster's address (with --executor ray)")
    run.add_argument("--tolerances", help="comma-separated rtol = atol (default 1e-3,1e-5,1e-7,1e-9,1e-11)")
    run.add_argument("--points", type=int, default=3, help="step sizes per fixed-step method (default 3)")
    run.add_argument("--time-limit", type=float, default=60.0, help="seconds one run may take (default 60)")
    run.add_argument("--threads", type=int, default=1, help="torch threads per run (default 1)")
    run.add_argument("--no-progress", action="store_true", help="no progress bar")
    store = commands.add_parser(
        "cache",
        help="the cache of compiled libraries (radau's jit=True): where it is, what it holds; clear it",
        description="The cache of compiled libraries (DAEMODEL_CACHE, else ~/.cache/daemodel; DAEMODEL_CACHE_SIZE "
        "bytes, default 1 GiB): 'info' shows its folder, entries, size, limit and whether it is safe; 'clear' "
        "removes daemodel's entries (no other file) and says how many bytes it freed.",
    )
    store.add_argument("action", choices=("info", "clear"), help="info: what the cache holds; clear: empty it")
    return parser


def main(argv=None) -> int:
    """Run ``daemodel``; returns the exit status (see the module docs)."""
    try:
        args = _parser().parse_args(argv)
    except _UsageError as error:
        print(error, file=sys.stderr)
        return EXIT_USER_MISTAKE
    if args.command == "cache":
        return _cache(args.action)
    if args.command == "bench":
        return _bench(args)
    import torch

    torch.set_num_threads(max(1, args.threads))
    return _compare(args)


def _compare(args) -> int:
    from daemodel.backends import get_backend
    from daemodel.backends.grids import SWEEP_FIRST_STEPS
    from daemodel.comparing.compare import plan_comparison
    from daemodel.comparing.sweeps import check_points
    from daemodel.problems import PROBLEMS

    def report(where: str, error: Exception) -> None:
        print(f"daemodel compare{where}: {error}", file=sys.stderr)

    # The arguments and --out: wrong for every target alike.
    try:
        methods = None
        if args.methods is not None:
            methods = [m.strip() for m in args.methods.split(",") if m.strip()]
            if not methods:
                raise ModelError(f"--methods {args.methods!r} names no method; give e.g. --methods radau,casadi-idas")
            for method in methods:
                get_backend(method)
        check_points(args.points, SWEEP_FIRST_STEPS if args.steps is None else args.steps)
        if args.t_end is not None and not math.isfinite(args.t_end):
            raise ModelError(f"--t-end must be a finite number; got {args.t_end}")
        if args.threads < 1:
            raise ModelError(f"--threads must be at least 1; got {args.threads}")
        check_out(args.out)
    except DaemodelError as error:
        report("", error)
        return EXIT_USER_MISTAKE

    # Every target, checked before the first solve.
    plans, status = [], 0
    for target in args.targets:
        try:
            model, t_span, exact = load_target(target)
            if args.t_end is not None:
                if args.t_end <= t_span[0]:
                    raise TargetError(
                        f"--t-end {args.t_end:g} is not after t0 = {t_span[0]:g}, where the target starts"
                    )
                t_span = (t_span[0], args.t_end)
            steps = args.steps
            if steps is None:
                steps = PROBLEMS[target].compare_steps if target in PROBLEMS else SWEEP_FIRST_STEPS
            plan = plan_comparison(model, t_span, methods, reference=exact, points=args.points, steps=steps)
            plans.append((target, plan))
        except DaemodelError as error:
            report(f" {target}", error)
            status = max(status, _exit_status(error))
    if status:
        return status

    for target, plan in plans:
        try:
            result = plan.run(progress=False if args.no_progress else None)
            print(result.table(detail=args.detail))
            for path in result.save(args.out):
                print(f"wrote {path}")
        except DaemodelError as error:  # e.g. a SolverError of the default reference solve
            report(f" {target}", error)
            status = max(status, _exit_status(error))
        except OSError as error:
            report(f" {target}", f"cannot write into --out {args.out}: {error}")
            status = max(status, EXIT_USER_MISTAKE)
        print()
    return status


def _bench(args) -> int:
    """``daemodel bench``: :func:`daemodel.comparing.bench.bench` with the command's arguments."""
    from daemodel.comparing.bench import DEFAULT_TOLERANCES, bench

    try:
        methods = None
        if args.methods is not None:
            methods = [m.strip() for m in args.methods.split(",") if m.strip()]
            if not methods:
                raise ModelError(f"--methods {args.methods!r} names no method; give e.g. --methods radau,casadi-idas")
        tolerances = DEFAULT_TOLERANCES
        if args.tolerances is not None:
            try:
                tolerances = [float(t) for t in args.tolerances.split(",") if t.strip()]
            except ValueError:
                raise ModelError(f"--tolerances {args.tolerances!r} is not a list of numbers like 1e-4,1e-8") from None
        result = bench(
            args.suites,
            methods,
            args.out,
            workers=args.workers,
            executor=args.executor,
            address=args.address,
            tolerances=tolerances,
            points=args.points,
            time_limit=args.time_limit,
            threads=args.threads,
            progress=False if args.no_progress else None,
        )
    except DaemodelError as error:
        print(f"daemodel bench: {error}", file=sys.stderr)
        return _exit_status(error)
    print(result.table())
    print(f"{len(result.records)} runs ({result.computed} solved now) in {result.elapsed:.1f} s")
    for path in result.paths:
        print(f"wrote {path}")
    return 0


def _cache(action: str) -> int:
    """``daemodel cache info`` or ``daemodel cache clear`` (see :mod:`daemodel.cache`)."""
    from daemodel.cache import cache_folder, clear, info

    try:
        if action == "clear":
            freed = clear()
            print(f"daemodel cache clear: freed {freed} bytes in {cache_folder()}")
            return 0
        for name, value in info().items():
            print(f"{name + ':':17} {value}")
        return 0
    except DaemodelError as error:
        print(f"daemodel cache {action}: {error}", file=sys.stderr)
        return _exit_status(error)


def _exit_status(error: DaemodelError) -> int:
    return EXIT_USER_MISTAKE if isinstance(error, ModelError) else EXIT_SOLVER_FAILURE


if __name__ == "__main__":
    sys.exit(main())

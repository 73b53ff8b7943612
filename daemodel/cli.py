"""The ``daemodel`` command.

    daemodel compare hessenberg pendulum
    daemodel compare examples/pendulum.py --methods radau,casadi-idas,pinn --out results/

A target is the name of a problem in :mod:`daemodel.problems` (``hessenberg``,
``pendulum``, ``pendulum-index3``) or a Python file that defines

* ``build_model()`` returning a :class:`~daemodel.Model` (or a module-level ``model``: a
  Model, a CompiledDAE, or a function returning one); and optionally
* ``T_SPAN = (t0, t1)``, the interval (default (0, 1); ``--t-end`` overrides t1), and
* ``exact(t)``, returning a dict name -> values, the reference for the errors (default: a
  tight scipy solve, ``method="reference"``).

For each target it prints the table and writes ``<model>.json``, ``<model>.csv`` and
``<model>_work_precision.png`` into ``--out``.
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
from pathlib import Path

from daemodel.errors import DaemodelError, TargetError

DEFAULT_T_SPAN = (0.0, 1.0)


def load_target(target: str):
    """``(model, t_span, exact)`` for a problem name or a model file (see the module docs)."""
    from daemodel.problems import PROBLEMS

    if target in PROBLEMS:
        problem = PROBLEMS[target]
        exact = problem.exact_solution() if problem.exact else None
        return problem.model(), DEFAULT_T_SPAN, exact
    path = Path(target)
    if path.suffix != ".py":
        raise TargetError(f"{target!r} is neither a problem ({', '.join(PROBLEMS)}) nor a .py model file")
    if not path.is_file():
        raise TargetError(f"no model file at {path}")
    spec = importlib.util.spec_from_file_location(f"daemodel_target_{path.stem}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    if callable(getattr(module, "build_model", None)):
        model = module.build_model()
    elif hasattr(module, "model"):
        model = module.model() if callable(module.model) and not _is_model(module.model) else module.model
    else:
        raise TargetError(
            f"{path} defines neither build_model() nor model; define build_model() returning a daemodel.Model"
        )
    if not _is_model(model):
        raise TargetError(f"{path}: build_model() / model gave {type(model).__name__}, not a Model or CompiledDAE")
    t_span = tuple(getattr(module, "T_SPAN", DEFAULT_T_SPAN))
    exact = getattr(module, "exact", None)
    return model, t_span, exact


def _is_model(value) -> bool:
    from daemodel.compiled import CompiledDAE
    from daemodel.model import Model

    return isinstance(value, Model | CompiledDAE)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="daemodel", description="Solve and compare DAEs.")
    commands = parser.add_subparsers(dest="command", required=True)
    cmp = commands.add_parser(
        "compare",
        help="every method on a model: table of wall time and errors, work-precision plot",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    cmp.add_argument("targets", nargs="+", metavar="TARGET", help="problem name or model file")
    cmp.add_argument("--methods", help="comma-separated methods (default: every method but 'reference')")
    cmp.add_argument("--out", default="results", help="directory for the JSON, CSV and PNG (default results/)")
    cmp.add_argument("--points", type=int, default=4, help="settings per method in the sweep (default 4)")
    cmp.add_argument("--t-end", type=float, help="end of the interval (default: the target's T_SPAN or 1)")
    cmp.add_argument("--threads", type=int, default=1, help="torch threads, fixed for comparable timings (default 1)")
    cmp.add_argument("--no-progress", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)

    from daemodel.compare import compare

    methods = [m.strip() for m in args.methods.split(",") if m.strip()] if args.methods else None
    import torch

    torch.set_num_threads(max(1, args.threads))
    status = 0
    for target in args.targets:
        try:
            model, t_span, exact = load_target(target)
            if args.t_end is not None:
                t_span = (t_span[0], args.t_end)
            result = compare(
                model,
                t_span,
                methods,
                reference=exact,
                points=args.points,
                progress=False if args.no_progress else None,
            )
        except DaemodelError as error:
            print(f"daemodel compare {target}: {error}", file=sys.stderr)
            status = 2
            continue
        print(result.table())
        for path in result.save(args.out):
            print(f"wrote {path}")
        print()
    return status


if __name__ == "__main__":
    sys.exit(main())

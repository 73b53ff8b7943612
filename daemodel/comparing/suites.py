"""What ``dm.bench`` runs: suites of problems by name, or model files, each with its values at the
end of its interval and the components its significant correct digits are read from.

Suites are read from the problem library (:data:`daemodel.problems.PROBLEMS`), so a problem added
there joins its suite with no change here:

* ``testset``: the problems whose ``source`` cites the Test Set for IVP Solvers and which carry its
  published ``reference`` at ``t_span[1]``;
* ``paper``: the problems of the paper daemodel's Radau-PINN follows (``source`` starting with
  :data:`daemodel.problems.paper.PAPER`): Hessenberg with its closed form, the pendulum;
* ``families``: the pendulum chain and reaction-diffusion at three sizes each
  (:data:`daemodel.problems.families.FAMILIES`), with scipy's references on their index-reduced ODEs.

A model file (``.py``) is read as ``daemodel compare`` reads it (:func:`~daemodel.comparing.targets.load_target`).

The end values come from, in this order: the problem's published ``reference``, its closed form
(``exact``, or a file's ``exact(t)``), else a tight scipy solve (``method="reference"``, rtol = atol
= 1e-12) that :func:`daemodel.comparing.bench.bench` computes once and keeps in its output folder.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from daemodel.backends.grids import SWEEP_FIRST_STEPS
from daemodel.errors import BenchError

# The words by which a problem's source cites the IVP Test Set (Mazzia, Magherini et al.).
TEST_SET = "Test Set for IVP Solvers"
SUITES = ("testset", "paper", "families")
# The largest relative error a scd is read from is floored here: a run that matches the end values
# to the last bit reads 17 digits (float64 holds 15.9), not infinitely many.
ERROR_FLOOR = 1e-17


@dataclass(frozen=True)
class BenchProblem:
    """One problem of a benchmark.

    Attributes
    ----------
    name : str
        The problem's name (a file's stem for a model file), unique within the benchmark.
    target : str
        What builds it: a problem name of :data:`daemodel.problems.PROBLEMS`, a member of
        :data:`daemodel.problems.families.FAMILIES` or a model file's path.
    suite : str
        ``"testset"``, ``"paper"``, ``"families"`` or ``"file"``.
    t_span : (float, float)
    steps : int
        Steps over ``t_span`` of the fixed-step methods' coarsest setting (the problem's ``compare_steps``).
    reference : dict name -> float
        The solution at ``t_span[1]``, published or exact; empty when it must be computed.
    reference_source : str
        Where ``reference`` comes from.
    scd_names : tuple of str
        The components scd is read from (empty: every component of ``reference``).
    """

    name: str
    target: str
    suite: str
    t_span: tuple
    steps: int = SWEEP_FIRST_STEPS
    reference: dict | None = None
    reference_source: str = ""
    scd_names: tuple = ()

    def model(self):
        """A fresh model of this problem (a model file is imported again)."""
        from daemodel.comparing.targets import load_target

        return load_target(self.target)[0]


def resolve(suites_or_files) -> list[BenchProblem]:
    """The problems of ``suites_or_files`` (suite names and model files, in that order, each once).

    Raises
    ------
    BenchError
        Nothing given, or a name that is neither a suite nor a ``.py`` file.
    TargetError
        A model file that cannot be read (see :func:`~daemodel.comparing.targets.load_target`).
    """
    from daemodel.problems import PROBLEMS
    from daemodel.problems.families import FAMILIES
    from daemodel.problems.paper import PAPER

    if isinstance(suites_or_files, str):
        suites_or_files = [suites_or_files]
    items = list(suites_or_files)
    if not items:
        raise BenchError(f"bench needs at least one suite ({', '.join(SUITES)}) or model file")
    out: dict[str, BenchProblem] = {}
    for item in items:
        if not isinstance(item, str):
            raise BenchError(f"a suite or model file is a str; got {type(item).__name__} {item!r}")
        if item == "testset":
            chosen = [p for p in PROBLEMS.values() if TEST_SET in p.source and p.reference]
        elif item == "paper":
            chosen = [p for p in PROBLEMS.values() if p.source.startswith(PAPER)]
        elif item == "families":
            chosen = list(FAMILIES.values())
        elif item.endswith(".py"):
            problem = _file_problem(item, set(out))
            out[problem.name] = problem
            continue
        else:
            raise BenchError(f"{item!r} is neither a suite ({', '.join(SUITES)}) nor a .py model file")
        for p in chosen:
            if p.name not in out:
                out[p.name] = _library_problem(p, item)
    return list(out.values())


def _library_problem(problem, suite: str) -> BenchProblem:
    if suite == "families":
        reference, source = dict(problem.reference), problem.source
    elif problem.reference:
        reference, source = dict(problem.reference), "published: " + problem.source
    elif problem.exact:
        t1 = problem.t_span[1]
        values = problem.exact_solution()(np.array([t1]))
        reference, source = {k: float(v[0]) for k, v in values.items()}, "closed form"
    else:
        reference, source = None, ""
    return BenchProblem(
        name=problem.name,
        target=problem.name,
        suite=suite,
        t_span=tuple(float(t) for t in problem.t_span),
        steps=problem.compare_steps,
        reference=reference,
        reference_source=source,
        scd_names=tuple(problem.scd_names),
    )


def _file_problem(path: str, taken: set) -> BenchProblem:
    from pathlib import Path

    from daemodel.comparing.targets import load_target

    _, t_span, exact = load_target(path)
    base = re.sub(r"[^A-Za-z0-9_\-]", "_", Path(path).stem) or "model"
    name, copy = base, 1
    while name in taken:  # two model.py in two folders
        copy += 1
        name = f"{base}_{copy}"
    reference, source = None, ""
    if exact is not None:
        values = exact(np.array([t_span[1]]))
        reference = {k: float(np.asarray(v).reshape(-1)[-1]) for k, v in values.items()}
        source = f"exact(t) of {path}"
    return BenchProblem(
        name=name, target=path, suite="file", t_span=t_span, reference=reference, reference_source=source
    )


def scd(values: dict, reference: dict, names=()) -> tuple[float, str]:
    """Significant correct digits at the end, as the Test Set defines them: ``-log10`` of the largest
    relative error over the components (``names``, default every one of ``reference``), the absolute
    error where the reference value is 0; and the component where that error is largest.

    ``values``: name -> float (the solution at the end).  An error below :data:`ERROR_FLOOR` reads as
    that floor; a non-finite value reads as ``-inf`` digits.
    """
    names = tuple(names) or tuple(reference)
    missing = [n for n in names if n not in values]
    if missing:
        raise BenchError(f"the solution has no value for {', '.join(missing)}, which the reference names")
    worst, where = -1.0, names[0]
    for name in names:
        ref, value = float(reference[name]), float(values[name])
        error = abs(value - ref) / (abs(ref) if ref != 0.0 else 1.0)
        if not np.isfinite(error):
            return -np.inf, name
        if error > worst:
            worst, where = error, name
    return float(-np.log10(max(worst, ERROR_FLOOR))), where

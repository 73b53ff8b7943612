"""What ``daemodel compare`` and ``daemodel bench`` are given: a problem of the library by name, or a
Python model file, read into ``(model, t_span, exact)`` (the file's contract is in :mod:`daemodel.comparing.cli`)."""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path

from daemodel.errors import InvalidValueError, TargetError
from daemodel.reals import is_real, real

DEFAULT_T_SPAN = (0.0, 1.0)


def load_target(target: str):
    """``(model, t_span, exact)`` for a problem name, a family member (``"pendulum_chain-8"``) or a
    model file (see :mod:`daemodel.comparing.cli`).

    Raises
    ------
    TargetError
        For anything wrong with the file, including any exception its code raises (a syntax
        error, at import, in ``build_model()``): the message names the file, the line where
        known, and the exception.
    """
    from daemodel.comparing.references import exception_summary
    from daemodel.problems import PROBLEMS
    from daemodel.problems.families import FAMILIES

    if target in PROBLEMS:
        problem = PROBLEMS[target]
        exact = problem.exact_solution() if problem.exact else None
        return problem.model(), problem.t_span, exact
    if target in FAMILIES:  # no closed form; bench reads its reference at the end from the member
        member = FAMILIES[target]
        return member.model(), member.t_span, None
    path = Path(target)
    if path.suffix != ".py":
        raise TargetError(f"{target!r} is neither a problem ({', '.join(PROBLEMS)}) nor a .py model file")
    if not path.is_file():
        raise TargetError(f"no model file at {path}")

    def run(what: str, function, *args):
        try:
            return function(*args)
        except (Exception, SystemExit) as error:  # the user's code: a message, not a traceback
            raise TargetError(f"{what} raised {exception_summary(error, filename=path)}") from error

    # The file runs as `python my_model.py` would run it: its folder first on sys.path, so that
    # `from params import K` finds params.py beside it.  Both the folder and the modules imported
    # from it leave again afterwards, so that a second target with its own params.py imports its
    # own (not the first one's cached in sys.modules) and nothing leaks into the caller's process.
    folder = path.resolve().parent
    loaded_before = set(sys.modules)
    sys.path.insert(0, str(folder))
    try:
        module = _import_file(path, run)
        build = getattr(module, "build_model", None)
        if build is not None:
            if not callable(build):
                raise TargetError(f"{path}: build_model is {type(build).__name__}, not a function returning a Model")
            model = run("build_model()", build)
        elif hasattr(module, "model"):
            model = module.model
            if callable(model) and not _is_model(model):
                model = run("model()", model)
        else:
            raise TargetError(
                f"{path} defines neither build_model() nor model; define build_model() returning a daemodel.Model"
            )
    finally:
        sys.path.remove(str(folder))
        _forget_modules_from(folder, set(sys.modules) - loaded_before)
    if not _is_model(model):
        raise TargetError(f"{path}: build_model() / model gave {type(model).__name__}, not a Model or CompiledDAE")
    t_span = _t_span(path, getattr(module, "T_SPAN", DEFAULT_T_SPAN))
    exact = getattr(module, "exact", None)
    if exact is not None and not callable(exact):
        raise TargetError(f"{path}: exact is {type(exact).__name__}, not a function t -> dict name -> values")
    return model, t_span, exact


def _import_file(path: Path, run):
    """The model file as a module, registered in sys.modules under a name no other target has."""
    name = base = f"daemodel_target_{path.stem}"
    copy = 1
    while name in sys.modules:  # two targets named model.py in two folders are two modules
        copy += 1
        name = f"{base}_{copy}"
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # as an import does: dataclasses and pickle look the module up there
    try:
        run("importing the model file", spec.loader.exec_module, module)
    except TargetError:
        del sys.modules[name]
        raise
    return module


def _forget_modules_from(folder: Path, names) -> None:
    """Drop from sys.modules the modules among ``names`` that were imported from ``folder`` (a model
    file's own helpers: ``params.py`` beside it, a package folder beside it).  The model keeps
    references to what it uses; sys.modules only must not hand them to the next target."""
    for name in names:
        top = name.partition(".")[0]
        if not ((folder / f"{top}.py").is_file() or (folder / top).is_dir()):
            continue  # numpy, scipy, ...: found elsewhere on sys.path, shared by every target
        origin = getattr(getattr(sys.modules.get(name), "__spec__", None), "origin", None)
        if origin and Path(origin).resolve().is_relative_to(folder):
            del sys.modules[name]


def _t_span(path: Path, value) -> tuple[float, float]:
    """``T_SPAN`` of a model file as floats: a pair of finite numbers, increasing."""
    expected = f"{path}: T_SPAN must be a pair (t0, t1) of finite numbers with t0 < t1; got {value!r}"
    try:
        pair = tuple(value)
    except TypeError:
        raise TargetError(expected) from None
    if len(pair) != 2 or not all(is_real(v) for v in pair):
        raise TargetError(expected)
    try:
        t0, t1 = real(pair[0], "t0", finite=False), real(pair[1], "t1", finite=False)
    except InvalidValueError:  # a sympy symbol: no number
        raise TargetError(expected) from None
    if not (math.isfinite(t0) and math.isfinite(t1) and t0 < t1):
        raise TargetError(expected)
    return t0, t1


def _is_model(value) -> bool:
    from daemodel.compiling.compiled import CompiledDAE
    from daemodel.compiling.compiler import Model

    return isinstance(value, Model | CompiledDAE)

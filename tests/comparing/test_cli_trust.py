"""`daemodel compare` and dm.compare never answer a user mistake with a traceback or a table
of NaN: every mistake is refused before the first solve with one line that names the culprit,
and the exit status tells a user mistake (2) from a solver failure (1)."""

import importlib
import json
import re
import textwrap
import warnings

import numpy as np
import pytest
from test_compare import MODEL_FILE

import daemodel as dm
import daemodel.solving.solver
from daemodel.comparing.cli import load_target, main
from daemodel.comparing.compare import plan_comparison
from daemodel.comparing.sweeps import MAX_POINTS, MAX_SWEEP_STEPS
from daemodel.errors import ComparisonError, ConvergenceError, InvalidOptionError, ResourceLimitError
from daemodel.problems import HESSENBERG

# the model file of test_compare, without and with its exact solution
MODEL, _, EXACT = MODEL_FILE.partition("\n\ndef exact(t):")
EXACT = "\n\ndef exact(t):" + EXACT


def decay():
    m = dm.Model("decay")
    (x,) = m.states("x")
    (w,) = m.algebraics("w")
    m.ode(x, -w)
    m.constraint(w - x, name="tie")
    m.initial(x=1.0)
    return m


def decay_exact(t):
    return {"x": np.exp(-t), "w": np.exp(-t)}


@pytest.fixture
def no_solve(monkeypatch):
    """Any solve fails the test: the mistake must be refused before the first one."""

    def solve(*args, **kwargs):
        raise AssertionError("a solve ran before the mistake was refused")

    monkeypatch.setattr(daemodel.solving.solver, "solve", solve)


def write(tmp_path, text, name="model.py"):
    path = tmp_path / name
    path.write_text(textwrap.dedent(text))
    return str(path)


def cli(capsys, *args):
    """``(status, stderr)`` of ``daemodel compare ARGS --no-progress``; stderr is one line, no traceback."""
    status = main(["compare", *map(str, args), "--no-progress"])
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return status, err


def one_line(err):
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    return lines[0]


# ---- dm.compare: the reference --------------------------------------------------------------
EXACT_HESSENBERG = HESSENBERG.exact_solution()


def changed(**values):
    """The Hessenberg exact solution with some variables replaced: ``name=function of t`` (None drops it)."""

    def reference(t):
        out = dict(EXACT_HESSENBERG(t))
        for name, function in values.items():
            if function is None:
                del out[name]
            else:
                out[name] = function(t)
        return out

    return reference


@pytest.mark.parametrize(
    ("reference", "match"),
    [
        (
            changed(y5=lambda t: np.where(t >= 0.25, np.nan, 1.0)),
            r"the reference's value for 'y5' is nan at t = 0.25 \(6 of 11 values not finite\); a reference must be "
            r"finite on t_span = \(0, 0.5\): fix it, or give none to measure against method='reference'",
        ),
        (changed(y2=lambda t: np.full_like(t, np.inf)), r"the reference's value for 'y2' is inf at t = 0 "),
        (
            changed(y5=None, y3=None),
            r"the reference gives no values for y3, y5; it gives y1, y2, y4, and must give every state and "
            r"algebraic variable of 'hessenberg': y1, y2, y3, y4, y5",
        ),
        (
            changed(y5=lambda t: t / 0 if isinstance(t, float) else 1 / 0),
            r"the reference, called on 11 times from 0 to 0.5, raised ZeroDivisionError: division by zero "
            r"\(line \d+ of .*test_cli_trust.py\); reference\(t\) must take an array of times",
        ),
        (lambda t: [t], r"the reference returned list on 11 times .* it must return a dict name -> array"),
        (
            changed(y5=lambda t: 1.0),
            r"the reference's values for 'y5' have shape \(\); expected \(11,\), one value per time",
        ),
        (changed(y1=lambda t: np.exp(t)[:-1]), r"the reference's values for 'y1' have shape \(10,\); expected \(11,\)"),
        (
            changed(y5=lambda t: t.astype(str)),
            r"the reference's values for 'y5' are not real numbers \(dtype <U32\); return a float array per variable",
        ),
    ],
    ids=["nan", "inf", "partial", "raises", "not-a-dict", "scalar", "short", "strings"],
)
def test_a_bad_reference_is_refused_before_any_solve(reference, match, no_solve):
    with pytest.raises(ComparisonError, match=match):
        dm.compare(HESSENBERG.model(), (0.0, 0.5), ["radau"], reference=reference, points=1, progress=False)


def test_the_reference_is_checked_again_on_every_runs_times():
    # finite on the check grid (multiples of 0.05) but NaN between: radau's h = 0.025 grid finds it
    reference = changed(y1=lambda t: np.where(np.isclose(t, 0.025), np.nan, np.exp(t)))
    with pytest.raises(ComparisonError, match=r"the reference's value for 'y1' is nan at t = 0.025 \(1 of 21"):
        dm.compare(HESSENBERG.model(), (0.0, 0.5), ["radau"], reference=reference, sweep={"radau": [{"h": 0.025}]})


# ---- dm.compare: the sweep --------------------------------------------------------------------
def test_points_are_bounded(no_solve):
    with pytest.raises(
        ComparisonError,
        match=rf"points = 1000 is more than {MAX_POINTS}: a fixed-step sweep halves h from span/10 at each point, "
        rf"so point {MAX_POINTS} already takes 20,480 steps per solve",
    ):
        dm.compare(decay(), (0.0, 0.5), ["radau"], points=1000)
    with pytest.raises(ComparisonError, match=r"points must be a positive integer; got 2\.0"):
        dm.compare(decay(), (0.0, 0.5), ["radau"], points=2.0)


def test_an_unusable_setting_is_refused_before_any_solve(no_solve):
    m = decay()
    with pytest.raises(
        InvalidOptionError,
        match=r"casadi-idas at rtol=1e-16, atol=1e-16 \(setting 7 of 7\): rtol = 1e-16 is outside the meaningful "
        r"range .*; "
        r"casadi-idas's default sweep is usable up to points = 6",
    ):
        dm.compare(m, (0.0, 0.5), ["radau", "casadi-idas"], points=7)
    with pytest.raises(
        ResourceLimitError,
        match=rf"radau at h=1e-07 \(setting 2 of 2\): h = 1e-07 makes 5,000,000 steps over t_span = \(0, 0.5\), "
        rf"more than the {MAX_SWEEP_STEPS:,} a compared setting may take; take h >= 5e-06; fix sweep\['radau'\]",
    ):
        dm.compare(m, (0.0, 0.5), ["radau"], sweep={"radau": [{"h": 0.1}, {"h": 1e-7}]})
    with pytest.raises(
        dm.errors.StepSizeError, match=r"radau at h=1 \(setting 1 of 1\): h = 1 is larger than the interval"
    ):
        dm.compare(m, (0.0, 0.5), ["radau"], sweep={"radau": [{"h": 1.0}]})
    with pytest.raises(
        dm.errors.UnknownOptionError, match=r"radau at hh=0.1 \(setting 1 of 1\): method 'radau' has no option 'hh'"
    ):
        dm.compare(m, (0.0, 0.5), ["radau"], sweep={"radau": [{"hh": 0.1}]})
    with pytest.raises(ResourceLimitError, match=r"pinn at h=1e-08 \(setting 1 of 1\): h = 1e-08 makes 50,000,000"):
        dm.compare(m, (0.0, 0.5), ["pinn"], sweep={"pinn": [{"config": dm.PINNConfig(h=1e-8)}]})


def test_a_method_that_failed_everywhere_says_so(monkeypatch, tmp_path):
    real = daemodel.solving.solver.solve

    def solve(model, t_span, *, method, **options):
        if method == "radau":
            raise ConvergenceError("radau: Newton did not converge at t = 0")
        return real(model, t_span, method=method, **options)

    monkeypatch.setattr(daemodel.solving.solver, "solve", solve)
    result = dm.compare(decay(), (0.0, 0.5), ["radau", "casadi-idas"], reference=decay_exact, points=2, progress=False)
    assert result.failed_methods == ("radau",)
    table = result.table()
    assert "nan" not in table
    assert re.search(r"\nradau +stages=3, h=0\.05 +- +-  failed: radau: Newton did not converge at t = 0\n", table)
    assert table.endswith("radau failed at every setting (2 of 2): no errors to compare, no curve")
    labels = [text.get_text() for text in result.plot().legends[0].get_texts()]
    assert labels[0] == "radau, 2 of 2 failed"
    assert re.fullmatch(
        r"casadi-idas: rtol=0.0001, atol=0.0001 -> rtol=1e-06, atol=1e-06 \(setup [0-9.e+-]+ ms\)", labels[1]
    )
    payload = json.loads(result.to_json(tmp_path / "decay.json").read_text())
    failed, solved = payload["runs"][0], payload["runs"][2]
    assert failed["setup_time"] is None and failed["solve_time"] >= 0  # the time it took to fail
    assert solved["solve_time"] > 0 and solved["setup_time"] > 0


def test_warnings_of_a_solve_go_into_its_run_not_above_the_table(monkeypatch, tmp_path):
    real = daemodel.solving.solver.solve

    def solve(model, t_span, *, method, **options):
        if options.get("h") == 0.025:
            warnings.warn("the Jacobian is badly conditioned", RuntimeWarning, stacklevel=1)
            warnings.warn("the Jacobian is badly conditioned", RuntimeWarning, stacklevel=1)
        return real(model, t_span, method=method, **options)

    monkeypatch.setattr(daemodel.solving.solver, "solve", solve)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a warning that escaped compare would fail here
        result = dm.compare(decay(), (0.0, 0.5), ["radau"], reference=decay_exact, points=2, progress=False)
    assert [r.messages for r in result.runs] == [(), ("RuntimeWarning: the Jacobian is badly conditioned",)]
    assert result.table().endswith("1 run(s) raised warnings (radau h=0.025): see 'messages' in the JSON and CSV")
    payload = json.loads(result.to_json(tmp_path / "decay.json").read_text())
    assert payload["runs"][1]["messages"] == ["RuntimeWarning: the Jacobian is badly conditioned"]
    rows = result.to_csv(tmp_path / "decay.csv").read_text().splitlines()
    assert rows[0].endswith(",failure,status,certified_distance,certificate_radau_error,messages") and rows[2].endswith(
        ",RuntimeWarning: the Jacobian is badly conditioned"
    )


def test_steps_sets_the_coarsest_fixed_step_and_leaves_tolerances_alone(no_solve):
    plan = plan_comparison(decay(), (0.0, 0.5), ["radau", "pinn", "casadi-idas"], points=2, steps=40)
    h = {method: [options.get("h") for m, options, *_ in plan.settings if m == method] for method in ("radau", "pinn")}
    assert h == {"radau": [0.5 / 40, 0.5 / 80], "pinn": [0.5 / 40, 0.5 / 80]}
    assert [options for m, options, *_ in plan.settings if m == "casadi-idas"] == [
        {"rtol": 1e-4, "atol": 1e-4},
        {"rtol": 1e-6, "atol": 1e-6},
    ]
    for steps in (0, 2.5, True):
        with pytest.raises(ComparisonError, match=rf"steps must be a positive integer .*; got {steps!r}"):
            dm.compare(decay(), (0.0, 0.5), ["radau"], steps=steps)
    with pytest.raises(ComparisonError, match=r"halves h from span/40 at each point, so point 12 already takes 81,920"):
        dm.compare(decay(), (0.0, 0.5), ["radau"], points=13, steps=40)


def test_the_command_takes_each_problems_own_steps_unless_told(monkeypatch, tmp_path):
    planned = []

    def plan(*args, **kwargs):
        planned.append(kwargs["steps"])
        raise dm.errors.ModelError("planned")  # stop before any solve

    monkeypatch.setattr(importlib.import_module("daemodel.comparing.compare"), "plan_comparison", plan)
    args = ["compare", "--methods", "radau", "--out", str(tmp_path)]
    assert main([*args, "car-axis", "hessenberg", "transistor-amplifier"]) == 2
    assert main([*args, "--steps", "25", "car-axis"]) == 2
    assert planned == [120, 10, 800, 25]


def test_the_command_refuses_steps_below_one(tmp_path, capsys, no_solve):
    assert main(["compare", "hessenberg", "--steps", "0", "--out", str(tmp_path)]) == 2
    assert "steps must be a positive integer (the coarsest fixed-step grid); got 0" in capsys.readouterr().err


# ---- the command: user mistakes -> exit 2, one line, no traceback, nothing solved ----------------
@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("def build_model(:\n    pass\n", r"importing the model file raised SyntaxError: .* \(line 1 of .*model.py\)"),
        (
            "import numpy\nx = numpy.undefined_name\n",
            r"importing the model file raised AttributeError: .* \(line 2 of ",
        ),
        ("x = 1\n", r"model.py defines neither build_model\(\) nor model; define build_model\(\) returning"),
        ("build_model = 3\n", r"model.py: build_model is int, not a function returning a Model"),
        (
            "def build_model():\n    raise RuntimeError('no parameters file\\nsecond line')\n",
            r"build_model\(\) raised RuntimeError: no parameters file \(line 2 of .*model.py\)$",
        ),
        (
            "import daemodel as dm\n\ndef build_model():\n    m = dm.Model('m')\n    m.ode('x', 1)\n",
            r"build_model\(\) raised ODETargetError: .* \(line 5 of .*model.py\)$",
        ),
        (MODEL.replace("T_SPAN = (0.0, 0.5)", "T_SPAN = 5"), r"T_SPAN must be a pair \(t0, t1\) of finite numbers"),
        (MODEL.replace("T_SPAN = (0.0, 0.5)", "T_SPAN = ('a', 1)"), r"with t0 < t1; got \('a', 1\)"),
        (MODEL.replace("T_SPAN = (0.0, 0.5)", "T_SPAN = (1.0, 0.0)"), r"with t0 < t1; got \(1.0, 0.0\)"),
        (MODEL.replace("T_SPAN = (0.0, 0.5)", "T_SPAN = (0, float('inf'))"), r"got \(0, inf\)"),
        (MODEL + "\nexact = 3\n", r"model.py: exact is int, not a function t -> dict name -> values"),
        (
            MODEL + "\ndef exact(t):\n    return {'x': t * np.nan, 'w': t}\n",
            r"the reference's value for 'x' is nan at t",
        ),
        (MODEL + "\ndef exact(t):\n    return {'w': t}\n", r"the reference gives no values for x"),
    ],
    ids=[
        "syntax",
        "import",
        "nothing",
        "build-not-callable",
        "build-raises",
        "build-model-error",
        "t-span-number",
        "t-span-text",
        "t-span-reversed",
        "t-span-infinite",
        "exact-not-callable",
        "exact-nan",
        "exact-partial",
    ],
)
def test_a_broken_model_file_is_one_line_and_exit_2(text, match, tmp_path, capsys, no_solve):
    path = write(tmp_path, text)
    status, err = cli(capsys, path, "--methods", "radau", "--points", 1, "--out", tmp_path / "out")
    assert status == 2
    assert one_line(err).startswith(f"daemodel compare {path}: ")
    assert re.search(match, one_line(err)), err


@pytest.mark.parametrize(
    ("args", "match"),
    [
        (("--points", 1000), r"^daemodel compare: points = 1000 is more than 12: "),
        (("--points", 0), r"^daemodel compare: points must be a positive integer; got 0$"),
        (("--points", "many"), r"^daemodel compare: argument --points: invalid int value: 'many' \(see daemodel"),
        (
            ("--methods", "radau,rk4"),
            r"^daemodel compare: unknown method 'rk4'; the methods are radau, casadi-collocation, casadi-idas",
        ),
        (("--methods", ","), r"^daemodel compare: --methods ',' names no method; give e.g. --methods radau"),
        (("--t-end", "nan"), r"^daemodel compare: --t-end must be a finite number; got nan$"),
        (("--t-end", "inf"), r"^daemodel compare: --t-end must be a finite number; got inf$"),
        (("--t-end", "-1"), r"^daemodel compare hessenberg: --t-end -1 is not after t0 = 0, where the target starts$"),
        (("--threads", "0"), r"^daemodel compare: --threads must be at least 1; got 0$"),
    ],
    ids=[
        "points-1000",
        "points-0",
        "points-text",
        "method",
        "no-method",
        "t-end-nan",
        "t-end-inf",
        "t-end-early",
        "threads",
    ],
)
def test_a_bad_argument_is_one_line_and_exit_2(args, match, tmp_path, capsys, no_solve):
    status, err = cli(capsys, "hessenberg", "--out", tmp_path / "out", *args)
    assert status == 2
    assert re.search(match, one_line(err)), err


def test_out_on_a_file_or_under_a_file_is_refused_before_any_solve(tmp_path, capsys, no_solve):
    model = write(tmp_path, MODEL + EXACT)
    existing = tmp_path / "results"
    existing.write_text("not a directory")
    status, err = cli(capsys, model, "--methods", "radau", "--points", 1, "--out", existing)
    assert status == 2
    assert one_line(err) == f"daemodel compare: --out {existing} is an existing file, not a directory; give a directory"
    under = existing / "sub"
    status, err = cli(capsys, model, "--methods", "radau", "--points", 1, "--out", under)
    assert status == 2
    assert one_line(err).startswith(f"daemodel compare: --out {under} cannot be created or written: ")
    assert one_line(err).endswith("; give a writable directory")


def test_out_is_created_and_probed_before_the_targets(tmp_path, capsys, no_solve):
    out = tmp_path / "new" / "results"
    status, err = cli(capsys, write(tmp_path, "x = 1\n"), "--out", out)
    assert status == 2 and "defines neither" in err
    assert out.is_dir() and list(out.iterdir()) == []  # the probe file is gone


def test_every_target_is_checked_before_any_is_solved(tmp_path, capsys, no_solve):
    good = write(tmp_path, MODEL + EXACT, "good.py")
    bad = write(tmp_path, "def build_model():\n    return 1 / 0\n", "bad.py")
    worse = write(tmp_path, MODEL.replace("T_SPAN = (0.0, 0.5)", "T_SPAN = 5"), "worse.py")
    status = main(["compare", good, bad, worse, "--methods", "radau", "--points", "1", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert status == 2 and "Traceback" not in err
    lines = err.strip().splitlines()
    assert [line.split(": ")[0] for line in lines] == [f"daemodel compare {bad}", f"daemodel compare {worse}"]
    assert "build_model() raised ZeroDivisionError: division by zero (line 2 of " in lines[0]


# ---- the command: solver failures and bugs --------------------------------------------------------
def test_failed_settings_are_a_table_and_exit_0(monkeypatch, tmp_path, capsys):
    def solve(model, t_span, *, method, **options):
        raise ConvergenceError(f"{method}: Newton did not converge at t = 0.1")

    monkeypatch.setattr(daemodel.solving.solver, "solve", solve)
    out = tmp_path / "out"
    status = main(["compare", write(tmp_path, MODEL + EXACT), "--methods", "radau", "--points", "2", "--out", str(out)])
    printed = capsys.readouterr()
    assert status == 0 and printed.err == ""
    assert "failed: radau: Newton did not converge at t = 0.1" in printed.out
    assert "radau failed at every setting (2 of 2)" in printed.out
    assert json.loads((out / "decay.json").read_text())["runs"][0]["setup_time"] is None


def test_a_failed_reference_solve_stops_the_target_with_exit_1(monkeypatch, tmp_path, capsys):
    real = daemodel.solving.solver.solve

    def solve(model, t_span, *, method, **options):
        if method == "reference":
            raise ConvergenceError("reference: solve_ivp failed at t = 0.2: step size underflow")
        return real(model, t_span, method=method, **options)

    monkeypatch.setattr(daemodel.solving.solver, "solve", solve)
    path = write(tmp_path, MODEL)  # no exact(): the errors need the reference solve
    status, err = cli(capsys, path, "--methods", "radau", "--points", 1, "--out", tmp_path / "out")
    assert status == 1
    assert one_line(err) == f"daemodel compare {path}: reference: solve_ivp failed at t = 0.2: step size underflow"


def test_a_bug_in_daemodel_still_shows_its_traceback(monkeypatch, tmp_path):
    def solve(*args, **kwargs):
        raise KeyError("internal")

    monkeypatch.setattr(daemodel.solving.solver, "solve", solve)
    with pytest.raises(KeyError, match="internal"):
        main(["compare", write(tmp_path, MODEL + EXACT), "--methods", "radau", "--points", "1", "--out", str(tmp_path)])


def test_a_model_file_loads_as_a_module(tmp_path):
    # dataclasses (and pickle) look the defining module up in sys.modules
    text = "from __future__ import annotations\nfrom dataclasses import dataclass\n\n\n@dataclass\nclass K:\n"
    text += "    k: float = 1.0\n" + MODEL
    model, t_span, exact = load_target(write(tmp_path, text))
    assert model.name == "decay" and t_span == (0.0, 0.5) and exact is None


def test_version_and_a_help_text_without_markup(capsys):
    """``daemodel --version`` prints the installed version; ``compare --help`` reads as plain text
    (no reST roles or double backquotes) and lists every problem with its interval."""
    from importlib.metadata import version

    from daemodel.problems import PROBLEMS

    with pytest.raises(SystemExit) as stopped:
        main(["--version"])
    assert stopped.value.code == 0 and capsys.readouterr().out == f"daemodel {version('daemodel')}\n"
    with pytest.raises(SystemExit):
        main(["compare", "--help"])
    text = capsys.readouterr().out
    assert "``" not in text and not re.search(r":[a-z]+:`", text)
    for name, problem in PROBLEMS.items():
        assert f"{name} [{problem.t_span[0]:g}, {problem.t_span[1]:g}]" in text
    assert "build_model() returning a Model" in text


# ---- a model file that imports a module beside it --------------------------------------------
SIBLING_MODEL = """
import daemodel as dm
from params import RATE


def build_model():
    m = dm.Model("decay")
    (x,) = m.states("x")
    m.ode(x, -RATE * x)
    m.initial(x=1.0)
    return m
"""


def test_a_model_file_imports_the_module_beside_it_and_each_target_its_own(tmp_path, capsys):
    import sys

    targets = []
    for folder, rate in (("a", 1), ("b", 3)):
        (tmp_path / folder).mkdir()
        (tmp_path / folder / "params.py").write_text(f"RATE = {rate}\n")
        targets.append(write(tmp_path / folder, SIBLING_MODEL))
    path_before = list(sys.path)
    models = [load_target(target)[0] for target in targets]
    assert sys.path == path_before and "params" not in sys.modules  # nothing leaks into the caller
    # each file got its own params.py: x' = -RATE x, so x(1) = exp(-RATE)
    for model, rate in zip(models, (1, 3), strict=True):
        sol = dm.solve(model, (0.0, 1.0), method="radau", rtol=1e-10, atol=1e-12)
        assert sol["x"][-1] == pytest.approx(np.exp(-rate), rel=1e-7)
    # and through the command: both targets compared, no import error
    status = main(["compare", *targets, "--methods", "radau", "--points", "1", "--out", str(tmp_path / "o")])
    captured = capsys.readouterr()
    assert status == 0, captured.err
    assert captured.err == "" and captured.out.count("decay on [0, 1]") == 2

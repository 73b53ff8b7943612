"""dm.compare and the `daemodel compare` command: errors measured against exact solutions
and the reference, the sweep's convergence order, the outputs, and every error message."""

import dataclasses
import json
import math
import re
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest

import daemodel as dm
from daemodel.comparing.cli import load_target, main
from daemodel.errors import ComparisonError, TargetError, UnknownMethodError
from daemodel.problems import HESSENBERG, PENDULUM, PROBLEMS

EXACT = HESSENBERG.exact_solution()


@pytest.fixture(scope="module")
def hessenberg():
    return dm.compare(
        HESSENBERG.model(), (0.0, 1.0), ["radau", "casadi-collocation"], reference=EXACT, points=2, progress=False
    )


def test_errors_are_those_of_a_direct_solve_against_the_exact_solution(hessenberg):
    assert [(r.method, r.settings) for r in hessenberg.runs] == [
        ("radau", "stages=3, h=0.1"),
        ("radau", "stages=3, h=0.05"),
        ("casadi-collocation", "stages=3, h=0.1"),
        ("casadi-collocation", "stages=3, h=0.05"),
    ]
    direct = dm.solve(HESSENBERG.model(), (0.0, 1.0), method="radau", stages=3, h=0.05).errors(EXACT)
    assert hessenberg.runs[1].errors == direct
    assert hessenberg.runs[1].errors["y3"]["max"] == pytest.approx(3.9e-8, rel=0.05)  # the s = 3 ceiling
    assert hessenberg.runs[1].drift["invariant"] < 1e-14


def test_the_sweep_shows_the_convergence_order(hessenberg):
    # halving h divides a y error by 2^(2s-1) = 32 at s = 3
    for coarse, fine in ((0, 1), (2, 3)):
        runs = hessenberg.runs
        order = np.log2(runs[coarse].errors["y1"]["max"] / runs[fine].errors["y1"]["max"])
        assert 4.5 < order < 5.5
    for name in ("y1", "y5"):  # two Newton solvers of the same equations
        assert hessenberg.runs[1].errors[name]["max"] == pytest.approx(hessenberg.runs[3].errors[name]["max"], rel=1e-3)


def test_default_reference_is_the_tight_scipy_solve_on_each_runs_times():
    result = dm.compare(PENDULUM.model(), (0.0, 0.5), ["radau"], points=1, progress=False)
    sol = dm.solve(PENDULUM.model(), (0.0, 0.5), method="radau", stages=3, h=0.05)
    reference = dm.solve(PENDULUM.model(), (0.0, 0.5), method="reference", t_eval=sol.t)
    assert result.runs[0].errors == sol.errors(reference)
    # the registry names the reference method; its backend describes its own default settings
    assert result.reference == "method='reference' (scipy DOP853, Radau where stiff, rtol = 1e-12, atol = 1e-12)"
    assert "reference" not in {r.method for r in dm.compare(PENDULUM.model(), (0, 0.1), points=1, progress=False).runs}


def test_a_failing_setting_is_recorded_not_raised():
    sweep = {"pinn": [{"config": dm.PINNConfig(iterations=1), "strict": True}, {"config": dm.PINNConfig(h=0.1)}]}
    result = dm.compare(HESSENBERG.model(), (0.0, 0.2), ["pinn"], reference=EXACT, sweep=sweep, progress=False)
    failed, ok = result.runs
    assert failed.settings == "h=0.05, iterations=1, strict=True" and failed.errors == {}
    assert failed.failure.startswith("pinn: not certified (the answer): at segment 1")
    assert ok.failure is None and ok.errors["y1"]["max"] < 1e-6
    assert "failed: pinn: not certified" in result.table()


def test_the_table_shows_the_pinns_certificate_and_its_time_against_radaus():
    """An under-trained PINN is flagged beside its certified distance and Radau's error; a
    trained one is success; each PINN row has its training against radau's solve, and its setup +
    solve (training, evaluation and certificate) against radau's, at the same stages and h."""
    sweep = {
        "pinn": [{"config": dm.PINNConfig(iterations=1)}, {"config": dm.PINNConfig()}],
        "radau": [{"stages": 3, "h": 0.05}],
    }
    result = dm.compare(HESSENBERG.model(), (0.0, 0.2), ["pinn", "radau"], reference=EXACT, sweep=sweep, progress=False)
    flagged, certified, radau = result.runs
    assert flagged.status.startswith("flagged: ") and certified.status == "success" and radau.status == "success"
    assert flagged.certificate["distance"] > flagged.certificate["radau_error"]
    assert certified.certificate["distance"] <= certified.certificate["radau_error"]
    assert radau.certificate == {}
    table = result.table()
    assert f"cert {flagged.certificate['distance']:.0e} >  {flagged.certificate['radau_error']:.0e}" in table
    assert f"cert {certified.certificate['distance']:.0e} <= {certified.certificate['radau_error']:.0e}" in table
    training = certified.setup_time / radau.solve_time
    total = (certified.solve_time + certified.setup_time) / (radau.solve_time + radau.setup_time)
    expected = f"pinn {certified.settings}: training {training:.3g}x radau's solve, setup + solve {total:.3g}x radau's"
    assert expected in table
    records = result.records()
    assert records[0]["status"].startswith("flagged") and records[1]["certified_distance"] > 0


def test_the_table_names_a_certificate_that_failed_at_a_step():
    """akzo-nobel at h = 2.25: the PINN equals radau, but the step estimating radau's own error
    leaves sqrt's domain; the row says why it is flagged instead of comparing two infinities."""
    from daemodel.backends.pinn import certificate

    from daemodel.comparing.tables import CERTIFICATE_FAILURES
    from daemodel.problems import PROBLEMS

    kinds = (certificate.NEWTON_FAILED, certificate.ESTIMATE_FAILED, certificate.NO_DIGIT)
    assert set(CERTIFICATE_FAILURES) == set(kinds)
    sweep = {"pinn": [{"h": 2.25}]}
    model = PROBLEMS["akzo-nobel"].model()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", dm.errors.UncertifiedWarning)
        result = dm.compare(model, (0.0, 4.5), ["pinn"], sweep=sweep, progress=False)
    (run,) = result.runs
    assert run.certificate["failure"] == certificate.ESTIMATE_FAILED and run.status.startswith("flagged: ")
    assert "cert: failed (no Radau error estimate)" in result.table()


def test_table_json_csv_and_plot(hessenberg, tmp_path):
    table = hessenberg.table()
    assert "hessenberg on [0, 1]: absolute errors against the exact solution" in table
    assert "casadi-collocation  stages=3, h=0.05" in table
    # grouped by default: the worst differential and algebraic variable of each run, by name
    head, row = table.splitlines()[1], table.splitlines()[4]
    assert "differential max" in head and "algebraic max" in head and "y1 max" not in head
    worst = max(HESSENBERG.model().compile().state_names, key=lambda n: hessenberg.runs[1].errors[n]["max"])
    assert f"{hessenberg.runs[1].errors[worst]['max']:.1e} ({worst})" in table.splitlines()[4]
    assert f"{hessenberg.runs[1].errors['y5']['max']:.1e} (y5)" in row
    detail = hessenberg.table(detail=True)
    assert all(f"{name} max (mean)" in detail for name in hessenberg.names)
    paths = hessenberg.save(tmp_path / "out")
    assert [p.name for p in paths] == ["hessenberg.json", "hessenberg.csv", "hessenberg_work_precision.png"]
    payload = json.loads(paths[0].read_text())
    assert len(payload["runs"]) == 4 and payload["algebraics"] == ["y5"]
    import pandas as pd

    frame = pd.read_csv(paths[1])
    assert list(frame.columns[:6]) == ["method", "settings", "solve_time", "setup_time", "y1_max", "y1_mean"]
    assert frame["y3_max"][1] == pytest.approx(hessenberg.runs[1].errors["y3"]["max"])
    assert paths[2].stat().st_size > 20_000
    fig = hessenberg.plot()
    assert [ax.get_title() for ax in fig.axes] == ["differential variables", "algebraic variables"]
    assert len(fig.axes[0].get_lines()) == 2  # one curve per method


def test_plot_draws_the_solve_clock_or_the_total(hessenberg):
    """The x values are each run's solve time, or setup + solve with ``clock="total"``; the legend
    notes each method's median setup time."""
    for clock, expected in (
        ("solve", [r.solve_time for r in hessenberg.runs]),
        ("total", [r.solve_time + r.setup_time for r in hessenberg.runs]),
    ):
        axis = hessenberg.plot(clock=clock).axes[0]
        drawn = [x for line in axis.get_lines() for x in line.get_xdata()]
        assert drawn == pytest.approx(expected, rel=1e-12)
        assert axis.get_xlabel() == ("solve time [s]" if clock == "solve" else "setup + solve time [s]")
    figure = hessenberg.plot()
    labels = [text.get_text() for text in figure.legends[0].get_texts()]
    assert all(ax.get_legend() is None for ax in figure.axes)  # one legend, below the panels, over no data
    # the legend names each sweep's two ends (cheapest and most accurate setting); no text on the data
    assert [label.split(" (setup ")[0] for label in labels] == [
        "radau: h=0.1 -> 0.05",
        "casadi-collocation: h=0.1 -> 0.05",
    ]
    assert all(not ax.texts for ax in figure.axes)
    assert all(run.setup_time > 0 and run.solve_time > 0 for run in hessenberg.runs)
    table = hessenberg.table().splitlines()
    assert "solve [s]" in table[1] and "setup [s]" in table[1]
    with pytest.raises(ComparisonError, match="clock must be one of 'solve', 'total'; got 'wall'"):
        hessenberg.plot(clock="wall")


def test_a_saved_comparison_loads_back_whole(hessenberg, tmp_path):
    failed = dataclasses.replace(hessenberg.runs[0], setup_time=math.nan, errors={}, drift={}, failure="radau: no")
    result = dataclasses.replace(hessenberg, runs=(failed, *hessenberg.runs[1:]))
    loaded = dm.Comparison.load(result.to_json(tmp_path / "h.json"))
    assert loaded.runs[1:] == result.runs[1:] and loaded.table() == result.table()
    assert math.isnan(loaded.runs[0].setup_time) and loaded.runs[0].failure == "radau: no"
    # a non-finite error or drift is null in the JSON and NaN again when loaded
    broken = dataclasses.replace(
        hessenberg.runs[1], errors={**hessenberg.runs[1].errors, "y1": {"max": math.nan, "mean": 1.0}}
    )
    loaded = dm.Comparison.load(dataclasses.replace(hessenberg, runs=(broken,)).to_json(tmp_path / "nan.json"))
    assert math.isnan(loaded.runs[0].errors["y1"]["max"]) and "nan" in loaded.table()
    (tmp_path / "bad.json").write_text('{"model": "m"}')
    with pytest.raises(ComparisonError, match=r"bad.json is not a comparison saved by Comparison.to_json: KeyError"):
        dm.Comparison.load(tmp_path / "bad.json")
    with pytest.raises(ComparisonError, match=r"no comparison file at .*missing.json"):
        dm.Comparison.load(tmp_path / "missing.json")


def test_a_long_variable_list_is_shortened_on_the_axis():
    """Up to six names are listed; the squeezer's 14 and 13 ran off the figure, so longer lists
    name their ends and their count."""
    from daemodel.comparing.tables import Comparison, Run

    states, algebraics = tuple(f"q{i}" for i in range(1, 15)), ("w1", "lam1")
    errors = {name: {"max": 1e-6, "mean": 1e-7} for name in (*states, *algebraics)}
    runs = (Run("radau", "h=0.1", 0.01, 0.001, errors, {}, short="h=0.1"),)
    figure = Comparison("many", (0.0, 1.0), "the exact solution", states, algebraics, runs).plot()
    assert [ax.get_ylabel() for ax in figure.axes] == [
        "max absolute error (q1 ... q14, 14 variables)",
        "max absolute error (w1, lam1)",
    ]


def test_compare_errors():
    m = HESSENBERG.model()
    with pytest.raises(UnknownMethodError, match="unknown method 'rk4'"):
        dm.compare(m, (0, 1), ["rk4"])
    with pytest.raises(ComparisonError, match="at least one method"):
        dm.compare(m, (0, 1), [])
    with pytest.raises(ComparisonError, match="sweep names pinn, which is not among the methods radau"):
        dm.compare(m, (0, 1), ["radau"], sweep={"pinn": [{}]})
    with pytest.raises(ComparisonError, match=r"sweep\['radau'\] must be a non-empty list of option dicts"):
        dm.compare(m, (0, 1), ["radau"], sweep={"radau": {"h": 0.1}})
    with pytest.raises(ComparisonError, match="points must be a positive integer; got 0"):
        dm.compare(m, (0, 1), ["radau"], points=0)
    with pytest.raises(ComparisonError, match=r"reference must be a callable .* got str"):
        dm.compare(m, (0, 1), ["radau"], reference="exact")
    with pytest.raises(dm.errors.ModelError, match=r"compare\(\) needs a Model or a CompiledDAE"):
        dm.compare("hessenberg", (0, 1))


MODEL_FILE = """
import numpy as np
import daemodel as dm

T_SPAN = (0.0, 0.5)


def build_model():
    m = dm.Model("decay")
    (x,) = m.states("x")
    (w,) = m.algebraics("w")
    m.ode(x, -w)
    m.constraint(w - x, name="tie")
    m.initial(x=1.0)
    return m


def exact(t):
    return {"x": np.exp(-t), "w": np.exp(-t)}
"""


def test_cli_compares_a_problem_and_a_model_file(tmp_path, capsys):
    path = tmp_path / "decay.py"
    path.write_text(MODEL_FILE)
    out = tmp_path / "results"
    status = main(
        [
            *("compare", "hessenberg", str(path), "--methods", "radau,casadi-idas"),
            *("--points", "2", "--out", str(out), "--no-progress"),
        ]
    )
    printed = capsys.readouterr().out
    assert status == 0
    assert "hessenberg on [0, 1]: absolute errors against the exact solution" in printed
    assert "decay on [0, 0.5]: absolute errors against the exact solution" in printed  # T_SPAN and exact()
    assert sorted(p.name for p in out.iterdir()) == [
        "decay.csv",
        "decay.json",
        "decay_work_precision.png",
        "hessenberg.csv",
        "hessenberg.json",
        "hessenberg_work_precision.png",
    ]
    decay = json.loads((out / "decay.json").read_text())
    assert decay["runs"][1]["errors"]["x"]["max"] < 1e-7  # radau at h = 0.025 on an index-1 decay
    assert "differential max" in printed and "x max (mean)" not in printed
    assert main(["compare", str(path), "--methods", "radau", "--points", "1", "--out", str(out), "--detail"]) == 0
    assert "x max (mean)" in capsys.readouterr().out  # --detail: a column per variable


def test_cli_t_end_and_target_errors(tmp_path, capsys):
    assert (
        main(
            [
                "compare",
                "pendulum",
                "--methods",
                "radau",
                "--points",
                "1",
                "--t-end",
                "0.3",
                "--out",
                str(tmp_path),
                "--no-progress",
            ]
        )
        == 0
    )
    assert "pendulum on [0, 0.3]" in capsys.readouterr().out
    assert main(["compare", "lorenz", "--out", str(tmp_path)]) == 2
    problems = (  # every one of PROBLEMS
        "hessenberg, pendulum, pendulum-index3, robertson, squeezer, akzo-nobel, car-axis, transistor-amplifier, "
        "wheelset, ring-modulator, hires, pollution, fekete, bouncing-ball"
    )
    assert problems == ", ".join(PROBLEMS)
    assert f"'lorenz' is neither a problem ({problems}) nor a .py model file" in capsys.readouterr().err
    empty = tmp_path / "empty.py"
    empty.write_text("x = 1\n")
    with pytest.raises(TargetError, match="defines neither build_model\\(\\) nor model"):
        load_target(str(empty))
    wrong = tmp_path / "wrong.py"
    wrong.write_text("def build_model():\n    return 3\n")
    with pytest.raises(TargetError, match="gave int, not a Model or CompiledDAE"):
        load_target(str(wrong))
    with pytest.raises(TargetError, match="no model file at"):
        load_target(str(tmp_path / "missing.py"))


@pytest.mark.parametrize("method", dm.methods())
def test_every_backend_sweeps_from_cheap_to_accurate(method):
    from daemodel.backends import get_backend

    backend = get_backend(method)
    sweep = backend.work_precision((0.0, 2.0), 3)
    assert len(sweep) == 3
    options = [backend.Options(**o) for o in sweep]  # every setting is a valid set of options
    steps = [getattr(o, "h", None) or getattr(getattr(o, "config", None), "h", None) for o in options]
    if all(steps):
        assert steps == pytest.approx([0.2, 0.1, 0.05])  # span / 10, halved
    else:
        assert [o.rtol for o in options] == pytest.approx([1e-4, 1e-6, 1e-8])


# ---- a model with events: each side compared on its own branch -------------------------------
def _ball():
    """The bouncing ball written out here (h = 1 at rest, g = 9.81, restitution 0.8), independent of
    the problem library."""
    ball = dm.Model("ball")
    ball.states("h v")
    ball.ode("h", "v")
    ball.ode("v", "-9.81")
    ball.initial(h=1.0, v=0.0)
    ball.event("floor", "h", direction=-1, reset={"v": "-0.8*v"})
    return ball


def _ball_exact(t):
    """Parabolas between the impacts t_1 = sqrt(2/g), t_(k+1) = t_k + 2 u_k / g, u_k = 0.8^k sqrt(2 g);
    a plain callable that states no events."""
    g, t = 9.81, np.asarray(t, dtype=float)
    starts, speeds = [0.0, np.sqrt(2 / g)], [0.0, 0.8 * np.sqrt(2 * g)]
    while len(starts) < 12:
        starts.append(starts[-1] + 2 * speeds[-1] / g)
        speeds.append(0.8 * speeds[-1])
    k = np.searchsorted(starts, t, side="right") - 1
    s = t - np.array(starts)[k]
    h = np.where(k == 0, 1.0, 0.0) + np.array(speeds)[k] * s - g * s**2 / 2
    return {"h": h, "v": np.array(speeds)[k] - g * s}


def test_errors_of_a_correct_bouncing_ball_solve_are_at_its_accuracy():
    """At an impact one side may hold the velocity before the reset and the other the one after it
    (8 m/s apart): every method was reported ~6-8 off.  Now the instants are left out of the
    variables' errors and compared by themselves, before with before and after with after."""
    from daemodel.problems import BOUNCING_BALL

    ball = _ball()
    sol = dm.solve(ball, (0.0, 3.0), method="radau", h=0.01)  # exact steps on parabolas: rounding only
    assert len(sol.events["floor"]["t"][0]) == 6
    for name, error in sol.errors(_ball_exact).items():  # was v: 6.4
        assert error["max"] < 1e-13, name
    report = sol.error_report(_ball_exact)  # a plain callable: only the solution's instants are known
    assert report.excluded == 6 and report.instants["floor"].reference_count is None
    assert math.isnan(report.instants["floor"].t) and report.instants["floor"].count == 6
    # the library's exact solution states its impacts: they are paired and compared
    report = sol.error_report(BOUNCING_BALL.exact_solution())
    floor = report.instants["floor"]
    assert (floor.count, floor.reference_count, report.excluded) == (6, 6, 6)
    assert floor.t < 1e-12 and floor.values < 1e-13 and set(floor.before) == {"h", "v"}
    # another method's Solution on the same times (its impacts 1e-12 from these)
    reference = dm.solve(ball, (0.0, 3.0), method="reference", t_eval=sol.t)
    for name, error in sol.errors(reference).items():  # was v: ~8
        assert error["max"] < 1e-10, name
    assert sol.error_report(reference).instants["floor"].values < 1e-10
    # and on its own times, through its dense output (which never interpolates across an impact)
    idas = dm.solve(ball, (0.0, 3.0), method="casadi-idas", rtol=1e-10, atol=1e-10)
    for one, other in ((sol, idas), (idas, sol)):
        report = one.error_report(other)
        assert max(e["max"] for e in report.variables.values()) < 1e-9
        assert report.instants["floor"].t < 1e-11 and report.instants["floor"].values < 1e-9


def test_compare_on_the_bouncing_ball_is_at_each_solves_accuracy():
    from daemodel.problems import BOUNCING_BALL

    exact = BOUNCING_BALL.exact_solution()
    methods = ["radau", "casadi-idas", "casadi-collocation", "reference", "pinn"]
    result = dm.compare(BOUNCING_BALL.model(), (0.0, 3.0), methods, reference=exact, points=1, steps=40, progress=False)
    # fixed steps (h = 0.075) on parabolas are exact but for the impacts' location (1e-12 in t);
    # the adaptive methods at rtol = atol = 1e-4
    bound = {"radau": 1e-9, "casadi-collocation": 1e-9, "pinn": 1e-9, "casadi-idas": 1e-4, "reference": 1e-4}
    for run in result.runs:
        assert run.failure is None and run.status == "success", run.method
        assert max(e["max"] for e in run.errors.values()) < bound[run.method], run.method  # was 6-8
        floor = run.instants["floor"]
        assert (floor["count"], floor["reference_count"], run.excluded) == (6, 6, 6)
        assert floor["t"] < bound[run.method] / 10 and max(floor["before"], floor["after"]) < bound[run.method]
    table = result.table()
    assert "event t   event y excluded" in table.splitlines()[1]
    assert all(line.split("  cert")[0].rstrip().endswith(" 6") for line in table.splitlines()[3:8])
    assert "excluded: output values within 1e-9 of the span of either side's instant" in table
    record = result.records()[0]
    assert record["floor_count"] == 6 and record["excluded"] == 6 and record["floor_t"] < 1e-10
    # the default reference (scipy at 1e-12, solved on each run's times) measures the same way
    result = dm.compare(BOUNCING_BALL.model(), (0.0, 3.0), ["radau"], points=1, steps=40, progress=False)
    assert max(e["max"] for e in result.runs[0].errors.values()) < 1e-9
    assert result.runs[0].instants["floor"]["t"] < 1e-11


def test_a_comparison_with_events_loads_back_whole_and_says_what_it_could_not_pair(tmp_path):
    result = dm.compare(_ball(), (0.0, 3.0), ["radau"], reference=_ball_exact, points=1, steps=40, progress=False)
    run = result.runs[0]
    assert run.instants["floor"]["reference_count"] is None and run.excluded == 6
    assert "radau stages=3, h=0.075: 6 floor instants; the reference states none" in result.table()
    assert f"{'-':>10}{'-':>10}{6:>9d}" in result.table()  # nothing paired: no event columns, 6 left out
    loaded = dm.Comparison.load(result.to_json(tmp_path / "ball.json"))
    assert loaded.table() == result.table() and loaded.runs[0].excluded == 6
    payload = json.loads((tmp_path / "ball.json").read_text())
    payload["runs"][0]["instants"]["floor"]["count"] = "six"
    (tmp_path / "bad.json").write_text(json.dumps(payload))
    with pytest.raises(ComparisonError, match=r"field 'runs\[0\].instants.floor.count' is not a number"):
        dm.Comparison.load(tmp_path / "bad.json")
    del payload["runs"][0]["instants"]["floor"]["count"]
    (tmp_path / "bad.json").write_text(json.dumps(payload))
    with pytest.raises(ComparisonError, match=r"instants.floor' is not an object of count, reference_count, t"):
        dm.Comparison.load(tmp_path / "bad.json")


def test_daemodel_compare_on_the_bouncing_ball(tmp_path, capsys):
    methods = "radau,casadi-idas,casadi-collocation,reference"
    assert main(["compare", "bouncing-ball", "--methods", methods, "--points", "1", "--out", str(tmp_path)]) == 0
    assert "bouncing-ball on [0, 3]: absolute errors against the exact solution" in capsys.readouterr().out
    result = dm.Comparison.load(tmp_path / "bouncing-ball.json")
    assert [max(e["max"] for e in r.errors.values()) < 1e-4 for r in result.runs] == [True] * 4


# (the model file imports the double pendulum of tests/backends/pinn from a copy beside it, as a user's would)
DOUBLE_PENDULUM_FILE = """
from pinn_hard_models import double_pendulum

T_SPAN = (0.0, 1.0)


def build_model():
    return double_pendulum(90.0, 180.0)  # (released at 90 and 180 degrees)
"""


def test_daemodel_compare_shows_a_certified_pinn_flagged_where_radau_is(tmp_path, capsys):
    """The double pendulum at h = 0.05: radau is flagged by its local error estimate and is 11 off in
    l1; the PINN, certified within 4e-16 of radau, is as far off. Before, its row read 'cert 4e-16 >
    2e-12' with no flag (and its status was "success"); now 'cert ... <= ...  flagged'."""
    model = tmp_path / "double_pendulum.py"
    model.write_text(DOUBLE_PENDULUM_FILE)
    shutil.copy(Path(__file__).parents[1] / "backends" / "pinn" / "pinn_hard_models.py", tmp_path)
    args = ["compare", str(model), "--methods", "radau,pinn", "--points", "1", "--steps", "20"]
    assert main([*args, "--out", str(tmp_path / "out"), "--no-progress"]) == 0
    table = capsys.readouterr().out
    rows = {
        line.split()[0]: line
        for line in table.splitlines()
        if line.startswith(("radau ", "pinn ")) and "training" not in line  # (not the notes below the table)
    }
    assert rows["radau"].endswith("flagged")
    assert re.search(r"e\+01 \(l\d\)", rows["pinn"]), rows["pinn"]  # the multipliers, as far off as radau's
    assert re.search(r"cert \de-\d\d <= \de-\d\d  flagged$", rows["pinn"]), rows["pinn"]
    saved = json.loads((tmp_path / "out" / "double_pendulum.json").read_text())
    (pinn,) = [run for run in saved["runs"] if run["method"] == "pinn"]
    assert pinn["status"].startswith("flagged: radau's local error estimate at the same h and stages")


def test_no_method_pays_for_the_work_the_models_solves_share(monkeypatch):
    """The first method compare timed carried the model's shared work (the reduced system, the branch
    check's functions, the initial-value checks) in its setup, and the others did not: the pendulum's
    first radau solve 231 ms before its method ran, the next 0.2 ms.  Slowed here by 0.3 s per piece of
    generated code, it must be on no method's clock."""
    import time

    from daemodel.compiling.init import NumericSystem

    lambdify = NumericSystem._lambdify

    def slow(self, exprs):
        time.sleep(0.3)
        return lambdify(self, exprs)

    monkeypatch.setattr(NumericSystem, "_lambdify", slow)
    # (radau on casadi's virtual machine: its machine code's compile is its own setup, not shared work)
    sweep = {"radau": [{"rtol": 1e-6, "atol": 1e-6, "jit": False}], "casadi-idas": [{"rtol": 1e-6, "atol": 1e-6}]}
    result = dm.compare(
        PENDULUM.model().compile(), (0.0, 0.5), ["radau", "casadi-idas"], reference=None, sweep=sweep, progress=False
    )
    assert [r.method for r in result.runs] == ["radau", "casadi-idas"]
    for run in result.runs:
        assert run.setup_time < 0.3, (run.method, run.setup_time)


def test_a_time_limit_is_raised_not_recorded_as_a_failing_setting(monkeypatch):
    """A SolverError is recorded as the setting's failure and the next setting runs; the caller's time
    limit (a TimeLimitError, a SolverError too) ended only that setting, and compare went on."""
    from daemodel.errors import TimeLimitError
    from daemodel.solving import solver

    calls = []

    def struck(*_, **__):
        calls.append(1)
        raise TimeLimitError("stop here")

    monkeypatch.setattr(solver, "solve", struck)
    with pytest.raises(TimeLimitError, match=r"^stop here$"):
        dm.compare(HESSENBERG.model(), (0.0, 0.2), ["radau"], reference=EXACT, progress=False)
    assert calls == [1]

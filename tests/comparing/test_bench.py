"""dm.bench and `daemodel bench`: scd read as the Test Set reads it, checked against direct solves and
closed forms; the runs stored, resumed and refused when damaged; processes and Ray; the report
(every plot inline, one per problem, labels that never overlap, opened in a headless browser)."""

import json
import math
import os
import shutil
import subprocess
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest
from daemodel.backends import get_backend

import daemodel as dm
from daemodel.comparing.bench import default_sweep, plan_settings, run_setting
from daemodel.comparing.bench_files import RUN_FILE_BYTES, read_run
from daemodel.comparing.cli import main
from daemodel.comparing.suites import ERROR_FLOOR, resolve, scd
from daemodel.errors import BenchError, InvalidOptionError
from daemodel.problems import FAMILIES, HESSENBERG, POLLUTION_SPECIES, PROBLEMS

SWEEP = {"radau": [{"h": 0.1, "estimate_bound": 1e-14}, {"rtol": 1e-8, "atol": 1e-8}]}


@pytest.fixture(scope="module")
def paper(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench")
    result = dm.bench(["paper"], ["casadi-idas", "radau"], out, tolerances=(1e-4, 1e-8), sweep=SWEEP, progress=False)
    return out, result


def test_scd_is_minus_log10_of_the_largest_relative_error_absolute_where_the_reference_is_zero():
    reference = {"a": 2.0, "b": 0.0, "c": -4.0}
    digits, where = scd({"a": 2.002, "b": 1e-5, "c": -4.0}, reference)
    assert (digits, where) == (pytest.approx(3.0), "a")  # |0.002| / 2 = 1e-3 beats b's absolute 1e-5
    digits, where = scd({"a": 2.0, "b": 1e-2, "c": -4.0}, reference)
    assert (digits, where) == (pytest.approx(2.0), "b")
    assert scd({"a": 2.002, "b": 0.0, "c": -4.0 * (1 + 1e-9)}, reference, names=("c",)) == (pytest.approx(9.0), "c")
    assert scd(dict(reference), reference) == (pytest.approx(-math.log10(ERROR_FLOOR)), "a")
    assert scd({"a": np.nan, "b": 0.0, "c": 1.0}, reference)[0] == -np.inf
    with pytest.raises(BenchError, match="the solution has no value for b"):
        scd({"a": 2.0}, reference)


def test_the_suites_are_read_from_the_problem_library():
    testset = resolve("testset")
    assert {p.name for p in testset} == {
        name for name, p in PROBLEMS.items() if "Test Set for IVP Solvers" in p.source and p.reference
    }
    assert {"akzo-nobel", "car-axis", "squeezer", "transistor-amplifier", "wheelset", "ring-modulator", "hires",
            "pollution", "fekete"} <= {p.name for p in testset}  # fmt: skip
    assert next(p for p in testset if p.name == "pollution").scd_names == tuple(
        name for name in POLLUTION_SPECIES if name != "O1D"
    )
    squeezer = next(p for p in testset if p.name == "squeezer")
    assert squeezer.scd_names == tuple(f"q{k}" for k in range(1, 8))
    assert squeezer.reference == PROBLEMS["squeezer"].reference
    paper = resolve(["paper", "paper"])
    assert [p.name for p in paper] == ["hessenberg", "pendulum"]
    assert paper[0].reference == pytest.approx({"y1": math.e**2, "y2": math.e**-1, "y3": math.e**2,
                                                "y4": math.e**-1, "y5": math.e})  # fmt: skip
    assert paper[1].reference is None  # no closed form, no published values: computed by bench
    with pytest.raises(BenchError, match=r"'tests' is neither a suite \(testset, paper, families\) nor a .py model"):
        resolve(["tests"])
    with pytest.raises(BenchError, match="at least one suite"):
        resolve([])


def test_the_families_suite_lists_each_family_at_three_sizes_with_its_scipy_reference():
    families = resolve("families")
    assert [p.name for p in families] == [
        "pendulum_chain-4", "pendulum_chain-8", "pendulum_chain-16",
        "reaction_diffusion-25", "reaction_diffusion-50", "reaction_diffusion-100",
    ]  # fmt: skip
    for p in families:
        assert p.suite == "families" and p.target == p.name and p.t_span == (0.0, 1.0)
        assert p.reference == FAMILIES[p.name].reference and p.scd_names == tuple(p.reference)
        assert "scipy solve_ivp" in p.reference_source
    assert [p.name for p in resolve(["families", "paper"])][-2:] == ["hessenberg", "pendulum"]


def test_a_family_member_run_reaches_six_digits_against_its_reference():
    grid = next(p for p in resolve("families") if p.name == "reaction_diffusion-25")
    runs, skipped = plan_settings(grid, "radau", get_backend("radau"), (1e-8,), 3, None)
    assert len(runs) == 1 and not skipped
    record = run_setting(None, runs[0], None, 1)
    assert record["status"] == "success" and record["problem"] == "reaction_diffusion-25"
    assert record["scd"] > 6


def test_default_sweeps_are_tolerances_for_adaptive_methods_and_steps_for_fixed_ones():
    akzo = next(p for p in resolve("testset") if p.name == "akzo-nobel")
    tolerances = (1e-3, 1e-7)
    assert default_sweep(get_backend("radau"), akzo, tolerances, 2) == [
        {"rtol": 1e-3, "atol": 1e-3},
        {"rtol": 1e-7, "atol": 1e-7},
    ]
    assert default_sweep(get_backend("casadi-collocation"), akzo, tolerances, 2) == [
        {"stages": 3, "h": 18.0},
        {"stages": 3, "h": 9.0},
    ]
    # the PINN beyond its bench_max_steps (200 segments) is skipped with the reason, never trained
    transistor = next(p for p in resolve("testset") if p.name == "transistor-amplifier")
    runs, skipped = plan_settings(transistor, "pinn", get_backend("pinn"), tolerances, 2, None)
    assert runs == [] and len(skipped) == 2
    assert "h = 0.00025 makes 800 steps over [0, 0.2], more than pinn's bench_max_steps = 200" in skipped[0][1]
    with pytest.raises(BenchError, match=r"h = 1e-09 makes .* fix sweep\['radau'\]"):
        plan_settings(akzo, "radau", get_backend("radau"), tolerances, 2, {"radau": [{"h": 1e-9}]})


def test_scd_of_a_run_is_that_of_the_same_solve_against_the_closed_form(paper):
    _, result = paper
    record = next(r for r in result.records if (r["problem"], r["method"], r["index"]) == ("hessenberg", "radau", 1))
    assert record["settings"] == "rtol=1e-08, atol=1e-08" and record["status"] == "success"
    solution = dm.solve(HESSENBERG.model(), (0.0, 1.0), method="radau", rtol=1e-8, atol=1e-8)
    exact = HESSENBERG.exact_solution()(np.array([1.0]))
    worst = max(abs(solution[n][-1] - exact[n][0]) / abs(exact[n][0]) for n in exact)
    assert record["scd"] == pytest.approx(-math.log10(worst), abs=1e-9)
    assert 7 < record["scd"] < 13
    assert record["wall_time"] == pytest.approx(record["setup_time"] + record["solve_time"])
    assert record["stats"]["steps"] == solution.stats["steps"]


def test_a_flagged_run_is_recorded_as_flagged_with_its_status(paper):
    _, result = paper
    record = next(r for r in result.records if (r["problem"], r["method"], r["index"]) == ("hessenberg", "radau", 0))
    assert record["status"] == "flagged"
    assert record["flag"].startswith("flagged: radau's local error estimate")
    assert record["scd"] is not None
    assert next(row for row in result.summary() if row["method"] == "radau")["flagged"] == 2


def test_the_pendulum_is_measured_against_a_tight_scipy_solve_kept_in_the_folder(paper):
    out, result = paper
    stored = json.loads((out / "references" / "pendulum.json").read_text())
    direct = dm.solve(PROBLEMS["pendulum"].model(), (0.0, 1.0), method="reference", t_eval=[0.0, 1.0])
    assert stored["values"]["y1"] == pytest.approx(float(direct["y1"][-1]), rel=1e-14)
    pendulum = next(p for p in result.problems if p.name == "pendulum")
    assert pendulum.reference_source.startswith("scipy")


def test_a_rerun_solves_only_the_run_whose_file_was_deleted(paper, tmp_path):
    out, first = paper
    shutil.copytree(out, tmp_path / "copy")
    (tmp_path / "copy" / "runs" / "pendulum.casadi-idas.01.json").unlink()
    before = {p.name: p.stat().st_mtime_ns for p in (tmp_path / "copy" / "runs").iterdir()}
    again = dm.bench(
        ["paper"], ["casadi-idas", "radau"], tmp_path / "copy", tolerances=(1e-4, 1e-8), sweep=SWEEP, progress=False
    )
    assert again.computed == 1
    after = {p.name: p.stat().st_mtime_ns for p in (tmp_path / "copy" / "runs").iterdir()}
    assert {n for n in after if before.get(n) != after[n]} == {"pendulum.casadi-idas.01.json"}
    redone = next(
        r for r in again.records if r["problem"] == "pendulum" and r["method"] == "casadi-idas" and r["index"] == 1
    )
    old = next(
        r for r in first.records if r["problem"] == "pendulum" and r["method"] == "casadi-idas" and r["index"] == 1
    )
    assert redone["scd"] == pytest.approx(old["scd"], abs=1e-12)  # IDAS is deterministic


def test_a_damaged_run_file_is_refused_naming_the_file_and_the_field(paper, tmp_path):
    out, _ = paper
    path = tmp_path / "hessenberg.radau.01.json"
    record = json.loads((out / "runs" / "hessenberg.radau.01.json").read_text())
    path.write_text(json.dumps({**record, "scd": "twelve"}))
    with pytest.raises(
        BenchError, match=r"hessenberg.radau.01.json: field 'scd' must be a number or null; found 'twelve'"
    ):
        read_run(path)
    path.write_text(json.dumps({**record, "status": "fine"}))
    with pytest.raises(BenchError, match="field 'status' must be success or flagged or failed or skipped"):
        read_run(path)
    path.write_text(json.dumps({**record, "format": "pickle"}))
    with pytest.raises(BenchError, match="field 'format'"):
        read_run(path)
    path.write_text(" " * (RUN_FILE_BYTES + 1))
    with pytest.raises(BenchError, match="more than a bench run file holds"):
        read_run(path)
    path.write_text("[1, 2")
    with pytest.raises(BenchError, match="is not a daemodel bench run file"):
        read_run(path)
    path.write_text('{"format": "daemodel-bench-run", "scd": 9')  # (cut short: the fix is said as for a field)
    with pytest.raises(BenchError, match=r"run file \(JSONDecodeError: .*\)\. Remove the file to"):
        read_run(path)
    path.write_text("[1, 2]")
    with pytest.raises(BenchError, match=r"it holds a list, not an object\. Remove the file to run it again$"):
        read_run(path)


def test_a_run_past_its_time_limit_is_a_failure_named_time_limit_error(tmp_path):
    # (in a fresh cache the limit strikes while radau compiles or factors; a method that took the signal's
    # error for one of its own and went on would still be recorded as a TimeLimitError)
    result = dm.bench(
        ["paper"], ["radau"], tmp_path, sweep={"radau": [{"rtol": 1e-11, "atol": 1e-11}]}, time_limit=1e-3,
        progress=False,
    )  # fmt: skip
    for record in result.records:
        assert record["status"] == "failed" and record["error_class"] == "TimeLimitError"
        assert "ran past the time limit of 0.001 s" in record["error"]
        assert record["solve_time"] >= 1e-3
    assert result.summary()[0]["failures"] == {"TimeLimitError": 2}


def test_a_time_limit_that_strikes_inside_idas_is_still_a_time_limit_error():
    from daemodel.comparing.bench import Setting, run_setting

    # IDAS needs over a minute for the transistor amplifier at 1e-9 (StepLimitError after 100,000
    # steps): the limit strikes inside its residual callback, which IDAS reports as its own failure
    transistor = next(p for p in resolve("testset") if p.name == "transistor-amplifier")
    setting = Setting(transistor, "casadi-idas", 0, {"rtol": 1e-9, "atol": 1e-9}, "rtol=1e-09, atol=1e-09", "")
    record = run_setting(None, setting, 1.0, 1)
    assert record["status"] == "failed" and record["error_class"] == "TimeLimitError"
    assert record["error"].startswith("transistor-amplifier: casadi-idas at rtol=1e-09, atol=1e-09 ran past the time")
    assert 1.0 <= record["solve_time"] < 30


def test_bench_options_are_checked_before_any_solve(tmp_path):
    with pytest.raises(InvalidOptionError, match="workers must be a positive integer; got 0"):
        dm.bench("paper", out=tmp_path, workers=0)
    with pytest.raises(InvalidOptionError, match="executor must be one of local, processes, ray; got 'mpi'"):
        dm.bench("paper", out=tmp_path, executor="mpi")
    with pytest.raises(InvalidOptionError, match="tolerances must be numbers between 0 and 1"):
        dm.bench("paper", out=tmp_path, tolerances=(1e-3, 2.0))
    with pytest.raises(InvalidOptionError, match="time_limit must be a positive number"):
        dm.bench("paper", out=tmp_path, time_limit=0)
    with pytest.raises(BenchError, match="sweep names pinn, which is not among the methods radau"):
        dm.bench("paper", ["radau"], out=tmp_path, sweep={"pinn": [{}]})
    assert not (tmp_path / "runs").exists()


def test_runs_on_processes_give_the_same_digits(paper, tmp_path):
    _, local = paper
    result = dm.bench(["paper"], ["casadi-idas"], tmp_path, tolerances=(1e-4, 1e-8), workers=2, progress=False)
    assert result.computed == 4
    expected = {(r["problem"], r["index"]): r["scd"] for r in local.records if r["method"] == "casadi-idas"}
    assert {(r["problem"], r["index"]): r["scd"] for r in result.records} == pytest.approx(expected, abs=1e-12)


def test_runs_on_ray(tmp_path):
    pytest.importorskip("ray", reason="Ray is not installed (pip install 'daemodel[ray]')")
    result = dm.bench(
        ["paper"], ["casadi-idas"], tmp_path, tolerances=(1e-4,), executor="ray", workers=2, progress=False
    )
    assert [r["status"] for r in result.records] == ["success", "success"]


class _Images(HTMLParser):
    def __init__(self):
        super().__init__()
        self.images, self.links = [], []

    def handle_starttag(self, tag, attrs):
        attrs = dict(attrs)
        if tag == "img":
            self.images.append(attrs)
        for key in ("href", "src"):
            if key in attrs and tag != "img":
                self.links.append(attrs[key])


def test_the_report_holds_every_plot_inline_one_per_problem(paper):
    out, result = paper
    parser = _Images()
    parser.feed((out / "report.html").read_text())
    assert parser.links == []  # no stylesheet, script or page it would need from elsewhere
    assert [image["data-problem"] for image in parser.images] == [p.name for p in result.problems]
    for image in parser.images:
        assert image["src"].startswith("data:image/png;base64,")
        assert len(image["src"]) > 10_000
    assert (out / "results.csv").read_text().count("\n") == len(result.records) + 1
    stored = json.loads((out / "results.json").read_text())
    assert len(stored["runs"]) == len(result.records)
    assert stored["summary"] == json.loads(json.dumps(result.summary()))
    assert stored["against_radau"] == []  # (no method beyond the classical ones in this run)
    page = (out / "report.html").read_text()
    assert "Against radau at equal error" not in page
    assert f"<p>2 problems, 2 methods, {len(result.records)} runs." in page
    # the runs' step counts under each method's own name: IDAS's nsteps (the column was empty for it)
    idas = next(r for r in result.records if r["method"] == "casadi-idas" and r["status"] == "success")
    row = f'<td>{idas["settings"]}</td><td class="success">success</td><td>{idas["scd"]:.2f}</td>'
    assert row in page and f"<td>{idas['stats']['nsteps']}</td>" in page.split(row)[1].split("</tr>")[0]


def _overlaps(fig) -> list:
    """Pairs of visible tick labels whose boxes intersect, per axis, as the renderer draws them."""
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    found = []
    for ax in fig.axes:
        for axis in (ax.xaxis, ax.yaxis):
            boxes = [
                (label.get_text(), label.get_window_extent(renderer))
                for label in axis.get_ticklabels(which="both")
                if label.get_visible() and label.get_text()
            ]
            lo, hi = sorted(axis.get_view_interval())
            boxes = [b for b, tick in zip(boxes, axis.get_ticklocs(), strict=False) if lo <= tick <= hi] or boxes
            found += [(a[0], b[0]) for i, a in enumerate(boxes) for b in boxes[i + 1 :] if a[1].overlaps(b[1])]
    return found


def test_compare_plot_labels_never_overlap_on_a_narrow_log_axis():
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from daemodel.comparing.tables import Comparison, Run

    # solve times from 3.1 to 3.9 ms: matplotlib's default labels the minor ticks "3x10^-3 4x10^-3"
    runs = tuple(
        Run("radau", f"h={h}", t, 0.01, {"y1": {"max": e, "mean": e}}, {}, short=f"h={h}")
        for h, t, e in ((0.1, 3.1e-3, 4e-6), (0.05, 3.5e-3, 2e-6), (0.025, 3.9e-3, 1.2e-6))
    )
    comparison = Comparison(model="m", t_span=(0.0, 1.0), reference="exact", states=("y1",), algebraics=(), runs=runs)
    fig = comparison.plot()
    FigureCanvasAgg(fig)
    assert _overlaps(fig) == []
    fig.canvas.draw()
    for axis in (fig.axes[0].xaxis, fig.axes[0].yaxis):
        lo, hi = sorted(axis.get_view_interval())
        shown = [
            t
            for t, label in zip(axis.get_ticklocs(), axis.get_ticklabels(), strict=True)
            if lo <= t <= hi and label.get_text()
        ]
        assert len(shown) >= 2
    # and over many decades
    wide = tuple(
        Run("radau", f"h={k}", 10.0**-k, 0.01, {"y1": {"max": 10.0**-k, "mean": 1.0}}, {}, short=f"h={k}")
        for k in range(1, 12)
    )
    fig = Comparison(model="m", t_span=(0.0, 1.0), reference="exact", states=("y1",), algebraics=(), runs=wide).plot()
    FigureCanvasAgg(fig)
    assert _overlaps(fig) == []


def test_bench_plot_labels_never_overlap(paper):
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from daemodel.comparing.bench_report import work_precision_figure

    _, result = paper
    for problem in result.problems:
        fig = work_precision_figure(
            problem, result.methods, [r for r in result.records if r["problem"] == problem.name]
        )
        FigureCanvasAgg(fig)
        assert _overlaps(fig) == []


def _browser():
    for name in ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable", "headless_shell"):
        found = shutil.which(name)
        if found:
            return found
    return None


def test_the_report_opens_in_a_headless_browser_without_console_errors(paper, tmp_path):
    out, _ = paper
    url = (out / "report.html").resolve().as_uri()
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        sync_playwright = None
    if sync_playwright is not None:
        errors = []
        with sync_playwright() as p:
            try:
                browser = p.chromium.launch()
            except Exception as error:  # no browser downloaded for playwright
                pytest.skip(f"playwright found no Chromium: {error}")
            page = browser.new_page()
            page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.goto(url)
            shot = page.screenshot(full_page=True)
            loaded = page.evaluate("Array.from(document.images).every(i => i.complete && i.naturalWidth > 0)")
            browser.close()
        assert errors == [] and loaded and len(shot) > 10_000
        return
    browser = _browser()
    if browser is None:
        pytest.skip("no headless browser: neither playwright nor a chromium/google-chrome binary is installed")
    shot = tmp_path / "shot.png"
    run = subprocess.run(
        [browser, "--headless", "--disable-gpu", "--no-sandbox", "--enable-logging=stderr", "--v=0",
         f"--screenshot={shot}", "--window-size=1280,2400", url],
        capture_output=True, text=True, timeout=120, env={**os.environ, "HOME": str(tmp_path)},
    )  # fmt: skip
    # Chromium logs every console message, errors included, as INFO:CONSOLE; the report has no script,
    # so any console line at all is a fault
    console = [line for line in run.stderr.splitlines() if ":CONSOLE" in line]
    assert console == []
    assert shot.is_file() and shot.stat().st_size > 10_000


def test_the_command_runs_a_suite_and_refuses_mistakes(tmp_path, capsys):
    out = tmp_path / "cli"
    assert (
        main(["bench", "paper", "--methods", "casadi-idas", "--tolerances", "1e-4", "--out", str(out), "--no-progress"])
        == 0
    )
    printed = capsys.readouterr().out
    assert "casadi-idas  2/2" in printed and f"wrote {out / 'report.html'}" in printed
    assert sorted(p.name for p in (out / "runs").iterdir()) == [
        "hessenberg.casadi-idas.00.json",
        "pendulum.casadi-idas.00.json",
    ]
    assert (
        main(["bench", "paper", "--methods", "casadi-idas", "--tolerances", "1e-4", "--out", str(out), "--no-progress"])
        == 0
    )
    assert "2 runs (0 solved now)" in capsys.readouterr().out
    assert main(["bench", "nosuch", "--out", str(out)]) == 2
    assert "daemodel bench: 'nosuch' is neither a suite" in capsys.readouterr().err
    assert main(["bench", "paper", "--tolerances", "tight", "--out", str(out)]) == 2
    assert "--tolerances 'tight' is not a list of numbers" in capsys.readouterr().err


def test_a_model_file_is_benched_against_its_exact_solution(tmp_path):
    model = tmp_path / "decay.py"
    model.write_text(
        "import numpy as np\n"
        "import daemodel as dm\n"
        "T_SPAN = (0.0, 2.0)\n"
        "def build_model():\n"
        "    m = dm.Model('decay')\n"
        "    m.states(['y'])\n"
        "    m.ode('y', '-y')\n"
        "    m.initial(y=1.0)\n"
        "    return m\n"
        "def exact(t):\n"
        "    return {'y': np.exp(-np.asarray(t))}\n"
    )
    result = dm.bench([str(model)], ["casadi-idas"], tmp_path / "out", tolerances=(1e-6,), progress=False)
    (record,) = result.records
    assert record["problem"] == "decay" and result.problems[0].reference == {"y": pytest.approx(math.exp(-2.0))}
    assert 4 < record["scd"] < 10
    assert Path(result.paths[0]).name == "report.html"


def test_a_neural_method_is_set_against_radau_at_equal_error():
    """Per problem, the PINN's most accurate success (its setup + solve: training included) beside radau's
    fastest success with at least as many digits; a problem it never solves says why, one where radau
    never gets as far says so."""
    from daemodel.comparing.bench_report import against_radau, against_radau_cells
    from daemodel.comparing.suites import BenchProblem

    def run(problem, method, status, scd, setup, solve, error_class=None, settings="s"):
        return {"problem": problem, "method": method, "status": status, "scd": scd, "setup_time": setup,
                "solve_time": solve, "error_class": error_class, "settings": settings}  # fmt: skip

    records = [
        run("a", "radau", "success", 5.0, 0.1, 0.002), run("a", "radau", "success", 9.0, 0.1, 0.005),
        run("a", "radau", "success", 12.0, 0.1, 0.020), run("a", "radau", "flagged", 9.5, 0.0, 0.001),
        run("a", "pinn", "success", 8.5, 1.0, 0.1, settings="h=0.1"), run("a", "pinn", "flagged", 10.0, 1.0, 0.1),
        run("a", "pinn", "success", 6.0, 0.5, 0.05),
        run("b", "radau", "success", 4.0, 0.1, 0.001), run("b", "pinn", "success", 7.0, 2.0, 0.2, settings="h=0.2"),
        run("c", "radau", "success", 4.0, 0.1, 0.001), run("c", "pinn", "skipped", None, None, None),
        run("c", "pinn", "failed", None, 0.0, 60.0, "TimeLimitError"),
        run("c", "pinn", "failed", None, 0.0, 1.0, "TimeLimitError"),
    ]  # fmt: skip
    problems = [BenchProblem(name, name, "testset", (0.0, 1.0)) for name in "abc"]
    rows = against_radau(records, ["radau", "casadi-idas", "pinn"], problems)
    assert [(r["problem"], r["method"]) for r in rows] == [("a", "pinn"), ("b", "pinn"), ("c", "pinn")]
    a, b, c = rows
    # a: its 8.5 digits (the flagged 10 does not count) against radau's 9 in 5 ms (the flagged 9.5 in 1 ms neither)
    assert (a["scd"], a["wall"], a["radau_scd"], a["radau_solve"]) == (8.5, 1.1, 9.0, 0.005)
    assert a["wall_ratio"] == pytest.approx(220.0) and a["solve_ratio"] == pytest.approx(20.0)
    assert against_radau_cells(a) == [
        "a", "pinn", "8.5 scd at h=0.1: 1.1 s setup + solve, 100 ms solve", "9.0 scd in 5 ms", "220x (20x solve)",
    ]  # fmt: skip
    assert b["none"] == "no successful radau run reaches 7.0 digits" and "radau_solve" not in b
    assert against_radau_cells(b)[3:] == ["no successful radau run reaches 7.0 digits", ""]
    assert c == {"problem": "c", "method": "pinn", "none": "2 TimeLimitError, 1 skipped"}
    assert against_radau_cells(c) == ["c", "pinn", "none: 2 TimeLimitError, 1 skipped", "", ""]
    assert against_radau(records, ["radau", "casadi-idas"], problems) == []


def test_against_radau_says_whether_radau_ran_failed_or_fell_short():
    """A row with no radau run beside it says which: radau not among the methods (before: 'no successful
    radau run reaches 7.0 digits', as if it had run), radau's runs there all failed or flagged (with their
    counts), or none of its successes as accurate."""
    from daemodel.comparing.bench_report import against_radau, against_radau_cells
    from daemodel.comparing.suites import BenchProblem

    def run(problem, method, status, scd, error_class=None):
        return {"problem": problem, "method": method, "status": status, "scd": scd, "setup_time": 0.5,
                "solve_time": 0.01, "error_class": error_class, "settings": "s"}  # fmt: skip

    pinn = [run(p, "pinn", "success", 7.0) for p in "abc"]
    radau = [
        run("a", "radau", "failed", None, "StepLimitError"), run("a", "radau", "flagged", 8.0),
        run("a", "radau", "flagged", 9.0), run("b", "radau", "success", 6.5),
    ]  # fmt: skip
    problems = [BenchProblem(name, name, "testset", (0.0, 1.0)) for name in "abc"]
    alone = against_radau(pinn, ["pinn"], problems)
    assert [r["none"] for r in alone] == ["radau is not among the methods run"] * 3
    rows = against_radau(pinn + radau, ["radau", "pinn"], problems)
    assert [r["none"] for r in rows] == [
        "no radau run succeeded (1 StepLimitError, 2 flagged)",
        "no successful radau run reaches 7.0 digits",
        "no radau run succeeded (none ran)",
    ]
    # a plugged-in method's clock reported as NaN: "not finite" in the cells, None in results.json (which
    # bench_tables.py prints from: it raised TypeError on the None)
    nan = [run("b", "pinn", "success", 7.0) | {"setup_time": math.nan}, run("b", "radau", "success", 7.5)]
    (row,) = against_radau(nan, ["radau", "pinn"], problems[1:2])
    stored = {k: None if isinstance(v, float) and not math.isfinite(v) else v for k, v in row.items()}
    for shown in (row, stored):
        assert against_radau_cells(shown)[2:] == [
            "7.0 scd at s: not finite setup + solve, 10 ms solve", "7.5 scd in 10 ms", "not finite (1x solve)",
        ]  # fmt: skip

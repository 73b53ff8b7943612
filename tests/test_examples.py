"""Examples run, print what the issue asks for, and declare the same systems as the problem library."""

import importlib.util
import re
import subprocess
import sys
from pathlib import Path

import pytest
import sympy as sp

from daemodel.problems import PROBLEMS

ROOT = Path(__file__).resolve().parents[1]


def load(name):
    spec = importlib.util.spec_from_file_location(f"example_{name}", ROOT / "examples" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def run(name, *args):
    return subprocess.run(
        [sys.executable, str(ROOT / "examples" / f"{name}.py"), *args], capture_output=True, text=True, check=True
    ).stdout


def test_hessenberg_example_prints_index_and_z0():
    out = run("hessenberg")
    assert "index = 2, z0 = {'y5': 1.0}" in out
    assert "y5(t0) = 1   (consistent: from hidden constraint invariant' = 0)" in out


def test_pendulum_example_reduces_position_form_and_solves_three_ways(tmp_path):
    out = run("pendulum", "--quick", "--plot", str(tmp_path / "pendulum.png"))
    assert "Model 'pendulum': index-2 DAE" in out and "Model 'pendulum-index3': index-3 DAE" in out
    assert "position form: index 3; reduced to index 2: 0 = 2*y1*y3 + 2*y2*y4" in out
    for method in ("radau", "casadi-collocation", "casadi-idas"):
        assert f"\n{method} " in out
    assert "radau vs casadi-collocation (same s, h): max difference" in out
    assert (tmp_path / "pendulum.png").stat().st_size > 10_000


def test_switches_example_keeps_the_order_across_the_switch():
    out = run("switches", "--quick")
    assert "Piecewise in switch: t - 0.3 crosses 0 (time breakpoint)" in out
    assert "breakpoints [0.3]: i jumps from 0 to 3" in out
    for method in ("radau", "casadi-idas", "casadi-collocation", "reference"):
        assert f"  {method} " in out


def test_events_example_locates_the_impacts_and_keeps_the_constraints():
    out = run("events", "--quick")
    assert "wall: x + 0.5 crosses 0 (falling); then u = -0.8*u, v = -0.8*v" in out
    assert "impacts at t = [0.71300838" in out and "terminal: the solve ends at t = 0.713008381" in out
    assert "a batch of 10: first impacts from t = " in out


def test_heat_2d_example_matches_the_decaying_eigenmode_to_second_order(capsys):
    """The 2-D heat equation declared as arrays (10 x 10 states, 2 x 10 algebraic boundary values):
    max error against exp(-2 pi^2 t) cos(pi x) sin(pi y) between 0.1 h^2 and 0.5 h^2 (measured 0.13 h^2),
    the arrays' shapes (asserted inside main)."""
    h = 1.0 / 11
    error = load("heat_2d").main(["--quick"])
    assert 0.1 * h**2 < error < 0.5 * h**2, error
    out = capsys.readouterr().out
    assert "heat_2d N = 10: 100 states, 20 algebraic" in out and "(radau, success," in out


@pytest.mark.parametrize(
    ("example", "kwargs", "problem"),
    [
        ("hessenberg", {}, "hessenberg"),
        ("pendulum", {}, "pendulum"),
        ("pendulum", {"position_level": True}, "pendulum-index3"),
    ],
)
def test_examples_match_problem_library(example, kwargs, problem):
    mine = load(example).build_model(**kwargs).compile()
    ref = PROBLEMS[problem].model().compile()
    assert mine.state_names == ref.state_names and mine.algebraic_names == ref.algebraic_names
    assert all(sp.simplify(a - b) == 0 for a, b in zip(mine.rhs + mine.g, ref.rhs + ref.g, strict=True))
    assert mine.y0.tolist() == ref.y0.tolist() and mine.z0.tolist() == ref.z0.tolist()


def test_fit_example_checks_sensitivities_adjoint_and_the_fit(tmp_path):
    out = run("fit", "--plot", str(tmp_path / "fit.png"))
    gap = float(out.split("largest relative gap to central differences: ")[1].split()[0])
    assert gap < 1e-6
    assert "Fit(radau, success" in out and "standard errors from the truth" in out
    assert "m and c together: fit: the data do not determine ['m', 'c']" in out
    assert (tmp_path / "fit.png").stat().st_size > 10_000


def test_every_example_runs_in_ci():
    """Each script in examples/ runs in CI: .ci/run names it, or a test runs it (``run``/``load`` here, an
    import in tests/test_plugin_method.py); .ci/run leaves to the tests those they run with its arguments."""
    ci = (ROOT / ".ci" / "run").read_text()
    tests = Path(__file__).read_text() + (ROOT / "tests" / "test_plugin_method.py").read_text()
    for path in sorted((ROOT / "examples").rglob("*.py")):
        name = path.relative_to(ROOT).as_posix()
        by_a_test = re.search(rf'\b(run|load)\("{path.stem}"', tests) or f"import {path.stem}\n" in tests
        assert name in ci or by_a_test, f"{name} runs neither in .ci/run nor in a test"

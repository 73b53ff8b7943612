"""Solution (daemodel/solution.py): what save/load keep (events, breakpoints, the dense output, stats
as arrays), what load refuses (another model's events or parameter values, each named), at() between
outputs across an event without a dense output, and the summary that printing stats gives.

The bouncing ball: h' = v, v' = -g, h(0) = 1, v(0) = 0, event "floor" when h falls through 0 with
v = -e v; its impacts are known in closed form: the first at sqrt(2/g), then each flight lasts
2 v_k / g with v_k = e^k sqrt(2 g)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import sympy as sp

import daemodel as dm
from daemodel import errors as E
from daemodel.errors import SolutionFileError
from daemodel.problems import DECAY
from daemodel.stats import Stats

# radau's default on casadi's virtual machine, but in the tests marked machine_code (tests/conftest.py)
pytestmark = pytest.mark.virtual_machine

G = 9.81
SPAN = (0.0, 2.5)  # four impacts, well before the Zeno point near 4.06
T_EVAL = np.linspace(0.0, 2.5, 6)  # sparse: the first impact (0.4515) lies inside [0, 0.5]


def ball(reset: str | None = "-0.8*v", g: float = G):
    m = dm.Model("ball")
    h, v = m.states("h v")
    gravity = m.parameter("g", g)
    m.ode(h, v)
    m.ode(v, -gravity)
    m.initial(h=1.0, v=0.0)
    if reset is not None:
        m.event("floor", when=h, direction=-1, reset={"v": reset})
    return m


def impacts(e: float = 0.8, g: float = G, end: float = SPAN[1]) -> np.ndarray:
    """The ball's impact times up to ``end``, exactly."""
    times, t, v = [], math.sqrt(2 / g), math.sqrt(2 * g)
    while t < end:
        times.append(t)
        v *= e
        t += 2 * v / g
    return np.array(times)


def exact(times, e: float = 0.8, g: float = G) -> dict:
    """h and v of the ball at ``times`` (inside SPAN)."""
    times = np.asarray(times, dtype=float)
    hits = impacts(e, g)
    k = np.searchsorted(hits, times, side="right")  # impacts at or before each time
    start = np.where(k > 0, hits[np.maximum(k - 1, 0)], 0.0)
    v0 = np.where(k > 0, e**k * math.sqrt(2 * g), 0.0)
    h0 = np.where(k > 0, 0.0, 1.0)
    s = times - start
    return {"h": h0 + v0 * s - 0.5 * g * s**2, "v": v0 - g * s}


QUERIES = np.array([0.05, 0.3, 0.44, 0.46, 0.6, 0.95, 1.2, 1.6, 1.8, 2.3, 2.49])


@pytest.mark.parametrize("method", ["radau", "reference", "casadi-idas"])
def test_a_loaded_solution_keeps_its_events_and_never_interpolates_across_one(method, tmp_path):
    """Saved and loaded, the events are the solve's (the impact times to 1e-8 of the closed form) and
    at() gives the in-memory values: radau's collocation polynomials are stored (the same values bit
    for bit); the reference's and IDAS's restarts are not, and the loaded at() interpolates within the
    pieces between impacts (free flight is a parabola: exact).  Before: no events came back, and at()
    interpolated across the first impact (h(0.3) = 0.235 instead of 0.559)."""
    sol = dm.solve(ball(), SPAN, method=method, t_eval=T_EVAL, rtol=1e-10, atol=1e-10)
    loaded = dm.Solution.load(sol.save(tmp_path / "ball.npz"), ball())
    assert list(loaded.events) == ["floor"]
    np.testing.assert_allclose(loaded.events["floor"]["t"][0], impacts(), rtol=0, atol=1e-8)
    for key in ("t", "moved"):
        np.testing.assert_array_equal(loaded.events["floor"][key], sol.events["floor"][key])
    for side in ("before", "after"):
        for name in ("h", "v"):
            np.testing.assert_array_equal(loaded.events["floor"][side][name], sol.events["floor"][side][name])
    here, there = sol.at(QUERIES), loaded.at(QUERIES)
    truth = exact(QUERIES)
    for name in ("h", "v"):
        np.testing.assert_allclose(there[name], truth[name], rtol=0, atol=1e-6)
        np.testing.assert_allclose(there[name], here[name], rtol=0, atol=1e-6)
    assert abs(there["h"][1] - 0.55855) < 1e-6
    if method == "radau":
        assert loaded.dense.description == sol.dense.description
        for name in ("h", "v"):
            np.testing.assert_array_equal(there[name], here[name])
    else:
        assert loaded.dense is None


def test_a_loaded_solution_keeps_its_breakpoints_and_the_batch_dense_output(tmp_path):
    """A time switch in a batch (its time a parameter): the breakpoints, NaN-padded, and the dense
    output of the groups of samples come back; at() is the in-memory one."""
    m = dm.Model("ramp")
    m.states("x")
    m.parameter("s", 0.5)
    m.ode("x", "Piecewise((1, t < s), (-1, True))")
    m.initial(x=0.0)
    sol = dm.solve(m, (0.0, 1.0), parameters={"s": [0.3, 0.7, 2.0]}, t_eval=np.linspace(0, 1, 3))
    loaded = dm.Solution.load(sol.save(tmp_path / "ramp.npz"), m)
    np.testing.assert_array_equal(loaded.breakpoints["t"], sol.breakpoints["t"])
    q = np.array([0.2, 0.3, 0.4, 0.69, 0.71, 0.95])
    np.testing.assert_array_equal(loaded.at(q)["x"], sol.at(q)["x"])
    switch = np.array([0.3, 0.7, 2.0])[:, None]
    np.testing.assert_allclose(loaded.at(q)["x"], np.where(q < switch, q, 2 * switch - q), atol=1e-9)


@pytest.mark.parametrize(
    ("other", "message"),
    [
        (
            ball("-0.5*v"),
            r"holds a solution of model 'ball' whose events differ from those of 'ball' \(its events \['floor: h "
            r"crosses 0 \(falling\); then v = -0\.8\*v'\], the model's \['floor: h crosses 0 \(falling\); then "
            r"v = -0\.5\*v'\]\): load it with the model that was solved",
        ),
        (ball(None), r"whose events differ from those of 'ball' \(its events \[.*\], the model's \[\]\)"),
        (ball(g=9.0), r"whose parameter values differ from those of 'ball' \(its g = 9\.81, the model's 9\.0\)"),
    ],
)
def test_load_refuses_a_model_with_other_events_or_parameter_values(other, message, tmp_path):
    """Before: the fingerprint held the equations and names only, and each of these loaded."""
    path = dm.solve(ball(), SPAN, t_eval=T_EVAL).save(tmp_path / "ball.npz")
    with pytest.raises(SolutionFileError, match=message):
        dm.Solution.load(path, other)


def test_stats_round_trip_with_their_arrays_and_non_finite_values(tmp_path):
    """IDAS reports NaN counters: the file was written with NaN in its JSON and could not be read back
    (SolutionFileError 'NaN is not a JSON number').  Stats now round-trip, arrays as arrays."""
    sol = dm.solve(ball(), SPAN, method="casadi-idas", t_eval=T_EVAL)
    assert any(isinstance(v, float) and math.isnan(v) for v in sol.stats.values())
    loaded = dm.Solution.load(sol.save(tmp_path / "idas.npz"), ball())
    assert set(loaded.stats) == set(sol.stats)
    for key, value in sol.stats.items():
        if isinstance(value, float) and math.isnan(value):
            assert math.isnan(loaded.stats[key])
        else:
            np.testing.assert_array_equal(np.asarray(loaded.stats[key]), np.asarray(value))


def test_a_solution_file_of_the_older_format_is_refused_by_name(tmp_path):
    import json
    import zipfile

    path = dm.solve(ball(), SPAN, t_eval=T_EVAL).save(tmp_path / "ball.npz")
    with zipfile.ZipFile(path) as archive:
        meta = json.loads(str(np.lib.format.read_array(archive.open("meta.npy"))))
    meta["format"] = "daemodel-solution/1"
    old = tmp_path / "old.npz"
    np.savez(old, t=np.zeros(2), values=np.zeros((1, 2, 2)), parameters=np.zeros((1, 1)), meta=json.dumps(meta))
    with pytest.raises(SolutionFileError, match=r"format 'daemodel-solution/1', which kept no events.*save it again"):
        dm.Solution.load(old, ball())


def test_printed_stats_are_a_summary():
    """Per-sample arrays print as their shape and range (a 1000-sample PINN's certificate printed as
    megabytes of nested lists), one entry a line, at most 40 lines; the dict itself is a plain dict."""
    sol = dm.solve(ball(None), SPAN, parameters={"g": np.linspace(9, 10, 1000)}, t_eval=T_EVAL)
    sol.stats["per_sample"] = np.arange(1000.0)
    sol.stats["segments"] = np.zeros((1000, 20))
    for k in range(60):
        sol.stats[f"extra_{k}"] = k
    text = repr(sol.stats)
    assert "'per_sample': <array (1000,) float64 from 0 to 999, median 499.5>" in text
    assert "'segments': <array (1000, 20) float64 from 0 to 0, median 0>" in text
    lines = text.splitlines()
    assert (
        len(lines) == 36 and lines[-1] == f" ... ({len(sol.stats) - 35} more entries)}}" and isinstance(sol.stats, dict)
    )
    assert str(sol.stats) == text and len(repr(sol).splitlines()) == 1


def test_stats_hold_arrays_not_lists_of_lists():
    """Per-step and per-segment figures were Python lists (of lists, per sample); they are arrays."""
    fixed = dm.solve(DECAY.model(), (0.0, 1.0), h=0.1, stages=3)
    estimates = fixed.stats["local_error_estimates"]
    assert isinstance(estimates, np.ndarray) and estimates.shape == (10,) and estimates.dtype == float
    stats = Stats(
        {
            "per_segment": [[1, 2], [3, 4], [5, 6]],
            "ragged": [np.array([1.0]), np.array([2.0, 3.0])],
            "nested": {"certified": [True, False], "error": [[0.5], [0.25]]},
            "names": ["network", "newton"],
            "empty": [],
            "flag": True,
        }
    )
    np.testing.assert_array_equal(stats["per_segment"], [[1, 2], [3, 4], [5, 6]])
    np.testing.assert_array_equal(stats["ragged"], [[1.0, np.nan], [2.0, 3.0]])
    assert stats["nested"]["certified"] == [True, False]  # (booleans are verdicts, kept as they are)
    np.testing.assert_array_equal(stats["nested"]["error"], [[0.5], [0.25]])
    assert stats["names"] == ["network", "newton"] and stats["empty"] == [] and stats["flag"] is True
    assert repr(stats) == (
        "{'per_segment': [[1, 2], [3, 4], [5, 6]],\n 'ragged': [[1.0, nan], [2.0, 3.0]],\n"
        " 'nested': {'certified': [True, False], 'error': [[0.5], [0.25]]},\n 'names': ['network', 'newton'],\n"
        " 'empty': [],\n 'flag': True}"
    )


def test_extended_stats_keep_their_arrays_and_convert_the_new_entries():
    """``Stats.extended`` (the solve's clock adds two entries to every solution's stats): a new Stats with
    the entries added, converted as the constructor converts, the original unchanged."""
    stats = Stats({"per_step": [1.0, 2.0], "steps": 2})
    more = stats.extended(seconds=0.5, per_segment=[[1, 2], [3, 4]])
    assert isinstance(more, Stats) and list(more) == ["per_step", "steps", "seconds", "per_segment"]
    assert more["per_step"] is stats["per_step"] and more["steps"] == 2 and more["seconds"] == 0.5
    np.testing.assert_array_equal(more["per_segment"], [[1, 2], [3, 4]])
    assert isinstance(more["per_segment"], np.ndarray) and "seconds" not in stats
    sol = dm.solve(DECAY.model(), (0.0, 1.0), rtol=1e-6, atol=1e-6)
    assert isinstance(sol.stats, Stats) and sol.stats["completion_seconds"] >= 0.0


def test_stats_as_plain_values_go_through_strict_json():
    """json.dumps(sol.stats) refuses numpy arrays; ``to_dict()`` is plain (NaN and inf as None)."""
    import json

    fixed = dm.solve(DECAY.model(), (0.0, 1.0), h=0.1, stages=3)
    with pytest.raises(TypeError):
        json.dumps(fixed.stats)
    back = json.loads(json.dumps(fixed.stats.to_dict(), allow_nan=False))
    assert back["local_error_estimates"] == fixed.stats["local_error_estimates"].tolist()
    assert back["steps"] == fixed.stats["steps"] == 10
    stats = Stats({"ragged": [np.array([1.0]), np.array([2.0, np.inf])], "n": np.int64(3), "inner": {"x": (np.nan,)}})
    assert json.loads(json.dumps(stats.to_dict(), allow_nan=False)) == {
        "ragged": [[1.0, None], [2.0, None]],
        "n": 3,
        "inner": {"x": [None]},
    }


def test_printed_stats_count_a_boolean_arrays_true_entries_and_show_numpy_scalars_as_numbers():
    stats = Stats({"certified": np.arange(1000) % 4 != 0, "steps": np.int64(3), "h": np.float64(0.5)})
    assert repr(stats) == "{'certified': <array (1000,) bool, 750 true>, 'steps': 3, 'h': 0.5}"


@pytest.fixture(scope="module")
def decay():
    return dm.solve(DECAY.model(), (0.0, 1.0), h=0.1, stages=3)


def test_at_refuses_times_that_are_not_numbers(decay):
    """Before: "0.5" was parsed as 0.5 and True taken as t = 1."""
    with pytest.raises(E.InvalidValueError, match=r"at\(\): times must be real numbers; got the string '0.5'"):
        decay.at("0.5")
    with pytest.raises(E.InvalidValueError, match=r"at\(\): times must be real numbers; got booleans, the first True"):
        decay.at(True)
    with pytest.raises(E.InvalidValueError, match=r"got complex numbers \(the imaginary part would be dropped\)"):
        decay.at([0.5 + 0.1j])
    with pytest.raises(E.InvalidValueError, match=r"at\(\): times\[1\] must be a real number; got None"):
        decay.at([0.5, None])
    # (found by review: the message named '0.5', which numpy had made a string beside the culprit)
    with pytest.raises(E.InvalidValueError, match=r"got strings, the first '0\.6'"):
        decay.at([0.5, "0.6"])
    with pytest.raises(E.InvalidValueError, match=r"at\(\): times must be finite; got nan"):
        decay.at(float("nan"))
    with pytest.MonkeyPatch.context() as patch:  # (an allowance of 16 MiB: 10^6 times need about 90 MiB)
        patch.setenv("DAEMODEL_MEMORY_LIMIT", "16M")
        with pytest.raises(E.ResourceLimitError, match=r"at\(\): 1000000 times of 1 sample\(s\) and 2 unknowns"):
            decay.at(np.full(10**6, 0.5))
    # numbers of every kind are times
    exact = decay.at(0.5)["y"]
    for t in (np.float32(0.5), sp.Rational(1, 2), [sp.S.Half], np.array([0.5])):
        assert np.atleast_1d(decay.at(t)["y"]) == pytest.approx(np.atleast_1d(exact), rel=1e-12)


def test_gradient_data_must_be_real_measurements():
    sol = dm.solve(DECAY.model(), (0.0, 1.0), h=0.1, stages=3, sensitivities=["k"])
    good = sol["y"] + 0.01
    with pytest.raises(E.DataError, match=r"gradient: the data for 'y' must be real numbers; got strings"):
        sol.gradient({"y": [str(v) for v in good]}, ["k"])
    with pytest.raises(E.DataError, match=r"the data for 'y' must be real numbers; got complex numbers"):
        sol.gradient({"y": good + 1e-3j}, ["k"])
    with pytest.raises(E.DataError, match=r"the data for 'y' are NaN everywhere: a series with no measurement"):
        sol.gradient({"y": np.full_like(good, np.nan)}, ["k"])  # (before: 0.0)
    assert sol.gradient({"y": good}, ["k"])["k"] != 0.0


def _tampered(path, edit):
    """The solution file at ``path`` with ``edit(arrays, meta)`` applied, written beside it."""
    import json

    arrays = {k: v.copy() for k, v in np.load(path).items()}
    meta = json.loads(str(arrays["meta"]))
    edit(arrays, meta)
    arrays["meta"] = np.array(json.dumps(meta))
    out = path.with_name("tampered.npz")
    np.savez(out, **arrays)
    return out


def _event_times(arrays, meta):
    return arrays[meta["events"]["floor"]["t"]["__array__"]]


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda a, m: m.update(events={}), r"field 'events' lacks the model's event\(s\) \['floor'\]"),
        (lambda a, m: m["events"].update(ghost=m["events"]["floor"]), r"field 'events' holds \['ghost'\], which"),
        (lambda a, m: _event_times(a, m).__setitem__((0, 0), 99.0), r"'events.floor.t' is not a sequence of times"),
        (lambda a, m: _event_times(a, m).__setitem__(0, _event_times(a, m)[0, ::-1].copy()), r"in order"),
        (lambda a, m: a.__setitem__(m["dense"]["edges"]["__array__"], a[m["dense"]["edges"]["__array__"]] * 0.1),
         r"field 'dense' does not give the stored values at the output times"),
    ],
)  # fmt: skip
def test_load_refuses_events_and_dense_outputs_that_are_not_the_solutions(edit, message, tmp_path):
    # (found by review: each loaded with status "success"; at() then extrapolated, h = -19 for 0.148)
    path = dm.solve(ball(), SPAN, rtol=1e-8, atol=1e-8).save(tmp_path / "ball.npz")
    with pytest.raises(SolutionFileError, match=message):
        dm.Solution.load(_tampered(path, edit), ball())


def test_load_takes_a_model_whose_values_are_those_the_solve_used(tmp_path):
    # (found by review: a solve at g = 5 of a model declared with 9.81 was refused with the model declared at 5)
    path = dm.solve(ball(), SPAN, rtol=1e-8, atol=1e-8, parameters={"g": 5.0}).save(tmp_path / "ball.npz")
    loaded = dm.Solution.load(path, ball(g=5.0))
    assert loaded.parameters.tolist() == [[5.0]]
    with pytest.raises(SolutionFileError, match=r"its g = 9\.81, the model's 7\.0"):
        dm.Solution.load(path, ball(g=7.0))


def test_a_solution_is_indexed_by_a_variables_name_or_its_symbol(decay):
    """sol[x] with the symbol m.states returned said 'the solution has no variable x; it has ['x', ...]'."""
    m = dm.Model("decay")
    (x,) = m.states("x")
    m.ode(x, -x)
    m.initial(x=1.0)
    sol = dm.solve(m, (0.0, 1.0), h=0.1)
    np.testing.assert_array_equal(sol[x], sol["x"])
    with pytest.raises(E.UnknownSymbolError, match=r"no variable 'y'; it has \['x'\]"):
        sol["y"]
    with pytest.raises(E.UnknownSymbolError, match=r"indexed by a variable's name or symbol .*; got int"):
        sol[0]


@pytest.mark.parametrize("method", ["radau", "casadi-idas"])
def test_a_solution_of_a_model_that_switches_on_a_state_loads_with_its_model(method, tmp_path):
    """y' = |x - 1| with x = t: the switch on x is located as an event of the solve ("Abs in y'"), which
    the model as declared does not list.  Before: load refused the file with the model that was solved
    ("whose events differ ... the model's []")."""
    m = dm.Model("kink")
    m.states("x y")
    m.ode("x", "1")
    m.ode("y", "Abs(x - 1)")
    m.initial(x=0.0, y=0.0)
    sol = dm.solve(m, (0.0, 2.0), method=method, rtol=1e-10, atol=1e-10)
    loaded = dm.Solution.load(sol.save(tmp_path / "kink.npz"), m)
    assert list(loaded.events) == ["Abs in y'"]
    np.testing.assert_array_equal(loaded.events["Abs in y'"]["t"], sol.events["Abs in y'"]["t"])
    assert abs(loaded.events["Abs in y'"]["t"][0, 0] - 1.0) < 1e-9
    np.testing.assert_array_equal(loaded["y"], sol["y"])
    assert abs(loaded["y"][-1] - 1.0) < 1e-8


def test_a_backends_values_are_views_of_one_block_made_when_read():
    """Columns (Solution.values as backends make it): each name's values a read-only view of the block's row,
    made when read, not held; names added later (aliases) hold their own; its mistakes named."""
    from daemodel.solution import Columns

    block = np.arange(12.0).reshape(3, 1, 4)
    columns = Columns(("a", "b", "c"), block)
    assert columns._index is None  # (nothing made by name until a name is read)
    assert list(columns) == ["a", "b", "c"] and len(columns) == 3 and "b" in columns and "d" not in columns
    np.testing.assert_array_equal(columns["b"], [[4.0, 5.0, 6.0, 7.0]])
    assert np.shares_memory(columns["c"], block)
    columns["d"] = np.zeros((1, 4))
    assert list(columns) == ["a", "b", "c", "d"] and len(columns) == 4 and columns.arrays()[0] is block
    assert dict(columns.items())["d"].tolist() == [[0.0] * 4]
    with pytest.raises(KeyError, match="'e'"):
        columns["e"]
    with pytest.raises(ValueError, match=r"'a' has values already"):
        columns["a"] = np.zeros((1, 4))
    with pytest.raises(ValueError, match=r"2 names for 3 variables' values"):
        Columns(("a", "b"), block)


def test_a_solutions_values_by_name_alias_and_array_from_the_backends_block():
    """A radau solution's values: sol[name], the aliases' (computed after the solve), sol.values as a mapping."""
    m = dm.Model("aliased")
    x, y = m.states("x y")
    (w,) = m.algebraics("w")
    m.ode(x, -x)
    m.ode(y, -2 * y)
    m.constraint(w - x, "alias")
    m.initial(x=1.0, y=1.0)
    sol = dm.solve(m, (0.0, 1.0), method="radau", rtol=1e-8, atol=1e-10, t_eval=[0.0, 0.5, 1.0])
    np.testing.assert_allclose(sol["x"], np.exp(-sol.t), rtol=1e-6)
    np.testing.assert_allclose(sol["y"], np.exp(-2 * sol.t), rtol=1e-6)
    np.testing.assert_allclose(sol["w"], sol["x"], rtol=1e-12)
    assert set(sol.values) == {"x", "y", "w"} and not sol["x"].flags.writeable and not sol["w"].flags.writeable

"""dm.ensemble: a large batch in chunks, in this process or on a local Ray cluster, against one
batched radau call, with failing samples recorded by index."""

from __future__ import annotations

import sys

import numpy as np
import pytest

import daemodel as dm
from daemodel.errors import ConvergenceError, InvalidOptionError, SolutionFileError
from daemodel.problems import PENDULUM


@pytest.fixture(scope="module")
def pendulum():
    return PENDULUM.model().compile()


@pytest.fixture(scope="module")
def states(pendulum):
    rng = np.random.default_rng(0)
    B = 1500
    return pendulum.consistent(y0={"y1": rng.uniform(0.99, 1.01, B), "y4": rng.uniform(0.99, 1.01, B)})


def same(a, b, names) -> float:
    return max(float(np.abs(a[name] - b[name]).max()) for name in names)


def test_local_ensemble_equals_one_batched_call(pendulum, states):
    one = dm.solve(pendulum, (0.0, 1.0), h=0.05, y0=states)
    ensemble = dm.ensemble(pendulum, (0.0, 1.0), y0=states, h=0.05, chunk=400)
    names = (*pendulum.state_names, *pendulum.algebraic_names)
    assert same(one, ensemble, names) < 1e-13
    assert ensemble["y5"].shape == (1500, 21) and ensemble.batched and ensemble.status == "success"
    np.testing.assert_array_equal(ensemble.stats["samples"], np.arange(1500))
    assert [c["size"] for c in ensemble.stats["chunks"]] == [400, 400, 400, 300]
    assert ensemble.stats["failures"] == [] and ensemble.stats["executor"] == "local"


def test_a_failing_sample_is_recorded_and_left_out(blowup):
    """k = 5 and 20 blow up inside [0, 1]: one batched call fails as a whole; the ensemble
    splits the failing chunk down to them, records them by index and returns the others."""
    k = np.array([0.1, 0.5, 5.0, 0.2, 20.0, 0.3, 0.4])
    with pytest.raises(ConvergenceError, match="Newton failed"):
        dm.solve(blowup, (0.0, 1.0), h=0.05, parameters={"k": k})
    ensemble = dm.ensemble(blowup, (0.0, 1.0), h=0.05, parameters={"k": k}, chunk=4)
    assert [(f.index, f.error) for f in ensemble.stats["failures"]] == [
        (2, "ConvergenceError"),
        (4, "ConvergenceError"),
    ]
    assert "Newton failed" in ensemble.stats["failures"][0].message
    kept = np.array([0, 1, 3, 5, 6])
    np.testing.assert_array_equal(ensemble.stats["samples"], kept)
    np.testing.assert_allclose(ensemble.parameters[:, 0], k[kept])
    np.testing.assert_allclose(ensemble["x"][:, -1], 1 / (1 - k[kept]), rtol=1e-6)  # the exact solution
    assert np.isfinite(ensemble["x"]).all()
    assert ensemble.status.endswith(
        "2 of 7 samples failed and are left out (stats['failures'], first: sample 2, ConvergenceError)"
    )


def test_an_ensemble_whose_every_sample_fails_raises(blowup):
    with pytest.raises(ConvergenceError, match=r"ensemble: every one of the 2 samples failed; sample 0: Convergence"):
        dm.ensemble(blowup, (0.0, 1.0), h=0.05, parameters={"k": [5.0, 20.0]})


def test_ray_ensemble_equals_the_local_one(ray_cluster, pendulum, states, blowup, tmp_path):
    """Four tasks on a local Ray cluster of 2 CPUs: the same values as one batched call, each
    task's peak memory recorded; failures travel back from the workers by index."""
    one = dm.solve(pendulum, (0.0, 1.0), h=0.05, y0=states)
    ensemble = dm.ensemble(pendulum, (0.0, 1.0), y0=states, h=0.05, chunk=400, executor="ray")
    assert same(one, ensemble, (*pendulum.state_names, *pendulum.algebraic_names)) < 1e-13
    np.testing.assert_array_equal(ensemble.stats["samples"], np.arange(1500))
    assert len(ensemble.stats["peak_memory_mb"]) == 4 and min(ensemble.stats["peak_memory_mb"]) > 0
    k = np.array([0.1, 5.0, 0.2, 0.3])
    failing = dm.ensemble(blowup, (0.0, 1.0), h=0.05, parameters={"k": k}, chunk=2, executor="ray")
    assert [f.index for f in failing.stats["failures"]] == [1]
    np.testing.assert_array_equal(failing.stats["samples"], [0, 2, 3])
    files = dm.ensemble(blowup, (0.0, 1.0), h=0.05, parameters={"k": k}, chunk=2, executor="ray", write_to=tmp_path)
    assert [f.index for f in files.failures] == [1] and files.executor == "ray"
    np.testing.assert_array_equal(files.solution()["x"], failing["x"])
    again = dm.ensemble(pendulum, (0.0, 0.1), h=0.05, executor="ray", workers=2)  # the running cluster's CPUs
    assert again.status == "success"
    with pytest.raises(InvalidOptionError, match=r"Ray is already running in this process with 2 CPUs, not workers=3"):
        dm.ensemble(pendulum, (0.0, 0.1), h=0.05, executor="ray", workers=3)
    with pytest.raises(InvalidOptionError, match=r"Ray is already running in this process: leave out address"):
        dm.ensemble(pendulum, (0.0, 0.1), h=0.05, executor="ray", address="auto")


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"executor": "dask"}, "executor must be one of local, ray; got 'dask'"),
        ({"chunk": 0}, r"chunk must be a positive integer \(samples per task\); got 0"),
        ({"chunk": 2.5}, r"chunk must be a positive integer \(samples per task\); got 2.5"),
        ({"workers": 2}, "workers and address are Ray's: pass executor='ray' with them"),
        ({"executor": "ray", "workers": 0}, "workers must be a positive integer; got 0"),
        (
            {"executor": "ray", "address": 6379},
            "address must be a string such as 'auto' or 'ray://host:10001'; got 6379",
        ),
        (
            {"executor": "ray", "device": "cuda"},
            r"executor='ray' runs each task on one of the workers' CPUs \(no GPU requested\); device = 'cuda' runs "
            "here",
        ),
        (
            {"y0": {"y4": [1.0, 1.0]}, "parameters": {"lam": [1.0, 1.0, 1.0]}},
            "y0, z0 and parameters make batches of different sizes: y0: 2, parameters: 3",
        ),
    ],
)
def test_ensemble_errors(pendulum, options, message):
    with pytest.raises(InvalidOptionError, match=message):
        dm.ensemble(pendulum, (0.0, 0.1), h=0.05, **options)


@pytest.mark.parametrize("executor", ["local", "ray"])
def test_the_old_spelling_engine_of_the_executor_is_refused_by_name(pendulum, executor):
    """engine='local' | 'ray' was the ensemble's executor: refused, with both spellings named,
    before any chunk runs (engine= names radau's casadi or torch engine)."""
    with pytest.raises(
        InvalidOptionError,
        match=rf"ensemble\(\): engine='{executor}' is now spelled executor='{executor}' \(engine= names radau's",
    ):
        dm.ensemble(pendulum, (0.0, 0.1), h=0.05, engine=executor)


def test_engine_is_the_methods_and_reaches_every_chunks_solve(pendulum, states):
    """engine='torch' or 'casadi' goes to radau in every chunk (the executor is executor=): each
    chunk gives what radau's solve with that engine gives, and what radau refuses, radau names."""
    names = (*pendulum.state_names, *pendulum.algebraic_names)
    few = {name: values[:6] for name, values in states.items()}
    one = dm.solve(pendulum, (0.0, 0.5), h=0.05, y0=few, engine="torch")
    chunks = dm.ensemble(pendulum, (0.0, 0.5), y0=few, h=0.05, chunk=4, engine="torch")
    assert same(one, chunks, names) < 1e-13 and chunks.stats["executor"] == "local"
    single = {name: values[:2] for name, values in states.items()}
    alone = dm.ensemble(pendulum, (0.0, 0.5), y0=single, h=0.05, chunk=1, engine="casadi")
    for i in range(2):
        own = dm.solve(pendulum, (0.0, 0.5), h=0.05, y0={k: v[i] for k, v in single.items()}, engine="casadi")
        assert max(float(np.abs(own[name] - alone[name][i]).max()) for name in names) == 0.0
    with pytest.raises(InvalidOptionError, match=r"engine='casadi' solves one trajectory; this batch has 2 samples"):
        dm.ensemble(pendulum, (0.0, 0.5), y0=single, h=0.05, chunk=2, engine="casadi")
    with pytest.raises(InvalidOptionError, match=r"engine must be one of 'auto', 'torch', 'casadi'; got 'dask'"):
        dm.ensemble(pendulum, (0.0, 0.1), h=0.05, engine="dask")


def test_ray_missing_says_how_to_install_it(pendulum, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray raises ImportError
    with pytest.raises(
        InvalidOptionError, match=r"executor='ray' needs Ray, which is not installed: pip install 'daemodel\[ray\]'"
    ):
        dm.ensemble(pendulum, (0.0, 0.1), h=0.05, executor="ray")


def test_a_model_with_an_eliminated_alias():
    """The compiler eliminates x = y1; every chunk's Solution, and the ensemble's, computes it."""
    m = dm.Model("aliased")
    y1, y2 = m.states("y1 y2")
    w, x = m.algebraics("w x")
    m.ode(y1, -w)
    m.ode(y2, x - y2)
    m.constraint(w - y1**2, name="law")
    m.constraint(x - y1, name="same")
    m.initial(y1=2.0, y2=0.5)
    ensemble = dm.ensemble(m, (0.0, 0.1), h=0.05, y0={"y1": [1.0, 2.0, 3.0]}, chunk=2)
    np.testing.assert_array_equal(ensemble["x"], ensemble["y1"])
    np.testing.assert_allclose(ensemble["y1"][:, -1], 1 / (1 / np.array([1.0, 2.0, 3.0]) + 0.1), rtol=1e-6)


# ---- chunks written to files --------------------------------------------------------------------
def test_chunks_written_to_files_read_back_a_chunk_at_a_time(pendulum, states, tmp_path):
    one = dm.solve(pendulum, (0.0, 1.0), h=0.05, y0=states)
    files = dm.ensemble(pendulum, (0.0, 1.0), y0=states, h=0.05, chunk=400, write_to=tmp_path / "sweep")
    assert sorted(p.name for p in (tmp_path / "sweep").iterdir()) == [
        "chunk-000000000000.npz",
        "chunk-000000000400.npz",
        "chunk-000000000800.npz",
        "chunk-000000001200.npz",
        "ensemble.json",
    ]
    assert repr(files).endswith("1500 of 1500 samples in 4 chunk files, status='success')")
    names = (*pendulum.state_names, *pendulum.algebraic_names)
    for part in files:
        rows = part.stats["samples"]
        assert len(rows) <= 400
        for name in names:
            np.testing.assert_array_equal(part[name], one[name][rows])
    picked = [1499, 3, 800, 3]
    again = dm.EnsembleFiles.load(tmp_path / "sweep", PENDULUM.model())  # another process would do this
    chosen = again.solution(picked)
    np.testing.assert_array_equal(chosen.stats["samples"], picked)
    for name in names:
        np.testing.assert_array_equal(chosen[name], one[name][picked])
    np.testing.assert_array_equal(chosen.parameters, one.parameters[picked])
    assert same(one, again.solution(), names) == 0.0


def test_failures_written_to_files(blowup, tmp_path):
    """Samples 2 and 3 (k = 5, 20) fail; their chunk has no file and asking for them names why."""
    k = np.array([0.1, 0.5, 5.0, 20.0, 0.3])
    files = dm.ensemble(blowup, (0.0, 1.0), h=0.05, parameters={"k": k}, chunk=2, write_to=tmp_path)
    assert [(f.index, f.error) for f in files.failures] == [(2, "ConvergenceError"), (3, "ConvergenceError")]
    assert len(files) == 2 and files.solved == 3 and files.total == 5
    assert files.status.endswith(
        "2 of 5 samples failed and are left out (stats['failures'], first: sample 2, ConvergenceError)"
    )
    np.testing.assert_array_equal(files.solution().stats["samples"], [0, 1, 4])
    np.testing.assert_allclose(files.solution([4, 0])["x"][:, -1], 1 / (1 - k[[4, 0]]), rtol=1e-6)
    with pytest.raises(
        InvalidOptionError, match=r"sample 3 failed \(ConvergenceError: .*Newton failed.*\) and has no values"
    ):
        files.solution([0, 3])
    with pytest.raises(InvalidOptionError, match="sample 5 is not in the ensemble of 5 samples"):
        files.solution([5])
    with pytest.raises(InvalidOptionError, match=r"samples must be a non-empty list of sample indices; got \[0.5\]"):
        files.solution([0.5])


def test_ensemble_file_errors(pendulum, blowup, tmp_path):
    files = dm.ensemble(blowup, (0.0, 0.1), h=0.05, parameters={"k": [0.1, 0.2]}, write_to=tmp_path / "a")
    with pytest.raises(
        InvalidOptionError, match=r"write_to .*a holds a finished ensemble of other samples, model, method or settings"
    ):
        dm.ensemble(blowup, (0.0, 0.1), h=0.05, write_to=tmp_path / "a")
    with pytest.raises(InvalidOptionError, match=r"write_to .* is an existing file, not a directory"):
        dm.ensemble(blowup, (0.0, 0.1), h=0.05, write_to=files.directory / "ensemble.json")
    with pytest.raises(
        SolutionFileError, match=r"holds an ensemble of model 'blowup' with other equations or names than 'pendulum'"
    ):
        dm.EnsembleFiles.load(files.directory, pendulum)
    with pytest.raises(SolutionFileError, match=r"no ensemble at .*: ensemble.json is missing"):
        dm.EnsembleFiles.load(tmp_path, blowup)
    (files.directory / "chunk-000000000000.npz").unlink()
    with pytest.raises(
        SolutionFileError, match=r"1 of the ensemble's 1 chunk files are missing \(first: chunk-000000000000.npz\)"
    ):
        dm.EnsembleFiles.load(files.directory, blowup)
    (files.directory / "ensemble.json").write_text('{"format": "something-else"}')
    with pytest.raises(
        SolutionFileError, match="is not a daemodel ensemble manifest \\(expected format 'daemodel-ensemble/3'\\)"
    ):
        dm.EnsembleFiles.load(files.directory, blowup)
    (files.directory / "ensemble.json").write_text('{"format": "daemodel-ensemble/3", "model": "blowup"}')
    with pytest.raises(
        SolutionFileError,
        match=r"ensemble.json is damaged: it lacks fingerprint, fingerprints, declared, run, total, chunk",
    ):
        dm.EnsembleFiles.load(files.directory, blowup)
    (files.directory / "ensemble.json").write_text("{not json")
    with pytest.raises(SolutionFileError, match=r"is not a daemodel ensemble manifest \(JSONDecodeError: "):
        dm.EnsembleFiles.load(files.directory, blowup)


@pytest.mark.parametrize(("method", "options"), [("casadi-idas", {}), ("casadi-collocation", {"h": 0.05})])
def test_casadi_methods_record_failing_samples_too(blowup, method, options):
    """casadi solves a chunk sample by sample; k = 5 blows up at t = 0.2 and is left out."""
    k = np.array([0.1, 0.5, 5.0, 0.2])
    ensemble = dm.ensemble(blowup, (0.0, 1.0), parameters={"k": k}, method=method, chunk=2, **options)
    assert [f.index for f in ensemble.stats["failures"]] == [2]
    np.testing.assert_allclose(ensemble["x"][:, -1], 1 / (1 - k[[0, 1, 3]]), rtol=1e-6)


def test_a_ray_worker_that_dies_is_named(ray_cluster):
    """A task whose worker process exits (as when it is killed for memory): WorkerError names
    the task, after Ray's own retries."""
    import os

    from daemodel.errors import WorkerError
    from daemodel.executors import run_tasks

    with pytest.raises(WorkerError, match=r"ensemble: the Ray worker running task 0 stopped before returning \(Worker"):
        run_tasks(os._exit, 1, [()], executor="ray", label="ensemble")


def test_a_killed_ray_workers_task_is_retried_with_nothing_lost(ray_cluster, tmp_path):
    """The first task to run kills its worker; Ray retries it on a new one, and every result
    comes back, in order."""
    from daemodel.executors import run_tasks

    def die_once(marker, value):  # defined here: Ray ships it by value (workers cannot import tests)
        import os
        from pathlib import Path

        if not Path(marker).exists():
            Path(marker).write_text("died once")
            os._exit(1)  # as the out-of-memory killer would end the worker
        return value

    marker = str(tmp_path / "died")
    assert run_tasks(die_once, marker, [(0,), (10,), (20,)], executor="ray", label="t") == [0, 10, 20]
    assert (tmp_path / "died").read_text() == "died once"


def test_a_ray_worker_fetches_the_shared_object_once_per_call(ray_cluster):
    """Tasks of one call on the same worker process share one copy of the shared object (and so
    the code it has generated): each task appends to it and sees the earlier tasks' entries."""
    import os

    from daemodel.executors import run_tasks

    def held(shared, i):
        shared["seen"].append(i)
        return os.getpid(), list(shared["seen"])

    first = run_tasks(held, {"seen": []}, [(i,) for i in range(8)], executor="ray", label="test")
    by_worker = {}
    for pid, seen in first:
        by_worker.setdefault(pid, []).append(seen)
    assert max(len(seen) for _, seen in first) >= 2  # 8 tasks on 2 CPUs: some worker ran several
    for runs in by_worker.values():
        assert sorted(len(seen) for seen in runs) == list(range(1, len(runs) + 1))
    second = run_tasks(held, {"seen": []}, [(i,) for i in range(2)], executor="ray", label="test")
    assert all(len(seen) <= 2 for _, seen in second)  # a new call ships a fresh copy


def test_chunks_that_end_with_different_statuses_are_all_reported():
    """An under-trained PINN's flag names its worst distance, which differs from chunk to chunk."""
    from daemodel.problems import HESSENBERG

    c = HESSENBERG.model().compile()
    config = dm.PINNConfig(tol=None, iterations=1)
    y0 = c.consistent(y0={"y1": [1.0, 1.0, 1.5, 1.5], "y2": [1.0, 1.0, 0.7, 0.7]})
    with pytest.warns(dm.errors.UncertifiedWarning):
        ensemble = dm.ensemble(c, (0.0, 0.1), y0=y0, method="pinn", config=config, chunk=2)
    first, second = (chunk["status"] for chunk in ensemble.stats["chunks"])
    assert first != second and first.startswith("flagged: not certified (2 of 2 samples): ")
    expected = f"the chunks' statuses differ: {first!r} (chunks from sample 0); {second!r} (chunks from sample 2)"
    assert ensemble.status == expected


def test_an_index_3_ensemble_written_to_files(tmp_path):
    """radau solves the index-2 reduction; the files carry its fingerprint and load with the
    index-3 model."""
    from daemodel.problems import PENDULUM_INDEX3

    m = PENDULUM_INDEX3.model()
    c = m.compile()
    y0 = {"y4": [0.99, 1.0, 1.01]}
    memory = dm.ensemble(c, (0.0, 0.2), y0=y0, h=0.05, chunk=np.int64(2))
    files = dm.ensemble(c, (0.0, 0.2), y0=y0, h=0.05, chunk=np.int64(2), write_to=tmp_path)
    assert files.chunk == 2 and memory.compiled.index == 2
    again = dm.EnsembleFiles.load(tmp_path, m).solution()
    assert same(memory, again, (*memory.compiled.state_names, *memory.compiled.algebraic_names)) == 0.0


def test_a_written_chunk_leaves_only_its_bookkeeping_in_memory(pendulum, tmp_path):
    from daemodel.solving.ensemble import solve_chunk
    from daemodel.solving.ensemble_files import write_chunk

    result = solve_chunk((pendulum, (0.0, 0.1), "radau", {"h": 0.05}, None), 0, {"y0": np.tile(pendulum.y0, (3, 1))})
    write_chunk((tmp_path, "run", {0: "inputs"}), pendulum, result)
    assert {"values", "parameters", "indices"}.isdisjoint(result) and result["solved"] == 3
    assert result["inputs"] == "inputs"
    assert (tmp_path / result["file"]).is_file()


def test_max_failures_stops_an_ensemble_whose_samples_keep_failing(blowup):
    """Every k here blows up inside [0, 1]: the ensemble stops at the bound instead of solving
    each sample alone, and names the first failure."""
    k = np.linspace(5.0, 20.0, 64)
    with pytest.raises(
        ConvergenceError, match=r"more than max_failures=3 samples failed \(4 found, first: sample 0, ConvergenceError"
    ):
        dm.ensemble(blowup, (0.0, 1.0), h=0.05, parameters={"k": k}, chunk=32, max_failures=3)
    few = dm.ensemble(blowup, (0.0, 1.0), h=0.05, parameters={"k": [0.1, 5.0, 0.2]}, chunk=2, max_failures=1)
    assert [f.index for f in few.stats["failures"]] == [1]
    with pytest.raises(InvalidOptionError, match="max_failures must be a non-negative integer or None; got -1"):
        dm.ensemble(blowup, (0.0, 1.0), h=0.05, max_failures=-1)


# ---- events, other inputs, memory --------------------------------------------------------------------------------
G = 9.81


def _ball(reset="-0.8*v"):
    """The bouncing ball on (0, 2.5): four impacts, known in closed form, before its Zeno point."""
    m = dm.Model("ball")
    h, v = m.states("h v")
    g = m.parameter("g", G)
    m.ode(h, v)
    m.ode(v, -g)
    m.initial(h=1.0, v=0.0)
    if reset is not None:
        m.event("floor", when=h, direction=-1, reset={"v": reset})
    return m


def _impacts(g: float, end: float = 2.5, e: float = 0.8) -> list:
    times, t, v = [], np.sqrt(2 / g), np.sqrt(2 * g)
    while t < end:
        times.append(t)
        v *= e
        t += 2 * v / g
    return times


GRAVITY = {"g": np.array([9.81, 9.0, 10.0, 8.0, 12.0])}
T_EVAL = np.linspace(0.0, 2.5, 11)


def test_an_ensemble_returns_its_events_as_a_batched_solve_does(tmp_path):
    """In memory and from files, the events of every sample, NaN-padded (B, K) like a batched solve's
    (before: events == {} both ways), each sample's impacts at the closed form's times."""
    batched = dm.solve(_ball(), (0.0, 2.5), parameters=GRAVITY, t_eval=T_EVAL)
    memory = dm.ensemble(_ball(), (0.0, 2.5), parameters=GRAVITY, t_eval=T_EVAL, chunk=2)
    files = dm.ensemble(_ball(), (0.0, 2.5), parameters=GRAVITY, t_eval=T_EVAL, chunk=2, write_to=tmp_path / "e")
    for sol in (memory, files.solution()):
        assert list(sol.events) == ["floor"]
        np.testing.assert_array_equal(sol.events["floor"]["t"], batched.events["floor"]["t"])
        for side in ("before", "after"):
            np.testing.assert_array_equal(sol.events["floor"][side]["v"], batched.events["floor"][side]["v"])
    for b, g in enumerate(GRAVITY["g"]):
        found = memory.events["floor"]["t"][b]
        exact = _impacts(g)
        np.testing.assert_allclose(found[: len(exact)], exact, rtol=0, atol=1e-7)
        assert np.isnan(found[len(exact) :]).all()
    some = files.solution([4, 0])
    np.testing.assert_array_equal(some.events["floor"]["t"], batched.events["floor"]["t"][[4, 0]])
    np.testing.assert_allclose(some.at([0.3])["h"][:, 0], 1 - 0.5 * GRAVITY["g"][[4, 0]] * 0.09, atol=1e-9)


def test_a_finished_directory_is_not_returned_for_other_inputs_or_another_model(tmp_path):
    """Before: a finished write_to directory run again with other parameters (or another reset, or no
    event) returned the first run's files without a word."""
    where = tmp_path / "e"
    dm.ensemble(_ball(), (0.0, 2.5), parameters=GRAVITY, t_eval=T_EVAL, chunk=2, write_to=where)
    again = dm.ensemble(_ball(), (0.0, 2.5), parameters=GRAVITY, t_eval=T_EVAL, chunk=2, write_to=where)
    assert again.solved == 5  # (the same call: its files)
    with pytest.raises(InvalidOptionError, match=r"write_to .*e holds a finished ensemble of other samples, model"):
        dm.ensemble(_ball(), (0.0, 2.5), parameters={"g": GRAVITY["g"] + 0.5}, t_eval=T_EVAL, chunk=2, write_to=where)
    for other, what in ((_ball("-0.5*v"), r"then v = -0\.5\*v'\]"), (_ball(None), r"the model's \[\]")):
        with pytest.raises(
            SolutionFileError,
            match=r"holds an ensemble of model 'ball' whose events differ from those of 'ball'.*" + what,
        ):
            dm.ensemble(other, (0.0, 2.5), parameters=GRAVITY, t_eval=T_EVAL, chunk=2, write_to=where)
        with pytest.raises(SolutionFileError, match=r"whose events differ"):
            dm.EnsembleFiles.load(where, other)


def test_an_ensemble_that_cannot_fit_in_memory_is_refused_before_its_first_chunk(monkeypatch):
    """5e6 samples of 2e4 output times: 745 GiB, refused with the estimate before any chunk runs
    (before: the first chunk of 10^4 samples was solved, then the total checked)."""
    from daemodel.errors import ResourceLimitError
    from daemodel.solving import ensemble as module

    def never(*args, **kwargs):
        raise AssertionError("a chunk ran")

    monkeypatch.setattr(module, "run_tasks", never)
    monkeypatch.setenv("DAEMODEL_MEMORY_LIMIT", "64G")
    m = dm.Model("decay")
    m.states("x")
    m.parameter("k", 1.0)
    m.ode("x", "-k*x")
    m.initial(x=1.0)
    with pytest.raises(
        ResourceLimitError,
        match=r"ensemble of 5000000 samples kept in memory would need 745 GiB \(outputs of at least 20000 times x 1 "
        r"variables 745 GiB\), more than the 64 GiB allowed",
    ):
        dm.ensemble(m, (0.0, 1.0), parameters={"k": np.ones(5_000_000)}, t_eval=np.linspace(0.0, 1.0, 20_000))


def test_a_time_limit_reported_by_the_method_as_its_own_failure_ends_the_chunk(monkeypatch):
    """A limit that strikes inside a call which reports it as its own failure (casadi: IDA_RES_FAIL, a
    ConvergenceError) ends the chunk as a TimeLimitError: the chunk is not taken for failing samples,
    bisected and solved again piece by piece."""
    import time

    from daemodel.errors import TimeLimitError
    from daemodel.executors import _time_limit
    from daemodel.solving import solver
    from daemodel.solving.ensemble import solve_chunk

    calls = []

    def reported_as_its_own(*args, **kwargs):
        calls.append(1)
        try:
            time.sleep(2.0)  # the limit strikes here
        except TimeLimitError:
            pass
        raise ConvergenceError("casadi-idas: the model could not be evaluated (IDA_RES_FAIL)")

    monkeypatch.setattr(solver, "solve", reported_as_its_own)
    decay = dm.Model("decay")
    (y,) = decay.states("y")
    decay.ode(y, -y)
    decay.initial(y=1.0)
    batch = {"y0": np.ones((8, 1))}
    with pytest.raises(TimeLimitError, match=r"chunks: task 3 ran past its time limit of 0.1 s"):
        with _time_limit(0.1, "chunks", 3):
            solve_chunk((decay.compile(), (0.0, 1.0), "casadi-idas", {}, None), 0, batch)
    assert len(calls) == 1


def _drop():
    m = dm.Model("drop")
    m.states("h v")
    m.ode("h", "v")
    m.ode("v", "-9.81")
    m.initial(h=1.0, v=0.0)
    m.event("floor", "h", direction=-1, terminal=True)
    return m


@pytest.mark.parametrize("chunk", [1, 2, 4])
@pytest.mark.parametrize("to_disk", [False, True])
def test_chunks_whose_samples_end_at_their_own_terminal_events(chunk, to_disk, tmp_path):
    # each chunk's times are t_eval and its own samples' ends: before, chunk=1 failed with a bare numpy ValueError
    # (arrays of 6 and 5 times) and chunk=2 put the second chunk's values on the first chunk's times, h off by
    # 0.28 with status "success"; now every value is at its own time (NaN after its sample's end), and the
    # times are those of t_eval and of each end that every chunk has a value at
    h0 = np.array([1.0, 2.0, 0.5, 3.0])
    grid = np.linspace(0.0, 0.5, 6)
    options = {"y0": {"h": h0}, "t_eval": grid, "rtol": 1e-10, "atol": 1e-10, "chunk": chunk}
    out = dm.ensemble(_drop(), (0.0, 0.5), **options, write_to=tmp_path / "drop" if to_disk else None)
    sol = out.solution() if to_disk else out
    ends = np.sqrt(2.0 * h0 / 9.81)
    assert set(grid) <= set(sol.t.tolist()) and sol.status == "success"
    exact = h0[:, None] - 0.5 * 9.81 * sol.t[None, :] ** 2
    exact[sol.t[None, :] > ends[:, None] + 1e-12] = np.nan
    np.testing.assert_allclose(sol["h"], exact, rtol=0, atol=1e-9)
    np.testing.assert_allclose(sol.events["floor"]["t"][[0, 2], 0], ends[[0, 2]], rtol=0, atol=1e-10)

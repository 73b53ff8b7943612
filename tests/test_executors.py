"""Where tasks run (daemodel/executors.py)."""

import pytest

from daemodel.errors import InvalidOptionError
from daemodel.executors import run_tasks


def _twice(shared, x):
    return shared * x


def test_tasks_run_locally_in_order():
    assert run_tasks(_twice, 2, [(1,), (2,), (3,)], executor="local", label="t") == [2, 4, 6]


@pytest.mark.parametrize("name", ["y5", "Ray", None, ""])
def test_an_executor_that_is_neither_local_nor_ray_is_refused_before_any_task(name):
    """Found by running the benchmarks: a loop variable shadowed the executor's name, and run_tasks
    sent executor='y5' to Ray (starting a cluster, or joining one already running)."""
    ran = []
    with pytest.raises(InvalidOptionError, match=rf"^surrogate: executor must be one of local, ray; got {name!r}$"):
        run_tasks(lambda shared, x: ran.append(x), None, [(1,)], executor=name, label="surrogate")
    assert ran == []


def test_a_time_limit_strikes_again_where_its_first_error_was_swallowed():
    """casadi's Python wrappers catch every exception in their type checks: a limit that struck while
    casadi built a model's functions was lost there, and the task ran on to its end (the transistor
    amplifier's IDAS at rtol 1e-9 under a 0.01 s limit: 9.5 s).  The limit strikes again until the
    block ends; once it has ended, nothing strikes."""
    import time

    from daemodel.errors import TimeLimitError
    from daemodel.executors import TIME_LIMIT_REPEAT, time_limit

    began = time.perf_counter()
    with pytest.raises(TimeLimitError, match="stop here"), time_limit(0.05, "stop here") as limit:
        try:
            time.sleep(1.0)  # the limit strikes here, and is swallowed, as by a bare except
        except Exception:
            pass
        assert limit.expired
        time.sleep(5.0)  # before: slept on to its end
    assert time.perf_counter() - began < 0.05 + TIME_LIMIT_REPEAT + 0.5
    with time_limit(0.05, "unused") as limit:
        pass
    time.sleep(0.1 + TIME_LIMIT_REPEAT)  # (no strike after the block)
    assert not limit.expired


def test_a_time_limit_does_not_strike_inside_an_import(tmp_path, monkeypatch):
    """torch, stopped half-imported by an ensemble chunk's 0.5 s limit, stayed broken for the process
    ("partially initialized module 'torch' has no attribute 'types'" in every later solve): the limit
    waits for the import to finish and strikes after it."""
    import sys
    import time

    from daemodel.errors import TimeLimitError
    from daemodel.executors import TIME_LIMIT_REPEAT, time_limit

    (tmp_path / "slow_to_import.py").write_text("import time\n\ntime.sleep(0.5)\nDONE = True\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "slow_to_import", raising=False)
    began = time.perf_counter()
    with pytest.raises(TimeLimitError, match="stop here"), time_limit(0.05, "stop here"):
        import slow_to_import  # noqa: F401

        time.sleep(5.0)
    assert sys.modules["slow_to_import"].DONE
    assert 0.5 <= time.perf_counter() - began < 0.5 + TIME_LIMIT_REPEAT + 0.5

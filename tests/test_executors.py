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

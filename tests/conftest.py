import pytest

import daemodel as dm
from daemodel.problems import PROBLEMS


@pytest.fixture
def hessenberg() -> dm.Model:
    return PROBLEMS["hessenberg"].model()


@pytest.fixture
def pendulum() -> dm.Model:
    return PROBLEMS["pendulum"].model()


@pytest.fixture
def pendulum3() -> dm.Model:
    return PROBLEMS["pendulum-index3"].model()


@pytest.fixture(scope="session")
def ray_cluster():
    """A local Ray cluster of 2 CPUs, started once for every test that takes it (skipped where
    Ray is not installed; CI installs it with the ``ray`` extra)."""
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, log_to_driver=False, include_dashboard=False)
    yield ray
    ray.shutdown()

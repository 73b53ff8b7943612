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

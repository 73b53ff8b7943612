import os
import sys
from pathlib import Path

# Under pytest-xdist (pyproject's ``-n 2``) each worker runs numpy's and torch's BLAS and OpenMP on one thread:
# two workers of two threads each on CI's two cores oversubscribe them, and OpenBLAS's threads, which spin while
# they wait, made BLAS-bound tests up to 35x slower (a 200 x 200 pinv test: 0.46 s alone, 16-31 s).  Set before
# numpy and torch are first imported (they read it then: pytest_configure ran after this module's imports, and
# OpenBLAS kept 2 threads in each worker).  The processes the tests start inherit it.
if os.environ.get("PYTEST_XDIST_WORKER"):
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import pytest

import daemodel as dm
from daemodel.problems import PROBLEMS

# tests/backends/pinn/pinn_hard_models.py is imported by tests in other folders too (test_pinn.py, test_compare.py,
# test_radau_control.py): importable whichever file runs alone, not only after pytest has collected its folder.
sys.path.insert(0, str(Path(__file__).parent / "backends" / "pinn"))


# A cache folder shared by several pytest runs (CI's fast and slow steps: .ci/run sets it); unset, each run has
# its own in its temporary folder.
SHARED_CACHE_VARIABLE = "DAEMODEL_TEST_CACHE"


@pytest.fixture(scope="session", autouse=True)
def compiled_cache(tmp_path_factory):
    """The cache of compiled libraries (daemodel.cache) of the whole run, in a temporary folder, one for all
    of the run's xdist workers (with one each, 74 of the fast suite's 478 libraries were compiled by both,
    ~3 s each): the tests, and the processes they start, never write to the user's ~/.cache.  Tests that
    count compiler runs or read a first "miss" set a fresh folder of their own."""
    shared = os.environ.get(SHARED_CACHE_VARIABLE)
    if shared:
        folder = Path(shared)
    else:  # (a worker's basetemp is <the run's>/popen-gw<N>: the run's folder is its parent)
        base = tmp_path_factory.getbasetemp()
        folder = (base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base) / "daemodel-cache" / "cache"
    before = os.environ.get("DAEMODEL_CACHE")
    os.environ["DAEMODEL_CACHE"] = str(folder)
    yield folder
    if before is None:
        os.environ.pop("DAEMODEL_CACHE", None)
    else:
        os.environ["DAEMODEL_CACHE"] = before


@pytest.fixture(autouse=True)
def radau_on_the_virtual_machine(request, monkeypatch):
    """In tests marked ``virtual_machine`` and not ``machine_code``, radau's ``jit="auto"`` runs its steps on
    casadi's virtual machine, as ``jit=False`` does (``stats["jit"]`` says so; a band model of 101-200 unknowns would
    still factor in the band kernel's C, and a module-scoped fixture's solve, made before this, compiles): modules
    whose subject lives around the engine's solves (events, switches, rests, branches, outputs' arrays, declaring)
    or is the same on both (the controller's trust: casadi's graph of the run, compiled or not).  The default
    compiled a library per model, per branch of its switches and per stages (each floor level, each side of a
    sign: ~1 s of the compiler for a model of two states); in those 18 modules, 647 of the fast suite's ~1,730
    test-seconds went to 336 (CPU, idle machine).  The tests marked ``machine_code`` there run the default as users
    get it: the event search's stops in the run's blocks of steps, resets, accumulating events, floor levels,
    sliding, crossings and crossings back within a step, balls at any scale, batches of events, the clocks (the
    compiler's time on the setup's), the tests that compare jit's values.  The rest of tests/backends, the
    examples, the docs and the fuzz pass keep the default everywhere."""
    if request.node.get_closest_marker("virtual_machine") is None or request.node.get_closest_marker("machine_code"):
        return
    from daemodel.backends.radau import backend

    choose = backend.jit_choice

    def on_the_virtual_machine(name, options, D):
        if name == "casadi" and options.jit == "auto":
            return False, "casadi's virtual machine (jit='auto' in a test marked virtual_machine)"
        return choose(name, options, D)

    monkeypatch.setattr(backend, "jit_choice", on_the_virtual_machine)


def _diffusion_grid(K: int) -> dm.Model:
    """A line of K cells diffusing c, each consuming it at the rate w = c^2 / (1 + c) (an algebraic
    variable per cell: K states, K algebraic variables, tridiagonal), c(0) = sin(pi x)."""
    import numpy as np

    m = dm.Model(f"grid{K}")
    c = m.states([f"c{k}" for k in range(K)])
    w = m.algebraics([f"w{k}" for k in range(K)])
    padded = (0, *c, 0)
    for k in range(K):
        m.ode(c[k], (padded[k] - 2 * padded[k + 1] + padded[k + 2]) * (K + 1) ** 2 / 10 - w[k])
        m.constraint(w[k] - c[k] ** 2 / (1 + c[k]), name=f"rate{k}")
    m.initial(**{f"c{k}": np.sin(np.pi * (k + 1) / (K + 1)) for k in range(K)})
    return m


def _first_engine(model, **options):
    """``(compiled, the casadi engine of model's first solve)``: its Jacobian pattern and static factors,
    on casadi's virtual machine, adaptive at rtol = atol = 1e-6 unless ``options`` say otherwise."""
    from daemodel.backends.radau.casadi_engine import CasadiEngine

    engines = []
    original = CasadiEngine.__init__

    def keep(self, *args, **kwargs):
        original(self, *args, **kwargs)
        engines.append(self)

    CasadiEngine.__init__ = keep
    try:
        compiled = model.compile()
        options = options or {"rtol": 1e-6, "atol": 1e-6}
        dm.solve(compiled, (0.0, 1e-3), jit=False, **options)  # (its pattern: nothing to compile)
    finally:
        CasadiEngine.__init__ = original
    return compiled, engines[-1]


@pytest.fixture(scope="session")
def first_engine():
    """The function ``first_engine(model, **options) -> (compiled, engine)`` (:func:`_first_engine`)."""
    return _first_engine


@pytest.fixture(scope="session")
def diffusion_grid():
    """The builder of :func:`_diffusion_grid`'s model of K cells (K states, K algebraic variables)."""
    return _diffusion_grid


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
def blowup() -> dm.CompiledDAE:
    """x' = k x^2, x(0) = 1: x = 1 / (1 - k t) blows up at t = 1/k, inside [0, 1] for k > 1."""
    m = dm.Model("blowup")
    (x,) = m.states("x")
    k = m.parameter("k", 1.0)
    m.ode(x, k * x**2)
    m.initial(x=1.0)
    return m.compile()


@pytest.fixture(scope="session")
def ray_cluster():
    """A local Ray cluster of 2 CPUs, started once for every test that takes it, as daemodel
    starts one (on 127.0.0.1; skipped where Ray is not installed; CI installs it with the ``ray``
    extra)."""
    ray = pytest.importorskip("ray")
    from daemodel.executors import connect

    connect(2, None)
    yield ray
    ray.shutdown()

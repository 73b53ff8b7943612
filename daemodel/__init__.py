"""daemodel: declare semi-explicit DAEs symbolically; solve and compare them with a
Radau-PINN and classical solvers."""

from daemodel import errors
from daemodel.backends import methods
from daemodel.backends.pinn.config import PINNConfig
from daemodel.comparing.bench import BenchResult, bench
from daemodel.comparing.compare import compare
from daemodel.comparing.tables import Comparison
from daemodel.compiling.compiled import CompiledDAE
from daemodel.compiling.compiler import Model
from daemodel.declaring.stencils import Stencil, stencil
from daemodel.fitting.fit import Fit, fit
from daemodel.solution import Solution
from daemodel.solving.ensemble import ensemble
from daemodel.solving.ensemble_files import EnsembleFiles
from daemodel.solving.solver import solve
from daemodel.tableau import RadauIIA, radau_iia

__all__ = [
    "BenchResult",
    "Comparison",
    "CompiledDAE",
    "EnsembleFiles",
    "Fit",
    "Model",
    "PINNConfig",
    "RadauIIA",
    "Solution",
    "Stencil",
    "Surrogate",
    "bench",
    "compare",
    "ensemble",
    "errors",
    "fit",
    "methods",
    "radau_iia",
    "solve",
    "stencil",
]
__version__ = "0.1.0"


def __getattr__(name):
    # Surrogate needs torch; load it on first use so that importing daemodel stays light.
    if name == "Surrogate":
        from daemodel.solving.surrogates import Surrogate

        return Surrogate
    raise AttributeError(f"module 'daemodel' has no attribute {name!r}")

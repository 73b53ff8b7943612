"""daemodel: declare semi-explicit DAEs symbolically; solve and compare them with a
Radau-PINN and classical solvers."""

from daemodel import errors
from daemodel.backends import methods
from daemodel.compiled import CompiledDAE
from daemodel.model import Model
from daemodel.solution import Solution
from daemodel.solver import solve
from daemodel.tableau import RadauIIA, radau_iia

__all__ = ["CompiledDAE", "Model", "RadauIIA", "Solution", "errors", "methods", "radau_iia", "solve"]
__version__ = "0.1.0"

"""daemodel: declare semi-explicit DAEs symbolically; solve and compare them with a
Radau-PINN and classical solvers."""

from daemodel import errors
from daemodel.compiled import CompiledDAE
from daemodel.model import Model
from daemodel.tableau import RadauIIA, radau_iia

__all__ = ["CompiledDAE", "Model", "RadauIIA", "errors", "radau_iia"]
__version__ = "0.1.0"

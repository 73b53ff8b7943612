"""``method="radau"``: Radau IIA with RADAU5's linear algebra, fixed or adaptive steps, on two engines.

The files read like the algorithm: :mod:`.transform` (the tableau in RADAU5's form and the
embedded estimate's weights), :mod:`.engines` with :mod:`.torch_engine` and :mod:`.casadi_engine`
(who evaluates and factors; :mod:`.compiled` holds the casadi functions, among them one compiled
adaptive attempt, :mod:`.loop` many attempts with the controller in one call, :mod:`.sparse` and
:mod:`.kernel` LU factors with a fixed pivot order), :mod:`.newton` (one policy object),
:mod:`.error` (the local error estimate), :mod:`.step` (one step on an engine), :mod:`.control`
(the fixed grid and RADAU5's controller) and :mod:`.backend` (the glue: engine, controller,
stepper, Solution).
"""

from daemodel.backends.base import LOCAL_ERROR_BOUND
from daemodel.backends.radau.backend import RadauBackend
from daemodel.backends.radau.options import (
    DEFAULT_MAX_ADAPTIVE_STEPS,
    DEFAULT_MAX_FIXED_STEPS,
    RadauOptions,
    adaptive_stages,
    stages_for_index,
)
from daemodel.backends.radau.transform import embedded_weights

__all__ = [
    "DEFAULT_MAX_ADAPTIVE_STEPS",
    "DEFAULT_MAX_FIXED_STEPS",
    "LOCAL_ERROR_BOUND",
    "RadauBackend",
    "RadauOptions",
    "adaptive_stages",
    "embedded_weights",
    "stages_for_index",
]

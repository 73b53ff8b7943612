"""Solution methods, one module each, found by name.

A new method is a new module with a final :class:`~daemodel.backends.base.AbstractBackend`
subclass plus one line in :data:`REGISTRY`.  Modules load on first use, so ``import
daemodel`` does not import torch.
"""

from __future__ import annotations

import importlib

from daemodel.errors import UnknownMethodError

# method name -> "module:class"
REGISTRY: dict[str, str] = {
    "radau": "daemodel.backends.radau.backend:RadauBackend",
    "casadi-collocation": "daemodel.backends.casadi.collocation:CollocationBackend",
    "casadi-idas": "daemodel.backends.casadi.idas:IDASBackend",
    "reference": "daemodel.backends.reference:ReferenceBackend",
    "pinn": "daemodel.backends.pinn.backend:PINNBackend",
}


# The method that compare() measures the others against when no exact solution is given (and
# leaves out of its default list of methods).
REFERENCE = "reference"


def methods() -> tuple[str, ...]:
    """The registered method names."""
    return tuple(REGISTRY)


def get_backend(method: str):
    """The backend registered as ``method``.

    Raises
    ------
    UnknownMethodError
        Listing the known methods.
    """
    if not isinstance(method, str) or method not in REGISTRY:
        raise UnknownMethodError(f"unknown method {method!r}; the methods are {', '.join(REGISTRY)}")
    module, cls = REGISTRY[method].split(":")
    return getattr(importlib.import_module(module), cls)()

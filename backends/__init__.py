"""Solution methods, one module or package each, found by name (:mod:`.registry`).

A new built-in method is a new module with a final :class:`~daemodel.backends.base.AbstractBackend`
subclass plus one line in :data:`~.registry.REGISTRY`; a method from outside is registered with
``dm.methods.register(name, cls)`` or installed under the ``daemodel.methods`` entry-point group
(docs/methods.md#writing-a-method).  Modules load on first use, so ``import daemodel`` does not
import torch.
"""

from daemodel.backends.registry import REFERENCE, REGISTRY, backends_for, get_backend, methods

__all__ = ["REFERENCE", "REGISTRY", "backends_for", "get_backend", "methods"]

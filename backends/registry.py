"""Methods found by name: the built-in ones, those registered in this process, and those installed.

A method is a final subclass of :class:`~daemodel.backends.base.AbstractBackend` (the contract:
that module's docstring and docs/methods.md#writing-a-method).  It is found by its name in three
places, in this order:

1. ``dm.methods.register(name, cls)`` in this process (a plain function call; ``replace=True``
   replaces a built-in or installed method of that name);
2. :data:`REGISTRY`, the built-in methods (``name -> "module:class"``, imported on first use, so
   ``import daemodel`` does not import torch);
3. the ``daemodel.methods`` entry-point group of the installed distributions
   (``[project.entry-points."daemodel.methods"] my-method = "my_package.module:MyBackend"``), read
   with :mod:`importlib.metadata` on the first lookup (and again when ``sys.path`` changes), each
   imported only when its method is asked for.  An entry point that cannot be used raises
   :class:`~daemodel.errors.MethodPluginError` naming its distribution and name when its method is
   asked for; the other methods are not touched.

Nothing here evaluates a user's string: names are checked against :data:`METHOD_NAME`, classes
come from ``import_module`` and ``getattr`` (through :meth:`importlib.metadata.EntryPoint.load`).
"""

from __future__ import annotations

import importlib
import re
import sys
import threading
import warnings

from daemodel.errors import (
    MethodClassError,
    MethodNameError,
    MethodPluginError,
    MethodPluginWarning,
    UnknownMethodError,
)

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

# The entry-point group that installed distributions declare their methods in.
ENTRY_POINT_GROUP = "daemodel.methods"

# A method name: a letter, then letters or digits in groups joined by single '-' or '_', at most
# 64 characters (it becomes a column of tables, a label of plots and part of file names).
METHOD_NAME = re.compile(r"[A-Za-z][A-Za-z0-9]*(?:[-_][A-Za-z0-9]+)*")
METHOD_NAME_LENGTH = 64


def check_method_name(name) -> str:
    """``name`` if it is a plain method name (:data:`METHOD_NAME`), else :class:`MethodNameError`."""
    if not isinstance(name, str):
        raise MethodNameError(f"a method name must be a string; got {type(name).__name__} {name!r}")
    if len(name) > METHOD_NAME_LENGTH or not METHOD_NAME.fullmatch(name):
        shown = name if len(name) <= METHOD_NAME_LENGTH else name[:METHOD_NAME_LENGTH] + "..."
        raise MethodNameError(
            f"method name {shown!r} is not a plain name: a letter, then letters, digits and single '-' or '_' "
            f"between them, at most {METHOD_NAME_LENGTH} characters (e.g. 'my-method')"
        )
    return name


def check_backend_class(name: str, cls) -> type:
    """``cls`` if it keeps the backend contract for method ``name``, else :class:`MethodClassError`
    naming what is missing: a concrete subclass of :class:`AbstractBackend` whose ``name`` is
    ``name``, whose ``Options`` is a dataclass and whose ``max_index`` is 1, 2 or 3."""
    import dataclasses
    import inspect

    from daemodel.backends.base import AbstractBackend

    what = f"method {name!r}"
    if not isinstance(cls, type) or not issubclass(cls, AbstractBackend):
        got = cls.__name__ if isinstance(cls, type) else f"{type(cls).__name__} {cls!r}"[:80]
        raise MethodClassError(
            f"{what}: expected a subclass of daemodel.backends.base.AbstractBackend (the class, not an instance); "
            f"got {got}"
        )
    if inspect.isabstract(cls):
        missing = ", ".join(sorted(cls.__abstractmethods__))
        raise MethodClassError(f"{what}: class {cls.__name__} is abstract: define {missing}")
    declared = getattr(cls, "name", None)
    if declared != name:
        raise MethodClassError(
            f"{what}: class {cls.__name__} has name = {declared!r}; a method's name is the one it is registered "
            f"under: set name = {name!r} in the class"
        )
    options = getattr(cls, "Options", None)
    if not (isinstance(options, type) and dataclasses.is_dataclass(options)):
        raise MethodClassError(
            f"{what}: class {cls.__name__}'s Options must be a (frozen, keyword-only) dataclass of its options; "
            f"got {options!r}"
        )
    index = getattr(cls, "max_index", None)
    if isinstance(index, bool) or index not in (1, 2, 3):
        raise MethodClassError(
            f"{what}: class {cls.__name__}'s max_index must be 1, 2 or 3 (the highest index it solves "
            f"directly; solve reduces higher ones); got {index!r}"
        )
    return cls


class MethodRegistry:
    """``dm.methods``: the method names (``dm.methods()``), and ``register``/``unregister``.

    One instance, :data:`methods`; it is safe to use from several threads.
    """

    def __init__(self) -> None:
        self._lock = threading.RLock()
        self._registered: dict[str, type] = {}
        self._loaded: dict[str, type] = {}  # entry points imported and checked
        self._entry_points: dict[str, list] = {}  # name -> its entry points (more than one: a clash)
        self._scanned_path: tuple | None = None

    def __call__(self) -> tuple[str, ...]:
        """The method names: the built-in ones, then the installed ones, then those registered here."""
        with self._lock:
            installed = self._installed()
            names = [*REGISTRY, *sorted(installed), *self._registered]
        return tuple(dict.fromkeys(names))

    def register(self, name: str, cls: type, *, replace: bool = False) -> None:
        """Make ``cls`` the method ``name`` in this process (``dm.solve(method=name)``, ``dm.compare``).

        Parameters
        ----------
        name : str
            A plain name (a letter, then letters, digits, single ``-`` or ``_``; at most 64 characters),
            equal to ``cls.name``.
        cls : type
            A concrete subclass of :class:`~daemodel.backends.base.AbstractBackend`.
        replace : bool
            Replace a built-in method, an installed one or one registered earlier of that name.

        Raises
        ------
        MethodNameError
            ``name`` is not a plain name, or is taken and ``replace`` is False.
        MethodClassError
            ``cls`` does not keep the contract (see :func:`check_backend_class`).

        Notes
        -----
        A registration lives in this process (and in processes forked from it); methods that
        ensembles run in other processes or on Ray find by name are installed ones (the entry point).
        """
        check_method_name(name)
        if not isinstance(replace, bool):
            raise MethodNameError(f"replace must be True or False; got {replace!r}")
        check_backend_class(name, cls)
        with self._lock:
            if not replace:
                taken = None
                if name in self._registered:
                    taken = f"registered earlier ({self._registered[name].__qualname__})"
                elif name in REGISTRY:
                    taken = "a built-in method"
                elif name in self._installed():
                    taken = f"installed by {describe_entry_points(self._entry_points[name])}"
                if taken:
                    raise MethodNameError(
                        f"method name {name!r} is taken: {taken}; pass replace=True to replace it, or choose "
                        "another name"
                    )
            self._registered[name] = cls

    def unregister(self, name: str) -> None:
        """Remove the method ``name`` registered in this process (a built-in or installed method it
        replaced is found again); :class:`UnknownMethodError` if none was registered under it."""
        with self._lock:
            if not isinstance(name, str) or name not in self._registered:
                known = ", ".join(self._registered) or "none"
                raise UnknownMethodError(
                    f"no method {name!r} was registered in this process (registered: {known}); built-in and "
                    "installed methods cannot be unregistered"
                )
            del self._registered[name]

    def backend_class(self, method: str) -> type:
        """The class of the method ``method``.

        Raises
        ------
        UnknownMethodError
            Listing the known methods.
        MethodPluginError
            An installed method that cannot be loaded, naming its distribution and entry point.
        """
        if not isinstance(method, str):
            raise UnknownMethodError(f"unknown method {method!r}; the methods are {', '.join(self())}")
        with self._lock:
            if method in self._registered:
                return self._registered[method]
        if method in REGISTRY:
            module, cls = REGISTRY[method].split(":")
            return getattr(importlib.import_module(module), cls)
        with self._lock:
            installed = self._installed()
            if method not in installed:
                raise UnknownMethodError(f"unknown method {method!r}; the methods are {', '.join(self())}")
            if method not in self._loaded:
                self._loaded[method] = load_entry_point(method, installed[method])
            return self._loaded[method]

    def entry_points_of(self, method: str) -> list:
        """The entry points ``method`` is loaded from: none for a built-in or registered method."""
        with self._lock:
            if method in self._registered or method in REGISTRY:
                return []
            return list(self._installed().get(method, []))

    def _installed(self) -> dict[str, list]:
        """The entry points of :data:`ENTRY_POINT_GROUP` by name, read again when ``sys.path`` has changed;
        those with an unusable name or a built-in's are left out with a :class:`MethodPluginWarning`."""
        path = tuple(sys.path)
        if self._scanned_path == path:
            return self._entry_points
        from importlib.metadata import entry_points

        found: dict[str, list] = {}
        for point in entry_points(group=ENTRY_POINT_GROUP):
            where = describe_entry_points([point])
            if not isinstance(point.name, str) or not METHOD_NAME.fullmatch(point.name):
                warnings.warn(
                    f"{where} is ignored: {point.name!r} is not a plain method name (a letter, then letters, digits "
                    "and single '-' or '_')",
                    MethodPluginWarning,
                    stacklevel=3,
                )
            elif point.name in REGISTRY:
                warnings.warn(
                    f"{where} is ignored: {point.name!r} is a built-in method, which is used; the distribution "
                    "should choose another name",
                    MethodPluginWarning,
                    stacklevel=3,
                )
            else:
                found.setdefault(point.name, []).append(point)
        self._entry_points, self._scanned_path = found, path
        self._loaded = {name: cls for name, cls in self._loaded.items() if name in found}
        return found


def describe_entry_points(points) -> str:
    """``"entry point 'name' = 'module:Class' of distribution 'dist' (group daemodel.methods)"``, for each."""
    parts = []
    for point in points:
        dist = getattr(point, "dist", None)
        dist = f"{dist.name} {dist.version}" if dist is not None else "an unknown distribution"
        parts.append(f"entry point {point.name!r} = {point.value!r} of distribution {dist!r}")
    return " and ".join(parts) + f" (group {ENTRY_POINT_GROUP})"


def load_entry_point(name: str, points: list) -> type:
    """The checked class of the method ``name`` from its entry points; :class:`MethodPluginError`
    naming the distribution and the entry point where there are two, or it does not load or keep the
    contract."""
    where = describe_entry_points(points)
    if len(points) > 1:
        raise MethodPluginError(
            f"method {name!r} is declared by {len(points)} entry points, {where}: uninstall one of them"
        )
    try:
        cls = points[0].load()
    except Exception as error:  # (any error of a third party's import: named, with its cause chained)
        raise MethodPluginError(
            f"method {name!r} cannot be loaded from {where}: {type(error).__name__}: {error}"
        ) from error
    try:
        return check_backend_class(name, cls)
    except MethodClassError as error:
        raise MethodPluginError(f"method {name!r} from {where} breaks the backend contract: {error}") from error


methods = MethodRegistry()


def backends_for(names, who: str) -> dict:
    """Backend instances by name: of ``names``, or, where it is None (a call given no methods:
    ``compare``, ``bench``), of every method but ``reference``.  Of every method, one installed that
    cannot be loaded is left out with a :class:`MethodPluginWarning` naming it and why, instead of
    stopping the call; named explicitly it raises :class:`MethodPluginError` (an unknown name
    :class:`UnknownMethodError`, a name given twice :class:`DuplicateMethodError`)."""
    from daemodel.errors import DuplicateMethodError, MethodPluginError, MethodPluginWarning

    if names is not None:
        out = {}
        for name in names:
            if name in out:  # (a dict of backends would keep it once, silently)
                raise DuplicateMethodError(
                    f"{who} is given method {name!r} twice in methods; name each method once, its settings in sweep"
                )
            out[name] = get_backend(name)
        return out
    out = {}
    for name in methods():
        if name == REFERENCE:
            continue
        try:
            out[name] = get_backend(name)
        except MethodPluginError as error:
            warnings.warn(f"{who} leaves out {error}", MethodPluginWarning, stacklevel=3)
    return out


def get_backend(method: str):
    """An instance of the method ``method`` (built in, installed or registered).

    Raises
    ------
    UnknownMethodError
        Listing the known methods.
    MethodPluginError
        An installed method that cannot be loaded, or whose class cannot be constructed, naming its
        distribution and entry point.
    """
    cls = methods.backend_class(method)
    points = methods.entry_points_of(method)
    if not points:
        return cls()
    try:
        return cls()
    except Exception as error:  # (a third party's constructor, e.g. one that needs a GPU: named as a failed load)
        raise MethodPluginError(
            f"method {method!r} from {describe_entry_points(points)} cannot be constructed: {type(error).__name__}: "
            f"{error}"
        ) from error

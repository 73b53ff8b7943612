"""Arrays of variables: their shapes, their elements' names, and those names taken apart.

``m.states("u", 1000)`` declares the states ``u[0]``, ..., ``u[999]``; ``m.states("T", (100, 100))``
declares ``T[0,0]``, ..., ``T[99,99]`` (numpy's notation for an element, one bracket, no spaces), in
numpy's order (the last index varies fastest).  An element's name is the only user text with
brackets: generated source never holds it, only :func:`identifier` of it (``u_0``, ``T_3_4``).
"""

from __future__ import annotations

import numbers
import re

import numpy as np

from daemodel.errors import ResourceLimitError, ShapeError, UnknownSymbolError
from daemodel.files import memory_limit

# An element's name: an identifier, then one index per axis (no spaces, no sign).
ELEMENT = re.compile(r"([A-Za-z][A-Za-z0-9_]*)\[([0-9]+(?:,[0-9]+)*)\]")
# Most elements one array may have: far beyond a model daemodel can solve, small enough that a typo
# (an extra zero or two) is an error, not an hour spent allocating symbols.
MAX_ELEMENTS = 10_000_000
# What an element costs before any equation: its sympy symbol, name and index entries (0.35 kB measured at
# 10^5 elements); an array whose elements alone would pass the memory limit is refused before they are made.
ELEMENT_BYTES = 350


def checked_shape(shape, what: str) -> tuple[int, ...]:
    """``shape`` (an int, or a tuple of ints, each at least 1) as a tuple, else a :class:`ShapeError`
    naming ``what`` (e.g. ``"differential variable array 'u'"``)."""
    dims = (shape,) if isinstance(shape, numbers.Integral) and not isinstance(shape, bool) else shape
    if isinstance(dims, str):
        raise ShapeError(
            f"{what}: the shape must be an int or a tuple of ints; got the string {dims!r} (to declare several "
            "names, give them in one string: m.states('x y'))"
        )
    if (
        not isinstance(dims, tuple | list)
        or not dims
        or not all(isinstance(d, numbers.Integral) and not isinstance(d, bool) for d in dims)
    ):
        raise ShapeError(f"{what}: the shape must be an int or a tuple of ints; got {shape!r}")
    dims = tuple(int(d) for d in dims)
    if any(d < 1 for d in dims):
        raise ShapeError(f"{what}: every axis needs at least one element; got shape {dims}")
    if int(np.prod(dims, dtype=object)) > MAX_ELEMENTS:
        raise ShapeError(f"{what}: shape {dims} has more than the {MAX_ELEMENTS:,} elements an array may have")
    count, limit = int(np.prod(dims, dtype=object)), memory_limit()
    if count * ELEMENT_BYTES > limit:
        raise ResourceLimitError(
            f"{what}: shape {dims} makes {count:,} elements, about {count * ELEMENT_BYTES / 2**30:.3g} GiB of "
            f"symbols ({ELEMENT_BYTES} bytes each) before any equation, over the memory limit of "
            f"{limit / 2**30:.3g} GiB (DAEMODEL_MEMORY_LIMIT)"
        )
    return dims


def element_names(name: str, shape: tuple[int, ...]) -> list[str]:
    """The names of the elements of the array ``name``, in numpy's (C) order: ``u[0]``, ``T[3,4]``."""
    if len(shape) == 1:
        return [f"{name}[{i}]" for i in range(shape[0])]
    return [f"{name}[{','.join(map(str, index))}]" for index in np.ndindex(*shape)]


def split_element(name: str) -> tuple[str, tuple[int, ...]] | None:
    """``("T", (3, 4))`` for ``"T[3,4]"`` (spaces after commas allowed), None for a name of no element."""
    match = ELEMENT.fullmatch(name.replace(" ", "")) if "[" in name else None
    if match is None:
        return None
    return match.group(1), tuple(int(i) for i in match.group(2).split(","))


def element_name(name: str, index: tuple[int, ...], shape: tuple[int, ...], what: str, error=UnknownSymbolError) -> str:
    """The name of element ``index`` of the array ``name`` of ``shape``, else ``error`` naming ``what``,
    the index and the shape (a wrong number of indices, one out of range)."""
    if len(index) != len(shape):
        raise error(
            f"{what}: {name}[{','.join(map(str, index))}] gives {len(index)} index(es) for the {len(shape)}-d array "
            f"'{name}' of shape {shape}"
        )
    for axis, (i, n) in enumerate(zip(index, shape, strict=True)):
        if not 0 <= i < n:
            raise error(f"{what}: index {i} is out of range for axis {axis} of '{name}', shape {shape} (0 to {n - 1})")
    return f"{name}[{','.join(map(str, index))}]"


def identifier(name: str) -> str:
    """An identifier for a declared name in generated source: the name itself, or for an element
    ``u[3]`` / ``T[3,4]``, ``u_3`` / ``T_3_4`` (the caller keeps them apart from other names)."""
    if "[" not in name:
        return name
    match = ELEMENT.fullmatch(name)
    if match is None:
        raise ValueError(f"refusing to emit the name {name!r}")  # the front end declares only these
    return f"{match.group(1)}_{match.group(2).replace(',', '_')}"


def symbol_array(symbols: list, shape: tuple[int, ...]) -> np.ndarray:
    """``symbols`` as a numpy object array of ``shape`` (numpy would unpack iterable elements)."""
    out = np.empty(len(symbols), dtype=object)
    out[:] = symbols
    return out.reshape(shape)


def compact_listing(names) -> str:
    """Names for a message, each array's elements as one entry: ``'x', 'u[0..999]' (1000)``."""
    out, counts = [], {}
    for name in names:
        parts = split_element(name)
        if parts is None:
            out.append(f"'{name}'")
            continue
        if parts[0] not in counts:
            out.append(parts[0])
        counts[parts[0]] = counts.get(parts[0], 0) + 1
    return ", ".join(f"'{e}[...]' ({counts[e]} elements)" if e in counts else e for e in out) or "(none)"

"""The one check of a number a user gives: an option, an initial or parameter value, a time.

A user's number comes as a Python ``int``/``float``, a numpy scalar (``np.float32(0.05)``,
``np.int64(3)``, read from an array) or a sympy number (``sp.pi``, ``sp.Rational(1, 3)``,
``sp.sqrt(2)``, from a symbolic derivation).  All of them are the same number to daemodel, and
leave this check as a Python ``float`` (or ``int``), which every backend, torch, casadi and JSON
take as they are.  Anything else (a bool, a string, a sympy symbol or expression of symbols, a
complex number, an array) is refused with a message that names the value's role.
"""

from __future__ import annotations

import math
import numbers

import numpy as np
import sympy as sp

from daemodel.errors import InvalidValueError
from daemodel.messages import quoted


def real(value, what: str, *, integer: bool = False, finite: bool = True, error: type = InvalidValueError):
    """``value`` as a Python float (``int`` with ``integer=True``), else ``error``.

    Parameters
    ----------
    value : int, float, numpy scalar or sympy number
        A sympy value must be a number (no free symbols) that evaluates to a real.
    what : str
        The value's role in messages: ``"h"``, ``"initial value of 'x'"``.
    integer : bool
        Accept only integers (``3``, ``np.int64(3)``, ``sp.Integer(3)``; not ``3.0``).
    finite : bool
        Refuse inf and NaN.
    error : type
        The :class:`~daemodel.errors.ModelError` subclass to raise (an option's is
        :class:`~daemodel.errors.InvalidOptionError`).

    Returns
    -------
    float or int
    """
    kind = "a finite integer" if integer else "a real number"
    if isinstance(value, bool | np.bool_):  # a bool is an int to Python, never a number meant here
        raise error(f"{what} must be {kind}; got {value!r} (bool)")
    if isinstance(value, sp.Basic):
        if not value.is_number:  # x, 2*x: a symbol has no value here
            raise error(
                f"{what} must be {kind}; got the sympy expression {quoted(str(value), 60)}, which has no numeric "
                "value (give a number, or substitute the symbols first)"
            )
        if integer and not value.is_Integer:
            raise error(f"{what} must be {kind}; got {quoted(str(value), 60)}")
        if not integer and value.is_extended_real is False:
            raise error(f"{what} must be {kind}; got the complex number {quoted(str(value), 60)}")
        try:
            number = int(value) if integer else float(value)
        except (TypeError, ValueError, OverflowError):
            raise error(f"{what} must be {kind}; got {quoted(str(value), 60)}") from None
    elif integer:
        if not isinstance(value, numbers.Integral):
            raise error(f"{what} must be {kind}; got {quoted(value)} ({type(value).__name__})")
        number = int(value)
    else:
        if not isinstance(value, numbers.Real):  # np.floating and np.integer are registered here
            raise error(f"{what} must be {kind}; got {quoted(value)} ({type(value).__name__})")
        try:
            number = float(value)
        except OverflowError:  # an int beyond float's range
            raise error(f"{what} must be {kind}; got {quoted(value)} (beyond float's range)") from None
    if finite and not integer and not math.isfinite(number):
        raise error(f"{what} must be finite; got {quoted(value)}")
    return number


def is_real(value) -> bool:
    """Whether :func:`real` would take ``value``'s type (a number of any of the three kinds, no bool);
    a sympy value may still be refused there (a symbol, a complex number)."""
    return isinstance(value, numbers.Real | sp.Basic) and not isinstance(value, bool | np.bool_)


def _not_real(values):
    """The entries of nested lists and tuples that are no real numbers (strings, bools, complex), in order:
    numpy turns ``[0.5, "0.6"]`` into strings throughout, and the culprit is the second."""
    for value in values:
        if isinstance(value, list | tuple):
            yield from _not_real(value)
        elif isinstance(value, str | bytes | bool | np.bool_ | complex | np.complexfloating):
            yield value


def real_array(values, what: str, *, error: type = InvalidValueError) -> np.ndarray:
    """``values`` (a number, list or array of real numbers) as a float64 array, else ``error``.

    NaN and inf pass (callers decide what a missing or infinite value means); strings, bools,
    complex numbers and anything else are refused by name, before numpy would parse ``"0.5"`` as a
    number, count ``True`` as 1 or drop an imaginary part.

    Parameters
    ----------
    values : number, sequence or array
        Python, numpy or sympy numbers, nested to any depth.
    what : str
        The values' role in messages: ``"at(): times"``, ``"fit: data['x']"``.
    error : type
        The :class:`~daemodel.errors.ModelError` subclass to raise.

    Returns
    -------
    ndarray of float64, the shape of ``values``
    """
    if isinstance(values, str | bytes):
        raise error(f"{what} must be real numbers; got the string {quoted(values, 40)}")
    try:
        array = np.asarray(values)
    except (TypeError, ValueError) as exc:  # (ragged nesting)
        raise error(f"{what} must be an array of real numbers; got {type(values).__name__} ({exc})") from None
    kind = array.dtype.kind
    if kind in "fiu":
        return array.astype(np.float64)
    if kind == "O":  # (sympy numbers, mixed Python objects): each one checked as a single value is
        out = np.empty(array.shape)
        for index, value in np.ndenumerate(array):
            out[index] = real(value, f"{what}{list(index) if array.ndim else ''}", finite=False, error=error)
        return out
    described = {"b": "booleans", "c": "complex numbers", "U": "strings", "S": "byte strings"}.get(kind, array.dtype)
    first = next(_not_real(values), None) if isinstance(values, list | tuple) else None
    if first is None:  # (an array of them: its first)
        first = array.flat[0].item() if array.size else None
    hint = " (the imaginary part would be dropped)" if kind == "c" else ""
    raise error(f"{what} must be real numbers; got {described}{hint}, the first {quoted(first, 40)}")

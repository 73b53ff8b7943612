"""Checks of the options several methods share (numbers, tolerances, stages, dtype, threads, memory)."""

from __future__ import annotations

from daemodel.errors import InvalidOptionError
from daemodel.reals import real

# Meaningful relative tolerances: below ~50 eps of float64 no integrator can deliver (IDAS and
# RADAU5 stall there, and an adaptive solve runs until the step underflows); at or above 0.1 not
# even one digit is asked for.
RTOL_RANGE = (1e-14, 0.1)


def check_number(name: str, value, *, positive: bool = True, integer: bool = False, allow_none: bool = False):
    """``value`` as a Python float (int with ``integer=True``) or None, else :class:`InvalidOptionError`.

    Any real number is accepted: Python, numpy (``np.float32(0.05)``) or sympy (``sp.Rational(1, 20)``)
    (see :func:`daemodel.reals.real`); options store the returned value.
    """
    if value is None and allow_none:
        return None
    number = real(value, name, integer=integer, error=InvalidOptionError)
    if positive and number <= 0:
        raise InvalidOptionError(f"{name} must be positive; got {value!r}")
    return number


def set_number(options, name: str, **check) -> None:
    """:func:`check_number` on the option ``name`` of a frozen options dataclass, which then holds the
    returned Python number (casadi, torch and JSON take it as it is)."""
    object.__setattr__(options, name, check_number(name, getattr(options, name), **check))


def set_tolerances(options, **check) -> None:
    """:func:`check_tolerances` on ``options.rtol`` and ``options.atol``, stored as floats."""
    rtol, atol = check_tolerances(options.rtol, options.atol, **check)
    object.__setattr__(options, "rtol", rtol)
    object.__setattr__(options, "atol", atol)


def check_tolerances(rtol, atol, *, minimum_rtol: float = RTOL_RANGE[0]) -> tuple[float, float]:
    """``(rtol, atol)`` as floats; :class:`InvalidOptionError` unless ``rtol`` lies in :data:`RTOL_RANGE`
    and ``atol`` is positive."""
    rtol = check_number("rtol", rtol)
    atol = check_number("atol", atol)
    low, high = minimum_rtol, RTOL_RANGE[1]
    if not low <= rtol <= high:
        raise InvalidOptionError(
            f"rtol = {rtol:g} is outside the meaningful range [{low:g}, {high:g}]: "
            + (
                "float64 cannot deliver more digits; use rtol >= " + f"{low:g}"
                if rtol < low
                else "that asks for no correct digit; use rtol <= " + f"{high:g}"
            )
        )
    return rtol, atol


def check_stages(stages) -> None:
    if isinstance(stages, bool) or not isinstance(stages, int) or not 1 <= stages <= 7:
        raise InvalidOptionError(f"stages must be an integer from 1 to 7 (Radau IIA of order 2s-1); got {stages!r}")


def check_dtype(dtype) -> str:
    """Normalise ``"float64"``, ``"float32"`` or a torch dtype to its name."""
    name = str(dtype).removeprefix("torch.")
    if name not in ("float64", "float32"):
        raise InvalidOptionError(f"dtype must be 'float64' (default) or 'float32'; got {dtype!r}")
    return name


def check_threads(threads) -> None:
    """``threads`` is None or a positive integer, else :class:`InvalidOptionError`."""
    if threads is not None and (isinstance(threads, bool) or not isinstance(threads, int) or threads < 1):
        raise InvalidOptionError(f"threads must be a positive integer or None (chosen by the work); got {threads!r}")


def check_output_memory(method: str, compiled, samples: int, points: int, extra: int = 0) -> None:
    """Refuse, before allocating, a solve whose outputs (``samples`` x ``points`` x variables
    float64) and ``extra`` bytes exceed the memory limit (:func:`daemodel.files.check_memory`)."""
    from daemodel.files import check_memory

    D = len(compiled.states) + len(compiled.algebraics)
    parts = {"outputs": samples * points * D * 8} | ({"working set": extra} if extra else {})
    check_memory(f"{method} on {samples} sample(s) of {D} unknowns", parts)

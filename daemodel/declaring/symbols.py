"""The symbols a Model hands out (``m.states``, ``m.algebraics``, ``m.parameter``, ``m.t``).

They are sympy Symbols in every respect but one: a numeric function applied to one of them,
``math.sin(x)`` (which calls ``float(x)``) or ``np.sin(x)`` (which calls ``x.sin()``), raises
:class:`~daemodel.errors.NumericFunctionError` naming the symbol and the fix (sympy's function,
``sp.sin(x)``, or the equation as a string) instead of sympy's ``Cannot convert expression to
float`` or numpy's ``loop of ufunc does not support argument 0``.  On a compound expression
(``np.sin(2 * x)``) numpy and sympy answer before daemodel can: only the symbol itself is caught.

Everywhere else a declared ``x`` is ``sp.Symbol("x")``: sympy tells symbols apart by their type
(``Basic.__eq__``, ``subs``), so the class compares and hashes as ``sympy.Symbol`` (its
metaclass, :class:`_AsSympySymbol`) and carries the same name (sympy orders, prints and hashes
by the class's name).  A user's own ``sp.Symbol("x")`` equals the declared ``x``, substitutes
for it and is substituted by it, and fingerprints are those of plain sympy symbols.
"""

from __future__ import annotations

import sympy as sp

from daemodel.errors import NumericFunctionError

# numpy ufunc (the method numpy calls on an object) -> the sympy expression to write instead, of {x}
# (the string form of an equation is the same without "sp.").
NUMPY_TO_SYMPY = {
    **{name: f"sp.{name}({{x}})" for name in ("sin", "cos", "tan", "sinh", "cosh", "tanh", "exp", "log", "sqrt")},
    **{f"arc{name}": f"sp.a{name}({{x}})" for name in ("sin", "cos", "tan", "sinh", "cosh", "tanh")},
    "arctan2": "sp.atan2({x}, ...)",
    "hypot": "sp.sqrt({x}**2 + ...)",
    "exp2": "2**{x}",
    "expm1": "sp.exp({x}) - 1",
    "log2": "sp.log({x}, 2)",
    "log10": "sp.log({x}, 10)",
    "log1p": "sp.log(1 + {x})",
    "cbrt": "{x}**(1/3)",
    "floor": "sp.floor({x})",
    "ceil": "sp.ceiling({x})",
    "sign": "sp.sign({x})",
}


def _refuse(symbol: sp.Symbol, called: str, fix: str) -> NumericFunctionError:
    """The error for ``called`` on ``symbol``; ``fix``: the sympy expression to write instead."""
    as_string = fix.replace("sp.", "")
    return NumericFunctionError(
        f"{called} on the declared symbol '{symbol.name}', which has no value until the solve: write the equation "
        f'with sympy\'s functions, {fix} (import sympy as sp), or as a string, "{as_string}"'
    )


class _AsSympySymbol(type):
    """The type of :class:`Symbol`: equal to ``sympy.Symbol``, with its hash (see the module docs)."""

    def __eq__(cls, other):
        return other is cls or other is sp.Symbol

    def __ne__(cls, other):
        return not (other is cls or other is sp.Symbol)

    def __hash__(cls):
        return hash(sp.Symbol)


class Symbol(sp.Symbol, metaclass=_AsSympySymbol):
    """A declared variable, parameter or time: a :class:`sympy.Symbol` that refuses numeric functions by name."""

    __slots__ = ()

    def __new__(cls, name: str, **assumptions):
        # not through sympy's cache, whose key (cls, name) is equal to sympy.Symbol's and would hand
        # back a plain Symbol("x") made earlier
        cls._sanitize(assumptions, cls)
        return sp.Symbol.__xnew__(cls, name, **assumptions)

    def __float__(self):
        # math.sin(x), math.exp(x), float(x): Python asks the symbol for a float
        n = self.name
        raise _refuse(self, f"math.sin({n}), math.exp({n}), ... or float({n})", f"sp.sin({n}), sp.exp({n}), ...")


def _numpy_method(numpy_name: str, fix: str):
    def refuse(self, *args):
        called = f"np.{numpy_name}({self.name}{', ...' if args else ''})"
        raise _refuse(self, called, fix.format(x=self.name))

    refuse.__name__ = numpy_name
    refuse.__doc__ = f"``np.{numpy_name}(x)`` on a declared symbol: refused, naming ``{fix.format(x='x')}``."
    return refuse


for _numpy_name, _fix in NUMPY_TO_SYMPY.items():
    if not hasattr(sp.Symbol, _numpy_name):  # never shadow a sympy method
        setattr(Symbol, _numpy_name, _numpy_method(_numpy_name, _fix))

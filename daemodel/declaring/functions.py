"""The one table of functions daemodel understands, shared by the parser and both emitters.

Each row maps a sympy function class to its torch function and its casadi function.  A
function missing here is rejected by the parser (:mod:`daemodel.declaring.parse`: unknown function) and
by the emitters (unsupported function) with the function's and the equation's name.
"""

from __future__ import annotations

import casadi
import sympy as sp

from daemodel.errors import UnsupportedFunctionError

# sympy class -> (name in strings, torch attribute, casadi callable)
FUNCTIONS: dict[type, tuple[str, str, object]] = {
    sp.sin: ("sin", "sin", casadi.sin),
    sp.cos: ("cos", "cos", casadi.cos),
    sp.tan: ("tan", "tan", casadi.tan),
    sp.asin: ("asin", "asin", casadi.asin),
    sp.acos: ("acos", "acos", casadi.acos),
    sp.atan: ("atan", "atan", casadi.atan),
    sp.sinh: ("sinh", "sinh", casadi.sinh),
    sp.cosh: ("cosh", "cosh", casadi.cosh),
    sp.tanh: ("tanh", "tanh", casadi.tanh),
    sp.asinh: ("asinh", "asinh", casadi.asinh),
    sp.acosh: ("acosh", "acosh", casadi.acosh),
    sp.atanh: ("atanh", "atanh", casadi.atanh),
    sp.exp: ("exp", "exp", casadi.exp),
    sp.log: ("log", "log", casadi.log),
    sp.Abs: ("Abs", "abs", casadi.fabs),
    sp.sign: ("sign", "sign", casadi.sign),
    sp.erf: ("erf", "erf", casadi.erf),
    sp.atan2: ("atan2", "atan2", casadi.atan2),
    sp.floor: ("floor", "floor", casadi.floor),
    sp.ceiling: ("ceiling", "ceil", casadi.ceil),
}


def _maximum(a, b):
    """``Max(a, b)`` on casadi that passes a nan on, as numpy's maximum does: casadi's fmax returns the other
    argument (fmax(0, nan) = 0: u' = Max(0, sqrt(c - 2)) x at c = 1 was solved to u = 0 with "success").  Neither
    ordered (a nan): their sum, a nan; each if_else keeps its other branch out (0, not 0 times a nan)."""
    return casadi.if_else(a >= b, a, casadi.if_else(a < b, b, a + b))


def _minimum(a, b):
    """``Min(a, b)`` on casadi that passes a nan on (:func:`_maximum`)."""
    return casadi.if_else(a <= b, a, casadi.if_else(a > b, b, a + b))


def compared(piecewise) -> list:
    """The operands of the comparisons in ``piecewise``'s conditions that are not numbers, in the order of a
    preorder walk (one per operand met).  Where one is a nan no condition is true or false: sympy's Piecewise
    took the otherwise branch (nan > 0 is False in numpy, torch and casadi alike), and u' = Piecewise((1,
    sqrt(c - 2) > 0), (0, True)) x at c = 1 was solved to u = 0 with "success".  The emitters give a nan there
    (passed on as Max's and Min's are: :func:`_maximum`)."""
    return [
        side
        for pair in piecewise.args[:-1]
        for node in sp.preorder_traversal(pair.cond)
        if isinstance(node, sp.core.relational.Relational)
        for side in (node.lhs, node.rhs)
        if side.free_symbols
    ]


def ordered(a):
    """On casadi: 1 where ``a`` compares (is no nan), else 0 (``a == a`` simplifies to 1 there)."""
    return casadi.logic_or(a <= 0, a > 0)


# Two-argument-or-more reductions, folded pairwise.
REDUCTIONS: dict[type, tuple[str, str, object]] = {
    sp.Max: ("Max", "maximum", _maximum),
    sp.Min: ("Min", "minimum", _minimum),
}


def supported_names() -> str:
    """The functions users may write, for error messages."""
    names = sorted(n for n, _, _ in (*FUNCTIONS.values(), *REDUCTIONS.values()))
    return ", ".join([*names, "sqrt", "Piecewise"])


_LOGIC = (sp.And, sp.Or, sp.Not, sp.Piecewise, sp.logic.boolalg.BooleanAtom, sp.core.relational.Relational)
_ARITHMETIC = (sp.Add, sp.Mul, sp.Pow, sp.Symbol, sp.Rational, sp.Float, sp.NumberSymbol)


# Node types found translatable (a set lookup where isinstance over the supported classes cost 60 %
# of checking a model of 10^4 equations); Piecewise is never kept here: each one's branches are checked.
_SUPPORTED_TYPES: set = set()


def check_supported(expr: sp.Expr, where: str) -> None:
    """Raise :class:`UnsupportedFunctionError` for any node the emitters cannot translate."""
    stack = [expr]
    while stack:
        node = stack.pop()
        stack.extend(reversed(node.args))  # (preorder, as sympy's traversal: the first culprit is named)
        kind = type(node)
        if kind in _SUPPORTED_TYPES or isinstance(node, sp.functions.elementary.piecewise.ExprCondPair):
            continue
        if kind in FUNCTIONS or kind in REDUCTIONS or isinstance(node, _ARITHMETIC + _LOGIC):
            if isinstance(node, sp.Piecewise):
                if node.args[-1].cond != sp.true:
                    raise UnsupportedFunctionError(
                        f"{where}: Piecewise {node} has no otherwise branch; add (value, True) last "
                        "so the expression is defined everywhere"
                    )
            else:
                _SUPPORTED_TYPES.add(kind)
            continue
        name = getattr(node.func, "__name__", type(node).__name__)
        raise UnsupportedFunctionError(
            f"{where}: function '{name}' in {node} is not supported by the torch and casadi "
            f"emitters; rewrite it with the supported functions ({supported_names()})"
        )

"""One walk over a declared expression that answers every question the declaration asks of it.

Declaring an equation asks its expression which kinds of node it holds (a derivative, an
undefined function, ``ITE``, ``Heaviside``, an infinite or complex constant), which symbols it
uses, and whether its constants are finite: asked one at a time (``has``, ``atoms``,
``free_symbols``, a preorder traversal with ``is_number`` at every node), that is six walks of the
tree and a recursive query per node, most of the cost of a declaration beyond the user's own sympy
arithmetic.  :func:`scan` walks the tree once; the declaration asks sympy's own questions only where
the walk finds something to look at closer (and then gets sympy's answers and messages, unchanged).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import sympy as sp
from sympy.core.relational import Relational
from sympy.functions.elementary.piecewise import ExprCondPair
from sympy.logic.boolalg import BooleanAtom, BooleanFunction

# Nodes whose free symbols are the union of their arguments' (no bound variables) and whose
# ``is_number`` is that of all their arguments: where a tree holds only these, the walk's symbols
# are ``free_symbols`` and a node with a symbol beneath it is no number.
PLAIN = (
    sp.Add,
    sp.Mul,
    sp.Pow,
    sp.Symbol,
    sp.Number,
    sp.NumberSymbol,
    sp.Function,
    ExprCondPair,
    Relational,
    BooleanFunction,
)
# Atoms the walk passes without a closer look: symbols, exact and float numbers (checked finite
# here), truth values.
QUIET_ATOMS = (sp.Symbol, sp.Number, BooleanAtom)


@dataclass(frozen=True)
class Scan:
    """What one walk found in an expression.

    Attributes
    ----------
    classes : frozenset of type
        The type of every node.
    symbols : frozenset of sympy.Symbol or None
        ``expr.free_symbols`` where every node is :data:`PLAIN` (or a quiet atom), else None (ask sympy).
    numbers_plain : bool
        Every constant is a finite int, rational or float and no subtree free of symbols needs
        evaluating: ``check_numbers`` would pass without a question (False: ask it).
    """

    classes: frozenset
    symbols: frozenset | None
    numbers_plain: bool

    def holds(self, kind: type) -> bool:
        """Whether a node is an instance of ``kind`` (``expr.has(kind)``)."""
        return any(issubclass(c, kind) for c in self.classes)


def scan(expr: sp.Basic) -> Scan:
    """Walk ``expr`` once (each distinct node object once, without recursion) and return its :class:`Scan`."""
    classes: set = set()
    symbols: set = set()
    state = {"plain": True, "numbers": True}

    def atom(a) -> None:
        classes.add(type(a))
        if a.is_Symbol:
            symbols.add(a)
        elif a.is_Number:
            try:
                finite = math.isfinite(float(a))  # oo, -oo, nan (zoo and I are no Number)
            except OverflowError:
                finite = False
            state["numbers"] = state["numbers"] and finite
        elif not isinstance(a, QUIET_ATOMS):
            state["numbers"] = False  # pi, E, I, zoo, an atom of another kind: ask check_numbers
            state["plain"] = state["plain"] and isinstance(a, PLAIN)

    if not expr.args:
        atom(expr)
    stack, seen = ([expr] if expr.args else []), set()
    plain = numbers = True
    while stack:
        node = stack.pop()
        key = id(node)
        if key in seen:
            continue
        seen.add(key)
        classes.add(type(node))
        plain = plain and isinstance(node, PLAIN)
        # A subtree free of symbols (2*pi, sqrt(2), exp(1000)) has a node whose arguments are all atoms
        # and no symbol: there, check_numbers evaluates it.
        constant = True
        for a in node.args:
            if a.args:
                constant = False
                stack.append(a)
            else:
                constant = constant and not a.is_Symbol
                atom(a)
        numbers = numbers and not constant
    plain = plain and state["plain"]
    # (outside PLAIN, a node with a symbol beneath may still be a number: an integral over it)
    return Scan(frozenset(classes), frozenset(symbols) if plain else None, numbers and state["numbers"] and plain)

"""``str`` of many expressions, each shape of expression printed once: the fingerprint's text.

sympy's ``str`` sorts the terms of every sum and the factors of every product (0.3-0.6 ms an equation of
the reaction-diffusion grid: 7 s to save a solution of 10^4 unknowns, minutes at 10^5).  Expressions of
one shape (as :func:`~daemodel.compiling.numeric_source.shape_key` says: the same tree up to the symbols
at its leaves) whose leaves' names stand in the same order print the same text up to those names: sympy's
printer reads a name only to print it and to compare it with another symbol's (its sort keys compare
names as strings, ``c[10]`` before ``c[9]``).  So the first expression of each (shape, order of its
leaves' names) is printed with its leaves renamed to placeholders that sort as they do, and the others
are that text with their own names in the placeholders' places, character for character what ``str``
gives (tests/compiling/test_texts.py checks it against ``str``).

One difference from ``str``: a float whose text (15 digits for a float64) does not give its value back is
printed with the digits that do (:func:`exact_str`), so that y' = -0.1 y and y' = -0.10000000000000002 y do
not share a fingerprint; every other text is ``str``'s, and the fingerprint of a model whose coefficients
``str`` prints exactly is the one it had before.
"""

from __future__ import annotations

import re

import sympy as sp
from mpmath.libmp import repr_dps, to_str
from sympy.printing.str import StrPrinter

from daemodel.compiling.numeric_source import SHAPED, SHAPED_ATOMS

# A placeholder's name: a character no declared name holds (names are identifiers), then its rank among
# the expression's leaves, zero-padded so that the placeholders sort as their ranks.
MARK = "\x00"
_PLACEHOLDER = re.compile(MARK + r"(\d{7})")


class _ExactFloats(StrPrinter):
    """``str``'s printer, but a Float whose text does not give its value back prints the digits that do."""

    def _print_Float(self, expr):
        text = super()._print_Float(expr)
        if expr._prec < 5 or not expr.is_finite or sp.Float(text, precision=expr._prec)._mpf_ == expr._mpf_:
            return text
        return to_str(expr._mpf_, repr_dps(expr._prec), strip_zeros=True).removeprefix("+")


def exact_str(expr) -> str:
    """``str(expr)``, its floats printed with the digits that give their values back (see the module's
    docstring)."""
    return _ExactFloats({"order": None}).doprint(expr)


def texts(exprs, symbols) -> list[str]:
    """``[exact_str(e) for e in exprs]``, each shape printed once (see the module docstring).  ``symbols``: every
    symbol the expressions may hold (an expression with another, or with a node no shape describes, is
    printed on its own)."""
    names = set(symbols)
    classes = []  # per expression: (shape, leaves' names, their order) or None
    kinds: dict = {}  # node type -> whether a shape describes it (isinstance once per type)
    counts: dict = {}
    for expr in exprs:
        shape = _shape(expr, names, kinds) if len(expr.args) else None
        if shape is None or len(shape[1]) >= 10**7:
            classes.append(None)
            continue
        key, leaves = shape
        leaf_names = [s.name for s in leaves]
        order = tuple(sorted(range(len(leaves)), key=leaf_names.__getitem__))
        classes.append((key, order, leaves, leaf_names))
        counts[key, order] = counts.get((key, order), 0) + 1
    templates: dict = {}
    out = []
    for expr, found in zip(exprs, classes, strict=True):
        if found is None or counts[found[:2]] == 1:  # (printed on its own: no other of its class)
            out.append(exact_str(expr))
            continue
        key, order, leaves, leaf_names = found
        template = templates.get((key, order))
        if template is None:
            template = templates[(key, order)] = _template(expr, leaves, order)
        out.append(template[0] + "".join(leaf_names[i] + text for i, text in template[1]))
    return out


def _shape(expr, names: set, kinds: dict) -> tuple[tuple, list] | None:
    """:func:`~daemodel.compiling.numeric_source.shape_key` without shared subexpressions, each node type's
    kind looked up once (its ``isinstance`` tests were most of its 0.15 ms an equation of the grid)."""
    key: list = []
    leaves: dict = {}
    stack = [expr]
    while stack:
        node = stack.pop()
        kind = type(node)
        args = node._args
        if args:
            shaped = kinds.get(kind)
            if shaped is None:
                shaped = kinds[kind] = issubclass(kind, SHAPED)
            if not shaped:
                return None
            key.append((kind, len(args)))
            stack.extend(reversed(args))
        elif node.is_Symbol:
            if node not in names:
                return None
            key.append(leaves.setdefault(node, len(leaves)))  # (an int: no other token is one)
        else:
            atom = kinds.get(kind)
            if atom is None:
                atom = kinds[kind] = issubclass(kind, SHAPED_ATOMS)
            if not atom:
                return None
            key.append((kind, node._hashable_content()))
    return tuple(key), list(leaves)


def _template(expr, leaves: list, order: tuple) -> tuple[str, list]:
    """``expr`` printed with each leaf renamed to a placeholder of its rank (``order``: the leaves by name),
    split at the placeholders: ``(head, [(leaf index, text after it), ...])``."""
    rank = {leaf: r for r, leaf in enumerate(order)}
    swap = {leaves[i]: sp.Symbol(f"{MARK}{rank[i]:07d}", **leaves[i].assumptions0) for i in range(len(leaves))}
    printed = exact_str(expr.xreplace(swap))
    pieces = _PLACEHOLDER.split(printed)  # [text, rank, text, rank, ...]
    return pieces[0], [(order[int(pieces[k])], pieces[k + 1]) for k in range(1, len(pieces), 2)]

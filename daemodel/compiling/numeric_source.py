"""numpy source for :class:`~daemodel.compiling.init.NumericSystem`: sympy's SciPy printer, strict about
names (items of the generated function's arguments), printing shared subexpressions once and each
shape of expression once."""

from __future__ import annotations

import sympy as sp
from sympy.core.relational import Relational
from sympy.functions.elementary.piecewise import ExprCondPair
from sympy.logic.boolalg import ITE, BooleanFunction
from sympy.printing.numpy import SciPyPrinter

from daemodel.declaring.functions import compared

# lambdify's modules: scipy first, for the functions numpy lacks (erf would fall back to math.erf,
# which takes no arrays).
NUMERIC_MODULES = ["scipy", "numpy"]


# Terms of a sum printed in one chain at most (a longer sum prints as nested groups: _print_Add).
LONG_SUM = 256


class NumericPrinter(SciPyPrinter):
    """The printer lambdify builds for ``NUMERIC_MODULES``, with four changes.

    * Variables print as items of the generated function's arguments (``_y[3]``), names that no
      user name can be (they start with a letter) and that shadow nothing of numpy's or scipy's
      (a state named 'select'): lambdify's ``dummify=True`` instead substitutes one symbol at a
      time into the expressions (variables x expression size), and an ``xreplace`` rebuilds every
      node.  Four plain arguments also spare lambdify sorting hundreds of argument symbols.
    * A subexpression that occurs more than once prints as the name it is assigned to first
      (``shared``, from :func:`shared_subexpressions`): printed and evaluated once.
    * The terms of sums and products print in their stored order: sorting them (the default)
      costs more than the rest of the printing on large expressions and changes nothing but the
      order of rounding.
    * Expressions of one shape (the same tree up to which variables sit at its leaves: the
      equations of an array, of a loop) are printed once: the others are that text with their own
      variables' names in the placeholders' places (:func:`shape_key`).  The text is what printing
      each would give, character for character (printing reads the tree, never a name, except to
      print the name).
    """

    def __init__(self, names: dict, shared: dict, has_re: bool):
        settings = {"fully_qualified_modules": False, "inline": True, "allow_unknown_functions": True}
        super().__init__({**settings, "user_functions": {}, "order": "none"})
        self._names, self._shared, self._top, self._has_re = names, shared, False, has_re
        self._texts: dict = {}  # shape key -> the printed text split at its variables' placeholders

    def _handle_UnevaluatedExpr(self, expr):
        # the base class rewrites re(...) nodes with a walk over every expression it prints (each
        # shared subexpression again); without re there is nothing to rewrite
        return super()._handle_UnevaluatedExpr(expr) if self._has_re else expr

    def _print_Add(self, expr, order=None):
        # a long sum prints as nested groups of at most LONG_SUM terms: Python's compiler recurses once
        # per '+' of a chain, and a constraint of 3,000 terms (one row coupling a grid) stopped compile
        # with a RecursionError
        if len(expr.args) <= LONG_SUM:
            return super()._print_Add(expr, order)
        texts = [f"({self._print(term)})" for term in expr.args]
        while len(texts) > LONG_SUM:
            texts = [f"({' + '.join(texts[i : i + LONG_SUM])})" for i in range(0, len(texts), LONG_SUM)]
        return " + ".join(texts)

    def _print_Piecewise(self, expr):
        # (a nan compared in a condition: no branch holds, and the value is a nan, not the otherwise branch's, as
        # casadi's and torch's: functions.compared)
        sides = dict.fromkeys(compared(expr))
        if not sides or any(pair.cond.has(ITE) for pair in expr.args):
            return super()._print_Piecewise(expr)
        isnan = self._module_format(self._module + ".isnan")
        conds = [" | ".join(f"{isnan}({self._print(side)})" for side in sides)]
        conds += [self._print(pair.cond) for pair in expr.args]
        values = ["nan", *(self._print(pair.expr) for pair in expr.args)]
        select = self._module_format(self._module + ".select")
        return f"{select}([{','.join(conds)}], [{','.join(values)}], default=nan)"

    def doprint(self, expr, assign_to=None):
        text = None if assign_to is not None else self.shaped_text(expr)
        return self._doprint(expr, assign_to) if text is None else text

    def shaped_text(self, expr, shape=False) -> str | None:
        """The text of ``expr``, from the text of its shape (printed at the first expression of that
        shape); None for an expression of no shape (:func:`shape_key`).  ``shape``: its
        :func:`shape_key` with these names and shared subexpressions, where already known."""
        if self._has_re:
            return None
        if shape is False:
            shape = shape_key(expr, self._names, self._shared)
        if shape is None:
            return None
        key, leaves = shape
        pieces = self._texts.get(key)
        if pieces is None:
            # printed once with placeholders for its variables; split there (no name or number prints a NUL)
            names, self._names = self._names, {s: f"\0{k}\0" for k, s in enumerate(leaves)}
            try:
                pieces = self._doprint(expr, None).split("\0")
            finally:
                self._names = names
            pieces[1::2] = [int(k) for k in pieces[1::2]]
            self._texts[key] = pieces
        names = self._names
        return "".join(p if k % 2 == 0 else names[leaves[p]] for k, p in enumerate(pieces))

    def _doprint(self, expr, assign_to):
        self._top = True  # the expression itself prints in full, also when it is shared
        return super().doprint(expr, assign_to)

    def _print(self, expr, **kwargs):
        if self._top:
            self._top = False
        else:
            name = self._shared.get(expr)
            if name is not None:
                return name
        return super()._print(expr, **kwargs)

    def _print_Symbol(self, expr):
        name = self._names.get(expr)
        return name if name is not None else super()._print_Symbol(expr)


def shared_subexpressions(exprs) -> dict:
    """``{node: "_c<k>"}`` for the subexpressions to print once, in an order that defines each
    after the ones it uses.

    A node is shared when more than one parent refers to it (equal subtrees count as one node,
    whether sympy built them as one object or not).  The base of a shared negative power is
    shared too: a product prints ``a / b**(3/2)`` for ``a * b**(-3/2)``, a new power of that base.
    Evaluating a name instead of its expression changes no rounding.
    """
    parents: dict = {}
    order = []  # each node after its arguments

    def visit(node) -> None:
        if node in parents:
            parents[node] += 1
            return
        parents[node] = 1
        for arg in node.args:
            if not arg.is_Atom:
                visit(arg)
        order.append(node)

    for expr in exprs:
        if not expr.is_Atom:
            visit(expr)
    shared = {n for n in order if parents[n] > 1 and isinstance(n, sp.Expr)}
    shared |= {n.base for n in shared if n.is_Pow and n.exp.is_negative and not n.base.is_Atom}
    return {node: f"_c{k}" for k, node in enumerate(n for n in order if n in shared)}


# Nodes a shape key describes by their type and arguments alone (their printed text depends on nothing
# else); an expression with another kind of node is printed on its own.
SHAPED = (sp.Add, sp.Mul, sp.Pow, sp.Function, ExprCondPair, Relational, BooleanFunction)
# Atoms (besides variables) a shape key describes by their type and content: numbers, pi, true.
SHAPED_ATOMS = (sp.Number, sp.NumberSymbol, sp.logic.boolalg.BooleanAtom)


def shape_key(expr, names: dict, shared: dict) -> tuple[tuple, list] | None:
    """``(key, leaves)``: ``key`` equal for two expressions exactly where they are the same tree but for
    the variables at its leaves, ``leaves`` those variables in the order they first occur (preorder).
    None where the expression is no such tree (a node outside :data:`SHAPED`, a symbol that is not
    among ``names``) or holds a subexpression of ``shared`` (printed as its name)."""
    key: list = []
    leaves: dict = {}
    stack = [(expr, True)]
    while stack:
        node, top = stack.pop()
        if node.is_Symbol:
            if node not in names:
                return None
            key.append(leaves.setdefault(node, len(leaves)))  # (an int: no other token is one)
        elif not node.args:
            if not isinstance(node, SHAPED_ATOMS):
                return None
            key.append((type(node), node._hashable_content()))
        else:
            if not isinstance(node, SHAPED) or (not top and node in shared):
                return None
            key.append((type(node), len(node.args)))
            stack.extend((a, False) for a in reversed(node.args))
    return tuple(key), list(leaves)


def holds_re(exprs, shapes) -> bool:
    """Whether an expression of ``exprs`` holds an ``re`` node (``any(e.has(sp.re) for e in exprs)``),
    with ``shapes`` their :func:`shape_key` (or None): an expression of a shape is read from its key
    (the type of every node), each distinct key once, instead of walking its tree."""
    keys = set()
    for expr, shape in zip(exprs, shapes, strict=True):
        if shape is None:
            if expr.has(sp.re):
                return True
        else:
            keys.add(shape[0])
    return any(isinstance(token, tuple) and _is_re(token[0]) for key in keys for token in key)


def _is_re(kind) -> bool:
    return isinstance(kind, type) and issubclass(kind, sp.re)

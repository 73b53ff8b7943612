"""Equation strings to sympy expressions without evaluating any Python.

A string is parsed by Python's :mod:`ast` (which builds a syntax tree and runs nothing) and
the tree is walked here: only numbers, the declared names (an array's element as ``u[3]``), the
supported functions and constants of :mod:`daemodel.declaring.functions`, arithmetic (``+ - * / ** ^``),
comparisons and logic (for ``Piecewise`` conditions) are admitted, and the sympy expression is built
node by node.  Anything else (attribute access, other subscripts, lambdas, comprehensions, strings, keyword
arguments, calls of anything but a supported function) is an :class:`ExpressionParseError`
that names the equation and quotes the offending construct.

Sizes are bounded (:data:`MAX_CHARACTERS`, :data:`MAX_NODES`, :data:`MAX_DEPTH`) so that a
huge or deeply nested string is a named error, not a ``RecursionError``; chains of ``+``/``-``
and ``*``/``/`` are flattened, so a sum of thousands of terms is not deep.
"""

from __future__ import annotations

import ast
import math
import re
import sys

import sympy as sp

from daemodel.declaring.arrays import compact_listing, element_name
from daemodel.declaring.functions import FUNCTIONS, REDUCTIONS, supported_names
from daemodel.errors import DerivativeInEquationError, ExpressionParseError, UnknownSymbolError
from daemodel.messages import quoted

# Longest equation string accepted: far beyond any hand-written equation, small enough that
# parsing and checking stay well under a second.
MAX_CHARACTERS = 50_000
# Syntax-tree nodes accepted in one equation (a 3,000-term polynomial has ~15,000).
MAX_NODES = 50_000
# Nesting depth after flattening +/- and * / chains: parentheses, function calls and powers
# nested this deep are not an equation anyone writes, and sympy's recursive passes need headroom.
MAX_DEPTH = 100

# Names a string may use besides the model's symbols: function name -> sympy callable.
STRING_FUNCTIONS: dict[str, object] = {
    **{name: cls for cls, (name, _, _) in {**FUNCTIONS, **REDUCTIONS}.items()},
    "abs": sp.Abs,
    "sqrt": sp.sqrt,
    "ln": sp.log,
    "Piecewise": sp.Piecewise,
    "Heaviside": sp.Heaviside,  # (written as a Piecewise: without_heaviside)
    # sympy's exact-number constructors, which sympy users write: their arguments are numbers
    "Rational": sp.Rational,
    "Integer": sp.Integer,
}
STRING_CONSTANTS: dict[str, sp.Expr] = {"pi": sp.pi}
# Names that would read as derivatives: refused with the semi-explicit form's explanation.
DERIVATIVE_NAMES = ("diff", "Derivative")
# Reserved: no variable or parameter may take one of these names.
RESERVED_NAMES = frozenset({*STRING_FUNCTIONS, *STRING_CONSTANTS, *DERIVATIVE_NAMES, "t", "True", "False"})

# "y1'" in a string that Python cannot parse: a prime right after a name is a derivative, which
# a semi-explicit DAE keeps on the left-hand side only.
_PRIMED = re.compile(r"([A-Za-z_][A-Za-z0-9_]*)\s*'")

_BINARY = {
    ast.Add: lambda a, b: a + b,
    ast.Sub: lambda a, b: a - b,
    ast.Mult: lambda a, b: a * b,
    ast.Div: lambda a, b: a / b,
    ast.Pow: lambda a, b: a**b,
    ast.BitAnd: lambda a, b: sp.And(a, b),
    ast.BitOr: lambda a, b: sp.Or(a, b),
}
_COMPARE = {
    ast.Lt: sp.Lt,
    ast.LtE: sp.Le,
    ast.Gt: sp.Gt,
    ast.GtE: sp.Ge,
    ast.Eq: sp.Eq,
    ast.NotEq: sp.Ne,
}
_DESCRIBE = {
    ast.Attribute: "attribute access",
    ast.Subscript: "subscript",
    ast.Lambda: "lambda",
    ast.ListComp: "list comprehension",
    ast.SetComp: "set comprehension",
    ast.DictComp: "dict comprehension",
    ast.GeneratorExp: "generator expression",
    ast.List: "list",
    ast.Dict: "dict",
    ast.Set: "set",
    ast.JoinedStr: "f-string",
    ast.NamedExpr: "assignment expression",
    ast.IfExp: "conditional expression (use Piecewise)",
    ast.Starred: "starred argument",
    ast.Await: "await",
    ast.Yield: "yield",
    ast.YieldFrom: "yield",
    ast.Slice: "slice",
}


def parse_equation(text: str, symbols: dict[str, sp.Symbol], where: str, shapes: dict | None = None) -> sp.Expr:
    """Parse one equation string over ``symbols`` (name -> Symbol, including ``t``).

    Parameters
    ----------
    text : str
        E.g. ``"-k*x + sin(t)"`` or ``"Piecewise((1, x > 0), (-1, True))"``.
    symbols : dict name -> sympy.Symbol
        Every name the equation may use.
    where : str
        How messages refer to the equation, e.g. ``"the ODE for 'x' (#1)"``.
    shapes : dict name -> tuple of int, optional
        The declared arrays' shapes, for messages: ``u[3]`` and ``T[3, 4]`` (non-negative integer
        indices) are the elements ``u[3]`` and ``T[3,4]`` of ``symbols``, an index out of an array's
        range is named as such, and any other subscript is refused.

    Raises
    ------
    ExpressionParseError
        Not an expression, a construct outside the admitted set, a number that is not a
        finite float64, too large or too deeply nested.
    UnknownSymbolError
        A name that is neither declared nor a supported function or constant.
    DerivativeInEquationError
        ``diff(...)`` or ``Derivative(...)``.
    """
    return _Parser(text, symbols, where, shapes or {}).parse()


class _Parser:
    """One parse: the source (for quoting constructs), the names, and a node budget."""

    def __init__(self, text: str, symbols: dict, where: str, shapes: dict):
        self.text, self.symbols, self.where, self.shapes = text, symbols, where, shapes
        self.nodes = 0

    def fail(self, why: str, cls=ExpressionParseError):
        return cls(f"{self.where}: cannot parse {quoted(self.text)}: {why}")

    def segment(self, node) -> str | None:
        """The source text of ``node``: sliced by offsets (ast.get_source_segment re-splits the whole
        text on every call, quadratic in a long sum of numbers)."""
        if self.text.isascii() and node.lineno == node.end_lineno == 1:
            return self.text[node.col_offset : node.end_col_offset]
        return ast.get_source_segment(self.text, node)

    def quote(self, node) -> str:
        segment = self.segment(node) or type(node).__name__
        return quoted(segment)

    def parse(self) -> sp.Expr:
        if len(self.text) > MAX_CHARACTERS:
            raise self.fail(f"{len(self.text)} characters is more than the {MAX_CHARACTERS} an equation may have")
        if not self.text.strip():
            raise self.fail("the string is empty")
        # '^' means power in equations (sympy's convert_xor), with the precedence of '**'
        self.text = self.text.strip().replace("^", "**")
        # CPython builds the tree of a long chain a + b + c + ... recursively, one level per
        # operator, under the interpreter's recursion limit: lift it for the parse (the length
        # bound above keeps that depth small enough for the C stack).
        limit = sys.getrecursionlimit()
        try:
            sys.setrecursionlimit(max(limit, len(self.text) + 1000))
            tree = ast.parse(self.text, mode="eval")
        except SyntaxError as error:
            primed = _PRIMED.search(self.text)
            if primed:
                raise DerivativeInEquationError(
                    f"{self.where}: derivative {primed.group(0).strip()} in {quoted(self.text)}; a semi-explicit "
                    "DAE has derivatives only on the left (declare them with m.ode)"
                ) from None
            raise self.fail(f"not a Python-syntax expression ({error.msg})") from None
        except (RecursionError, MemoryError, ValueError) as error:
            raise self.fail(f"the expression is too deeply nested or malformed ({type(error).__name__})") from None
        finally:
            sys.setrecursionlimit(limit)
        try:
            return without_ite(self.build(tree.body, 0))
        except RecursionError:
            raise self.fail(f"nested more than {MAX_DEPTH} levels deep") from None

    def build(self, node, depth: int):
        self.nodes += 1
        if self.nodes > MAX_NODES:
            raise self.fail(f"more than {MAX_NODES} syntax nodes; split it into aliases (algebraic variables)")
        if depth > MAX_DEPTH:
            raise self.fail(f"nested more than {MAX_DEPTH} levels deep")
        if isinstance(node, ast.Constant):
            return self.constant(node)
        if isinstance(node, ast.Name):
            return self.name(node)
        if isinstance(node, ast.BinOp):
            return self.binary(node, depth)
        if isinstance(node, ast.UnaryOp):
            operand = self.build(node.operand, depth + 1)
            if isinstance(node.op, ast.USub):
                return self.apply(lambda v: -v, (operand,), node)
            if isinstance(node.op, ast.UAdd):
                return operand
            return self.apply(sp.Not, (self.condition(operand, node.operand),), node)  # 'not x' and '~x'
        if isinstance(node, ast.BoolOp):
            values = [self.condition(self.build(v, depth + 1), v) for v in node.values]
            return self.construct(sp.And if isinstance(node.op, ast.And) else sp.Or, values, node)
        if isinstance(node, ast.Compare):
            return self.compare(node, depth)
        if isinstance(node, ast.Call):
            return self.call(node, depth)
        if isinstance(node, ast.Subscript) and isinstance(node.value, ast.Name):
            element = self.element(node)
            if element is not None:
                return element
        if isinstance(node, ast.Tuple):
            raise self.fail(f"a tuple {self.quote(node)} is only allowed as a (value, condition) pair of Piecewise")
        what = _DESCRIBE.get(type(node), f"the construct '{type(node).__name__}'")
        raise self.fail(
            f"{what} {self.quote(node)} is not allowed in an equation; equations use numbers, declared names, "
            f"arithmetic, comparisons and the functions {supported_names()}"
        )

    def constant(self, node):
        value = node.value
        if isinstance(value, bool):
            return sp.true if value else sp.false
        if isinstance(value, int):
            if abs(value) > 2**1023:
                raise self.fail(f"the number {self.quote(node)} is not a finite float64")
            return sp.Integer(value)
        if isinstance(value, float):
            literal = self.segment(node) or repr(value)
            if not math.isfinite(value):
                raise self.fail(f"the number {quoted(literal)} overflows float64 (largest ~1.8e308)")
            if value == 0.0 and any(d in literal.lower().split("e")[0] for d in "123456789"):
                raise self.fail(f"the number {quoted(literal)} underflows float64 to 0; write 0 if you mean it")
            return sp.Float(literal.replace("_", ""))
        kind = "string" if isinstance(value, str | bytes) else type(value).__name__
        raise self.fail(f"a {kind} constant {self.quote(node)} is not a number")

    def name(self, node):
        name = node.id
        if name in self.symbols:
            return self.symbols[name]
        if name in STRING_CONSTANTS:
            return STRING_CONSTANTS[name]
        if name in STRING_FUNCTIONS:
            raise self.fail(f"'{name}' is a function: call it, e.g. {name}(x)")
        if name in DERIVATIVE_NAMES:
            raise self._derivative(node)
        if name in self.shapes:
            raise self.whole_array(name)
        declared = compact_listing(sorted(self.symbols, key=lambda n: n == "t"))  # (t last)
        raise UnknownSymbolError(f"{self.where}: unknown name(s) '{name}' in {quoted(self.text)}; declared: {declared}")

    def whole_array(self, name: str) -> ExpressionParseError:
        """The error for an array's name used as a value (``2*u``) or called (``u(3)``)."""
        zeros = ", ".join("0" * len(self.shapes[name]))
        return self.fail(
            f"'{name}' is an array of shape {self.shapes[name]}: an equation takes its elements, e.g. "
            f"{name}[{zeros}] (an array of equations: m.ode({name}, exprs), m.constraint(exprs))"
        )

    def element(self, node):
        """``u[3]``, ``T[3, 4]``: an element of a declared array, by non-negative integer literals; None
        for a subscript of a name that is no array (refused as a subscript)."""
        name = node.value.id
        items = node.slice.elts if isinstance(node.slice, ast.Tuple) else [node.slice]
        index = tuple(i.value for i in items if isinstance(i, ast.Constant) and type(i.value) is int)
        element = f"{name}[{','.join(map(str, index))}]"
        if len(index) == len(items) and element in self.symbols:  # (an element among the symbols: also
            return self.symbols[element]  # where no shapes are given, e.g. a solution's names)
        if name not in self.shapes:
            return None
        if len(index) != len(items):
            raise self.fail(
                f"the subscript {self.quote(node)} is not allowed: an array's element is written with integer "
                f"indices, e.g. {name}[{', '.join('0' * len(self.shapes[name]))}]"
            )
        element = element_name(name, index, self.shapes[name], self.where)  # (raises: out of range)
        raise UnknownSymbolError(f"{self.where}: unknown name '{element}' in {quoted(self.text)}")

    def binary(self, node, depth: int):
        op = type(node.op)
        if op not in _BINARY:
            symbol = {ast.Mod: "%", ast.FloorDiv: "//", ast.MatMult: "@", ast.LShift: "<<", ast.RShift: ">>"}
            raise self.fail(f"the operator '{symbol.get(op, op.__name__)}' in {self.quote(node)} is not supported")
        if op in (ast.Add, ast.Sub, ast.Mult, ast.Div):
            # a left-deep chain a + b - c + ... is one level, however long
            family = (ast.Add, ast.Sub) if op in (ast.Add, ast.Sub) else (ast.Mult, ast.Div)
            chain, left = [], node
            while isinstance(left, ast.BinOp) and isinstance(left.op, family):
                chain.append((type(left.op), left.right))
                left = left.left
            first = self.build(left, depth + 1)
            rest = [(kind, self.build(right, depth + 1)) for kind, right in reversed(chain)]
            combine = sp.Add if family[0] is ast.Add else sp.Mul

            def fold(first, *rest):
                terms = [-v if kind is ast.Sub else (1 / v if kind is ast.Div else v) for kind, v in rest]
                return combine(first, *terms)

            return self.apply(fold, (first, *rest), node)
        left, right = self.build(node.left, depth + 1), self.build(node.right, depth + 1)
        if op in (ast.BitAnd, ast.BitOr):
            left, right = self.condition(left, node.left), self.condition(right, node.right)
        return self.apply(_BINARY[op], (left, right), node)

    def condition(self, value, node):
        """``value`` if it is a condition (a comparison or logic of comparisons): sympy would read
        a number or a variable in ``x and 1`` as a truth value and return plain ``x``."""
        if isinstance(value, sp.core.relational.Relational | sp.logic.boolalg.BooleanFunction) or value in (
            sp.true,
            sp.false,
        ):
            return value
        raise self.fail(
            f"{self.quote(node)} is not a condition: 'and', 'or', 'not', '&', '|' and '~' combine comparisons "
            "such as x > 0"
        )

    def compare(self, node, depth: int):
        values = [self.build(node.left, depth + 1), *(self.build(c, depth + 1) for c in node.comparators)]
        parts = []
        for op, a, b in zip(node.ops, values, values[1:], strict=False):
            if type(op) not in _COMPARE:
                raise self.fail(f"the comparison '{type(op).__name__}' in {self.quote(node)} is not supported")
            parts.append(self.apply(_COMPARE[type(op)], (a, b), node))
        return parts[0] if len(parts) == 1 else self.construct(sp.And, parts, node)

    def call(self, node, depth: int):
        if not isinstance(node.func, ast.Name):
            raise self.fail(f"only supported functions may be called; {self.quote(node.func)} is not one")
        name = node.func.id
        if name in DERIVATIVE_NAMES:
            raise self._derivative(node)
        if name in self.shapes:
            raise self.whole_array(name)
        # the arguments first: a hostile call such as open('f', 'w') fails on its string argument
        if name == "Piecewise":
            args = [self.piece(a, depth) for a in node.args]
            if not args or args[-1][1] != sp.true:
                raise self.fail(
                    f"{self.quote(node)} has no otherwise branch; add (value, True) last so that it is defined "
                    "everywhere"
                )
        else:
            args = [self.build(a, depth + 1) for a in node.args]
        if name not in STRING_FUNCTIONS:
            if name in self.symbols:
                raise self.fail(f"'{name}' is a variable, not a function: {self.quote(node)}")
            raise UnknownSymbolError(
                f"{self.where}: unknown function(s) {name} in {quoted(self.text)}; the supported functions are "
                f"{supported_names()}"
            )
        if node.keywords:
            raise self.fail(f"keyword arguments in {self.quote(node)} are not allowed")
        return self.apply(STRING_FUNCTIONS[name], args, node)

    def piece(self, node, depth: int):
        if not isinstance(node, ast.Tuple) or len(node.elts) != 2:
            raise self.fail(f"each Piecewise argument must be a pair (value, condition); got {self.quote(node)}")
        value, condition = node.elts
        return (self.build(value, depth + 1), self.condition(self.build(condition, depth + 1), condition))

    def construct(self, cls, args, node):
        return self.apply(lambda *a: cls(*a), args, node)

    def apply(self, fn, args, node):
        """Call a sympy constructor; its TypeError/ValueError (wrong arity, a condition where a
        value belongs, ...) becomes an error naming the construct."""
        try:
            return fn(*args)
        except (TypeError, ValueError, AttributeError, ZeroDivisionError) as error:
            first = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
            raise self.fail(f"{self.quote(node)} is not a valid expression ({quoted(first, 160)})") from None
        except RecursionError:
            raise self.fail(f"nested more than {MAX_DEPTH} levels deep") from None

    def _derivative(self, node):
        return DerivativeInEquationError(
            f"{self.where}: derivative {self.quote(node)} in {quoted(self.text)}; a semi-explicit DAE has "
            "derivatives only on the left (declare them with m.ode)"
        )


def without_ite(expr):
    """``expr`` with sympy's boolean ``ITE(c, a, b)`` (which it makes of a Piecewise inside a
    comparison) written as ``(c & a) | (~c & b)``, which every emitter translates."""
    if not isinstance(expr, sp.Basic) or not expr.has(sp.ITE):
        return expr
    return expr.replace(
        lambda e: isinstance(e, sp.ITE),
        lambda e: sp.Or(sp.And(e.args[0], e.args[1]), sp.And(sp.Not(e.args[0]), e.args[2])),
    )


def without_heaviside(expr):
    """``expr`` with ``Heaviside(x, h0)`` written as ``Piecewise((0, x < 0), (h0, x = 0), (1, True))``
    (sympy's value at 0, 1/2 unless given), which every emitter translates and :mod:`daemodel.solving.switches`
    reads as a switch of x."""
    if not isinstance(expr, sp.Basic) or not expr.has(sp.Heaviside):
        return expr
    return expr.replace(
        lambda e: isinstance(e, sp.Heaviside),
        lambda e: sp.Piecewise(
            (0, e.args[0] < 0), (e.args[1] if len(e.args) > 1 else sp.S.Half, sp.Eq(e.args[0], 0)), (1, True)
        ),
    )


def check_numbers(expr: sp.Expr, where: str) -> None:
    """Refuse an expression whose constant parts are not finite real float64 values.

    ``1/0`` (zoo), ``sqrt(-1)`` (I), ``exp(1000)`` (overflows when evaluated) and ``oo`` would
    reach the generated code as ``inf``/``nan`` or complex numbers and fail, or silently
    poison, every evaluation.
    """
    if expr.has(sp.zoo, sp.oo, -sp.oo, sp.nan, sp.I):
        raise ExpressionParseError(
            f"{where}: {quoted(str(expr))} contains an infinite, undefined or complex constant "
            "(e.g. 1/0 or sqrt(-1)); equations must be real and finite"
        )
    for node in sp.preorder_traversal(expr):
        if isinstance(node, sp.Expr) and node.is_number and not node.is_Number:
            try:
                value = complex(node)
            except (TypeError, ValueError, OverflowError):
                value = complex(math.inf)
            if not (math.isfinite(value.real) and abs(value.imag) <= 1e-12 * max(1.0, abs(value.real))):
                shown = value.real if not value.imag else value
                raise ExpressionParseError(
                    f"{where}: the constant {quoted(str(node))} evaluates to {shown}, not a finite real float64"
                )
        elif isinstance(node, sp.Number) and not math.isfinite(float(node)):
            raise ExpressionParseError(f"{where}: the number {quoted(str(node))} is not a finite float64")

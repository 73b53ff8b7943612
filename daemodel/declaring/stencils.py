"""Stencils: an array expression recorded once, as one sympy template over placeholders.

Numpy's arithmetic on the object arrays of :meth:`~daemodel.declaring.model.Declaration.states`
builds one sympy tree per element, one evaluated operation at a time: at 10^5 unknowns that
arithmetic alone is most of the cost of a model.  A :class:`Stencil` records the same arithmetic
once: ``C = stencil(np.array([0, *c, 0], dtype=object))``; ``D * (C[:-2] - 2 * C[1:-1] + C[2:])``
is one sympy expression ``D*(a - 2*b + e)`` over three placeholders (``a``, ``b``, ``e``), each with
the array whose elements it stands for (the shifted views ``c[:-2]``, ``c[1:-1]``, ``c[2:]``): the
leaves.  ``m.ode(c, rhs)`` and ``m.constraint(rhs, name=...)`` take a stencil as they take an array.

The element expressions are made by :func:`expand`, equal (``==``, the same tree) to those numpy's
arithmetic builds.  Where an element's placeholders stand for distinct symbols, distinct from the
template's own, renaming the template's symbols changes no step of sympy's evaluation of sums,
products and powers (their evaluation asks which terms are equal and of which type, never their
names), only the order of their arguments: each sum and product is rebuilt with its arguments
sorted by sympy's own key, without evaluating it again.  Other nodes (functions) are evaluated, and
an element whose function evaluates to another tree, or whose placeholder stands for a number or
for the same symbol as another, is made by sympy's ``xreplace`` (evaluated, as numpy's arithmetic).
"""

from __future__ import annotations

import gc
import numbers
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from functools import cmp_to_key

import numpy as np
import sympy as sp

from daemodel.errors import ExpressionParseError, ShapeError

# The order sympy's evaluation gives the arguments of a sum or product (sympy's own ``_args_sortkey``).
ARGUMENT_ORDER = cmp_to_key(sp.Basic.compare)


class Stencil:
    """An array of expressions recorded as one template (see the module docs).

    Attributes
    ----------
    template : sympy.Expr
        The expression of every element, over the placeholders of ``leaves``.
    leaves : dict sympy.Dummy -> numpy.ndarray
        Each placeholder's array (of sympy symbols and numbers, of ``shape``).
    shape : tuple of int
    """

    __slots__ = ("leaves", "shape", "template")
    __array_ufunc__ = None  # numpy array (op) stencil: numpy defers to the stencil's reflected operator

    def __init__(self, template: sp.Expr, leaves: dict, shape: tuple):
        self.template, self.leaves, self.shape = template, leaves, shape

    @property
    def ndim(self) -> int:
        return len(self.shape)

    @property
    def size(self) -> int:
        return int(np.prod(self.shape))

    def __repr__(self) -> str:
        return f"Stencil(shape={self.shape}, {self.template})"

    def __getitem__(self, index) -> Stencil:
        """The same expression on the elements ``index`` selects (numpy's indexing of every leaf)."""
        try:
            leaves = {p: a[index] for p, a in self.leaves.items()}
            shape = np.empty(self.shape, dtype=np.int8)[index].shape
        except IndexError as err:
            raise ShapeError(f"stencil of shape {self.shape}: index {index!r} is out of range ({err})") from None
        if not shape or 0 in shape:
            raise ShapeError(
                f"stencil of shape {self.shape}: index {index!r} selects shape {shape}; a stencil keeps at least "
                "one element on at least one axis (a slice such as [3:4] keeps the axis)"
            )
        return Stencil(self.template, leaves, shape)

    def apply(self, function: Callable, *others) -> Stencil:
        """``function(self, *others)`` element by element, for a sympy function (``sp.exp``, ``sp.atan2``):
        ``others`` are stencils of the same shape, sympy expressions or numbers."""
        operands = [self, *(as_operand(o, f"apply({getattr(function, '__name__', function)})") for o in others)]
        return combine(operands, lambda *exprs: function(*exprs), f"apply({getattr(function, '__name__', function)})")

    def __neg__(self) -> Stencil:
        return Stencil(-self.template, self.leaves, self.shape)

    def __pos__(self) -> Stencil:
        return self


def _binary(op: Callable, symbol: str, reflected: bool):
    def method(self, other):
        operand = as_operand(other, f"stencil {symbol}", none=True)
        if operand is None:
            return NotImplemented
        return combine([operand, self] if reflected else [self, operand], op, f"stencil {symbol}")

    method.__doc__ = f"``a {symbol} b`` element by element (the template once)."
    return method


for _name, (_symbol, _op) in {
    "add": ("+", lambda a, b: a + b),
    "sub": ("-", lambda a, b: a - b),
    "mul": ("*", lambda a, b: a * b),
    "truediv": ("/", lambda a, b: a / b),
    "pow": ("**", lambda a, b: a**b),
}.items():
    setattr(Stencil, f"__{_name}__", _binary(_op, _symbol, False))
    setattr(Stencil, f"__r{_name}__", _binary(_op, _symbol, True))


def stencil(array) -> Stencil:
    """``array`` (of declared symbols and numbers, such as the array ``m.states("u", n)`` returned, a
    slice of it, or one padded with boundary values) as a :class:`Stencil` of one placeholder."""
    if isinstance(array, Stencil):
        return array
    values = np.asarray(array, dtype=object)
    if values.ndim == 0 or values.size == 0:
        raise ShapeError(f"stencil: needs an array of at least one element; got shape {values.shape}")
    flat = values.ravel()
    out = np.empty(flat.size, dtype=object)
    for k, value in enumerate(flat):
        if isinstance(value, sp.Symbol | sp.Number):
            out[k] = value
        elif isinstance(value, numbers.Real) and not isinstance(value, bool):
            out[k] = sp.sympify(value)
        else:
            where = np.unravel_index(k, values.shape)
            raise ExpressionParseError(
                f"stencil: element {tuple(map(int, where))} is {value!r} ({type(value).__name__}); a stencil's array "
                "holds declared symbols and numbers (combine arrays with +, -, *, /, ** and .apply)"
            )
    out = out.reshape(values.shape)
    out.flags.writeable = False
    placeholder = sp.Dummy("s")
    return Stencil(placeholder, {placeholder: out}, values.shape)


def as_operand(value, what: str, none: bool = False):
    """``value`` as a stencil or a scalar sympy expression; ``none``: None for what is neither."""
    if isinstance(value, Stencil):
        return value
    if isinstance(value, np.ndarray):
        return stencil(value)
    if isinstance(value, sp.Basic | numbers.Number) and not isinstance(value, bool):
        return sp.sympify(value)
    if none:
        return None
    raise ExpressionParseError(f"{what}: {value!r} is neither a stencil, an array nor a scalar expression")


def _view_key(array: np.ndarray) -> tuple:
    """Equal for two views of the same elements of one array (its data, shape and strides)."""
    return array.__array_interface__["data"][0], array.shape, array.strides


def combine(operands: list, op: Callable, what: str) -> Stencil:
    """``op`` of the operands' templates, their leaves merged (one placeholder per view of the same elements)."""
    shapes = {o.shape for o in operands if isinstance(o, Stencil)}
    if len(shapes) > 1:
        raise ShapeError(
            f"{what}: operands of shapes {' and '.join(map(str, sorted(shapes)))}; stencils combine "
            "element by element and need one shape (slice them to it)"
        )
    leaves, by_key, exprs = {}, {}, []
    for operand in operands:
        if not isinstance(operand, Stencil):
            exprs.append(operand)
            continue
        renamed = {}
        for placeholder, array in operand.leaves.items():
            key = _view_key(array)
            if key in by_key:  # (the same elements: the same placeholder)
                if by_key[key] is not placeholder:
                    renamed[placeholder] = by_key[key]
                continue
            if placeholder in leaves:  # (a slice of the same stencil: other elements, a placeholder of its own)
                renamed[placeholder] = placeholder = sp.Dummy("s")
            by_key[key] = placeholder
            leaves[placeholder] = array
        exprs.append(operand.template.xreplace(renamed) if renamed else operand.template)
    template = op(*exprs)
    if not isinstance(template, sp.Expr):
        raise ExpressionParseError(f"{what}: the result {template!r} is not a sympy expression")
    return Stencil(template, leaves, shapes.pop())


def leaf_symbols(s: Stencil) -> set:
    """Every symbol of the stencil's leaves (for the model's check that it declared them)."""
    out = set()
    for array in s.leaves.values():
        out.update(v for v in array.flat if v.is_Symbol)
    return out


def _program(template: sp.Expr, placeholders: dict) -> list:
    """The template's nodes in post-order, each an instruction of :func:`_run`."""
    program, index, holders = [], {}, set(placeholders)

    def visit(node) -> int:
        if node in index:
            return index[node]
        if node in placeholders:
            step = ("leaf", placeholders[node])
        elif not (node.free_symbols & holders):
            step = ("constant", node)
        else:
            args = tuple(visit(a) for a in node.args)
            if node.is_Add or node.is_Mul:
                step = ("sorted", node.func, args, node.args[0].is_Number)
            elif node.is_Pow:
                step = ("pow", node.func, args)
            else:
                step = ("evaluated", node.func, args)
        program.append(step)
        index[node] = len(program) - 1
        return index[node]

    visit(template)
    return program


def _power(base, exponent) -> sp.Pow:
    """``base**exponent`` as ``Pow(base, exponent, evaluate=False)`` builds it, less its argument checks
    (both are sympy expressions already; no constructor postprocessor applies to plain symbols)."""
    power = sp.Expr.__new__(sp.Pow, base, exponent)
    power.is_commutative = base.is_commutative and exponent.is_commutative
    return power


def _run(program: list, columns: list, k: int, orders: list | None):
    """Element ``k`` of the template by ``program``, or None where a function evaluates to another tree.

    ``orders``: the order of each sum's and product's arguments (positions into the renamed ones), from
    an element whose symbols' names are in the same order (:func:`_name_orders`); an empty list: sort
    them by :data:`ARGUMENT_ORDER` and append each order to it.
    """
    values, sums, record = [], 0, orders is not None and not orders
    for step in program:
        kind = step[0]
        if kind == "leaf":
            values.append(columns[step[1]][k])
        elif kind == "constant":
            values.append(step[1])
        elif kind == "sorted":
            args = [values[i] for i in step[2]]
            if orders is not None and not record:
                args = [args[i] for i in orders[sums]]
            else:
                start = 1 if step[3] else 0  # (the number stays first, as sympy's evaluation puts it)
                order = [*range(start), *sorted(range(start, len(args)), key=lambda i: ARGUMENT_ORDER(args[i]))]
                args = [args[i] for i in order]
                if record:
                    orders.append(order)
            sums += 1
            values.append(step[1]._from_args(args, True))
        elif kind == "pow":
            values.append(_power(values[step[2][0]], values[step[2][1]]))
        else:
            args = tuple(values[i] for i in step[2])
            value = step[1](*args)
            if value.func is not step[1] or value.args != args:
                return None
            values.append(value)
    return values[-1]


# Most symbols per element whose order by name :func:`_name_orders` encodes (a bit per pair, in an int64).
MAX_ORDERED = 11


def _name_orders(columns: list, fixed: tuple, slow: np.ndarray) -> np.ndarray | None:
    """Per element, the order of its symbols' names as one integer (a bit per pair), or None.

    Sympy orders two plain symbols (:func:`_plain`) by their names, so a renamed element's arguments
    are in the order of another's wherever its symbols' names are: the sort is done once per order
    of names.  None where the symbols are too many.
    """
    count = len(columns) + len(fixed)
    if count > MAX_ORDERED:
        return None
    names = [np.array([v.name if v.is_Symbol else "" for v in column]) for column in columns]
    names += [np.full(len(slow), v.name) for v in fixed]
    code, bit = np.zeros(len(slow), dtype=np.int64), 0
    for i in range(count):
        for j in range(i + 1, count):
            code |= (names[i] < names[j]).astype(np.int64) << bit
            bit += 1
    return code


@contextmanager
def paused_collection() -> Iterator[None]:
    """Python's cyclic garbage collector paused (and restored as it was) while a block builds 10^5 trees:
    its full collections walk every object alive, more of them as the model grows (at 10^5 unknowns,
    2.7 of 4.9 s of CPU declaring the reaction-diffusion family).  Sympy trees hold no cycles: nothing
    waits longer to be freed than until the collector runs again.

    On leaving, what the block made is moved to the oldest generation unscanned (``gc.freeze()`` then
    ``gc.unfreeze()``, where nothing was frozen before): else the first allocation after would scan it
    all as the youngest generation (0.6 of 7 s compiling at 10^5 unknowns)."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            if gc.get_freeze_count() == 0:  # (a caller's frozen objects stay frozen)
                gc.freeze()
                gc.unfreeze()
            gc.enable()


# What a symbol of no assumptions (as the model declares them) says of itself.
PLAIN_ASSUMPTIONS = sp.Symbol("x").assumptions0


def _plain(symbol) -> bool:
    """A sympy Symbol (by class name, as sympy orders classes) of no assumptions: the kind a model declares,
    and the kind the template's placeholders are (an assumption, ``positive``, changes evaluation)."""
    return type(symbol).__name__ == "Symbol" and symbol.assumptions0 == PLAIN_ASSUMPTIONS


def expand(s: Stencil) -> tuple[list, list]:
    """The stencil's element expressions in numpy's (C) order, equal to numpy's arithmetic's (module
    docs), and the free symbols of each where renaming made it (None where sympy evaluated it: a
    placeholder of a number, two of one symbol, a function that evaluates to another tree)."""
    placeholders = list(s.leaves)
    columns = [s.leaves[p].ravel() for p in placeholders]
    fixed = s.template.free_symbols - set(placeholders)
    codes_of: dict = {}
    own = [codes_of.setdefault(x, len(codes_of)) for x in fixed]
    codes = [
        np.fromiter((codes_of.setdefault(v, len(codes_of)) if v.is_Symbol else -1 for v in c), int, c.size)
        for c in columns
    ]
    # two leaves of the same symbols everywhere (u and a slice of a padded u) are one placeholder
    template, keep = s.template, []
    for j, p in enumerate(placeholders):
        twin = next((i for i in keep if np.array_equal(codes[i], codes[j])), None)
        if twin is None:
            keep.append(j)
        else:
            template = template.xreplace({p: placeholders[twin]})
    present = template.free_symbols  # (merging may cancel a placeholder: u*u - u**2)
    keep = [j for j in keep if placeholders[j] in present]
    placeholders = [placeholders[j] for j in keep]
    columns, codes = [columns[j] for j in keep], [codes[j] for j in keep]
    size = s.size
    # (renaming is sympy's evaluation only among plain symbols: others are evaluated, every element)
    slow = np.full(size, not all(map(_plain, codes_of)), dtype=bool)
    for i, code in enumerate(codes):
        slow |= code < 0
        slow |= np.isin(code, own)
        for other in codes[i + 1 :]:
            slow |= code == other
    program = _program(template, {p: i for i, p in enumerate(placeholders)})
    exprs, symbols = [None] * size, [None] * size
    fixed = tuple(fixed)
    signature = _name_orders(columns, fixed, slow)
    known: dict = {}
    for k in range(size):
        if not slow[k]:
            orders = None if signature is None else known.setdefault(signature[k], [])
            exprs[k] = _run(program, columns, k, orders)
            if exprs[k] is None and orders is not None:
                orders.clear()  # (a function evaluated to another tree: an order recorded in part is none)
        if exprs[k] is None:
            exprs[k] = template.xreplace({p: c[k] for p, c in zip(placeholders, columns, strict=True)})
        else:
            symbols[k] = frozenset((*fixed, *(c[k] for c in columns)))
    return exprs, symbols

"""Code generation: sympy -> batched torch functions, and sympy -> casadi expressions.

Both emitters accept exactly the expression nodes of
:func:`~daemodel.declaring.functions.check_supported` (arithmetic, the functions of
:mod:`daemodel.declaring.functions`, ``Piecewise`` with an otherwise branch, comparisons and
logic), which the compiler runs on every equation and ``Model.event`` on its expressions, and
raise :class:`UnsupportedFunctionError` naming the function, the equation and the supported set
for anything else.

The torch emitter writes readable Python source (one local per variable, common
subexpressions as ``_c0, _c1, ...``), registers it with :mod:`linecache` so tracebacks show
the generated lines, and broadcasts every output to the common batch shape of
``t (...)``, ``y (..., n)``, ``z (..., m)`` and ``p (..., k)``.
"""

from __future__ import annotations

import functools
import itertools
import keyword
import linecache
import math
import re
from dataclasses import dataclass, field

import numpy as np
import sympy as sp
from sympy.printing.str import StrPrinter

from daemodel.declaring.arrays import identifier
from daemodel.declaring.functions import FUNCTIONS, REDUCTIONS, compared, ordered
from daemodel.errors import ShapeError, UnsupportedFunctionError

_COUNTER = itertools.count()


class TorchPrinter(StrPrinter):
    """Prints a checked sympy expression as torch source over named locals."""

    def __init__(self, names: dict):
        # terms in sympy's stored order: sorting them ("order": None) is most of printing's cost
        super().__init__({"full_prec": True, "order": "none"})
        self._names = names

    def _print_Symbol(self, expr):
        return self._names[expr]

    def _print_Float(self, expr):
        return _literal(float(expr))

    def _print_Pi(self, expr):
        return "math.pi"

    def _print_Exp1(self, expr):
        return "math.e"

    def _print_NumberSymbol(self, expr):
        return _literal(float(expr))

    def _branch(self, expr):
        """A torch.where operand: constants become tensors of y's dtype and device (Python
        numbers would make torch.where return int64 or float32)."""
        if not expr.free_symbols:
            return f"y.new_tensor({_literal(float(expr))})"
        return self._print(expr)

    def _print_Pow(self, expr, rational=False):
        if not expr.free_symbols:  # e.g. sqrt(2): torch.sqrt needs a tensor
            return _literal(float(expr))
        base, exponent = expr.as_base_exp()
        if exponent == sp.S.Half:
            return f"torch.sqrt({self._print(base)})"
        if exponent == -sp.S.Half:
            return f"(1/torch.sqrt({self._print(base)}))"
        return super()._print_Pow(expr, rational)

    def _print_function(self, expr):
        if not expr.free_symbols:  # e.g. sin(1): torch functions need tensors
            return _literal(float(expr))
        # a constant among several arguments (atan2(y, 1.5)) must be a tensor for torch
        args = ", ".join(self._branch(a) if len(expr.args) > 1 else self._print(a) for a in expr.args)
        return f"torch.{FUNCTIONS[type(expr)][1]}({args})"

    def _print_reduction(self, expr):
        # (torch.maximum passes a nan on, as numpy's maximum does, where torch.where(a >= b, a, b) returned b for a
        # nan in a; at a tie its gradient is split between the two, a subgradient as good as either)
        name = "maximum" if isinstance(expr, sp.Max) else "minimum"
        out = self._branch(expr.args[0])
        for arg in expr.args[1:]:
            out = f"torch.{name}({out}, {self._branch(arg)})"
        return out

    def _print_Piecewise(self, expr):
        out = self._branch(expr.args[-1].expr)
        for value, cond in reversed(expr.args[:-1]):
            out = f"torch.where({self._print(cond)}, {self._branch(value)}, {out})"
        sides = dict.fromkeys(compared(expr))  # (a nan compared: no branch holds, a nan: functions.compared)
        if sides:
            unordered = " | ".join(f"torch.isnan({self._print(side)})" for side in sides)
            out = f"torch.where({unordered}, y.new_tensor(math.nan), {out})"
        return out

    def _print_Relational(self, expr):
        return f"(({self._print(expr.lhs)}) {expr.rel_op} ({self._print(expr.rhs)}))"

    _print_Equality = _print_Unequality = _print_Relational

    def _print_And(self, expr):
        return "(" + " & ".join(f"({self._print(a)})" for a in expr.args) + ")"

    def _print_Or(self, expr):
        return "(" + " | ".join(f"({self._print(a)})" for a in expr.args) + ")"

    def _print_Not(self, expr):
        return f"(~({self._print(expr.args[0])}))"


def _tuple(items) -> str:
    """Python source of a tuple of source items."""
    items = list(items)
    return f"({', '.join(items)},)" if items else "()"


def _literal(value: float) -> str:
    """A float as Python source; non-finite values through ``math`` (``repr`` gives ``inf``, a NameError)."""
    if math.isnan(value):
        return "math.nan"
    if math.isinf(value):
        return "math.inf" if value > 0 else "(-math.inf)"
    return repr(value)


for _cls in FUNCTIONS:
    setattr(TorchPrinter, f"_print_{_cls.__name__}", TorchPrinter._print_function)
for _cls in REDUCTIONS:
    setattr(TorchPrinter, f"_print_{_cls.__name__}", TorchPrinter._print_reduction)

_RESERVED = {"t", "y", "z", "p", "torch", "math", "_stack", "_prepare"}
# Text daemodel writes into generated source besides expressions: no quotes, no newlines.
_SAFE_TEXT = re.compile(r"[A-Za-z0-9_ .,:#()\[\]/*+\-]*")
_IDENTIFIER = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


def local_names(groups: dict) -> dict:
    """Map each symbol to a valid, collision-free Python local named after it (an array's element
    ``u[3]`` / ``T[3,4]`` after :func:`~daemodel.declaring.arrays.identifier`: ``u_3`` / ``T_3_4``)."""
    names, taken = {}, set()
    for symbols in groups.values():
        for s in symbols:
            name = identifier(s.name)
            if not _IDENTIFIER.fullmatch(name):
                raise ValueError(f"refusing to emit the symbol name {name!r}")  # the front end validates names
            while name in _RESERVED or name.startswith("_layout") or keyword.iskeyword(name) or name in taken:
                name += "_"
            names[s] = name
            taken.add(name)
    return names


def torch_source(fname: str, exprs, comments, t, groups: dict, doc: str) -> str:
    """Python source of ``fname(t, y, z, p=None) -> Tensor (..., len(exprs))``.

    The only user text in the source is symbol names, which the front end validated as
    identifiers or array elements (:func:`local_names` makes identifiers of the elements and keeps
    all clear of Python keywords and the generated names); ``fname``, ``comments`` and ``doc``
    come from daemodel itself and are checked here.

    Parameters
    ----------
    groups : dict {"y": states, "z": algebraics, "p": parameters}
        Symbols unpacked from the last axis of each argument, in order.
    comments : list of str
        One comment per output (its position and equation number).
    """
    for text in (fname, doc, *comments):
        if not _SAFE_TEXT.fullmatch(text):
            raise ValueError(f"refusing to emit {text!r} into generated source")  # daemodel's own bug
    names = local_names(groups)
    names[t] = "t"
    printer = TorchPrinter(names)
    replacements, reduced = sp.cse(list(exprs), symbols=sp.numbered_symbols("_c"), order="none")
    used = set().union(*(e.free_symbols for e in reduced), *(e.free_symbols for _, e in replacements))
    # constant outputs (e.g. the 1 of d x / d u) are placed by one assignment, not one per entry
    constant = [i for i, e in enumerate(reduced) if not e.free_symbols]
    varying = [i for i, e in enumerate(reduced) if e.free_symbols]
    lines = []
    if constant:
        values = ", ".join(_literal(float(reduced[i])) for i in constant)
        lines.append(f"_layout_{fname} = ({_tuple(map(str, varying))}, {_tuple(map(str, constant))}, ({values},))")
    else:
        lines.append(f"_layout_{fname} = None")
    lines += [f"def {fname}(t, y, z, p=None):", f'    """{doc}"""', "    t, p = _prepare(t, y, z, p)"]
    for arg, symbols in groups.items():
        lines += [f"    {names[s]} = {arg}[..., {i}]" for i, s in enumerate(symbols) if s in used]
    for sym, sub in replacements:
        names[sym] = sym.name
        lines.append(f"    {sym.name} = {printer.doprint(sub)}")
    lines.append("    return _stack((")
    lines += [f"        {printer.doprint(reduced[i])},  # {comments[i]}" for i in varying]
    lines.append(f"    ), t, y, z, p, _layout_{fname})")
    return "\n".join(lines) + "\n"


@dataclass(frozen=True)
class TorchFunctions:
    """Batched torch callables of a compiled DAE.

    Each callable takes ``t (...)``, ``y (..., n)``, ``z (..., m)`` and optionally
    ``p (..., k)`` (default: the model's parameter values), broadcastable, and returns a
    tensor of the broadcast batch shape plus one trailing axis.

    Attributes
    ----------
    f : callable -> Tensor (..., n)
        ODE right-hand sides, in ``state_names`` order.
    g : callable -> Tensor (..., m)
        Constraints, in ``constraint_names`` order.
    aliases : callable -> Tensor (..., a)
        Eliminated alias variables, in ``alias_names`` order.
    invariants : callable -> Tensor (..., i)
        The original constraints, in ``invariant_names`` order (for drift).
    jacobian : callable -> Tensor (..., nnz), or None
        The entries of ``d(f, g)/d(y, z)`` at ``jacobian_pattern`` (the rest are zero); None
        when a derivative leaves the supported functions (e.g. of ``Abs``), and solvers use
        autograd instead.
    jacobian_pattern : (rows, cols) of int arrays (nnz,), or None
    parameters : Tensor (k,)
        The default parameter values.
    source : dict name -> str
        The generated source of each function.
    """

    f: object
    g: object
    aliases: object
    invariants: object
    parameters: object
    jacobian: object
    jacobian_pattern: object
    dtype: object
    device: object
    source: dict = field(repr=False)


def build_torch_functions(
    specs, sizes: tuple[int, int, int], parameters, model: str, jacobian_pattern=None
) -> TorchFunctions:
    """Compile generated sources into callables.

    Parameters
    ----------
    specs : dict name -> source
    sizes : (n, m, k)
    parameters : Tensor (k,)
    jacobian_pattern : (rows, cols), optional
        Where the ``jacobian`` source's outputs sit in ``d(f, g)/d(y, z)``.
    """
    import torch

    n, m, k = sizes
    _layout_tensors = {}

    def _prepare(t, y, z, p):
        if p is None:
            p = parameters
        for arg, value, size in (("y", y, n), ("z", z, m), ("p", p, k)):
            if value.ndim == 0 or value.shape[-1] != size:
                raise ShapeError(f"model '{model}': {arg} must have shape (..., {size}); got {tuple(value.shape)}")
        return torch.as_tensor(t, dtype=y.dtype, device=y.device), p

    def _stack(values, t, y, z, p, layout):
        """The outputs as one tensor (..., len): ``values`` are the varying ones; ``layout`` is
        None, or (their positions, the constants' positions, the constants)."""
        shape = _broadcast_shape(t.shape, y.shape[:-1], z.shape[:-1], p.shape[:-1])
        full = all(isinstance(v, torch.Tensor) and v.shape == shape and v.dtype == y.dtype for v in values)
        if layout is None:
            if not values:
                return y.new_zeros((*shape, 0))
            if full:
                return torch.stack(values, dim=-1)  # the common case, without copies
            return torch.stack(
                [torch.broadcast_to(torch.as_tensor(v, dtype=y.dtype, device=y.device), shape) for v in values],
                dim=-1,
            )
        varying, constant, constants = layout
        key = (layout, y.dtype, y.device)
        if key not in _layout_tensors:  # index and value tensors made once per device, not per call
            index = lambda positions: torch.tensor(positions, dtype=torch.long, device=y.device)  # noqa: E731
            _layout_tensors[key] = (index(varying), index(constant), y.new_tensor(constants))
        varying_at, constant_at, constant_values = _layout_tensors[key]
        out = y.new_empty((*shape, len(varying) + len(constant)))
        out[..., constant_at] = constant_values
        if full and values:
            out[..., varying_at] = torch.stack(values, dim=-1)
        else:
            for i, v in zip(varying, values, strict=True):
                out[..., i] = v
        return out

    out = {}
    for name, source in specs.items():
        filename = f"<daemodel generated {name} #{next(_COUNTER)}>"
        linecache.cache[filename] = (len(source), None, source.splitlines(True), filename)
        namespace = {"torch": torch, "math": math, "_stack": _stack, "_prepare": _prepare}
        exec(compile(source, filename, "exec"), namespace)
        out[name] = namespace[name]
    return TorchFunctions(
        f=out["f"],
        g=out["g"],
        aliases=out["aliases"],
        invariants=out["invariants"],
        parameters=parameters,
        jacobian=out.get("jacobian"),
        jacobian_pattern=jacobian_pattern if "jacobian" in out else None,
        dtype=parameters.dtype,
        device=parameters.device,
        source=dict(specs),
    )


@functools.lru_cache(maxsize=256)
def _broadcast_shape(*shapes) -> tuple:
    """numpy's broadcasting rule on shapes (cached: solvers call with the same few shapes)."""
    import torch

    return tuple(torch.broadcast_shapes(*shapes))


# Expressions of one structure are converted together from this many on (fewer: one at a time).
VECTOR_GROUP = 8


class CasadiConverter:
    """Converts checked sympy expressions into casadi SX over a symbol map.

    :meth:`stack` converts many at once: the expressions of one structure (the same tree of
    operations, with other symbols and numbers at its leaves; a discretised PDE has a few such
    structures for 10^4 equations) become one casadi operation per node on vectors of all of them,
    not one per node and expression (~25 us each through casadi's Python binding: 6 s for the
    10^4 equations of reaction-diffusion).  Each element gets the operations the one-at-a-time
    conversion gives it, in the same order."""

    def __init__(self, symbols: dict):
        self._memo = dict(symbols)
        self._symbols = frozenset(symbols)

    def stack(self, exprs):
        """``exprs`` as one SX column (an empty one for none)."""
        import casadi

        if not exprs:
            return casadi.SX(0, 1)
        groups: dict = {}
        for position, expr in enumerate(exprs):
            groups.setdefault(self._structure(expr), []).append(position)
        parts, order = [], []
        for positions in groups.values():
            members = [exprs[i] for i in positions]
            if len(members) < VECTOR_GROUP:
                parts += [casadi.SX(self(e)) for e in members]
            else:
                parts.append(casadi.SX(self._vector(members)))
            order += positions
        stacked = casadi.vertcat(*parts)
        if order != list(range(len(exprs))):
            inverse = [0] * len(order)
            for row, position in enumerate(order):
                inverse[position] = row
            stacked = stacked[inverse]
        # (subexpressions two groups share, or two members of one, were made twice: merged again)
        return casadi.cse(stacked) if len(parts) < len(exprs) else stacked

    @staticmethod
    def _number(expr) -> float | None:
        """The value of a number leaf (a logical constant as 1 or 0), else None."""
        if expr.is_Number or isinstance(expr, sp.NumberSymbol):
            return float(expr)
        # (sympy's logical constants are singletons: an identity test, where == costs a sympify)
        return 1.0 if expr is sp.true else 0.0 if expr is sp.false else None

    @staticmethod
    def _piecewise(pieces: int, value, condition, sides=()):
        """A Piecewise of ``pieces`` (value, condition) pairs as nested ``if_else``, the last value the
        otherwise branch; ``value(k)``, ``condition(k)`` convert pair k (a scalar or a vector); ``sides``: the
        converted operands of its conditions' comparisons (a nan among them gives a nan:
        :func:`~daemodel.declaring.functions.compared`)."""
        import casadi

        out = value(pieces - 1)
        for k in reversed(range(pieces - 1)):
            out = casadi.if_else(condition(k), value(k), out)
        if len(sides):
            out = casadi.if_else(_fold(casadi.logic_and, [ordered(side) for side in sides]), out, math.nan)
        return out

    def _structure(self, expr) -> tuple:
        """The tree of operations of ``expr``, leaves as "S" (a symbol of the map) or "N" (a number);
        a power's exponent of one half (a square root) is part of the tree."""
        if expr.is_Atom:  # (symbols and numbers are atoms: other nodes skip both tests)
            if expr in self._symbols:
                return ("S",)
            if self._number(expr) is not None:
                return ("N",)
        head = (type(expr), len(expr.args))
        if isinstance(expr, sp.Pow):
            head += (expr.exp == sp.S.Half,)
        elif isinstance(expr, sp.core.relational.Relational):
            head += (expr.rel_op,)
        if isinstance(expr, sp.Piecewise):
            return (*head, *(self._structure(part) for pair in expr.args for part in pair))
        return (*head, *(self._structure(a) for a in expr.args))

    def _vector(self, exprs):
        """The SX column of ``exprs``, all of one :meth:`_structure`."""
        import casadi

        first = exprs[0]
        if first in self._symbols:
            return casadi.vertcat(*[self._memo[e] for e in exprs])
        if all(e == first for e in exprs[1:]):  # one subexpression shared by all: converted once (memo)
            return casadi.repmat(casadi.SX(self(first)), len(exprs), 1)
        if self._number(first) is not None:
            return casadi.SX(casadi.DM([self._number(e) for e in exprs]))
        if isinstance(first, sp.Piecewise):
            operands = [compared(e) for e in exprs]  # (of one structure: in the same places)
            return self._piecewise(
                len(first.args),
                lambda k: self._vector([e.args[k].expr for e in exprs]),
                lambda k: self._vector([e.args[k].cond for e in exprs]),
                [self._vector([sides[j] for sides in operands]) for j in range(len(operands[0]))],
            )
        args = [self._vector([e.args[k] for e in exprs]) for k in range(len(first.args))]
        return self._combine(first, args)

    @staticmethod
    def _combine(expr, args):
        """The operation of node ``expr`` on its converted arguments ``args`` (scalars or vectors)."""
        import casadi

        if isinstance(expr, sp.Add):
            return sum(args[1:], args[0])
        if isinstance(expr, sp.Mul):
            return math.prod(args[1:], start=args[0])
        if isinstance(expr, sp.Pow):
            if expr.exp == sp.S.Half:
                return casadi.sqrt(args[0])
            return args[0] ** args[1]
        if type(expr) in FUNCTIONS:
            return FUNCTIONS[type(expr)][2](*args)
        if type(expr) in REDUCTIONS:
            return _fold(REDUCTIONS[type(expr)][2], args)
        if isinstance(expr, sp.core.relational.Relational):
            ops = {"<": "__lt__", "<=": "__le__", ">": "__gt__", ">=": "__ge__", "==": "__eq__", "!=": "__ne__"}
            return getattr(casadi.SX(args[0]), ops[expr.rel_op])(args[1])
        if isinstance(expr, sp.And):
            return _fold(casadi.logic_and, args)
        if isinstance(expr, sp.Or):
            return _fold(casadi.logic_or, args)
        if isinstance(expr, sp.Not):
            return casadi.logic_not(args[0])
        raise UnsupportedFunctionError(f"casadi emitter: no translation for {expr}")  # check_supported ran first

    def __call__(self, expr):
        if expr in self._memo:
            return self._memo[expr]
        out = self._convert(expr)
        self._memo[expr] = out
        return out

    def _convert(self, expr):
        number = self._number(expr)
        if number is not None:
            return number
        if isinstance(expr, sp.Piecewise):
            pairs = expr.args
            sides = [self(side) for side in compared(expr)]
            return self._piecewise(len(pairs), lambda k: self(pairs[k].expr), lambda k: self(pairs[k].cond), sides)
        return self._combine(expr, [self(a) for a in expr.args])


# A row of more nonzeros than this is differentiated apart from the others (:func:`casadi_jacobian`).
DENSE_ROW_NONZEROS = 64


def casadi_jacobian(expr, variables, row_counts=None):
    """casadi's Jacobian of the column ``expr`` in ``variables`` (SX), its rows of more than
    :data:`DENSE_ROW_NONZEROS` nonzeros differentiated apart from the rest.

    casadi colours the Jacobian's columns (forward sweeps) or its rows (reverse sweeps), whichever needs
    fewer colours; a model with a dense row and a dense column (a mean every equation reads: an arrow)
    needs about one colour per unknown either way, so its Jacobian cost O(D^2): 8.3 s at 4,001 unknowns
    (the arrow of tests/compiling/test_codegen.py at K = 2,000), 11 s of radau's setup.  Apart, the rest
    is coloured forward and the dense rows backward: 0.05 s, the same entries.  ``row_counts``: the
    nonzeros of each row where the caller knows them (else from casadi's sparsity pattern).
    """
    import casadi

    if row_counts is None:
        row_counts = np.diff(np.asarray(casadi.jacobian_sparsity(expr, variables).T.colind()))
    counts = np.asarray(row_counts)
    dense = np.flatnonzero(counts > DENSE_ROW_NONZEROS)
    if dense.size == 0 or dense.size == counts.size:
        return casadi.jacobian(expr, variables)
    rest = np.flatnonzero(counts <= DENSE_ROW_NONZEROS)
    stacked = casadi.vertcat(
        casadi.jacobian(expr[rest.tolist()], variables), casadi.jacobian(expr[dense.tolist()], variables)
    )
    return stacked[np.argsort(np.concatenate([rest, dense])).tolist(), :]


def _fold(op, args):
    out = args[0]
    for a in args[1:]:
        out = op(out, a)
    return out

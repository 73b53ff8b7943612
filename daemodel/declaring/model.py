"""The symbolic front end: declare a semi-explicit DAE by name.

    y' = f(t, y, z, p),    0 = g(t, y, z, p)

``y`` are the differential variables (``m.states``), ``z`` the algebraic ones
(``m.algebraics``), ``p`` named parameters with values.  Equations are sympy expressions or
strings parsed against the declared names only.  Mistakes that can be seen at declaration
(unknown names, an ODE for a non-state, a derivative in an equation) raise at once; mistakes
of the whole system (a state without an ODE, unbalanced constraints) raise in ``compile``.
"""

from __future__ import annotations

import keyword
import re
from dataclasses import dataclass
from types import MappingProxyType

import numpy as np
import sympy as sp
from sympy.core.function import AppliedUndef

from daemodel.declaring.arrays import checked_shape, compact_listing, element_names, symbol_array
from daemodel.declaring.functions import check_supported, supported_names
from daemodel.declaring.parse import RESERVED_NAMES, check_numbers, parse_equation, without_heaviside, without_ite
from daemodel.declaring.scan import scan
from daemodel.declaring.stencils import Stencil, expand, leaf_symbols, paused_collection
from daemodel.declaring.symbols import Symbol
from daemodel.errors import (
    DerivativeInEquationError,
    DuplicateODEError,
    ExpressionParseError,
    InvalidNameError,
    InvalidValueError,
    ODETargetError,
    ShapeError,
    UnknownSymbolError,
)
from daemodel.messages import quoted
from daemodel.reals import real

# Variable, parameter and constraint names: identifiers, ASCII, so that generated code can use
# them as locals (they are the only user text that ever reaches generated source).
_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")
# Model names also appear in file names (compare's results) and reports, never in generated code.
_MODEL_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_.\-]*$")
# What one element of each kind of array is called in messages.
_WHAT = {"states": "differential variable", "algebraics": "algebraic variable", "parameters": "parameter"}
# Longest name accepted (model, variable, parameter, constraint).
MAX_NAME_LENGTH = 64


@dataclass(frozen=True)
class Equation:
    """One declared equation.

    Attributes
    ----------
    kind : {"ode", "constraint"}
    name : str
        The state's name for an ODE; the given or default name (``g1``, ``g2``, ...) for a
        constraint.
    number : int
        1-based position among all equations in declaration order (shown as ``#k``).
    expr : sympy.Expr
        The right-hand side of ``y' = expr`` or the constraint ``0 = expr``.
    """

    kind: str
    name: str
    number: int
    expr: sp.Expr

    @property
    def label(self) -> str:
        """How messages and reports refer to the equation."""
        if self.kind == "ode":
            return f"the ODE for '{self.name}' (#{self.number})"
        return f"constraint '{self.name}' (#{self.number})"


@dataclass(frozen=True)
class Declared:
    """What a :class:`Declaration` holds, read-only: what the compiler reads.  The mappings are views
    of the declaration's tables, no copies (a later declaration shows in them); ``constraints``,
    ``events`` and ``t0`` are as they were when :meth:`Declaration.declared` was called.

    Attributes
    ----------
    name : str
    t : sympy.Symbol
    states, algebraics, parameters : Mapping[str, sympy.Symbol]
        The variables and parameters by name, in declaration order.
    parameter_values : Mapping[str, float or None]
    odes : Mapping[str, Equation]
        Each state's ODE by the state's name.
    constraints : tuple of Equation
    initial, guess : Mapping[str, float]
        Initial values of states (and algebraic variables), and Newton's starting values.
    t0 : float
    events : tuple
        ``(name, when, direction, ((state, expr), ...), terminal)`` per event.
    arrays : Mapping[str, tuple]
        Each declared array's ``(kind, shape, symbols)`` by its name: kind is ``"states"``,
        ``"algebraics"`` or ``"parameters"`` (its elements are in that table as ``u[0]``, ``T[3,4]``,
        ...), symbols the read-only object array the declaration returned.
    free_symbols : Mapping[sympy.Expr, frozenset]
        The free symbols of declared expressions, found while checking them (the compiler starts
        from them instead of walking each equation again); not every expression is in it.
    """

    name: str
    t: sp.Symbol
    states: MappingProxyType
    algebraics: MappingProxyType
    parameters: MappingProxyType
    parameter_values: MappingProxyType
    odes: MappingProxyType
    constraints: tuple
    initial: MappingProxyType
    guess: MappingProxyType
    t0: float
    events: tuple
    arrays: MappingProxyType
    free_symbols: MappingProxyType

    def symbols(self) -> dict[str, sp.Symbol]:
        """Every declared symbol by name: states, algebraic variables, parameters."""
        return {**self.states, **self.algebraics, **self.parameters}


def _block(exprs, shape: tuple, what: str) -> list:
    """``exprs`` (an array or nested lists of expressions or strings) as a flat list, if of ``shape``."""
    values = np.asarray(exprs, dtype=object) if not isinstance(exprs, str) else np.asarray(exprs)
    if values.shape != shape:
        got = quoted(exprs) if values.ndim == 0 else f"shape {values.shape}"
        raise ShapeError(f"{what} need expressions of that shape; got {got}")
    return list(values.flat)


def _split_names(names, what: str) -> list[str]:
    if isinstance(names, str):
        return [n for n in re.split(r"[\s,]+", names.strip()) if n]
    if isinstance(names, list | tuple) and all(isinstance(n, str) for n in names):
        return list(names)
    raise InvalidNameError(f'{what} names must be a string such as "x y" or a list of strings; got {quoted(names)}')


class Declaration:
    """The declarations of a semi-explicit DAE by name: variables, parameters, equations, initial
    values and events, as sympy expressions (a plain record of what the user wrote).
    :class:`daemodel.Model` adds ``compile``; this layer never compiles anything."""

    def __init__(self, name: str = "model"):
        if not isinstance(name, str) or not _MODEL_NAME.fullmatch(name) or len(name) > MAX_NAME_LENGTH:
            raise InvalidNameError(
                f"model name {name!r} is not allowed: use letters, digits, '_', '-' and '.', starting with a "
                f"letter, at most {MAX_NAME_LENGTH} characters"
            )
        self.name = name
        self.t = Symbol("t")
        self._states: dict[str, sp.Symbol] = {}
        self._algebraics: dict[str, sp.Symbol] = {}
        self._parameters: dict[str, sp.Symbol] = {}
        self._parameter_values: dict[str, float | None] = {}
        self._odes: dict[str, Equation] = {}
        self._constraints: list[Equation] = []
        self._initial: dict[str, float] = {}
        self._guess: dict[str, float] = {}  # starting values of algebraic variables for Newton, not claims
        self._t0 = 0.0
        self._events: list[tuple] = []  # (name, when, direction, ((state, expr), ...), terminal)
        self._equation_count = 0
        # t and every declared name -> its symbol: kept as names are declared, so that a declaration
        # looks names up in O(1) (merging the tables on every m.ode made a loop quadratic)
        self._known: dict[str, sp.Symbol] = {"t": self.t}
        self._constraint_names: set[str] = set()
        # arrays of variables and parameters: name -> (kind, shape, object array of the symbols)
        self._arrays: dict[str, tuple[str, tuple, np.ndarray]] = {}
        self._constraint_arrays: set[str] = set()  # the names of arrays of constraints (m.constraint(array))
        self._free_symbols: dict = {}  # expression -> its free symbols, where the declaration's check found them
        self._compiled = None  # (what it was compiled from, CompiledDAE) of the last compile (compiling/)

    def declared(self) -> Declared:
        """What is declared so far, read-only (the compiler's input)."""
        view = MappingProxyType
        return Declared(
            name=self.name,
            t=self.t,
            states=view(self._states),
            algebraics=view(self._algebraics),
            parameters=view(self._parameters),
            parameter_values=view(self._parameter_values),
            odes=view(self._odes),
            constraints=tuple(self._constraints),
            initial=view(self._initial),
            guess=view(self._guess),
            t0=self._t0,
            events=tuple(self._events),
            arrays=view(self._arrays),
            free_symbols=view(self._free_symbols),
        )

    # ---- declarations -------------------------------------------------------------------
    def states(self, names, shape=None):
        """Declare differential variables: ``m.states("y1 y2")`` (or ``"y1, y2"``, or a list) returns a
        tuple of symbols; ``m.states("u", 1000)`` or ``m.states("T", (100, 100))`` declares an array
        and returns a numpy object array of that shape whose elements are the symbols ``u[0]``, ...
        (``T[0,0]``, ...): ``m.ode(u, exprs)`` gives all their ODEs at once, ``sol["u"]`` their values."""
        if shape is not None:
            with paused_collection():
                return self._declare_array(names, shape, "states")
        return self._declare(names, self._states, "differential variable")

    def algebraics(self, names, shape=None):
        """Declare algebraic variables (determined by the constraints): names as :meth:`states`,
        or one name and a shape for an array (``m.algebraics("b", (2, 100))``)."""
        if shape is not None:
            with paused_collection():
                return self._declare_array(names, shape, "algebraics")
        return self._declare(names, self._algebraics, "algebraic variable")

    def parameter(self, name: str, value: float | None = None) -> sp.Symbol:
        """Declare a named parameter; a value is needed by ``compile`` (see ``set_parameters``)."""
        value = None if value is None else real(value, f"parameter '{name}'")  # (before declaring: a refused
        # value leaves the name free)
        (symbol,) = self._declare([name], self._parameters, "parameter")
        self._parameter_values[name] = value
        return symbol

    def parameters(self, name: str, shape, value=None) -> np.ndarray:
        """Declare an array of parameters ``k[0]``, ... (numpy object array of ``shape``); ``value``: one
        number for all, or an array of ``shape`` (or later, :meth:`set_parameters` with ``k=array``)."""
        values = (
            None
            if value is None
            else self._array_values(name, checked_shape(shape, f"parameter array {name!r}"), value, "parameter value")
        )
        out = self._declare_array(name, shape, "parameters")
        for symbol, v in zip(out.flat, [None] * out.size if values is None else values, strict=True):
            self._parameter_values[symbol.name] = v
        return out

    def set_parameters(self, /, **values: float) -> None:
        """Give or change parameter values by name; an array of parameters takes one number or an
        array of its shape."""
        for name, value in values.items():
            if self._arrays.get(name, ("",))[0] == "parameters":
                _, shape, symbols = self._arrays[name]
                for symbol, v in zip(
                    symbols.flat, self._array_values(name, shape, value, "parameter value"), strict=True
                ):
                    self._parameter_values[symbol.name] = v
                continue
            if name not in self._parameters:
                raise UnknownSymbolError(
                    f"set_parameters: '{name}' is not a declared parameter; parameters: {_listing(self._parameters)}"
                )
            self._parameter_values[name] = real(value, f"parameter '{name}'")

    def _check_name(self, name, what: str) -> None:
        """Refuse ``name`` for a new ``what``: not an identifier, reserved, or declared already."""
        if (
            not isinstance(name, str)
            or not _NAME.fullmatch(name)
            or keyword.iskeyword(name)
            or len(name) > MAX_NAME_LENGTH
        ):
            raise InvalidNameError(
                f"{what} name {name!r} is not an identifier (ASCII letters, digits, '_', starting with a "
                f"letter, at most {MAX_NAME_LENGTH} characters)"
            )
        if name == "t":
            raise InvalidNameError(f"{what} name 't' is reserved for time (m.t)")
        if name in RESERVED_NAMES:
            raise InvalidNameError(
                f"{what} name {name!r} is the name of a supported function or constant; choose another name"
            )
        if name in self._known or name in self._arrays:  # (t is refused above)
            raise InvalidNameError(f"{what} name {name!r} is already declared as {self._kind(name)}")

    def _declare(self, names, table: dict, what: str) -> tuple[sp.Symbol, ...]:
        """Declare ``names`` in ``table``, all or none: every name is checked before any is declared."""
        names, seen = _split_names(names, what), set()
        for name in names:
            self._check_name(name, what)
            if name in seen:
                raise InvalidNameError(f"{what} name {name!r} is given twice")
            seen.add(name)
        if not names:
            raise InvalidNameError(f"no {what} names given")
        out = tuple(Symbol(name) for name in names)
        for name, symbol in zip(names, out, strict=True):
            table[name] = self._known[name] = symbol
        return out

    def _declare_array(self, name, shape, kind: str) -> np.ndarray:
        """Declare the array ``name`` of ``shape`` in the table of ``kind``: one name checked, then its
        elements (whose names need no check: an identifier, then indices) in one pass, O(size)."""
        what = _WHAT[kind]
        if not isinstance(name, str) or not _NAME.fullmatch(name):
            raise InvalidNameError(
                f"an array of {what}s takes one name and a shape, e.g. m.{kind}('u', 1000); got the name {name!r}"
            )
        self._check_name(name, f"{what} array")
        shape = checked_shape(shape, f"{what} array {name!r}")
        names = element_names(name, shape)
        symbols = [Symbol(n) for n in names]
        table = {"states": self._states, "algebraics": self._algebraics, "parameters": self._parameters}[kind]
        pairs = dict(zip(names, symbols, strict=True))
        table.update(pairs)
        self._known.update(pairs)
        out = symbol_array(symbols, shape)
        out.flags.writeable = False  # (the model's record of the array: sliced and combined, never changed)
        self._arrays[name] = (kind, shape, out)
        return out

    def _array_values(self, name: str, shape: tuple, value, what: str) -> list:
        """``value`` (one number, or an array of ``shape``) as one checked float per element of ``name``;
        ``what``: ``"initial value"``, ``"guess"`` or ``"parameter value"``."""
        if np.ndim(value) == 0:
            return [real(value, f"{what} of '{name}'")] * int(np.prod(shape))
        values = np.asarray(value, dtype=object)
        if values.shape != shape:
            plural = "guesses" if what == "guess" else f"{what}s"
            raise ShapeError(
                f"the {plural} of the array '{name}' must be one number or of shape {shape}; got shape {values.shape}"
            )
        return [real(v, f"{what} of '{name}[{','.join(map(str, i))}]'") for i, v in np.ndenumerate(values)]

    def _shapes(self) -> dict[str, tuple]:
        """Each array's shape by its name (for the parser: ``"u[3]"`` in a string)."""
        return {name: shape for name, (_, shape, _) in self._arrays.items()}

    def _kind(self, name: str) -> str:
        if name in self._arrays:
            kind, shape, _ = self._arrays[name]
            return f"an array of {_WHAT[kind]}s of shape {shape}"
        if name in self._states:
            return "a differential variable"
        if name in self._algebraics:
            return "an algebraic variable"
        return "a parameter"

    # ---- equations ----------------------------------------------------------------------
    def ode(self, state, rhs) -> None:
        """Declare ``state' = rhs``; ``state`` is a declared symbol or its name.

        For an array of states (the array :meth:`states` returned, a slice of it, or the array's name),
        ``rhs`` is an array of expressions of the same shape and each element gets its ODE, all or
        none (``m.ode(u[1:-1], (u[2:] - 2*u[1:-1] + u[:-2]) / h**2)``)."""
        if isinstance(state, np.ndarray) or (isinstance(state, str) and state in self._arrays):
            with paused_collection():  # (a block builds one tree per element)
                self._ode_block(state, rhs)
            return
        name = self._ode_target(state)
        number = self._equation_count + 1
        expr = self._expression(rhs, f"the ODE for '{name}' (#{number})")
        self._equation_count = number
        self._odes[name] = Equation("ode", name, number, expr)

    def _ode_target(self, state) -> str:
        """The name of ``state``, a differential variable without an ODE, else the error naming it."""
        name = state if isinstance(state, str) else getattr(state, "name", None)
        if not isinstance(state, (str, sp.Symbol)) or name not in self._states:
            if name in self._algebraics:
                why = f"'{name}' is an algebraic variable; algebraic variables get constraints, not ODEs"
            elif name in self._parameters:
                why = f"'{name}' is a parameter"
            else:
                why = f"{quoted(state)} is not a declared differential variable"
            raise ODETargetError(f"m.ode: {why}; differential variables: {_listing(self._states)}")
        if name in self._odes:
            raise DuplicateODEError(
                f"differential variable '{name}' already has an ODE "
                f"({self._odes[name].label}: {name}' = {self._odes[name].expr}); a state has exactly one"
            )
        return name

    def _ode_block(self, states, rhs) -> None:
        if isinstance(states, str):
            name, (kind, _, states) = states, self._arrays[states]
            if kind != "states":
                raise ODETargetError(f"m.ode: '{name}' is an array of {_WHAT[kind]}s, not of differential variables")
        what = f"m.ode: {states.size} differential variable(s) of shape {states.shape}"
        exprs = None if isinstance(rhs, Stencil) else _block(rhs, states.shape, what)
        names, seen = [], set()
        for state in states.flat:
            names.append(self._ode_target(state))
            if names[-1] in seen:
                raise DuplicateODEError(f"m.ode: differential variable '{names[-1]}' is given twice in one array")
            seen.add(names[-1])
        first = self._equation_count + 1
        if exprs is None:
            parsed = self._stencil(rhs, states.shape, what, lambda k: f"the ODE for '{names[k]}' (#{first + k})")
        else:
            parsed = [
                self._expression(e, f"the ODE for '{n}' (#{first + k})")
                for k, (n, e) in enumerate(zip(names, exprs, strict=True))
            ]
        for k, (name, expr) in enumerate(zip(names, parsed, strict=True)):
            self._odes[name] = Equation("ode", name, first + k, expr)
        self._equation_count = first + len(names) - 1

    def constraint(self, expr, name: str | None = None) -> None:
        """Declare ``0 = expr``; a string may be ``"lhs = rhs"`` (meaning ``0 = lhs - rhs``).

        ``expr`` may be an array (or list) of them: one constraint per element, all or none, named
        ``name[0]``, ``name[1]``, ... (``name[i,j]`` for a 2-d array), or ``g<k>`` each without a name.
        """
        if isinstance(expr, np.ndarray | list | tuple | Stencil):
            with paused_collection():
                self._constraint_block(expr, name)
            return
        number = self._equation_count + 1
        if name is not None and not isinstance(name, str):
            raise InvalidNameError(f"constraint name must be a string; got {type(name).__name__}")
        name = f"g{len(self._constraints) + 1}" if name is None else name
        if not _NAME.fullmatch(name) or keyword.iskeyword(name) or len(name) > MAX_NAME_LENGTH:
            raise InvalidNameError(f"constraint name {name!r} is not an identifier")
        if name in self._constraint_names or name in self._constraint_arrays:
            raise InvalidNameError(f"constraint name '{name}' is already used")
        value = self._constraint_value(expr, f"constraint '{name}' (#{number})")
        self._add_constraint(Equation("constraint", name, number, value))

    def _constraint_block(self, exprs, name) -> None:
        if name is not None and (
            not isinstance(name, str)
            or not _NAME.fullmatch(name)
            or keyword.iskeyword(name)
            or len(name) > MAX_NAME_LENGTH
        ):
            raise InvalidNameError(f"constraint array name {quoted(name)} is not an identifier")
        if name in self._constraint_names or name in self._constraint_arrays:
            raise InvalidNameError(f"constraint name '{name}' is already used")
        values = (
            np.empty(0, dtype=object)
            if isinstance(exprs, list | tuple) and not exprs
            else np.empty(exprs.shape, dtype=np.int8)  # (its shape: the stencil makes the expressions)
            if isinstance(exprs, Stencil)
            else np.asarray(exprs, dtype=object)
        )
        if values.size == 0:
            raise ShapeError(f"m.constraint: the array of constraints {quoted(name)} is empty")
        first, count = self._equation_count + 1, len(self._constraints)
        if name is None:
            names = [f"g{count + k + 1}" for k in range(values.size)]
            clash = next((n for n in names if n in self._constraint_names), None)
            if clash:
                raise InvalidNameError(
                    f"constraint name '{clash}' is already used; name the array: m.constraint(exprs, name=...)"
                )
        else:
            names = element_names(name, values.shape)
        if isinstance(exprs, Stencil):
            what = f"m.constraint: the array of constraints {quoted(name)} of shape {values.shape}"
            parsed = self._stencil(exprs, values.shape, what, lambda k: f"constraint '{names[k]}' (#{first + k})")
        else:
            parsed = [
                self._constraint_value(e, f"constraint '{n}' (#{first + k})")
                for k, (n, e) in enumerate(zip(names, values.flat, strict=True))
            ]
        for k, (n, value) in enumerate(zip(names, parsed, strict=True)):
            self._add_constraint(Equation("constraint", n, first + k, value))
        if name is not None:
            self._constraint_arrays.add(name)

    def _constraint_value(self, expr, label: str) -> sp.Expr:
        """The checked expression of one constraint: ``expr``, ``lhs - rhs`` of ``"lhs = rhs"``, or of an equality."""
        single = re.search(r"(?<![=<>!])=(?!=)", expr) if isinstance(expr, str) else None
        if single:  # "lhs = rhs": a single '=' never occurs inside an admitted expression
            lhs, rhs = expr[: single.start()], expr[single.end() :]
            return self._expression(lhs, label) - self._expression(rhs, label)
        if isinstance(expr, str):  # "lhs == rhs" parses as an equality; '==' inside a condition stays there
            expr = parse_equation(expr, self._known, label, self._shapes())
        if isinstance(expr, sp.Equality):
            return self._expression(expr.lhs, label) - self._expression(expr.rhs, label)
        return self._expression(expr, label)

    def _add_constraint(self, equation: Equation) -> None:
        self._equation_count = equation.number
        self._constraints.append(equation)
        self._constraint_names.add(equation.name)

    def event(self, name: str, when, direction: int = 0, reset: dict | None = None, terminal: bool = False) -> None:
        """Declare an event at each zero crossing of ``when`` (see :mod:`daemodel.solving.events`).

        Parameters
        ----------
        name : str
            An identifier: ``sol.events[name]`` holds its times and the values around them.
        when : str or sympy expression
            Of t, the variables and parameters; the event is where it crosses 0.
        direction : int
            +1: rising crossings only; -1: falling only; 0: both.
        reset : dict state name -> str or expression, optional
            The states' values after the event, as expressions of the values just before
            (``{"v": "-0.8*v"}``; events at one instant all read the values before it, and two
            that set one state to different values raise ``ResetConflictError``); states not named
            keep theirs.  Algebraic variables are solved anew (they cannot be reset), and the
            states are projected onto the constraints where the reset leaves them.
        terminal : bool
            End the solve at the event.
        """
        if (
            not isinstance(name, str)
            or not _NAME.fullmatch(name)
            or keyword.iskeyword(name)
            or len(name) > MAX_NAME_LENGTH
        ):
            raise InvalidNameError(f"event name {name!r} is not an identifier")
        if any(e[0] == name for e in self._events):
            raise InvalidNameError(f"event name '{name}' is already used")
        if isinstance(direction, bool) or direction not in (-1, 0, 1):
            raise InvalidValueError(f"event '{name}': direction must be -1, 0 or +1; got {direction!r}")
        if not isinstance(terminal, bool):
            raise InvalidValueError(f"event '{name}': terminal must be True or False; got {terminal!r}")
        expr = self._expression(when, f"event '{name}' (when)")
        # (the emitters' strict check now, as the compiler's for equations: not at the solve)
        check_supported(expr, f"model '{self.name}', event '{name}' (when)")
        resets = []
        if reset is not None:
            if not isinstance(reset, dict):
                raise InvalidValueError(
                    f"event '{name}': reset must be a dict state name -> expression; got {type(reset).__name__}"
                )
            for target, value in reset.items():
                if target in self._algebraics:
                    raise InvalidValueError(
                        f"event '{name}': reset names the algebraic variable '{target}'; algebraic variables are "
                        "solved anew after a reset from the constraints, reset the states they depend on"
                    )
                if target not in self._states:
                    raise UnknownSymbolError(
                        f"event '{name}': reset names {target!r}, which is no state; states: {_listing(self._states)}"
                    )
                where = f"event '{name}' (reset of '{target}')"
                resets.append((target, self._expression(value, where)))
                check_supported(resets[-1][1], f"model '{self.name}', {where}")
        self._events.append((name, expr, int(direction), tuple(resets), terminal))

    def initial(self, /, t: float | None = None, **values: float) -> None:
        """Initial values by name: all differential variables; algebraic ones are optional.

        An array's name takes one number for every element or an array of its shape
        (``m.initial(u=np.sin(np.pi * x))``); an element may be given by its name
        (``m.initial(**{"u[0]": 1.0})``).  A given algebraic value must agree with the consistent one
        (``compile`` checks it); ``t`` sets the initial time (default 0).
        """
        for name, value in self._by_element(values, ("states", "algebraics"), "initial value"):
            if name not in self._states and name not in self._algebraics:
                raise UnknownSymbolError(
                    f"m.initial: '{name}' is not a declared variable; variables: "
                    f"{_listing([*self._states, *self._algebraics])}"
                )
            self._initial[name] = real(value, f"initial value of '{name}'")
        if t is not None:
            self._t0 = real(t, "initial time t")

    def guess(self, **values: float) -> None:
        """Starting values of algebraic variables for the Newton that computes them at t0.

        A guess only picks the root (``0 = z**2 - x`` has two: ``m.guess(z=1)`` or
        ``m.guess(z=-1)``); unlike a value given to :meth:`initial`, it is not a claim that the
        root must match.  A variable without a guess starts at its :meth:`initial` value, else 0.
        An array's name takes one number or an array of its shape, as in :meth:`initial`.
        """
        for name, value in self._by_element(values, ("algebraics",), "guess"):
            if name not in self._algebraics:
                where = "a differential variable: give it with m.initial" if name in self._states else "not declared"
                raise UnknownSymbolError(
                    f"m.guess: '{name}' is {where}; guesses are for algebraic variables: {_listing(self._algebraics)}"
                )
            self._guess[name] = real(value, f"guess for '{name}'")

    def _by_element(self, values: dict, kinds: tuple, what: str):
        """``values`` by name with each array of ``kinds`` spread over its elements (checked first: all or none)."""
        out = []
        for name, value in values.items():
            kind, shape, symbols = self._arrays.get(name, (None, None, None))
            if kind is None:
                out.append((name, value))
            elif kind not in kinds:
                raise UnknownSymbolError(
                    f"m.{'guess' if what == 'guess' else 'initial'}: '{name}' is {self._kind(name)}"
                )
            else:
                out += zip((s.name for s in symbols.flat), self._array_values(name, shape, value, what), strict=True)
        return out

    def _expression(self, value, where: str) -> sp.Expr:
        """Turn a sympy expression, number or string into a checked sympy expression."""
        if isinstance(value, str):
            expr = parse_equation(value, self._known, where, self._shapes())
        else:
            try:
                expr = sp.sympify(value, strict=True)
            except (sp.SympifyError, TypeError) as err:
                raise ExpressionParseError(f"{where}: {value!r} is not an expression ({err})") from None
        if not isinstance(expr, sp.Expr) or getattr(expr, "is_Matrix", False):
            raise ExpressionParseError(
                f"{where}: {quoted(value)} is not a scalar expression (got {type(expr).__name__})"
            )
        found = scan(expr)  # (one walk; sympy is asked where it finds something to look at closer)
        if found.holds(sp.Derivative):
            derivatives = sorted(map(str, expr.atoms(sp.Derivative)))
            raise DerivativeInEquationError(
                f"{where}: derivative {', '.join(derivatives)} in {expr}; a semi-explicit DAE has "
                "derivatives only on the left (declare them with m.ode)"
            )
        undefined = sorted({str(a.func) for a in expr.atoms(AppliedUndef)}) if found.holds(AppliedUndef) else []
        if undefined:
            raise UnknownSymbolError(
                f"{where}: unknown function(s) {', '.join(undefined)} in {expr}; variables are "
                "plain symbols (use those returned by m.states / m.algebraics), and the supported "
                f"functions are {supported_names()}"
            )
        known = self._known
        free = expr.free_symbols if found.symbols is None else found.symbols
        unknown = sorted(s.name for s in free if known.get(s.name) != s)
        if unknown:
            listing = _listing(sorted(known, key=lambda n: n == "t"))  # (t last)
            raise UnknownSymbolError(
                f"{where}: unknown name(s) {', '.join(repr(u) for u in unknown)} in {expr}; declared: {listing}"
            )
        if found.holds(sp.ITE) or found.holds(sp.Heaviside):
            expr = without_heaviside(without_ite(expr))
            check_numbers(expr, where)
            return expr
        if not found.numbers_plain:
            check_numbers(expr, where)
        if found.symbols is not None:
            self._free_symbols[expr] = found.symbols
        return expr

    def _stencil(self, stencil: Stencil, shape: tuple, what: str, label) -> list:
        """The checked element expressions of ``stencil`` for ``shape`` (``label(k)``: element k's equation):
        the template is checked once and each element made by renaming (:func:`expand`), the elements
        sympy evaluated (and a template of anything beyond plain arithmetic) checked one by one."""
        if stencil.shape != shape:
            raise ShapeError(f"{what} need expressions of that shape; got a stencil of shape {stencil.shape}")
        known = self._known
        foreign = sorted(v.name for v in leaf_symbols(stencil) if known.get(v.name) != v)
        if foreign:
            raise UnknownSymbolError(
                f"{what}: the stencil's arrays hold {_listing(foreign)}, not declared in model '{self.name}'"
            )
        found = scan(stencil.template)
        plain = found.symbols is not None and found.numbers_plain
        plain = plain and not any(found.holds(k) for k in (sp.Derivative, AppliedUndef, sp.ITE, sp.Heaviside))
        if plain:  # (the template's own symbols, checked on the first element: its message names them)
            plain = all(known.get(s.name) == s for s in found.symbols - set(stencil.leaves))
        exprs, symbols = expand(stencil)
        out = []
        for k, (expr, free) in enumerate(zip(exprs, symbols, strict=True)):
            if plain and free is not None:
                self._free_symbols[expr] = free
                out.append(expr)
            else:
                out.append(self._expression(expr, label(k)))
        return out

    def _fingerprint(self) -> tuple:
        """Everything declared so far, comparable with ``==``."""
        return (
            self.name,
            tuple(self._states),
            tuple(self._algebraics),
            tuple(self._parameter_values.items()),
            tuple((name, eq.expr) for name, eq in self._odes.items()),
            tuple((eq.name, eq.expr) for eq in self._constraints),
            tuple(self._initial.items()),
            tuple(self._guess.items()),
            self._t0,
            tuple(self._events),
        )

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}({self.name!r}: {len(self._states)} differential, "
            f"{len(self._algebraics)} algebraic, "
            f"{len(self._constraints)} constraints, {len(self._parameters)} parameters)"
        )


def _listing(table) -> str:
    """The names of ``table`` for a message, an array's elements as one entry."""
    return compact_listing(table)

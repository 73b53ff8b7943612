"""Semi-explicit structure: per-constraint index, structural and numeric singularity checks.

For each constraint ``0 = g`` we build its *derivative chain*: ``h_0 = g``, and while
``h_k`` does not involve any algebraic variable, ``h_{k+1} = dh_k/dt`` along the ODE
(``dh/dt = h_t + h_y f``).  The constraint's index is the chain's length:

* index 1: ``g`` itself involves z (``g_z`` determines z);
* index 2: ``g(t, y)`` and ``g' = g_t + g_y f`` involves z (``g_y f_z``);
* index 3: ``g`` and ``g'`` are free of z, ``g''`` involves z (``g_y f_y f_z``, Hessenberg).

The last element of each chain is the equation that determines z; the earlier ones are
(hidden) constraints on y.  Stacking the determining equations gives the iteration matrix
``H_z``; it must be nonsingular, which is checked structurally (a perfect matching between
constraints and algebraic variables) and numerically (singular values at the initial point).
"""

from __future__ import annotations

import functools
import math
import zlib
from dataclasses import dataclass
from fractions import Fraction

import mpmath
import numpy as np
import scipy.sparse
import scipy.sparse.csgraph
import sympy as sp

from daemodel.errors import IndexTooHighError, SingularSystemError, UnsupportedFunctionError
from daemodel.messages import clip

MAX_INDEX = 3  # Hessenberg index 3 is the highest form the compiler recognises.
# Relative singular-value threshold of the numeric rank check: float64 Jacobians of
# well-posed models sit far above it; exact singularity lands at round-off (~1e-16).
RANK_RTOL = 1e-10

ITERATION_MATRIX = {1: "g_z", 2: "g_y f_z", 3: "g_y f_y f_z"}
# Iteration matrices of at least this size are split into their independent square blocks for
# the rank check and Newton's linear solves: a dense SVD or LU is O(m^3), the blocks of a sparse
# system cost next to nothing.  Smaller ones are factored whole (microseconds either way).
BLOCK_MIN_SIZE = 16


@dataclass(frozen=True)
class Constraint:
    """A constraint with its derivative chain.

    Attributes
    ----------
    name : str
    number : int
        Equation number in declaration order (``#k`` in messages).
    chain : tuple of sympy.Expr
        ``(g, g', ...)`` up to the first derivative that involves an algebraic variable.
    """

    name: str
    number: int
    chain: tuple

    @property
    def index(self) -> int:
        return len(self.chain)

    @property
    def expr(self) -> sp.Expr:
        """The constraint as posed: ``0 = g``."""
        return self.chain[0]

    @property
    def determining(self) -> sp.Expr:
        """The chain's last element, the equation that determines the algebraic variables."""
        return self.chain[-1]

    @property
    def label(self) -> str:
        return f"constraint '{self.name}' (#{self.number})"

    def level_name(self, k: int) -> str:
        """Name of the k-th time derivative: ``rod``, ``rod'``, ``rod''``."""
        return self.name + "'" * k


def is_zero(expr: sp.Expr) -> bool:
    """Whether ``expr`` is identically zero: exact structure, then numbers, then a bounded expansion.

    1. ``expr == 0``, or a nonzero exact rational value (:func:`exact_value`): decided.
    2. Numbers (:func:`numeric_zero_test`): the value at a few points, in high precision.  A value
       that two precisions agree on proves "not zero" (the expansion would have the same value
       there).  Values that vanish to the precision's noise at every point prove "zero" where the
       expression is analytic (:data:`ANALYTIC_FUNCTIONS`): a meromorphic function that is not
       identically zero vanishes only on a set of measure zero, which random points miss.
    3. Otherwise (a ``sqrt``, ``Abs``, ``Max``, ``Piecewise``... that vanishes at every point tried,
       or no point where the expression has a value): ``sp.expand``, when it produces at most
       :data:`MAX_EXPANSION_TERMS` terms (:func:`expansion_size`) from a tree of at most
       :data:`MAX_EXPANSION_NODES` nodes.  Above that, "not zero".

    "Not zero" is the safe answer for every caller: a derivative taken for nonzero makes the
    constraint depend on the variable, and the numeric rank check of the iteration matrix at
    the initial point then names the singular constraint; a derivative chain whose last element
    is taken for nonzero is differentiated again and ends in :class:`IndexTooHighError` at
    :data:`MAX_INDEX`.  A wrong "zero" would instead change the index silently.
    """
    if expr == 0:
        return True
    if _nonzero_somewhere(expr):
        return False
    verdict = numeric_zero_test(expr)
    if verdict is not None:
        return verdict
    if _more_nodes_than(expr, MAX_EXPANSION_NODES) or expansion_size(expr) > MAX_EXPANSION_TERMS:
        return False  # undecided and too costly to expand: "not zero", the safe side (see above)
    return sp.expand(expr) == 0


def _more_nodes_than(expr: sp.Expr, limit: int) -> bool:
    """Whether the tree of ``expr`` (a shared subexpression counted where it occurs) has more
    than ``limit`` nodes, counted up to there."""
    return any(count > limit for count, _ in enumerate(sp.preorder_traversal(expr), start=1))


# Expansion of an expression that the numbers leave undecided (see is_zero), bounded by the
# number of terms it would produce (expansion_size, a rough estimate: a derivative of the
# wheelset's creep force, estimated at ~3,000 terms and of ~4,500 operations, did not finish
# expanding in minutes), so the bound is low ...
MAX_EXPANSION_TERMS = 1_000
# ... and by its tree's size: expand walks every occurrence of a shared subexpression again.
MAX_EXPANSION_NODES = 500


def expansion_size(expr: sp.Expr) -> int:
    """An upper estimate of the terms ``sp.expand(expr)`` produces, counted without expanding.

    A sum has its terms' counts added, a product multiplied, ``b**n`` (n > 0) the number of
    monomials of degree n in b's terms; a function, a negative or fractional power counts as
    one term outside, and what ``expand`` produces inside it (its arguments, the denominator
    ``b**n``) is added to the total.
    """
    memo: dict = {}
    inside = [0]

    def terms(node) -> int:
        if node in memo:
            return memo[node]
        if node.is_Add:
            out = sum(terms(a) for a in node.args)
        elif node.is_Mul:
            out = math.prod(terms(a) for a in node.args)
        elif node.is_Pow and node.exp.is_Rational:
            # b**(7/2) expands as b**3 * sqrt(b): the integer part multiplies out
            k, n = terms(node.base), abs(int(node.exp))  # int() truncates towards zero
            monomials = math.comb(n + k - 1, n) if k > 1 else 1
            if node.exp > 0:
                out = monomials
            else:
                inside[0] += monomials
                out = 1
            if not node.exp.is_Integer:
                inside[0] += k
        else:
            inside[0] += sum(terms(a) for a in node.args)
            out = 1
        memo[node] = out
        return out

    return terms(expr) + inside[0]


# Precisions (decimal digits) of the numeric zero test: a value is a number where both agree
# to ZERO_TEST_AGREEMENT relative digits; round-off noise of a zero shrinks ~10**-40 from the
# first to the second, so it never agrees with itself.
ZERO_TEST_DIGITS = (40, 80)
ZERO_TEST_AGREEMENT = 1e-20
# Points tried (each symbol at :func:`numeric_point`): the first are in
# [0.5, 2.5) (physical quantities are mostly positive: sqrt and log stay real), the later ones
# with either sign.  A zero verdict needs ZERO_TEST_POINTS points where the value vanishes.
ZERO_TEST_POINTS = 3
ZERO_TEST_ATTEMPTS = 8
ZERO_TEST_POSITIVE_ATTEMPTS = 4

# Functions that are meromorphic in every argument on the whole complex plane: an expression
# built from them, sums, products and integer powers is identically zero when it vanishes on an
# open set (or at random points).  sqrt, log, atan, Abs, Max, Piecewise are not (branches, kinks,
# pieces): sqrt(x**2) - x vanishes for every x > 0.
ANALYTIC_FUNCTIONS = (sp.sin, sp.cos, sp.tan, sp.cot, sp.sec, sp.csc, sp.exp, sp.sinh, sp.cosh, sp.tanh, sp.coth)


def numeric_zero_test(expr: sp.Expr) -> bool | None:
    """Decide ``expr == 0`` from its values at points, or None when the values cannot.

    Returns False as soon as the value at one point is a number that both precisions of
    :data:`ZERO_TEST_DIGITS` agree on and is not zero.  Returns True when the value vanishes
    (the two precisions give round-off noise that shrinks with the precision) at
    :data:`ZERO_TEST_POINTS` points and the expression is analytic (:data:`ANALYTIC_FUNCTIONS`).
    Returns None otherwise: vanishing values of a non-analytic expression, too few points
    where the expression has a finite value, or unsupported nodes (``Piecewise``, ...).

    Values may be complex (``sqrt`` of a negative number, on the principal branch: the points
    know nothing of the model's domain, and a rail profile ``sqrt(RS**2 - X**2)`` is imaginary
    at most of them).  A nonzero complex value can mislead only towards "not zero" (an
    expression such as ``sqrt(x**2) - x``, zero for x > 0 only), the safe answer of
    :func:`is_zero`; a "zero" verdict needs an analytic expression, whose values anywhere
    decide.
    """
    vanishing = 0
    for attempt in range(ZERO_TEST_ATTEMPTS):
        try:
            low, high = (_numeric_value(expr, attempt, digits) for digits in ZERO_TEST_DIGITS)
        except _NoValue:
            continue
        if high != 0 and abs(low - high) <= ZERO_TEST_AGREEMENT * abs(high):
            return False
        if high == 0 or abs(high) <= ZERO_TEST_AGREEMENT * abs(low):
            vanishing += 1  # noise that shrank with the precision
            if vanishing == ZERO_TEST_POINTS:
                return True if _analytic(expr) else None
        # else: neither a number nor noise (cancellation beyond the first precision): next point
    return None


def numeric_value(expr: sp.Expr, attempt: int = 0, digits: int = ZERO_TEST_DIGITS[0]):
    """The value (an mpmath number) of ``expr`` at point number ``attempt`` of the numeric zero
    test, each symbol at :func:`numeric_point`, or None where it has no finite value there."""
    try:
        return _numeric_value(expr, attempt, digits)
    except _NoValue:
        return None


class _NoValue(Exception):
    """Raised inside :func:`_numeric_value` where the expression has no finite value at the point."""


def _analytic(expr: sp.Expr) -> bool:
    """Whether ``expr`` is built of numbers, symbols, sums, products, integer powers and
    :data:`ANALYTIC_FUNCTIONS` only."""
    seen, todo = set(), [expr]  # each distinct subexpression once: derivatives share many
    while todo:
        node = todo.pop()
        if node in seen:
            continue
        seen.add(node)
        if node.is_Pow and not node.exp.is_Integer:
            return False
        if not (node.is_Symbol or node.is_Number or node.is_NumberSymbol or node.is_Add or node.is_Mul or node.is_Pow):
            if not isinstance(node, ANALYTIC_FUNCTIONS):
                return False
        todo.extend(node.args)
    return True


def numeric_point(symbol: sp.Symbol, attempt: int, ctx=mpmath.mp):
    """The value of ``symbol`` at point number ``attempt``: an exact binary fraction from its name
    (the same in every run), an mpmath number of context ``ctx``."""
    code = zlib.crc32(f"{symbol.name}#{attempt}".encode())
    value = ctx.mpf(0.5) + ctx.mpf(code & 0xFFFFF) / 2**19  # in [0.5, 2.5)
    return -value if attempt >= ZERO_TEST_POSITIVE_ATTEMPTS and code >> 31 else value


def _numeric_functions(ctx) -> dict:
    """sympy function -> the mpmath function of context ``ctx``."""
    return {
        sp.sin: ctx.sin, sp.cos: ctx.cos, sp.tan: ctx.tan, sp.cot: ctx.cot, sp.sec: ctx.sec, sp.csc: ctx.csc,
        sp.exp: ctx.exp, sp.log: ctx.log, sp.sinh: ctx.sinh, sp.cosh: ctx.cosh, sp.tanh: ctx.tanh,
        sp.coth: ctx.coth, sp.asin: ctx.asin, sp.acos: ctx.acos, sp.atan: ctx.atan, sp.asinh: ctx.asinh,
        sp.acosh: ctx.acosh, sp.atanh: ctx.atanh, sp.atan2: ctx.atan2, sp.erf: ctx.erf, sp.Abs: abs,
        sp.sign: ctx.sign, sp.Min: min, sp.Max: max, sp.Heaviside: lambda x, at_zero=0.5: _step(ctx, x, at_zero),
    }  # fmt: skip


def _step(ctx, x, at_zero):
    """Heaviside(x) (sympy's: ``at_zero`` at 0) of a real value; no value for a complex one."""
    if ctx.im(x) != 0:
        raise _NoValue
    x = ctx.re(x)
    return ctx.mpf(1) if x > 0 else ctx.mpf(0) if x < 0 else ctx.mpf(at_zero)


@functools.cache
def _context(digits: int):
    """An mpmath context of ``digits`` decimal digits and its function table, made once (0.5 ms)
    and never changed after: the global mpmath precision stays as it is."""
    ctx = mpmath.MPContext()
    ctx.dps = digits
    return ctx, _numeric_functions(ctx)


def _real_part_derivative(node) -> bool:
    """Whether ``node`` is ``Derivative(re(x), x)`` or ``Derivative(im(x), x)`` for a symbol x."""
    return (
        isinstance(node, sp.Derivative)
        and isinstance(node.expr, sp.re | sp.im)
        and node.expr.args[0].is_Symbol
        and node.variable_count == ((node.expr.args[0], 1),)
    )


def _numeric_value(expr: sp.Expr, attempt: int, digits: int):
    """The value of ``expr`` at point ``attempt`` (:func:`numeric_point`) with ``digits`` decimal digits.

    Raises
    ------
    _NoValue
        Where a subexpression has no finite value there (a pole, log(0), Max of complex
        number) or is of a kind not evaluated here (``Piecewise``, relations, ...).
    """
    ctx, functions = _context(digits)
    memo: dict = {}

    def value(node):
        if node in memo:
            return memo[node]
        if node.is_Symbol:
            out = numeric_point(node, attempt, ctx)
        elif node.is_Rational:
            out = ctx.mpf(int(node.p)) / int(node.q)
        elif node.is_Float:
            out = ctx.mpf(node._mpf_)  # the float itself (at every precision the same number)
        elif node.is_NumberSymbol:
            out = ctx.mpf(node.evalf(digits + 5))
        elif node.is_Add:
            out = ctx.fsum(value(a) for a in node.args)
        elif node.is_Mul:
            out = ctx.fprod(value(a) for a in node.args)
        elif node.is_Pow:
            base = value(node.base)
            if node.exp.is_Integer:
                if base == 0 and node.exp < 0:
                    raise _NoValue
                out = base ** int(node.exp)
            else:
                exponent = value(node.exp)
                if base == 0 and ctx.re(exponent) <= 0:
                    raise _NoValue
                out = ctx.power(base, exponent)  # principal branch: complex for a negative base
        elif type(node) in functions:
            out = functions[type(node)](*(value(a) for a in node.args))
        elif isinstance(node, sp.re | sp.im):
            out = ctx.re(value(node.args[0])) if isinstance(node, sp.re) else ctx.im(value(node.args[0]))
        elif _real_part_derivative(node):
            # sympy differentiates Abs(x) of a symbol of unknown sign into re(x) d re(x)/dx + ...;
            # the model's variables are real: d re(x)/dx = 1, d im(x)/dx = 0
            out = ctx.mpf(1 if isinstance(node.expr, sp.re) else 0)
        else:
            raise _NoValue
        if not ctx.isfinite(out):
            raise _NoValue  # a pole, or nan
        memo[node] = out
        return out

    try:
        return value(expr)
    except (ZeroDivisionError, ValueError, OverflowError, TypeError):  # TypeError: Max of complex values
        raise _NoValue from None


# Largest integer power evaluated exactly by exact_value: beyond, the fractions grow too long to pay.
MAX_EXACT_POWER = 64


def _nonzero_somewhere(expr: sp.Expr) -> bool:
    """Whether ``expr`` has an exact nonzero rational value at the point of :func:`exact_value`."""
    value = exact_value(expr)
    return value is not None and value != 0


def exact_value(expr: sp.Expr) -> Fraction | None:
    """The exact value of ``expr`` at a fixed rational point (each symbol a rational number
    derived from its name), or None where the expression is not a rational function of its
    symbols with rational coefficients (a float, ``sqrt``, ``sin``, ...) or is undefined there.

    A certificate, never a proof of zero: two expressions whose values differ there are
    different (so neither expands to the other).  Floats are refused because rounding could make
    expressions that expand to the same look different.  Evaluated in Python's exact fractions,
    without building sympy objects.
    """
    memo: dict = {}

    def value(node) -> Fraction:
        if node in memo:
            return memo[node]
        if node.is_Symbol:
            out = point_value(node)
        elif node.is_Rational:
            out = Fraction(int(node.p), int(node.q))
        elif node.is_Add:
            out = sum((value(a) for a in node.args), Fraction(0))
        elif node.is_Mul:
            out = Fraction(1)
            for a in node.args:
                out *= value(a)
        elif node.is_Pow and node.exp.is_Integer and abs(node.exp) <= MAX_EXACT_POWER:
            out = value(node.base) ** int(node.exp)  # ZeroDivisionError at a pole
        else:
            raise _NotRational
        memo[node] = out
        return out

    try:
        return value(expr)
    except (_NotRational, ZeroDivisionError):
        return None


class _NotRational(Exception):
    """Raised inside :func:`exact_value` by a node that has no exact rational value."""


def point_value(symbol: sp.Symbol) -> Fraction:
    """The rational value of ``symbol`` at the point of :func:`exact_value`: from its name, so
    that every run evaluates at the same point."""
    name = symbol.name.encode()
    return Fraction(2 + zlib.crc32(name) % 1009, 3 + zlib.crc32(name[::-1]) % 1013)


class Differentiator:
    """``sp.diff`` for the compiler: the same derivatives, without sympy's repeated work.

    ``sp.diff(expr, s)`` walks every subtree for its free symbols at every level of the
    recursion, asks the assumptions system whether each partial result is zero, and builds
    ``0 * log(base)`` for every power (whose ``is_finite`` query is most of a derivative's cost
    on a sum of squares).  Here the free symbols of each node are computed once and shared
    by every derivative, subtrees free of ``s`` are skipped, and sums, products and powers
    with an ``s``-free exponent are differentiated by the rules sympy applies to them
    (``Add``: term by term; ``Mul``: Leibniz, one factor at a time, in argument order;
    ``Pow``: ``b**e * (b' * e / b)``; functions of the default rule, ``sin``, ``tanh``, ``atan2``...:
    the chain rule), so the result is the expression ``sp.diff`` returns.  Every other node
    (``Abs``, ``Max``, ``Piecewise``, ...) is handed to ``sp.diff``.  Derivatives
    and the zero tests of :func:`depends_on` are memoised: the derivative chain, the incidence
    and the Jacobian of the determining equations reuse them.

    One instance serves one compilation (it holds references to the expressions it saw).
    """

    def __init__(self) -> None:
        self._free: dict = {}
        self._derivatives: dict = {}
        self._depends: dict = {}

    def free_symbols(self, expr: sp.Expr) -> frozenset:
        """``expr.free_symbols``, memoised per node."""
        try:
            return self._free[expr]
        except KeyError:
            pass
        if expr.is_Symbol:
            out = frozenset((expr,))
        elif expr.is_Add or expr.is_Mul or expr.is_Pow:
            out = frozenset().union(*(self.free_symbols(a) for a in expr.args))
        else:  # functions, Piecewise, numbers: sympy knows their bound variables
            out = frozenset(expr.free_symbols)
        self._free[expr] = out
        return out

    def diff(self, expr: sp.Expr, s: sp.Symbol) -> sp.Expr:
        """``sp.diff(expr, s)`` for a symbol ``s``."""
        key = (expr, s)
        try:
            return self._derivatives[key]
        except KeyError:
            pass
        if s not in self.free_symbols(expr):
            out = sp.S.Zero
        elif expr == s:
            out = sp.S.One
        elif expr.is_Add:
            out = sp.Add(*[self.diff(a, s) for a in expr.args])
        elif expr.is_Mul:
            args, terms = expr.args, []
            for i, a in enumerate(args):
                d = self.diff(a, s)
                if d != 0:
                    terms.append(sp.Mul(*args[:i], d, *args[i + 1 :]))
            out = sp.Add(*terms)
        elif expr.is_Pow and s not in self.free_symbols(expr.exp):
            # sympy: b**e * (e' * log(b) + b' * e / b) with e' = 0
            out = expr * (self.diff(expr.base, s) * expr.exp / expr.base)
        elif isinstance(expr, sp.Function) and type(expr)._eval_derivative is sp.Function._eval_derivative:
            out = self._chain_rule(expr, s)
        else:
            out = sp.diff(expr, s)
        self._derivatives[key] = out
        return out

    def _chain_rule(self, expr: sp.Function, s: sp.Symbol) -> sp.Expr:
        """``f(a_1, ..., a_k)' = sum_i f_i(a) a_i'``, the rule of ``sp.Function._eval_derivative``.

        sympy drops the terms whose ``a_i'`` its assumptions prove zero: that question, asked of
        the derivative of a long argument (``tanh`` of the wheelset's creepage), took minutes.
        Here a term is dropped where ``a_i'`` is structurally zero, which is what sympy's answer
        is wherever the arguments are not zero in disguise.
        """
        terms = []
        for i, a in enumerate(expr.args, start=1):
            d = self.diff(a, s)
            if d == 0:
                continue
            try:
                outer = expr.fdiff(i)
            except sp.ArgumentIndexError:
                outer = sp.Function.fdiff(expr, i)
            terms.append(outer * d)
        return sp.Add(*terms)

    def depends(self, expr: sp.Expr, s: sp.Symbol) -> bool:
        """Whether ``expr`` really depends on ``s``: its derivative is not zero (:func:`is_zero`)."""
        key = (expr, s)
        try:
            return self._depends[key]
        except KeyError:
            pass
        out = s in self.free_symbols(expr) and not is_zero(self.diff(expr, s))
        self._depends[key] = out
        return out


def depends_on(expr: sp.Expr, symbols, calculus: Differentiator | None = None) -> bool:
    """Whether ``expr`` really depends on any of ``symbols`` (its derivative is not zero)."""
    calculus = calculus or Differentiator()
    occurring = calculus.free_symbols(expr)
    return any(calculus.depends(expr, s) for s in symbols if s in occurring)


def time_derivative(expr: sp.Expr, t: sp.Symbol, rhs: dict, calculus: Differentiator | None = None) -> sp.Expr:
    """``d expr/dt = expr_t + sum_i expr_{y_i} f_i`` for an expression free of z."""
    calculus = calculus or Differentiator()
    occurring = calculus.free_symbols(expr)
    out = calculus.diff(expr, t)
    for y, f in rhs.items():
        if y in occurring:
            out += calculus.diff(expr, y) * f
    return out


def derivative_chain(
    name: str, number: int, g: sp.Expr, t, rhs: dict, algebraics, calculus: Differentiator | None = None
) -> Constraint:
    """Differentiate ``0 = g`` along ``y' = rhs`` until an algebraic variable appears."""
    calculus = calculus or Differentiator()
    chain = [g]
    label = f"constraint '{name}' (#{number})"
    while not depends_on(chain[-1], algebraics, calculus):
        if is_zero(chain[-1]):
            which = name + "'" * (len(chain) - 1)
            raise IndexTooHighError(
                f"{label}: {which} is identically zero along the ODE, so the constraint holds by "
                "itself (an invariant of the differential equations) and determines no algebraic "
                "variable; remove it or make an algebraic variable enter it"
            )
        if len(chain) == MAX_INDEX:
            raise IndexTooHighError(
                f"{label}: no algebraic variable appears in it or in its first {MAX_INDEX - 1} time "
                f"derivatives (index above {MAX_INDEX}, or a variable that should be algebraic is "
                "missing from the right-hand sides); daemodel handles index 1, 2 and Hessenberg 3"
            )
        chain.append(time_derivative(chain[-1], t, rhs, calculus))
        # sympy differentiates Abs of a symbol of unknown sign into re/im derivatives that
        # nothing can evaluate (Max/Min give Heaviside, which the emitters name themselves)
        if chain[-1].has(sp.Derivative, sp.re, sp.im):
            raise UnsupportedFunctionError(
                f"{label} has to be differentiated (it holds no algebraic variable), but its derivative "
                f"{name + chr(39) * (len(chain) - 1)} = {clip(str(chain[-1]), 120)} leaves the supported functions: "
                "Abs, sign, Max, Min and Piecewise have no usable derivative at their kinks. Write the constraint "
                "with smooth functions (e.g. sqrt(x**2 + eps) for |x|), or declare its derivative as the constraint"
            )
    return Constraint(name, number, tuple(chain))


def incidence(constraints, algebraics, calculus: Differentiator | None = None) -> list[set[int]]:
    """For each constraint, the indices of algebraic variables its determining equation involves.

    Only the variables that occur in the equation are differentiated (the sparse incidence),
    so the cost grows with the nonzeros, not with constraints x variables.
    """
    calculus = calculus or Differentiator()
    column = {z: j for j, z in enumerate(algebraics)}
    rows = []
    for c in constraints:
        occurring = calculus.free_symbols(c.determining)
        candidates = sorted(column[z] for z in occurring if z in column)  # ascending, as a full scan adds them
        rows.append({j for j in candidates if calculus.depends(c.determining, algebraics[j])})
    return rows


def _describe(constraint: Constraint) -> str:
    return f"{constraint.label} (index {constraint.index}: through {ITERATION_MATRIX[constraint.index]})"


def match(constraints, algebraics, calculus: Differentiator | None = None) -> list[int]:
    """Match each constraint to one algebraic variable it determines (augmenting paths).

    Returns
    -------
    list of int
        ``owner[j]``: the constraint matched to algebraic variable j.

    Raises
    ------
    SingularSystemError
        When no perfect matching exists; the message names the variables and constraints
        of the structurally singular block.
    """
    rows = incidence(constraints, algebraics, calculus)
    names = [z.name for z in algebraics]
    owner = [-1] * len(algebraics)

    def augment(i: int, seen: set[int]) -> bool:
        for j in rows[i]:
            if j not in seen:
                seen.add(j)
                if owner[j] < 0 or augment(owner[j], seen):
                    owner[j] = i
                    return True
        return False

    unmatched_rows = [i for i in range(len(constraints)) if not augment(i, set())]
    if not unmatched_rows:
        return owner
    for j, name in enumerate(names):
        if not any(j in r for r in rows):
            hint = "; ".join(_describe(c) for c in constraints) or "there are no constraints"
            raise SingularSystemError(
                f"algebraic variable '{name}' appears in no constraint's Jacobian: no constraint "
                f"determines it ({hint}). Make '{name}' enter a right-hand side or a constraint"
            )
    # Rows competing for too few variables: follow alternating paths from an unmatched row.
    start = unmatched_rows[0]
    block_rows, block_cols, todo = {start}, set(), [start]
    while todo:
        i = todo.pop()
        for j in rows[i] - block_cols:
            block_cols.add(j)
            if owner[j] >= 0 and owner[j] not in block_rows:
                block_rows.add(owner[j])
                todo.append(owner[j])
    row_text = ", ".join(_describe(constraints[i]) for i in sorted(block_rows))
    col_text = ", ".join(f"'{names[j]}'" for j in sorted(block_cols)) or "no algebraic variable"
    raise SingularSystemError(
        f"structurally singular: {len(block_rows)} constraint(s) {row_text} can only determine "
        f"{len(block_cols)} algebraic variable(s) {col_text}; the iteration matrix is singular "
        "for every value (a redundant constraint, or a missing algebraic variable)"
    )


def check_rank(jacobian: np.ndarray, constraints, algebraics, t0: float) -> None:
    """Numeric rank check of the iteration matrix ``H_z`` at the initial point.

    Raises
    ------
    SingularSystemError
        Naming the constraints (left null vector) and variables (right null vector) involved.
    """
    if jacobian.size == 0 or not np.all(np.isfinite(jacobian)):
        return  # nothing to judge; a non-finite Jacobian is reported as a failed Newton
    if len(jacobian) >= BLOCK_MIN_SIZE:
        # the singular values of a block-diagonal matrix are those of its blocks together
        groups = square_blocks(jacobian != 0)
        if groups is not None:
            sigma = np.concatenate(
                [
                    np.linalg.svd(jacobian[rows[:, :, None], cols[:, None, :]], compute_uv=False).ravel()
                    for rows, cols in groups
                ]
            )
            if sigma.min() > RANK_RTOL * max(sigma.max(), np.finfo(float).tiny):
                return
    u, sigma, vt = np.linalg.svd(jacobian)  # singular, or on the edge: the whole matrix names the culprits
    if sigma[-1] > RANK_RTOL * max(sigma[0], np.finfo(float).tiny):
        return
    left, right = np.abs(u[:, -1]), np.abs(vt[-1])
    rows = [constraints[i] for i in np.flatnonzero(left > 0.1 * left.max())]
    cols = [algebraics[j].name for j in np.flatnonzero(right > 0.1 * right.max())]
    forms = sorted({ITERATION_MATRIX[c.index] for c in rows})
    raise SingularSystemError(
        f"the constraint(s) {', '.join(c.label for c in rows)} do not determine the algebraic "
        f"variable(s) {', '.join(repr(c) for c in cols)}: {' / '.join(forms)} is singular at "
        f"t={t0:g} (smallest singular value {sigma[-1]:.3g}, largest {sigma[0]:.3g}) "
        "at the initial point"
    )


def square_blocks(pattern: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]] | None:
    """The independent diagonal blocks of a square matrix with nonzero ``pattern``, grouped by size.

    Rows and columns are linked where an entry is nonzero; each connected set of rows and
    columns is one block, and the matrix is block diagonal after permuting them.

    Parameters
    ----------
    pattern : ndarray of bool, shape (m, m)

    Returns
    -------
    list of (rows, cols), or None
        For each block size k, ``rows`` and ``cols`` of shape (blocks, k): the row and column
        indices of every block of that size.  None when a block is not square (then the matrix
        is singular, whatever its values).
    """
    m = len(pattern)
    i, j = np.nonzero(pattern)
    graph = scipy.sparse.coo_matrix((np.ones(len(i)), (i, m + j)), shape=(2 * m, 2 * m))
    _, labels = scipy.sparse.csgraph.connected_components(graph, directed=False)
    row_labels, col_labels = labels[:m], labels[m:]
    row_order, col_order = np.argsort(row_labels, kind="stable"), np.argsort(col_labels, kind="stable")
    row_counts = np.bincount(row_labels, minlength=labels.max() + 1)
    col_counts = np.bincount(col_labels, minlength=labels.max() + 1)
    if not np.array_equal(row_counts, col_counts):
        return None
    # blocks of one size side by side: rows sorted by label, then split into equal chunks
    starts = np.concatenate([[0], np.cumsum(row_counts)[:-1]])
    groups = []
    for k in np.unique(row_counts[row_counts > 0]):
        first = starts[row_counts == k]
        take = first[:, None] + np.arange(k)[None, :]
        groups.append((row_order[take], col_order[take]))
    return groups

"""Is an expression identically zero?  Exactly where it can be decided cheaply (sympy's
simplification within a size budget, exact rational values at rational points), else numerically
at several random points in high precision (mpmath), agreeing at two precisions: the test behind
every structural decision of the compiler (which variables an equation involves, aliases, index)."""

from __future__ import annotations

import functools
import math
import zlib
from fractions import Fraction

import mpmath
import sympy as sp


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
    is taken for nonzero is differentiated again and ends in :class:`~daemodel.errors.IndexTooHighError` at
    :data:`~daemodel.compiling.structure.MAX_INDEX`.  A wrong "zero" would instead change the index silently.
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
    if modular_value(expr):  # (nonzero modulo a prime: nonzero, without fractions)
        return True
    value = exact_value(expr)
    return value is not None and value != 0


# The prime of modular_value: 2^61 - 1 (a Mersenne prime), so that a nonzero rational value is zero
# modulo it only where its numerator is a multiple of 2^61 - 1.
MODULUS = 2**61 - 1


@functools.lru_cache(maxsize=1 << 18)  # (a symbol's residue is asked of every expression it is in)
def _symbol_residue(name: str) -> int:
    """:func:`point_value` of the symbol ``name`` modulo :data:`MODULUS` (its fraction, unreduced)."""
    code = name.encode()
    return (2 + zlib.crc32(code) % 1009) * pow(3 + zlib.crc32(code[::-1]) % 1013, -1, MODULUS) % MODULUS


def modular_value(expr: sp.Expr) -> int | None:
    """:func:`exact_value` modulo :data:`MODULUS`, with integers instead of fractions (~20 times cheaper).

    None wherever :func:`exact_value` is None (a node with no exact value by its rules) and wherever
    a denominator is a multiple of the modulus.  Where not None, it is the residue of the exact value:
    a nonzero residue proves the value nonzero, and two different residues prove two values different
    (a zero or equal residue proves nothing).
    """
    memo: dict = {}

    def value(node) -> int:
        out = memo.get(node)
        if out is not None:
            return out
        if node.is_Symbol:
            out = _symbol_residue(node.name)
        elif node.is_Rational:
            out = int(node.p) * pow(int(node.q), -1, MODULUS) % MODULUS  # ValueError: q a multiple of it
        elif node.is_Add:
            out = 0
            for a in node.args:
                out += value(a)
            out %= MODULUS
        elif node.is_Mul:
            out = 1
            for a in node.args:
                out = out * value(a) % MODULUS
        elif node.is_Pow and node.exp.is_Integer and abs(k := int(node.exp)) <= MAX_EXACT_POWER:
            # (compared as a Python int: sympy's comparison would sympify the bound at every power)
            out = pow(value(node.base), k, MODULUS)  # ValueError: a pole, or one modulo it
        else:
            raise _NotRational
        memo[node] = out
        return out

    try:
        return value(expr)
    except (_NotRational, ValueError):
        return None


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
        elif node.is_Pow and node.exp.is_Integer and abs(k := int(node.exp)) <= MAX_EXACT_POWER:
            out = value(node.base) ** k  # ZeroDivisionError at a pole
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

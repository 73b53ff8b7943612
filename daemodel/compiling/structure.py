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
constraints and algebraic variables) and numerically (singular values at the initial point; for a
large sparse ``H_z`` its sparse LU and a condition estimate, see :func:`check_rank`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse
import sympy as sp

from daemodel.compiling.linear import BLOCK_MIN_SIZE, factor, square_blocks
from daemodel.compiling.zero_test import is_zero
from daemodel.errors import IndexTooHighError, SingularSystemError, UnsupportedFunctionError
from daemodel.messages import clip

MAX_INDEX = 3  # Hessenberg index 3 is the highest form the compiler recognises.
# Relative singular-value threshold of the numeric rank check: float64 Jacobians of
# well-posed models sit far above it; exact singularity lands at round-off (~1e-16).
RANK_RTOL = 1e-10

ITERATION_MATRIX = {1: "g_z", 2: "g_y f_z", 3: "g_y f_y f_z"}
# A sparse iteration matrix found singular is taken dense to name its culprits (singular vectors)
# up to this size (an SVD of 2,000^2 takes a second and 32 MB); a larger one, or a larger block of
# it, is named by its rows and columns.
DENSE_RANK_MAX = 2000
# Constraints and variables listed by name in the message about a large singular block.
NAMED_MAX = 12


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
    the chain rule), so the result is the expression ``sp.diff`` returns.  ``Abs``, ``sign``, ``floor`` and
    ``ceiling`` are differentiated as functions of real values (``sign(u) u'``; 0 between their jumps), where
    sympy's answers hold ``Derivative`` nodes no printer prints.  Every other node (``Max``, ``Piecewise``,
    ...) is handed to ``sp.diff``.  Derivatives
    and the zero tests of :func:`depends_on` are memoised: the derivative chain, the incidence
    and the Jacobian of the determining equations reuse them.

    One instance serves one compilation (it holds references to the expressions it saw).
    """

    def __init__(self, free_symbols=None) -> None:
        """``free_symbols``: expression -> its free symbols, already known (the declaration's)."""
        self._free: dict = dict(free_symbols or {})
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
        elif isinstance(expr, sp.Abs):
            # (of real values: sign(u) u'; sympy's, for symbols not declared real, is written in re(u) and im(u)
            # with Derivative(im(u), u), which no printer prints: z |z| + z - x = 0 failed every solve with
            # sympy's PrintMethodNotImplementedError, as did sensitivities to k through Abs(k))
            out = sp.sign(expr.args[0]) * self.diff(expr.args[0], s)
        elif isinstance(expr, sp.sign | sp.floor | sp.ceiling):
            out = sp.S.Zero  # (constant between its jumps, where every piece lies; sympy's: an unprintable Derivative)
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
    """Whether ``expr`` really depends on any of ``symbols`` (its derivative is not zero).  Only the
    symbols occurring in it are looked at: pass a set or frozenset, made once, where this is asked of
    many expressions (a list is made a set on every call)."""
    calculus = calculus or Differentiator()
    wanted = symbols if isinstance(symbols, set | frozenset) else set(symbols)
    occurring = calculus.free_symbols(expr)
    return any(calculus.depends(expr, s) for s in sorted(occurring & wanted, key=str))


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
    unmatched_rows = [i for i in range(len(constraints)) if not _augment(i, rows, owner)]
    if not unmatched_rows:
        return owner
    occurring = set().union(*rows)  # (one pass over the nonzeros, not one per variable)
    for j, name in enumerate(names):
        if j not in occurring:
            hint = _listed([_describe(c) for c in constraints], "; ") or "there are no constraints"
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
    row_text = _listed([_describe(constraints[i]) for i in sorted(block_rows)])
    col_text = _listed([f"'{names[j]}'" for j in sorted(block_cols)]) or "no algebraic variable"
    raise SingularSystemError(
        f"structurally singular: {len(block_rows)} constraint(s) {row_text} can only determine "
        f"{len(block_cols)} algebraic variable(s) {col_text}; the iteration matrix is singular "
        "for every value (a redundant constraint, or a missing algebraic variable)"
    )


def _augment(start: int, rows: list[set[int]], owner: list[int]) -> bool:
    """Match row ``start`` by an augmenting path (``owner[j]``: the row matched to column j, -1 if
    none), and say whether one was found.  Depth first, each row first looking for a free column
    among its own (MC21's look-ahead: a chain ``w[i] + w[i-1]`` is matched in one pass, where a
    search without it walked back along the chain from every row, O(n^2)), with a stack of its own
    (a path as long as the chain: Python's recursion stopped at ~1,000 rows)."""
    for j in rows[start]:
        if owner[j] < 0:
            owner[j] = start
            return True
    seen: set[int] = set()
    stack, tried = [(start, iter(rows[start]))], []  # tried[k]: the column stack[k] is trying
    while stack:
        i, columns = stack[-1]
        for j in columns:
            if j in seen:
                continue
            seen.add(j)
            k = owner[j]
            free = next((c for c in rows[k] if owner[c] < 0), None)
            if free is not None:  # k moves to a free column, row i takes j, and so up the path
                owner[free], owner[j] = k, i
                for (row, _), column in zip(stack, tried, strict=False):
                    owner[column] = row
                return True
            tried.append(j)
            stack.append((k, iter(rows[k])))
            break
        else:
            stack.pop()
            if tried:
                tried.pop()
    return False


def _listed(items: list[str], separator: str = ", ") -> str:
    """``items`` joined, the first :data:`NAMED_MAX` of them where there are more (a message stays a
    line or two at 10^5 constraints)."""
    if len(items) <= NAMED_MAX:
        return separator.join(items)
    return f"{separator.join(items[:NAMED_MAX])}{separator}... ({len(items)} in all; the first {NAMED_MAX} listed)"


def check_rank(jacobian, constraints, algebraics, t0: float) -> None:
    """Numeric rank check of the iteration matrix ``H_z`` at the initial point.

    ``jacobian`` is a dense ndarray (m, m) or a scipy.sparse matrix.  A sparse one passes on its
    sparse LU with a condition estimate below ``1 / RANK_RTOL`` (no dense m x m); one that fails
    is taken dense to name its culprits when m <= :data:`DENSE_RANK_MAX`, else split into its
    independent blocks and the singular block is named (dense within it when it is small enough).

    Raises
    ------
    SingularSystemError
        Naming the constraints (left null vector) and variables (right null vector) involved.
    """
    if scipy.sparse.issparse(jacobian):
        jacobian = scipy.sparse.csc_matrix(jacobian)
        if jacobian.shape[0] == 0 or not np.all(np.isfinite(jacobian.data)):
            return  # nothing to judge; a non-finite Jacobian is reported as a failed Newton
        if factor(jacobian)[1] * RANK_RTOL < 1:
            return
        if jacobian.shape[0] > DENSE_RANK_MAX:
            _check_sparse_blocks(jacobian, constraints, algebraics, t0)
            return
        jacobian = jacobian.toarray()
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


def _check_sparse_blocks(jacobian, constraints, algebraics, t0: float) -> None:
    """The rank check of a large sparse ``H_z`` (CSC) that its whole LU found (nearly) singular:
    each independent block is factored, and the first singular one is named, by its null vectors
    (:func:`check_rank` on the dense block) when it has at most :data:`DENSE_RANK_MAX` rows, else
    by its rows and columns."""
    groups = square_blocks(jacobian)
    if groups is None:  # structurally singular: the whole matrix is the block to name
        _name_block(jacobian, np.arange(jacobian.shape[0]), np.arange(jacobian.shape[1]), constraints, algebraics, t0)
        return
    coo = jacobian.tocoo()
    for rows, cols in groups:
        blocks, k = rows.shape
        if blocks * k * k <= DENSE_RANK_MAX**2:  # the blocks of this size as one dense stack
            block_of, row_in, col_in = (
                np.full(len(constraints), -1),
                np.zeros(len(constraints), dtype=int),
                np.zeros(len(algebraics), dtype=int),
            )
            block_of[rows] = np.arange(blocks)[:, None]
            row_in[rows], col_in[cols] = np.arange(k)[None, :], np.arange(k)[None, :]
            inside = block_of[coo.row] >= 0
            stack = np.zeros((blocks, k, k))
            stack[block_of[coo.row[inside]], row_in[coo.row[inside]], col_in[coo.col[inside]]] = coo.data[inside]
            sigma = np.linalg.svd(stack, compute_uv=False)
            ratio = sigma[:, -1] / np.maximum(sigma[:, 0], np.finfo(float).tiny)
            for b in np.flatnonzero(ratio <= RANK_RTOL):
                check_rank(stack[b], [constraints[i] for i in rows[b]], [algebraics[j] for j in cols[b]], t0)
            continue
        for r, c in zip(rows, cols, strict=True):
            _name_block(jacobian, r, c, constraints, algebraics, t0)


def _name_block(jacobian, rows, cols, constraints, algebraics, t0: float) -> None:
    """Raise the :class:`SingularSystemError` of the block ``rows x cols`` of a large sparse ``H_z``
    when it is singular: by its null vectors (:func:`check_rank`) when it is small enough to take
    dense, else by its rows and columns where its sparse LU's condition estimate exceeds
    ``m / RANK_RTOL``."""
    block = jacobian.tocsr()[rows][:, cols]
    if len(rows) <= DENSE_RANK_MAX and len(rows) == len(cols):
        check_rank(block.toarray(), [constraints[i] for i in rows], [algebraics[j] for j in cols], t0)
        return
    # the 1-norm condition is at most m times the 2-norm one (the dense check's): named only where
    # the block is singular by the dense check's measure too
    if len(rows) == len(cols) and factor(block)[1] * RANK_RTOL <= len(rows):
        return
    names = ", ".join(constraints[i].label for i in rows[:NAMED_MAX])
    variables = ", ".join(repr(algebraics[j].name) for j in cols[:NAMED_MAX])
    more = f" (of {len(rows)}; the first {NAMED_MAX} listed)" if len(rows) > NAMED_MAX else ""
    forms = sorted({ITERATION_MATRIX[constraints[i].index] for i in rows})
    raise SingularSystemError(
        f"the constraint(s) {names}{more} do not determine the algebraic variable(s) {variables}: "
        f"{' / '.join(forms)} is singular at t={t0:g} at the initial point (its sparse LU meets a zero "
        f"or negligible pivot in a coupled block of {len(rows)} equations, too large to name the "
        "culprits by singular vectors)"
    )

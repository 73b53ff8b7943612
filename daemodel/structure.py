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

from dataclasses import dataclass

import numpy as np
import sympy as sp

from daemodel.errors import IndexTooHighError, SingularSystemError, UnsupportedFunctionError
from daemodel.messages import clip

MAX_INDEX = 3  # Hessenberg index 3 is the highest form the compiler recognises.
# Relative singular-value threshold of the numeric rank check: float64 Jacobians of
# well-posed models sit far above it; exact singularity lands at round-off (~1e-16).
RANK_RTOL = 1e-10

ITERATION_MATRIX = {1: "g_z", 2: "g_y f_z", 3: "g_y f_y f_z"}


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
    """Symbolic zero test: exact structure first, then after expansion."""
    return expr == 0 or sp.expand(expr) == 0


def depends_on(expr: sp.Expr, symbols) -> bool:
    """Whether ``expr`` really depends on any of ``symbols`` (its derivative is not zero)."""
    return any(s in expr.free_symbols and not is_zero(sp.diff(expr, s)) for s in symbols)


def time_derivative(expr: sp.Expr, t: sp.Symbol, rhs: dict) -> sp.Expr:
    """``d expr/dt = expr_t + sum_i expr_{y_i} f_i`` for an expression free of z."""
    out = sp.diff(expr, t)
    for y, f in rhs.items():
        if y in expr.free_symbols:
            out += sp.diff(expr, y) * f
    return out


def derivative_chain(name: str, number: int, g: sp.Expr, t, rhs: dict, algebraics) -> Constraint:
    """Differentiate ``0 = g`` along ``y' = rhs`` until an algebraic variable appears."""
    chain = [g]
    label = f"constraint '{name}' (#{number})"
    while not depends_on(chain[-1], algebraics):
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
        chain.append(time_derivative(chain[-1], t, rhs))
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


def incidence(constraints, algebraics) -> list[set[int]]:
    """For each constraint, the indices of algebraic variables its determining equation involves."""
    return [{j for j, z in enumerate(algebraics) if depends_on(c.determining, [z])} for c in constraints]


def _describe(constraint: Constraint) -> str:
    return f"{constraint.label} (index {constraint.index}: through {ITERATION_MATRIX[constraint.index]})"


def match(constraints, algebraics) -> list[int]:
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
    rows = incidence(constraints, algebraics)
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
    u, sigma, vt = np.linalg.svd(jacobian)
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

"""Exact derivatives of radau's solution: forward sensitivities and the discrete adjoint.

A radau solution is the discrete map of its accepted steps.  Step ``k`` (start ``t_k``, length
``h_k``, start value ``y_k``) has stage values ``W_k = (Y_i, Z_i)`` that zero the stage equations
``R(W_k; y_k, p) = 0`` of :func:`daemodel.collocation.stage_residual`, and ``y_{k+1} = Y_s``.  The
implicit function theorem gives the derivatives of that map::

    M_k dW_k = -R_y dy_k - R_p dp,     M_k = dR/dW  (the stage equations' full Jacobian)

with ``-R_y`` = the identity on every stage's ``F`` rows and ``-R_p`` = ``h sum_j a_ij f_p(j)`` on
the ``F`` rows, ``-g_p(i)`` on the ``G`` rows.  These are the sensitivities of the discrete
solution that radau returns, with its steps as taken (an adaptive controller's step sizes are
held, as every discrete sensitivity method holds them): central finite differences of a re-solve
on the same steps agree with them to their own rounding.  The values between the steps' nodes
(``t_eval``, :meth:`Solution.at`) are the collocation polynomial's, a fixed linear combination of
the nodes, so their derivatives are the same combination of the nodes' derivatives.

Why ``M_k`` is factored afresh rather than radau's own Newton matrices: radau's simplified Newton
keeps one Jacobian (at some earlier step's start) for many steps and reaches the stage values by
iterating; the exact derivative needs the Jacobian at each step's own stage values, and a solve
with the kept matrices would need as many iterations again, one step at a time.  Here every
step's ``M_k`` is built from the recorded stage values (the dense output's nodes) and factored
together with all the others, a block of steps at a time in one batched LAPACK call, and only the
small recursion ``dy_{k+1} = Phi_k dy_k + Psi_k`` runs step by step.

Adaptive steps on a system of index 2 or 3 return the algebraic variables solved from the returned
states (:mod:`daemodel.compiling.algebraic`), ``H(t, y, z, p) = 0``: their derivatives at the outputs
are ``-H_z^-1 (H_y dy + H_p dp)`` of the states' (:func:`resolved_derivatives`), in both directions.

The adjoint of a scalar ``J = sum over outputs of phi(u(t))`` runs the same steps backwards with
the transposed matrices: one column for the cotangent and ``n`` for the state's recursion per
step, whatever the number of parameters (their gradient is one product ``lambda_k^T (-R_p)`` per
step).  Memory: blocks of steps are built, used and dropped, in the forward order for the forward
sensitivities and in the reverse order for the adjoint; the recorded nodes are the checkpoints.

Initial values: a named initial state moves with the others held where the constraints allow it
(the derivative of ``compiled.consistent(y0, fix=[name])``); a parameter moves the initial states
the least that keeps every z-free constraint level satisfied (the derivative of
``compiled.consistent(y0, parameters=...)``); the algebraic values follow from their determining
equations.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from daemodel.collocation import lagrange_matrix
from daemodel.compiling.init import hidden_constraints
from daemodel.dense import CollocationPolynomials, step_owners
from daemodel.errors import SensitivityError, UnknownSymbolError
from daemodel.files import check_dense
from daemodel.tableau import radau_iia

# Bytes of step matrices (M_k and its right-hand sides) built at a time: a block of steps is
# built, factored, used and dropped before the next.
BLOCK_BYTES = 32 * 2**20
# The constraints fix a named initial state when the other states cannot absorb its change: the
# least-squares correction leaves a violation above this, relative to the constraint rows' size.
FIXED_STATE_RTOL = 1e-8


@dataclass(frozen=True)
class Directions:
    """What the derivatives are taken with respect to.

    Attributes
    ----------
    names : tuple of str
        As the caller named them: parameters and states (their initial values).
    parameter : ndarray of int, shape (Q,)
        Each name's parameter index, -1 for a state.
    state : ndarray of int, shape (Q,)
        Each name's state index, -1 for a parameter.
    """

    names: tuple
    parameter: np.ndarray
    state: np.ndarray

    @property
    def size(self) -> int:
        return len(self.names)

    def parameter_columns(self, k: int) -> np.ndarray:
        """``dp / d(direction)``, shape (k, Q): a one where a direction is a parameter."""
        out = np.zeros((k, self.size))
        for q, j in enumerate(self.parameter):
            if j >= 0:
                out[j, q] = 1.0
        return out


def check_stage_systems(compiled, stages: int, caller: str = "sensitivities") -> None:
    """Refuse (:class:`~daemodel.errors.ResourceLimitError`) a model whose sensitivities would factor
    dense systems of ``stages`` (n + m) unknowns above :data:`daemodel.files.DENSE_MAX_ORDER` (their
    stage systems and Jacobians are dense), before anything is allocated."""
    D = len(compiled.states) + len(compiled.algebraics)
    check_dense(
        f"{caller} of '{compiled.name}' ({D} unknowns, {stages} stage(s))",
        stages * D,
        "differentiate a smaller model, or by finite differences of two solves",
    )


def directions(compiled, names, caller: str = "sensitivities") -> Directions:
    """Resolve ``names`` (a name or a list of parameter and state names) against ``compiled``.

    Raises
    ------
    SensitivityError
        For an empty list, a repeated name, or an algebraic variable (its initial value is not free:
        the constraints determine it).
    UnknownSymbolError
        For a name the model does not have.
    ResourceLimitError
        For a model beyond the dense systems' limit (:func:`check_stage_systems`), before anything is
        allocated.
    """
    check_stage_systems(compiled, 1, caller)
    if isinstance(names, str):
        names = (names,)
    try:
        names = tuple(names)
    except TypeError:
        raise SensitivityError(f"{caller} must be a list of parameter or state names; got {names!r}") from None
    if not names:
        raise SensitivityError(f"{caller}: name at least one parameter or state")
    if any(not isinstance(n, str) for n in names):
        raise SensitivityError(f"{caller} must be names (strings); got {names!r}")
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise SensitivityError(f"{caller} names {', '.join(repr(r) for r in repeated)} more than once")
    parameters, states = compiled.parameter_names, compiled.state_names
    pruned = set(compiled.dropped.get("parameters", ()))
    parameter, state = [], []
    for name in names:
        if name in compiled.algebraic_names:
            raise SensitivityError(
                f"{caller}: {name!r} is an algebraic variable: its initial value is not free (the constraints "
                "determine it from the states and parameters), so nothing can be differentiated with respect to it; "
                f"name states or parameters: {list(states) + list(parameters)}"
            )
        if name not in parameters and name not in states and name not in pruned:
            raise UnknownSymbolError(
                f"{caller}: {name!r} is neither a parameter nor a state of model '{compiled.name}'; the parameters are "
                f"{list(parameters)} and the states {list(states)}"
            )
        parameter.append(parameters.index(name) if name in parameters else -1)
        state.append(states.index(name) if name in states else -1)
    return Directions(names=names, parameter=np.array(parameter, dtype=int), state=np.array(state, dtype=int))


def zero_free_levels(compiled) -> list:
    """Every z-free constraint expression of the system and of the model it was reduced from (its
    invariants): what the initial states must satisfy."""
    exprs = [e for _, _, e in hidden_constraints(compiled.constraints)]
    algebraics = set(compiled.algebraics)
    for _, expr in compiled.invariants:
        # (structural comparison: a repeated row does no harm to the projection, an expansion can cost seconds)
        if not (expr.free_symbols & algebraics) and all(expr != e for e in exprs):
            exprs.append(expr)
    return exprs


def prepare(compiled) -> None:
    """Generate (once per compiled model: cached on its numeric system) every numeric Jacobian the
    passes use, so that a caller can charge code generation to setup, apart from the pass."""
    numeric = compiled.numeric
    exprs, determining = [*compiled.rhs, *compiled.g], [c.determining for c in compiled.constraints]
    numeric.batch_jacobian(exprs, [*compiled.states, *compiled.algebraics])
    numeric.batch_jacobian(exprs, list(compiled.parameters))
    levels = zero_free_levels(compiled)
    for wrt in (compiled.states, compiled.parameters):
        if levels:
            numeric.batch_jacobian(levels, wrt)
    for wrt in (compiled.algebraics, compiled.states, compiled.parameters):
        if determining:
            numeric.batch_jacobian(determining, wrt)


def initial_sensitivities(
    compiled, t0: float, y0: np.ndarray, z0: np.ndarray, p: np.ndarray, where: Directions, given=None
):
    """``(dy0, dz0)``, shapes (B, n, Q) and (B, m, Q): the consistent initial values' derivatives
    (``dy0`` as ``given`` when given: then only ``dz0`` is derived).

    Raises
    ------
    SensitivityError
        When the constraints fix a named state given the others (it cannot move alone), or their
        Jacobian in the algebraic variables is singular at t0.
    """
    numeric = compiled.numeric
    B, n, m, k, Q = len(y0), y0.shape[1], z0.shape[1], p.shape[1], where.size
    dy = np.zeros((B, n, Q))
    for q, i in enumerate(where.state):
        if i >= 0:
            dy[:, i, q] = 1.0
    dp = np.broadcast_to(where.parameter_columns(k), (B, k, Q))
    levels = zero_free_levels(compiled) if given is None else []
    if given is not None:
        dy = np.broadcast_to(np.asarray(given, dtype=float), (B, n, Q)).copy()
    if levels:
        C = numeric.batch_jacobian(levels, compiled.states)(t0, y0, z0, p)  # (B, L, n)
        Cp = numeric.batch_jacobian(levels, compiled.parameters)(t0, y0, z0, p)  # (B, L, k)
        violation = C @ dy + Cp @ dp  # (B, L, Q)
        for q in range(Q):
            free = np.arange(n) != where.state[q]
            Cf = C[:, :, free]
            correction = -np.linalg.pinv(Cf) @ violation[:, :, q, None]  # the least change of the free states
            left = np.abs(Cf @ correction + violation[:, :, q, None])[..., 0]  # (B, L)
            scale = np.abs(C).max(axis=-1, initial=0.0) + np.abs(Cp).max(axis=-1, initial=0.0) + 1.0
            if (left > FIXED_STATE_RTOL * scale).any():
                b, level = np.argwhere(left > FIXED_STATE_RTOL * scale)[0]
                raise SensitivityError(
                    f"the constraints fix {where.names[q]!r} given the other states ({levels[level]} = 0 of sample "
                    f"{b} cannot hold when it moves alone), so the solution has no derivative with respect to it; "
                    "name the parameters or states the constraints leave free"
                )
            dy[:, free, q] += correction[..., 0]
    if m == 0:
        return dy, np.zeros((B, 0, Q))
    determining = [c.determining for c in compiled.constraints]
    Hz = numeric.batch_jacobian(determining, compiled.algebraics)(t0, y0, z0, p)
    Hy = numeric.batch_jacobian(determining, compiled.states)(t0, y0, z0, p)
    Hp = numeric.batch_jacobian(determining, compiled.parameters)(t0, y0, z0, p)
    try:
        dz = -np.linalg.solve(Hz, Hy @ dy + Hp @ dp)
    except np.linalg.LinAlgError:
        dz = np.full((B, m, Q), np.nan)
    if not np.isfinite(dz).all():
        raise SensitivityError(
            f"the algebraic variables' equations are singular in {list(compiled.algebraic_names)} at t0 = {t0:g}: the "
            "initial algebraic values have no derivative there"
        )
    return dy, dz


class StepSystems:
    """The stage equations' derivatives of the recorded steps, a block of steps at a time.

    Parameters
    ----------
    compiled : CompiledDAE
        The system the steps solved.
    dense : CollocationPolynomials
    p : ndarray, shape (B, k)
    """

    def __init__(self, compiled, dense: CollocationPolynomials, p: np.ndarray):
        check_stage_systems(compiled, len(dense.c))
        self.compiled, self.dense, self.p = compiled, dense, p
        self.n, self.m = len(compiled.states), len(compiled.algebraics)
        self.D = self.n + self.m
        self.s = len(dense.c)
        self.A = np.array(radau_iia(self.s).A, dtype=float)
        self.B, self.S = dense.nodes.shape[0], len(dense.starts)
        exprs = [*compiled.rhs, *compiled.g]
        self.jacobian = compiled.numeric.batch_jacobian(exprs, [*compiled.states, *compiled.algebraics])
        self.parameter_jacobian = compiled.numeric.batch_jacobian(exprs, list(compiled.parameters))
        k = max(1, p.shape[1])
        per_step = 8 * self.B * (self.s * self.D) * (2 * self.s * self.D + self.n + k)
        self.block = max(1, int(BLOCK_BYTES // per_step))

    def blocks(self, reverse: bool = False):
        starts = list(range(0, self.S, self.block))
        for first in reversed(starts) if reverse else starts:
            yield first, min(self.S, first + self.block)

    def build(self, first: int, last: int):
        """``(M, rhs_p)`` of steps ``first:last``: M (B, K, sD, sD), rows stage by stage ``[F_i, G_i]``
        and columns ``[Y_j, Z_j]``; ``rhs_p = -dR/dp`` (B, K, sD, k)."""
        n, s, D, B = self.n, self.s, self.D, self.B
        K = last - first
        h = self.dense.lengths[first:last]  # (K,)
        times = self.dense.starts[first:last, None] + self.dense.c[None, :] * h[:, None]  # (K, s)
        W = np.asarray(self.dense.nodes[:, first:last, 1:], dtype=float)  # (B, K, s, D)
        rows = W.reshape(B * K * s, D)
        P = np.repeat(self.p, K * s, axis=0)
        t = np.tile(times.reshape(K * s), B)
        J = self.jacobian(t, rows[:, :n], rows[:, n:], P).reshape(B, K, s, D, D)
        Jp = self.parameter_jacobian(t, rows[:, :n], rows[:, n:], P).reshape(B, K, s, D, -1)
        hA = h[:, None, None] * self.A  # (K, s, s)
        M = np.zeros((B, K, s, D, s, D))
        # (a broadcast product: einsum's loops run 5x slower here)
        M[:, :, :, :n] = -hA[None, :, :, None, :, None] * np.swapaxes(J[:, :, :, :n, :], 2, 3)[:, :, None]
        stage = np.arange(s)
        M[:, :, stage, n:, stage, :] = J[:, :, :, n:, :].transpose(2, 0, 1, 3, 4)
        M[:, :, stage, :n, stage, :n] += np.eye(n)
        rhs_p = np.empty((B, K, s, D, Jp.shape[-1]))
        rhs_p[:, :, :, :n] = (hA[None, :, :, :, None, None] * Jp[:, :, None, :, :n, :]).sum(axis=3)
        rhs_p[:, :, :, n:] = -Jp[:, :, :, n:, :]
        return M.reshape(B, K, s * D, s * D), rhs_p.reshape(B, K, s * D, -1)

    def solve(self, M, rhs, first: int, transposed: bool = False):
        """``M^-1 rhs`` (or ``M^-T rhs``) of a block; a singular step is named by its time."""
        M = np.swapaxes(M, -1, -2) if transposed else M
        try:
            X = np.linalg.solve(M, rhs)
        except np.linalg.LinAlgError:
            X = None
        finite = None if X is None else np.isfinite(X).reshape(X.shape[0], X.shape[1], -1).all(axis=(0, 2))
        if finite is not None and finite.all():
            return X
        if finite is None:  # LAPACK stopped at an exactly singular matrix: which step's
            finite = np.array([(np.linalg.matrix_rank(M[:, k]) == M.shape[-1]).all() for k in range(M.shape[1])])
        bad = first + int(np.flatnonzero(~finite)[0])
        raise SensitivityError(
            f"the stage equations of the step at t = {self.dense.starts[bad]:.6g} (h = {self.dense.lengths[bad]:.3g}) "
            "are singular: the solution has no derivative there"
        )

    def state_rhs(self):
        """``-dR/dy_k``, (sD, n): the identity on every stage's F rows."""
        out = np.zeros((self.s, self.D, self.n))
        out[:, : self.n] = np.eye(self.n)
        return out.reshape(self.s * self.D, self.n)


def _outputs_by_step(dense, times):
    """``(owner step, Lagrange weights (T, s+1))`` of each output time."""
    step, theta = step_owners(dense.starts, dense.lengths, times)
    return step, lagrange_matrix(np.concatenate([[0.0], dense.c]), theta)


def forward(sol, names, model=None, initial=None) -> tuple[Directions, np.ndarray]:
    """The forward sensitivities of ``sol`` (a radau solution with its dense output) at its output
    times: ``(directions, S)`` with S (B, T, n+m, Q), ``S[b, t, :, q] = d u(t) / d names[q]``.
    ``initial`` (B, n, Q), when given, is the initial states' derivative to use instead of the
    least-change one (a caller whose initial states are another function of the names: ``fit``)."""
    compiled = sol.compiled
    where = directions(model or compiled, names)
    dense = check_solution(sol, "sensitivities")
    n = len(compiled.states)
    start = dense.nodes[:, 0, 0]  # the first step's start (the outputs need not begin at t0)
    dy0, dz0 = initial_sensitivities(
        compiled, float(dense.starts[0]), start[:, :n], start[:, n:], sol.parameters, where, given=initial
    )
    out = _forward_piece(compiled, dense, sol.parameters, where, dy0, dz0, np.asarray(sol.t))
    resolved = resolved_derivatives(sol)
    if resolved is not None:  # (the returned algebraic variables: functions of the returned states)
        dz_dy, dz_dp = resolved
        out[:, :, n:] = dz_dy @ out[:, :, :n] + dz_dp @ where.parameter_columns(sol.parameters.shape[1])
    return where, out


def resolved_derivatives(sol) -> tuple[np.ndarray, np.ndarray] | None:
    """``(dz/dy (B, T, m, n), dz/dp (B, T, m, k))`` at the output times of a solution whose algebraic variables
    are solved from its states (``sol.dense.resolves_algebraic``), from their determining equations; else None."""
    compiled = sol.compiled
    if not sol.dense.resolves_algebraic or not compiled.algebraics:
        return None
    B, T, n, m = sol.batch_size, len(sol.t), len(compiled.states), len(compiled.algebraics)
    Y = np.stack([np.reshape(sol.values[name], (B, T)) for name in compiled.state_names], axis=-1).reshape(B * T, n)
    Z = np.stack([np.reshape(sol.values[name], (B, T)) for name in compiled.algebraic_names], axis=-1)
    Z = Z.reshape(B * T, m)
    P, times = np.repeat(sol.parameters, T, axis=0), np.tile(np.asarray(sol.t, dtype=float), B)
    determining, numeric = [c.determining for c in compiled.constraints], compiled.numeric
    Hz = numeric.batch_jacobian(determining, compiled.algebraics)(times, Y, Z, P)
    Hy = numeric.batch_jacobian(determining, compiled.states)(times, Y, Z, P)
    Hp = numeric.batch_jacobian(determining, compiled.parameters)(times, Y, Z, P)
    try:
        dz = -np.linalg.solve(Hz, np.concatenate([Hy, Hp], axis=-1))
    except np.linalg.LinAlgError:
        dz = np.full((B * T, m, n + P.shape[1]), np.nan)
    if not np.isfinite(dz).all():
        row = int(np.flatnonzero(~np.isfinite(dz).all(axis=(1, 2)))[0])
        raise SensitivityError(
            f"the algebraic variables' equations are singular in {list(compiled.algebraic_names)} at t = "
            f"{times[row]:g} (sample {row // T}): the algebraic values there have no derivative"
        )
    dz = dz.reshape(B, T, m, n + P.shape[1])
    return dz[..., :n], dz[..., n:]


def _forward_piece(compiled, dense, p, where: Directions, dy0, dz0, times):
    systems = StepSystems(compiled, dense, p)
    n, s, D, B, Q = systems.n, systems.s, systems.D, systems.B, where.size
    columns = where.parameter_columns(p.shape[1])  # (k, Q)
    owner, weights = _outputs_by_step(dense, times)
    out = np.zeros((B, len(times), D, Q))
    Sy, Sz = dy0, dz0
    for first, last in systems.blocks():
        M, rhs_p = systems.build(first, last)
        K = last - first
        rhs = np.concatenate([np.broadcast_to(systems.state_rhs(), (B, K, s * D, n)), rhs_p @ columns], axis=-1)
        X = systems.solve(M, rhs, first).reshape(B, K, s, D, n + Q)
        Phi, Psi = X[..., :n], X[..., n:]
        # step by step only the end values' recursion: (B, D, n) @ (B, n, Q) a step
        starts = np.empty((B, K, D, Q))
        for k in range(K):
            starts[:, k, :n], starts[:, k, n:] = Sy, Sz
            end = Phi[:, k, -1] @ Sy + Psi[:, k, -1]
            Sy, Sz = end[:, :n], end[:, n:]
        # the nodes of the steps that hold outputs, all at once
        here = np.flatnonzero((owner >= first) & (owner < last))
        if len(here):
            k = owner[here] - first
            stages = Phi[:, k] @ starts[:, k, None, :n] + Psi[:, k]  # (B, T_here, s, D, Q)
            nodes = np.concatenate([starts[:, k, None], stages], axis=2)  # (B, T_here, s+1, D, Q)
            out[:, here] = np.einsum("tj,btjdq->btdq", weights[here], nodes)
    return out


def adjoint(sol, cotangent: tuple, names, model=None) -> tuple[Directions, np.ndarray]:
    """The gradient of ``J`` with respect to ``names`` by the discrete adjoint, given ``cotangent =
    (dJ/du (B, T, n+m) at the output times, dJ/dp (B, k) directly)``: ``(directions, gradient (B, Q))``."""
    cotangent, direct_p = cotangent
    compiled = sol.compiled
    where = directions(model or compiled, names, caller="gradient")
    dense = check_solution(sol, "gradient")
    n, k = len(compiled.states), sol.parameters.shape[1]
    start = dense.nodes[:, 0, 0]
    dy0, dz0 = initial_sensitivities(
        compiled, float(dense.starts[0]), start[:, :n], start[:, n:], sol.parameters, where
    )
    resolved = resolved_derivatives(sol)
    if resolved is not None:  # (the returned algebraic variables' cotangent, moved onto the states and parameters)
        dz_dy, dz_dp = resolved
        zbar = cotangent[:, :, n:]
        cotangent = np.concatenate(
            [cotangent[:, :, :n] + np.einsum("btm,btmn->btn", zbar, dz_dy), np.zeros_like(zbar)], axis=-1
        )
        direct_p = direct_p + np.einsum("btm,btmk->bk", zbar, dz_dp)
    ybar0, zbar0, pbar = _adjoint_piece(compiled, dense, sol.parameters, cotangent, sol.t)
    gradient = (
        np.einsum("bn,bnq->bq", ybar0, dy0)
        + np.einsum("bm,bmq->bq", zbar0, dz0)
        + (pbar + direct_p) @ where.parameter_columns(k)
    )
    return where, gradient


def _adjoint_piece(compiled, dense, p, cotangent, times):
    """``(dJ/dy0 (B, n), dJ/dz0 (B, m), dJ/dp (B, k))`` with the initial values held.

    Backwards over the steps: the stage values' cotangent ``Wbar_k`` (the outputs' direct share,
    the next step's start value) gives ``lambda_k = M_k^-T Wbar_k``, then ``dJ/dy_k = ystart_k +
    sum_i lambda_k[F_i]`` and ``dJ/dp += lambda_k^T (-R_p)``.  ``Wbar_k = c_k + E dJ/dy_{k+1}``
    splits into what the outputs give (known for every step at once) and the state's share, so the
    transposed solves of a block run together (one column for ``c_k``, n for ``E``) and only the
    n-vector recursion ``dJ/dy_k = alpha_k + Gamma_k dJ/dy_{k+1}`` runs step by step."""
    systems = StepSystems(compiled, dense, p)
    n, s, D, B = systems.n, systems.s, systems.D, systems.B
    owner, weights = _outputs_by_step(dense, np.asarray(times))
    E = np.zeros((s, D, n))
    E[-1, :n] = np.eye(n)
    pbar = np.zeros((B, p.shape[1]))
    ybar = np.zeros((B, n))  # dJ/dy at the start of the block after this one
    for first, last in systems.blocks(reverse=True):
        K = last - first
        # the outputs' direct cotangents of each node of steps first..last (the step after the block
        # included: its start value is the block's last stage)
        direct = np.zeros((B, K + 1, s + 1, D))
        for t in np.flatnonzero((owner >= first) & (owner <= last)):
            direct[:, owner[t] - first] += weights[t][None, :, None] * cotangent[:, t, None, :]
        c = direct[:, :K, 1:].copy()  # (B, K, s, D)
        c[:, :, -1, n:] += direct[:, 1:, 0, n:]  # the next step's start z is this step's last stage
        M, rhs_p = systems.build(first, last)
        rhs = np.concatenate(
            [c.reshape(B, K, s * D, 1), np.broadcast_to(E.reshape(s * D, n), (B, K, s * D, n))], axis=-1
        )
        X = systems.solve(M, rhs, first, transposed=True).reshape(B, K, s, D, 1 + n)
        a, G = X[..., 0], X[..., 1:]  # lambda_k = a_k + G_k dJ/dy_{k+1}
        alpha = a[:, :, :, :n].sum(axis=2) + direct[:, :K, 0, :n]  # (B, K, n)
        Gamma = G[:, :, :, :n].sum(axis=2)  # (B, K, n, n): dJ/dy_k's share of dJ/dy_{k+1}
        carried = np.empty((B, K, n))
        for k in range(K - 1, -1, -1):
            carried[:, k] = ybar
            ybar = alpha[:, k] + (Gamma[:, k] @ ybar[..., None])[..., 0]
        lam = a + (G @ carried[:, :, None, :, None])[..., 0]  # (B, K, s, D)
        pbar += np.einsum("bkr,bkrq->bq", lam.reshape(B, K, s * D), rhs_p)
    start = np.zeros((B, s + 1, D))
    for t in np.flatnonzero(owner == 0):
        start += weights[t][None, :, None] * cotangent[:, t, None, :]
    return ybar, start[:, 0, n:], pbar


def check_solution(sol, what: str):
    """The collocation polynomials of a solution whose derivatives can be taken, else a SensitivityError
    (a batch solved in groups, :class:`daemodel.dense.Groups`, only arises across switches: refused above)."""
    if sol.method != "radau":
        raise SensitivityError(
            f"{what}: derivatives are taken of radau's discrete solution (its stage equations); this solution is "
            f"{sol.method!r}'s: solve with method='radau'"
        )
    if sol.breakpoints or sol.events:
        raise SensitivityError(
            f"{what}: the model has {'events' if sol.events else 'time switches'}, across which the derivatives of "
            "the solution jump; daemodel does not differentiate through them yet: fit the span between two of them"
        )
    if not isinstance(sol.dense, CollocationPolynomials):
        raise SensitivityError(
            f"{what}: the solution keeps no record of its steps (dense_output=False, or a solve restarted at events): "
            "solve with dense_output=True"
        )
    return sol.dense


def alias_derivatives(compiled, alias: str, times, Y, Z, P) -> tuple[np.ndarray, np.ndarray]:
    """``(d alias / d(y, z) (N, n+m), d alias / dp (N, k))`` of an eliminated alias at the rows
    ``times (N,)``, ``Y``, ``Z``, ``P``: what the chain rule through its expression needs."""
    expr = next(e for a, e, _ in compiled.aliases if a == alias)
    numeric = compiled.numeric
    dw = numeric.batch_jacobian([expr], [*compiled.states, *compiled.algebraics])(times, Y, Z, P)[:, 0]
    return dw, numeric.batch_jacobian([expr], list(compiled.parameters))(times, Y, Z, P)[:, 0]


def objective_cotangent(sol, objective) -> tuple[np.ndarray, np.ndarray]:
    """``(dJ/du (B, T, n+m), dJ/dp (B, k))`` of an objective (see :meth:`Solution.gradient`): the
    outputs' share and, through aliases and parameters the objective names, the parameters' own."""
    import sympy as sp

    from daemodel.declaring.parse import parse_equation
    from daemodel.errors import DataError, ShapeError
    from daemodel.reals import real_array

    c = sol.compiled
    B, T, D = sol.batch_size, len(sol.t), len(c.states) + len(c.algebraics)
    Y, Z, P, times = sol._flat()
    kept = (*c.state_names, *c.algebraic_names)
    if isinstance(objective, dict):
        cot_u, cot_p = np.zeros((B * T, D)), np.zeros((B * T, len(c.parameters)))
        for name, data in objective.items():
            if name not in sol.values:
                raise UnknownSymbolError(
                    f"gradient: the data name {name!r}, which the solution does not have; it has {list(sol.names)}"
                )
            array = real_array(data, f"gradient: the data for {name!r}", error=DataError)
            if array.shape != sol[name].shape:
                raise ShapeError(
                    f"gradient: the data for {name!r} have shape {array.shape}; the solution's values {sol[name].shape}"
                )
            if np.isnan(array).all():  # (as fit refuses it: J would be 0 whatever the parameters)
                raise DataError(
                    f"gradient: the data for {name!r} are NaN everywhere: a series with no measurement; drop it"
                )
            misfit = np.nan_to_num(2 * (sol.values[name] - array.reshape(B, T)), nan=0.0).reshape(B * T)
            if name in kept:
                cot_u[:, kept.index(name)] += misfit
            else:  # an alias: through its expression
                dw, dp = alias_derivatives(c, name, times, Y, Z, P)
                cot_u += misfit[:, None] * dw
                cot_p += misfit[:, None] * dp
        return cot_u.reshape(B, T, D), cot_p.reshape(B, T, -1).sum(axis=1)
    table = {s.name: s for s in (c.t, *c.states, *c.algebraics, *c.parameters)}
    table.update({name: sp.Symbol(name) for name in c.alias_names})
    if isinstance(objective, str):
        phi = parse_equation(objective, table, "the gradient's objective")
    elif isinstance(objective, sp.Expr):
        stray = sorted(s.name for s in objective.free_symbols if s.name not in table)
        if stray:
            raise UnknownSymbolError(
                f"gradient: the objective names {stray}, which the solution does not have; it has "
                f"{list(sol.names)} and the parameters {list(c.parameter_names)}"
            )
        # through the parser as text: it admits the supported functions only (a sympy Function of any
        # name would otherwise reach the generated numeric code as written)
        phi = parse_equation(sp.sstr(objective), table, "the gradient's objective")
    else:
        raise SensitivityError(
            "gradient: the objective must be a dict of measured data by output name, or an expression of the "
            f"outputs (a string or sympy expression); got {type(objective).__name__}"
        )
    phi = phi.xreplace({sp.Symbol(name): expr for name, expr, _ in c.aliases})
    derivatives = [sp.diff(phi, v) for v in (*c.states, *c.algebraics, *c.parameters)]
    out = c.numeric.batch_function(derivatives)(times, Y, Z, P)
    if not np.isfinite(out).all():
        raise SensitivityError("gradient: the objective's derivatives are not finite on the solution")
    return out[:, :D].reshape(B, T, D), out[:, D:].reshape(B, T, -1).sum(axis=1)

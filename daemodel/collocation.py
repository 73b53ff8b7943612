"""The Radau IIA stage residual: the equations that Newton zeroes and the Radau-PINN minimises.

One step of size ``h`` from ``(t_n, y_n)`` with stage values ``Y_i ~ y(t_n + c_i h)`` and
``Z_i ~ z(t_n + c_i h)``, i = 1..s::

    F_i = Y_i - y_n - h sum_j a_ij f(t_n + c_j h, Y_j, Z_j, p)
    G_i = g(t_n + c_i h, Y_i, Z_i, p)

A network that predicts the step's end values ``y_end, z_end`` separately (the paper's
outputs y_{n+1}, z_{n+1}) adds three residuals::

    F_end = y_end - y_n - h sum_j b_j f(t_n + c_j h, Y_j, Z_j, p)
    G_end = g(t_n + h, y_end, z_end, p)
    S     = z_end - Z_s

Radau IIA is stiffly accurate (``b`` is the last row of ``A`` and ``c_s = 1``), so the
classical step takes ``y_{n+1} = Y_s`` and ``z_{n+1} = Z_s``, and all three vanish.  The paper's
loss terms are ``L_f = mean |F|^2`` (its sign ``y_n - (xi_i - h sum a f)`` is ``-F_i``), ``L_g =
mean |G|^2`` and ``L_s = mean |S|^2``.  :mod:`daemodel.backends.radau` solves ``F = 0, G = 0``
with Newton; the Radau-PINN trainer minimises the same function.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

# Full Newton (collocation_step): increments that stop shrinking (ratio above STAGNATION_THETA)
# while below STAGNATION_SIZE (relative to 1 + |value|) have reached the rounding floor of the
# residual.  That floor depends on the conditioning: on the squeezer (accelerations of 1e5) the
# increments wander at 1e-13, 50x radau's 10 eps; the last increment is returned as the
# solution's uncertainty.
STAGNATION_THETA, STAGNATION_SIZE = 0.5, 1e-10


@dataclass(frozen=True)
class StageResidual:
    """The residuals of one Radau IIA step.

    Attributes
    ----------
    F : Tensor, shape (..., s, n)
        Stage equations of the differential variables.
    G : Tensor, shape (..., s, m)
        Constraints at the stages.
    stage_f : Tensor, shape (..., s, n)
        ``f`` at the stages (reused by error estimates and the end row).
    F_end, G_end : Tensor, shape (..., n) and (..., m), or None
        End-value rows, when ``y_end`` (and ``z_end``) were given.
    S : Tensor, shape (..., m), or None
        ``z_end - Z_s``, when ``z_end`` was given.
    """

    F: object
    G: object
    stage_f: object
    F_end: object = None
    G_end: object = None
    S: object = None


def stage_residual(functions, A, b, c, t_n, h, y_n, Y, Z, p=None, y_end=None, z_end=None) -> StageResidual:
    """Evaluate the Radau IIA stage residual of one step.

    Parameters
    ----------
    functions : TorchFunctions
        The compiled ``f`` and ``g`` (:meth:`CompiledDAE.torch_functions`).
    A, b, c : Tensor, shapes (s, s), (s,), (s,)
        The tableau (:meth:`RadauIIA.to_torch`).
    t_n : Tensor, shape (...) or float
    h : Tensor, shape (...) or float
    y_n : Tensor, shape (..., n)
    Y : Tensor, shape (..., s, n)
    Z : Tensor, shape (..., s, m)
    p : Tensor, shape (..., k), optional
        Parameter values; the model's values when omitted.
    y_end : Tensor, shape (..., n), optional
    z_end : Tensor, shape (..., m), optional
        Requires ``y_end``.
    """
    import torch

    t_n = torch.as_tensor(t_n, dtype=Y.dtype, device=Y.device)
    h = torch.as_tensor(h, dtype=Y.dtype, device=Y.device)
    times = t_n[..., None] + c * h[..., None]  # (..., s)
    p_stage = None if p is None else p[..., None, :]
    stage_f = functions.f(times, Y, Z, p_stage)  # (..., s, n)
    hk = h[..., None, None] * stage_f
    F = Y - y_n[..., None, :] - torch.einsum("ij,...jn->...in", A, hk)
    G = functions.g(times, Y, Z, p_stage)
    F_end = G_end = S = None
    if y_end is not None:
        F_end = y_end - y_n - torch.einsum("j,...jn->...n", b, hk)
        if z_end is not None:
            G_end = functions.g(t_n + h, y_end, z_end, p)
            S = z_end - Z[..., -1, :]
    return StageResidual(F=F, G=G, stage_f=stage_f, F_end=F_end, G_end=G_end, S=S)


def model_jacobian(functions, t, y, z, p) -> object:
    """``d(f, g)/d(y, z)`` at points ``t (...)``, ``y (..., n)``, ``z (..., m)``, shape (..., D, D)
    with D = n + m: the compiler's symbolic Jacobian at its nonzeros, or, where it has none (a
    derivative outside the supported functions, or a system too large for a symbolic one),
    reverse-mode autograd with the D rows as one batch of cotangents.  (Forward mode would need
    fewer directions on a sparse system, but torch runs its rules for a Python scalar times a
    dual tensor through Python decompositions: 3-6x slower here.)"""
    import torch

    n, m = y.shape[-1], z.shape[-1]
    D, lead = n + m, y.shape[:-1]
    if functions.jacobian is not None:
        rows, cols = (torch.as_tensor(a, device=y.device) for a in functions.jacobian_pattern)
        J = y.new_zeros((*lead, D * D))
        J[..., rows * D + cols] = functions.jacobian(t, y, z, p)
        return J.reshape(*lead, D, D)
    with torch.enable_grad():
        y, z = y.detach().requires_grad_(), z.detach().requires_grad_()
        values = torch.cat([functions.f(t, y, z, p), functions.g(t, y, z, p)], dim=-1)  # (..., D)
        rows = torch.eye(D, dtype=y.dtype, device=y.device).reshape(D, *([1] * len(lead)), D)
        # each point's outputs depend on its own inputs only: one cotangent per row serves all points
        grads = torch.autograd.grad(
            values, (y, z), rows.expand(D, *values.shape), is_grads_batched=True, allow_unused=True
        )
    parts = [y.new_zeros((D, *x.shape)) if g is None else g for g, x in zip(grads, (y, z), strict=True)]
    return torch.cat(parts, dim=-1).movedim(0, -2)  # (row, ..., column) -> (..., row, column)


def stage_jacobian(functions, A, c, t_n, h, Y, Z, p=None):
    """``d(F, G)/d(Y, Z)`` of :func:`stage_residual`, shape (..., s D, s D) with D = n + m: rows
    stage by stage ``[F_i, G_i]``, columns stage by stage ``[Y_j, Z_j]``::

        dF_i/dY_j = delta_ij I - h a_ij f_y(j),   dF_i/dZ_j = -h a_ij f_z(j)
        dG_i/dY_j = delta_ij g_y(i),              dG_i/dZ_j = delta_ij g_z(i)

    the full Newton matrix of the stage equations (each stage's own Jacobian)."""
    import torch

    t_n = torch.as_tensor(t_n, dtype=Y.dtype, device=Y.device)
    h = torch.as_tensor(h, dtype=Y.dtype, device=Y.device)
    s, n, m = Y.shape[-2], Y.shape[-1], Z.shape[-1]
    D, lead = n + m, Y.shape[:-2]
    times = t_n[..., None] + c * h[..., None]  # (..., s)
    J = model_jacobian(functions, times, Y, Z, None if p is None else p[..., None, :])  # (..., s, D, D)
    hA = h[..., None, None] * A  # (..., s, s)
    jac = Y.new_zeros((*lead, s, D, s, D))
    jac[..., :n, :, :] = -torch.einsum("...ij,...jpq->...ipjq", hA, J[..., :n, :])
    stage = torch.arange(s, device=Y.device)
    jac[..., stage, n:, stage, :] = J[..., n:, :].movedim(-3, 0)
    jac[..., stage, :n, stage, :n] += torch.eye(n, dtype=Y.dtype, device=Y.device)
    return jac.reshape(*lead, s * D, s * D)


@dataclass(frozen=True)
class CollocationStep:
    """The collocation solution of one step per row, by full Newton (:func:`collocation_step`).

    Attributes
    ----------
    Y, Z : Tensor, shapes (..., s, n) and (..., s, m)
        The stage values; ``Y[..., -1, :]``, ``Z[..., -1, :]`` are the step's end values.
    converged : Tensor of bool, shape (...)
        Whether the last increment was below the tolerance, or stopped shrinking at the rounding
        floor (and everything is finite).
    increment : Tensor, shape (..., s, n + m)
        The last increment of each converged row: the stage values' uncertainty.
    jacobian : Tensor, shape (..., s D, s D)
        The stage equations' Jacobian at the last iterate: within the last increment (below the
        tolerance for a converged row) of the returned stage values, which is all a first-order
        sensitivity needs; one Jacobian fewer than evaluating it again.
    iterations : int
    """

    Y: object
    Z: object
    converged: object
    increment: object
    jacobian: object
    iterations: int

    def end_sensitivity(self):
        """``d(y_{n+1}, z_{n+1})/dy_n`` of the step map, shape (..., n + m, n): the stage
        equations' Jacobian solved against ``dF_i/dy_n = -I`` (the constraints hold no y_n)."""
        import torch

        s, n, m = self.Y.shape[-2], self.Y.shape[-1], self.Z.shape[-1]
        D = n + m
        rhs = self.Y.new_zeros((*self.Y.shape[:-2], s, D, n))
        rhs[..., :n, :] = torch.eye(n, dtype=self.Y.dtype, device=self.Y.device)
        X = torch.linalg.solve_ex(self.jacobian, rhs.reshape(*rhs.shape[:-3], s * D, n))[0]
        return X[..., (s - 1) * D :, :]


def collocation_step(functions, A, c, t_n, h, y_n, Y, Z, p=None, *, max_iterations: int, tol: float) -> CollocationStep:
    """Full Newton on the stage equations F = 0, G = 0 from the stage values ``Y``, ``Z``, every
    row of the batch at once (each with its own ``t_n``, ``h``, ``y_n``): the Radau IIA step that
    :mod:`daemodel.backends.radau` takes, solved to ``tol`` (increments relative to
    ``1 + |value|``) in at most ``max_iterations`` iterations.  A row whose matrix is singular or
    whose values leave f's domain ends with ``converged`` False."""
    import torch

    n = Y.shape[-1]
    W = torch.cat([Y, Z], dim=-1)
    converged = torch.zeros(W.shape[:-2], dtype=torch.bool, device=W.device)
    previous = torch.full_like(converged, math.inf, dtype=W.dtype)
    last = torch.zeros_like(W)
    iterations, J = 0, None
    for iterations in range(1, max_iterations + 1):  # noqa: B007  (the count is returned)
        res = stage_residual(functions, A, None, c, t_n, h, y_n, W[..., :n], W[..., n:], p)
        R = torch.cat([res.F, res.G], dim=-1).reshape(*W.shape[:-2], -1)
        J = stage_jacobian(functions, A, c, t_n, h, W[..., :n], W[..., n:], p)
        dW = torch.linalg.solve_ex(J, -R[..., None])[0][..., 0].reshape(W.shape)
        dW = torch.where(converged[..., None, None], torch.zeros_like(dW), dW)  # converged rows keep their values
        W = W + dW
        size = (dW.abs() / (1 + W.abs())).flatten(-2).amax(-1)
        # the increment is below tol, or has stopped shrinking while small (the rounding floor of R)
        settled = (size <= tol) | ((size >= STAGNATION_THETA * previous) & (size <= STAGNATION_SIZE))
        last = torch.where(converged[..., None, None], last, dW.abs())
        converged = converged | (torch.isfinite(size) & settled)
        previous = torch.where(converged, previous, size)
        if bool(converged.all()) or not bool(torch.isfinite(W).any()):
            break
    if J is None:  # no iteration: the Jacobian at the start
        J = stage_jacobian(functions, A, c, t_n, h, W[..., :n], W[..., n:], p)
    finite = torch.isfinite(W).flatten(-2).all(-1) & torch.isfinite(J).flatten(-2).all(-1)
    return CollocationStep(
        Y=W[..., :n], Z=W[..., n:], converged=converged & finite, increment=last, jacobian=J, iterations=iterations
    )


def extrapolation_matrix(c, ratio: float):
    """Radau's start guess: the Lagrange matrix (s, s+1) that carries a step's collocation
    polynomial, through its start (node 0) and its stages (nodes ``c``), to the stage nodes of
    the next step, ``ratio`` = h_next / h times as long (radau's Newton, the PINN's predictor)."""
    import numpy as np

    c = np.asarray(c, dtype=float)
    return lagrange_matrix(np.concatenate([[0.0], c]), 1.0 + c * ratio)


def extrapolation_polynomial(c, pattern=None):
    """Coefficients ``C (s+1, s, s+1)`` of :func:`extrapolation_matrix` as a polynomial in the ratio:
    ``L(ratio) = sum_k C[k] ratio^k``, evaluated by :func:`horner` in a few array operations (radau
    extrapolates every step, mostly at a new ratio: the product form costs 20 us a time there).

    ``pattern`` (s,): the stage values are read as a polynomial of degree s - 1 plus an unknown multiple
    of ``pattern`` at the stages (0 at the start node), and that polynomial alone is extrapolated
    (radau's guess of index-2 algebraic variables, whose stages carry ``A^-1 1`` times the start
    value's constraint defect over h; exact on polynomials of degree s - 1, blind to the pattern)."""
    import numpy as np
    from numpy.polynomial import polynomial as P

    c = np.asarray(c, dtype=float)
    nodes = np.concatenate([[0.0], c])
    s = len(c)
    C = np.zeros((s + 1, s, s + 1))
    if pattern is not None:
        # the monomials of degree < s and the pattern at the nodes, solved for: their coefficients
        # (rows) as functions of the node values; the monomials at 1 + c_i ratio expanded in the ratio
        basis = np.column_stack([nodes**k for k in range(s)] + [np.concatenate([[0.0], pattern])])
        coefficients = np.linalg.inv(basis)[:s]  # (s, s+1): the monomials' coefficients
        for i in range(s):
            for k in range(s):
                # (1 + c_i r)^k = sum_j binom(k, j) c_i^j r^j
                for j in range(k + 1):
                    C[j, i] += math.comb(k, j) * c[i] ** j * coefficients[k]
        return C
    for i in range(s):
        for j in range(s + 1):
            poly = np.array([1.0])
            for m in range(s + 1):
                if m != j:  # (1 + c_i r - x_m) / (x_j - x_m)
                    poly = P.polymul(poly, np.array([1.0 - nodes[m], c[i]]) / (nodes[j] - nodes[m]))
            C[: len(poly), i, j] = poly
    return C


def horner(C, x):
    """``sum_k C[k] x^k`` by Horner's rule, on numpy arrays or casadi expressions alike (the same
    operations in the same order, so both give the same bits)."""
    out = C[-1]
    for k in range(len(C) - 2, -1, -1):
        out = out * x + C[k]
    return out


def lagrange_matrix(nodes, points):
    """``L[i, j]``: the j-th Lagrange basis polynomial on ``nodes`` (N,) at ``points[i]`` (P,),
    shape (P, N), in numpy: the interpolation of stage values (a start guess, dense output)."""
    import numpy as np

    others, denominators = _lagrange_denominators(tuple(np.asarray(nodes, dtype=float).tolist()))
    factors = np.where(others, points[:, None, None] - np.asarray(nodes)[None, None, :], 1.0)  # x - x_m, (P, j, m)
    return factors.prod(axis=-1) / denominators


@functools.lru_cache(maxsize=64)
def _lagrange_denominators(nodes: tuple):
    """``(others, prod_m (x_j - x_m))`` of :func:`lagrange_matrix`'s nodes, ``others[j, m]``: m != j
    (computed once per node set: a dense output evaluates the same tableau's nodes on every solve)."""
    import numpy as np

    nodes = np.asarray(nodes)
    others = ~np.eye(len(nodes), dtype=bool)
    return others, np.where(others, nodes[:, None] - nodes[None, :], 1.0).prod(axis=-1)

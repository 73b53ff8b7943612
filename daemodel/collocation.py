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

from dataclasses import dataclass


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

"""The Radau-PINN loss: the Radau IIA stage residual that Newton zeroes, squared and weighted.

For N training inputs y_n with predictions ``Y_i, y_{n+1}, Z_i, z_{n+1}``
(:func:`daemodel.collocation.stage_residual` gives F, G, F_end, G_end, S)::

    L_f = 1/(N (s+1)) sum_samples (sum_i |F_i|^2 + |F_end|^2)
    L_g = 1/(N (s+1)) sum_samples (sum_i |G_i|^2 + |G_end|^2)
    L_s = 1/N         sum_samples |S|^2
    loss = W_f L_f + W_g L_g + W_s L_s = |r|^2

The residual vector ``r`` (per sample, weights folded in) is what Levenberg-Marquardt works
on; Adam and L-BFGS minimise ``|r|^2``.  At the classical Radau IIA solution (Newton's stage
values, ``y_{n+1} = Y_s``, ``z_{n+1} = Z_s``) every residual is zero.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from daemodel.collocation import stage_residual

TERMS = ("L_f", "L_g", "L_s")


@dataclass(frozen=True)
class Residuals:
    """Unweighted residuals of a batch of N samples.

    Attributes
    ----------
    F : Tensor, shape (N, s+1, n)
        Stage rows, then the end row (y_{n+1} with b).
    G : Tensor, shape (N, s+1, m)
        Constraints at the stages, then at (y_{n+1}, z_{n+1}).
    S : Tensor, shape (N, m)
        ``z_{n+1} - Z_s``.
    """

    F: torch.Tensor
    G: torch.Tensor
    S: torch.Tensor

    def terms(self) -> dict[str, float]:
        """The loss terms L_f, L_g, L_s (means as in the paper)."""
        N, rows = self.F.shape[0], self.F.shape[1]
        with torch.no_grad():
            return {
                "L_f": float((self.F**2).sum()) / (N * rows),
                "L_g": float((self.G**2).sum()) / (N * rows),
                "L_s": float((self.S**2).sum()) / N,
            }

    def max_abs(self) -> float:
        """The largest residual component: the stopping criterion."""
        with torch.no_grad():
            return max((float(r.abs().max()) if r.numel() else 0.0) for r in (self.F, self.G, self.S))


class RadauLoss:
    """Residuals of one segment ``[t_n, t_n + h]`` for a network's predictions.

    Parameters
    ----------
    functions : TorchFunctions
        The compiled, batched f and g.
    tableau : RadauIIA
    config : PINNConfig
        Supplies the weights W_f, W_g, W_s.
    dtype, device
    """

    def __init__(self, functions, tableau, config, dtype, device):
        self.functions = functions
        self.A, self.b, self.c = tableau.to_torch(dtype=dtype, device=device)
        self.stages = tableau.stages
        self.weights = (config.weight_f, config.weight_g, config.weight_s)

    def residuals(self, t_n: float, h: float, y_n, p, out) -> Residuals:
        """Residuals at inputs ``y_n`` (N, n), parameters ``p`` (N, k), predictions ``out``."""
        res = stage_residual(
            self.functions, self.A, self.b, self.c, t_n, h, y_n, out.Y, out.Z, p, y_end=out.y_end, z_end=out.z_end
        )
        F = torch.cat([res.F, res.F_end[:, None, :]], dim=1)
        G = torch.cat([res.G, res.G_end[:, None, :]], dim=1)
        return Residuals(F=F, G=G, S=res.S)

    def vector(self, residuals: Residuals, total: int) -> torch.Tensor:
        """Weighted residual vector, shape (N, R), with ``|r|^2`` = the loss over ``total`` samples."""
        W_f, W_g, W_s = self.weights
        rows = self.stages + 1
        N = residuals.F.shape[0]
        return torch.cat(
            [
                math.sqrt(W_f / (total * rows)) * residuals.F.reshape(N, -1),
                math.sqrt(W_g / (total * rows)) * residuals.G.reshape(N, -1),
                math.sqrt(W_s / total) * residuals.S,
            ],
            dim=1,
        )

"""The Radau-PINN's networks: the paper's "attention" MLP with an adaptive activation.

One segment's networks map an input ``x = (y_n, p)`` to the Radau IIA stage values
``Y_1..Y_s``, the end value ``y_{n+1}``, the algebraic stage values ``Z_1..Z_s`` and the end
value ``z_{n+1}``.  Each network is a modified MLP (Wang, Teng & Perdikaris 2021)::

    U = phi(x W_u + b_u),   R = phi(x W_r + b_r)
    H_1 = phi(eta * l * x W_1 + b_1)                    l trainable (Jagtap et al. 2020)
    M_k = phi(H_k W_k + b_k),  H_{k+1} = (1 - M_k) * U + M_k * R,   k = 1..depth-1
    N(x) = H_depth W_out + b_out

so ``depth`` counts the hidden layers H_1..H_depth.  Approach 2 ("per-variable") has one
network per differential variable (its s stages and end value) and two for the algebraic
variables (all stages; all end values); approach 1 ("shared") has one network for all
outputs.  The K networks of a segment are stored stacked (leading axis K) and evaluated in
one batched product per layer, which is what makes their Jacobians cheap.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

# Parameters stacked as (depth - 1, K, ...); all others are (K, ...).
GATE_PARAMETERS = ("W_gate", "b_gate")

ACTIVATION_FUNCTIONS = {
    "tanh": torch.tanh,
    "sigmoid": torch.sigmoid,
    "sin": torch.sin,
    "gelu": torch.nn.functional.gelu,
    "softplus": torch.nn.functional.softplus,
}


@dataclass(frozen=True)
class Outputs:
    """A segment's predictions for a batch of inputs.

    Attributes
    ----------
    Y : Tensor, shape (B, s, n)
    y_end : Tensor, shape (B, n)
    Z : Tensor, shape (B, s, m)
    z_end : Tensor, shape (B, m)
    """

    Y: torch.Tensor
    y_end: torch.Tensor
    Z: torch.Tensor
    z_end: torch.Tensor


def output_layout(n: int, m: int, stages: int, architecture: str) -> tuple[list[int], list[list[int]]]:
    """Output sizes of the K networks, and for each network the positions of its outputs
    in the flat vector ``[Y (s, n) row-major, y_end (n), Z (s, m) row-major, z_end (m)]``."""
    s = stages
    y_at = lambda i, j: i * n + j  # noqa: E731  (stage i, variable j)
    z_at = lambda i, j: s * n + n + i * m + j  # noqa: E731
    if architecture == "shared":
        total = (s + 1) * (n + m)
        return [total], [list(range(total))]
    sizes, positions = [], []
    for j in range(n):  # one network per differential variable: its stages, then its end value
        sizes.append(s + 1)
        positions.append([y_at(i, j) for i in range(s)] + [s * n + j])
    if m:
        sizes += [s * m, m]  # two for the algebraic variables: all stages; all end values
        positions.append([z_at(i, j) for i in range(s) for j in range(m)])
        positions.append([s * n + n + s * m + j for j in range(m)])
    return sizes, positions


class RadauNetwork(torch.nn.Module):
    """The networks of one segment, stacked.

    Parameters
    ----------
    inputs : int
        Input size d (states, then the parameters that vary).
    n, m : int
        Numbers of differential and algebraic variables.
    config : PINNConfig
    generator : torch.Generator
        Draws the initial weights (Xavier normal; biases zero; slope 1/eta).
    """

    def __init__(self, inputs: int, n: int, m: int, config, generator: torch.Generator):
        super().__init__()
        dtype = getattr(torch, config.dtype)
        self.n, self.m, self.stages = n, m, config.stages
        self.eta, self.increment = float(config.eta), config.increment
        self.activation = config.activation
        sizes, positions = output_layout(n, m, config.stages, config.architecture)
        K, w, d, out = len(sizes), config.width, inputs, max(sizes)
        self.count, self.sizes = K, sizes  # sizes: how many of its stacked outputs each network uses

        def weight(*shape):
            fan_in, fan_out = shape[-2], shape[-1]
            std = math.sqrt(2.0 / (fan_in + fan_out))
            return torch.nn.Parameter(torch.randn(*shape, generator=generator, dtype=dtype) * std)

        def bias(*shape):
            return torch.nn.Parameter(torch.zeros(*shape, dtype=dtype))

        self.W_u, self.b_u = weight(K, d, w), bias(K, 1, w)
        self.W_r, self.b_r = weight(K, d, w), bias(K, 1, w)
        self.W_1, self.b_1 = weight(K, d, w), bias(K, 1, w)
        self.slope = torch.nn.Parameter(torch.full((K, 1, 1), 1.0 / self.eta, dtype=dtype))
        self.W_gate = weight(config.depth - 1, K, w, w)
        self.b_gate = bias(config.depth - 1, K, 1, w)
        self.W_out, self.b_out = weight(K, w, out), bias(K, 1, out)
        # Column of the stacked output (K * out) that holds each entry of the flat output vector.
        order = torch.empty(sum(sizes), dtype=torch.long)
        for k, pos in enumerate(positions):
            order[pos] = torch.arange(len(pos)) + k * out
        self.register_buffer("order", order)
        # Input normalisation x -> (x - center) / scale, set from the training inputs.
        self.register_buffer("center", torch.zeros(d, dtype=dtype))
        self.register_buffer("scale", torch.ones(d, dtype=dtype))

    def forward(self, x: torch.Tensor, stacked: bool = False) -> torch.Tensor:
        """Raw network outputs, shape (B, U), for inputs ``x`` of shape (B, d); with ``stacked``,
        each network's own outputs, shape (K, B, out) (padded to the largest network)."""
        phi = ACTIVATION_FUNCTIONS[self.activation]
        xn = (x - self.center) / self.scale
        U = phi(torch.einsum("bd,kdw->kbw", xn, self.W_u) + self.b_u)
        R = phi(torch.einsum("bd,kdw->kbw", xn, self.W_r) + self.b_r)
        H = phi(self.eta * self.slope * torch.einsum("bd,kdw->kbw", xn, self.W_1) + self.b_1)
        for W, b in zip(self.W_gate, self.b_gate, strict=True):
            M = phi(torch.bmm(H, W) + b)
            H = (1 - M) * U + M * R
        out = torch.bmm(H, self.W_out) + self.b_out  # (K, B, out)
        if stacked:
            return out
        return out.permute(1, 0, 2).reshape(x.shape[0], -1)[:, self.order]

    def split(self, raw: torch.Tensor, y_n: torch.Tensor, h) -> Outputs:
        """Stage and end values from raw outputs (B, U); ``y_n`` (B, n) for the increment form."""
        n, m, s = self.n, self.m, self.stages
        B = raw.shape[0]
        Y = raw[:, : s * n].reshape(B, s, n)
        y_end = raw[:, s * n : s * n + n]
        if self.increment:
            Y = y_n[:, None, :] + h * Y
            y_end = y_n + h * y_end
        Z = raw[:, s * n + n : s * n + n + s * m].reshape(B, s, m)
        z_end = raw[:, s * n + n + s * m :]
        return Outputs(Y=Y, y_end=y_end, Z=Z, z_end=z_end)

    def predict(self, x: torch.Tensor, h) -> Outputs:
        """Stage and end values for inputs ``x`` (B, d) whose first n columns are y_n."""
        return self.split(self(x), x[:, : self.n], h)

    def normalise(self, x: torch.Tensor) -> None:
        """Centre and scale the inputs on the spread of ``x`` (B, d), keeping the function the
        network computes (the first layers absorb the change).  One point is used raw, as in the paper."""
        if x.shape[0] == 1:
            center, scale = torch.zeros_like(self.center), torch.ones_like(self.scale)
        else:
            lo, hi = x.min(0).values, x.max(0).values
            spread = (hi - lo) / 2
            center, scale = (hi + lo) / 2, torch.where(spread > 0, spread, torch.ones_like(spread))
        # (x - c_old) / s_old = ((x - c_new) / s_new) * (s_new / s_old) + (c_new - c_old) / s_old
        ratio, shift = scale / self.scale, (center - self.center) / self.scale
        with torch.no_grad():
            for W, b, gain in ((self.W_u, self.b_u, 1.0), (self.W_r, self.b_r, 1.0), (self.W_1, self.b_1, None)):
                gain = self.eta * self.slope if gain is None else gain
                b += gain * torch.einsum("d,kdw->kw", shift, W)[:, None, :]
                W *= ratio[None, :, None]
            self.center.copy_(center)
            self.scale.copy_(scale)

    def unstack(self, params: dict) -> dict:
        """``params`` (as ``named_parameters``) with the network axis K moved first and each
        network's slice kept as a K = 1 stack: vmapping over axis 0 then gives one network."""
        return {
            name: (p.movedim(1, 0).unsqueeze(2) if name in GATE_PARAMETERS else p.unsqueeze(1))
            for name, p in params.items()
        }

    def parameter_count(self) -> int:
        return sum(p.numel() for p in self.parameters())

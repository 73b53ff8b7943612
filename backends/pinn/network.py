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
one batched product per layer.  Their Jacobians with respect to their parameters, which
Levenberg-Marquardt needs at every step, are written out the same way, for all K networks at
once and kept in factors (:meth:`RadauNetwork.hidden_jacobian`, :class:`HiddenJacobian`).
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import torch

# Parameters stacked as (depth - 1, K, ...); all others are (K, ...).
GATE_PARAMETERS = ("W_gate", "b_gate")
# The parameters before the output layer, in registration order (as ``named_parameters``).
HIDDEN_PARAMETERS = ("W_u", "b_u", "W_r", "b_r", "W_1", "b_1", "slope", "W_gate", "b_gate")

ACTIVATION_FUNCTIONS = {
    "tanh": torch.tanh,
    "sigmoid": torch.sigmoid,
    "sin": torch.sin,
    "gelu": torch.nn.functional.gelu,
    "softplus": torch.nn.functional.softplus,
}


def _sigmoid_derivative(a, value):
    value = torch.sigmoid(a) if value is None else value
    return value * (1 - value)


def _gelu_derivative(a, value):
    return 0.5 * (1 + torch.erf(a / math.sqrt(2))) + a * torch.exp(-0.5 * a * a) / math.sqrt(2 * math.pi)


def _softplus_derivative(a, value):
    return torch.where(a > 20, torch.ones_like(a), torch.sigmoid(a))  # torch's softplus is linear above 20


# phi'(a), given a and (when known, else None) phi(a).
ACTIVATION_DERIVATIVES = {
    "tanh": lambda a, value: 1 - (torch.tanh(a) if value is None else value) ** 2,
    "sigmoid": _sigmoid_derivative,
    "sin": lambda a, value: torch.cos(a),
    "gelu": _gelu_derivative,
    "softplus": _softplus_derivative,
}


@dataclass(frozen=True)
class HiddenJacobian:
    """The Jacobian of the last hidden layer H (K networks, B inputs, w units) with respect to
    each network's hidden parameters, in factors.

    Every hidden parameter but the slope belongs to a linear map ``A = a W + b`` followed by
    the activation, so its Jacobian is an outer product: ``dH_r/dW[i, j] = a_i abar_{rj}`` and
    ``dH_r/db_j = abar_{rj}``, with ``abar = dH_r/dA`` from reverse mode.  Gram matrices and
    transposed products then cost O(w^3) per map instead of O(w^2 P).

    Attributes
    ----------
    H : Tensor, shape (K, B, w)
    maps : tuple of (a, abar)
        ``a`` (K, B, inputs of the map), ``abar`` (K, B, w rows of H, units of the map), for
        W_u/b_u, W_r/b_r, W_1/b_1 and each gated layer W_gate[l]/b_gate[l].
    slope : Tensor, shape (K, B, w, 1)
        dH/dl of the adaptive slope.
    """

    H: torch.Tensor
    maps: tuple
    slope: torch.Tensor

    def dense(self, W: torch.Tensor | None = None) -> torch.Tensor:
        """dH/dtheta, shape (K, B, w, P_hidden), or with ``W`` (K, w, out) the rows of ``W^T dH``,
        shape (K, B, out, P_hidden) (the Jacobian of outputs ``H W``, formed without dH).  Columns
        in the order of :data:`HIDDEN_PARAMETERS`, each parameter of one network flattened as
        :meth:`RadauNetwork.unstack` lays it out."""
        K, B, w = self.H.shape
        rows = w if W is None else W.shape[-1]

        def project(abar):  # (K, B, w, units) -> (K, B, rows, units)
            return abar if W is None else torch.einsum("kri,kbrj->kbij", W, abar)

        def outer(a, abar):
            return (a[:, :, None, :, None] * abar[:, :, :, None, :]).reshape(K, B, rows, -1)

        (a_u, bar_u), (a_r, bar_r), (a_1, bar_1), *gates = ((a, project(abar)) for a, abar in self.maps)
        columns = [outer(a_u, bar_u), bar_u, outer(a_r, bar_r), bar_r, outer(a_1, bar_1), bar_1, project(self.slope)]
        columns += [outer(a, abar) for a, abar in gates] + [abar for _, abar in gates]
        return torch.cat(columns, dim=3)

    def gram(self) -> torch.Tensor:
        """``dH dH^T`` over each network's hidden parameters, shape (K, B w, B w)."""
        K, B, w = self.H.shape
        total = torch.einsum("kbr,kcq->kbrcq", self.slope[..., 0], self.slope[..., 0])
        for a, abar in self.maps:  # weights and bias: (a_b . a_c + 1) (abar_b abar_c^T)
            inputs = a @ a.transpose(1, 2) + 1  # (K, B, B)
            total = total + inputs[:, :, None, :, None] * torch.einsum("kbrj,kcqj->kbrcq", abar, abar)
        return total.reshape(K, B * w, B * w)

    def transpose(self, v: torch.Tensor) -> torch.Tensor:
        """``sum_b dH_b^T v_b`` for ``v`` (K, B, w): shape (K, P_hidden), in :meth:`dense`'s order."""
        K = v.shape[0]
        parts = []
        for a, abar in self.maps:
            back = torch.einsum("kbr,kbrj->kbj", v, abar)  # (K, B, units)
            parts.append((torch.einsum("kbi,kbj->kij", a, back).reshape(K, -1), back.sum(1)))
        (W_u, b_u), (W_r, b_r), (W_1, b_1), *gates = parts
        slope = torch.einsum("kbr,kbr->k", v, self.slope[..., 0])[:, None]
        columns = [W_u, b_u, W_r, b_r, W_1, b_1, slope] + [W for W, _ in gates] + [b for _, b in gates]
        return torch.cat(columns, dim=1)

    def diagonal(self, Q: torch.Tensor) -> torch.Tensor:
        """``diag(sum_b dH_b^T Q_b dH_b)`` for ``Q`` (K, B, w, w): shape (K, P_hidden), in :meth:`dense`'s order."""
        K = Q.shape[0]
        parts = []
        for a, abar in self.maps:
            quad = torch.einsum("kbrj,kbrq,kbqj->kbj", abar, Q, abar)  # (K, B, units)
            parts.append((torch.einsum("kbi,kbj->kij", a * a, quad).reshape(K, -1), quad.sum(1)))
        (W_u, b_u), (W_r, b_r), (W_1, b_1), *gates = parts
        slope = torch.einsum("kbr,kbrq,kbq->k", self.slope[..., 0], Q, self.slope[..., 0])[:, None]
        columns = [W_u, b_u, W_r, b_r, W_1, b_1, slope] + [W for W, _ in gates] + [b for _, b in gates]
        return torch.cat(columns, dim=1)


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


def parameter_count_of(inputs: int, n: int, m: int, config, copies: int = 1) -> int:
    """The parameters of one segment's networks (:class:`RadauNetwork` with these arguments), counted
    without building them: ``K (3 (d w + w) + 1 + (depth - 1) (w^2 + w) + w out + out)`` for K
    networks of width w, d inputs and ``out`` outputs (the largest network's)."""
    count, out = output_sizes(n, m, config.stages, config.architecture)
    K, w, d = count * copies, config.width, inputs
    return K * (3 * (d * w + w) + 1 + (config.depth - 1) * (w * w + w) + w * out + out)


def output_sizes(n: int, m: int, stages: int, architecture: str) -> tuple[int, int]:
    """The number of networks of :func:`output_layout` and the largest one's outputs, in O(1) (the
    layout's lists took 0.1-0.2 s at 10^5 unknowns, in the PINN's memory check before it refuses)."""
    if architecture == "shared":
        return 1, (stages + 1) * (n + m)
    sizes = ([stages + 1] if n else []) + ([stages * m, m] if m else [])
    return n + (2 if m else 0), max(sizes, default=0)


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
    copies : int
        Independent sets of networks, one per sample of a batch (``batch="independent"``): set
        b sees only input row b, so a batch must come whole and in order.  1: every network
        sees every input (a trajectory, or ``batch="shared"``: the inputs carry the parameters).
    """

    def __init__(self, inputs: int, n: int, m: int, config, generator: torch.Generator, copies: int = 1):
        super().__init__()
        dtype = getattr(torch, config.dtype)
        self.n, self.m, self.stages = n, m, config.stages
        self.eta, self.increment = float(config.eta), config.increment
        self.activation = config.activation
        self.copies = copies
        one, positions = output_layout(n, m, config.stages, config.architecture)
        U = sum(one)
        # copy b's networks follow copy b-1's; copy b's outputs are flat positions b U .. (b+1) U - 1
        sizes = one * copies
        positions = [[b * U + i for i in pos] for b in range(copies) for pos in positions]
        K, w, d, out = len(sizes), config.width, inputs, max(sizes)
        self.count, self.sizes = K, sizes  # sizes: how many of its stacked outputs each network uses
        self.output_count = U  # U: stage and end values of every variable (of one sample)

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
        # Column of the stacked output (K * out) that holds each entry of the flat output vector
        # (of every copy, one after the other).
        order = torch.empty(sum(sizes), dtype=torch.long)
        for k, pos in enumerate(positions):
            order[pos] = torch.arange(len(pos)) + k * out
        self.register_buffer("order", order)
        # Input normalisation x -> (x - center) / scale, set from the training inputs.
        self.register_buffer("center", torch.zeros(d, dtype=dtype))
        self.register_buffer("scale", torch.ones(d, dtype=dtype))

    def forward(self, x: torch.Tensor, stacked: bool = False, params: dict | None = None) -> torch.Tensor:
        """Raw network outputs, shape (B, U), for inputs ``x`` of shape (B, d); with ``stacked``,
        each network's own outputs, shape (K, B', out) (padded to the largest network; B' = B,
        or 1 for independent copies, each of which sees its own row).  ``params`` (as
        ``named_parameters``) replaces the network's own parameters."""
        p = dict(self.named_parameters()) if params is None else params
        H = self._hidden(p, x)[0]
        out = torch.baddbmm(p["b_out"], H, p["W_out"])  # (K, B', out)
        if stacked:
            return out
        return self.unstacked(out)

    def evaluate(self, x: torch.Tensor, params: dict) -> tuple:
        """The raw outputs (B, U) at ``params``, and the forward pass's intermediates, which
        :meth:`hidden_jacobian` at the same ``params`` and ``x`` takes instead of recomputing them."""
        hidden = self._hidden(params, x)
        return self.unstacked(torch.baddbmm(params["b_out"], hidden[0], params["W_out"])), hidden

    def unstacked(self, out: torch.Tensor) -> torch.Tensor:
        """Stacked outputs (K, B', out) as the flat outputs (B, U) of every input row."""
        if out.shape[1] == 1 and self.copies == 1:  # one input row
            return out.reshape(1, -1)[:, self.order]
        rows = out.shape[1] if self.copies == 1 else self.copies
        return out.permute(1, 0, 2).reshape(out.shape[1], -1)[:, self.order].reshape(rows, -1)

    def stack(self, flat: torch.Tensor) -> torch.Tensor:
        """Flat values (B, U) of every input row in the stacked layout (K, B', out), zero at padding."""
        out = max(self.sizes)
        rows = flat.shape[0] if self.copies == 1 else 1
        stacked = flat.new_zeros(rows, self.count * out)
        stacked[:, self.order] = flat.reshape(rows, -1)
        return stacked.reshape(rows, self.count, out).transpose(0, 1)

    def network_inputs(self, xn: torch.Tensor) -> torch.Tensor:
        """Normalised inputs (B, d) as each network sees them, (K, B', d): all rows, or, for
        independent copies, its own row only."""
        if self.copies == 1:
            return xn.expand(self.count, *xn.shape)
        if xn.shape[0] != self.copies:
            raise ValueError(f"these networks are {self.copies} independent copies; got {xn.shape[0]} input rows")
        return xn.repeat_interleave(self.count // self.copies, dim=0)[:, None, :]

    def _hidden(self, p: dict, x: torch.Tensor):
        """The last hidden layer H_depth, shape (K, B', w), and what its Jacobian needs."""
        phi = ACTIVATION_FUNCTIONS[self.activation]
        xn = self.network_inputs((x - self.center) / self.scale)  # (K, B', d)
        A_u = torch.baddbmm(p["b_u"], xn, p["W_u"])
        A_r = torch.baddbmm(p["b_r"], xn, p["W_r"])
        X_1 = torch.bmm(xn, p["W_1"])
        A_1 = torch.addcmul(p["b_1"], self.eta * p["slope"], X_1)
        U, R, H = phi(A_u), phi(A_r), phi(A_1)
        H_1 = H
        layers = []  # (H_k, pre-activation of M_k, M_k) of each gated layer
        for W, b in zip(p["W_gate"], p["b_gate"], strict=True):
            A = torch.baddbmm(b, H, W)
            M = phi(A)
            layers.append((H, A, M))
            H = torch.addcmul(U, M, R - U)  # (1 - M) U + M R
        return H, (xn, A_u, A_r, X_1, A_1, U, R, H_1, layers)

    def hidden_jacobian(
        self, params: dict, x: torch.Tensor, rows: torch.Tensor | None = None, forward: tuple | None = None
    ) -> HiddenJacobian:
        """The last hidden layer and its Jacobian with respect to each network's own hidden
        parameters (all but ``W_out``, ``b_out``), by reverse mode written out for its w rows,
        kept in the factors of every linear map (see :class:`HiddenJacobian`).  With ``rows``
        (K, w, out) the reverse pass starts from ``rows^T`` instead: the factors are those of the
        Jacobian of ``H rows`` (the outputs less their bias, for ``rows = W_out``), out rows each
        instead of w, which is all that one input per network needs.  ``forward``: the
        intermediates of :meth:`evaluate` at these ``params`` and ``x``."""
        p = params
        H, (xn, A_u, A_r, X_1, A_1, U, R, H_1, layers) = self._hidden(p, x) if forward is None else forward
        K, B, w = H.shape
        dphi = ACTIVATION_DERIVATIVES[self.activation]
        if rows is None:
            bar_H = torch.eye(w, dtype=H.dtype, device=H.device).expand(K, B, w, w)
        else:
            bar_H = rows.transpose(1, 2)[:, None].expand(K, B, rows.shape[-1], w)
        # bar_H: (K, B, row, unit of the current layer), a row of H_depth or of H rows
        bar_U = bar_R = None  # zero until a gated layer adds to them
        gates = []
        for (H_k, A, M), W in zip(reversed(layers), reversed(list(p["W_gate"])), strict=True):
            to_U, to_R = bar_H * (1 - M)[:, :, None, :], bar_H * M[:, :, None, :]
            bar_U = to_U if bar_U is None else bar_U + to_U
            bar_R = to_R if bar_R is None else bar_R + to_R
            bar_A = bar_H * ((R - U) * dphi(A, M))[:, :, None, :]
            gates.append((H_k, bar_A))
            bar_H = bar_A @ W.transpose(-1, -2)[:, None]
        if bar_U is None:  # depth 1: H = H_1, U and R take no part
            bar_U = bar_R = torch.zeros_like(bar_H)
        bar_A1 = bar_H * dphi(A_1, H_1)[:, :, None, :]
        bar_Au = bar_U * dphi(A_u, U)[:, :, None, :]
        bar_Ar = bar_R * dphi(A_r, R)[:, :, None, :]
        inputs = xn
        return HiddenJacobian(
            H=H,
            maps=(
                (inputs, bar_Au),
                (inputs, bar_Ar),
                (self.eta * p["slope"] * inputs, bar_A1),  # A_1 = eta l x W_1 + b_1
                *gates[::-1],
            ),
            slope=self.eta * (bar_A1 * X_1[:, :, None, :]).sum(-1, keepdim=True),
        )

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

    def values(self, raw: torch.Tensor, y_n: torch.Tensor, h) -> torch.Tensor:
        """The stage and end values that :meth:`split` reads from raw outputs (B, U), flat in the
        same order ``[Y (s, n), y_end, Z (s, m), z_end]``; ``y_n`` (B, n) for the increment form."""
        if not self.increment:
            return raw
        B, k = raw.shape[0], (self.stages + 1) * self.n
        stages = (h * raw[:, :k]).reshape(B, self.stages + 1, self.n) + y_n[:, None, :]
        return torch.cat([stages.reshape(B, k), raw[:, k:]], dim=1)

    def value_steps(self, step: torch.Tensor, h) -> torch.Tensor:
        """How much a step of the raw outputs (B, U) moves the values of :meth:`values`."""
        if not self.increment:
            return step
        k = (self.stages + 1) * self.n
        return torch.cat([h * step[:, :k], step[:, k:]], dim=1)

    def predict(self, x: torch.Tensor, h) -> Outputs:
        """Stage and end values for inputs ``x`` (B, d) whose first n columns are y_n."""
        return self.split(self(x), x[:, : self.n], h)

    def start_at_rest(self, x: torch.Tensor, z: torch.Tensor) -> None:
        """Shift the output biases so that, on average over the inputs ``x`` (B, d), every stage
        and end value starts at the step's start: ``Y = y_n`` (increment form: raw outputs 0) and
        ``Z = z_n``, the consistent algebraic values ``z`` (B, m) (from the compiler's solve, which
        follows ``m.guess``).  That is the constant guess Newton starts from; a random start can sit
        where a constraint is singular (often z = 0), on another root, or outside f's domain."""
        n, s = self.n, self.stages
        if self.copies == 1:  # one set of networks for every row: on average
            z = z.mean(0, keepdim=True)
        target = torch.cat([z.new_zeros(len(z), s * n + n), z.repeat(1, s + 1)], dim=1)  # flat, as split reads
        self.start_at(x, target)

    def start_at(self, x: torch.Tensor, target: torch.Tensor) -> tuple:
        """Shift the output biases so that the raw outputs at the inputs ``x`` (B, d) are ``target``
        (B, U) (for one set of networks over several rows: on average, ``target`` (1, U)).
        Returns the raw outputs (B, U) at ``x`` after the shift (the outputs move with it, to
        rounding) and the forward pass's intermediates (as :meth:`evaluate`; the shift leaves them)."""
        with torch.no_grad():
            p = dict(self.named_parameters())
            hidden = self._hidden(p, x)
            raw = torch.baddbmm(p["b_out"], hidden[0], p["W_out"])
            mean = raw.mean(1, keepdim=True) if raw.shape[1] > 1 else raw
            shift = self.stack(target) - mean * self.used()[:, None, :]
            self.b_out += shift
            return self.unstacked(raw + shift), hidden

    def used(self) -> torch.Tensor:
        """1 at the stacked outputs (K, out) that a network uses, 0 at its padding."""
        sizes = torch.tensor(self.sizes, device=self.b_out.device)
        out = self.b_out.shape[-1]
        return (torch.arange(out, device=sizes.device)[None, :] < sizes[:, None]).to(self.b_out.dtype)

    def raw_outputs(self, Y: torch.Tensor, Z: torch.Tensor, y_n: torch.Tensor, h) -> torch.Tensor:
        """The raw outputs (B, U) that :meth:`split` reads as the stage values ``Y`` (B, s, n) and
        ``Z`` (B, s, m), the last stage also as the end values (Radau IIA is stiffly accurate)."""
        B = Y.shape[0]
        if self.increment:
            Y = (Y - y_n[:, None, :]) / h
        return torch.cat([Y.reshape(B, -1), Y[:, -1], Z.reshape(B, -1), Z[:, -1]], dim=1)

    def normalise(self, x: torch.Tensor) -> None:
        """Centre and scale the inputs on the spread of ``x`` (B, d), keeping the function the
        network computes (the first layers absorb the change).  One point is used raw, as in the
        paper, and so are independent copies (each sees one point)."""
        if x.shape[0] == 1 or self.copies > 1:
            if not (self.center.any() or (self.scale != 1).any()):
                return  # already raw
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

    def clone(self) -> RadauNetwork:
        """An independent copy (parameters and buffers copied; a warm start's new network): what
        ``copy.deepcopy`` gives, without its recursive walk (a tenth of a segment's time there)."""
        twin = copy.copy(self)
        twin.__dict__ = {key: v.copy() if isinstance(v, dict | list | set) else v for key, v in self.__dict__.items()}
        twin._parameters = {name: torch.nn.Parameter(p.detach().clone()) for name, p in self._parameters.items()}
        twin._buffers = {name: b.clone() for name, b in self._buffers.items()}
        twin._modules = {}
        return twin

    def unstack(self, params: dict) -> dict:
        """``params`` (as ``named_parameters``) with the network axis K moved first and each
        network's slice kept as a K = 1 stack: vmapping over axis 0 then gives one network."""
        return {
            name: (p.movedim(1, 0).unsqueeze(2) if name in GATE_PARAMETERS else p.unsqueeze(1))
            for name, p in params.items()
        }

    def parameter_count(self) -> int:
        return sum(p.numel() for p in self.parameters())

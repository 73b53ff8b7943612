"""Levenberg-Marquardt's linear systems for stacked networks (used by :mod:`.train`).

J = du/dtheta of K networks is block diagonal (an output depends on its own network's
parameters only) and is kept in factors (:class:`~.network.HiddenJacobian`); each system
solves ``(J^T J + mu I) delta = -J^T e`` (or its residual-space form) in whichever space is
smaller, and reports the decrease of the merit its step predicts.
"""

from __future__ import annotations

import torch
from daemodel.backends.pinn.network import HIDDEN_PARAMETERS

# Columns of W_out's and b_out's Jacobian follow the hidden parameters'.
BLOCK_ORDER = (*HIDDEN_PARAMETERS, "W_out", "b_out")
# Where every set of networks sees one input (a trajectory, independent networks per sample), LM
# measures its steps in a metric that weighs the hidden parameters' squares by 1 / this: a step
# moves mostly the output layer, in which the outputs are linear, so Gauss-Newton's model of them
# holds over longer steps (the hidden parameters still move).  Measured LM iterations (1 -> 1e-4):
# squeezer 226 -> 99, car axis 300 -> 201, slider-crank at h = 0.01 87 -> 58, heat 36 -> 25;
# 0 (the output layer alone, a random-feature network) took squeezer to 29 but left heat flagged.
HIDDEN_STEP_WEIGHT = 1e-4


def output_layer_jacobian(hidden, W, valid):
    """du/dtheta of each network, shape (K, B, out, P/K), from its last hidden layer and that
    layer's Jacobian (``hidden``, a :class:`HiddenJacobian`), the output weights ``W`` (K, w, out)
    and the outputs in use ``valid`` (K, out).  Columns: hidden parameters, W_out (w, out), b_out."""
    H = hidden.H
    K, B, w = H.shape
    out = W.shape[-1]
    eye = torch.diag_embed(valid)[:, None]  # (K, 1, out, out): output i moves with column i only
    weights = (H[:, :, None, :, None] * eye[:, :, :, None, :]).reshape(K, B, out, w * out)
    return torch.cat([hidden.dense(W), weights, eye.expand(K, B, out, out)], dim=3)


class NetworkGram:
    """J = du/dtheta of the K networks at N inputs, kept in factors, with each network's Gram
    matrix ``G_k = J_k J_k^T`` (N out, N out).  With u = H W_out + b_out,
    ``G_k = W^T (dH dH^T) W + (H H^T + 1) I``, and dH dH^T comes from the factors of
    :class:`HiddenJacobian`: the (out, P) Jacobian is never formed.

    Parameters
    ----------
    hidden : HiddenJacobian
        The last hidden layer (K, N, w) and its Jacobian.
    W : Tensor, shape (K, w, out)
        Output weights, zero columns at padded outputs.
    valid : Tensor, shape (K, out)
        1 at the outputs in use, 0 at padding.
    where : Tensor, shape (K, P/K)
        Each network's positions in the flat parameter vector (:meth:`SegmentTrainer._block_index`).
    P : int
    hidden_weight : float
        The hidden parameters' weight in the step's metric (:data:`HIDDEN_STEP_WEIGHT`, or 1):
        J's hidden columns count as scaled by its square root, and the step in them by it again.

    Attributes
    ----------
    groups : list of (networks, count, G)
        Networks with equal output counts share one batched matrix of their own size (approach 2:
        the n differential networks have s + 1 outputs, padded to the algebraic ones' s m):
        their indices (k,), the count, and G (k, N count, N count).
    """

    def __init__(self, hidden, W, valid, where, P: int, hidden_weight: float = 1.0):
        H = hidden.H
        K, N, w = H.shape
        self.hidden, self.W, self.valid, self.where, self.P = hidden, W, valid, where, P
        self.hidden_weight = hidden_weight
        M = hidden_weight * hidden.gram().reshape(K, N, w, N, w)
        inner = H @ H.transpose(1, 2) + 1  # (K, N, N): the output layer's share, per output
        counts = valid.sum(1).long()
        self.groups = []
        for count in sorted(set(counts.tolist())):
            k = torch.nonzero(counts == count)[:, 0]
            Wg = W[k, :, :count]
            G = torch.einsum("kai,kbacd,kdj->kbicj", Wg, M[k], Wg)
            G = G + inner[k][:, :, None, :, None] * torch.eye(count, dtype=W.dtype, device=W.device)[:, None, :]
            self.groups.append((k, count, G.reshape(len(k), N * count, N * count)))

    def transpose(self, v: torch.Tensor) -> torch.Tensor:
        """``J^T v`` for ``v`` (K, N, out) (zero at padded outputs), its hidden entries weighted by
        ``hidden_weight`` (the step in the parameters themselves): the flat parameter vector (P,)."""
        H = self.hidden.H
        K = H.shape[0]
        hidden = self.hidden_weight * self.hidden.transpose(v @ self.W.transpose(1, 2))
        weights = torch.einsum("kba,kbi->kai", H, v).reshape(K, -1)
        local = torch.cat([hidden, weights, v.sum(1)], dim=1)  # (K, P/K) in BLOCK_ORDER
        flat = torch.empty(self.P, dtype=v.dtype, device=v.device)
        flat[self.where.reshape(-1)] = local.reshape(-1)
        return flat

    def largest_diagonal(self, C: torch.Tensor) -> float:
        """The largest entry of ``diag(J^T C J)`` for a block-diagonal ``C`` (K, N, out, out) (one
        block per network and input): the first damping's scale."""
        H = self.hidden.H
        hidden = self.hidden_weight * self.hidden.diagonal(self.W[:, None] @ C @ self.W[:, None].transpose(-1, -2))
        Cii = torch.diagonal(C, dim1=-2, dim2=-1)  # (K, N, out)
        weights = torch.einsum("kba,kbi->kai", H**2, Cii)
        return float(torch.cat([hidden.reshape(-1), weights.reshape(-1), Cii.sum(1).reshape(-1)]).max())


class OutputGramSystem:
    """Levenberg-Marquardt on the Newton corrections e, solved per network in its outputs:
    ``delta_k = -J_k^T (J_k J_k^T + mu I)^{-1} e_k`` with J_k = du_k/dtheta_k, which equals
    ``-(J^T J + mu I)^{-1} J^T e`` of :class:`OutputSystem` (a push-through identity) at the
    cost of a (N out, N out) solve per network.  With the gram's ``hidden_weight`` D (one input
    per set of networks, a case :class:`OutputSystem` never serves) J is read as J D^(1/2) and
    the step in the parameters is D^(1/2) times it.

    Parameters
    ----------
    gram : NetworkGram
    e : Tensor, shape (K, N, out)
        The merit, zero at padded outputs.
    """

    def __init__(self, gram: NetworkGram, e):
        self.gram = gram
        N = e.shape[1]
        self.parts = []
        for k, count, G in gram.groups:
            eg = e[k, :, :count].reshape(len(k), N * count)
            self.parts.append((k, count, G, eg, (G @ eg[..., None])[..., 0]))

    @property
    def scale(self) -> float:
        """The largest diagonal entry of J^T J, J in the weighted metric (sets the first damping)."""
        K, N, out = self.gram.valid.shape[0], self.gram.hidden.H.shape[1], self.gram.W.shape[-1]
        return self.gram.largest_diagonal(torch.diag_embed(self.gram.valid)[:, None].expand(K, N, out, out))

    def step(self, mu: float):
        """``(delta, predicted decrease of |e|^2 / 2)``, or None when a ``G + mu I`` is not positive definite."""
        H = self.gram.hidden.H
        K, N, _ = H.shape
        w = H.new_zeros(K, N, self.gram.W.shape[-1])
        predicted = 0.0
        for k, count, G, e, Ge in self.parts:
            eye = torch.eye(G.shape[-1], dtype=G.dtype, device=G.device)
            L, info = torch.linalg.cholesky_ex(G + mu * eye)
            if bool((info != 0).any()):
                return None
            wg = torch.cholesky_solve(e[..., None], L)[..., 0]  # (k, N count)
            Gw = (G @ wg[..., None])[..., 0]
            # delta = -J^T w, g = J^T e: delta.delta = w.G w, delta.g = -w.G e
            predicted += 0.5 * float((mu * (wg * Gw) + wg * Ge).sum())
            w[k, :, :count] = wg.reshape(len(k), N, count)
        return -self.gram.transpose(w), predicted


def output_groups(sizes, units: int) -> list:
    """Networks grouped for :class:`OneInputSystem`: ``(networks, count)``, the indices of
    networks with at most ``count`` outputs (``sizes``), solved as one batch padded to ``count``.
    The networks of one output count join the group of the next larger count where their padding
    costs fewer multiplies (``(count^2 - size^2) units`` each, in G's product) than a batch's
    overhead, :data:`GROUP_OVERHEAD`: per-variable heat by lines (4, 6 and 2 outputs) is one
    group; the squeezer's 39 and 13 are one and its fourteen 4s another."""
    groups = []  # [members, count], largest count first
    for size in sorted(set(sizes), reverse=True):
        members = [k for k, other in enumerate(sizes) if other == size]
        if groups and len(members) * (groups[-1][1] ** 2 - size**2) * units <= GROUP_OVERHEAD:
            groups[-1][0].extend(members)
        else:
            groups.append([members, size])
    return [(torch.tensor(sorted(members)), count) for members, count in groups]


# A batch of networks costs about this many multiplies' time in fixed per-operation overhead
# (~15 torch operations of ~5 us on this machine's 1-thread float64 at ~5 GFlop/s): padding that
# costs less than this keeps networks of different output counts in one batch.
GROUP_OVERHEAD = 300_000


class OneInputSystem:
    """Levenberg-Marquardt on the Newton corrections e where every network sees one input (a
    trajectory, or independent networks per sample): :class:`OutputGramSystem`'s step, whose
    factors collapse to one product per network.  With one input each hidden map's Jacobian
    is ``a_i abar_j`` (weights) and ``abar_j`` (biases), so with ``V = W^T [abar of every map,
    dH/dl]`` (out, units) and each map's column weight ``|a|^2 + 1``::

        G_k = D_h V diag(|a|^2 + 1) V^T + (|H|^2 + 1) I   (out, out)

    and a step ``delta = -D J^T w`` is ``-D_h a (V^T w)`` and ``-D_h V^T w`` in the hidden maps,
    ``-H w^T`` and ``-w`` in the output layer.  The networks are solved in batches of
    :func:`output_groups`, padded outputs carrying an identity row (their correction, 0, stays 0).

    Parameters
    ----------
    hidden : HiddenJacobian
        At one input per network, H (K, 1, w): with rows ``W`` (the factors of ``H W``, whose
        reverse pass gives ``V`` directly, :meth:`RadauNetwork.hidden_jacobian`) or of H itself
        (w rows, where W has more columns than H has units).
    W : Tensor, shape (K, w, out)
        Output weights, zero columns at padded outputs.
    valid : Tensor, shape (K, out)
    e : Tensor, shape (K, 1, out)
        The Newton corrections, zero at padded outputs.
    hidden_weight : float
        D_h, the hidden parameters' weight in the step's metric (:data:`HIDDEN_STEP_WEIGHT`).
    groups : list of (networks, count)
        :func:`output_groups`.
    projected : bool
        Whether ``hidden`` holds the factors of ``H W`` (else of H).
    """

    def __init__(self, hidden, W, valid, e, hidden_weight: float, groups, projected: bool):
        self.H, self.weight = hidden.H[:, 0], hidden_weight
        K = valid.shape[0]
        self.inputs = [a[:, 0] for a, _ in hidden.maps]  # (K, inputs of the map)
        bars = [abar[:, 0] for _, abar in hidden.maps] + [hidden.slope[:, 0]]  # (K, rows, units)
        self.units = [bar.shape[-1] for bar in bars]
        factors = torch.cat(bars, dim=2)  # (K, rows, units)
        norms = [(a * a).sum(-1, keepdim=True) + 1 for a in self.inputs] + [self.H.new_ones(K, 1)]
        columns = torch.cat([norm.expand(-1, u) for norm, u in zip(norms, self.units, strict=True)], dim=1)
        beta = (self.H * self.H).sum(1) + 1
        self.whole = len(groups) == 1  # one batch of all K networks: no gathers
        self.parts = []
        for networks, count in groups:
            at = slice(None) if self.whole else networks
            Wg = W[at, :, :count]
            V = factors[at, :count] if projected else Wg.transpose(1, 2) @ factors[at]
            used = valid[at, :count]
            G = hidden_weight * (V * columns[at][:, None, :]) @ V.transpose(1, 2)
            G = G + beta[at][:, None, None] * torch.diag_embed(used) + torch.diag_embed(1 - used)
            eg = e[at, 0, :count, None]  # (k, count, 1)
            self.parts.append((at, count, V, G, eg, G @ eg))

    @property
    def scale(self) -> float:
        """The largest diagonal entry of J^T J, J in the weighted metric (sets the first damping):
        ``a_i^2 |V_j|^2`` and ``|V_j|^2`` in a map's weights and bias, ``|V_l|^2`` in the slope
        (all by D_h), ``H_i^2`` in W_out, 1 in b_out."""
        K = self.H.shape[0]
        inputs = [(a * a).amax(1, keepdim=True).clamp(min=1.0) for a in self.inputs] + [self.H.new_ones(K, 1)]
        inputs = torch.cat([a.expand(-1, u) for a, u in zip(inputs, self.units, strict=True)], dim=1)  # (K, units)
        largest = max(float(((V * V).sum(1) * inputs[at]).max()) for at, _, V, *_ in self.parts)
        return max(self.weight * largest, float((self.H * self.H).max()), 1.0)

    def step(self, mu: float):
        """``(delta, predicted decrease of |e|^2 / 2)``, delta by parameter name (shaped as the
        network's parameters), or None when a ``G + mu I`` is not positive definite."""
        K, w_units = self.H.shape
        predicted = 0.0
        if not self.whole:
            w = self.H.new_zeros(K, max(count for _, count, *_ in self.parts))
            back = self.H.new_zeros(K, sum(self.units))
        for at, count, V, G, e, Ge in self.parts:
            eye = torch.eye(count, dtype=G.dtype, device=G.device)
            L, info = torch.linalg.cholesky_ex(G + mu * eye)
            if bool((info != 0).any()):
                return None
            wg = torch.cholesky_solve(e, L)  # (k, count, 1)
            # delta = -D J^T w, g = J^T e: delta.D^-1 delta = w.G w, delta.g = -w.G e
            predicted += 0.5 * float((mu * (wg * (G @ wg)) + wg * Ge).sum())
            backg = -self.weight * (V.transpose(1, 2) @ wg)[..., 0]  # (k, units): -D_h V^T w
            if self.whole:
                w, back = wg[..., 0], backg
            else:
                w[at, :count], back[at] = wg[..., 0], backg
        parts = torch.split(back, self.units, dim=1)
        maps = [(a[:, :, None] * b[:, None, :], b[:, None, :]) for a, b in zip(self.inputs, parts, strict=False)]
        (W_u, b_u), (W_r, b_r), (W_1, b_1), *gates = maps
        delta = {"W_u": W_u, "b_u": b_u, "W_r": W_r, "b_r": b_r, "W_1": W_1, "b_1": b_1}
        delta["slope"] = parts[-1][:, :, None]
        delta["W_gate"] = torch.stack([W for W, _ in gates]) if gates else back.new_zeros(0, K, w_units, w_units)
        delta["b_gate"] = torch.stack([b for _, b in gates]) if gates else back.new_zeros(0, K, 1, w_units)
        delta["W_out"] = -self.H[:, :, None] * w[:, None, :]
        delta["b_out"] = -w[:, None, :]
        return delta, predicted


class ResidualGramSystem:
    """Levenberg-Marquardt on the residual vector r with J = dr/dtheta = (dr/du)(du/dtheta),
    ``delta = -J^T (J J^T + mu I)^{-1} r``, where ``J J^T = sum_k (dr/du_k) G_k (dr/du_k)^T``
    with the networks' Gram matrices G_k: one (N R, N R) solve.

    Parameters
    ----------
    gram : NetworkGram
    Ru : Tensor, shape (N, R, K, out)
        dr_b/du_b with the outputs in the networks' stacked layout (zero columns for padding).
    r : Tensor, shape (N R,)
    """

    def __init__(self, gram: NetworkGram, Ru, r):
        N, R = Ru.shape[:2]
        self.gram, self.Ru, self.r = gram, Ru, r
        A = Ru.new_zeros(N, R, N, R)
        for k, count, G in gram.groups:
            Rk = Ru[:, :, k, :count]  # (N, R, k, count)
            A += torch.einsum("brki,kbicj,cqkj->brcq", Rk, G.reshape(len(k), N, count, N, count), Rk)
        self.A = A.reshape(N * R, N * R)
        self.Ar = self.A @ r

    @property
    def scale(self) -> float:
        """The largest diagonal entry of J^T J, J in the weighted metric (sets the first damping)."""
        C = torch.einsum("brki,brkj->kbij", self.Ru, self.Ru)  # (dr/du)^T (dr/du), per network and input
        return self.gram.largest_diagonal(C)

    def step(self, mu: float):
        """``(delta, predicted decrease of |r|^2 / 2)``, or None when ``A + mu I`` is not positive definite."""
        eye = torch.eye(self.A.shape[0], dtype=self.A.dtype, device=self.A.device)
        L, info = torch.linalg.cholesky_ex(self.A + mu * eye)
        if bool((info != 0).any()):
            return None
        w = torch.cholesky_solve(self.r[:, None], L)[:, 0]
        # delta = -J^T w, g = J^T r: delta.delta = w.A w, delta.g = -w.A r
        predicted = 0.5 * float(mu * (w @ (self.A @ w)) + w @ self.Ar)
        N, R = self.Ru.shape[:2]
        v = torch.einsum("brki,br->kbi", self.Ru, w.reshape(N, R))  # (dr/du)^T w, per network
        return -self.gram.transpose(v), predicted


class OutputSystem:
    """Levenberg-Marquardt on the Newton corrections e, ``(J^T J + mu I) delta = -J^T e`` with
    J = du/dtheta, solved as one (P/K, P/K) system per network.

    Parameters
    ----------
    JtJ : Tensor, shape (K, P/K, P/K)
    Jte : Tensor, shape (K, P/K)
    where : Tensor, shape (K, P/K)
    P : int
    """

    def __init__(self, JtJ, Jte, where, P: int):
        self.JtJ, self.Jte, self.where, self.P = JtJ, Jte, where, P

    @property
    def scale(self) -> float:
        """The largest diagonal entry of J^T J (sets the first damping)."""
        return float(torch.diagonal(self.JtJ, dim1=1, dim2=2).max())

    def step(self, mu: float):
        """``(delta, predicted decrease of |e|^2 / 2)``, or None when ``J^T J + mu I`` is not positive definite."""
        eye = torch.eye(self.JtJ.shape[-1], dtype=self.JtJ.dtype, device=self.JtJ.device)
        L, info = torch.linalg.cholesky_ex(self.JtJ + mu * eye)
        if bool((info != 0).any()):
            return None
        local = -torch.cholesky_solve(self.Jte[..., None], L)[..., 0]  # (K, P/K)
        predicted = 0.5 * float((local * (mu * local - self.Jte)).sum())  # delta.(mu delta - g) / 2, g = J^T e
        delta = torch.empty(self.P, dtype=local.dtype, device=local.device)
        delta[self.where.reshape(-1)] = local.reshape(-1)
        return delta, predicted

"""Training one segment's networks: Levenberg-Marquardt, L-BFGS or Adam on the Radau loss.

Levenberg-Marquardt drives to zero the vector e that stacks every sample's Newton correction
``e_b = (dr_b/du_b)^+ r_b``: how far the network outputs u_b (stage and end values) of sample b
are from its own collocation solution, to first order.  J = du/dtheta, and each step solves
``(J^T J + mu I) delta = -J^T e`` (Gauss-Newton on Newton targets); the damping mu follows
Nielsen's gain-ratio rule.  At e = 0 every residual r is zero, so with one sample per segment
(a trajectory) training ends on Newton's stage values, the classical Radau solution.

Why Newton corrections rather than the residuals themselves (the gradient the loss gives): an
index-2 algebraic variable moves the residual by O(h) only, and the multipliers of a chain of
rods by less, so a least-squares fit of r through the networks takes tiny, badly scaled steps
(measured on the first segment of a chain of rods: 83 LM steps for three links and more than
200 for eight, against 6 and 9 here) and, over a box of many samples where r cannot vanish,
leaves z errors of about residual / h.  Measured in e, the
nonlinearity of the networks costs a constant factor per step, not a stall.

The Jacobian is never formed whole.  dr/du comes from the model's Jacobian at the stages and
the end point (:meth:`RadauLoss.jacobian`).  An output depends only on its own network's
parameters, so J^T J is block diagonal over the K networks (approach 2: one per differential
variable, two for the algebraic ones); each block is solved in whichever space is smaller:

* its outputs (few samples, the usual trajectory): ``delta_k = -J_k^T (J_k J_k^T + mu I)^{-1} e_k``,
  an (N out, N out) system whose matrix is built from the factors of the hand-written reverse
  pass (:class:`HiddenJacobian`), O(w^3) per layer;
* its parameters (many samples, surrogates): ``(J_k^T J_k + mu I) delta_k = -J_k^T e_k``, (P/K, P/K).

Training stops on the residual, every |r| component below ``tol``, or with ``tol=None`` after
``iterations`` (sooner if no step decreases the merit).  A segment that ends above ``tol`` says
so in its stats; whether the answer is good enough is the certificate's verdict
(:mod:`.certificate`), not the residual's.
"""

from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass

import numpy as np
import torch
from daemodel.backends.pinn.network import HIDDEN_PARAMETERS

from daemodel.errors import InvalidOptionError, TrainingError

# A loss this many times its starting value has diverged (Adam/L-BFGS; LM never goes up).
EXPLODE_FACTOR = 1e8
# LM's first damping, relative to the largest diagonal entry of J^T J (Madsen, Nielsen & Tingleff).
LM_TAU = 1e-6
# LM gives up when the damping exceeds this multiple of that diagonal: no step decreases the loss.
LM_MAX_DAMPING = 1e16
# L-BFGS runs in chunks of this many iterations between tolerance checks.
LBFGS_CHUNK = 20
# LM fits the Newton corrections of the outputs where a full Newton step on them cuts the
# residual norm to at most this fraction (Newton converges from there); measured at the start of
# a segment, it is 0.004-0.08 for the fast mode's networks (paper problems, chains of 3-8 rods,
# a 30-point grid) and 1-176 for the paper's networks, whose first outputs are random.
NEWTON_CONTRACTION = 0.5
# Columns of W_out's and b_out's Jacobian follow the hidden parameters'.
BLOCK_ORDER = (*HIDDEN_PARAMETERS, "W_out", "b_out")
# Entries of du/dtheta held at once; larger sample sets are processed in chunks.
JACOBIAN_ENTRIES = 2**24
# Progress is reported at most this often (seconds).
REPORT_SECONDS = 0.2
# Adam on a GPU (one CUDA graph per iteration): eager iterations before the capture, and
# iterations between two reads of the loss terms.
GRAPH_WARMUP = 3
GRAPH_CHECK_EVERY = 100


@dataclass(frozen=True)
class SegmentStats:
    """What training one segment did.

    Attributes
    ----------
    segment : int
    t : float
        The segment's start time.
    h : float
    iterations : int
    L_f, L_g, L_s : float
        Final loss terms (unweighted means, as in the paper).
    max_residual : float
        Final largest residual component (the quantity compared with ``tol``).
    seconds : float
    inputs_low, inputs_high : tuple of float
        Range of the training inputs, per input (states, then the parameters that are inputs):
        where the segment's networks were trained, checked by ``Surrogate.solve``.
    converged : bool
        Whether every residual met ``tol`` (True for a fixed budget, tol=None).
    largest : str
        Where the largest residual is (equation, row, sample).
    """

    segment: int
    t: float
    h: float
    iterations: int
    L_f: float
    L_g: float
    L_s: float
    max_residual: float
    seconds: float
    inputs_low: tuple
    inputs_high: tuple
    converged: bool = True
    largest: str = ""


@dataclass(frozen=True)
class Segment:
    """One segment's training problem.

    Attributes
    ----------
    index : int
    t : float
    h : float
    x : Tensor, shape (N, d)
        Network inputs: states, then the parameters that vary.
    p : Tensor, shape (N, k)
        Full parameter vectors of the inputs.
    """

    index: int
    t: float
    h: float
    x: torch.Tensor
    p: torch.Tensor


def _where(segment: Segment) -> str:
    return f"segment {segment.index + 1} (t = {segment.t:.6g} to {segment.t + segment.h:.6g})"


class SegmentTrainer:
    """Trains a :class:`RadauNetwork` on one :class:`Segment` with the configured optimizer.

    Parameters
    ----------
    net : RadauNetwork
    loss : RadauLoss
    config : PINNConfig
    report : callable(iteration, terms), optional
        Called with the loss terms as training goes (for a progress bar).
    """

    def __init__(self, net, loss, config, report=None):
        self.net, self.loss, self.config = net, loss, config
        self.report = report or (lambda iteration, terms: None)

    # ---- residuals --------------------------------------------------------------------------
    def residuals(self, segment: Segment, raw=None):
        n = self.net.n
        raw = self.net(segment.x) if raw is None else raw
        out = self.net.split(raw, segment.x[:, :n], segment.h)
        return self.loss.residuals(segment.t, segment.h, segment.x[:, :n], segment.p, out)

    def finite_start(self, segment: Segment) -> bool:
        """Whether the network's current predictions give finite residuals on ``segment``."""
        with torch.no_grad():
            return all(math.isfinite(value) for value in self.residuals(segment).terms().values())

    def _vector_of_raw(self, segment: Segment, raw):
        return self.loss.vector(self.residuals(segment, raw), segment.x.shape[0])

    def _check(self, segment: Segment, residuals, iteration: int, start: float | None) -> dict:
        terms = residuals.terms()
        bad = [name for name, value in terms.items() if not math.isfinite(value)]
        if bad:
            if iteration == 0:  # even the start at rest (Newton's constant guess) left f's or g's domain
                fix = "the start values themselves, or the network's first predictions, lie outside f's or g's domain"
                fix += " (e.g. inside sqrt or log): check the initial values, or shorten h"
            elif self.config.optimizer == "lm":
                fix = "shorten h"
            else:
                fix = "lower learning_rate, shorten h, or use optimizer='lm'"
            raise TrainingError(
                f"pinn: {_where(segment)}: loss term {', '.join(bad)} is not finite at iteration {iteration}; {fix}"
            )
        total = self._weighted(terms)
        if start is not None and total > EXPLODE_FACTOR * max(start, 1e-300):
            worst = max(terms, key=lambda k: terms[k])
            raise TrainingError(
                f"pinn: {_where(segment)}: the loss exploded at iteration {iteration} ({start:.3g} -> {total:.3g}, "
                f"mostly {worst} = {terms[worst]:.3g}); lower learning_rate or shorten h"
            )
        return terms

    def _weighted(self, terms: dict) -> float:
        W_f, W_g, W_s = self.loss.weights
        return W_f * terms["L_f"] + W_g * terms["L_g"] + W_s * terms["L_s"]

    def _done(self, residuals) -> bool:
        return self.config.tol is not None and residuals.max_abs() <= self.config.tol

    def _finish(self, segment: Segment, iterations: int, began: float) -> SegmentStats:
        with torch.no_grad():
            residuals = self.residuals(segment)
        terms = self._check(segment, residuals, iterations, None)
        worst = residuals.max_abs()
        _, where = residuals.largest(getattr(self.loss, "names", None))
        # a missed tol is not an error here: the certificate judges the answer (backend.certified_status)
        return SegmentStats(
            segment=segment.index,
            t=segment.t,
            h=segment.h,
            iterations=iterations,
            max_residual=worst,
            seconds=time.perf_counter() - began,
            inputs_low=tuple(segment.x.amin(0).tolist()),
            inputs_high=tuple(segment.x.amax(0).tolist()),
            converged=self.config.tol is None or worst <= self.config.tol,
            largest=where,
            **terms,
        )

    def train(self, segment: Segment) -> SegmentStats:
        """Train until every residual is below ``tol`` (or ``iterations`` for tol=None)."""
        began = time.perf_counter()
        method = {"lm": self._levenberg_marquardt, "lbfgs": self._lbfgs, "adam": self._adam}[self.config.optimizer]
        iterations = method(segment)
        return self._finish(segment, iterations, began)

    # ---- Adam and L-BFGS ----------------------------------------------------------------------
    def _adam(self, segment: Segment) -> int:
        return self._adam_graphed(segment) if segment.x.is_cuda else self._adam_eager(segment)

    def _adam_eager(self, segment: Segment) -> int:
        optimizer = torch.optim.Adam(self.net.parameters(), lr=self.config.learning_rate)
        start, last_report = None, 0.0
        for iteration in range(self.config.iterations):
            optimizer.zero_grad()
            residuals = self.residuals(segment)
            r = self.loss.vector(residuals, segment.x.shape[0])
            loss = (r**2).sum()
            terms = self._check(segment, residuals, iteration, start)
            start = self._weighted(terms) if start is None else start
            if time.perf_counter() - last_report > REPORT_SECONDS:
                self.report(iteration, terms)
                last_report = time.perf_counter()
            if self._done(residuals):
                return iteration
            loss.backward()
            optimizer.step()
        return self.config.iterations

    def _adam_graphed(self, segment: Segment) -> int:
        """Adam on a GPU, each iteration (forward, loss, backward, step) replayed as one captured
        CUDA graph.  A segment's networks see one or a few inputs, so eager Adam is bound by
        kernel launches (hundreds per iteration); the graph launches them at once.  The loss terms
        are read, checked and compared with ``tol`` every :data:`GRAPH_CHECK_EVERY` iterations,
        at the parameters reached so far, by one more evaluation outside the graph."""
        params = list(self.net.parameters())
        optimizer = torch.optim.Adam(params, lr=self.config.learning_rate, capturable=True)
        N, device = segment.x.shape[0], segment.x.device
        # t and h as tensors on the device: a Python float would be copied from the host inside the graph
        graphed = Segment(
            index=segment.index,
            t=torch.tensor(segment.t, dtype=segment.x.dtype, device=device),
            h=torch.tensor(segment.h, dtype=segment.x.dtype, device=device),
            x=segment.x,
            p=segment.p,
        )

        def iteration():
            r = self.loss.vector(self.residuals(graphed), N)
            (r**2).sum().backward()
            optimizer.step()

        def check(done: int, start):
            with torch.no_grad():
                residuals = self.residuals(segment)
            terms = self._check(segment, residuals, done, start)
            self.report(done, terms)
            return terms, self._done(residuals)

        total = self.config.iterations
        terms, finished = check(0, None)
        start = self._weighted(terms)
        if finished or total == 0:
            return 0
        warmup = min(GRAPH_WARMUP, total)  # eager iterations on a side stream: Adam's state, autograd's buffers
        side = torch.cuda.Stream(device)
        side.wait_stream(torch.cuda.current_stream(device))
        with torch.cuda.stream(side):
            for _ in range(warmup):
                optimizer.zero_grad(set_to_none=True)
                iteration()
        torch.cuda.current_stream(device).wait_stream(side)
        done = warmup
        graph = torch.cuda.CUDAGraph()
        optimizer.zero_grad(set_to_none=True)  # the graph's backward allocates .grad in its own pool
        with torch.cuda.graph(graph):
            iteration()
        while done < total:
            for _ in range(min(GRAPH_CHECK_EVERY - done % GRAPH_CHECK_EVERY, total - done)):
                graph.replay()
                done += 1
            terms, finished = check(done, start)
            if finished:
                return done
        return done

    def _lbfgs(self, segment: Segment) -> int:
        optimizer = torch.optim.LBFGS(
            self.net.parameters(),
            lr=self.config.learning_rate,
            max_iter=LBFGS_CHUNK,
            history_size=50,
            tolerance_grad=0.0,
            tolerance_change=0.0,
            line_search_fn="strong_wolfe",
        )
        start = None

        def closure():
            optimizer.zero_grad()
            r = self._vector_of_raw(segment, self.net(segment.x))
            loss = (r**2).sum()
            loss.backward()
            return loss

        done = 0
        while done < self.config.iterations:
            with torch.no_grad():
                residuals = self.residuals(segment)
            terms = self._check(segment, residuals, done, start)
            start = self._weighted(terms) if start is None else start
            self.report(done, terms)
            if self._done(residuals):
                return done
            before = optimizer.state[optimizer._params[0]].get("n_iter", 0)
            optimizer.step(closure)
            after = optimizer.state[optimizer._params[0]].get("n_iter", 0)
            if after == before:  # L-BFGS made no progress: the loss is flat to rounding
                break
            done += after - before
        return done

    # ---- Levenberg-Marquardt --------------------------------------------------------------------
    def _output_jacobian(self, segment: Segment, raw: torch.Tensor) -> torch.Tensor:
        """dr_b/du_b of every sample b with respect to its raw network outputs, shape (N, R, U),
        from the model's Jacobian at the stages and the end point (:meth:`RadauLoss.jacobian`)."""
        net, n = self.net, self.net.n
        y_n = segment.x[:, :n]
        out = net.split(raw, y_n, segment.h)
        Ru = self.loss.jacobian(segment.t, segment.h, y_n, segment.p, out)
        if net.increment:  # Y = y_n + h N(x), y_end = y_n + h N(x)
            Ru[..., : (net.stages + 1) * n] *= segment.h
        return Ru

    def _correction(self, segment: Segment, raw, r):
        """Every sample's Newton correction ``e = R_u^+ r``, shape (N, U): the step of its raw
        outputs to its collocation solution, to first order; NaN where r or R_u is not finite."""
        Ru = self._output_jacobian(segment, raw)
        if not (bool(torch.isfinite(r).all()) and bool(torch.isfinite(Ru).all())):
            # a step into NaN is rejected; a start in NaN is reported by _check
            return torch.full_like(raw, math.nan)
        return torch.linalg.lstsq(Ru, r[..., None]).solution[..., 0]

    def _merit(self, segment: Segment, params: dict, space: str):
        """Residuals and the vector that LM drives to zero: in ``"output"`` space every sample's
        Newton correction (:meth:`_correction`), in ``"residual"`` space the residual vector r."""
        with torch.no_grad():
            raw = self.net(segment.x, params=params)
            residuals = self.residuals(segment, raw)
            r = self.loss.vector(residuals, segment.x.shape[0])
            if space == "residual":
                return residuals, r.reshape(-1)
            return residuals, self._correction(segment, raw, r).reshape(-1)

    def _newton_contracts(self, segment: Segment, params: dict):
        """Whether the full Newton step on the outputs, ``u - e``, cuts the residual norm to at most
        :data:`NEWTON_CONTRACTION` of its value: where it does, the Newton corrections are a guide
        and LM fits them; where not (far from the solution, dr/du nearly singular: the paper's
        networks start from random stage values), LM works on the residuals.

        Returns ``(contracts, residuals, r, e)``."""
        with torch.no_grad():
            raw = self.net(segment.x, params=params)
            residuals = self.residuals(segment, raw)
            N = segment.x.shape[0]
            r = self.loss.vector(residuals, N)
            e = self._correction(segment, raw, r)
            newton = self.loss.vector(self.residuals(segment, raw - e), N)
            contracts = bool(torch.linalg.norm(newton) <= NEWTON_CONTRACTION * torch.linalg.norm(r))
        return contracts, residuals, r.reshape(-1), e.reshape(-1)

    def _levenberg_marquardt(self, segment: Segment) -> int:
        params = {name: p.detach().clone() for name, p in self.net.named_parameters()}
        names = list(params)
        sizes = [params[k].numel() for k in names]
        # With few samples the residual-space system is small (N R <= P / K), and LM works there
        # until a Newton step on the outputs contracts, then on the Newton corrections; with many
        # (surrogates) always on the corrections.
        N, K = segment.x.shape[0], self.net.count
        # (independent copies: Newton corrections only; each starts at rest, Newton's constant guess)
        fallback = self.net.copies == 1 and N * (self.net.output_count + self.net.m) <= sum(sizes) // K
        if fallback:
            contracts, residuals, r, e = self._newton_contracts(segment, params)
            space = "output" if contracts else "residual"
            e = e if contracts else r
        else:
            space = "output"
            residuals, e = self._merit(segment, params, space)
        self.report(0, self._check(segment, residuals, 0, None))
        mu, nu, system, scale = None, 2.0, None, 1.0
        iteration = 0
        while iteration < self.config.iterations and not self._done(residuals):
            iteration += 1
            if system is None:
                system = self._normal_system(segment, params, e, space)
                if mu is None:
                    scale = system.scale
                    mu = LM_TAU * scale
            step = system.step(mu)
            if step is None:  # not positive definite: more damping
                mu, nu = mu * nu, nu * 2
                continue
            delta, predicted = step
            trial = {}
            offset = 0
            for name, size in zip(names, sizes, strict=True):
                trial[name] = params[name] + delta[offset : offset + size].reshape(params[name].shape)
                offset += size
            residuals_t, e_t = self._merit(segment, trial, space)
            actual = 0.5 * float(e @ e - e_t @ e_t)
            if math.isfinite(actual) and actual > 0 and predicted > 0:
                rho = actual / predicted
                params, residuals, e = trial, residuals_t, e_t
                mu *= max(1 / 3, 1 - (2 * rho - 1) ** 3)
                nu, system = 2.0, None
                self.report(iteration, self._check(segment, residuals, iteration, None))
                if space == "residual" and not self._done(residuals):
                    contracts, _, _, correction = self._newton_contracts(segment, params)
                    if contracts:  # near enough for Newton: fit its corrections from here
                        space, mu, e = "output", None, correction
            else:
                mu, nu = mu * nu, nu * 2
                if mu > LM_MAX_DAMPING * scale:
                    if space == "residual" or not fallback:
                        break  # no step decreases the merit: report through _finish
                    # no step decreases the Newton corrections: continue on the residuals
                    space, mu, nu, system = "residual", None, 2.0, None
                    _, e = self._merit(segment, params, space)
        with torch.no_grad():
            for name, p in self.net.named_parameters():
                p.copy_(params[name])
        return iteration

    def _normal_system(self, segment: Segment, params: dict, e: torch.Tensor, space: str = "output"):
        """The linearised merit ``e + J delta`` as an :class:`OutputGramSystem` (J = du/dtheta; few
        outputs per network: a (N out, N out) solve per network), an :class:`OutputSystem` (many:
        a (P/K, P/K) solve per network) or, in residual space, a :class:`ResidualGramSystem`
        (J = dr/dtheta: one (N R, N R) solve).  An output depends on its own network's parameters
        only, so du/dtheta is block diagonal over the networks and never formed whole."""
        net, K, N = self.net, self.net.count, segment.x.shape[0]
        out = max(net.sizes)
        P = sum(p.numel() for p in params.values())
        where = self._block_index(params)  # (K, P/K): flat parameter positions of each network
        sizes = torch.tensor(net.sizes, device=e.device)
        valid = (torch.arange(out, device=e.device)[None, :] < sizes[:, None]).to(e.dtype)  # (K, out): outputs in use
        W = params["W_out"] * valid[:, None, :]  # padded outputs take no part
        if space == "residual":
            with torch.no_grad():
                Ru = self._output_jacobian(segment, net(segment.x, params=params))  # (N, R, U)
            stacked = Ru.new_zeros(N, Ru.shape[1], K * out)
            stacked[..., net.order] = Ru  # padded outputs: zero columns
            gram = NetworkGram(net.hidden_jacobian(params, segment.x), W, valid, where, P)
            return ResidualGramSystem(gram, stacked.reshape(N, -1, K, out), e)
        stacked = net.stack(e.reshape(N, -1))  # (K, N', out), zero at padded outputs
        if stacked.shape[1] * out <= P // K:
            return OutputGramSystem(NetworkGram(net.hidden_jacobian(params, segment.x), W, valid, where, P), stacked)
        JtJ = torch.zeros(K, P // K, P // K, dtype=e.dtype, device=e.device)
        Jte = torch.zeros(K, P // K, dtype=e.dtype, device=e.device)
        step = max(1, JACOBIAN_ENTRIES // max(1, P * out))
        for first in range(0, N, step):
            chunk = slice(first, min(N, first + step))
            J = output_layer_jacobian(net.hidden_jacobian(params, segment.x[chunk]), W, valid).reshape(K, -1, P // K)
            JtJ += J.transpose(1, 2) @ J
            Jte += (J.transpose(1, 2) @ stacked[:, chunk].reshape(K, -1, 1))[..., 0]
        return OutputSystem(JtJ, Jte, where, P)

    def _block_index(self, params: dict) -> torch.Tensor:
        """Positions in the flat parameter vector of each network's parameters, shape (K, P/K),
        in the order of :func:`output_layer_jacobian`'s columns (hidden parameters, W_out, b_out)."""
        flat, offset = {}, 0
        for name, p in params.items():
            flat[name] = torch.arange(offset, offset + p.numel(), device=p.device).reshape(p.shape)
            offset += p.numel()
        stacks = self.net.unstack(flat)
        return torch.cat([stacks[name].reshape(self.net.count, -1) for name in BLOCK_ORDER], dim=1)


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

    Attributes
    ----------
    groups : list of (networks, count, G)
        Networks with equal output counts share one batched matrix of their own size (approach 2:
        the n differential networks have s + 1 outputs, padded to the algebraic ones' s m):
        their indices (k,), the count, and G (k, N count, N count).
    """

    def __init__(self, hidden, W, valid, where, P: int):
        H = hidden.H
        K, N, w = H.shape
        self.hidden, self.W, self.valid, self.where, self.P = hidden, W, valid, where, P
        M = hidden.gram().reshape(K, N, w, N, w)
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
        """``J^T v`` for ``v`` (K, N, out) (zero at padded outputs): the flat parameter vector (P,)."""
        H = self.hidden.H
        K = H.shape[0]
        hidden = self.hidden.transpose(v @ self.W.transpose(1, 2))
        weights = torch.einsum("kba,kbi->kai", H, v).reshape(K, -1)
        local = torch.cat([hidden, weights, v.sum(1)], dim=1)  # (K, P/K) in BLOCK_ORDER
        flat = torch.empty(self.P, dtype=v.dtype, device=v.device)
        flat[self.where.reshape(-1)] = local.reshape(-1)
        return flat

    def largest_diagonal(self, C: torch.Tensor) -> float:
        """The largest entry of ``diag(J^T C J)`` for a block-diagonal ``C`` (K, N, out, out) (one
        block per network and input): the first damping's scale."""
        H = self.hidden.H
        hidden = self.hidden.diagonal(self.W[:, None] @ C @ self.W[:, None].transpose(-1, -2))
        Cii = torch.diagonal(C, dim1=-2, dim2=-1)  # (K, N, out)
        weights = torch.einsum("kba,kbi->kai", H**2, Cii)
        return float(torch.cat([hidden.reshape(-1), weights.reshape(-1), Cii.sum(1).reshape(-1)]).max())


class OutputGramSystem:
    """Levenberg-Marquardt on the Newton corrections e, solved per network in its outputs:
    ``delta_k = -J_k^T (J_k J_k^T + mu I)^{-1} e_k`` with J_k = du_k/dtheta_k, which equals
    ``-(J^T J + mu I)^{-1} J^T e`` of :class:`OutputSystem` (a push-through identity) at the
    cost of a (N out, N out) solve per network.

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
        """The largest diagonal entry of J^T J (sets the first damping)."""
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
        """The largest diagonal entry of J^T J (sets the first damping)."""
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


# ---- segments in time ------------------------------------------------------------------------
def make_network(compiled, config, inputs: int, segment: int, copies: int = 1):
    """A fresh network for ``segment`` (``copies`` independent ones for a batch), seeded from
    ``config.seed`` and the segment number."""
    from daemodel.backends.pinn.network import RadauNetwork

    generator = torch.Generator().manual_seed(config.seed * 100_003 + segment)
    net = RadauNetwork(inputs, len(compiled.states), len(compiled.algebraics), config, generator, copies)
    return net.to(config.device)


def copies_for(config, batch: int) -> int:
    """Independent network copies for a batch of ``batch`` samples: one each with
    ``batch="independent"`` (1 for a single trajectory), else 1 shared set."""
    if config.batch != "independent" or batch == 1:
        return 1
    if config.samples > 1:
        raise InvalidOptionError(
            f"samples = {config.samples} trains each network on a box around its start, which independent networks "
            f"for a batch of {batch} do not have: use batch='shared' (one set of networks over the batch), or samples=1"
        )
    return batch


def make_loss(compiled, config):
    from daemodel.backends.pinn.loss import RadauLoss

    from daemodel.tableau import radau_iia

    dtype = getattr(torch, config.dtype)
    functions = compiled.torch_functions(dtype=dtype, device=config.device)
    loss = RadauLoss(functions, radau_iia(config.stages), config, dtype, config.device)
    loss.names = (compiled.state_names, compiled.constraint_names, compiled.algebraic_names)
    return loss


def training_inputs(x: torch.Tensor, p: torch.Tensor, n: int, config, generator: torch.Generator):
    """A segment's training inputs and their parameter vectors: the rows of ``x`` (B, d), each
    followed by ``samples - 1`` points uniform in a box of half-width ``radius * max(1, |y|)``
    around its states (parameters are not perturbed)."""
    if config.samples == 1:
        return x, p
    B, d = x.shape
    noise = torch.rand(B, config.samples - 1, n, generator=generator, dtype=torch.float64).to(x) * 2 - 1
    half = config.radius * torch.clamp(x[:, None, :n].abs(), min=1.0)
    extra = x[:, None, :].repeat(1, config.samples - 1, 1)
    extra[..., :n] = extra[..., :n] + half * noise
    # extra rows are grouped by their source row, as are their parameter vectors
    return torch.cat([x, extra.reshape(-1, d)]), torch.cat([p, p.repeat_interleave(config.samples - 1, dim=0)])


class Progress:
    """A tqdm bar over segments whose postfix shows the iteration and the loss terms."""

    def __init__(self, total: int, enabled: bool, label: str):
        from daemodel.backends.base import LOG_PROGRESS_SECONDS, progress_bar, stderr_is_terminal

        self.bar = progress_bar(total, label, "segment") if enabled else None
        # a terminal shows every report in place; a log gets one line every LOG_PROGRESS_SECONDS
        self.every = 0.0 if stderr_is_terminal() else LOG_PROGRESS_SECONDS
        self.shown = -math.inf  # perf_counter of the last redraw
        self.segment = 0

    def report(self, iteration: int, terms: dict) -> None:
        if self.bar is not None:
            shown = " ".join(f"{k}={v:.1e}" for k, v in terms.items())
            self.bar.set_postfix_str(f"seg {self.segment + 1} it {iteration} {shown}", refresh=False)
            if time.perf_counter() - self.shown >= self.every:
                self.bar.refresh()
                self.shown = time.perf_counter()

    def advance(self) -> None:
        self.segment += 1
        if self.bar is not None:
            self.bar.update(1)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def fit_sequential(compiled, grid, x0: torch.Tensor, p: torch.Tensor, z0: torch.Tensor, config, progress: Progress):
    """Train the segments one after the other (time-domain decomposition).

    Segment k trains on the states its predecessor predicted (``x0`` (B, d) for the first), plus
    the box samples of ``config``; its predicted ``y_{n+1}`` becomes segment k+1's input.  A fresh
    network starts at rest on the consistent algebraic values ``z0`` (B, m) (the previous
    segment's predicted ``z_{n+1}`` later on).

    Returns
    -------
    networks : list of RadauNetwork
    stats : list of SegmentStats
    """
    n = len(compiled.states)
    loss = make_loss(compiled, config)
    generator = torch.Generator().manual_seed(config.seed)
    copies = copies_for(config, x0.shape[0])
    x, z, networks, stats = x0, z0, [], []
    for k in range(len(grid) - 1):
        h = float(grid[k + 1] - grid[k])
        inputs, samples_p = training_inputs(x, p, n, config, generator)
        segment = Segment(index=k, t=float(grid[k]), h=h, x=inputs, p=samples_p)
        net = None
        if config.warm_start and networks:
            net = copy.deepcopy(networks[-1])
            net.normalise(inputs)
            if not SegmentTrainer(net, loss, config).finite_start(segment):
                net = None  # the previous segment's slopes leave f's domain here (akzo-nobel: sqrt)
        if net is None:
            net = make_network(compiled, config, x.shape[1], k, copies)
            net.normalise(inputs)
            if config.increment:
                net.start_at_rest(inputs, z)
        stats.append(SegmentTrainer(net, loss, config, progress.report).train(segment))
        with torch.no_grad():
            out = net.predict(x, h)
        x, z = torch.cat([out.y_end, x[:, n:]], dim=1), out.z_end
        networks.append(net)
        progress.advance()
    return networks, stats


def fit_one(shared: tuple, k: int, t: float, h: float, x, z) -> dict:
    """Train segment k from the known inputs ``x`` (B, d) and algebraic values ``z`` (B, m): an
    engine task, plain data in and out.  ``shared`` is (compiled, config, p)."""
    compiled, config, p = shared
    dtype = getattr(torch, config.dtype)
    x, z, p = (torch.as_tensor(np.array(a), dtype=dtype, device=config.device) for a in (x, z, p))
    generator = torch.Generator().manual_seed(config.seed * 100_003 + k)
    inputs, samples_p = training_inputs(x, p, len(compiled.states), config, generator)
    net = make_network(compiled, config, x.shape[1], k, copies_for(config, x.shape[0]))
    net.normalise(inputs)
    if config.increment:
        net.start_at_rest(inputs, z)
    segment = Segment(k, t, h, inputs, samples_p)
    stats = SegmentTrainer(net, make_loss(compiled, config), config).train(segment)
    return {"state": {name: value.cpu() for name, value in net.state_dict().items()}, "stats": stats}


def fit_parallel(
    compiled, grid, starts, algebraics, p, config, progress: Progress, engine="local", workers=None, address=None
):
    """Train every segment independently on known start values, as tasks of ``engine``
    (:func:`daemodel.engine.run_tasks`: one after another here, or in parallel on Ray).

    Parameters
    ----------
    starts : ndarray, shape (segments, B, d)
        Network inputs at each segment's start (from a classical solve or an earlier sweep).
    algebraics : ndarray, shape (segments, B, m)
        The consistent algebraic values at each segment's start.

    Returns
    -------
    networks, stats, peak_memory_mb
        The last: each Ray task's peak resident memory (empty for the local engine).
    """
    from daemodel.engine import run_tasks

    tasks = [(k, float(grid[k]), float(grid[k + 1] - grid[k]), starts[k], algebraics[k]) for k in range(len(grid) - 1)]
    results = run_tasks(
        fit_one,
        (compiled, config, np.asarray(p)),
        tasks,
        engine=engine,
        workers=workers,
        address=address,
        label="pinn",
        on_result=lambda *_: progress.advance(),
    )
    networks = []
    for k, result in enumerate(results):
        net = make_network(compiled, config, starts.shape[2], k, copies_for(config, starts.shape[1]))
        net.load_state_dict(result["state"])
        networks.append(net)
    memory = [result["peak_memory_mb"] for result in results if "peak_memory_mb" in result]
    return networks, [result["stats"] for result in results], memory

"""Training one segment's networks: Levenberg-Marquardt, L-BFGS or Adam on the Radau loss.

Levenberg-Marquardt drives a vector e(theta) to zero; the damping mu follows Nielsen's
gain-ratio rule.  Two regimes, chosen by the count of residuals R against the parameters
P / K of one of the K networks:

* R <= P / K (few samples: the usual trajectory, 21 residuals against thousands of parameters):
  e is the residual vector r, J = dr/dtheta = (dr/du)(du/dtheta) by the chain rule through
  the network outputs u, and each step solves in the small residual space::

      delta = -J^T (J J^T + mu I)^{-1} r

  This is Newton's method on the Radau stage equations seen through the network's
  parametrisation, which is why it reaches the classical solution in a few steps.
* R > P / K (many samples: surrogates): the residuals may not all vanish, and a least-squares fit
  of r would weigh an index-2 algebraic variable by how much it moves the residual, O(h),
  leaving its error ~ residual / h.  Instead e stacks every sample's Newton correction
  ``(dr/du)^+ r`` (how far its outputs are from its own collocation solution), J = du/dtheta,
  and each step solves ``(J^T J + mu I) delta = -J^T e`` (Gauss-Newton on Newton targets).
  An output depends only on its own network's parameters, so J^T J is block diagonal: with
  the per-variable networks (approach 2) that is K small solves, not one of size P.

Either way the training stops on the residual, every |r| component below ``tol``, or with
``tol=None`` after ``iterations`` (sooner if no step decreases the merit).
"""

from __future__ import annotations

import copy
import math
import time
from dataclasses import dataclass

import numpy as np
import torch
from torch.func import functional_call, jacrev, vmap

from daemodel.errors import TrainingError

# A loss this many times its starting value has diverged (Adam/L-BFGS; LM never goes up).
EXPLODE_FACTOR = 1e8
# LM's first damping, relative to the largest diagonal entry of J^T J (Madsen, Nielsen & Tingleff).
LM_TAU = 1e-6
# LM gives up when the damping exceeds this multiple of that diagonal: no step decreases the loss.
LM_MAX_DAMPING = 1e16
# L-BFGS runs in chunks of this many iterations between tolerance checks.
LBFGS_CHUNK = 20
# Entries of dr/dtheta held at once; larger sample sets are processed in chunks.
JACOBIAN_ENTRIES = 2**24
# Progress is reported at most this often (seconds).
REPORT_SECONDS = 0.2


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

    def _vector_of_raw(self, segment: Segment, raw):
        return self.loss.vector(self.residuals(segment, raw), segment.x.shape[0])

    def _check(self, segment: Segment, residuals, iteration: int, start: float | None) -> dict:
        terms = residuals.terms()
        bad = [name for name, value in terms.items() if not math.isfinite(value)]
        if bad:
            raise TrainingError(
                f"pinn: {_where(segment)}: loss term {', '.join(bad)} is not finite at iteration {iteration}; "
                "lower learning_rate, shorten h, or use optimizer='lm'"
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
        if self.config.tol is not None and worst > self.config.tol:
            dominant = max(terms, key=lambda k: terms[k])
            raise TrainingError(
                f"pinn: {_where(segment)}: the residual is still {worst:.3g} > tol = {self.config.tol:g} after "
                f"{iterations} {self.config.optimizer} iterations (largest term {dominant} = {terms[dominant]:.3g}); "
                + (
                    "raise iterations, widen the network, or loosen tol"
                    if self.config.optimizer == "lm"
                    else "raise iterations, loosen tol, or use optimizer='lm'"
                )
            )
        return SegmentStats(
            segment=segment.index,
            t=segment.t,
            h=segment.h,
            iterations=iterations,
            max_residual=worst,
            seconds=time.perf_counter() - began,
            inputs_low=tuple(segment.x.amin(0).tolist()),
            inputs_high=tuple(segment.x.amax(0).tolist()),
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
        """dr_b/du_b for every sample b, shape (N, R_per, U)."""
        N = raw.shape[0]

        def summed(u):
            # r of sample b depends on u of sample b only: the Jacobian of the sum over samples
            # is the stack of per-sample Jacobians.
            return self.loss.vector(self.residuals(segment, u), N).sum(0)

        return jacrev(summed)(raw.detach()).permute(1, 0, 2)

    def _parameter_jacobians(self, segment: Segment, params: dict, U: int, P: int):
        """Yield ``(chunk, du/dtheta)`` sample chunk by sample chunk, the latter of shape (c, U, P)."""
        net, x = self.net, segment.x

        def single(p, xi):
            return functional_call(net, p, (xi[None],))[0]

        step = max(1, JACOBIAN_ENTRIES // max(1, U * P))
        for first in range(0, x.shape[0], step):
            chunk = slice(first, min(x.shape[0], first + step))
            du = vmap(jacrev(single), in_dims=(None, 0))(params, x[chunk])  # name -> (c, U, *shape)
            yield chunk, torch.cat([du[name].reshape(du[name].shape[0], U, -1) for name in params], dim=2)

    def _merit(self, segment: Segment, params: dict, output_space: bool):
        """Outputs, residuals and the vector e that LM drives to zero: r itself, or in output
        space every sample's Newton correction ``R_u^+ r`` (the step to its collocation solution)."""
        raw = functional_call(self.net, params, (segment.x,)).detach()
        with torch.no_grad():
            residuals = self.residuals(segment, raw)
            r = self.loss.vector(residuals, segment.x.shape[0])
        if not output_space:
            return raw, residuals, r.reshape(-1)
        e = torch.linalg.lstsq(self._output_jacobian(segment, raw), r[..., None]).solution[..., 0]
        return raw, residuals, e.reshape(-1)

    def _levenberg_marquardt(self, segment: Segment) -> int:
        params = {name: p.detach().clone() for name, p in self.net.named_parameters()}
        names = list(params)
        sizes = [params[k].numel() for k in names]
        P = sum(sizes)
        raw, residuals, r = self._merit(segment, params, False)
        # Many samples: least squares may not zero all residuals, and weighing them by residual
        # would let an index-2 z (which moves the residual by O(h) only) keep errors ~ residual / h.
        # Fit every output's Newton correction instead.  The switch is where the block-diagonal
        # output-space solve (R (P/K)^2) gets cheaper than the residual-space one (R^2 P).
        output_space = r.numel() > P // self.net.count
        raw, residuals, e = self._merit(segment, params, output_space) if output_space else (raw, residuals, r)
        U = raw.shape[1]
        self.report(0, self._check(segment, residuals, 0, None))
        mu, nu, system, scale = None, 2.0, None, 1.0
        iteration = 0
        while iteration < self.config.iterations and not self._done(residuals):
            iteration += 1
            if system is None:
                system = self._normal_system(segment, params, raw, e, U, P, output_space)
                if mu is None:
                    scale = float(system[4].max())
                    mu = LM_TAU * scale
            kind, J, A, g, _ = system
            delta = self._lm_step(kind, J, A, g, e, mu)
            if delta is None:  # not positive definite: more damping
                mu, nu = mu * nu, nu * 2
                continue
            trial = {}
            offset = 0
            for name, size in zip(names, sizes, strict=True):
                trial[name] = params[name] + delta[offset : offset + size].reshape(params[name].shape)
                offset += size
            raw_t, residuals_t, e_t = self._merit(segment, trial, output_space)
            predicted = 0.5 * float(delta @ (mu * delta - g))
            actual = 0.5 * float(e @ e - e_t @ e_t)
            if math.isfinite(actual) and actual > 0 and predicted > 0:
                rho = actual / predicted
                params, raw, residuals, e = trial, raw_t, residuals_t, e_t
                mu *= max(1 / 3, 1 - (2 * rho - 1) ** 3)
                nu, system = 2.0, None
                self.report(iteration, self._check(segment, residuals, iteration, None))
            else:
                mu, nu = mu * nu, nu * 2
                if mu > LM_MAX_DAMPING * scale:
                    break  # no step decreases the merit: report through _finish
        with torch.no_grad():
            for name, p in self.net.named_parameters():
                p.copy_(params[name])
        return iteration

    def _normal_system(self, segment: Segment, params: dict, raw, e, U: int, P: int, output_space: bool):
        """``(kind, J, A, J^T e, diag(J^T J))`` of the linearised merit ``e + J delta``.

        Residual space: J = dr/dtheta = (dr/du)(du/dtheta), A = J J^T ("dual", an R x R solve).
        Output space: J = du/dtheta, A = the diagonal blocks of J^T J, one per network
        ("blocks"), accumulated over sample chunks so that J is never held whole.
        """
        if not output_space:
            Ru = self._output_jacobian(segment, raw)
            J = torch.cat(
                [
                    torch.bmm(Ru[chunk], Ju).reshape(-1, P)
                    for chunk, Ju in self._parameter_jacobians(segment, params, U, P)
                ]
            )
            return "dual", J, J @ J.T, J.T @ e, (J**2).sum(0)
        # An output depends on its own network's parameters only, so J = du/dtheta and J^T J
        # are block diagonal over the K networks: K solves of size P/K instead of one of size P.
        net, K, N = self.net, self.net.count, segment.x.shape[0]
        where = self._block_index(params)  # (K, P/K): flat parameter positions of each network
        sizes = torch.tensor(net.sizes, device=e.device)
        valid = torch.arange(max(net.sizes), device=e.device)[None, :] < sizes[:, None]  # (K, out): outputs in use
        stacked = torch.zeros(N, valid.numel(), dtype=e.dtype, device=e.device)
        stacked[:, net.order] = e.reshape(N, U)
        stacked = stacked.reshape(N, K, -1).permute(1, 0, 2)  # (K, N, out)
        JtJ = torch.zeros(K, P // K, P // K, dtype=e.dtype, device=e.device)
        Jte = torch.zeros(K, P // K, dtype=e.dtype, device=e.device)
        for chunk, J in self._block_jacobians(segment, params, P):
            J = (J * valid[:, None, :, None]).reshape(K, -1, P // K)  # padded outputs take no part
            JtJ += J.transpose(1, 2) @ J
            Jte += (J.transpose(1, 2) @ stacked[:, chunk].reshape(K, -1, 1))[..., 0]
        g, diagonal = torch.empty(P, dtype=e.dtype, device=e.device), torch.empty(P, dtype=e.dtype, device=e.device)
        g[where.reshape(-1)] = Jte.reshape(-1)
        diagonal[where.reshape(-1)] = torch.diagonal(JtJ, dim1=1, dim2=2).reshape(-1)
        return "blocks", where, JtJ, g, diagonal

    def _block_index(self, params: dict) -> torch.Tensor:
        """Positions in the flat parameter vector of each network's parameters, shape (K, P/K),
        in the order of :meth:`_block_jacobians`' columns."""
        flat, offset = {}, 0
        for name, p in params.items():
            flat[name] = torch.arange(offset, offset + p.numel(), device=p.device).reshape(p.shape)
            offset += p.numel()
        return torch.cat([v.reshape(self.net.count, -1) for v in self.net.unstack(flat).values()], dim=1)

    def _block_jacobians(self, segment: Segment, params: dict, P: int):
        """Yield ``(chunk, du/dtheta)`` per network, the latter of shape (K, c, out, P/K)."""
        net, x, K = self.net, segment.x, self.net.count
        out = max(net.sizes)

        def single(theta, xi):  # one network (K = 1 stack), one input: its outputs (out,)
            return functional_call(net, theta, (xi[None],), {"stacked": True})[0, 0]

        jacobian = vmap(vmap(jacrev(single), in_dims=(None, 0)), in_dims=(0, None))
        stacks = net.unstack(params)
        step = max(1, JACOBIAN_ENTRIES // max(1, P * out))
        for first in range(0, x.shape[0], step):
            chunk = slice(first, min(x.shape[0], first + step))
            du = jacobian(stacks, x[chunk])  # name -> (K, c, out, *one network's shape)
            yield chunk, torch.cat([du[name].reshape(K, du[name].shape[1], out, -1) for name in params], dim=3)

    @staticmethod
    def _lm_step(kind, J, A, g, r, mu):
        """The damped step; ``None`` when ``A + mu I`` is not positive definite.  For "blocks",
        A is (K, P/K, P/K) and ``J`` (K, P/K) holds each network's positions in the flat parameters."""
        eye = torch.eye(A.shape[-1], dtype=A.dtype, device=A.device)
        L, info = torch.linalg.cholesky_ex(A + mu * eye)
        if bool((info != 0).any()):
            return None
        if kind == "dual":
            w = torch.cholesky_solve(r[:, None], L)[:, 0]
            return -(J.T @ w)
        delta = torch.empty_like(g)
        delta[J.reshape(-1)] = -torch.cholesky_solve(g[J][..., None], L).reshape(-1)
        return delta


# ---- segments in time ------------------------------------------------------------------------
def make_network(compiled, config, inputs: int, segment: int):
    """A fresh network for ``segment``, seeded from ``config.seed`` and the segment number."""
    from daemodel.backends.pinn.network import RadauNetwork

    generator = torch.Generator().manual_seed(config.seed * 100_003 + segment)
    net = RadauNetwork(inputs, len(compiled.states), len(compiled.algebraics), config, generator)
    return net.to(config.device)


def make_loss(compiled, config):
    from daemodel.backends.pinn.loss import RadauLoss

    from daemodel.tableau import radau_iia

    dtype = getattr(torch, config.dtype)
    functions = compiled.torch_functions(dtype=dtype, device=config.device)
    return RadauLoss(functions, radau_iia(config.stages), config, dtype, config.device)


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
        self.bar = None
        if enabled:
            from tqdm.auto import tqdm

            self.bar = tqdm(total=total, desc=label, unit="segment", leave=False)
        self.segment = 0

    def report(self, iteration: int, terms: dict) -> None:
        if self.bar is not None:
            shown = " ".join(f"{k}={v:.1e}" for k, v in terms.items())
            self.bar.set_postfix_str(f"seg {self.segment + 1} it {iteration} {shown}", refresh=False)
            self.bar.refresh()

    def advance(self) -> None:
        self.segment += 1
        if self.bar is not None:
            self.bar.update(1)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def fit_sequential(compiled, grid, x0: torch.Tensor, p: torch.Tensor, config, progress: Progress):
    """Train the segments one after the other (time-domain decomposition).

    Segment k trains on the states its predecessor predicted (``x0`` for the first), plus the
    box samples of ``config``; its predicted ``y_{n+1}`` becomes segment k+1's input.

    Returns
    -------
    networks : list of RadauNetwork
    stats : list of SegmentStats
    """
    n = len(compiled.states)
    loss = make_loss(compiled, config)
    generator = torch.Generator().manual_seed(config.seed)
    x, networks, stats = x0, [], []
    for k in range(len(grid) - 1):
        h = float(grid[k + 1] - grid[k])
        inputs, samples_p = training_inputs(x, p, n, config, generator)
        if config.warm_start and networks:
            net = copy.deepcopy(networks[-1])
        else:
            net = make_network(compiled, config, x.shape[1], k)
        net.normalise(inputs)
        segment = Segment(index=k, t=float(grid[k]), h=h, x=inputs, p=samples_p)
        stats.append(SegmentTrainer(net, loss, config, progress.report).train(segment))
        with torch.no_grad():
            y_end = net.predict(x, h).y_end
        x = torch.cat([y_end, x[:, n:]], dim=1)
        networks.append(net)
        progress.advance()
    return networks, stats


def fit_one(payload):
    """Train one segment on known inputs (a worker process's task; arguments are plain data)."""
    compiled, config, k, t, h, x, p, threads = payload
    if threads:
        torch.set_num_threads(threads)
    dtype = getattr(torch, config.dtype)
    x = torch.as_tensor(np.array(x), dtype=dtype, device=config.device)
    p = torch.as_tensor(np.array(p), dtype=dtype, device=config.device)
    generator = torch.Generator().manual_seed(config.seed * 100_003 + k)
    inputs, samples_p = training_inputs(x, p, len(compiled.states), config, generator)
    net = make_network(compiled, config, x.shape[1], k)
    net.normalise(inputs)
    stats = SegmentTrainer(net, make_loss(compiled, config), config).train(Segment(k, t, h, inputs, samples_p))
    return {name: value.cpu() for name, value in net.state_dict().items()}, stats


def fit_parallel(compiled, grid, starts, p, config, workers: int, progress: Progress):
    """Train every segment independently on known start values, in ``workers`` processes.

    Parameters
    ----------
    starts : ndarray, shape (segments, B, d)
        Network inputs at each segment's start (from a classical solve or an earlier sweep).
    """
    import multiprocessing
    import os
    from concurrent.futures import ProcessPoolExecutor

    segments = len(grid) - 1
    threads = max(1, (os.cpu_count() or 1) // workers) if workers > 1 else 0
    tasks = [
        (compiled, config, k, float(grid[k]), float(grid[k + 1] - grid[k]), starts[k], p, threads)
        for k in range(segments)
    ]
    results = [None] * segments
    if workers == 1:
        for k, task in enumerate(tasks):
            results[k] = fit_one(task)
            progress.advance()
    else:
        # spawn: a forked child would inherit torch's thread pool in an unusable state
        with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
            for k, result in enumerate(pool.map(fit_one, tasks)):
                results[k] = result
                progress.advance()
    networks = []
    for k, (state, _) in enumerate(results):
        net = make_network(compiled, config, starts.shape[2], k)
        net.load_state_dict(state)
        networks.append(net)
    return networks, [stats for _, stats in results]

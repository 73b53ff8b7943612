"""Training one segment's networks: Levenberg-Marquardt on the Radau loss (L-BFGS and Adam are
:mod:`.first_order`'s; :meth:`SegmentTrainer.train` runs the configured one).

Levenberg-Marquardt drives to zero the vector e that stacks every sample's Newton correction
``e_b = (dr_b/du_b)^+ r_b``: how far the network outputs u_b (stage and end values) of sample b
are from its own collocation solution, to first order.  J = du/dtheta, and each step solves
``(J^T J + mu I) delta = -J^T e`` (Gauss-Newton on Newton targets); the damping mu follows
Nielsen's gain-ratio rule.  At e = 0 every residual r is zero, so with one sample per segment
(a trajectory) training ends on Newton's stage values, the classical Radau solution.  For one
sample in float64 on the CPU the loss's casadi kernel solves e in dr/du's two blocks instead
(:class:`~.loss.CasadiKernel`): the stage values take radau's own Newton increment (the stage
rows are square), the end values fit their rows by least squares; both forms of e are the same
wherever every residual can vanish, and both vanish exactly where r does.

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

Where every set of networks sees one input (a trajectory, or independent networks per sample)
three things change.  The step is measured in a metric that weighs the hidden parameters'
squares by ``1 / HIDDEN_STEP_WEIGHT`` (:mod:`.lm`), so it moves mostly the output layer, in
which the outputs are linear.  After an accepted LM step in Newton's region (it contracted the
corrections a hundredfold, or left every residual below :data:`NEWTON_FINISH`), Gauss-Newton on
the output biases alone, which is exactly Newton on the stage values
(:meth:`SegmentTrainer._newton_finish`), continues while it decreases the corrections, until they
are at rounding.  And the start is
accepted untouched only where its Newton correction is already at rounding.

Training stops on the residual, every |r| component below ``tol`` after at least one step (or
the start's correction at rounding), or with ``tol=None`` after ``iterations`` (sooner if no
step decreases the merit); the closing Newton steps count as iterations.  A segment that ends
above ``tol`` says so in its stats; whether the answer is good enough is the certificate's
verdict (:mod:`.certificate`), not the residual's.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass

import torch
from daemodel.backends.pinn.first_order import adam, lbfgs
from daemodel.backends.pinn.lm import (
    BLOCK_ORDER,
    HIDDEN_STEP_WEIGHT,
    NetworkGram,
    OneInputSystem,
    OutputGramSystem,
    OutputSystem,
    ResidualGramSystem,
    output_groups,
    output_layer_jacobian,
)
from daemodel.backends.pinn.network import HIDDEN_PARAMETERS, Outputs

from daemodel.errors import TrainingError

# A loss this many times its starting value has diverged (Adam/L-BFGS; LM never goes up).
EXPLODE_FACTOR = 1e8
# LM's first damping, relative to the largest diagonal entry of J^T J (Madsen, Nielsen & Tingleff).
LM_TAU = 1e-6
# LM gives up when the damping exceeds this multiple of that diagonal: no step decreases the loss.
LM_MAX_DAMPING = 1e16
# In Newton's region, after an accepted LM step that cut |e|^2 to at most NEWTON_REGION of its
# value or left every residual below NEWTON_FINISH, at most NEWTON_FINISH_STEPS Gauss-Newton steps
# on the output biases (:meth:`SegmentTrainer._newton_finish`), each kept only where it decreases
# the corrections: quadratic convergence from 1e-6 reaches 1e-12 in one step and rounding in two.
# Measured against the residual test alone: the squeezer 101 -> 75 iterations, heat by lines
# 29 -> 20, the other nine models within 5 %.  After every accepted step, contracting or not, the
# squeezer took 50, but akzo-nobel at h = 4.5 (far outside Newton's region) ended 370 and more from
# radau's values or with a non-finite loss.
NEWTON_REGION = 1e-2
NEWTON_FINISH = 1e-6
NEWTON_FINISH_STEPS = 3
# LM fits the Newton corrections of the outputs where a full Newton step on them cuts the
# residual norm to at most this fraction (Newton converges from there); measured at the start of
# a segment, it is 0.004-0.08 for the fast mode's networks (paper problems, chains of 3-8 rods,
# a 30-point grid) and 1-176 for the paper's networks, whose first outputs are random.
NEWTON_CONTRACTION = 0.5
# Entries of du/dtheta held at once; larger sample sets are processed in chunks.
JACOBIAN_ENTRIES = 2**24


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
        Where the largest residual is (equation, row, sample), for a segment that missed ``tol``
        ("" for one that met it).
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


def _per_sample(mask, new, old):
    """Residuals with sample b's rows from ``new`` where ``mask[b]``, else from ``old``."""

    def pick(a, b):
        return None if a is None else torch.where(mask.reshape(-1, *([1] * (a.dim() - 1))), a, b)

    return dataclasses.replace(
        new, **{f.name: pick(getattr(new, f.name), getattr(old, f.name)) for f in dataclasses.fields(new)}
    )


def segment_label(index: int, t0: float, t1: float) -> str:
    """How messages name a segment: ``segment k (t = t0 to t1)``, k counted from 1."""
    return f"segment {index + 1} (t = {t0:.6g} to {t1:.6g})"


def _where(segment: Segment) -> str:
    return segment_label(segment.index, segment.t, segment.t + segment.h)


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
        self._reporting = report is not None  # LM's accepted steps compute their terms only for a report
        self._start = None  # (segment, raw outputs) of finite_start
        self._forward = None  # (parameters, forward intermediates) of LM's last forward pass
        self._memo = None  # (raw, residuals, e, moved) of the last _residuals_and_correction
        self._valid = None  # the network's outputs in use (K, out)
        self._hidden_layer = None  # (inputs, last hidden layer) at the trained hidden parameters
        self._groups = None  # output_groups of the network (one input per network)

    # ---- residuals --------------------------------------------------------------------------
    def residuals(self, segment: Segment, raw=None):
        n = self.net.n
        raw = self.net(segment.x) if raw is None else raw
        out = self.net.split(raw, segment.x[:, :n], segment.h)
        return self.loss.residuals(segment.t, segment.h, segment.x[:, :n], segment.p, out)

    def finite_start(self, segment: Segment, start=None) -> bool:
        """Whether the network's current predictions give finite residuals on ``segment`` (its
        raw outputs, and the forward pass's intermediates where the caller knows them, ``start``
        = (raw, intermediates) as :meth:`RadauNetwork.start_at` returns them, are kept for the
        training that follows, where they are its start)."""
        with torch.no_grad():
            if start is None:
                raw, forward = self.net.evaluate(segment.x, dict(self.net.named_parameters()))
            else:
                raw, forward = start
            self._start = (segment, raw, forward)
            if self.config.optimizer == "lm" and self.loss.kernel_applies(segment.x, raw, segment.p):
                res = self._residuals_and_correction(segment, raw)[0]  # LM's first merit, kept
            else:
                res = self.residuals(segment, raw)
            return math.isfinite(float((res.F * res.F).sum() + (res.G * res.G).sum() + (res.S * res.S).sum()))

    def _start_outputs(self, segment: Segment) -> tuple:
        """The raw outputs (N, U) that :meth:`finite_start` evaluated on ``segment`` and the forward
        pass's intermediates, taken once (the network is trained right after the check, from those
        parameters), or (None, None)."""
        start, self._start = self._start, None
        return start[1:] if start is not None and start[0] is segment else (None, None)

    def residual_vector(self, segment: Segment, raw):
        """The residual vector r at the raw outputs ``raw`` (what the first-order optimizers square)."""
        return self.loss.vector(self.residuals(segment, raw), segment.x.shape[0])

    def check_terms(self, segment: Segment, residuals, iteration: int, start: float | None) -> dict:
        """The loss terms of ``residuals``; a :class:`TrainingError` where one is not finite, or where
        the weighted loss exceeds :data:`EXPLODE_FACTOR` times its value ``start`` at the start."""
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
        total = self.weighted(terms)
        if start is not None and total > EXPLODE_FACTOR * max(start, 1e-300):
            worst = max(terms, key=lambda k: terms[k])
            raise TrainingError(
                f"pinn: {_where(segment)}: the loss exploded at iteration {iteration} ({start:.3g} -> {total:.3g}, "
                f"mostly {worst} = {terms[worst]:.3g}); lower learning_rate or shorten h"
            )
        return terms

    def weighted(self, terms: dict) -> float:
        """The loss: the terms weighted as the loss weighs them."""
        W_f, W_g, W_s = self.loss.weights
        return W_f * terms["L_f"] + W_g * terms["L_g"] + W_s * terms["L_s"]

    def reached_tol(self, residuals) -> bool:
        """Whether every residual is within ``tol`` (never, for a fixed budget: tol=None)."""
        return self.config.tol is not None and residuals.max_abs() <= self.config.tol

    def _finish(self, segment: Segment, iterations: int, began: float, residuals=None) -> SegmentStats:
        """The segment's stats, from ``residuals`` at the trained parameters when the optimizer
        has them (LM's last accepted evaluation), else evaluated here."""
        if residuals is None:
            with torch.no_grad():
                residuals = self.residuals(segment)
        terms = self.check_terms(segment, residuals, iterations, None)
        worst = residuals.max_abs()
        converged = self.config.tol is None or worst <= self.config.tol
        where = "" if converged else residuals.largest(getattr(self.loss, "names", None))[1]
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
            converged=converged,
            largest=where,
            **terms,
        )

    def train(self, segment: Segment) -> SegmentStats:
        """Train until every residual is below ``tol`` (or ``iterations`` for tol=None)."""
        began = time.perf_counter()
        # the residuals at the end where the optimizer has them (LM; Adam and L-BFGS, first_order.py: None)
        if self.config.optimizer == "lm":
            iterations, residuals = self._levenberg_marquardt(segment)
        else:
            optimizer = {"lbfgs": lbfgs, "adam": adam}[self.config.optimizer]
            iterations, residuals = optimizer(self, segment)
        return self._finish(segment, iterations, began, residuals)

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

    def _residuals_and_correction(self, segment: Segment, raw):
        """The residuals at the raw outputs ``raw`` (N, U) and every sample's Newton correction
        (:meth:`_correction`): by one call of the loss's casadi kernel where it applies."""
        if self._memo is not None and self._memo[0] is raw:
            return self._memo[1:3]
        net, n, h = self.net, self.net.n, segment.h
        y_n = segment.x[:, :n]
        fused, moved = None, None
        if self.loss.kernel_applies(y_n, raw, segment.p):
            fused = self.loss.residuals_and_correction(segment.t, h, y_n, segment.p, net.values(raw, y_n, h))
            residuals, e, moved = fused
            if e is not None and net.increment:  # the raw outputs of the increment form are the stage values / h
                e[:, : (net.stages + 1) * n] /= h
        if fused is None:
            residuals = self.loss.residuals(segment.t, h, y_n, segment.p, net.split(raw, y_n, h))
        if fused is None or fused[1] is None:
            e = self._correction(segment, raw, self.loss.vector(residuals, segment.x.shape[0]))
        self._memo = (raw, residuals, e, moved)  # the start's, asked again by LM; moved for _at_rounding
        return residuals, e

    def _merit(self, segment: Segment, params: dict, space: str, raw=None):
        """Residuals and the vector that LM drives to zero: in ``"output"`` space every sample's
        Newton correction (:meth:`_correction`), in ``"residual"`` space the residual vector r.
        ``raw``: the outputs at ``params`` where the caller knows them."""
        with torch.no_grad():
            if raw is None:  # a forward pass, whose intermediates the next system at params takes
                raw, forward = self.net.evaluate(segment.x, params)
                self._forward = (params, forward)
            self._raw = raw  # for the closing Newton steps' rounding test
            if space == "residual":
                residuals = self.residuals(segment, raw)
                return residuals, self.loss.vector(residuals, segment.x.shape[0]).reshape(-1)
            residuals, e = self._residuals_and_correction(segment, raw)
            return residuals, e.reshape(-1)

    def _newton_contracts(self, segment: Segment, params: dict, raw=None):
        """Whether the full Newton step on the outputs, ``u - e``, cuts the residual norm to at most
        :data:`NEWTON_CONTRACTION` of its value: where it does, the Newton corrections are a guide
        and LM fits them; where not (far from the solution, dr/du nearly singular: the paper's
        networks start from random stage values), LM works on the residuals.

        Returns ``(contracts, residuals, r, e)``."""
        with torch.no_grad():
            raw = self.net(segment.x, params=params) if raw is None else raw
            self._raw = raw
            residuals, e = self._residuals_and_correction(segment, raw)
            N = segment.x.shape[0]
            r = self.loss.vector(residuals, N)
            newton = self.loss.vector(self.residuals(segment, raw - e), N)
            contracts = bool(torch.linalg.norm(newton) <= NEWTON_CONTRACTION * torch.linalg.norm(r))
        return contracts, residuals, r.reshape(-1), e.reshape(-1)

    def _levenberg_marquardt(self, segment: Segment) -> tuple:
        with torch.no_grad():  # the parameters themselves: steps make new tensors
            return self._lm_steps(segment, dict(self.net.named_parameters()))

    def _lm_steps(self, segment: Segment, params: dict) -> tuple:
        names = list(params)
        sizes = [params[k].numel() for k in names]  # (flat steps)
        # With few samples the residual-space system is small (N R <= P / K), and LM works there
        # until a Newton step on the outputs contracts, then on the Newton corrections; with many
        # (surrogates) always on the corrections.
        N, K = segment.x.shape[0], self.net.count
        # (independent copies: Newton corrections only; each starts at Newton's guess: at rest, or predicted)
        fallback = self.net.copies == 1 and N * (self.net.output_count + self.net.m) <= sum(sizes) // K
        # the increment form starts at Newton's own guess (at rest, predicted or warm), where the
        # corrections always guide (contraction 0.004-0.08, measured): no check needed
        start, forward = self._start_outputs(segment)  # the parameters are the network's own here
        if forward is not None:  # the first system at params takes them
            self._forward = (params, forward)
        if fallback and not self.config.increment:
            contracts, residuals, r, e = self._newton_contracts(segment, params, start)
            space = "output" if contracts else "residual"
            e = e if contracts else r
        else:
            space = "output"
            residuals, e = self._merit(segment, params, space, start)
        if self._reporting or start is None:  # (a start that finite_start passed has finite terms)
            self.report(0, self.check_terms(segment, residuals, 0, None))
        mu, nu, system, scale = None, 2.0, None, 1.0
        iteration, stepped = 0, False
        one_input = N == self.net.copies  # every set of networks sees one input
        if (
            space == "output"
            and one_input
            and bool(torch.isfinite(e).all())
            and self._at_rounding(segment, self._raw, e)
        ):
            stepped = True  # the start's own Newton correction is at rounding: converged (an exact predictor)
        # as Newton judges convergence by an increment, a start (at rest, warm or predicted) is
        # accepted untouched only where its Newton correction is at rounding: a small residual
        # need not mean a small distance (a predictor within tol = 1e-12 left 6e-12 on a model
        # whose Radau error is rounding)
        while iteration < self.config.iterations and not (stepped and self.reached_tol(residuals)):
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
            if isinstance(delta, dict):  # by parameter
                trial = {name: params[name] + delta[name] for name in names}
            else:  # flat, in the order of named_parameters
                trial, offset = {}, 0
                for name, size in zip(names, sizes, strict=True):
                    trial[name] = params[name] + delta[offset : offset + size].reshape(params[name].shape)
                    offset += size
            residuals_t, e_t = self._merit(segment, trial, space)
            before, after = float(e @ e), float(e_t @ e_t)
            actual = 0.5 * (before - after)
            if math.isfinite(actual) and actual > 0 and predicted > 0:
                rho = actual / predicted
                params, residuals, e, stepped = trial, residuals_t, e_t, True
                mu *= max(1 / 3, 1 - (2 * rho - 1) ** 3)
                nu = 2.0
                if self._reporting:
                    self.report(iteration, self.check_terms(segment, residuals, iteration, None))
                contracted = after <= NEWTON_REGION * before  # Newton's region: |e|^2 cut a hundredfold
                if space == "output" and one_input and (contracted or residuals.max_abs() <= NEWTON_FINISH):
                    params, residuals, e, iteration = self._newton_finish(segment, params, residuals, e, iteration)
                system = None
                if space == "residual" and not self.reached_tol(residuals):
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
        for name, p in self.net.named_parameters():
            if params[name] is not p:
                p.copy_(params[name])
        forward = self._forward
        if forward is not None and all(params[name] is forward[0][name] for name in HIDDEN_PARAMETERS):
            self._hidden_layer = (segment.x, forward[1][0])  # H at the trained hidden parameters
        return iteration, residuals

    def predict(self, x: torch.Tensor, h) -> Outputs:
        """The trained network's stage and end values at ``x`` (B, d), bit for bit a forward pass
        (what the rollout evaluates): where ``x`` is the segment's input and LM's last forward pass
        was at the trained hidden parameters (its closing Newton steps move the output biases
        only), its last hidden layer and the output layer alone."""
        p = dict(self.net.named_parameters())
        with torch.no_grad():
            if self._hidden_layer is not None and self._hidden_layer[0] is x:
                raw = self.net.unstacked(torch.baddbmm(p["b_out"], self._hidden_layer[1], p["W_out"]))
            else:
                raw = self.net(x)
        return self.net.split(raw, x[:, : self.net.n], h)

    def _newton_finish(self, segment: Segment, params: dict, residuals, e, iteration: int):
        """The steps after an accepted LM step in Newton's region (one input per set of networks,
        :data:`NEWTON_FINISH`): Gauss-Newton on
        the output biases alone.  The outputs are linear in them, so where each set of networks
        has one input a step moves every output by exactly its Newton correction: Newton on the
        stage values (quadratic near the solution; farther away a step that does not decrease
        the corrections is dropped and LM goes on), at the cost of one evaluation and no Gram
        matrix.  At most :data:`NEWTON_FINISH_STEPS`, each kept only where it
        decreases the Newton corrections, until they are at rounding (10 eps of each value, as
        radau's fixed step iterates Newton).  A residual at tol = 1e-12 can leave the stages
        5e-13 from the collocation solution, above Radau's own error on an accurate model
        (measured: a damped oscillator at h = 0.05, Radau's error 1.8e-13).

        Each step counts as an iteration (of ``config.iterations``) and is reported as one.
        Returns ``(params, residuals, e, iteration)``."""
        N, K = segment.x.shape[0], self.net.count
        for _ in range(min(NEWTON_FINISH_STEPS, self.config.iterations - iteration)):
            if self._at_rounding(segment, self._raw, e):
                break
            trial = dict(params)
            trial["b_out"] = params["b_out"] - self.net.stack(e.reshape(N, -1))
            raw = self._raw
            # the outputs are linear in b_out, and each network sees one input: they move by -e
            residuals_t, e_t = self._merit(segment, trial, "output", raw=raw - e.reshape(raw.shape))
            before, after = ((a.reshape(N, -1) ** 2).sum(1) for a in (e, e_t))
            better = torch.isfinite(after) & (after < before)  # per sample (each copy its own networks)
            if not bool(better.any()):
                self._raw = raw
                break
            if not bool(better.all()):  # keep the step only for the samples it improved
                networks = better.repeat_interleave(K // N)[:, None, None]  # copy b's networks follow copy b-1's
                trial["b_out"] = torch.where(networks, trial["b_out"], params["b_out"])
                residuals_t = _per_sample(better, residuals_t, residuals)
                e_t = torch.where(better[:, None], e_t.reshape(N, -1), e.reshape(N, -1)).reshape(-1)
                self._raw = torch.where(better[:, None], self._raw, raw)
            params, residuals, e, iteration = trial, residuals_t, e_t, iteration + 1
            if self._reporting:
                self.report(iteration, self.check_terms(segment, residuals, iteration, None))
        return params, residuals, e, iteration

    def _at_rounding(self, segment: Segment, raw, e) -> bool:
        """Whether the Newton corrections ``e`` move no stage or end value by more than 10 eps of
        its size (the outputs ``raw`` as :meth:`RadauNetwork.split` reads them)."""
        if self._memo is not None and self._memo[0] is raw and self._memo[3] is not None:  # the kernel's
            return self._memo[3] <= 10 * torch.finfo(raw.dtype).eps
        now = self.net.values(raw, segment.x[:, : self.net.n], segment.h)
        moved = self.net.value_steps(e.reshape(raw.shape), segment.h)
        return bool((moved.abs() <= 10 * torch.finfo(raw.dtype).eps * (1 + now.abs())).all())

    def _normal_system(self, segment: Segment, params: dict, e: torch.Tensor, space: str = "output"):
        """The linearised merit ``e + J delta`` as an :class:`OutputGramSystem` (J = du/dtheta; few
        outputs per network: a (N out, N out) solve per network), an :class:`OutputSystem` (many:
        a (P/K, P/K) solve per network) or, in residual space, a :class:`ResidualGramSystem`
        (J = dr/dtheta: one (N R, N R) solve).  An output depends on its own network's parameters
        only, so du/dtheta is block diagonal over the networks and never formed whole."""
        net, K, N = self.net, self.net.count, segment.x.shape[0]
        out = max(net.sizes)
        if self._valid is None:
            self._valid = net.used()  # (K, out): the outputs in use
        valid = self._valid
        W = params["W_out"] * valid[:, None, :]  # padded outputs take no part
        weight = HIDDEN_STEP_WEIGHT if N == net.copies else 1.0  # one input per set of networks
        stacked = net.stack(e.reshape(N, -1)) if space == "output" else None  # (K, N', out), zero at padding
        if space == "output" and stacked.shape[1] == 1:  # every network sees one input
            forward = self._forward[1] if self._forward is not None and self._forward[0] is params else None
            projected = out <= W.shape[1]  # the reverse pass from W's out rows, or from H's w
            hidden = net.hidden_jacobian(params, segment.x, rows=W if projected else None, forward=forward)
            if self._groups is None:
                units = sum(p.shape[-1] for p in (params["W_u"], params["W_r"], params["W_1"]))
                units += W.shape[1] * params["W_gate"].shape[0] + 1
                self._groups = output_groups(net.sizes, units)
            return OneInputSystem(hidden, W, valid, stacked, weight, self._groups, projected)
        P = sum(p.numel() for p in params.values())
        where = self._block_index(params)  # (K, P/K): flat parameter positions of each network
        if space == "residual":
            with torch.no_grad():
                Ru = self._output_jacobian(segment, net(segment.x, params=params))  # (N, R, U)
            stacked = Ru.new_zeros(N, Ru.shape[1], K * out)
            stacked[..., net.order] = Ru  # padded outputs: zero columns
            gram = NetworkGram(net.hidden_jacobian(params, segment.x), W, valid, where, P, weight)
            return ResidualGramSystem(gram, stacked.reshape(N, -1, K, out), e)
        if stacked.shape[1] * out <= P // K:
            gram = NetworkGram(net.hidden_jacobian(params, segment.x), W, valid, where, P, weight)
            return OutputGramSystem(gram, stacked)
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

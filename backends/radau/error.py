"""The embedded local error estimate of a Radau IIA step (order s), as RADAU5 computes it.

With ``gamma0`` the real eigenvalue of A (s odd) and ``bhat`` of order s including the start point
(:func:`~.transform.embedded_weights`; Hairer & Wanner, Solving ODEs II, IV.8, generalised to s
stages),

    (M - h gamma0 J) err = [gamma0 h f(y_n) + h sum_i (bhat_i - b_i) f(Y_i) ; 0]

where ``M = diag(I, 0)``.  As in RADAU5, the error of an algebraic variable determined through an
index-k constraint is multiplied by ``h^(k-1)`` before the norm (its stage values are only accurate
to order s - k + 2); so adaptive steps return them solved from the states at the outputs (:mod:`.outputs`).
A batch shares the step sequence (the worst sample decides).

The adaptive controller reads :meth:`ErrorEstimate.norm`; the fixed grid checks every step with
:meth:`ErrorEstimate.check_fixed`, in units of the solution's size ``1 + max |u|`` so far: Newton
converges on a step across a singularity as readily as on a good one, and only the estimate
tells them apart.
"""

from __future__ import annotations

import math

import numpy as np
from daemodel.backends.base import LOCAL_ERROR_BOUND, estimate_status
from daemodel.backends.radau import formulas

from daemodel.errors import LocalErrorBoundError


class ErrorEstimate:
    """The local error estimate of the steps of one :class:`~.step.Stepper`."""

    def __init__(self, stepper, e):
        self.stepper = stepper
        self.e = stepper.engine.asarray(e)  # bhat - b, (s,)
        self.gamma0 = stepper.engine.transform.gamma0
        self.scale = None  # fixed grid: 1 + max |u| over the steps' start values so far, (B, n+m)
        self.per_step = []  # fixed grid: each step's largest estimate in units of scale (z unweighted)
        self.worst = None  # fixed grid: (estimate, step, t, h, estimates (B, n+m)) of the largest so far

    def local(self, h, factors, f0, stage_f):
        """The embedded local error estimate of the step, shape (B, n+m).

        ``factors`` hold ``(1 / (h gamma0)) M - J``, ``f0`` (B, n) is ``f`` at the step's start,
        ``stage_f`` (B, s, n) at its stages.  Returns the estimate and what :meth:`refiltered` needs.
        """
        stepper = self.stepper
        xp = stepper.xp
        quadrature = xp.einsum("i,bin->bn", self.e, stage_f)  # sum_i (bhat_i - b_i) f(Y_i), (B, n)
        # (M - h gamma0 J) err = [h (quadrature + gamma0 f0); 0] divided row-wise by diag(h gamma0, -1).
        # The constraint rows carry no local error: each step's Newton enforces g at its stages,
        # and its leftover |g(y_n)| (Newton's tolerance) must not block ever smaller steps.
        zeros = xp.zeros_like(stepper.z)
        rhs = formulas.error_rhs(stepper.ops, quadrature, self.gamma0, f0, zeros)
        return stepper.engine.error_solve(factors, rhs), (factors, quadrature, zeros)

    def refiltered(self, t, err, matrices):
        """The estimate with the stiff filter applied once more (Hairer-Wanner's first or rejected step)."""
        stepper = self.stepper
        factors, quadrature, zeros = matrices
        n = stepper.n
        f1 = stepper.engine.f(t, stepper.y + err[:, :n], stepper.z + err[:, n:])
        return stepper.engine.error_solve(factors, formulas.error_rhs(stepper.ops, quadrature, self.gamma0, f1, zeros))

    def norm(self, t, h, r, W, first) -> float:
        """RADAU5's scaled local error of the step, worst sample (the adaptive controller's)."""
        stepper = self.stepper
        xp = stepper.xp
        err, matrices = self.local(h, stepper.factors, stepper.start_f(t), r.stage_f)
        u_new = W[:, -1]
        w = stepper.weights(h, xp.maximum(xp.abs(stepper.state()), xp.abs(u_new)))
        norm = formulas.error_norm(stepper.ops, err, w, first, lambda: self.refiltered(t, err, matrices))
        return formulas.finite_or_inf(formulas.SCALAR, float(norm.max()))  # (max: NaN where any is)

    def check_fixed(self, step, t, h, r):
        """Fixed step: the step's local error estimate in units of the solution's size; raise beyond the bound.

        The unit is ``1 + max |u|`` over the steps' start values so far (an algebraic variable of
        index k: that over ``h^(k-1)``), so a step across a singularity cannot excuse its error by
        its own huge result, nor an oscillation be judged where it crosses zero.  It reuses the
        factored Newton matrix of the step's Jacobian and takes ``f`` at the step's start from the
        last step's final stage (Radau IIA is stiffly accurate: ``c_s = 1``).
        """
        stepper = self.stepper
        xp, stats = stepper.xp, stepper.stats
        u = xp.abs(stepper.state()) + 1.0
        self.scale = u if self.scale is None else xp.maximum(self.scale, u)
        err, matrices = self.local(h, stepper.factors, stepper.start_f(t), r.stage_f)
        index_weight = stepper.index_weights(h)
        raw = xp.abs(err) / self.scale
        ratio = raw * index_weight
        worst = float(ratio.max())
        if worst > LOCAL_ERROR_BOUND or float(raw.max()) > stepper.options.estimate_bound:
            # the stiff filter once more before judging (Hairer-Wanner): unfiltered, a stiff mode's
            # estimate flagged y' = -1e6 (y - cos t) at h = 0.01 from y0 = 0.95 at 2.6e-2, 1.5e-5 off
            filtered = xp.abs(self.refiltered(t, err, matrices)) / self.scale
            if bool(xp.isfinite(filtered).all()):  # (f at y + err may leave f's domain: keep the first then)
                raw = filtered
                ratio = raw * index_weight
                worst = float(ratio.max())
        if worst <= LOCAL_ERROR_BOUND:  # the usual case: False for NaN too
            stats["max_local_error_estimate"] = max(stats["max_local_error_estimate"], worst)
            # estimate_bound reads the estimate in each variable's own units (an index-2 z's is not
            # weighted by h: the slider-crank's multipliers at h = 0.02 are 5e-3 off where the weighted
            # estimate said 5e-4)
            largest = float(raw.max())
            self.per_step.append(largest)
            if self.worst is None or largest > self.worst[0]:
                self.worst = (largest, step, t, h, numpy_copy(raw))
            return
        stats["max_local_error_estimate"] = math.inf if math.isnan(worst) else worst
        ratio = np.nan_to_num(np.asarray(numpy_copy(ratio)), nan=math.inf)
        D = stepper.n + stepper.m
        sample, k = divmod(int(np.argmax(ratio.reshape(-1))), D)
        compiled = stepper.compiled
        name = (*compiled.state_names, *compiled.algebraic_names)[k]
        index = int(stepper.z_index[k - stepper.n]) if k >= stepper.n else 1
        size = f"1 + max|{name}|" if index == 1 else f"(1 + max|{name}|) / h^{index - 1}"
        value = float(ratio.reshape(-1)[sample * D + k])
        raise LocalErrorBoundError(
            f"radau: step {step} from t = {t:.6g} with h = {h:.3g}: the local error estimate of '{name}' "
            f"(sample {sample}) is {value:.3g} times the solution's size {size} so far, beyond "
            f"LOCAL_ERROR_BOUND = {LOCAL_ERROR_BOUND:g}: the step has no correct digit (the solution may be "
            "singular, switch or change too fast there); take a smaller h, or the adaptive mode (rtol=...)"
        )

    def status(self, method: str, bound: float) -> str:
        """The fixed grid's status: "success", or flagged at its worst step beyond ``bound`` (see
        :func:`~daemodel.backends.base.estimate_status`)."""
        if self.worst is None:
            return "success"
        worst, step, t, h, ratio = self.worst
        stepper = self.stepper
        sample, k = divmod(int(np.argmax(ratio.reshape(-1))), stepper.n + stepper.m)
        name = (*stepper.compiled.state_names, *stepper.compiled.algebraic_names)[k]
        where = f"step {step} from t = {t:.6g} (h = {h:.3g}), in '{name}'"
        where += f", sample {sample}" if stepper.B > 1 else ""
        return estimate_status(method, worst, bound, where)


def numpy_copy(values) -> np.ndarray:
    """A float64 numpy copy of an engine's array."""
    if isinstance(values, np.ndarray):
        return values.astype(float, copy=False)
    return values.detach().cpu().double().numpy()

"""Newton on the stage equations of one step: simplified (one Jacobian, the transformed systems), full
(each stage's Jacobian) and damped (Deuflhard), under one :class:`NewtonPolicy` set by the controller.

The equations are :func:`daemodel.collocation.stage_residual`'s (the ones the Radau-PINN
minimises).  Simplified Newton factors ``(gamma / h) M - J`` once (:mod:`.transform`); where it
contracts too slowly, a fixed step switches to full Newton with each stage's Jacobian at the
current iterate, and where that fails too, to damped Newton: a fixed step has no smaller h to fall
back on.  An adaptive step instead fails, and the controller shrinks h, as RADAU5 does.

Which is written where: the simplified iteration's passes (its tests, the check of a one-iteration
convergence, the evaluation of f at the final stages, the counts) are :func:`.iteration.newton_pass`,
which the compiled attempt runs too (:func:`.compiled.newton_tests`); :meth:`Newton.simplified` runs
them on the samples' arrays and adds what Python alone does (the increments, the worded failure, the
fixed grid's rescue).  :meth:`Newton.full` (the rescue, and the steps that start with stage
Jacobians) and :meth:`Newton.damped` are Python's alone: the compiled attempt has no counterpart.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from daemodel.backends.radau import formulas
from daemodel.backends.radau.engines import StageFactors
from daemodel.backends.radau.formulas import STAGNATION_FACTOR, STAGNATION_THETA
from daemodel.backends.radau.iteration import newton_pass, newton_start

# Above this contraction rate, Newton switches to per-stage Jacobians at the current iterate.
REFRESH_THETA = 0.05
# After a step needed full Newton (per-stage Jacobians), this many steps start with it directly,
# then the transformed systems are tried again: where the Jacobian varies along the step (the
# pendulum at h = 0.05 contracts at ~0.1 with one Jacobian) the transformed start only costs.
STAGE_NEWTON_STEPS = 8
# (Simplified Newton's passes are .iteration.newton_pass, its tests .formulas.newton_iteration, shared
# with the compiled step; the damped iteration's stagnation test reads its STAGNATION_THETA and _FACTOR.)
# A fixed step whose Newton iterations (simplified, then full) both fail gets a last attempt:
# damped Newton from the start guess with each stage's Jacobian at every iterate (Deuflhard's
# natural monotonicity test: a step lam dW is taken when the next simplified increment is at
# most (1 - lam / 2) times dW; lam halves down to DAMPING_MIN = 2^-DAMPING_HALVINGS), for at most
# DAMPED_NEWTON_FACTOR x max_newton_iterations iterations.  casadi's collocation (full Newton, no
# divergence test) converged on steps where the undamped iterations here failed: the transistor
# amplifier at h = 1e-3 (contraction 30 at step 1) and 2.5e-4 (10 iterations too few, step 52).
DAMPED_NEWTON_FACTOR, DAMPING_HALVINGS = 5, 10
DAMPING_MIN = 2.0**-DAMPING_HALVINGS


@dataclass(frozen=True, kw_only=True)
class NewtonPolicy:
    """How a controller wants the stage equations solved.

    Attributes
    ----------
    tol : float
        Newton stops when the (predicted) scaled increment is below this.
    atol, rtol : float
        Increments are measured in units of ``atol + rtol |u|`` (an index-k algebraic variable's
        divided by ``h^(k-1)``); the adaptive error estimate uses the same units.
    iterations : int
        Most iterations of one solve.
    trust_last_rate : bool
        RADAU5's start: the last step's contraction rate predicts this one's, so one iteration
        may converge; such a convergence is checked with one more increment (trusting the rate
        alone accepted 100 x rtol errors on the pendulum and finite garbage on sign(x)).
    to_rounding : bool
        The collocation solution to rounding: no early trust, and increments that stop shrinking
        near ``tol`` are at the rounding floor (converged), not diverging.
    rescue : bool
        A fixed step has no smaller h: slow contraction switches to full Newton, and a failure to
        full and then damped Newton.  Without rescue a slow or failed Newton ends the attempt.
    """

    tol: float
    atol: float
    rtol: float
    iterations: int
    trust_last_rate: bool
    to_rounding: bool
    rescue: bool


class Newton:
    """The Newton iterations of one :class:`~.step.Stepper` under its policy.

    Each solve returns ``((W, residual, theta) or None, iterations, why it failed, sample)``.
    """

    def __init__(self, stepper, policy: NewtonPolicy):
        self.stepper, self.policy = stepper, policy

    def simplified(self, t, h, factors, W, owned: bool = False):
        """Solve the stage equations from the guess ``W`` with ``factors`` (transformed systems or full); ``owned``:
        ``W`` is made for this call alone (numpy), and its increments are added in place.

        The passes of :func:`.iteration.newton_pass` (the compiled attempt's, on the samples' arrays),
        each on the increment at the current stage values; around them what Python alone does: no
        increment where only f is needed (EVALUATE), the worded failure, the fixed grid's rescue.
        """
        stepper, policy = self.stepper, self.policy
        xp, ops, engine, stats = stepper.xp, stepper.ops, stepper.engine, stepper.stats
        scale = stepper.weights(h, xp.abs(stepper.state()))[:, None, :]
        if policy.trust_last_rate:
            # RADAU5: trust the last step's contraction rate, so one iteration may suffice
            eta = formulas.start_rate(ops, stepper.eta, float(np.finfo(stepper.options.dtype).eps))
        else:
            eta = xp.ones_like(stepper.eta)
        zeros = xp.zeros_like(stepper.eta)
        state = newton_start(eta, zeros, zeros == 0)
        # slow contraction ends the attempt with the transformed systems and no rescue (the controller
        # shrinks h, as RADAU5 does); else slow_contraction refreshes the matrices
        slow_ends = not policy.rescue and not isinstance(factors, StageFactors)
        # (the first increment makes Newton's own stage values, later ones are added in place: the guess stays the
        # caller's, a retry's, unless it is owned; the increment's norm is squared in the engine's scratch where it
        # has one)
        own, scratch = owned and xp is np, None if engine.increment is None else engine.increment.scratch
        while state.active:  # (no idle pass: Python's branch where every sample is done)
            mode = state.mode
            r = dW = None  # (the last pass's go before the next are made: two of each were the solve's peak)
            if mode == formulas.EVALUATE:  # the error estimate needs f at the final stage values
                r, dW, norm = engine.stage_values(t, h, stepper.y, W), None, None
            else:
                r, dW = engine.newton_step(factors, t, h, stepper.y, W)
                if stepper.B > 1 and mode == formulas.ITERATING:
                    dW = dW * state.iterating[:, None, None]  # samples that converged keep their stage values
                norm = stepper.ops.rms_ratio(dW, scale, out=scratch)
            found = newton_pass(
                ops, state, norm, policy.tol, policy.iterations, to_rounding=policy.to_rounding,
                slow_ends=slow_ends, trust_last_rate=policy.trust_last_rate,
                geometric=policy.trust_last_rate and formulas.geometric_contraction(stepper.s),  # (adaptive only)
            )  # fmt: skip
            state, tests = found.state, found.tests
            if state.outcome != formulas.CONVERGED:  # (named at the W of r and dW: a failed pass iterates too)
                stats["residual_evaluations"] += state.evaluations
                return None, state.k, *self.failure(state, tests, r, dW, t, h, W)
            if found.iterate:  # (a refuted check's increment moves the samples it refuted)
                step = dW * found.moved[:, None, None] if mode == formulas.CHECK and stepper.B > 1 else dW
                if own:
                    W += step
                else:  # (in an array of the step's nodes where the stepper has one: accept takes it whole)
                    buffer = stepper.stage_buffer(np.result_type(W, step)) if xp is np else None
                    W, own = (W + step if buffer is None else np.add(W, step, out=buffer)), True
            if found.iterate and tests.running and state.k > 1 and policy.iterations > state.k and not slow_ends:
                factors = self.slow_contraction(t, h, W, factors, state.theta, tests.slow, state.iterating)
        stats["residual_evaluations"] += state.evaluations
        stepper.eta = state.eta
        stats["newton_iterations"] += state.k
        stats["max_newton_iterations"] = max(stats["max_newton_iterations"], state.k)
        return (W, r, float(state.theta.max())), state.k, None, None

    def failure(self, state, tests, r, dW, t, h, W):
        """Why the iteration failed (``state.outcome``) and at which sample: the first that failed the test."""
        engine, theta = self.stepper.engine, state.theta
        if state.outcome == formulas.NON_FINITE:
            sample = engine.first(tests.failing)
            if dW is not None and engine.increment is not None:  # (the increment is over the residual's R and G
                # (.engines.AbstractEngine.newton_step): the residual at W once more, for the culprit; not counted,
                # as the compiled attempt, which names none, has the general path's counts)
                dW = dW.copy()
                r = engine.residual(t, h, self.stepper.y, W)
            return f"non-finite values: {self.non_finite(r, dW, sample, t, h)}", sample
        if state.outcome == formulas.DIVERGING:
            worst = engine.first(tests.failing)
            return f"diverging (contraction {float(theta[worst]):.2f})", worst
        if state.outcome == formulas.SLOW:
            worst = float((theta * state.iterating).max())
            return f"converging too slowly (contraction {worst:.2f})", engine.first(state.iterating & (theta >= worst))
        return f"not converged in {state.k} iteration{'s' if state.k != 1 else ''}", engine.first(state.iterating)

    def slow_contraction(self, t, h, W, factors, theta, slow, active):
        """The factors to go on with where Newton contracts slowly and the policy rescues (a fixed step):
        under full Newton the stage Jacobians are refreshed while it contracts slower than
        REFRESH_THETA; with the transformed systems, where the contraction will not reach the
        tolerance (``slow``: :func:`.formulas.newton_iteration`'s test), full Newton with each stage's
        Jacobian at the current iterate takes over, which stays quadratic.  (Without rescue a slow
        contraction ends the attempt: the controller shrinks h, as RADAU5 does.)
        """
        stepper = self.stepper
        if isinstance(factors, StageFactors):
            refresh = float((theta * active).max()) > REFRESH_THETA
        else:
            refresh = bool(slow.any())
        if not refresh:
            return factors
        stage_J = stepper.engine.stage_jacobians(t, h, W)
        stepper.stats["jacobian_evaluations"] += 1
        stepper.drop_jacobian()  # the next step starts from a fresh Jacobian too
        return stepper.factor_stages(stage_J, t, h)

    def non_finite(self, r, dW, sample, t, h) -> str:
        """Where a sample's first non-finite value arose: ``f`` or ``g`` at a stage, else an increment of a variable."""
        stepper = self.stepper
        xp, compiled, n = stepper.xp, stepper.compiled, stepper.n
        for values, names, what in (
            (r.stage_f, compiled.state_names, "the right-hand side of {}'"),
            (r.G, compiled.constraint_names, "constraint '{}'"),
            (dW[..., :n], compiled.state_names, "the Newton increment of '{}'"),
            (dW[..., n:], compiled.algebraic_names, "the Newton increment of '{}'"),
        ):
            bad = np.argwhere(~host(xp.isfinite(values[sample])))
            if len(bad):
                stage, k = (int(i) for i in bad[0])
                when = t + float(stepper.tableau.c[stage]) * h
                return f"{what.format(names[k])} at stage {stage + 1} (t = {when:.6g})"
        return "the Newton increment"

    def full(self, t, h, W0):
        """Full Newton from ``W0`` with each stage's Jacobian at ``W0`` (and at later iterates while
        it contracts slowly); with rescue, damped Newton if that fails."""
        stepper = self.stepper
        stage_J = stepper.engine.stage_jacobians(t, h, W0)
        stepper.stats["jacobian_evaluations"] += 1
        stepper.check_determined(stage_J, t, h)
        result, iterations, why, sample = self.simplified(t, h, stepper.factor_stages(stage_J, t, h), W0)
        if result is not None or not self.policy.rescue:
            return result, iterations, why, sample
        damped, more, why_damped, sample = self.damped(t, h, W0)
        if damped is not None:
            return damped, iterations + more, None, None
        return None, iterations + more, f"{why}; damped Newton: {why_damped}", sample

    def damped(self, t, h, W):
        """A fixed step's last attempt: Newton from ``W`` with each stage's Jacobian at every iterate,
        damped by the natural monotonicity test (see :data:`DAMPED_NEWTON_FACTOR`).

        Returns ``(W, residual, 1.0)`` or None, the iterations, why it failed and the sample, as
        :meth:`simplified` does; the contraction 1.0 makes the next step evaluate a fresh Jacobian.
        """
        stepper, tol = self.stepper, self.policy.tol
        xp, engine, stats = stepper.xp, stepper.engine, stepper.stats
        stats["damped_newton_attempts"] += 1
        scale = stepper.weights(h, xp.abs(stepper.state()))[:, None, :]
        lam = xp.ones_like(stepper.eta)
        active = lam > 0
        previous = xp.full_like(lam, math.inf)
        limit = DAMPED_NEWTON_FACTOR * self.policy.iterations
        for k in range(1, limit + 1):
            stage_J = engine.stage_jacobians(t, h, W)
            stats["jacobian_evaluations"] += 1
            factors = engine.factor_stages(stage_J, h)
            stats["lu_decompositions"] += 1
            stats["newton_refreshes"] += 1
            stepper.stage_steps = STAGE_NEWTON_STEPS
            if bool(factors.singular.any()):  # an iterate left f's domain, or a stiff mode meets a shift
                finite = all(bool(xp.isfinite(J).all()) for J in stage_J)
                cause = "" if finite else " (the Jacobian of f and g is not finite there)"
                return None, k, f"the Newton matrix at iterate {k} is singular{cause}", engine.first(factors.singular)
            stats["residual_evaluations"] += 1
            r, dW = engine.newton_step(factors, t, h, stepper.y, W)
            norm = stepper.rms(dW / scale)
            finite = xp.isfinite(norm)
            if not bool(finite.all()):
                sample = engine.first(~finite)
                return None, k, f"non-finite values: {self.non_finite(r, dW, sample, t, h)}", sample
            # converged: the increment is below tol, or it stopped shrinking at the rounding floor near it
            stagnant = (norm >= STAGNATION_THETA * previous) & (norm <= STAGNATION_FACTOR * tol)
            active = active & (norm > tol) & ~stagnant
            previous = norm
            if not bool(active.any()):
                W = W + dW  # every sample's increment is below the tolerance: take it whole
                stats["newton_iterations"] += k
                stats["max_newton_iterations"] = max(stats["max_newton_iterations"], k)
                return (W, stepper.residual(t, h, W), 1.0), k, None, None
            lam = xp.clip(2 * lam, None, 1.0)
            while True:  # lam halves each pass, down to DAMPING_MIN: at most DAMPING_HALVINGS + 1 passes
                trial = W + (lam * active)[:, None, None] * dW
                stats["residual_evaluations"] += 1
                _, simplified = engine.newton_step(factors, t, h, stepper.y, trial)
                after = stepper.rms(simplified / scale)
                fine = ~active | (xp.isfinite(after) & (after <= (1 - lam / 2) * norm))
                if bool(fine.all()):
                    break
                if bool((~fine & (lam <= DAMPING_MIN)).any()):
                    sample = engine.first(~fine & (lam <= DAMPING_MIN))
                    return (
                        None,
                        k,
                        f"no damped step down to {DAMPING_MIN:.2g} of the increment decreases it (increment "
                        f"{float(norm[sample]):.2g}, tolerance {tol:.2g})",
                        sample,
                    )
                lam = xp.where(fine, lam, lam / 2)
            W = trial
        return None, limit, f"not converged in {limit} iteration{'s' if limit != 1 else ''}", engine.first(active)


def host(values) -> np.ndarray:
    """A numpy view or copy of an engine's array, of its own dtype."""
    return values if isinstance(values, np.ndarray) else values.detach().cpu().numpy()


def jacobian_not_finite(compiled, engine, matrices) -> str:
    """The cause a singular Newton matrix gives where a Jacobian of ``matrices`` is not finite: its first such entry
    by name (d(u')/d(x) for sample 0), and the fix.  Each matrix a stack ``(B, ..., D, D)`` (rows f then g, columns
    y then z), or the nonzeros of one sample at ``engine.rows``, ``engine.cols`` (the casadi engine's)."""
    names = (*compiled.state_names, *compiled.algebraic_names)
    rows = (*(f"{y}'" for y in compiled.state_names), *compiled.constraint_names)
    at, where = (getattr(engine, "rows", None), getattr(engine, "cols", None)), ""
    for matrix in matrices:
        values = host(matrix) if hasattr(matrix, "detach") else np.asarray(matrix)
        bad = np.argwhere(~np.isfinite(values))
        if not len(bad):
            continue
        index = tuple(bad[0])
        if values.ndim >= 3 and values.shape[-2:] == (len(rows), len(names)):
            sample, row, column = index[0], index[-2], index[-1]
        elif values.ndim == 1 and at[0] is not None and len(values) == len(at[0]):
            sample, row, column = 0, at[0][index[0]], at[1][index[0]]
        else:
            continue
        where = f"d({rows[row]})/d({names[column]}) = {values[index]} for sample {sample}: "
        break
    return (
        f"the Jacobian of f and g is not finite there ({where}f or g is not differentiable at this state, e.g. "
        "sqrt(x) at x = 0, or the state left their domain, e.g. sqrt or log of a negative value, which a step "
        "this long can cause); take a smaller h, or the adaptive mode (rtol=..., atol=...)"
    )

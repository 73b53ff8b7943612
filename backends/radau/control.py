"""The two controllers of ``method="radau"``: where the steps go, and what Newton must reach.

A controller owns the step sequence and hands the :class:`~.step.Stepper` its Newton policy; the
step itself (start guess, Newton, error estimate, acceptance) is the same for both:

- :class:`FixedGrid` steps along ``t0 + k h`` and solves each step's stage equations to rounding
  (the Radau IIA collocation solution), checking every step's local error estimate.
- :class:`Radau5Controller` is RADAU5's step-size control: the embedded estimate against
  ``rtol``/``atol``, the step kept within a band so the factorisations are reused, a failed Newton
  halving h; every attempt counts against ``max_steps``.  Its attempt's decisions (before the
  attempt: h and the underflow; after it: accept or reject, the next h) are :mod:`.sequence`'s,
  which the compiled run (:mod:`.loop`) makes on casadi symbols; what is written here is what only
  Python does: the budget and the progress watch, the named errors, the stepper's calls.
"""

from __future__ import annotations

import warnings

import numpy as np
from daemodel.backends.base import caller_level
from daemodel.backends.grids import fixed_grid
from daemodel.backends.progress import PROGRESS_WINDOW, ProgressWatch
from daemodel.backends.radau import formulas, sequence
from daemodel.backends.radau.formulas import INITIAL_STEP_FLOOR, SCALAR
from daemodel.backends.radau.newton import NewtonPolicy
from daemodel.backends.radau.options import DEFAULT_NEWTON_ITERATIONS
from daemodel.backends.radau.sequence import HANDBACK

from daemodel.errors import ConvergenceError, LocalErrorWarning, StepLimitError, StepSizeError

# Newton's tolerance (adaptive_newton_tol) for more than three stages is at most this: rtol^(3/4) at s = 7,
# rtol = atol = 1e-3 (5.6e-3) ran the pendulum over [0, 20] in 11,902 attempts, 40 x (atol + rtol) off, 3e-3
# in 175, 1e-3 in 118 within 0.005 x (with RADAU5's contraction, formulas.GEOMETRIC_CONTRACTION_STAGES;
# with the last ratio alone: 7,307, 50 x at 5.6e-3, 241 at 1e-3)
HIGH_ORDER_NEWTON_TOL = 1e-3
# ... and at least this many times the rounding floor 10 eps / rtol, where three stages' rule is that loose:
# within a few floors the increments stall on rounding and the contraction tests fail Newton (the transistor
# amplifier at rtol = atol = 1e-9, s = 7, at the floor 2.2e-6: 2,264 attempts, 850 Newton failures; at 10
# floors: 913 and 132, as at three stages' 3.2e-5 before: 902 and 137)
HIGH_ORDER_ROUNDING_MARGIN = 10
# Fixed step: Newton stops when the scaled increment is below this many eps of the dtype.
FIXED_NEWTON_TOL_EPS = 10
# (The step-size formulas, RADAU5's safety factor and bounds, are .formulas', shared with .loop.)
# Keep h (and the LU) when the controller asks for a change within this band (RADAU5's QUOT1/2).
KEEP_H_BAND = (1.0, 1.2)
# Gustafsson's predictive controller (RADAU5's default): after the second accepted step, the new h is
# also predicted from the last two steps' errors and sizes, and the smaller of the two is taken
# (transistor amplifier: 109 -> 74 rejections at rtol 1e-6).  Not where Newton's tolerance sits at the
# rounding floor (Radau5Controller.rounding_floor): the estimates are noise there, and the prediction,
# which squares them, drove a chain of 40 pendulums (s = 7, rtol 1e-13) to step size underflow.
PREDICTIVE = True
# The last failure of a step size underflow that the error estimate caused, not Newton (underflow_error).
SHRUNK_BY_ESTIMATE = "the error estimate kept shrinking the step"
# The same where the step is compiled (a refactorisation costs 10-50 Newton iterations there): growth
# up to 1.5x keeps h (RADAU5 lets users widen QUOT2 where factorisations are costly); measured with
# REUSE_THETA_COMPILED, see there.
KEEP_H_BAND_COMPILED = (1.0, 1.5)
# A step size underflow that the error estimate caused is float64's resolution of t's doing where its threshold,
# UNDERFLOW |t| (45-90 spacings of t), is at least this share of t_span: the Max model from t0 = 1e14 over 2.5
# (threshold 1.0) asked for steps of ~0.13 at rtol 1e-6, and was told its solution may blow up (ConvergenceError).
RESOLUTION_SHARE = 1e-6


# Where the caller may stop the integration (Stepper.integrate's stop), a compiled run makes at most this
# many attempts between its looks at the outputs: the steps it makes past the stop are lost (the wheelset's
# event searches on [0, 1], rtol 1e-6, 28 events: 743 steps with the run's usual budget, 397 with 4)
STOP_ATTEMPTS = 4


def adaptive_newton_tol(rtol: float, stages: int, eps: float) -> float:
    """Newton's tolerance of an adaptive step, in units of the error tolerance: RADAU5's ``min(0.03,
    rtol^(1/2))`` for up to three stages, ``min(1e-3, rtol^((s - 1) / (s + 1)))`` for more, never below
    the rounding floor ``10 eps / rtol`` (for more than three stages not below
    :data:`HIGH_ORDER_ROUNDING_MARGIN` floors either, where three stages' rule is not: s = 7 below rtol
    1.6e-8, s = 5 below 6.4e-9, down to rtol 5e-10 where three stages' rule meets the floor).

    Hairer's variable-order RADAU (radau.f, s = 3, 5, 7) stops Newton at the estimate's tolerance to the
    power ``2s / (s + 1)`` (its FNEWT is that tolerance to ``(s - 1) / (s + 1)`` in its units): the
    estimate is O(h^(s+1)) and the solution's local error O(h^(2s)), so the stage errors Newton leaves
    stay at the latter's level, below what the estimate must see shrink with h.  RADAU5's sqrt(rtol) at
    s = 7 left them at 0.01 of rtol 1e-4 on the pendulum: the estimate stopped shrinking with h and h
    collapsed (step size underflow at t = 4.4); rtol^(3/4) is 1e-3 there.  Above rtol 1e-4 the power
    alone is not enough for s = 7: :data:`HIGH_ORDER_NEWTON_TOL` caps it.
    """
    if stages <= 3:
        return max(10 * eps / rtol, min(0.03, rtol**0.5))
    power, floor = (stages - 1) / (stages + 1), 10 * eps / rtol
    margin = min(0.03, rtol**0.5, HIGH_ORDER_ROUNDING_MARGIN * floor)
    return max(floor, margin, min(HIGH_ORDER_NEWTON_TOL, rtol**power))


class FixedGrid:
    """Steps along ``t0 + k h`` (the last one shortened to end at t1), Newton to rounding, each step's
    local error estimate checked (:meth:`~.error.ErrorEstimate.check_fixed`)."""

    name = "fixed"
    rounding_floor = True  # Newton to rounding: see Radau5Controller.rounding_floor

    def __init__(self, options):
        self.h, self.max_steps = options.h, options.max_steps
        eps = float(np.finfo(options.dtype).eps)
        # converge to rounding, increments measured against 1 + |w|
        self.policy = NewtonPolicy(
            tol=options.newton_tol or FIXED_NEWTON_TOL_EPS * eps,
            atol=1.0,
            rtol=1.0,
            iterations=options.max_newton_iterations,
            trust_last_rate=False,
            to_rounding=True,
            rescue=True,
        )

    def grid(self, t_span):
        return fixed_grid(t_span, self.h, max_steps=self.max_steps)

    def start_stats(self, stats: dict) -> None:
        # worst step, sample and variable, in units of 1 + max|u| (see ErrorEstimate.check_fixed)
        stats["max_local_error_estimate"] = 0.0
        stats["damped_newton_attempts"] = 0  # runs of the last resort (DAMPED_NEWTON_FACTOR); a step may need 2

    def run(self, stepper, t_span, grid) -> None:
        """Step along ``grid``, checking each step's local error estimate."""
        for step in range(1, len(grid)):
            if stepper.stopped():
                break
            t, h = float(grid[step - 1]), float(grid[step] - grid[step - 1])
            if abs(h - self.h) <= 1e-12 * self.h:
                h = self.h  # not its rounded copy: the LU and the estimate's weights are kept per h
            stepper.stats["attempts"] += 1
            result = None  # (the last step's stages and residual go before this one's are made)
            result, _, why, sample = stepper.attempt(t, h)
            if result is None:
                stepper.stats["newton_failures"] += 1
                raise ConvergenceError(
                    f"radau: Newton failed in step {step} from t = {t:.6g} with h = {h:.3g} ({why}, "
                    f"sample {sample}); take a smaller h, or the adaptive mode (rtol=..., atol=...)"
                )
            stepper.error.check_fixed(step, t, h, result[1])
            stepper.accept(t, h, result, float(grid[step]))
        stepper.stats["local_error_estimates"] = stepper.error.per_step


class Radau5Controller:
    """RADAU5's step-size controller on the embedded estimate (Hairer & Wanner, IV.8)."""

    name = "adaptive"

    def __init__(self, options):
        self.options = options
        self.rtol, self.atol = options.rtol, options.atol
        eps = float(np.finfo(options.dtype).eps)
        tol = options.newton_tol or adaptive_newton_tol(self.rtol, options.stages, eps)
        # below rtol ~5e-10 RADAU5's tolerance meets the rounding floor (10 eps / rtol): the stage errors, and
        # so the estimates, are near noise there (a newton_tol given that low too).  Read on three stages'
        # rule: the tighter one of more stages meets the floor sooner (s = 7 below rtol 3.8e-9), where the
        # estimates are not noise yet
        floor = 10 * eps / self.rtol
        self.rounding_floor = (options.newton_tol or adaptive_newton_tol(self.rtol, 3, eps)) <= floor * (1 + 1e-12)
        self.newton_default = adaptive_newton_tol(self.rtol, options.stages, eps)
        self.newton_hint = loose_newton_tol_hint(options.newton_tol, self.newton_default)
        self.policy = NewtonPolicy(
            tol=tol,
            atol=self.atol,
            rtol=self.rtol,
            iterations=options.max_newton_iterations,
            trust_last_rate=True,
            to_rounding=False,
            rescue=False,
        )

    def grid(self, t_span):
        return None  # the steps are found as they go

    def start_stats(self, stats: dict) -> None:
        pass

    def run(self, stepper, t_span, grid) -> None:
        """Steps from t0 to t1; every attempt counts against ``max_steps``.

        Each attempt is :mod:`.sequence`'s (the decisions before and after it, as the compiled run
        makes them), on Python floats; here only what Python alone does: the budget's and the
        progress watch's checks, the named errors, the stepper's calls, the hand-over to the
        compiled run (:mod:`.loop`) for as many attempts as the budget's next check allows.
        """
        options, stats = self.options, stepper.stats
        iterations = options.max_newton_iterations
        t0, t1 = t_span
        # the probe's step, also where h0 is given: no estimate above it is refiltered before a step is
        # accepted (formulas.refiltered_here: the floor's 1e7 from t0 = 1e17 and a user's h0 = 1e7 damped an
        # oscillator to 1e-79 as "success")
        trusted = self.initial_step(stepper, t_span)
        h = options.h0 or formulas.floored_step(SCALAR, trusted, t0, t1)
        # (h_acc 0: no accepted step yet, for Gustafsson's prediction)
        carried = dict(t=t0, h=h, first=True, rejected_last=False, h_acc=0.0, err_acc=0.0)
        keep = KEEP_H_BAND_COMPILED if stepper.keep_longer else KEEP_H_BAND
        settings = dict(
            t0=t0,
            t1=t1,
            limit=options.max_steps,  # (the compiled run's: up to the budget's next check, below)
            newton_tol=self.policy.tol,
            rtol=self.rtol,
            atol=self.atol,
            reuse_theta=stepper.reuse_theta(),
            keep_low=keep[0],
            keep_high=keep[1],
            predictive=float(PREDICTIVE and not self.rounding_floor),
            trusted=trusted,
        )
        half = (t0, 0)  # (t, accepted steps) when half the budget was spent: the recent rate of progress
        watch = ProgressWatch(t0, h, extra=0)  # extra: the accepted steps when the window began
        python_next = False  # the compiled run handed the next attempt back (see .loop)
        while not formulas.finished(SCALAR, carried["t"], t0, t1) and not stepper.stopped():
            t, h = carried["t"], carried["h"]
            attempts = stats["attempts"]
            if attempts >= options.max_steps:
                raise self.budget_error(stats, t, h, t1, half, options.max_steps - options.max_steps // 2)
            if attempts == options.max_steps // 2:
                half = (t, stats["steps"])
            needed = watch.hopeless(
                attempts,
                t,
                h,
                t1,
                options.max_steps,
                extra=stats["steps"],
                accepted=stats["steps"],
                err=float(carried["err_acc"]) if stats["steps"] else None,
                exponent=1.0 / (stepper.s + 1),
            )
            if needed is not None:
                t_w, count_w, _, accepted_w = watch.start
                raise self.budget_error(stats, t, h, t1, (t_w, accepted_w), attempts - count_w, projected=needed)
            if not python_next and stepper.run_ready():
                # the attempts up to the next budget check in compiled calls (the same steps as below): the
                # half and the whole budget, and the end of the progress watch's window
                checkpoint = options.max_steps // 2 if attempts < options.max_steps // 2 else options.max_steps
                checkpoint = min(checkpoint, max(watch.start[1] + PROGRESS_WINDOW, attempts + 1))
                if stepper.stop is not None:  # (the caller looks at the outputs this often: a few steps past its stop)
                    checkpoint = min(checkpoint, attempts + STOP_ATTEMPTS)
                limited = dict(settings, limit=checkpoint - attempts)
                carried, ended = stepper.compiled_run.advance(stepper, carried, limited)
                python_next = ended == HANDBACK
                continue
            python_next = False
            head = sequence.before_attempt(SCALAR, carried, settings)
            if head["underflow"]:
                probe = self.probe(stats, trusted)
                raise underflow_error(h, t, SHRUNK_BY_ESTIMATE, None, self.newton_hint, t1 - t0, probe)
            h = head["h"]
            result = None  # (the last attempt's stages and residual go before this one's are made)
            result, newton_iterations, why, sample, err = stepper.attempt_with_error(t, h, head["first"])
            failed = result is None
            attempt = dict(h=h, iterations=newton_iterations, error_norm=err, newton_failed=failed)
            attempt["jac_kept"] = not failed and stepper.keeps_jacobian(result[2])
            carried, decisions = sequence.after_attempt(SCALAR, carried, settings, attempt, stepper.s, iterations)
            accepted = decisions["accepted"]
            sequence.add_attempt(stats, accepted, failed)
            if not accepted:
                if decisions["shrunk_away"]:
                    if failed and why == formulas.UNNAMED_NON_FINITE:  # (the general path names where they arose)
                        result, _, named, named_sample = stepper.attempt(t, h)
                        why, sample = (named, named_sample) if result is None else (why, sample)
                    why = why if failed else f"error estimate {decisions['err']:.2g} > 1"
                    probe = self.probe(stats, trusted)
                    raise underflow_error(decisions["h_rejected"], t, why, sample, self.newton_hint, t1 - t0, probe)
                stepper.drop_factors()
                continue
            stepper.accept(t, h, result, decisions["t_next"])

    @staticmethod
    def probe(stats, trusted):
        """The probe's first step where no step was accepted yet (what :func:`underflow_error` reads of t's
        resolution), else None."""
        return trusted if not stats["steps"] else None

    def initial_step(self, stepper, t_span) -> float:
        """Hairer-Wanner's starting step (Solving ODEs I, II.4, as scipy's ``select_initial_step``):
        the first guess ``h0 = 0.01 |u0| / |f(u0)|`` in the error norm, then an explicit Euler probe
        to ``t0 + h0`` that measures how fast f changes, ``d2 = |f(t0 + h0, y0 + h0 f0, z0) - f0| / h0``
        (the algebraic variables held at their start), and the step ``min(100 h0, (0.01 / max(d1,
        d2))^(1/(s+1)))`` for the order-s estimate, capped by the interval.  Before
        :func:`.formulas.floored_step` lifts it (the caller's): no estimate above it is refiltered before
        the first accepted step.

        The first guess alone took the whole interval where f(u0) is small: from near a stirred tank's
        unstable steady state (f0 ~ 1e-5 of the state) one implicit step of 200 landed on that steady
        state, and no error estimate could see it (a wrong answer as "success"); the probe gives 0.10,
        scipy's Radau's own first step there.

        The casadi engine makes it in one call (:mod:`.start`: 35 of the pendulum's
        ~330 us solve on the path below), the same formula (:func:`.formulas.initial_step`).
        """
        t0, t1 = t_span
        if not stepper.n:  # (no states: no estimate to refilter)
            return min(max(1e-6, INITIAL_STEP_FLOOR * max(1.0, abs(t0))), t1 - t0)
        if stepper.engine.first_step is not None:
            h, stepper._f_start = stepper.engine.first_step(t0, t1, stepper.y, stepper.z, self.atol, self.rtol)
            return h
        f0 = stepper.start_f(t0)

        def probe(h0):
            return stepper.engine.f(t0 + h0, stepper.y + h0 * f0, stepper.z)

        rms = lambda x: float(stepper.rms(x).max())  # noqa: E731
        return formulas.initial_step(SCALAR, rms, stepper.y, f0, probe, self.atol, self.rtol, stepper.s, t0, t1)

    def status(self, method: str) -> str:
        """ "success" (every accepted step's estimate within rtol and atol), or "flagged: ..." with a
        :class:`~daemodel.errors.LocalErrorWarning` where the user's ``newton_tol`` is looser than the
        stages' default (:func:`adaptive_newton_tol`): the estimate does not see the stage errors Newton
        leaves (seven stages at rtol 1e-4 on the pendulum, newton_tol 0.03 for 1e-3: "success" 1.7e-2 off
        over [0, 6], 1.1 over [0, 20]; since each step is the one t's float64 spacing makes of h, 1.5e-2 off
        over [0, 4], and h underflows at t = 4.13 on longer spans)."""
        if not self.newton_hint:
            return "success"
        status = (
            f"flagged: {method}'s newton_tol = {self.options.newton_tol:g} is looser than these stages' default "
            f"({self.newton_default:.3g}): the error estimate does not see the stage errors Newton leaves, and the "
            "values may be further from the solution than rtol and atol say (seven stages at rtol 1e-4 on the "
            "pendulum over [0, 4]: 1.5e-2 off); leave newton_tol out"
        )
        warnings.warn(status, LocalErrorWarning, stacklevel=caller_level())
        return status

    def budget_error(self, stats, t, h, t1, half, recent, projected=None) -> StepLimitError:
        """max_steps ran out (or, ``projected``, cannot suffice): say where, and why it likely did
        (chattering, or a span too long); ``half`` is (t, accepted steps) ``recent`` attempts ago."""
        budget, accepted = self.options.max_steps, stats["steps"]
        failed = stats["rejected_steps"] + stats["newton_failures"]
        recent_accepted = accepted - half[1]
        progress = t - half[0]
        iterations = self.options.max_newton_iterations
        if stats["newton_failures"] > stats["rejected_steps"] and iterations < DEFAULT_NEWTON_ITERATIONS:
            reason = (
                f"{stats['newton_failures']} attempts failed in Newton, which stops at max_newton_iterations = "
                f"{iterations}: raise it (the default is {DEFAULT_NEWTON_ITERATIONS})"
            )
        elif recent_accepted < recent / 2:
            reason = (
                f"{recent - recent_accepted} of the last {recent} attempts were rejected or failed in Newton, "
                f"and they advanced t by {progress:.3g} of the {t1 - half[0]:.3g} left: the right-hand side is "
                "likely discontinuous near "
                f"t = {t:.6g} (sign(x), abs(x), min/max or a Piecewise that switches), and steps across the "
                "switch need h -> 0 (chattering); stop the integration at the switch and restart from there, "
                "or smooth the switch"
            )
        else:
            rate = progress / max(recent, 1)
            if projected is not None:
                more = f"about {projected:.3g} more"
            else:
                more = f"about {(t1 - t) / rate:.3g} more" if rate > 0 else "endlessly many"
            reason = (
                f"the steps are accepted, but at the last {recent} attempts' rate ({rate:.3g} per attempt) the "
                f"rest of t_span needs {more} attempts: t_span is too long for max_steps at this tolerance; "
                f"raise max_steps, loosen rtol/atol or shorten t_span{self.newton_hint}"
            )
        if projected is None:
            head = f"radau: max_steps = {budget} reached at t = {t:.6g}"
        else:
            head = (
                f"radau: max_steps = {budget} cannot suffice (about {projected:.3g} more attempts projected, "
                f"{budget - stats['attempts']} left), stopped early at t = {t:.6g}"
            )
        return StepLimitError(
            f"{head} (h = {h:.3g}) before t1 = {t1:g}, after {accepted} accepted steps and {failed} rejected or "
            f"failed attempts: {reason}"
        )


def loose_newton_tol_hint(given, default) -> str:
    """What the budget's and the underflow's errors add where the user's ``newton_tol`` is looser than the
    stages' own (``default``, :func:`adaptive_newton_tol`): nothing where none was given or it is not looser.

    (The pendulum at s = 7, rtol = atol = 1e-4 over [0, 20]: newton_tol = 0.03 collapsed h to 4e-6 at t = 3.9
    and the budget's error blamed the span alone; the default, 1e-3 there, runs it in 114 attempts.)"""
    if given is None or given <= default * (1 + 1e-12):
        return ""
    return (
        f"; or newton_tol = {given:g} is looser than these stages' default ({default:.3g}): the stage errors "
        "it leaves may not shrink with h, which then collapses where the solution is smooth: leave newton_tol out"
    )


def underflow_error(new, t, why, sample, newton_hint="", span=None, probe=None) -> ConvergenceError | StepSizeError:
    """The step size underflow at ``t`` with the step ``new`` (the last failure named); ``newton_hint``:
    :func:`loose_newton_tol_hint`'s, where the error estimate shrank the step.  A :class:`StepSizeError` that
    names t's float64 spacing where the error estimate shrank the step to a threshold that is t's resolution's
    (at least :data:`RESOLUTION_SHARE` of ``span``, t_span's length), or before any accepted step, where the
    start's probe (``probe``: its step, :meth:`Radau5Controller.initial_step`) asked for a step below that
    threshold (an oscillator from t0 = 1e17 over 9e17: 0.013, where t's spacing is 16)."""
    estimate = why is not None and (why == SHRUNK_BY_ESTIMATE or why.startswith("error estimate "))
    floor = formulas.UNDERFLOW * max(1.0, abs(t))
    unresolved = probe is not None and probe < floor
    if estimate and abs(t) > 1.0 and (unresolved or (span is not None and floor >= RESOLUTION_SHARE * span)):
        spacing = float(np.spacing(abs(t)))
        asked = f", where the start's probe asked for h = {probe:.3g}" if unresolved else ""
        asked += f", {floor / span:.2g} of t_span" if span else ""
        return StepSizeError(
            f"radau: the steps that rtol and atol ask for at t = {t:.17g} are shorter than float64 resolves "
            f"there: h = {new:.3g} (last failure: {why}) reached the step size underflow's threshold, 1e-14 |t| = "
            f"{floor:.3g}, {floor / spacing:.0f} float64 spacings of t at |t| = {abs(t):.3g} (spacing "
            f"{spacing:.3g}){asked}; start t_span nearer 0 (shift the model's time), loosen rtol and atol, or take "
            "more stages (longer steps at the same tolerance); a solution that blows up there ends so too"
        )
    who = f", sample {sample}" if sample is not None else ""
    if why is not None and why.startswith("not converged in"):  # (the iterations ran out, at every h)
        cause = (
            "Newton stops at max_newton_iterations before it converges: raise it (the default is "
            f"{DEFAULT_NEWTON_ITERATIONS})"
        )
    else:
        cause = "the solution may blow up or leave the domain of f there"
    if estimate:
        # (the pendulum at s = 7, rtol 1e-4, atol 1e-6 ended here at t = 4.4, smooth and bounded, under RADAU5's
        # Newton tolerance, 0.01 there: stage errors that do not shrink with h; adaptive_newton_tol's 1e-3 runs it)
        cause += (
            ", or, where it stays smooth, Newton's tolerance leaves stage errors that do not shrink with h (more "
            "stages at a looser rtol need a tighter one): give a smaller newton_tol (e.g. 1e-10), or leave stages out"
        ) + newton_hint
    return ConvergenceError(
        f"radau: step size underflow at t = {t:.6g} (h = {new:.3g}; last failure: {why}{who}); {cause}"
    )


def make_controller(options):
    """The controller ``options`` select: a fixed grid for ``h``, RADAU5's otherwise."""
    return Radau5Controller(options) if options.adaptive else FixedGrid(options)

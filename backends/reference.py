"""A tight-tolerance reference: scipy's integrators, stepped one by one, on the underlying ODE.

The algebraic variables are eliminated: ``z(t, y)`` solves the determining equations (the
constraints differentiated until z appears: ``g = 0`` at index 1, ``g_y f = 0`` at index 2,
...) by Newton, so the integrator sees the ODE ``y' = f(t, y, z(t, y))``.  The functions are
sympy's numpy lambdas, independent of the torch code generator that ``method="radau"`` uses.
This is the reference the paper used for the pendulum, which has no closed form, and the truth
that :func:`daemodel.compare` measures every method against, so it follows these rules:

1. Newton for z stops only on a small step *and* a small residual, within
   ``max_newton_iterations``; otherwise (no root, a singular ``H_z``, divergence) the solve
   raises :class:`~daemodel.errors.ConvergenceError` naming the time, the sample and the
   constraint with the largest residual: the algebraic variables are not determined there.
2. A non-finite state or derivative raises ConvergenceError naming the time, the sample and the
   state; so does a step size that underflows (a blow-up), naming the largest state.
3. A failed evaluation is localised before it is reported: the integrator restarts from the last
   accepted point with steps :data:`LOCATE_SHRINK` times shorter than the distance to the
   failure.  A trial point off the solution (an over-long step) then passes, and a real failure
   is reported where it happens, to :data:`LOCATE_RTOL`.
4. At most ``max_steps`` accepted steps per sample (:class:`~daemodel.errors.StepLimitError`).
5. ``integrator="auto"`` (default) starts with DOP853 and continues with Radau from the point
   where Hairer's stiffness test fires; ``stats["integrator"]`` says where
   (``"DOP853 -> Radau at t = 0.00153"``).  rtol = atol = 1e-12 by default.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace

import numpy as np
from daemodel.backends.base import (
    DEFAULT_OUTPUT_POINTS,
    SWEEP_FIRST_STEPS,
    AbstractBackend,
    ProgressWatch,
    check_number,
    check_output_memory,
    check_tolerances,
    make_solution,
    output_times,
    tolerance_sweep,
)

from daemodel.dense import Restarts
from daemodel.errors import ConvergenceError, InvalidOptionError, StepLimitError
from daemodel.init import NumericSystem, jacobian_entries

INTEGRATORS = ("DOP853", "RK45", "Radau", "BDF", "LSODA")
AUTO = "auto"
# scipy's solvers raise an rtol below 100 eps to 100 eps (with a warning): refuse it instead.
MIN_RTOL = 100 * float(np.finfo(float).eps)
# Accepted steps per sample: DOP853 at rtol 1e-12 takes ~12 per unit time on the pendulum and
# Hessenberg problems and Radau ~3000 on Robertson to t = 1e5, so 2e4 leaves a wide margin,
# while an explicit integrator on a stiff problem stops within seconds instead of hours.
MAX_STEPS = 20_000
# Newton for z(t, y): from the previous evaluation's z it converges in 2-3 iterations; 30
# leave room for the long steps of a loose-tolerance sweep, and a failure costs one call.
Z_NEWTON_MAXITER = 30
# Converged when the estimated error of z (the last step, times theta / (1 - theta) once the
# contraction theta is known) is below this, relative to 1 + max|z|: far below rtol = 1e-12.
Z_NEWTON_TOL = 1e-13
# ... and each residual is below this, relative to 1 + sum_j |dH_i/dz_j| |z_j|: the rounding
# level of the determining equations with eight digits to spare.
Z_RESIDUAL_TOL = 1e-8
# Newton that stalls (theta above Z_STALL_RATE) with a step below Z_STALL_TOL (relative) has
# reached the rounding level of an ill-conditioned H_z: accepted, not reported as a failure.
Z_STALL_RATE, Z_STALL_TOL = 0.5, 1e-9
# A failure is localised by restarting with steps LOCATE_SHRINK times shorter than the distance
# to it (about 8 steps a round), until that distance is below LOCATE_RTOL * max(1, |t|).
LOCATE_SHRINK = 8.0
LOCATE_RTOL = 1e-9
# Stiffness test of DOP853 (Hairer & Wanner II, Sec. IV.2; dop853.f): a step is flagged when
# h |lambda| exceeds 6.1, just inside DOP853's real stability interval (-6.39, 0); 15 flagged
# steps switch "auto" to Radau, and 6 unflagged steps in a row clear the count.
STIFF_H_LAMBDA = 6.1
STIFF_STEPS = 15
NONSTIFF_RESET = 6


@dataclass(frozen=True, kw_only=True)
class ReferenceOptions:
    """Options of ``method="reference"``.

    Attributes
    ----------
    rtol, atol : float
        The integrator's tolerances (default 1e-12 both; rtol from 100 eps to 0.1).
    integrator : str
        ``"auto"`` (default: DOP853, switched to Radau where the problem turns stiff), or one of
        scipy's DOP853, RK45, Radau, BDF, LSODA for the whole interval.
    max_steps : int
        Accepted steps per sample before :class:`~daemodel.errors.StepLimitError`.
    max_newton_iterations : int
        Newton iterations for z(t, y) per evaluation before
        :class:`~daemodel.errors.ConvergenceError`.
    t_eval : array, optional
        Output times; default 101 equally spaced.
    """

    rtol: float = 1e-12
    atol: float = 1e-12
    integrator: str = AUTO
    max_steps: int = MAX_STEPS
    max_newton_iterations: int = Z_NEWTON_MAXITER
    t_eval: object = None

    def __post_init__(self) -> None:
        check_tolerances(self.rtol, self.atol, minimum_rtol=MIN_RTOL)
        check_number("max_steps", self.max_steps, integer=True)
        check_number("max_newton_iterations", self.max_newton_iterations, integer=True)
        if self.integrator != AUTO and self.integrator not in INTEGRATORS:
            raise InvalidOptionError(
                f"integrator must be one of {', '.join(INTEGRATORS)} or {AUTO!r} (DOP853, then Radau where the "
                f"problem turns stiff); got {self.integrator!r}"
            )


def _finite(values: np.ndarray) -> bool:
    """Whether every value is finite (the sum first: one reduction instead of two on the hot path)."""
    return math.isfinite(values.sum()) or bool(np.isfinite(values).all())


class _EvaluationFailure(Exception):
    """Raised inside the right-hand side; the driver localises it, then reports it.

    ``reason`` completes "... near t = <t> (sample <b>): <reason>".
    """

    def __init__(self, t: float, reason: str):
        super().__init__(reason)
        self.t, self.reason = float(t), reason


class AlgebraicSolver:
    """Newton for the algebraic variables: ``z(t, y)`` with ``H(t, y, z, p) = 0``.

    Parameters
    ----------
    compiled : CompiledDAE
    numeric : NumericSystem
    maxiter : int
    """

    def __init__(self, compiled, numeric: NumericSystem, maxiter: int):
        determining = [c.determining for c in compiled.constraints]
        self.H = numeric.function(determining)
        self.Hz = numeric.jacobian(determining, compiled.algebraics)
        # Linear in z (H_z free of z, as in mechanics): one Newton step is exact but for rounding.
        # The entries of H_z that are not identically zero (the others hold no z either).
        _, _, entries = jacobian_entries(determining, compiled.algebraics, numeric.calculus)
        self.linear = not any(e.has(*compiled.algebraics) for e in entries)
        self.labels = [c.label for c in compiled.constraints]
        self.names = compiled.algebraic_names
        self.maxiter = maxiter
        self.iterations = 0

    def solve(self, t, y, z, p) -> np.ndarray:
        """``z`` of shape (m,) solving the determining equations, from the guess ``z``.

        Raises
        ------
        _EvaluationFailure
            Naming the constraint with the largest residual, when Newton does not converge,
            meets a singular Jacobian, or diverges.
        """
        if z.size == 0:
            return z
        r = self.H(t, y, z, p)
        previous = None  # the last step's size, for the contraction theta
        for _ in range(self.maxiter):
            self.iterations += 1
            J = self.Hz(t, y, z, p)
            try:
                dz = np.linalg.solve(J, -r)
            except np.linalg.LinAlgError:
                raise self._failure(t, z, r, "dH/dz is singular there") from None
            z = z + dz
            r = self.H(t, y, z, p)
            size = float(np.max(np.abs(dz)))
            if not math.isfinite(size):  # a non-finite residual makes the next step non-finite
                raise self._failure(t, z, r, "Newton for z diverged to non-finite values")
            scale = 1.0 + float(np.max(np.abs(z)))
            error, stalled = (0.0 if self.linear else size), False
            if previous is not None:
                theta = size / previous if previous > 0 else math.inf
                error = size * theta / (1 - theta) if theta < 1 else size
                stalled = theta > Z_STALL_RATE and size <= Z_STALL_TOL * scale
            if (error <= Z_NEWTON_TOL * scale or stalled) and np.all(
                np.abs(r) <= Z_RESIDUAL_TOL * (1.0 + np.abs(J) @ np.abs(z))
            ):
                return z
            previous = size
        raise self._failure(t, z, r, f"Newton for z did not converge within max_newton_iterations = {self.maxiter}")

    def _failure(self, t, z, r, why: str) -> _EvaluationFailure:
        worst = int(np.nanargmax(np.abs(r))) if np.any(np.isfinite(r)) else 0
        values = ", ".join(f"{n} = {v:.6g}" for n, v in zip(self.names, z, strict=True))
        return _EvaluationFailure(
            t,
            "the algebraic variables are not determined: the determining equations have no root there or are "
            f"singular ({why}; {self.labels[worst]} has the largest residual, {r[worst]:.3g}, at {values}). "
            "The DAE's solution cannot be continued past this time: end t_span before it, check the constraints, "
            "or raise max_newton_iterations if Newton was merely slow",
        )


class StiffnessDetector:
    """Hairer's stiffness test for DOP853, fed one accepted step at a time.

    Stage 12 (``c = 1``) and the new solution both approximate ``y(t + h)``; the difference of
    ``f`` over the difference of ``y`` there estimates the dominant eigenvalue's modulus, so
    ``h |lambda|`` shows whether the step size is held at the stability boundary.
    """

    def __init__(self):
        self.flagged = self.unflagged = 0
        self.h_lambda = 0.0
        self.stiff = False  # whether the test has fired once

    def update(self, solver) -> bool:
        """Whether the problem has been stiff for :data:`STIFF_STEPS` flagged steps, after ``solver.step()``."""
        h, K = solver.h_previous, solver.K
        y12 = solver.y_old + h * (K[:11].T @ solver.A[11, :11])
        spread = np.linalg.norm(solver.y - y12)
        if spread > 0:
            self.h_lambda = abs(h) * float(np.linalg.norm(K[12] - K[11])) / spread
        if self.h_lambda > STIFF_H_LAMBDA:
            self.flagged, self.unflagged = self.flagged + 1, 0
        else:
            self.unflagged += 1
            if self.unflagged >= NONSTIFF_RESET:
                self.flagged = 0
        self.stiff = self.stiff or self.flagged >= STIFF_STEPS
        return self.flagged >= STIFF_STEPS


class ReferenceBackend(AbstractBackend):
    """``method="reference"``: scipy on the underlying ODE, algebraic variables by Newton."""

    name = "reference"
    Options = ReferenceOptions
    max_index = 3

    def work_precision(self, t_span, points, steps=SWEEP_FIRST_STEPS):
        return tolerance_sweep(points)

    def describe(self, options: ReferenceOptions) -> str:
        integrator = "DOP853, Radau where stiff" if options.integrator == AUTO else options.integrator
        return f"method={self.name!r} (scipy {integrator}, rtol = {options.rtol:g}, atol = {options.atol:g})"

    def solve(self, compiled, t_span, start, options: ReferenceOptions):
        times = output_times(options.t_eval, t_span, np.linspace(*t_span, DEFAULT_OUTPUT_POINTS))
        check_output_memory(self.name, compiled, start.size, len(times))
        numeric = NumericSystem(compiled.t, compiled.states, compiled.algebraics, compiled.parameters)
        algebraic = AlgebraicSolver(compiled, numeric, options.max_newton_iterations)
        n, m = len(compiled.states), len(compiled.algebraics)
        values = np.empty((start.size, len(times), n + m))
        finals = []  # (each sample's integrator at its end)
        stats = {"integrator": [], "batch": start.size, "steps": 0, "nfev": 0, "njev": 0, "nlu": 0, "restarts": 0}
        began = time.perf_counter()
        with np.errstate(all="ignore"):  # non-finite values are detected and reported, never warned about
            f = numeric.function(compiled.rhs)
            setup = time.perf_counter() - began  # the right-hand side as a numpy function
            began = time.perf_counter()
            for b in range(start.size):
                run = _SampleRun(compiled, f, algebraic, start, b, options)
                values[b] = run.integrate(t_span, times)
                stats["integrator"].append(run.description)
                finals.append(run.integrator)
                for key in ("steps", "nfev", "njev", "nlu", "restarts"):
                    stats[key] += run.counts[key]
        distinct = list(dict.fromkeys(stats["integrator"]))
        stats["integrator"] = (
            distinct[0]
            if len(distinct) == 1
            else "; ".join(f"sample {b}: {d}" for b, d in enumerate(stats["integrator"]))
        )
        stats["newton_iterations"] = algebraic.iterations
        wall = time.perf_counter() - began
        # the dense output restarts with the integrator the samples ended with: a stiff problem's restart
        # would otherwise begin with DOP853 again (20x the error on akzo-nobel before it turns to Radau)
        ended = options if options.integrator != AUTO else replace(options, integrator=_ended_with(finals))
        dense = Restarts(self, compiled, ended, times, values, np.asarray(start.p, dtype=float))
        return make_solution(self, compiled, start, options, times, values, wall, stats, setup_time=setup, dense=dense)


def _ended_with(integrators: list) -> str:
    """The integrator for restarts of samples that ended with ``integrators``: Radau if any turned stiff."""
    return "Radau" if "Radau" in integrators else integrators[0]


class _SampleRun:
    """One sample's integration: the right-hand side, the stepping loop, the failure reports."""

    def __init__(self, compiled, f, algebraic: AlgebraicSolver, start, b: int, options: ReferenceOptions):
        self.compiled, self.f, self.algebraic, self.b, self.options = compiled, f, algebraic, b, options
        self.p, self.z = start.p[b], start.z0[b].copy()  # self.z: Newton's next guess
        self.y0 = start.y0[b]
        self.integrator = "DOP853" if options.integrator == AUTO else options.integrator
        self.description = self.integrator
        self.counts = dict.fromkeys(("steps", "nfev", "njev", "nlu", "restarts"), 0)
        self.h = math.nan  # the last accepted step

    def rhs(self, t, y):
        t = np.float64(t)  # numpy semantics (inf, nan) for 1/(t - 1) and the like
        if not _finite(y):
            raise _EvaluationFailure(t, self._nonfinite(y, "the state"))
        try:
            self.z = self.algebraic.solve(t, y, self.z, self.p)
            dy = self.f(t, y, self.z, self.p)
        except ArithmeticError as error:  # a Python-float operation (math.exp, **) overflowed
            raise _EvaluationFailure(t, f"evaluating the equations raised {type(error).__name__}: {error}") from None
        if not _finite(dy):
            raise _EvaluationFailure(t, self._nonfinite(dy, "the derivative of"))
        return dy

    def _nonfinite(self, values, what: str) -> str:
        bad = np.flatnonzero(~np.isfinite(values))
        listing = ", ".join(f"'{self.compiled.state_names[i]}' = {values[i]:g}" for i in bad)
        return (
            f"{what} {listing} is not finite: the solution blows up there or leaves the domain of the equations; "
            "end t_span before this time or check the equations"
        )

    def _start(self, t, y, max_step: float, first_step: float | None):
        from scipy import integrate

        return getattr(integrate, self.integrator)(
            self.rhs,
            t,
            y,
            self.t1,
            rtol=self.options.rtol,
            atol=self.options.atol,
            max_step=max_step,
            first_step=None if first_step is None else min(first_step, self.t1 - t),
        )

    def integrate(self, t_span, times) -> np.ndarray:
        """Values of shape (T, n + m) at ``times``."""
        t0, self.t1 = t_span
        out = np.empty((len(times), len(self.y0) + len(self.z)))
        done = 0  # outputs filled
        t, y = t0, self.y0.copy()
        self.t = t0  # the last accepted time, for the reports
        solver, detector, watch = None, StiffnessDetector(), None
        # While a failure at time ``guard`` is localised: steps at most max_step, and the distance
        # to the failure (window) must shrink from round to round.
        max_step, first_step, guard, window = math.inf, None, None, math.inf
        while solver is None or solver.status == "running":
            try:
                if solver is None:
                    solver = self._start(t, y, max_step, first_step)
                if self.counts["steps"] >= self.options.max_steps:
                    raise self._step_limit(detector)
                message = solver.step()
            except _EvaluationFailure as failure:
                distance = failure.t - t
                if distance <= LOCATE_RTOL * max(1.0, abs(t)) or distance >= window:
                    raise self._failed(failure.t, failure.reason) from None
                self._restart(solver)
                solver, window, guard = None, distance, failure.t
                max_step = first_step = distance / LOCATE_SHRINK
                continue
            if solver.status == "failed":
                raise self._stopped(solver, message.rstrip("."))
            self.counts["steps"] += 1
            t, y, self.h = solver.t, solver.y.copy(), solver.step_size
            self.t = t
            watch = watch or ProgressWatch(t0, self.h)
            needed = watch.hopeless(self.counts["steps"], t, self.h, self.t1, self.options.max_steps)
            if needed is not None:
                raise self._step_limit(detector, projected=needed)
            later = int(np.searchsorted(times, t, side="right"))
            if later > done:
                done = self._outputs(solver, times, done, later, out)
            if solver.status == "finished":
                break
            if guard is not None and t > guard:  # the failure was at a trial point off the solution
                self._restart(solver)
                solver, max_step, first_step, guard, window = None, math.inf, self.h, None, math.inf
            elif self.integrator == "DOP853" and detector.update(solver) and self.options.integrator == AUTO:
                self._restart(solver)
                self.integrator, solver, first_step = "Radau", None, None if guard is None else max_step
                self.description = f"DOP853 -> Radau at t = {t:.6g}"
        self._count(solver)
        return out

    def _restart(self, solver) -> None:
        self._count(solver)
        self.counts["restarts"] += 1

    def _count(self, solver) -> None:
        if solver is not None:
            for key in ("nfev", "njev", "nlu"):
                self.counts[key] += int(getattr(solver, key))

    def _outputs(self, solver, times, done: int, later: int, out) -> int:
        """Fill ``out[done:later]`` from the step's dense output; returns ``later``."""
        try:
            Y = solver.dense_output()(times[done:later]).T.reshape(later - done, -1)
            for k in range(done, later):
                self.z = self.algebraic.solve(np.float64(times[k]), Y[k - done], self.z, self.p)
                out[k] = np.concatenate([Y[k - done], self.z])
        except _EvaluationFailure as failure:
            raise self._failed(failure.t, failure.reason) from None
        return later

    def _where(self) -> str:
        return f"sample {self.b} of '{self.compiled.name}', integrator {self.description}"

    def _failed(self, t, reason: str) -> ConvergenceError:
        return ConvergenceError(f"reference: near t = {t:.8g} ({self._where()}): {reason}")

    def _stopped(self, solver, message: str) -> ConvergenceError:
        """The integrator gave up (in scipy's words: the step size underflowed, LSODA's work limit, ...)."""
        names = self.compiled.state_names
        big = int(np.argmax(np.abs(solver.y)))
        return ConvergenceError(
            f"reference: the integrator stopped near t = {solver.t:.8g} ({self._where()}): {message}; the "
            f"largest state there is '{names[big]}' = {solver.y[big]:.3g}: the solution may blow up (a singularity) "
            "at this time. End t_span before it, or check the equations"
        )

    def _step_limit(self, detector: StiffnessDetector, projected: float | None = None) -> StepLimitError:
        """max_steps ran out or, ``projected`` (steps still needed at the recent rate), cannot suffice."""
        hint = (
            f"use integrator='auto' or 'Radau': the problem is stiff (h |lambda| = {detector.h_lambda:.2g} holds "
            "DOP853 at its stability limit)"
            if self.integrator == "DOP853" and detector.stiff
            else "loosen rtol/atol, or use integrator='Radau' if the problem is stiff"
        )
        budget = self.options.max_steps
        if projected is None:
            head = f"reference: max_steps = {budget} reached at t = {self.t:.6g}"
        else:
            head = (
                f"reference: max_steps = {budget} cannot suffice (about {projected:.3g} more steps projected at the "
                f"recent rate, {budget - self.counts['steps']} left), stopped early at t = {self.t:.6g}"
            )
        return StepLimitError(
            f"{head} (h = {self.h:.3g}) before t1 = {self.t1:g} ({self._where()}); raise max_steps, shorten t_span, "
            f"or {hint}"
        )

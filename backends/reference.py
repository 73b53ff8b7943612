"""A tight-tolerance reference: scipy's integrators, stepped one by one, on the underlying ODE.

The algebraic variables are eliminated: ``z(t, y)`` solves the determining equations (the
constraints differentiated until z appears: ``g = 0`` at index 1, ``g_y f = 0`` at index 2,
...) by Newton, so the integrator sees the ODE ``y' = f(t, y, z(t, y))``.  The functions are
sympy's numpy lambdas, independent of the torch code generator that ``method="radau"`` uses.
This is the reference the paper used for the pendulum, which has no closed form, and the truth
that :func:`daemodel.compare` measures every method against, so it follows these rules:

1. Newton for z (:func:`daemodel.compiling.init.solve_algebraic`, the one algebraic Newton) stops only on a
   small step *and* a small residual, within ``max_newton_iterations``; otherwise (no root, a
   singular ``H_z``, divergence) the solve raises :class:`~daemodel.errors.ConvergenceError`
   naming the time, the sample and the constraint with the largest residual: the algebraic
   variables are not determined there.
2. z stays on the branch of roots chosen at t0: Newton starts from the branch's tangent
   prediction at each evaluation, and a root that does not continue the branch (``det H_z``
   changed sign since the last accepted point, or a jump far beyond the prediction's reach), or a
   Newton failure where ``H_z`` has turned nearly singular (a fold), raises
   :class:`~daemodel.errors.BranchError` (a ConvergenceError) once located as in rule 4.
3. A non-finite state or derivative raises ConvergenceError naming the time, the sample and the
   state; so does a step size that underflows (a blow-up), naming the largest state.
4. A failed evaluation is localised before it is reported: the integrator restarts from the last
   accepted point with steps :data:`LOCATE_SHRINK` times shorter than the distance to the
   failure.  A trial point off the solution (an over-long step) then passes, and a real failure
   is reported where it happens, to :data:`LOCATE_RTOL`.
5. At most ``max_steps`` accepted steps per sample (:class:`~daemodel.errors.StepLimitError`).
6. ``integrator="auto"`` (default) starts with DOP853 and continues with Radau from the point
   where Hairer's stiffness test fires; ``stats["integrator"]`` says where
   (``"DOP853 -> Radau at t = 0.00153"``).  It starts with Radau where the ODE's Jacobian at t0
   already decays faster than DOP853 could follow over the span (:data:`STIFF_DECAY_SPAN`;
   ``"Radau (stiff at t0: max -Re(lambda) = 2.6e+04)"``).  rtol = atol = 1e-12 by default.
"""

from __future__ import annotations

import contextlib
import math
import time
from dataclasses import dataclass, replace

import numpy as np
from daemodel.backends.base import AbstractBackend, make_solution
from daemodel.backends.checks import check_output_memory, set_number, set_tolerances
from daemodel.backends.grids import SWEEP_FIRST_STEPS, default_times, output_times, tolerance_sweep
from daemodel.backends.progress import ProgressWatch

from daemodel.compiling.init import NewtonTolerances, NumericSystem, jacobian_entries, solve_algebraic
from daemodel.compiling.linear import SPARSE_MIN_SIZE
from daemodel.dense import Restarts
from daemodel.errors import BranchError, ConvergenceError, InvalidOptionError, StepLimitError
from daemodel.files import check_dense

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
# The root Newton finds at a trial point continues the branch when it is within BRANCH_JUMP_RATIO
# times the larger of the predicted change of z and its change over the last accepted step of the
# tangent prediction, plus BRANCH_ATOL relative to 1 + max|z|: a continuation's correction is second
# order in the step (far below either), a jump to another root a distance between branches.  A
# trial point that fails the test only because its step is long passes once localisation shortens it.
BRANCH_JUMP_RATIO = 1.0
BRANCH_ATOL = 1e-6
# A Newton failure located just past an accepted point whose H_z has a smallest singular value
# below BRANCH_END_TOL times the norm of [H_z, H_t, H_y] (z changing 100 times faster than H)
# is the end of the branch (a fold, or a root running off to infinity), a BranchError.
BRANCH_END_TOL = 1e-2
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
# That test sees the eigenvalue that dominates the step's error, which at tight tolerances need not be
# the stiff one: on a driven heat equation DOP853 keeps h |lambda| near 3 (accuracy in the fast, quasi-
# steady modes) and never flags a step. So "auto" also looks at t0: where the ODE's Jacobian has a
# decay rate max(-Re lambda) with rate * (t1 - t0) above STIFF_DECAY_SPAN, DOP853 would need more than
# ~STIFF_DECAY_SPAN / 6.4 steps (1600) for stability alone, and Radau starts the solve. For up to
# STIFF_EIG_MAX unknowns (a dense eigenvalue problem, ~0.2 s at 1000); larger models rely on the test.
STIFF_DECAY_SPAN = 1e4
STIFF_EIG_MAX = 1000


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
        set_tolerances(self, minimum_rtol=MIN_RTOL)
        set_number(self, "max_steps", integer=True)
        set_number(self, "max_newton_iterations", integer=True)
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

    def __init__(self, t: float, reason: str, error: type[ConvergenceError] = ConvergenceError):
        super().__init__(reason)
        self.t, self.reason, self.error = float(t), reason, error


@dataclass(frozen=True)
class BranchPoint:
    """An accepted point ``(t, y, z)`` of a sample's branch of roots, with what continues it.

    Attributes
    ----------
    t : float
    y : ndarray, shape (n,)
    z : ndarray, shape (m,)
    dz_dt : ndarray, shape (m,)
    dz_dy : ndarray, shape (m, n)
        The tangent of the branch, ``-H_z^{-1} [H_t, H_y]`` (implicit function theorem): the
        prediction of z at a nearby ``(t, y)`` to first order.
    sign : float
        The sign of ``det H_z`` there: a branch that keeps it never crossed a singular ``H_z``.
    change : float
        ``max |z - z_before|`` over the last accepted step: how far z moves in a step, the scale of
        a correction that is still a continuation.
    """

    t: float
    y: np.ndarray
    z: np.ndarray
    dz_dt: np.ndarray
    dz_dy: np.ndarray
    sign: float
    change: float

    def predict(self, t, y) -> np.ndarray:
        return self.z + self.dz_dt * (t - self.t) + self.dz_dy @ (y - self.y)


class AlgebraicSolver:
    """The algebraic variables ``z(t, y)`` with ``H(t, y, z, p) = 0``, on one branch of roots.

    Newton is :func:`daemodel.compiling.init.solve_algebraic` (the one algebraic Newton) with this method's
    tolerances; it starts from the branch's tangent prediction, and the root it converges to must
    continue the branch (:meth:`leaves_branch`).

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
        # Newton's Jacobian: the dense one above, or its sparse nonzeros for large m (no dense m x m)
        if len(compiled.algebraics) >= SPARSE_MIN_SIZE:
            sparse = numeric.newton_jacobian(determining, compiled.algebraics)
            self.newton_Hz = lambda t, y, x, p: sparse(t, y[None], x, p[None])
        else:
            self.newton_Hz = lambda t, y, x, p: self.Hz(t, y, x[0], p)[None]
        self.Ht = numeric.jacobian(determining, (compiled.t,))
        self.Hy = numeric.jacobian(determining, compiled.states)
        # Linear in z (H_z free of z, as in mechanics): one Newton step is exact but for rounding,
        # and the root is unique wherever H_z is regular (no other branch to jump to).
        _, _, entries = jacobian_entries(determining, compiled.algebraics, numeric.calculus)
        linear = not any(e.has(*compiled.algebraics) for e in entries)
        self.tolerances = NewtonTolerances(
            step=Z_NEWTON_TOL,
            residual=Z_RESIDUAL_TOL,
            max_iterations=maxiter,
            stall_rate=Z_STALL_RATE,
            stall_step=Z_STALL_TOL,
            linear=linear,
        )
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
        result = solve_algebraic(
            lambda x: self.H(t, y, x[0], p)[None, :],
            lambda x: self.newton_Hz(t, y, x, p),
            z[None, :],
            self.tolerances,
        )
        self.iterations += result.iterations
        if result.converged[0]:
            return result.x[0]
        x, r = result.x[0], result.residual[0]
        if result.singular[0]:
            why = "dH/dz is singular there"
        elif not np.isfinite(x).all() or not np.isfinite(r).all():
            why = "Newton for z diverged to non-finite values"
        else:
            why = f"Newton for z did not converge within max_newton_iterations = {self.maxiter}"
        raise self._failure(t, x, r, why)

    def branch_point(self, t, y, z, p, before: BranchPoint | None) -> BranchPoint:
        """The :class:`BranchPoint` of an accepted ``(t, y, z)``; ``before``, the previous one."""
        if z.size == 0:
            return BranchPoint(t, y, z, z, np.zeros((0, y.size)), 1.0, 0.0)
        J = self.Hz(t, y, z, p)
        sign, _ = np.linalg.slogdet(J)
        try:
            tangent = -np.linalg.solve(J, np.column_stack([self.Ht(t, y, z, p), self.Hy(t, y, z, p)]))
        except np.linalg.LinAlgError:
            tangent = np.zeros((z.size, 1 + y.size))
        change = 0.0 if before is None else float(np.max(np.abs(z - before.z)))
        return BranchPoint(float(t), y.copy(), z.copy(), tangent[:, 0], tangent[:, 1:], float(sign), change)

    def leaves_branch(self, t, y, z, p, predicted: np.ndarray, point: BranchPoint) -> str | None:
        """Why the root ``z`` at ``(t, y)`` (Newton from ``predicted``) does not continue the branch
        through ``point``, or None when it does.

        Two measurable departures: ``det H_z`` changed sign since ``point`` (a singular ``H_z`` lies
        between: the branch folds or meets another, and z is not determined there), or the root is
        further from the tangent prediction than :data:`BRANCH_JUMP_RATIO` times the larger of the
        predicted change and z's change over the last step, plus :data:`BRANCH_ATOL` (relative),
        and further than that from the last root itself: a continuation's correction is second order
        in the step, a jump to another root is not (where H has a kink the tangent misleads, and
        the constant prediction is the closer one).
        """
        if z.size == 0:
            return None
        sign, _ = np.linalg.slogdet(self.Hz(t, y, z, p))
        if sign != point.sign:
            values, before = self._values(z), self._values(point.z)
            return (
                f"the algebraic variables leave their branch of roots: det(dH/dz) changes sign between t = "
                f"{point.t:.8g} ({before}) and here ({values}), so dH/dz is singular in between: the branch "
                "turns back (a fold) or meets another one, and the constraints do not determine z past it. End "
                "t_span before this time, or change the constraints so that their root stays isolated"
            )
        if self.tolerances.linear:
            return None  # a regular H_z linear in z has one root: nothing to jump to
        jump = float(np.max(np.abs(z - predicted)))
        allowed = BRANCH_JUMP_RATIO * max(float(np.max(np.abs(predicted - point.z))), point.change)
        allowed += BRANCH_ATOL * (1.0 + float(np.max(np.abs(point.z))))
        # (where H has a kink, Min or Max of the states, the tangent misleads: a root as close to the last
        # root itself, the constant prediction, continues the branch too)
        if min(jump, float(np.max(np.abs(z - point.z)))) <= allowed:
            return None
        guess, values, before = self._values(predicted), self._values(z), self._values(point.z)
        return (
            f"the algebraic variables leave their branch of roots: continuing it from t = {point.t:.8g} "
            f"({before}) predicts {guess}, but Newton converged to another root, {values} (a jump of {jump:.3g}, "
            f"allowed {allowed:.3g}): the branch ends (a fold) or comes close to another one there. End t_span "
            "before this time, or change the constraints so that their root stays isolated"
        )

    def branch_ends(self, point: BranchPoint, p) -> str | None:
        """Why a Newton failure just past ``point`` is the end of its branch of roots, or None.

        The branch ends where ``H_z`` turns singular relative to the other derivatives of the
        determining equations (smallest singular value of ``H_z`` below :data:`BRANCH_END_TOL`
        times the norm of ``[H_z, H_t, H_y]``): z's rate of change blows up there, at a fold where
        the root meets another and both vanish, or as the root runs off to infinity.
        """
        if point.z.size == 0:
            return None
        t, y, z = point.t, point.y, point.z
        J = self.Hz(t, y, z, p)
        whole = np.linalg.norm(np.column_stack([J, self.Ht(t, y, z, p), self.Hy(t, y, z, p)]), 2)
        smallest = np.linalg.svd(J, compute_uv=False)[-1]
        if not smallest <= BRANCH_END_TOL * whole:
            return None
        return (
            f"; the branch of roots ends here: at the last accepted point, t = {t:.8g} ({self._values(z)}), dH/dz "
            f"is nearly singular (smallest singular value {smallest:.2g}, against {whole:.2g} for all of H's "
            "derivatives): the root meets another one and both vanish (a fold), or runs off to infinity"
        )

    def _values(self, z) -> str:
        return ", ".join(f"{n} = {v:.6g}" for n, v in zip(self.names, z, strict=True))

    def _failure(self, t, z, r, why: str) -> _EvaluationFailure:
        finite = np.isfinite(r)
        worst = int(np.argmax(np.where(finite, np.abs(r), -np.inf))) if finite.any() else 0
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
        began = time.perf_counter()  # (the checks, z's solver and the right-hand side made: setup)
        n, m = len(compiled.states), len(compiled.algebraics)
        check_dense(
            f"method='reference' on '{compiled.name}' ({n} states, {m} algebraic variables: H_z, its tangent and "
            "scipy's Jacobian)",
            max(n, m),
            "use method='radau' or 'casadi-idas' (sparse), and a reference= of either in compare",
        )
        times = output_times(options.t_eval, t_span, default_times(t_span))
        check_output_memory(self.name, compiled, start.size, len(times))
        numeric = compiled.numeric
        values = np.empty((start.size, len(times), n + m))
        finals = []  # (each sample's integrator at its end)
        stats = {"integrator": [], "batch": start.size, "steps": 0, "nfev": 0, "njev": 0, "nlu": 0, "restarts": 0}
        with np.errstate(all="ignore"):  # non-finite values are detected and reported, never warned about
            # (z's solver: H, its Jacobians as numpy functions, 0.8 s of a chain of 20 pendulums' first solve, and
            # scipy's integrators imported, 0.6 s: on neither clock, hence on the solve's, before)
            algebraic = AlgebraicSolver(compiled, numeric, options.max_newton_iterations)
            f = numeric.function(compiled.rhs)
            if options.integrator == AUTO:  # (the stiffness test's Jacobians, made at its first use: 72 ms there)
                _stiffness_jacobians(compiled)
            import scipy.integrate  # noqa: F401

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
        # (from each sample's own start where t_eval leaves t0 out: a piece after a breakpoint or event)
        starts, first = (times, values) if times[0] == t_span[0] else _with_start(t_span[0], times, values, start)
        dense = Restarts(self, compiled, ended, starts, first, np.asarray(start.p, dtype=float))
        return make_solution(self, compiled, start, options, times, values, wall, stats, setup_time=setup, dense=dense)


def _stiffness_jacobians(compiled) -> None:
    """The numpy Jacobians :meth:`_SampleRun.decay_rate` evaluates, made now (in a setup) where it uses them;
    one that has no numeric form (a switch's derivative) is left to it, which then lets the steps decide."""
    n, m = len(compiled.states), len(compiled.algebraics)
    if n == 0 or n + m > STIFF_EIG_MAX:
        return
    with contextlib.suppress(ValueError, TypeError, NotImplementedError, ArithmeticError):
        compiled.numeric.jacobian(compiled.rhs, compiled.states)
        if m:
            compiled.numeric.jacobian(compiled.rhs, compiled.algebraics)


def _with_start(t0: float, times, values, start):
    """``times`` and ``values`` (B, T, n+m) with each sample's start at ``t0`` first."""
    first = np.concatenate([start.y0, start.z0], axis=1)[:, None]
    return np.concatenate([[t0], times]), np.concatenate([first, values], axis=1)


def _ended_with(integrators: list) -> str:
    """The integrator for restarts of samples that ended with ``integrators``: Radau if any turned stiff."""
    return "Radau" if "Radau" in integrators else integrators[0]


class _SampleRun:
    """One sample's integration: the right-hand side, the stepping loop, the failure reports."""

    def __init__(self, compiled, f, algebraic: AlgebraicSolver, start, b: int, options: ReferenceOptions):
        self.compiled, self.f, self.algebraic, self.b, self.options = compiled, f, algebraic, b, options
        self.p, self.y0, self.z0 = start.p[b], start.y0[b], start.z0[b].copy()
        self.point = None  # the branch of roots chosen at t0, moved from accepted point to accepted point
        self.last = None  # (t, y, z) of the last evaluation: z at an accepted point without a new solve
        self.integrator = "DOP853" if options.integrator == AUTO else options.integrator
        self.description = self.integrator
        self.counts = dict.fromkeys(("steps", "nfev", "njev", "nlu", "restarts"), 0)
        self.h = math.nan  # the last accepted step

    def decay_rate(self, t, y, z) -> float:
        """``max(-Re lambda)`` of the ODE's Jacobian ``f_y - f_z H_z^-1 H_y`` at ``(t, y, z)``; 0 for
        models above :data:`STIFF_EIG_MAX` unknowns or where it is not finite."""
        compiled, numeric, p = self.compiled, self.compiled.numeric, self.p
        n = len(compiled.states)
        if n == 0 or n + len(compiled.algebraics) > STIFF_EIG_MAX:
            return 0.0
        try:  # (the derivative of a switch, sign or Abs, has no numeric form: then the steps decide, as before)
            J = numeric.jacobian(compiled.rhs, compiled.states)(t, y, z, p)
            if len(compiled.algebraics):
                fz = numeric.jacobian(compiled.rhs, compiled.algebraics)(t, y, z, p)
                J = J - fz @ np.linalg.solve(self.algebraic.Hz(t, y, z, p), self.algebraic.Hy(t, y, z, p))
        except (np.linalg.LinAlgError, ValueError, TypeError, NotImplementedError, ArithmeticError):
            return 0.0
        if not np.isfinite(J).all():
            return 0.0
        return float(max(0.0, -np.linalg.eigvals(J).real.min()))

    def rhs(self, t, y):
        t = np.float64(t)  # numpy semantics (inf, nan) for 1/(t - 1) and the like
        if not _finite(y):
            raise _EvaluationFailure(t, self._nonfinite(y, "the state"))
        try:
            z = self.z_at(t, y)
            self.last = (t, y.copy(), z)
            dy = self.f(t, y, z, self.p)
        except ArithmeticError as error:  # a Python-float operation (math.exp, **) overflowed
            raise _EvaluationFailure(t, f"evaluating the equations raised {type(error).__name__}: {error}") from None
        if not _finite(dy):
            raise _EvaluationFailure(t, self._nonfinite(dy, "the derivative of"))
        return dy

    def z_at(self, t, y) -> np.ndarray:
        """z at ``(t, y)`` on this sample's branch: Newton from the branch's tangent prediction.

        Raises
        ------
        _EvaluationFailure
            When Newton fails, or its root leaves the branch (a :class:`BranchError` once located).
        """
        if not self.z0.size:  # (an ODE: no branch to follow, and its prediction's products took ~1/6 of a solve)
            return self.z0
        predicted = self.point.predict(t, y)
        z = self.algebraic.solve(t, y, predicted, self.p)
        why = self.algebraic.leaves_branch(t, y, z, self.p, predicted, self.point)
        if why is not None:
            raise _EvaluationFailure(t, why, BranchError)
        return z

    def _accept(self, t, y) -> None:
        """Move the branch's anchor to the accepted point ``(t, y)``."""
        last = self.last
        if last is not None and last[0] == t and np.array_equal(last[1], y):
            z = last[2]  # (the integrator's last evaluation is at the new point: FSAL, Radau's f_new)
        else:
            z = self.z_at(np.float64(t), y)
        self.point = self.algebraic.branch_point(t, y, z, self.p, self.point)

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
        self.point = self.algebraic.branch_point(np.float64(t0), self.y0, self.z0, self.p, None)
        out = np.empty((len(times), len(self.y0) + len(self.z0)))
        done = 0  # outputs filled
        t, y = t0, self.y0.copy()
        self.t = t0  # the last accepted time, for the reports
        started_stiff = False  # (Radau from t0 by the Jacobian: DOP853 once more where its steps look hopeless)
        if self.options.integrator == AUTO:
            decay = self.decay_rate(np.float64(t0), y, self.z0)
            if decay * (self.t1 - t0) > STIFF_DECAY_SPAN:
                self.integrator, started_stiff = "Radau", True
                self.description = f"Radau (stiff at t0: max -Re(lambda) = {decay:.2g})"
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
                    raise self._failed(failure.t, failure.reason, failure.error) from None
                self._restart(solver)
                solver, window, guard = None, distance, failure.t
                max_step = first_step = distance / LOCATE_SHRINK
                continue
            if solver.status == "failed":
                raise self._stopped(solver, message.rstrip("."))
            self.counts["steps"] += 1
            t, y, self.h = solver.t, solver.y.copy(), solver.step_size
            self.t = t
            try:
                self._accept(t, y)
            except _EvaluationFailure as failure:
                raise self._failed(failure.t, failure.reason, failure.error) from None
            watch = watch or ProgressWatch(t0, self.h)
            needed = watch.hopeless(self.counts["steps"], t, self.h, self.t1, self.options.max_steps)
            if needed is not None and started_stiff and solver.status != "finished":
                # (a transient that only looked stiff at t0, beside an oscillation Radau must resolve too)
                self._restart(solver)
                self.integrator, solver, first_step, watch, started_stiff = "DOP853", None, None, None, False
                self.description = f"Radau (stiff at t0) -> DOP853 at t = {t:.6g}"
                detector = StiffnessDetector()
                continue
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
            if not self.z0.size:  # (an ODE: the outputs are the states)
                out[done:later] = Y
                return later
            for k in range(done, later):
                z = self.z_at(np.float64(times[k]), Y[k - done])
                out[k] = np.concatenate([Y[k - done], z])
        except _EvaluationFailure as failure:
            raise self._failed(failure.t, failure.reason, failure.error) from None
        return later

    def _where(self) -> str:
        return f"sample {self.b} of '{self.compiled.name}', integrator {self.description}"

    def _failed(self, t, reason: str, error: type[ConvergenceError] = ConvergenceError) -> ConvergenceError:
        ends = None if error is BranchError else self.algebraic.branch_ends(self.point, self.p)
        if ends is not None:
            error, reason = BranchError, reason + ends
        return error(f"reference: near t = {t:.8g} ({self._where()}): {reason}", float(t))

    def _stopped(self, solver, message: str) -> ConvergenceError:
        """The integrator gave up (in scipy's words: the step size underflowed, LSODA's work limit, ...)."""
        names = self.compiled.state_names
        big = int(np.argmax(np.abs(solver.y)))
        return ConvergenceError(
            f"reference: the integrator stopped near t = {solver.t:.8g} ({self._where()}): {message}; the "
            f"largest state there is '{names[big]}' = {solver.y[big]:.3g}: the solution may blow up (a singularity) "
            "at this time. End t_span before it, or check the equations",
            float(solver.t),
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
            f"or {hint}",
            float(self.t),
        )

"""``method="casadi-idas"``: SUNDIALS IDAS (BDF, variable order) on the index-1 reduction
(:func:`daemodel.solve` hands it the reduction; the original constraints' drift is reported
through :meth:`Solution.drift`).

Trust: IDAS starts from consistent derivatives.  ``y'(t0) = f(t0, y0, z0)``: ``calc_ic`` lets IDAS
compute it for each sample inside the call, so one integrator serves a whole batch (``init_xdot``
fixes it per integrator: a rebuild per sample, 5x slower on a batch of 50 pendulums); a sample
whose IDACalcIC fails gets its own integrator with ``init_xdot = f``.  Without either, IDAS
assumes ``y' = 0`` and fails its error test at t0 on most models.  IDACalcIC's own step is a share
of IDAS's first one (:func:`~.plumbing.consistent_start`): left at casadi's 0.001 of the last output,
it moved nearly consistent algebraic values off their constraints by about that step times z', and
IDAS failed at its first step.  ``z'(t0)`` cannot be given to IDAS at all: it predicts z with
``z' = 0``, so its first step must be short enough for that prediction to pass the error test,
``h |z'(t0)| < rtol |z0| + atol``; ``step0`` is set so (see :data:`FIRST_STEP_SAFETY`) from
``z'(t0) = -g_z^{-1} (g_t + g_y f)``.  IDAS then doubles the step
as usual (a few steps more).  Leaving z out of the error test instead (``suppress_algebraic``) is
no fix: IDAS's Newton then stops correcting z where y does not depend on it, and z drifts off its
constraint.  A failure is one line: :class:`~daemodel.errors.StepLimitError` when IDAS exhausts
``max_num_steps``, :class:`~daemodel.errors.ConvergenceError` otherwise, IDAS's flag translated.

Events: ``solve(..., stop=...)`` (the event search) runs IDAS in windows read at two outputs or more an
IDAS step (:mod:`.idas_search`): casadi shows nothing between the outputs it is given.  A span shorter than
:data:`SHORT_SPAN` is solved on normalised time: casadi's IDAS takes no step towards an output within about
1e-9 of its start.
"""

from __future__ import annotations

import re
import time
from dataclasses import dataclass

import numpy as np
from daemodel.backends.base import AbstractBackend, make_solution
from daemodel.backends.casadi.idas_search import FIRST_WINDOW, MIN_POINTS, real_times, search
from daemodel.backends.casadi.plumbing import (
    QUIET,
    cached_integrator,
    consistent_start,
    dae_of,
    first_non_finite,
    integrator_stats,
    last_lines,
    last_number,
    run_samples,
    scaled_dae,
)
from daemodel.backends.checks import check_output_memory, set_number, set_tolerances
from daemodel.backends.grids import SWEEP_FIRST_STEPS, default_times, output_times, tolerance_sweep
from daemodel.backends.progress import captured_output

from daemodel.compiling.codegen import casadi_jacobian
from daemodel.dense import AbstractDenseOutput, outputs_before
from daemodel.errors import ConvergenceError, DaemodelError, InvalidOptionError, SolverError, StepLimitError
from daemodel.executors import struck_limit

# IDAS's first step: this fraction of the longest step whose z' = 0 prediction passes the error
# test, h |z'(t0)| = rtol |z0| + atol (order 1: the estimate is about the prediction's error).
FIRST_STEP_SAFETY = 0.1

# A span shorter than this (relative to max(1, |t|)) is solved on normalised time: casadi's IDAS takes no step
# towards an output within about 1e-9 of the start (x' = 1 from x(0.5) = 0.5: x(0.5 + 1e-9) came back 0.5, so
# the trial solves that located a crossing 1e-7 from an output saw no change and settled 1e-7 late).
SHORT_SPAN = 1e-6

# IDAS's return flags: what happened (with the time spliced in) and what to do about it.
IDAS_REASONS = {
    "IDA_ERR_FAIL": (
        "the error test failed repeatedly{at}",
        "the problem may be singular there or need a smaller atol",
    ),
    "IDA_CONV_FAIL": (
        "the Newton iteration failed repeatedly{at}",
        "the constraints may stop determining the algebraic variables there (g_z singular), or the "
        "solution is not smooth there",
    ),
    "IDA_TOO_MUCH_ACC": (
        "IDAS cannot deliver the accuracy asked for{at}",
        "loosen rtol/atol",
    ),
    "IDA_LSETUP_FAIL": (
        "the linear solver's setup failed{at}",
        "the iteration matrix is singular: the constraints may stop determining the algebraic variables there",
    ),
    "IDA_LSOLVE_FAIL": (
        "the linear solve failed{at}",
        "the iteration matrix is singular: the constraints may stop determining the algebraic variables there",
    ),
    "IDA_RES_FAIL": (
        "the model could not be evaluated{at}",
        "it leaves its domain there (division by zero, log or sqrt of a negative number)",
    ),
    "IDA_REP_RES_ERR": (
        "the model's evaluation failed repeatedly{at}",
        "it leaves its domain there (division by zero, log or sqrt of a negative number)",
    ),
    "IDA_NO_RECOVERY": (
        "the consistent initial derivative could not be computed{at}",
        "the constraints may not determine the algebraic variables at t0 (g_z singular)",
    ),
    "IDA_LINESEARCH_FAIL": (
        "the consistent initial derivative could not be computed (line search failed){at}",
        "the constraints may not determine the algebraic variables at t0 (g_z singular)",
    ),
    "IDA_FIRST_RES_FAIL": (
        "the model could not be evaluated at the initial state{at}",
        "it leaves its domain there (division by zero, log or sqrt of a negative number)",
    ),
}


@dataclass(frozen=True, kw_only=True)
class IDASOptions:
    """Options of ``method="casadi-idas"``.

    Attributes
    ----------
    rtol, atol : float
        IDAS's relative and absolute tolerances (rtol in
        :data:`~daemodel.backends.checks.RTOL_RANGE`).
    t_eval : array, optional
        Output times; default 101 equally spaced.
    max_num_steps : int
        IDAS's step limit per output interval; exhausting it raises
        :class:`~daemodel.errors.StepLimitError`.
    suppress_algebraic : bool
        Leave the algebraic variables out of IDAS's local error test (its ``suppressalg``).  Off
        by default, as in IDAS.  On the transistor amplifier the node potentials in the test
        cost 16,000 steps at rtol = 1e-7 (40 % of them failing it), and 1e-10 ran out of
        max_num_steps; without them IDAS takes about 1,900 steps at 1e-7.  The algebraic
        variables then follow the states' accuracy only through the constraints.
    """

    rtol: float = 1e-8
    atol: float = 1e-10
    t_eval: object = None
    max_num_steps: int = 100_000
    suppress_algebraic: bool = False

    def __post_init__(self) -> None:
        set_tolerances(self)
        set_number(self, "max_num_steps", integer=True)
        if not isinstance(self.suppress_algebraic, bool):
            raise InvalidOptionError(f"suppress_algebraic must be True or False; got {self.suppress_algebraic!r}")


def idas_failure(
    error: str, printed: str, *, sample: int, model: str, grid, max_num_steps: int, t0: float = 0.0
) -> SolverError:
    """casadi-idas's failure as one line: IDAS's return flag translated, with the time IDAS printed (its own
    time, since ``t0``: :func:`~daemodel.backends.casadi.plumbing.shifted_dae`).

    ``error`` holds casadi's ``IDASolve returned "IDA_ERR_FAIL"``; ``printed`` IDAS's own
    message, e.g. ``At t = 0.5 and h = 3.8e-10, the error test failed repeatedly ...``.
    """
    name = IDASBackend.name
    flag = re.search(r'(IDA\w+) returned "(\w+)"', error)
    function, code = flag.groups() if flag else ("IDAS", None)
    t, h = last_number(r"t = ([-+0-9.eE]+)", printed), last_number(r"h = ([-+0-9.eE]+)", printed)
    t = None if t is None else t0 + t
    at = "" if t is None else f" at t = {t:.6g}" + ("" if h is None else f" with step size {h:.3g}")
    where = f"sample {sample} of '{model}'"
    if code == "IDA_TOO_MUCH_WORK":
        if t is None:
            ended = "did not reach the next output time"
        else:
            target = grid[min(int(np.searchsorted(grid, t)), len(grid) - 1)]
            ended = (
                f"ended just before the output time t = {target:.6g}"
                if f"{t:.6g}" == f"{target:.6g}"
                else f"ended at t = {t:.6g}, before the output time t = {target:.6g}"
            )
        return StepLimitError(
            f"{name}: max_num_steps = {max_num_steps:,} steps {ended} ({where}); raise max_num_steps (the limit "
            "per output interval) or loosen rtol/atol, or, if the solution is singular there, shorten t_span",
            t,
        )
    if code in IDAS_REASONS:
        reason, fix = IDAS_REASONS[code]
        return ConvergenceError(f"{name}: {reason.format(at=at)} ({where}, {code}); {fix}", t)
    said = last_lines(printed) or last_lines(error)
    return ConvergenceError(f"{name}: {function} failed{at} ({where}, {code}): {said}", t)


def slopes_function(dae: dict):
    """The casadi function ``(t, x, z, p) -> (f, g_z, g_t + g_y f)`` of ``dae`` (index 1): ``g_z`` a
    sparse matrix, the last a directional derivative (no dense ``g_y``)."""
    import casadi

    t, x, z, p, alg = dae["t"], dae["x"], dae["z"], dae["p"], dae["alg"]
    rate = casadi.jacobian(alg, t) + casadi.jtimes(alg, x, dae["ode"])
    return casadi.Function("slopes", [t, x, z, p], [dae["ode"], casadi_jacobian(alg, z), rate])


def initial_slopes(compiled, dae: dict, t0: float, start) -> tuple[np.ndarray, np.ndarray]:
    """``y'(t0) = f`` (B, n) and ``z'(t0) = -g_z^{-1} (g_t + g_y f)`` (B, m) of every sample (index 1),
    by a sparse LU of ``g_z`` (the function made once per model: :func:`slopes_function`)."""
    from scipy.sparse.linalg import splu

    slopes = compiled.cached("casadi-idas-slopes", lambda: slopes_function(dae))
    B, n, m = start.size, start.y0.shape[1], start.z0.shape[1]
    ydot, zdot = np.zeros((B, n)), np.zeros((B, m))
    for b in range(B):
        f, g_z, rate = slopes(t0, start.y0[b], start.z0[b], start.p[b])
        ydot[b] = np.asarray(f, dtype=float).reshape(n)
        if m:
            try:
                zdot[b] = -splu(g_z.sparse().tocsc()).solve(np.asarray(rate, dtype=float).reshape(m))
            except DaemodelError:  # (a time limit's signal, raised inside the call: not a singular system)
                raise
            except RuntimeError:  # g_z singular: IDAS will say where it fails
                zdot[b] = np.nan
    return ydot, zdot


def first_step(zdot, z0, rtol: float, atol: float, t_span, first_output: float) -> float | None:
    """IDAS's ``step0``: short enough that predicting z with ``z' = 0`` passes the first error test.

    None (IDAS chooses) when IDAS's own first guess, ``0.001 (t_out - t0)``, is short enough
    already; never below the float resolution of t at t0, where it is taken (not at the far end of
    t_span: on (0, 1e20) that floor was 2.6e5, and the pendulum failed at t = 0).
    """
    moving = np.isfinite(zdot) & (zdot != 0)
    if not moving.any():
        return None
    longest = float(np.min((rtol * np.abs(z0[moving]) + atol) / np.abs(zdot[moving])))
    step = FIRST_STEP_SAFETY * longest
    if step >= 1e-3 * (first_output - t_span[0]):
        return None
    return max(step, 16 * float(np.spacing(max(abs(t_span[0]), 1.0))))


@dataclass(frozen=True, eq=False)
class IDASRestarts(AbstractDenseOutput):
    """casadi-idas's dense output: IDAS started again from the output before each time asked for, with
    the solve's tolerances, to that time (casadi keeps IDAS's interpolating polynomials to itself).
    Every time is one short IDAS run from consistent values, on normalised time (:func:`~.plumbing.normalised_dae`),
    all of them in one mapped call; an output time itself is the solve's own value."""

    times: np.ndarray  # (T,)
    values: np.ndarray  # (B, T, n+m)
    parameters: np.ndarray  # (B, k)
    integrator: object  # () -> the integrator from s = 0 to 1 on normalised time
    n: int
    solves_again = True

    @property
    def description(self) -> str:
        return "IDAS started again from the output before each time"

    def __call__(self, times: np.ndarray) -> np.ndarray:
        times = np.asarray(times, dtype=float)
        B, D = len(self.values), self.values.shape[2]
        before, out, after = outputs_before(self.times, self.values, times)
        inside = np.flatnonzero(after)
        if not len(inside):
            return out
        K = len(inside)
        starts = self.values[:, before[inside]].reshape(B * K, D)
        tau = np.tile(self.times[before[inside]], B)
        p = np.concatenate(
            [np.repeat(self.parameters, K, axis=0), tau[:, None], np.tile(times[inside], B)[:, None] - tau[:, None]],
            axis=1,
        )
        try:
            with captured_output() as printed:
                found = self.integrator().map(B * K)(x0=starts[:, : self.n].T, z0=starts[:, self.n :].T, p=p.T)
        except DaemodelError:  # (a time limit's signal, raised inside the call: not a singular system)
            raise
        except RuntimeError as error:
            if struck_limit() is not None:  # (the time limit struck inside IDAS's callback: not IDAS's failure)
                raise struck_limit() from error
            asked = ", ".join(f"{t:.6g}" for t in times[inside][:3])
            raise ConvergenceError(
                f"casadi-idas's dense output: IDAS started again from the outputs before t = {asked} failed "
                f"({last_lines(printed.getvalue()) or error}); ask for those times with t_eval instead"
            ) from None
        ends = np.concatenate([np.asarray(found["xf"]), np.asarray(found["zf"])], axis=0).T.reshape(B, K, D)
        out[:, inside] = ends
        return out


class IDASBackend(AbstractBackend):
    """``method="casadi-idas"``: SUNDIALS IDAS (BDF, variable order) on the index-1 reduction.

    ``stats["first_step"]`` is the ``step0`` given to IDAS (None: IDAS chose; a batch shares the
    shortest any sample needs, so its values can differ from single solves within the tolerance), and
    ``stats["initial_slope_fallbacks"]`` counts the samples whose IDACalcIC failed and that got
    an integrator of their own with ``init_xdot = f(t0, y0, z0)``.
    """

    name = "casadi-idas"
    Options = IDASOptions
    max_index = 1
    stops = True  # solve(..., stop=...): the event search in windows read at each step (.idas_search)

    def work_precision(self, t_span, points, steps=SWEEP_FIRST_STEPS):
        return tolerance_sweep(points)

    def solve(self, compiled, t_span, start, options: IDASOptions, stop=None):
        import casadi

        if stop is not None and start.size != 1:
            raise InvalidOptionError(f"stop=... reads one sample's outputs; this solve has {start.size} samples")
        times = output_times(options.t_eval, t_span, default_times(t_span))
        grid = times[1:] if times[0] == t_span[0] else times
        check_output_memory(self.name, compiled, start.size, len(times))
        began = time.perf_counter()
        if len(grid) == 0 or not t_span[1] > t_span[0]:  # only t0 asked for, or a span of length 0 (an event's trial
            # solve from a to a bracket's end one float64 spacing on, at its midpoint: divided by the span, 0, before)
            times = times[:1]
            values = np.concatenate([start.y0, start.z0], axis=1)[:, None, :]
            return make_solution(self, compiled, start, options, times, values, time.perf_counter() - began, {})
        dae = dae_of(compiled)
        ydot, zdot = initial_slopes(compiled, dae, t_span[0], start)
        settings = {
            "abstol": options.atol,
            "reltol": options.rtol,
            "max_num_steps": options.max_num_steps,
            "suppress_algebraic": options.suppress_algebraic,
            "disable_internal_warnings": True,
            **QUIET,
        }
        step0 = first_step(zdot, start.z0, options.rtol, options.atol, t_span, grid[0])
        if step0 is not None:
            settings["step0"] = step0
        if stop is not None:
            return self._search(compiled, t_span, start, options, dae, settings, zdot, stop, began)
        # (on the time since t0, given as the last parameter: plumbing.shifted_dae; a span shorter than casadi's
        # IDAS steps over on normalised time, where it is 1 long, t0 and the span the last two parameters)
        t0, span = float(t_span[0]), 1.0
        if t_span[1] - t_span[0] < SHORT_SPAN * max(1.0, abs(t_span[0]), abs(t_span[1])):
            span = float(t_span[1] - t_span[0])
            scale, extra = "normalised", [t0, span]
            settings = {**settings, "step0": step0 / span} if step0 is not None else settings
        else:
            scale, extra = "shifted", [t0]
        out = [(float(t) - t0) / span for t in grid]
        P = np.concatenate(
            [np.asarray(start.p, dtype=float).reshape(start.size, -1), np.tile(extra, (start.size, 1))], 1
        )
        start_ic = consistent_start(out[0], settings.get("step0"))  # (IDACalcIC's own step: on the run's time)
        shared = cached_integrator(compiled, "idas", scale, 0.0, out, {**settings, **start_ic})
        fallbacks = []
        setup = time.perf_counter() - began  # building the integrator: reported apart from the solve
        began = time.perf_counter()

        def call(b):
            """IDAS with y'(t0) from IDACalcIC; where that fails, a one-off integrator given y'(t0) = f(t0, y0, z0)."""
            try:
                return shared(x0=start.y0[b], z0=start.z0[b], p=P[b])
            except RuntimeError as error:
                if "IDACalcIC" not in str(error) or struck_limit() is not None:
                    raise
            fallbacks.append(b)
            exact = {**settings, "calc_ic": False, "init_xdot": (ydot[b] * span).tolist()}
            integrator = casadi.integrator("idas", "idas", scaled_dae(compiled, scale), 0.0, out, exact)
            return integrator(x0=start.y0[b], z0=start.z0[b], p=P[b])

        def explain(sample, error, printed):
            # (normalised time: IDAS's times said on the real scale; shifted: its time is since t0)
            printed, since = (real_times(printed, t0, span), 0.0) if len(extra) == 2 else (printed, t0)
            return idas_failure(
                error, printed, sample=sample, model=compiled.name, grid=grid, max_num_steps=options.max_num_steps,
                t0=since,
            )  # fmt: skip

        values = run_samples(call, compiled, start, len(grid), explain)
        stats = {
            "batch": start.size,
            "casadi_calls": start.size,
            "first_step": step0,
            "initial_slope_fallbacks": len(fallbacks),
        }
        stats.update(integrator_stats(shared))
        times_out = np.concatenate([[t_span[0]], grid])
        failure = first_non_finite(self.name, compiled, times_out, values, "tighten rtol/atol or shorten t_span")
        if failure is not None:
            raise failure
        wall = time.perf_counter() - began
        # (built on the first query, kept with the model; the first step IDAS chose on the real time
        # scale means nothing on the normalised one)
        restart_settings = {key: v for key, v in settings.items() if key != "step0"} | consistent_start(1.0, None)

        def restart():
            return cached_integrator(compiled, "idas", "normalised", 0.0, [1.0], restart_settings)

        dense = IDASRestarts(times_out, values, np.asarray(start.p, dtype=float), restart, len(compiled.states))
        if times[0] != t_span[0]:
            values = values[:, 1:]
        return make_solution(self, compiled, start, options, times, values, wall, stats, setup_time=setup, dense=dense)

    def _search(self, compiled, t_span, start, options, dae, settings, zdot, stop, began):
        """The solve of one sample that ends where ``stop`` says (:func:`.idas_search.search`), its outputs
        about one an IDAS step, with the dense output of IDAS started again from them."""
        first_output = t_span[0] + FIRST_WINDOW * (t_span[1] - t_span[0]) / MIN_POINTS
        step0 = first_step(zdot, start.z0, options.rtol, options.atol, t_span, first_output)
        restart_settings = {key: v for key, v in settings.items() if key != "step0"}  # (search adds IDACalcIC's)

        def explain(error, printed, outputs):
            return idas_failure(
                error, printed, sample=0, model=compiled.name, grid=outputs, max_num_steps=options.max_num_steps
            )

        slopes = compiled.cached("casadi-idas-slopes", lambda: slopes_function(dae))

        def slope(t, y, z):
            return np.asarray(slopes(t, y, z, start.p[0])[0], dtype=float).reshape(-1)

        times, values, stats = search(
            compiled, t_span, start.y0[0], start.z0[0], start.p[0], restart_settings, step0, stop, explain,
            options.max_num_steps, slope,
        )  # fmt: skip
        failure = first_non_finite(self.name, compiled, times, values, "tighten rtol/atol or shorten t_span")
        if failure is not None:
            raise failure
        stats |= {"batch": 1, "casadi_calls": stats["search_windows"] + stats["search_redos"], "first_step": step0}
        stats.setdefault("initial_slope_fallbacks", 0)

        def restart():
            dense_settings = restart_settings | consistent_start(1.0, None)
            return cached_integrator(compiled, "idas", "normalised", 0.0, [1.0], dense_settings)

        dense = IDASRestarts(times, values, np.asarray(start.p, dtype=float), restart, len(compiled.states))
        wall = time.perf_counter() - began
        return make_solution(self, compiled, start, options, times, values, wall, stats, dense=dense)

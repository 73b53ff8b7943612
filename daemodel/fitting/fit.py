"""``fit``: parameters (and initial states) of a DAE from measured outputs.

Least squares on the misfit between the data and radau's solution at the measured times, with the
exact derivatives of that solution (:mod:`daemodel.sensitivities`): scipy's trust-region
reflective ``least_squares`` with the sensitivities as its Jacobian, bounds kept.  Each series is
weighed by its noise level: the one given (``sigma``), else one estimated from its own residuals
(feasible weighted least squares: start from the series' root mean square, fit, estimate each
series' level from its residuals, fit again while a level changes by more than 10 %), so series of
different magnitudes and noise count by their information.  The standard errors come from the
Jacobian at the estimate, ``cov = s^2 (J^T J)^-1`` with ``s^2`` the weighted residuals' mean
square (the usual asymptotic estimate: independent noise of one level within each series, a model
nearly linear over the estimate's uncertainty).  Over 200 noise draws on the damped pendulum the
two-standard-error intervals held the truth 92.5 % (L) and 96.5 % (m) of the time.

Before and after the iterations the Jacobian's columns are checked: a parameter the data do not
determine (no effect on the outputs, an effect that has faded beside the others', or one that
another's change can undo) is refused with :class:`~daemodel.errors.UnidentifiableError`, naming
the parameters involved, instead of returning an arbitrary value with a meaningless standard error.

``method="pinn"`` trains the Radau-PINN's segment networks together with the parameters
(:mod:`daemodel.backends.pinn.inverse`); the result has the same form, with the PINN's certificate.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field

import numpy as np

from daemodel.compiling.compiler import as_compiled
from daemodel.errors import (
    DataError,
    InvalidOptionError,
    UnidentifiableError,
    UnknownSymbolError,
)
from daemodel.reals import is_real, real, real_array
from daemodel.sensitivities import directions
from daemodel.solving.solver import solve

# A direction in the (scaled) parameter space along which the weighted outputs change less than this
# fraction of the Jacobian's largest singular value is one the data do not determine.
IDENTIFIABILITY_RTOL = 1e-7
# In a dependent direction, the parameters whose share of the (unit) null vector is at least this are named.
CULPRIT_SHARE = 0.1
# Without sigma, each series' noise level is estimated from its residuals and the fit run again with
# those weights, until no level changes by more than REWEIGHT_RTOL (at most REWEIGHTINGS times); a
# level is kept above NOISE_FLOOR times the series' root mean square (noise-free data).
REWEIGHTINGS, REWEIGHT_RTOL, NOISE_FLOOR = 4, 0.1, 1e-10
# A start on a bound moves this fraction of the interval inside it.
START_INSIDE = 1e-3
# An estimate within this of a bound (relative to 1 + |value|) is reported at the bound.
BOUND_RTOL = 1e-8
# Central differences of the initial-state projection (an algebraic map): step relative to 1 + |value|.
PROJECTION_STEP = 1e-6
# Iterations (Jacobian evaluations) of the least-squares solver, unless max_iterations says otherwise.
DEFAULT_MAX_ITERATIONS = 100


@dataclass(frozen=True)
class Fit:
    """The result of :func:`fit`.

    Attributes
    ----------
    parameters : dict name -> float
        The estimates.
    std : dict name -> float
        Their standard errors from the Jacobian at the estimate.
    correlation : ndarray, shape (P, P)
        The estimates' correlation matrix, in the order of ``parameters``.
    residuals : dict output -> ndarray (T,)
        data - model at the measured times (NaN where the data are missing).
    solution : Solution
        The model solved at the estimate, on the measured times (t0 first).
    cost : float
        Half the sum of the weighted residuals' squares (radau: each series divided by its noise
        level, given or estimated, so about half the degrees of freedom at a good fit; pinn: by its
        sigma when every series has one, else by its data's spread).
    iterations : int
        Jacobian evaluations (one solve with sensitivities each).
    status : str
        ``"success"`` when the solver's convergence test held; otherwise why it stopped.
    method : str
    fit_time : float
        Seconds from start to result (solves, sensitivities and the solver's own work).
    certificate : object or None
        The Radau-PINN's certificate (``method="pinn"``); None for ``"radau"``.
    """

    parameters: dict
    std: dict
    correlation: np.ndarray = field(repr=False)
    residuals: dict = field(repr=False)
    solution: object = field(repr=False)
    cost: float
    iterations: int
    status: str
    method: str
    fit_time: float
    certificate: object = field(default=None, repr=False)

    def __repr__(self) -> str:
        rows = [f"  {name:>12} = {value:.10g} +- {self.std[name]:.3g}" for name, value in self.parameters.items()]
        return (
            f"Fit({self.method}, {self.status}, cost {self.cost:.4g}, {self.iterations} iterations, "
            f"{self.fit_time:.3g} s)\n" + "\n".join(rows)
        )


@dataclass(frozen=True)
class _Problem:
    """The checked inputs of one fit."""

    compiled: object
    names: tuple
    start: np.ndarray
    low: np.ndarray
    high: np.ndarray
    times: np.ndarray  # the solve's output times: t0, then the measured times
    rows: np.ndarray  # each measured time's index in ``times``
    data: dict  # output -> (T,) with NaN
    scale: dict  # output -> the series' weight's inverse: its noise level, given or first guessed
    estimated: frozenset  # the series whose noise level the fit estimates (no sigma given)

    @property
    def size(self) -> int:
        """The number of measured values (NaN left out)."""
        return sum(int((~np.isnan(d)).sum()) for d in self.data.values())


def fit(
    model,
    t,
    data: dict,
    parameters: dict,
    *,
    method: str = "radau",
    y0=None,
    sigma: dict | None = None,
    max_iterations: int = DEFAULT_MAX_ITERATIONS,
    tol: float = 1e-10,
    progress: bool | None = None,
    **options,
) -> Fit:
    """Estimate parameters and initial states from measured outputs.

    Parameters
    ----------
    model : Model or CompiledDAE
    t : array (T,)
        Measurement times, increasing, at or after the model's initial time.
    data : dict output name -> array (T,)
        Measured values of states, algebraic variables or aliases; NaN where missing.
    parameters : dict name -> float or (low, high) or (low, start, high)
        What to estimate: parameters and states (their initial values), each with a starting
        value, or bounds (the start is then their geometric mean when both are finite and positive,
        their midpoint when finite, else the model's value), or both; a start on a bound moves
        1e-3 of the interval inside.  Every other parameter and state keeps the model's value
        (``y0`` overrides the states', fitted ones' starts included).  At each trial the initial
        states are projected onto the constraints with the fitted states held.
    method : {"radau", "pinn"}
    y0 : dict state -> float, optional
        Known initial states other than the model's.
    sigma : dict output -> float, optional
        The noise level (standard deviation) of each series: its residuals are divided by it, so
        it sets the series' relative weights; the standard errors still scale with the residuals
        (see :func:`standard_errors`).  Default: estimated from the series' residuals (see the
        module docstring).  The PINN uses them when every series has one, else each series' spread.
    max_iterations : int
        radau: most evaluations of the residuals (solves), summed over the noise-level
        reweightings; pinn: most Gauss-Newton steps.  The result is flagged (``status``) when they run out.
    progress : bool, optional
        A progress bar over the solves (radau) or the Gauss-Newton steps (pinn), with the current
        estimates (default: when stderr is a terminal).
    tol : float
        radau: the least-squares solver's tolerance on the relative change of the cost and of the
        estimates (the PINN stops on its own tests, with ``config.tol`` on the Radau residual).
    **options
        radau's options for each solve (default ``rtol=1e-8``), or the Radau-PINN's for ``"pinn"``.

    Returns
    -------
    Fit

    Raises
    ------
    DataError
        For times outside the model's span or not increasing, a series that is all NaN, or arrays
        of the wrong length.
    UnidentifiableError
        When the data do not determine some parameters (the Jacobian's columns are dependent), naming them.
    UnknownSymbolError, SensitivityError, InvalidOptionError
        For names the model does not have, algebraic variables named as parameters, bad options.
    """
    started = time.perf_counter()
    compiled = as_compiled(model)
    problem = _problem(compiled, t, data, parameters, sigma, y0)
    if isinstance(max_iterations, bool) or not isinstance(max_iterations, int) or max_iterations < 1:
        raise InvalidOptionError(f"max_iterations must be a positive integer; got {max_iterations!r}")
    if not (is_real(tol) and 0 < float(tol) < 1):
        raise InvalidOptionError(f"tol must be a number in (0, 1); got {tol!r}")
    if method == "pinn":
        return _fit_pinn(problem, y0, max_iterations, {**options, "progress": progress}, started)
    if method != "radau":
        raise InvalidOptionError(f"fit: method must be 'radau' or 'pinn'; got {method!r}")
    return _fit_radau(problem, y0, max_iterations, float(tol), options, started, progress)


def _problem(compiled, t, data, parameters, sigma, y0=None) -> _Problem:
    times = real_array(t, "fit: t", error=DataError)
    if times.ndim != 1 or len(times) == 0 or not np.isfinite(times).all():
        raise DataError(f"fit: t must be a non-empty 1-d array of finite times; got {np.shape(t)!r}")
    if (np.diff(times) <= 0).any():
        k = int(np.flatnonzero(np.diff(times) <= 0)[0])
        raise DataError(f"fit: t must increase; t[{k}] = {times[k]:g} and t[{k + 1}] = {times[k + 1]:g}")
    if times[0] < compiled.t0:
        raise DataError(
            f"fit: t[0] = {times[0]:g} is before the initial time t0 = {compiled.t0:g} of '{compiled.name}': data "
            "outside the span the model integrates over; drop those points or declare m.initial(t=...) earlier"
        )
    if times[-1] <= compiled.t0:
        raise DataError(
            f"fit: every time in t is the initial time t0 = {compiled.t0:g}: data there measure the initial values "
            "only, which the parameters do not move along a solution; measure later times"
        )
    if not isinstance(data, dict) or not data:
        raise DataError("fit: data must be a dict output name -> measured values, with at least one series")
    outputs = (*compiled.state_names, *compiled.algebraic_names, *compiled.alias_names)
    series, scale = {}, {}
    sigma = dict(sigma or {})
    given = set(sigma)
    for name, values in data.items():
        if name not in outputs:
            raise UnknownSymbolError(
                f"fit: data name {name!r}, which model '{compiled.name}' has no output of; its outputs are "
                f"{list(outputs)}"
            )
        array = real_array(values, f"fit: data[{name!r}]", error=DataError)  # (no strings, complex or bools)
        if array.shape != times.shape:
            raise DataError(f"fit: data[{name!r}] has shape {array.shape}; t has {times.shape}")
        if np.isinf(array).any():
            raise DataError(
                f"fit: data[{name!r}] holds infinite values (at t = {times[np.isinf(array)][0]:g}); use NaN for missing"
            )
        if np.isnan(array).all():
            raise DataError(f"fit: data[{name!r}] is NaN everywhere: a series with no measurement; drop it")
        series[name] = array
        if name in sigma:
            scale[name] = real(sigma.pop(name), f"sigma[{name!r}]")
            if not scale[name] > 0:
                raise DataError(f"fit: sigma[{name!r}] must be positive; got {scale[name]}")
        else:
            rms = float(np.sqrt(np.nanmean(array**2)))
            scale[name] = rms if rms > 0 else 1.0
    if sigma:
        raise DataError(f"fit: sigma names {sorted(sigma)}, for which data has no series")
    if not isinstance(parameters, dict) or not parameters:
        raise InvalidOptionError("fit: parameters must be a dict name -> start value or (low, high) bounds, not empty")
    where = directions(compiled, tuple(parameters), caller="fit")
    values = dict(zip(compiled.parameter_names, compiled.parameter_values, strict=True))
    values.update(_initial_states(compiled, y0))
    start, low, high = [], [], []
    for name, spec in parameters.items():
        lo, x0, hi = _bounds(name, spec)
        start.append(x0 if x0 is not None else values.get(name, 0.0))
        low.append(lo)
        high.append(hi)
    start, low, high = (np.array(a, dtype=float) for a in (start, low, high))
    start = _inside(start, low, high)
    if times[0] > compiled.t0:
        grid, rows = np.concatenate([[compiled.t0], times]), np.arange(1, len(times) + 1)
    else:
        grid, rows = times, np.arange(len(times))
    estimated = frozenset(name for name in series if name not in given)
    return _Problem(compiled, where.names, start, low, high, grid, rows, series, scale, estimated)


def _inside(start, low, high):
    """``start`` strictly inside its bounds: a value on or beyond one moves inside by 1e-3 of the
    interval (or of the bound's size, for a one-sided bound); the optimizers need an interior start."""
    start = np.clip(start, low, high)
    finite_low, finite_high = np.isfinite(low), np.isfinite(high)
    size = np.maximum(1.0, np.abs(np.where(finite_low, low, np.where(finite_high, high, 1.0))))
    width = np.where(finite_low & finite_high, high - low, size)
    step = START_INSIDE * width
    start = np.where(finite_low & (start <= low), low + step, start)
    return np.where(finite_high & (start >= high), high - step, start)


def _bounds(name, spec):
    """``(low, start or None, high)`` of one entry of ``parameters``."""
    if is_real(spec):
        return -math.inf, real(spec, f"parameters[{name!r}]"), math.inf
    if isinstance(spec, tuple | list) and len(spec) in (2, 3) and all(is_real(v) for v in spec):
        numbers = [real(v, f"parameters[{name!r}]", finite=False) for v in spec]
        low, high = numbers[0], numbers[-1]
        if not low < high:
            raise InvalidOptionError(
                f"fit: parameters[{name!r}] has bounds ({low:g}, {high:g}): low must be below high"
            )
        if len(numbers) == 3:
            if not low <= numbers[1] <= high:
                raise InvalidOptionError(
                    f"fit: parameters[{name!r}]: the start {numbers[1]:g} is outside ({low:g}, {high:g})"
                )
            return low, numbers[1], high
        if not (math.isfinite(low) and math.isfinite(high)):
            return low, None, high
        return low, (math.sqrt(low * high) if low > 0 else 0.5 * (low + high)), high
    raise InvalidOptionError(
        f"fit: parameters[{name!r}] must be a start value, (low, high) bounds or (low, start, high); got {spec!r}"
    )


class _Model:
    """The weighted residuals and their Jacobian at parameter vectors, one solve with sensitivities
    each, kept for the last vector (scipy asks for the residuals and the Jacobian apart).

    The initial states at a vector are the model's (or ``y0``'s) with the fitted states replaced,
    projected onto the constraints with the fitted states held (:meth:`initial`).  Where the model
    has constraint levels free of algebraic variables, the derivative of that projection is taken
    by central differences of the projection itself (an algebraic map, cheap, to ~1e-9), so the
    Jacobian is the derivative of the very map the fit evaluates; the rest is the exact sensitivity
    of radau's solution from those initial states."""

    def __init__(self, problem: _Problem, y0, options):
        from daemodel.sensitivities import zero_free_levels

        # radau adaptive at rtol 1e-8 unless the caller chose (fixed steps: h; the PINN's grid)
        self.problem = problem
        self.options = {"rtol": 1e-8, **options} if "h" not in options and "rtol" not in options else dict(options)
        c = problem.compiled
        self.base_p = dict(zip(c.parameter_names, c.parameter_values, strict=True))
        self.base_y = _initial_states(c, y0)
        self.states = [name for name in problem.names if name in c.state_names]
        self.projected = bool(zero_free_levels(c))
        self.scale = dict(problem.scale)  # each series' noise level: given, or estimated (reweight)
        self.last = None
        self.solves = 0
        self.bar = None  # a progress bar over the solves, when the fit shows one

    def values(self, x) -> tuple[dict, dict]:
        """``(parameters, initial states)`` by name at ``x``, the states not yet projected."""
        names = self.problem.names
        parameters = {**self.base_p, **{n: v for n, v in zip(names, x, strict=True) if n in self.base_p}}
        return parameters, {**self.base_y, **{n: v for n, v in zip(names, x, strict=True) if n in self.base_y}}

    def initial(self, x) -> np.ndarray:
        """The consistent initial states (n,) at ``x``: the fitted states held, the others moved the least."""
        c = self.problem.compiled
        parameters, y0 = self.values(x)
        projected = c.consistent(y0=y0, parameters=parameters, fix=self.states) if self.projected else y0
        return np.array([float(projected[name]) for name in c.state_names])

    def initial_derivative(self, x) -> np.ndarray:
        """``d initial / d x`` (1, n, P) by central differences of :meth:`initial`."""
        columns = []
        for q in range(len(x)):
            step = PROJECTION_STEP * max(1.0, abs(float(x[q])))
            up, down = x.copy(), x.copy()
            up[q] += step
            down[q] -= step
            columns.append((self.initial(up) - self.initial(down)) / (2 * step))
        return np.stack(columns, axis=-1)[None]

    def solve(self, x):
        """The solution with sensitivities at ``x``, or None where the model cannot be solved there
        (the error kept in ``self.failure``: a trial point scipy then rejects)."""
        from daemodel.errors import DaemodelError, TimeLimitError
        from daemodel.sensitivities import forward

        if self.last is not None and np.array_equal(self.last[0], x):
            return self.last[1]
        p = self.problem
        c = p.compiled
        parameters, _ = self.values(x)
        try:
            y0 = self.initial(x)
            sol = solve(c, (c.t0, float(p.times[-1])), parameters=parameters, y0=y0, t_eval=p.times, **self.options)
            initial = self.initial_derivative(x) if self.projected else None
            started = time.perf_counter()
            where, values = forward(sol, p.names, initial=initial)
            sol = dataclasses.replace(
                sol,
                sensitivities={name: values[..., q] for q, name in enumerate(where.names)},
                solve_time=sol.solve_time + time.perf_counter() - started,
            )
            self.failure = None
        except TimeLimitError:  # (the caller's time is up: not a point that cannot be solved)
            raise
        except DaemodelError as error:  # (SolverError, InitialisationError, ...: this point cannot be solved)
            sol, self.failure = None, error
        self.solves += 1
        self.last = (x.copy(), sol)
        if self.bar is not None:
            self.bar.update(1)
            estimates = ", ".join(f"{n}={v:.5g}" for n, v in zip(p.names, x, strict=True))
            self.bar.set_postfix_str(
                estimates + ("" if sol is not None else " (not solvable: rejected)"), refresh=False
            )
        return sol

    def residuals(self, x):
        sol = self.solve(x)
        p = self.problem
        if sol is None:  # scipy's trust region shrinks and tries again
            return np.full(p.size, np.inf)
        parts = [((sol[o][p.rows] - d) / self.scale[o])[~np.isnan(d)] for o, d in p.data.items()]
        return np.concatenate(parts)

    def reweight(self, x) -> bool:
        """Estimate each series' noise level (where ``sigma`` gave none) from its residuals at ``x``;
        True when one changed by more than :data:`REWEIGHT_RTOL` (the fit then runs again).  Nothing
        to estimate from where the data leave no degrees of freedom."""
        p = self.problem
        sol = self.solve(x)
        N = p.size
        if N <= len(p.names) or sol is None:
            return False
        changed = False
        for o, d in p.data.items():
            if o not in p.estimated:
                continue
            r = (sol[o][p.rows] - d)[~np.isnan(d)]
            # the residuals' mean square, with the parameters' share of the degrees of freedom taken out
            level = float(np.sqrt(r @ r / max(len(r) * (N - len(p.names)) / N, 1.0)))
            level = max(level, NOISE_FLOOR * float(np.sqrt(np.nanmean(d**2))), np.finfo(float).tiny)
            changed |= abs(level / self.scale[o] - 1) > REWEIGHT_RTOL
            self.scale[o] = level
        return changed

    def jacobian(self, x):
        sol = self.solve(x)
        p = self.problem
        columns = []
        for name in p.names:
            columns.append(
                np.concatenate(
                    [(sol.sensitivity(o, name)[p.rows] / self.scale[o])[~np.isnan(d)] for o, d in p.data.items()]
                )
            )
        return np.stack(columns, axis=-1)

    def checked_start(self, x):
        """The solution at the start, or the error that prevents it, naming the fit's values."""
        sol = self.solve(x)
        if sol is None:
            error = self.failure
            values = ", ".join(f"{n} = {v:.6g}" for n, v in zip(self.problem.names, x, strict=True))
            raise type(error)(f"fit: at the start values ({values}): {error}") from error
        return sol


def _initial_states(compiled, y0) -> dict:
    """The model's initial states by name, with ``y0``'s values where given."""
    states = dict(zip(compiled.state_names, (float(v) for v in compiled.y0), strict=True))
    if y0:
        unknown = [k for k in y0 if k not in states]
        if unknown:
            raise UnknownSymbolError(f"fit: y0 names {unknown}, which are not states of '{compiled.name}'")
        states.update({k: real(v, f"y0[{k!r}]") for k, v in y0.items()})
    return states


def _fit_radau(
    problem: _Problem, y0, max_iterations: int, tol: float, options: dict, started: float, progress=None
) -> Fit:
    from scipy.optimize import least_squares

    from daemodel.backends.progress import progress_bar, show_progress

    if "t_eval" in options or "sensitivities" in options:
        raise InvalidOptionError(
            "fit: t_eval and sensitivities are set by the fit (the measured times, the fitted names)"
        )
    model = _Model(problem, y0, options)
    model.bar = progress_bar(max_iterations + 2, "fit", "solve") if show_progress(progress) else None
    try:
        return _least_squares(problem, model, max_iterations, tol, started, least_squares)
    finally:
        if model.bar is not None:
            model.bar.close()


def _least_squares(problem, model, max_iterations, tol, started, least_squares) -> Fit:
    """The radau fit proper (see :func:`fit`): scipy's least squares, reweighted, then the checks."""
    model.checked_start(problem.start)
    check_identifiable(problem.names, model.jacobian(problem.start), problem.start, "at the start")
    x, evaluations, jacobians = problem.start, 0, 0
    for _ in range(REWEIGHTINGS + 1):
        result = least_squares(
            model.residuals,
            x,
            jac=model.jacobian,
            bounds=(problem.low, problem.high),
            method="trf",
            x_scale="jac",
            ftol=tol,
            xtol=tol,
            gtol=tol,
            max_nfev=max(1, max_iterations - evaluations),
        )
        x, evaluations, jacobians = result.x, evaluations + result.nfev, jacobians + (result.njev or result.nfev)
        if not model.reweight(x) or evaluations >= max_iterations or result.status <= 0:
            break
    x = result.x
    J = model.jacobian(x)
    r = model.residuals(x)
    check_identifiable(problem.names, J, x, "at the estimate")
    std, correlation = standard_errors(J, r, known=not problem.estimated)
    sol = model.solve(x)
    status = (
        "success"
        if result.status > 0
        else (
            f"not converged: {result.message.rstrip('.')} after {evaluations} evaluations "
            f"(max_iterations={max_iterations}); "
            f"the estimate is the best found, gradient norm {np.linalg.norm(result.grad, np.inf):.3g}"
        )
    )
    at_bound = [
        n
        for n, v, lo, hi in zip(problem.names, x, problem.low, problem.high, strict=True)
        if min(abs(v - lo), abs(hi - v)) <= BOUND_RTOL * max(1.0, abs(v))
    ]
    if at_bound and status == "success":
        status = f"success, with {at_bound} at a bound (their standard errors assume the bound is not active)"
    if problem.size <= len(problem.names) and problem.estimated and status.startswith("success"):
        status += (
            f"; {problem.size} data points for {len(problem.names)} parameters leave no degrees of freedom to estimate "
            "the noise from: standard errors unknown (NaN); give sigma, or more data"
        )
    return Fit(
        parameters={n: float(v) for n, v in zip(problem.names, x, strict=True)},
        std={n: float(v) for n, v in zip(problem.names, std, strict=True)},
        correlation=correlation,
        residuals={o: np.where(np.isnan(d), np.nan, d - sol[o][problem.rows]) for o, d in problem.data.items()},
        solution=sol,
        cost=float(0.5 * r @ r),
        iterations=int(jacobians),
        status=status,
        method="radau",
        fit_time=time.perf_counter() - started,
    )


def check_identifiable(names, J, x, when: str) -> None:
    """Raise :class:`UnidentifiableError` when the columns of ``J`` (residuals x parameters) are
    dependent, naming the parameters of each dependent direction, or when a parameter's effect (its
    column times its value, the change of the outputs per relative change) is negligible beside the
    others' (a rate constant run off to 1e59 whose effect has faded away)."""
    norms = np.linalg.norm(J, axis=0)
    dead = [n for n, v in zip(names, norms, strict=True) if not v > 0]
    if dead:
        it = "it" if len(dead) == 1 else "them"
        raise UnidentifiableError(
            f"fit: the data do not depend on {dead} {when}: the outputs measured do not change with {it}; fix {it} "
            f"at known values, or measure an output that depends on {it}"
        )
    scaled = J / norms
    _, singular, vt = np.linalg.svd(scaled, full_matrices=False)
    small = singular <= IDENTIFIABILITY_RTOL * singular[0]
    if len(singular) < len(names):  # fewer residuals than parameters
        raise UnidentifiableError(
            f"fit: {len(J)} data points cannot determine the {len(names)} parameters {list(names)}; measure more"
        )
    effect = norms * np.where(np.asarray(x) != 0, np.abs(x), 1.0)
    faint = [n for n, e in zip(names, effect, strict=True) if e <= IDENTIFIABILITY_RTOL * effect.max()]
    if faint:
        it = "it" if len(faint) == 1 else "them"
        shares = ", ".join(f"{n}: {e / effect.max():.1e}" for n, e in zip(names, effect, strict=True) if n in faint)
        raise UnidentifiableError(
            f"fit: the data barely depend on {faint} {when} (a relative change moves the outputs {shares} as much as "
            f"the largest effect does); fix {it} at known values, bound {it}, or measure an output that depends on {it}"
        )
    if small.any():
        first = np.flatnonzero(small)[0]
        v = vt[first]
        culprits = [n for n, share in zip(names, np.abs(v), strict=True) if share >= CULPRIT_SHARE]
        change = " and ".join(
            f"{n} by {share:+.3g}" for n, share in zip(names, v, strict=True) if abs(share) >= CULPRIT_SHARE
        )
        raise UnidentifiableError(
            f"fit: the data do not determine {culprits} {when}: a change of {change} (each relative to its own "
            f"effect) leaves the outputs unchanged to {singular[first] / singular[0]:.1e}; fix all but one of them "
            "at known values, or measure an output that tells them apart"
        )


def standard_errors(J, r, known: bool = False):
    """``(std (P,), correlation (P, P))`` from the Jacobian and residuals at the estimate: the
    residuals' mean square scales the covariance (as scipy's curve_fit with absolute_sigma=False),
    unless ``known`` (every series' sigma given) and then only where the data leave degrees of
    freedom; with none left and the noise unknown, the standard errors are NaN."""
    N, P = J.shape
    if N <= P and not known:
        return np.full(P, np.nan), np.full((P, P), np.nan)
    s2 = float(r @ r) / (N - P) if N > P else 1.0
    cov = s2 * np.linalg.inv(J.T @ J)
    std = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    with np.errstate(invalid="ignore", divide="ignore"):
        correlation = cov / np.outer(std, std)
    return std, correlation


def _fit_pinn(problem: _Problem, y0, max_iterations: int, options: dict, started: float) -> Fit:
    """``method="pinn"``: the Radau-PINN's inverse mode (:func:`daemodel.backends.pinn.inverse.fit_inverse`).

    Its standard errors are those of the same least-squares problem at the PINN's estimate, from
    radau's exact sensitivities on the PINN's grid (fixed h, its stages: the discrete model its
    certificate measures the networks against); they cost one solve."""
    import warnings

    from daemodel.backends.pinn.config import PINNConfig
    from daemodel.backends.pinn.inverse import fit_inverse
    from daemodel.compiling.initial_states import initial_states
    from daemodel.errors import UncertifiedWarning

    c = problem.compiled
    known = {"config", "h", "stages", "progress"}
    unknown = sorted(set(options) - known)
    if unknown:
        raise InvalidOptionError(f"fit(method='pinn') has no option {unknown}; its options are {sorted(known)}")
    states = [n for n in problem.names if n in c.state_names]
    if states:
        raise InvalidOptionError(
            f"fit(method='pinn') estimates parameters only: the networks start from known initial states; "
            f"{states} {'is a state' if len(states) == 1 else 'are states'}: use method='radau' to fit initial values"
        )
    config = options.get("config") or PINNConfig()
    if not isinstance(config, PINNConfig):
        raise InvalidOptionError(f"config must be a dm.PINNConfig; got {type(config).__name__}")
    given = {k: options[k] for k in ("h", "stages") if options.get(k) is not None}
    config = dataclasses.replace(config, **given) if given else config
    aliases = [o for o in problem.data if o in c.alias_names]
    if aliases:
        of = {name: str(expr) for name, expr, _ in c.aliases}
        raise InvalidOptionError(
            "fit(method='pinn') measures states and algebraic variables; "
            + ", ".join(f"{a!r} is an alias of {of[a]}" for a in aliases)
            + ": give the data under the variable's own name"
        )
    # refuse what the data cannot determine before training (radau on the PINN's grid, one solve)
    model = _Model(problem, y0, {"h": config.h, "stages": config.stages})
    model.checked_start(problem.start)
    check_identifiable(problem.names, model.jacobian(problem.start), problem.start, "at the start")
    state = initial_states(c, y0=y0)
    measured = problem.times[problem.rows]
    inverse = fit_inverse(
        c,
        (c.t0, float(problem.times[-1])),
        measured,
        problem.data,
        problem.names,
        problem.start,
        (problem.low, problem.high),
        state,
        config,
        max_iterations=max_iterations,
        progress=options.get("progress"),
        # (every series' sigma, when all are given; else each series' spread, the inverse mode's default)
        scales=None if problem.estimated else [problem.scale[o] for o in problem.data],
    )
    x = inverse.parameters
    sol = inverse.solution
    model.reweight(x)
    J, r = model.jacobian(x), model.residuals(x)
    std, correlation = standard_errors(J, r, known=not problem.estimated)
    values = sol.at(measured)
    status = sol.status if inverse.converged else f"not converged after {inverse.iterations} iterations; {sol.status}"
    if status != "success":
        warnings.warn(f"fit(method='pinn'): {status}", UncertifiedWarning, stacklevel=3)
    return Fit(
        parameters={n: float(v) for n, v in zip(problem.names, x, strict=True)},
        std={n: float(v) for n, v in zip(problem.names, std, strict=True)},
        correlation=correlation,
        residuals={o: np.where(np.isnan(d), np.nan, d - values[o]) for o, d in problem.data.items()},
        solution=sol,
        cost=float(inverse.loss["misfit"]),
        iterations=int(inverse.iterations),
        status=status,
        method="pinn",
        fit_time=time.perf_counter() - started,
        certificate=inverse.certificate,
    )

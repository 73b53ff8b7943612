"""casadi's integrators: Radau collocation, and IDAS on the index-1 reduction.

Both build one casadi integrator per model, output times and settings, kept with the compiled
model (:func:`cached_integrator`: a sweep or a repeated solve pays the setup once), and call it
once per sample (casadi integrates one initial state per call).  ``casadi-collocation`` applies
Radau IIA collocation with ``stages`` points and one finite element per step ``h`` to the system
as compiled (index 2 is fine: its root finder solves the same stage equations as
``method="radau"``);
``casadi-idas`` needs index 1, so :func:`daemodel.solve` hands it the index-1 reduction and
the original constraints' drift is reported through :meth:`Solution.drift`.

Trust:

1. Nothing casadi prints reaches the user: its evaluation warnings are switched off, and what
   it still prints during a call (IDAS's error text, the root finder's input dump) is captured
   and read for the time of the failure.
2. A failure is one exception line naming the method, the sample, the time and the reason, with
   the fix: :class:`~daemodel.errors.StepLimitError` when IDAS exhausts ``max_num_steps``,
   :class:`~daemodel.errors.ConvergenceError` otherwise.
3. IDAS starts from consistent derivatives.  ``y'(t0) = f(t0, y0, z0)``: ``calc_ic`` lets IDAS
   compute it for each sample inside the call, so one integrator serves a whole batch
   (``init_xdot`` fixes it per integrator: a rebuild per sample, 5x slower on a batch of 50
   pendulums); a sample whose IDACalcIC fails gets its own integrator with ``init_xdot = f``.
   Without either, IDAS assumes ``y' = 0`` and fails its error test at t0 on most models.
   ``z'(t0)`` cannot be given to IDAS at all: it predicts z with ``z' = 0``, so its first step
   must be short enough for that prediction to pass the error test, ``h |z'(t0)| <
   rtol |z0| + atol``; ``step0`` is set so (see :data:`FIRST_STEP_SAFETY`) from
   ``z'(t0) = -g_z^{-1} (g_t + g_y f)``.  IDAS then doubles the step as usual (a few steps more).
   Leaving z out of the error test instead (``suppress_algebraic``) is no fix: IDAS's Newton
   then stops correcting z where y does not depend on it, and z drifts off its constraint.
4. ``casadi-collocation`` is fixed-step, so nothing inside it notices a step over a singularity
   that lands on a finite root of the stage equations.  Every step is therefore checked after
   the solve: it is repeated from the same start with one more collocation point (Radau IIA of
   order 2s+1, one mapped casadi call for all steps and samples), and the difference estimates
   the step's local error.  An estimate above :data:`LOCAL_ERROR_BOUND` times the variable's
   scale raises :class:`~daemodel.errors.LocalErrorBoundError`.
"""

from __future__ import annotations

import collections
import dataclasses
import re
import threading
import time
from dataclasses import dataclass

import numpy as np
from daemodel.backends.base import (
    DEFAULT_ESTIMATE_BOUND,
    LOCAL_ERROR_BOUND,
    AbstractBackend,
    estimate_status,
    make_solution,
)
from daemodel.backends.checks import check_output_memory, check_stages, set_number, set_tolerances
from daemodel.backends.grids import (
    DEFAULT_OUTPUT_POINTS,
    SWEEP_FIRST_STEPS,
    fixed_grid,
    fixed_step_sweep,
    output_times,
    tolerance_sweep,
)
from daemodel.backends.progress import captured_output

from daemodel.dense import AbstractDenseOutput, CollocationPolynomials, outputs_before, step_owners
from daemodel.errors import ConvergenceError, InvalidOptionError, LocalErrorBoundError, SolverError, StepLimitError

# Steps of casadi-collocation over the interval when h is not given.
DEFAULT_STEPS = 100
# Options that stop casadi from printing a warning for every non-finite evaluation (tens of
# thousands of lines when Newton wanders into a singularity).
QUIET = {"show_eval_warnings": False}
# casadi-collocation's root finder: absolute residual tolerance per unit of the solution's size
# 1 + max|u0| (casadi's default 1e-12 assumes unit size; the squeezing mechanism's w ~ 1e4-4e5
# leaves residuals at 1e-11 from rounding alone).
ROOT_ABSTOL = 1e-12
# A casadi-collocation step that returns its start value is steady, not stuck, when its change h |f|
# is below the root finder's abstol or this many units in the last place of the value: rounding in
# f (a constraint met to the last bit, x' = 1e-14 at rest) moves nothing that the values can show.
STEADY_ULPS = 16
# Integrators kept per model (least recently used dropped first): a sweep's tolerances or steps, a
# few start values; each holds its output times (a 20,000-step grid is 160 kB) and casadi's memory.
KEPT_INTEGRATORS = 32
# IDAS's first step: this fraction of the longest step whose z' = 0 prediction passes the error
# test, h |z'(t0)| = rtol |z0| + atol (order 1: the estimate is about the prediction's error).
FIRST_STEP_SAFETY = 0.1
# casadi-collocation's dense output: a step's stages solved again must end at the step's own end value
# to this much, relative to 1 + its size (the root finder's tolerance is 1e-12 of it).
DENSE_END_MATCH = 1e-8
# Lines of casadi's captured output quoted in an error that cannot be translated.
QUOTED_LINES = 3

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
# What an adaptive alternative to a fixed step is called in messages.
ADAPTIVE_FIX = 'take a smaller h, or an adaptive method (method="radau" with rtol=..., or method="casadi-idas")'


@dataclass(frozen=True, kw_only=True)
class CollocationOptions:
    """Options of ``method="casadi-collocation"``.

    Attributes
    ----------
    stages : int
        Collocation points per step (casadi's ``interpolation_order``), Radau scheme.
    h : float, optional
        Step size; default: the interval in 100 steps.  Values are reported on the step grid.
    t_eval : array, optional
        Output times instead of the step grid, within the interval.  casadi does not expose its
        collocation polynomials, so the values there are :meth:`Solution.at`'s: cubic Hermite
        states through the step grid with the model's f (O(h^4) on top of the method's error)
        and algebraic values solved from the constraints.
    estimate_bound : float
        A run whose largest local error estimate (a step repeated with one more collocation
        point, in units of the solution's size ``1 + max |u|``) exceeds this is flagged (status
        ``"flagged: ..."`` naming the step, and a :class:`~daemodel.errors.LocalErrorWarning`);
        every step's estimate is in ``stats["local_error_estimates"]``.  Default
        :data:`~daemodel.backends.base.DEFAULT_ESTIMATE_BOUND`.
    """

    stages: int = 3
    h: float | None = None
    t_eval: object = None
    estimate_bound: float = DEFAULT_ESTIMATE_BOUND

    def __post_init__(self) -> None:
        check_stages(self.stages)
        set_number(self, "h", allow_none=True)
        set_number(self, "estimate_bound")


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


def cached_integrator(compiled, plugin: str, dae: dict, t0, times, settings: dict):
    """casadi's ``plugin`` integrator of ``dae`` from ``t0`` to ``times``, built once per model, times,
    settings and thread, and kept with the model (its setup, 2-30 ms, otherwise paid on every solve of a
    sweep); the :data:`KEPT_INTEGRATORS` most recently used are kept.

    Per thread: a solve reads the integrator's statistics after its calls, which another thread's call
    of a shared integrator would overwrite in between."""
    import json

    import casadi

    times = [float(t) for t in times]
    key = (plugin, float(t0), tuple(times), json.dumps(settings, sort_keys=True), threading.get_ident())
    with _KEPT_LOCK:
        kept = compiled.cached("casadi-integrators", collections.OrderedDict)  # the most recently used last
        if key in kept:
            kept.move_to_end(key)
            return kept[key]
    built = casadi.integrator(plugin, plugin, dae, float(t0), times, settings)
    with _KEPT_LOCK:
        kept[key] = built
        while len(kept) > KEPT_INTEGRATORS:
            kept.popitem(last=False)
    return built


_KEPT_LOCK = threading.Lock()  # (the kept integrators of every model: a cache shared by threads)


def _dae(compiled) -> dict:
    dae = compiled.casadi_dae()
    return {key: dae[key] for key in ("x", "z", "p", "t", "ode", "alg") if key in dae}


def _number(pattern: str, text: str) -> float | None:
    """The last number ``pattern`` captures in ``text`` (casadi's latest message comes last)."""
    found = re.findall(pattern, text)
    return float(found[-1]) if found else None


def _last_lines(text: str) -> str:
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    return " | ".join(lines[-QUOTED_LINES:])


def _run(call, compiled, start, T: int, explain) -> np.ndarray:
    """``call(sample)`` for each sample, quietly: values (B, T + 1, n + m) with t0 first.

    ``call`` returns casadi's result (``xf`` (n, T), ``zf`` (m, T)) or raises casadi's
    RuntimeError; ``explain(sample, error, printed)`` turns that failure (its text and what
    casadi printed meanwhile) into the exception to raise.
    """
    B = start.size
    n, m = len(compiled.states), len(compiled.algebraics)
    out = np.empty((B, T + 1, n + m))
    out[:, 0, :n], out[:, 0, n:] = start.y0, start.z0
    for b in range(B):
        with captured_output() as printed:
            try:
                result = call(b)
            except RuntimeError as error:
                failure = explain(b, str(error), printed.getvalue())
            else:
                failure = None
        if failure is not None:
            raise failure from None
        out[b, 1:, :n] = np.asarray(result["xf"]).T.reshape(T, n)
        out[b, 1:, n:] = np.asarray(result["zf"]).T.reshape(T, m)
    return out


def _stats(integrator) -> dict:
    """casadi's scalar statistics of the integrator's last call."""
    try:
        return {k: v for k, v in integrator.stats().items() if isinstance(v, (int, float, bool, str))}
    except (RuntimeError, AttributeError):
        return {}


def first_non_finite(name: str, compiled, times, values, fix: str, what: str = "") -> ConvergenceError | None:
    """The error for the earliest non-finite value of any sample, or None when all are finite.

    ``values`` (B, T, n + m) are the solution's, or (``what="f at"``) the right-hand sides ``f``
    and constraints ``g`` evaluated there.
    """
    bad = ~np.isfinite(values)
    if not bad.any():
        return None
    sample, k, j = min(zip(*np.nonzero(bad), strict=True), key=lambda hit: (hit[1], hit[0]))
    names = (*compiled.state_names, *compiled.algebraic_names)
    if what:
        rows = (*(f"{y}'" for y in compiled.state_names), *compiled.constraint_names)
        subject = f"the right-hand side of {rows[j]} is not finite at the returned values"
    else:
        subject = f"'{names[j]}' is not finite"
    return ConvergenceError(
        f"{name}: {subject} at t = {times[k]:.6g} (sample {sample} of '{compiled.name}', "
        f"after t = {times[max(k - 1, 0)]:.6g}): the solution may be singular there or leave the domain of the "
        f"equations; {fix}"
    )


def stuck_step(compiled, grid, values, slopes, root_abstol: float = ROOT_ABSTOL) -> ConvergenceError | None:
    """The error for the first step that returned its start value exactly although f is not zero
    there: casadi's root finder gave up (f or g turned NaN inside its Newton iteration, with casadi's
    evaluation warnings off) and casadi returned its last iterate instead of failing.

    A step whose whole change ``h |f|`` is within rounding of its start is not stuck but steady
    (a start at rest up to rounding, ``x' = 1e-14``, or a constraint met to the last bit): the
    collocation residual at the start guess is ``h f`` at the stages, so the root finder accepts that
    guess once ``h |f| < root_abstol``; and a change below :data:`STEADY_ULPS` units in the last place
    of ``u`` is not a change that the values can show.
    """
    n = len(compiled.states)
    same = np.all(values[:, 1:] == values[:, :-1], axis=2)  # (B, T-1): step k returned u_k
    h = np.diff(grid)[None, :, None]
    rounding = np.maximum(root_abstol, STEADY_ULPS * np.finfo(values.dtype).eps * np.abs(values[:, :-1, :n]))
    moving = np.any(h * np.abs(slopes[:, :-1, :n]) > rounding, axis=2)  # f(t_k, u_k) moves u_k visibly
    stuck = np.argwhere(same & moving)
    if not len(stuck):
        return None
    sample, k = (int(i) for i in stuck[0])
    return ConvergenceError(
        f"casadi-collocation: step {k + 1} from t = {grid[k]:.6g} (h = {grid[k + 1] - grid[k]:.3g}) of sample {sample} "
        f"of '{compiled.name}' returned its start value although f is not zero there: casadi's Newton iteration "
        "gave up (f or g likely turned NaN inside it, e.g. sqrt or log of a negative value) and casadi returned its "
        'last iterate; take a smaller h, or an adaptive method (method="radau" with rtol=..., or method="casadi-idas")'
    )


def _right_hand_sides(dae, grid, values, parameters) -> np.ndarray:
    """``[f, g]`` at every returned point, shape (B, T, n + m): one mapped casadi call per sample."""
    import casadi

    fg = casadi.Function("fg", [dae["t"], dae["x"], dae["z"], dae["p"]], [casadi.vertcat(dae["ode"], dae["alg"])])
    n = dae["x"].shape[0]
    out = np.empty_like(values)
    mapped = fg.map(len(grid))
    for b in range(values.shape[0]):
        with np.errstate(all="ignore"), captured_output():
            result = mapped(
                grid, values[b, :, :n].T, values[b, :, n:].T, np.repeat(parameters[b][:, None], len(grid), 1)
            )
        out[b] = np.asarray(result).T
    return out


def normalised_dae(dae: dict) -> dict:
    """``dae`` on normalised time ``t = tau + h s``, ``s`` in [0, 1], with ``tau`` and ``h`` appended to
    its parameters: one integrator from s = 0 to 1 serves any step or interval."""
    import casadi

    tau, h, s = casadi.SX.sym("tau"), casadi.SX.sym("h"), casadi.SX.sym("s")
    now = tau + h * s
    return {
        "x": dae["x"],
        "z": dae["z"],
        "p": casadi.vertcat(dae["p"], tau, h),
        "t": s,
        "ode": h * casadi.substitute(dae["ode"], dae["t"], now),
        "alg": casadi.substitute(dae["alg"], dae["t"], now),
    }


class LocalErrorCheck:
    """The a-posteriori local error estimate of every casadi-collocation step.

    Each step from ``u_k`` to ``u_{k+1}`` is repeated from ``u_k`` with ``stages + 1`` Radau
    points (order 2s + 1 against the step's 2s - 1), so ``|u_{k+1} - û_{k+1}|`` estimates the
    step's own local error (asymptotically exactly, for a smooth solution).
    As in RADAU5, an algebraic variable determined through an index-k constraint has its
    estimate multiplied by ``h^(k-1)`` (its values are only accurate to a lower order).  The
    estimate is divided by the variable's scale ``1 + max|u|`` over the sample's trajectory.

    The repeat solves the step on normalised time ``t = tau + h s``, ``s`` in [0, 1], so one
    casadi Function, mapped over all steps of all samples, serves any grid.  Its root finder
    does not raise: a step whose repeat has no solution gets a large or non-finite estimate.
    """

    def __init__(self, compiled, stages: int, dae: dict | None = None, root_abstol: float = ROOT_ABSTOL):
        """``dae``: the system's casadi DAE dict when the caller has built it already; ``root_abstol``:
        the root finder's residual tolerance (see :data:`ROOT_ABSTOL`)."""
        import casadi

        dae = dae if dae is not None else _dae(compiled)
        self.step = casadi.integrator(
            "collocation_check",
            "collocation",
            normalised_dae(dae),
            0.0,
            1.0,
            {
                "collocation_scheme": "radau",
                "interpolation_order": stages + 1,
                "number_of_finite_elements": 1,
                "rootfinder_options": {"error_on_fail": False, "abstol": root_abstol, **QUIET},
                **QUIET,
            },
        )
        self.compiled = compiled
        self.stages = stages
        self.z_index = np.array(compiled.algebraic_index, dtype=float)

    def __call__(self, grid, values, parameters) -> np.ndarray:
        """Estimates, shape (B, N, n + m), in units of each variable's scale ``1 + max |u|``, for
        ``values`` (B, N + 1, n + m)."""
        B, N = values.shape[0], len(grid) - 1
        n = len(self.compiled.states)
        h = np.diff(grid)
        starts = values[:, :-1].reshape(B * N, -1).T  # (n + m, B N): every step of every sample
        p = np.concatenate(
            [np.repeat(parameters, N, axis=0).T, np.tile(grid[:-1], B)[None, :], np.tile(h, B)[None, :]], axis=0
        )
        with captured_output():
            repeat = self.step.map(B * N)(x0=starts[:n], z0=starts[n:], p=p)
        again = np.concatenate([np.asarray(repeat["xf"]), np.asarray(repeat["zf"])], axis=0).T.reshape(B, N, -1)
        scale = 1.0 + np.max(np.abs(values), axis=1, keepdims=True)
        return np.nan_to_num(np.abs(values[:, 1:] - again) / scale, nan=np.inf)

    def weighted(self, grid, estimates) -> np.ndarray:
        """``estimates`` with an index-k algebraic variable's multiplied by ``h^(k-1)`` (RADAU5's
        units, which :data:`LOCAL_ERROR_BOUND` bounds)."""
        n = len(self.compiled.states)
        out = estimates.copy()
        out[..., n:] *= np.diff(grid)[None, :, None] ** (self.z_index - 1)
        return out

    def status(self, name: str, grid, estimates, bound: float, batched: bool) -> str:
        """ "success", or flagged at the step with the largest estimate beyond ``bound``
        (:func:`~daemodel.backends.base.estimate_status`)."""
        if not estimates.size:
            return "success"
        sample, step, j = np.unravel_index(int(np.argmax(estimates)), estimates.shape)
        variable = (*self.compiled.state_names, *self.compiled.algebraic_names)[j]
        t, h = grid[step], grid[step + 1] - grid[step]
        where = f"step {step + 1} from t = {t:.6g} (h = {h:.3g}), in '{variable}'"
        where += f", sample {sample}" if batched else ""
        return estimate_status(name, float(estimates[sample, step, j]), bound, where)

    def raise_beyond_bound(self, name: str, grid, estimates) -> None:
        """:class:`LocalErrorBoundError` for the earliest step whose estimate exceeds the bound."""
        beyond = estimates > LOCAL_ERROR_BOUND
        if not beyond.any():
            return
        step = int(np.argmax(beyond.any(axis=(0, 2))))
        sample = int(np.argmax(beyond[:, step].any(axis=1)))
        j = int(np.argmax(estimates[sample, step]))
        n = len(self.compiled.states)
        variable = (*self.compiled.state_names, *self.compiled.algebraic_names)[j]
        power = int(self.z_index[j - n]) - 1 if j >= n else 0
        scale = f"1 + max|{variable}|" + (f" over h^{power}" if power else "")
        t, h = grid[step], grid[step + 1] - grid[step]
        raise LocalErrorBoundError(
            f"{name}: step {step + 1} from t = {t:.6g} to {t + h:.6g} (h = {h:.3g}) of sample {sample} of "
            f"'{self.compiled.name}' is not trustworthy: the local error estimate of '{variable}' is "
            f"{estimates[sample, step, j]:.3g} times its scale {scale}, beyond LOCAL_ERROR_BOUND = "
            f"{LOCAL_ERROR_BOUND:g} (a step with {self.stages + 1} collocation points from the same start disagrees): "
            f"the solution may be singular there; {ADAPTIVE_FIX}"
        )


class CollocationStages:
    """The stage values of casadi-collocation's steps, for its dense output.

    casadi keeps its collocation polynomials to itself; they are determined by each step's start and
    length, so they are found again here: the Radau IIA stage equations of the step (the equations
    casadi's root finder solved, ``X_i = u_k + h sum_j a_ij f(t_k + c_j h, X_j, Z_j)``, ``0 = g(t_k + c_i
    h, X_i, Z_i)``), solved by casadi's Newton from the straight line between the step's two ends, in
    one mapped call for all the steps asked for.  Their root is the one casadi found where the end
    value agrees: :meth:`__call__` checks it.
    """

    def __init__(self, compiled, stages: int, dae: dict, root_abstol: float):
        import casadi

        from daemodel.tableau import radau_iia

        tableau = radau_iia(stages)
        A, self.c = np.asarray(tableau.A, dtype=float), np.asarray(tableau.c, dtype=float)
        n, m = dae["x"].shape[0], dae["z"].shape[0]
        f = casadi.Function("f", [dae["t"], dae["x"], dae["z"], dae["p"]], [dae["ode"]])
        g = casadi.Function("g", [dae["t"], dae["x"], dae["z"], dae["p"]], [dae["alg"]])
        X, Z = casadi.SX.sym("X", n, stages), casadi.SX.sym("Z", m, stages)
        x0, p = casadi.SX.sym("x0", n), casadi.SX.sym("p", dae["p"].shape[0])
        tau, h = casadi.SX.sym("tau"), casadi.SX.sym("h")
        slopes = [f(tau + self.c[j] * h, X[:, j], Z[:, j], p) for j in range(stages)]
        equations = []
        for i in range(stages):
            equations.append(X[:, i] - x0 - h * sum(A[i, j] * slopes[j] for j in range(stages)))
            equations.append(g(tau + self.c[i] * h, X[:, i], Z[:, i], p))
        unknowns = casadi.vertcat(*[casadi.vertcat(X[:, i], Z[:, i]) for i in range(stages)])
        residual = casadi.Function("stages", [unknowns, casadi.vertcat(x0, p, tau, h)], [casadi.vertcat(*equations)])
        options = {"abstol": root_abstol, "error_on_fail": False, **QUIET}
        self.solve = casadi.rootfinder("collocation_stages", "newton", residual, options)
        self.n, self.stages = n, stages

    def __call__(self, starts, ends, parameters, tau, h) -> np.ndarray:
        """Stage values ``(K, s, n+m)`` of ``K`` steps from ``starts`` (K, n+m) to ``ends`` (K, n+m),
        with ``parameters`` (K, k), start times ``tau`` (K,) and lengths ``h`` (K,).

        Raises
        ------
        ConvergenceError
            Where Newton finds no root, or one whose last stage is not the step's end value (casadi's).
        """
        K, D = starts.shape
        guess = starts[:, None] + self.c[None, :, None] * (ends - starts)[:, None]  # (K, s, n+m)
        inputs = np.concatenate([starts[:, : self.n], parameters, tau[:, None], h[:, None]], axis=1)
        with captured_output():
            found = self.solve.map(K)(guess.reshape(K, -1).T, inputs.T)
        stages = np.asarray(found).T.reshape(K, self.stages, D)
        scale = 1.0 + np.abs(ends).max(axis=1)
        mismatch = np.abs(stages[:, -1] - ends).max(axis=1) / scale
        bad = ~(mismatch <= DENSE_END_MATCH)
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            raise ConvergenceError(
                f"casadi-collocation's dense output: the stage equations of the step from t = {tau[k]:.6g} (h = "
                f"{h[k]:.3g}) solved again from its ends give an end value {mismatch[k]:.3g} (relative) away from the "
                "step's own: no polynomial between those outputs; ask for the times with t_eval instead"
            )
        return stages


@dataclass(frozen=True, eq=False)
class CollocationSteps(AbstractDenseOutput):
    """casadi-collocation's dense output: each step's collocation polynomial, its stages found again by
    :class:`CollocationStages` for the steps a query needs (and kept for the next query)."""

    grid: np.ndarray
    values: np.ndarray  # (B, N + 1, n+m)
    parameters: np.ndarray  # (B, k)
    stages: CollocationStages
    _found: dict = dataclasses.field(default_factory=dict)  # step -> (B, s, n+m)

    @property
    def description(self) -> str:
        return f"each step's collocation polynomial (degree {self.stages.stages}), its stages solved again"

    def __call__(self, times: np.ndarray) -> np.ndarray:
        times = np.asarray(times, dtype=float)
        B = len(self.values)
        lengths = np.diff(self.grid)
        step, _ = step_owners(self.grid[:-1], lengths, times)
        needed = [k for k in np.unique(step).tolist() if k not in self._found]
        if needed:
            rows = np.array(needed)
            starts = self.values[:, rows].reshape(-1, self.values.shape[2])  # (B * len, n+m), sample-major
            ends = self.values[:, rows + 1].reshape(-1, self.values.shape[2])
            found = self.stages(
                starts,
                ends,
                np.repeat(self.parameters, len(rows), axis=0),
                np.tile(self.grid[rows], B),
                np.tile(lengths[rows], B),
            ).reshape(B, len(rows), self.stages.stages, -1)
            for j, k in enumerate(needed):
                self._found[k] = found[:, j]
        used = np.unique(step)
        nodes = np.stack([np.concatenate([self.values[:, k, None], self._found[k]], axis=1) for k in used], axis=1)
        within = CollocationPolynomials(self.stages.c, self.grid[used], lengths[used], nodes)
        out = within(times)
        on_grid = np.isin(times, self.grid)  # (a grid time: the step's own value, not its re-solved last stage)
        out[:, on_grid] = self.values[:, np.searchsorted(self.grid, times[on_grid])]
        return out


class CollocationBackend(AbstractBackend):
    """``method="casadi-collocation"``: casadi's collocation integrator, Radau scheme, checked step by step.

    ``stats["max_local_error_estimate"]`` is the largest estimate of :class:`LocalErrorCheck`
    over all steps, samples and variables, in units of the variable's scale (the quantity that
    :data:`LOCAL_ERROR_BOUND` bounds).
    """

    name = "casadi-collocation"
    Options = CollocationOptions
    max_index = 2

    def work_precision(self, t_span, points, steps=SWEEP_FIRST_STEPS):
        return fixed_step_sweep(t_span, points, steps)

    def solve(self, compiled, t_span, start, options: CollocationOptions):
        h = options.h if options.h is not None else (t_span[1] - t_span[0]) / DEFAULT_STEPS
        grid = fixed_grid(t_span, h)
        points = len(grid) + len(output_times(options.t_eval, t_span, ()))  # t_eval validated first
        check_output_memory(self.name, compiled, start.size, points)
        began = time.perf_counter()
        dae = _dae(compiled)
        # casadi's Newton stops on |residual| < abstol (default 1e-12, for unit-size values): scale it
        # with the solution, or mechanisms with accelerations of 1e4-1e6 never reach it (rounding)
        root_abstol = ROOT_ABSTOL * (1.0 + float(np.abs(np.concatenate([start.y0, start.z0], axis=1)).max(initial=0)))
        plugin_options = {
            "collocation_scheme": "radau",
            "interpolation_order": options.stages,
            "number_of_finite_elements": 1,
            "rootfinder_options": {"abstol": root_abstol, **QUIET},
            **QUIET,
        }
        # built once per model, grid and settings, as radau builds its functions once: sweeps and
        # repeated solves pay the setup once
        integrator = cached_integrator(compiled, "collocation", dae, grid[0], grid[1:], plugin_options)
        check = compiled.cached(
            ("casadi-collocation-check", options.stages, root_abstol),
            lambda: LocalErrorCheck(compiled, options.stages, dae, root_abstol),
        )
        setup = time.perf_counter() - began  # building the integrators: reported apart from the solve
        began = time.perf_counter()

        def call(b):
            return integrator(x0=start.y0[b], z0=start.z0[b], p=start.p[b])

        def explain(sample, error, printed):
            return collocation_failure(error, printed, sample=sample, model=compiled.name, grid=grid)

        values = _run(call, compiled, start, len(grid) - 1, explain)
        stats = {"batch": start.size, "casadi_calls": start.size, **_stats(integrator)}
        failure = first_non_finite(self.name, compiled, grid, values, ADAPTIVE_FIX)
        if failure is None:  # casadi's root finder returns its last iterate when f turns NaN inside a step
            slopes = _right_hand_sides(dae, grid, values, start.p)
            failure = first_non_finite(self.name, compiled, grid, slopes, ADAPTIVE_FIX, "f at") or stuck_step(
                compiled, grid, values, slopes, root_abstol
            )
        if failure is not None:
            raise failure
        estimates = check(grid, values, start.p)
        weighted = check.weighted(grid, estimates)
        check.raise_beyond_bound(self.name, grid, weighted)
        stats = {
            "stages": options.stages,
            "steps": len(grid) - 1,
            "max_local_error_estimate": float(weighted.max(initial=0.0)),
            "local_error_estimates": estimates.max(axis=(0, 2), initial=0.0).tolist(),
            **stats,
        }
        status = check.status(self.name, grid, estimates, options.estimate_bound, start.batched)
        settings = {k: v for k, v in dataclasses.asdict(options).items() if k != "t_eval"}
        stage_solver = compiled.cached(
            ("casadi-collocation-stages", options.stages, root_abstol),
            lambda: CollocationStages(compiled, options.stages, dae, root_abstol),
        )
        dense = CollocationSteps(grid, values, np.asarray(start.p, dtype=float), stage_solver)
        times = grid
        if options.t_eval is not None:
            times = output_times(options.t_eval, t_span, grid)
            values = dense(times)
        wall = time.perf_counter() - began
        return make_solution(
            self,
            compiled,
            start,
            options,
            times,
            values,
            wall,
            stats,
            settings,
            status=status,
            setup_time=setup,
            dense=dense,
        )


def collocation_failure(error: str, printed: str, *, sample: int, model: str, grid) -> ConvergenceError:
    """casadi-collocation's failure as one line, from casadi's exception text and what it printed.

    A root-finder failure comes with an input dump that names the step ("Input 0 (t): 0.99",
    "Input 1 (h): 0.03"); anything else quotes casadi's last lines.
    """
    name = CollocationBackend.name
    t, h = _number(r"Input 0 \(t\): (\S+)", printed), _number(r"Input 1 \(h\): (\S+)", printed)
    if t is None or h is None or "rootfinder" not in error:
        return ConvergenceError(
            f"{name}: casadi failed for sample {sample} of '{model}': {_last_lines(error)}; {ADAPTIVE_FIX}"
        )
    step = int(np.searchsorted(grid, t + 0.5 * h))
    return ConvergenceError(
        f"{name}: casadi's Newton iteration did not solve the collocation equations of step {step} from "
        f"t = {t:.6g} to {t + h:.6g} (h = {h:.3g}) for sample {sample} of '{model}'; the solution may be "
        f"singular there; {ADAPTIVE_FIX}"
    )


def idas_failure(error: str, printed: str, *, sample: int, model: str, grid, max_num_steps: int) -> SolverError:
    """casadi-idas's failure as one line: IDAS's return flag translated, with the time IDAS printed.

    ``error`` holds casadi's ``IDASolve returned "IDA_ERR_FAIL"``; ``printed`` IDAS's own
    message, e.g. ``At t = 0.5 and h = 3.8e-10, the error test failed repeatedly ...``.
    """
    name = IDASBackend.name
    flag = re.search(r'(IDA\w+) returned "(\w+)"', error)
    function, code = flag.groups() if flag else ("IDAS", None)
    t, h = _number(r"t = ([-+0-9.eE]+)", printed), _number(r"h = ([-+0-9.eE]+)", printed)
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
            "per output interval) or loosen rtol/atol, or, if the solution is singular there, shorten t_span"
        )
    if code in IDAS_REASONS:
        reason, fix = IDAS_REASONS[code]
        return ConvergenceError(f"{name}: {reason.format(at=at)} ({where}, {code}); {fix}")
    said = _last_lines(printed) or _last_lines(error)
    return ConvergenceError(f"{name}: {function} failed{at} ({where}, {code}): {said}")


def initial_slopes(dae: dict, t0: float, start) -> tuple[np.ndarray, np.ndarray]:
    """``y'(t0) = f`` (B, n) and ``z'(t0) = -g_z^{-1} (g_t + g_y f)`` (B, m) of every sample (index 1)."""
    import casadi

    t, x, z, p = dae["t"], dae["x"], dae["z"], dae["p"]
    alg = dae["alg"]
    parts = casadi.Function(
        "slopes",
        [t, x, z, p],
        [dae["ode"], casadi.jacobian(alg, z), casadi.jacobian(alg, t), casadi.jacobian(alg, x)],
    )
    B, n, m = start.size, start.y0.shape[1], start.z0.shape[1]
    ydot, zdot = np.zeros((B, n)), np.zeros((B, m))
    for b in range(B):
        f, g_z, g_t, g_y = (np.asarray(v, dtype=float) for v in parts(t0, start.y0[b], start.z0[b], start.p[b]))
        ydot[b] = f.reshape(n)
        if m:
            try:
                zdot[b] = -np.linalg.solve(g_z.reshape(m, m), g_t.reshape(m) + g_y.reshape(m, n) @ ydot[b])
            except np.linalg.LinAlgError:  # g_z singular: IDAS will say where it fails
                zdot[b] = np.nan
    return ydot, zdot


def first_step(zdot, z0, rtol: float, atol: float, t_span, first_output: float) -> float | None:
    """IDAS's ``step0``: short enough that predicting z with ``z' = 0`` passes the first error test.

    None (IDAS chooses) when IDAS's own first guess, ``0.001 (t_out - t0)``, is short enough
    already; never below the float resolution of t.
    """
    moving = np.isfinite(zdot) & (zdot != 0)
    if not moving.any():
        return None
    longest = float(np.min((rtol * np.abs(z0[moving]) + atol) / np.abs(zdot[moving])))
    step = FIRST_STEP_SAFETY * longest
    if step >= 1e-3 * (first_output - t_span[0]):
        return None
    return max(step, 16 * float(np.spacing(max(abs(t_span[0]), abs(t_span[1]), 1.0))))


@dataclass(frozen=True, eq=False)
class IDASRestarts(AbstractDenseOutput):
    """casadi-idas's dense output: IDAS started again from the output before each time asked for, with
    the solve's tolerances, to that time (casadi keeps IDAS's interpolating polynomials to itself).
    Every time is one short IDAS run from consistent values, on normalised time (:func:`normalised_dae`),
    all of them in one mapped call; an output time itself is the solve's own value."""

    times: np.ndarray  # (T,)
    values: np.ndarray  # (B, T, n+m)
    parameters: np.ndarray  # (B, k)
    integrator: object  # () -> the integrator from s = 0 to 1 on normalised time
    n: int

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
        except RuntimeError as error:
            asked = ", ".join(f"{t:.6g}" for t in times[inside][:3])
            raise ConvergenceError(
                f"casadi-idas's dense output: IDAS started again from the outputs before t = {asked} failed "
                f"({_last_lines(printed.getvalue()) or error}); ask for those times with t_eval instead"
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

    def work_precision(self, t_span, points, steps=SWEEP_FIRST_STEPS):
        return tolerance_sweep(points)

    def solve(self, compiled, t_span, start, options: IDASOptions):
        import casadi

        times = output_times(options.t_eval, t_span, np.linspace(*t_span, DEFAULT_OUTPUT_POINTS))
        grid = times[1:] if times[0] == t_span[0] else times
        check_output_memory(self.name, compiled, start.size, len(times))
        began = time.perf_counter()
        if len(grid) == 0:  # only t0 asked for: the initial state is the answer
            values = np.concatenate([start.y0, start.z0], axis=1)[:, None, :]
            return make_solution(self, compiled, start, options, times, values, time.perf_counter() - began, {})
        dae = _dae(compiled)
        ydot, zdot = initial_slopes(dae, t_span[0], start)
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
        out = [float(t) for t in grid]
        shared = cached_integrator(compiled, "idas", dae, t_span[0], out, {**settings, "calc_ic": True})
        fallbacks = []
        setup = time.perf_counter() - began  # building the integrator: reported apart from the solve
        began = time.perf_counter()

        def call(b):
            """IDAS with y'(t0) from IDACalcIC; where that fails, a one-off integrator given y'(t0) = f(t0, y0, z0)."""
            try:
                return shared(x0=start.y0[b], z0=start.z0[b], p=start.p[b])
            except RuntimeError as error:
                if "IDACalcIC" not in str(error):
                    raise
            fallbacks.append(b)
            exact = {**settings, "calc_ic": False, "init_xdot": ydot[b].tolist()}
            return casadi.integrator("idas", "idas", dae, float(t_span[0]), out, exact)(
                x0=start.y0[b], z0=start.z0[b], p=start.p[b]
            )

        def explain(sample, error, printed):
            return idas_failure(
                error, printed, sample=sample, model=compiled.name, grid=grid, max_num_steps=options.max_num_steps
            )

        values = _run(call, compiled, start, len(grid), explain)
        stats = {
            "batch": start.size,
            "casadi_calls": start.size,
            "first_step": step0,
            "initial_slope_fallbacks": len(fallbacks),
        }
        stats.update(_stats(shared))
        times_out = np.concatenate([[t_span[0]], grid])
        failure = first_non_finite(self.name, compiled, times_out, values, "tighten rtol/atol or shorten t_span")
        if failure is not None:
            raise failure
        wall = time.perf_counter() - began
        # (built on the first query, kept with the model; the first step IDAS chose on the real time
        # scale means nothing on the normalised one)
        restart_settings = {key: v for key, v in settings.items() if key != "step0"} | {"calc_ic": True}

        def restart():
            return cached_integrator(compiled, "idas", normalised_dae(dae), 0.0, [1.0], restart_settings)

        dense = IDASRestarts(times_out, values, np.asarray(start.p, dtype=float), restart, len(compiled.states))
        if times[0] != t_span[0]:
            values = values[:, 1:]
        return make_solution(self, compiled, start, options, times, values, wall, stats, setup_time=setup, dense=dense)
